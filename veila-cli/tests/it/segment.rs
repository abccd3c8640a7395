//! `veila segment`: predict round trip on a tiny model (every point labelled, the same bytes
//! twice, never over an input, no partial output on a bad scan), the bundled segmenter without
//! `--model`, eval against the numpy reference of `veila-metrics/tests/data` on the real
//! SemanticKITTI labels of `../shared/data/real` (skipped with a message when absent; predictions
//! made to give the reference's confusion matrix), and train: a run stopped and
//! resumed ends with the model bytes of an uninterrupted one; clear errors on mismatched label
//! maps.

use std::path::{Path, PathBuf};
use std::process::Output;

use candle_core::{DType, Device};
use candle_nn::VarMap;
use veila_diffusion::app::segment::{LabelSpace, SegmenterModel, SegmenterModelConfig};
use veila_geom::LidarSensor;
use veila_nn::segmenter::{Segmenter, SegmenterConfig};

use crate::common::{ok, tiny_scene, veila};

fn fails_with(o: &Output, needles: &[&str]) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "succeeded; stderr:\n{err}");
    for n in needles {
        assert!(err.contains(n), "`{n}` not in:\n{err}");
    }
}

/// A tiny segmenter (seeded weights) in `dir`.
fn tiny_model(dir: &Path) {
    let network = SegmenterConfig::tiny();
    let mut classes = LabelSpace::semantic_kitti().classes();
    classes.truncate(network.num_classes);
    let cfg = SegmenterModelConfig::new(network, &LidarSensor::hdl64e(), classes);
    let vm = VarMap::new();
    Segmenter::new(
        &cfg.network,
        veila_nn::seeded_var_builder(&vm, 5, DType::F32, &Device::Cpu),
    )
    .unwrap();
    let weights = veila_diffusion::app::varmap_tensors(&vm).unwrap();
    SegmenterModel::save(dir, &cfg, &weights).unwrap();
}

/// KITTI records of `n` points on walls around the sensor (a NaN record among them).
fn scan_bytes(seed: u32, n: usize) -> Vec<u8> {
    (0..n)
        .flat_map(|i| {
            let a = i as f32 * 0.0137 + seed as f32;
            let r = 5.0 + ((i * 7 + seed as usize) % 23) as f32;
            let z = -0.2 - 0.01 * (i % 150) as f32;
            if i == 3 {
                [f32::NAN, 0.0, 0.0, 0.5]
            } else {
                [r * a.cos(), r * a.sin(), z, (i % 10) as f32 / 10.0]
            }
        })
        .flat_map(f32::to_le_bytes)
        .collect()
}

fn predict(scans: &Path, out: &Path, extra: &[&str]) -> Output {
    veila()
        .args(["segment", "predict", "--quiet", "--scans"])
        .arg(scans)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap()
}

fn tree(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "label"))
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect();
    v.sort();
    v
}

