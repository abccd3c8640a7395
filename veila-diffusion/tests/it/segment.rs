//! The segmenter's application layer: exact resume of its training, the model folder (written,
//! read back, predicted with; refused when tampered with, oversized or inconsistent), and the
//! scores of label folders (`veila-cli`'s segment tests check them against the numpy reference
//! on real SemanticKITTI labels).

use std::ops::ControlFlow;
use std::path::Path;

use candle_core::Device;
use glam::Vec3;
use veila_diffusion::app::segment::train::SegTrainInput;
use veila_diffusion::app::segment::{
    LabelSpace, SegEvent, SegFrame, SegTrainSettings, SegmenterModel, SegmenterModelConfig,
    evaluate_label_dirs, fit_segmenter,
};
use veila_geom::{LidarSensor, ProjectionOptions, Projector};
use veila_nn::segmenter::SegmenterConfig;

fn tiny_model() -> SegmenterModelConfig {
    let network = SegmenterConfig::tiny();
    let labels = LabelSpace::semantic_kitti();
    let mut classes = labels.classes();
    classes.truncate(network.num_classes);
    SegmenterModelConfig::new(network, &LidarSensor::hdl64e(), classes)
}

/// A synthetic scan: walls at 4-30 m around the sensor, the class by azimuth sector and height.
fn scan(seed: u64, n: usize) -> (Vec<Vec3>, Vec<f32>, Vec<u32>) {
    let mut pts = Vec::with_capacity(n);
    let mut inten = Vec::with_capacity(n);
    let mut cls = Vec::with_capacity(n);
    for i in 0..n {
        let h = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ seed.wrapping_mul(0xD1B5);
        let az = (h % 10_000) as f32 / 10_000.0 * std::f32::consts::TAU - std::f32::consts::PI;
        let el = -0.4 * ((h >> 20) % 1000) as f32 / 1000.0;
        let r = 4.0 + 26.0 * ((h >> 40) % 1000) as f32 / 1000.0;
        pts.push(Vec3::new(
            r * el.cos() * az.cos(),
            r * el.cos() * az.sin(),
            r * el.sin(),
        ));
        inten.push(((h >> 50) % 100) as f32 / 100.0);
        cls.push(if el < -0.3 {
            1
        } else {
            2 + (az > 0.0) as u32 + (r > 15.0) as u32
        });
    }
    (pts, inten, cls)
}

fn frames(model: &SegmenterModelConfig, count: u64) -> Vec<SegFrame> {
    let proj = Projector::new(&model.sensor, ProjectionOptions::default()).unwrap();
    (0..count)
        .map(|s| {
            let (p, i, c) = scan(s, 600);
            SegFrame::from_points(&p, &i, &c, &proj, &model.network).unwrap()
        })
        .collect()
}

fn settings() -> SegTrainSettings {
    SegTrainSettings {
        steps: 6,
        batch: 3,
        lr: 5e-3,
        min_lr: 5e-4,
        warmup_steps: 2,
        weight_decay: 1e-4,
        seed: 3,
        augment: true,
        checkpoint_every: 2,
        keep_checkpoints: None,
        eval_every: Some(3),
    }
}

fn weight_bytes(w: &std::collections::HashMap<String, candle_core::Tensor>) -> Vec<u8> {
    veila_nn::checkpoint::safetensors_bytes(w, Path::new("w")).unwrap()
}