#[test]
fn predict_labels_every_point_of_every_scan_and_never_writes_over_inputs() {
    let tmp = tempfile::tempdir().unwrap();
    let model = tmp.path().join("model");
    tiny_model(&model);
    let scans = tmp.path().join("scans");
    std::fs::create_dir(&scans).unwrap();
    for (i, n) in [(0, 900), (1, 1200)] {
        std::fs::write(scans.join(format!("{i:06}.bin")), scan_bytes(i, n)).unwrap();
    }
    let m = model.to_str().unwrap();
    let out = tmp.path().join("labels");
    ok(&predict(&scans, &out, &["--model", m]));
    let first = tree(&out);
    assert_eq!(first.len(), 2);
    for ((name, bytes), n) in first.iter().zip([900, 1200]) {
        assert_eq!(bytes.len(), 4 * n, "{name}: one label per record");
        let raw: Vec<u32> = bytes
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        assert_eq!(raw[3], 0, "the NaN record is unlabelled");
        assert!(
            raw.iter().all(|r| [0, 10, 11, 15, 18].contains(r)),
            "{name}"
        );
    }
    // the same bytes again
    let again = tmp.path().join("labels2");
    ok(&predict(&scans, &again, &["--model", m]));
    assert_eq!(tree(&again), first);
    // an existing output needs --force; the scans folder is never the output
    fails_with(&predict(&scans, &out, &["--model", m]), &["not empty"]);
    ok(&predict(&scans, &out, &["--model", m, "--force"]));
    fails_with(
        &predict(&scans, &scans, &["--model", m, "--force"]),
        &["is the input"],
    );
    assert_eq!(std::fs::read_dir(&scans).unwrap().count(), 2);
    // a scan of a wrong size: an error naming it, nothing written
    std::fs::write(scans.join("000002.bin"), [0u8; 17]).unwrap();
    let bad = tmp.path().join("bad");
    fails_with(
        &predict(&scans, &bad, &["--model", m]),
        &["000002.bin", "not a multiple of the 16-byte record"],
    );
    assert!(!bad.exists(), "a partial output was left");
    std::fs::remove_file(scans.join("000002.bin")).unwrap();
    // a missing model, a label map the model does not write
    fails_with(
        &predict(&scans, &bad, &["--model", "/nonexistent/seg"]),
        &["/nonexistent/seg"],
    );
    let yaml = tmp.path().join("mine.yaml");
    std::fs::write(&yaml, LABEL_YAML).unwrap();
    fails_with(
        &predict(
            &scans,
            &bad,
            &["--model", m, "--label-map", yaml.to_str().unwrap()],
        ),
        &["mismatched label maps", "mine.yaml", "segmenter.json"],
    );
    assert!(!bad.exists());
}

#[test]
fn predict_uses_the_bundled_segmenter_without_model() {
    let bundled = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/segmenter");
    if !bundled.join("manifest.json").is_file() {
        println!("skipped: models/segmenter is absent");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let scans = tmp.path().join("scans");
    std::fs::create_dir(&scans).unwrap();
    std::fs::write(scans.join("a.bin"), scan_bytes(2, 3000)).unwrap();
    let out = tmp.path().join("labels");
    let o = predict(&scans, &out, &[]);
    ok(&o);
    assert!(String::from_utf8_lossy(&o.stdout).contains("models/segmenter"));
    assert_eq!(
        std::fs::metadata(out.join("a.label")).unwrap().len(),
        4 * 3000
    );
}

/// A three-class label map: road is train id 2 here, 9 in SemanticKITTI's.
const LABEL_YAML: &str = "labels:\n  0: unlabeled\n  10: car\n  40: road\ncolor_map:\n  0: [0, 0, 0]\n  10: [1, 2, 3]\n  40: [4, 5, 6]\nlearning_map:\n  0: 0\n  10: 1\n  40: 2\nlearning_map_inv:\n  0: 0\n  1: 10\n  2: 40\nlearning_ignore:\n  0: True\n  1: False\n  2: False\n";

fn real_labels() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real/semantickitti/sequences/00/labels");
    p.is_dir().then_some(p)
}

fn eval(pred: &Path, labels: &Path, extra: &[&str]) -> Output {
    veila()
        .args(["segment", "eval", "--quiet", "--predictions"])
        .arg(pred)
        .arg("--labels")
        .arg(labels)
        .args(extra)
        .output()
        .unwrap()
}

#[test]
fn eval_matches_the_numpy_reference_on_real_labels() {
    let Some(labels) = real_labels() else {
        println!("skipped: ../shared/data/real/semantickitti is absent");
        return;
    };
    let reference: serde_json::Value = serde_json::from_slice(
        &std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../veila-metrics/tests/data/segmentation_reference.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let space = LabelSpace::semantic_kitti();
    let inv = space.classes();
    let tmp = tempfile::tempdir().unwrap();
    let pred = tmp.path().join("pred");
    std::fs::create_dir(&pred).unwrap();
    // predictions that give the reference's confusion matrix (rows prediction, columns truth):
    // the points of true class t take the predictions of column t, in order; every score the
    // evaluator reports is a function of that matrix
    let mut column: Vec<Vec<(usize, u64)>> = vec![Vec::new(); 20];
    for (p, row) in reference["confusion"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
    {
        for (t, n) in row.as_array().unwrap().iter().enumerate() {
            column[t].push((p, n.as_u64().unwrap()));
        }
    }
    for name in ["000000", "000001"] {
        let raw =
            veila_data::semantic_kitti::read_labels(&labels.join(format!("{name}.label")), None)
                .unwrap();
        let out: Vec<u32> = raw
            .iter()
            .map(|&r| {
                let col = &mut column[space.train_id(r) as usize];
                let slot = col
                    .iter_mut()
                    .find(|(_, n)| *n > 0)
                    .expect("the matrix's count");
                slot.1 -= 1;
                inv[slot.0].raw_id
            })
            .collect();
        veila_data::semantic_kitti::write_labels(&pred.join(format!("{name}.label")), &out)
            .unwrap();
    }
    assert!(
        column.iter().flatten().all(|(_, n)| *n == 0),
        "every count used"
    );
    let json = tmp.path().join("scores.json");
    let o = eval(&pred, &labels, &["--json", json.to_str().unwrap()]);
    ok(&o);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("mIoU") && stdout.contains("road"),
        "{stdout}"
    );
    let got: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let s = &got["scores"];
    let mut worst = 0f64;
    for (a, b) in s["iou"]
        .as_array()
        .unwrap()
        .iter()
        .zip(reference["iou"].as_array().unwrap())
    {
        worst = worst.max((a.as_f64().unwrap() - b.as_f64().unwrap()).abs());
    }
    for k in ["miou", "miou_present", "accuracy"] {
        worst = worst.max((s[k].as_f64().unwrap() - reference[k].as_f64().unwrap()).abs());
    }
    println!("veila segment eval against numpy: largest difference {worst:.1e}");
    assert!(worst <= 1e-6, "{worst:e}");
    assert_eq!(s["present"], reference["present"]);
    // the json is never written over an input; a missing prediction names the file
    fails_with(
        &eval(
            &pred,
            &labels,
            &["--json", labels.join("000000.label").to_str().unwrap()],
        ),
        &["--json"],
    );
    std::fs::remove_file(pred.join("000001.label")).unwrap();
    fails_with(&eval(&pred, &labels, &[]), &["000001.label", "missing"]);
    let mine = tmp.path().join("mine.yaml");
    std::fs::write(&mine, LABEL_YAML).unwrap();
    fails_with(
        &eval(&pred, &labels, &["--label-map", mine.to_str().unwrap()]),
        &["mismatched label maps", "mine.yaml"],
    );
}

/// A scene list of the tiny scene (`frames` frames, seeds 0-9) in `dir`.
fn scene_list(dir: &Path, name: &str, seeds: &str) -> PathBuf {
    std::fs::write(dir.join("tiny.toml"), tiny_scene(16, 128, 2)).unwrap();
    let list = dir.join(name);
    std::fs::write(&list, format!("tiny.toml {seeds}\n")).unwrap();
    list
}

fn train(config: &Path, extra: &[&str]) -> Output {
    veila()
        .args(["segment", "train", "--quiet", "--config"])
        .arg(config)
        .args(extra)
        .output()
        .unwrap()
}

const TRAIN: &str = "[model]\npreset = \"tiny\"\n[train]\nsteps = 4\nbatch = 2\nlr = 3e-3\nwarmup_steps = 1\nseed = 1\nclass_weights = \"inverse-sqrt-frequency\"\ncheckpoint_every = 2\neval_every = 2\n";

#[test]
fn train_resumes_to_the_model_bytes_of_an_uninterrupted_run() {
    let tmp = tempfile::tempdir().unwrap();
    scene_list(tmp.path(), "train.txt", "0 9");
    scene_list(tmp.path(), "test.txt", "100 109");
    let config = |run: &str| {
        let p = tmp.path().join(format!("{run}.toml"));
        std::fs::write(
            &p,
            format!(
                "[data]\nscenes = \"train.txt\"\nscene_count = 2\nframes_per_scene = 2\nheld_out_scenes = \"test.txt\"\nheld_out_count = 1\n{TRAIN}[output]\ndir = \"{run}\"\n"
            ),
        )
        .unwrap();
        p
    };
    let a = config("a");
    let o = train(&a, &[]);
    ok(&o);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("held-out mIoU"), "{stdout}");
    let model_a = std::fs::read(tmp.path().join("a/segmenter/segmenter.safetensors")).unwrap();
    let log = std::fs::read_to_string(tmp.path().join("a/train_log.jsonl")).unwrap();
    assert_eq!(
        log.lines().filter(|l| l.contains("\"segmenter\"")).count(),
        4
    );
    assert_eq!(log.lines().filter(|l| l.contains("held-out")).count(), 2);
    let b = config("b");
    let o = train(&b, &["--stop-after", "3"]);
    ok(&o);
    assert!(String::from_utf8_lossy(&o.stdout).contains("stopped at step 3 of 4"));
    assert!(!tmp.path().join("b/segmenter").exists());
    ok(&train(&b, &[]));
    let model_b = std::fs::read(tmp.path().join("b/segmenter/segmenter.safetensors")).unwrap();
    assert!(model_a == model_b, "the resumed run's weights differ");
    // a finished run's model is replaced only with --force
    fails_with(
        &train(&b, &[]),
        &["b/segmenter", "a segmenter is already there"],
    );
    ok(&train(&b, &["--force"]));
    // the model predicts the simulator's scans
    let m = tmp.path().join("b/segmenter");
    SegmenterModel::from_dir(&m, &Device::Cpu).unwrap();
    // a config with two data sources names itself
    let bad = tmp.path().join("bad.toml");
    std::fs::write(
        &bad,
        "[data]\nscenes = \"train.txt\"\nshards = \"x\"\n[output]\ndir = \"c\"\n",
    )
    .unwrap();
    fails_with(&train(&bad, &[]), &["bad.toml", "exactly one of"]);
}