#[test]
fn a_stopped_and_resumed_run_ends_with_the_bytes_of_an_uninterrupted_one() {
    let model = tiny_model();
    let frames = frames(&model, 5);
    let weights = vec![0.0, 1.0, 2.0, 1.5, 0.5];
    let dev = Device::Cpu;
    let proj = Projector::new(&model.sensor, ProjectionOptions::default()).unwrap();
    let held_out: Vec<_> = (10..12)
        .map(|s| {
            let (p, i, c) = scan(s, 500);
            veila_diffusion::app::segment::HeldOutScan {
                scan: veila_diffusion::app::segment::GridScan::new(&p, &i, &proj, &model.network)
                    .unwrap(),
                truth: c,
            }
        })
        .collect();
    let tmp = tempfile::tempdir().unwrap();
    fn make<'a>(
        model: &'a SegmenterModelConfig,
        frames: &'a [SegFrame],
        weights: &'a [f32],
        held_out: &'a [veila_diffusion::app::segment::HeldOutScan],
        dir: &'a Path,
    ) -> SegTrainInput<'a> {
        SegTrainInput {
            model,
            frames,
            class_weights: weights,
            ignored: &[0],
            held_out,
            ck_dir: dir,
            data: serde_json::json!({"synthetic": 5}),
        }
    }
    let input = |dir| make(&model, &frames, &weights, &held_out, dir);
    let a_dir = tmp.path().join("a");
    let mut losses = Vec::new();
    let mut scored = Vec::new();
    let a = fit_segmenter(&input(&a_dir), &settings(), &dev, |e| {
        match e {
            SegEvent::Step { loss, .. } => losses.push(loss),
            SegEvent::HeldOut { step, scores } => scored.push((step, scores.miou)),
            _ => {}
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(a.step, 6);
    assert_eq!(losses.len(), 6);
    assert!(
        losses.iter().all(|l| l.is_finite() && *l > 0.0),
        "{losses:?}"
    );
    assert_eq!(scored.iter().map(|s| s.0).collect::<Vec<_>>(), vec![3, 6]);
    // stopped after 4 updates (a checkpoint there), then resumed to the end
    let b_dir = tmp.path().join("b");
    let mut n = 0;
    let b1 = fit_segmenter(&input(&b_dir), &settings(), &dev, |e| {
        if let SegEvent::Step { .. } = e {
            n += 1;
            if n == 4 {
                return ControlFlow::Break(());
            }
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(b1.step, 4);
    assert!(b_dir.join("step-0000000004/state.json").is_file());
    let mut resumed = None;
    let b2 = fit_segmenter(&input(&b_dir), &settings(), &dev, |e| {
        if let SegEvent::Resumed { step, .. } = e {
            resumed = Some(step);
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(resumed, Some(4));
    assert_eq!(b2.step, 6);
    assert_eq!(
        weight_bytes(&a.weights),
        weight_bytes(&b2.weights),
        "resumed weights differ"
    );
    assert_eq!(a.held_out, b2.held_out);
    // a finished run run again does nothing more and still reports its weights and scores
    let again = fit_segmenter(&input(&a_dir), &settings(), &dev, |e| {
        assert!(
            !matches!(e, SegEvent::Step { .. }),
            "an update after the last"
        );
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(weight_bytes(&again.weights), weight_bytes(&a.weights));
    assert_eq!(again.held_out, a.held_out);
    // the BatchNorm statistics were trained and kept
    let rm = a.weights["stem.0.bn.running_mean"]
        .to_vec1::<f32>()
        .unwrap();
    assert!(rm.iter().any(|v| *v != 0.0));
    // another seed is another run: its checkpoints are refused in this folder
    let other = SegTrainSettings {
        seed: 4,
        ..settings()
    };
    let e = fit_segmenter(&input(&b_dir), &other, &dev, |_| ControlFlow::Continue(()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("other settings"), "{e}");
    // a checkpoint with a corrupted weights file is an error naming it, not a panic
    let c_dir = tmp.path().join("c");
    let one = SegTrainSettings {
        steps: 2,
        ..settings()
    };
    fit_segmenter(&input(&c_dir), &one, &dev, |_| ControlFlow::Continue(())).unwrap();
    let w = c_dir.join("step-0000000002/model.safetensors");
    std::fs::write(&w, b"not safetensors").unwrap();
    let e = fit_segmenter(&input(&c_dir), &one, &dev, |_| ControlFlow::Continue(()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("model.safetensors"), "{e}");
}

#[test]
fn a_model_folder_round_trips_and_predicts_every_point() {
    let model = tiny_model();
    let dev = Device::Cpu;
    let out = fit_segmenter(
        &SegTrainInput {
            model: &model,
            frames: &frames(&model, 3),
            class_weights: &[0.0, 1.0, 1.0, 1.0, 1.0],
            ignored: &[0],
            held_out: &[],
            ck_dir: &tempfile::tempdir().unwrap().path().join("ck"),
            data: serde_json::Value::Null,
        },
        &SegTrainSettings {
            steps: 2,
            ..settings()
        },
        &dev,
        |_| ControlFlow::Continue(()),
    )
    .unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("seg");
    SegmenterModel::save(&dir, &model, &out.weights).unwrap();
    let m = SegmenterModel::from_dir(&dir, &dev).unwrap();
    assert_eq!(m.config, model);
    let (p, i, _) = scan(77, 700);
    let mut p = p;
    p.push(Vec3::new(f32::NAN, 0.0, 0.0)); // rejected: labelled 0
    p.push(Vec3::new(0.0, 0.0, 50.0)); // above the field of view
    let i: Vec<f32> = i.into_iter().chain([0.1, 0.1]).collect();
    let grid = m.grid_scan(&p, &i).unwrap();
    let pred = m
        .predict(std::slice::from_ref(&grid))
        .unwrap()
        .pop()
        .unwrap();
    assert_eq!(pred.len(), p.len());
    assert_eq!(&pred[700..], &[0, 0]);
    assert!(
        pred.iter()
            .all(|&t| (t as usize) < model.network.num_classes)
    );
    let raw = m.raw_ids(&pred);
    assert!(
        raw.iter()
            .all(|r| model.classes.iter().any(|c| c.raw_id == *r))
    );
    // the same scan gives the same labels
    assert_eq!(m.predict(&[grid]).unwrap()[0], pred);

    // tampered, missing, oversized and inconsistent files are errors naming the file
    let copy = |name: &str| {
        let d = tmp.path().join(name);
        std::fs::create_dir_all(&d).unwrap();
        for f in ["manifest.json", "segmenter.json", "segmenter.safetensors"] {
            std::fs::copy(dir.join(f), d.join(f)).unwrap();
        }
        d
    };
    let d = copy("tampered");
    let mut w = std::fs::read(d.join("segmenter.safetensors")).unwrap();
    let last = w.len() - 1;
    w[last] ^= 1;
    std::fs::write(d.join("segmenter.safetensors"), w).unwrap();
    let e = SegmenterModel::from_dir(&d, &dev).unwrap_err().to_string();
    assert!(
        e.contains("sha256 mismatch") && e.contains("segmenter.safetensors"),
        "{e}"
    );
    let d = copy("missing");
    std::fs::remove_file(d.join("segmenter.safetensors")).unwrap();
    let e = SegmenterModel::from_dir(&d, &dev).unwrap_err().to_string();
    assert!(e.contains("segmenter.safetensors"), "{e}");
    let d = copy("huge");
    std::fs::File::create(d.join("segmenter.json"))
        .unwrap()
        .set_len(3 << 30)
        .unwrap();
    let e = SegmenterModel::from_dir(&d, &dev).unwrap_err().to_string();
    assert!(
        e.contains("segmenter.json") && e.contains("more than the cap"),
        "{e}"
    );
    // a config whose sensor grid is not the network's, re-signed so only the check can refuse it
    let mut bad = model.clone();
    bad.sensor.cols = 128;
    let e = SegmenterModel::save(&tmp.path().join("bad"), &bad, &out.weights)
        .unwrap_err()
        .to_string();
    assert!(e.contains("grid is 16 x 128"), "{e}");
    let d = copy("regrid");
    let json = serde_json::to_vec_pretty(&bad).unwrap();
    std::fs::write(d.join("segmenter.json"), &json).unwrap();
    let mut manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(d.join("manifest.json")).unwrap()).unwrap();
    manifest["files"]["segmenter.json"] = veila_nn::checkpoint::sha256_hex(&json).into();
    std::fs::write(d.join("manifest.json"), manifest.to_string()).unwrap();
    let e = SegmenterModel::from_dir(&d, &dev).unwrap_err().to_string();
    assert!(
        e.contains("segmenter.json") && e.contains("grid is 16 x 128"),
        "{e}"
    );
}

#[test]
fn label_folders_are_scored_and_bad_predictions_refused_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let (truth, pred) = (tmp.path().join("truth"), tmp.path().join("pred"));
    std::fs::create_dir(&truth).unwrap();
    std::fs::create_dir(&pred).unwrap();
    let write = |dir: &Path, name: &str, labels: &[u32]| {
        veila_data::semantic_kitti::write_labels(&dir.join(format!("{name}.label")), labels)
            .unwrap()
    };
    // car (10, and moving car 252 with an instance), road (40), unlabelled (0)
    write(&truth, "000000", &[10, 252 | (3 << 16), 40, 40, 0]);
    write(&truth, "000001", &[40, 40, 10]);
    // perfect but for one road predicted as car; the unlabelled point is not scored
    write(&pred, "000000", &[10, 10, 40, 10, 50]);
    write(&pred, "000001", &[40, 40, 10]);
    let space = LabelSpace::semantic_kitti();
    let mut seen = Vec::new();
    let f = evaluate_label_dirs(&pred, &truth, &space, |n| seen.push(n.to_string())).unwrap();
    assert_eq!(seen, ["000000", "000001"]);
    let s = &f.scores;
    // car: TP 3, FP 1; road: TP 3, FN 1
    assert!((s.iou[1] - 0.75).abs() < 1e-12 && (s.iou[9] - 0.75).abs() < 1e-12);
    assert_eq!(s.present, vec![1, 9]);
    assert!((s.miou_present - 0.75).abs() < 1e-12);
    assert!((s.miou - 1.5 / 19.0).abs() < 1e-12);
    assert_eq!((f.scans, f.class_names[9].as_str()), (2, "road"));

    // a prediction missing, of another length, or in another label map: errors naming the file
    std::fs::remove_file(pred.join("000001.label")).unwrap();
    let e = evaluate_label_dirs(&pred, &truth, &space, |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("000001.label") && e.contains("missing"), "{e}");
    write(&pred, "000001", &[40, 40]);
    let e = evaluate_label_dirs(&pred, &truth, &space, |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("000001.label") && e.contains("2 labels"), "{e}");
    write(&pred, "000001", &[40, 7, 10]);
    let e = evaluate_label_dirs(&pred, &truth, &space, |_| {})
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("000001.label") && e.contains("mismatched label maps") && e.contains("raw id 7"),
        "{e}"
    );
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let e = evaluate_label_dirs(&pred, &empty, &space, |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("empty") && e.contains("no `.label` file"), "{e}");
}