#[test]
fn shards_of_another_label_map_are_refused_naming_the_shard_and_the_map() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("kitti");
    let seq = root.join("sequences/00");
    std::fs::create_dir_all(seq.join("velodyne")).unwrap();
    std::fs::create_dir_all(seq.join("labels")).unwrap();
    for f in 0..2u32 {
        let bytes = scan_bytes(f, 1500);
        let labels: Vec<u32> = (0..1500u32)
            .map(|i| if i % 3 == 0 { 10 } else { 40 })
            .collect();
        std::fs::write(seq.join(format!("velodyne/{f:06}.bin")), bytes).unwrap();
        veila_data::semantic_kitti::write_labels(
            &seq.join(format!("labels/{f:06}.label")),
            &labels,
        )
        .unwrap();
    }
    let mine = tmp.path().join("mine.yaml");
    std::fs::write(&mine, LABEL_YAML).unwrap();
    let shards = tmp.path().join("shards");
    ok(&veila()
        .args(["convert", "--quiet", "--dataset", "semantickitti", "--root"])
        .arg(&root)
        .arg("--out")
        .arg(&shards)
        .arg("--label-map")
        .arg(&mine)
        .output()
        .unwrap());
    // the shards' train ids (road = 2) against SemanticKITTI's map (road = 9)
    let other = tmp.path().join("other.yaml");
    std::fs::write(
        &other,
        LABEL_YAML
            .replace("40: 2\n", "40: 1\n")
            .replace("10: 1\n", "10: 2\n")
            .replace("  1: 10\n  2: 40\n", "  1: 40\n  2: 10\n"),
    )
    .unwrap();
    let config = |map: &Path, run: &str| {
        let p = tmp.path().join(format!("{run}.toml"));
        std::fs::write(
            &p,
            format!(
                "[data]\nshards = \"shards\"\nlabel_map = \"{}\"\n{TRAIN}[output]\ndir = \"{run}\"\n",
                map.display()
            ),
        )
        .unwrap();
        p
    };
    fails_with(
        &train(&config(&other, "x"), &[]),
        &["mismatched label maps", "other.yaml", "shard", "sample"],
    );
    // with the map they were converted with, the model writes its raw ids
    ok(&train(&config(&mine, "y"), &[]));
    let m = SegmenterModel::from_dir(&tmp.path().join("y/segmenter"), &Device::Cpu).unwrap();
    let raws: Vec<u32> = m.config.classes.iter().map(|c| c.raw_id).collect();
    assert_eq!(raws, [0, 10, 40]);
}
