//! The range-view segmenter and RangeNet++'s point-label clean-up.
//!
//! Parity: `tests/data/segmenter/segmenter_yardstick.py` (run by hand with `torch`, `numpy` and
//! `safetensors`) builds the network of `SegmenterConfig::tiny()` in PyTorch from the module docs,
//! draws its weights by name (BatchNorm statistics included), and writes the weights, a fixed
//! input with empty pixels and PyTorch's logits in inference and training mode; candle must match
//! both within 1e-5 relative L2. The clean-up is checked against a brute-force vote written here
//! from RangeNet++'s description, on a synthetic scan with occlusions.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_geom::{LidarSensor, ProjectionOptions, Projector, RangeImage};
use veila_nn::segmenter::knn::{self, IGNORED_CLASS, KnnConfig, PointPixel};
use veila_nn::segmenter::{
    IN_CHANNELS, SegStage, Segmenter, SegmenterConfig, pixel_classes, segmenter_input,
};
use veila_nn::{Error, seeded_var_builder};

const DEV: Device = Device::Cpu;
const REL_L2_TOL: f64 = 1e-5;

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/segmenter")
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

fn rel_l2(got: &Tensor, want: &Tensor) -> f64 {
    assert_eq!(got.dims(), want.dims());
    let (g, w) = (flat(got), flat(want));
    let num: f64 = g
        .iter()
        .zip(&w)
        .map(|(a, b)| f64::from(a - b).powi(2))
        .sum();
    let den: f64 = w.iter().map(|b| f64::from(*b).powi(2)).sum();
    assert!(den > 0.0, "the reference is all zeros");
    (num / den).sqrt()
}

fn seeded(cfg: &SegmenterConfig, seed: u64) -> (Segmenter, VarMap) {
    let vm = VarMap::new();
    let net = Segmenter::new(cfg, seeded_var_builder(&vm, seed, DType::F32, &DEV)).unwrap();
    (net, vm)
}

fn trainable_count(vm: &VarMap) -> usize {
    vm.data()
        .lock()
        .unwrap()
        .iter()
        .filter(|(k, _)| !k.ends_with("running_mean") && !k.ends_with("running_var"))
        .map(|(_, v)| v.elem_count())
        .sum()
}

#[test]
fn matches_the_pytorch_yardstick() {
    let dir = data_dir();
    let cfg: SegmenterConfig = serde_json::from_str(
        &std::fs::read_to_string(dir.join("tiny_config.json")).expect("tiny_config.json"),
    )
    .unwrap();
    assert_eq!(
        cfg,
        SegmenterConfig::tiny(),
        "the script's config is tiny()"
    );
    let weights =
        candle_core::safetensors::load(dir.join("tiny_weights.safetensors"), &DEV).unwrap();
    // strict: the file holds exactly the tensors the network asks for, with their shapes
    let (_, vm) = seeded(&cfg, 0);
    let want: BTreeMap<String, Vec<usize>> = vm
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.dims().to_vec()))
        .collect();
    let got: BTreeMap<String, Vec<usize>> = weights
        .iter()
        .map(|(k, v)| (k.clone(), v.dims().to_vec()))
        .collect();
    assert_eq!(got, want, "tensor names and shapes");
    let net = Segmenter::new(&cfg, VarBuilder::from_tensors(weights, DType::F32, &DEV)).unwrap();
    let io: HashMap<String, Tensor> =
        candle_core::safetensors::load(dir.join("tiny_io.safetensors"), &DEV).unwrap();
    let x = &io["input"];
    let eval = rel_l2(&net.forward(x).unwrap(), &io["logits_eval"]);
    let train = rel_l2(&net.forward_t(x, true).unwrap(), &io["logits_train"]);
    println!("segmenter yardstick: relative L2 {eval:.2e} (inference), {train:.2e} (training)");
    assert!(eval <= REL_L2_TOL, "inference: relative L2 {eval:e}");
    assert!(train <= REL_L2_TOL, "training: relative L2 {train:e}");
    // and the comparison can fail: another seed's weights are far off
    let (other, _) = seeded(&cfg, 1);
    assert!(rel_l2(&other.forward(x).unwrap(), &io["logits_eval"]) > 0.1);
}

#[test]
fn parameter_counts_match_the_closed_form() {
    for (cfg, lo, hi) in [
        (SegmenterConfig::hdl64(), 2_000_000, 8_000_000),
        (SegmenterConfig::bundled(), 100_000, 1_000_000),
        (SegmenterConfig::tiny(), 1_000, 20_000),
    ] {
        let (_, vm) = seeded(&cfg, 0);
        let n = trainable_count(&vm);
        println!("{}: {n} parameters", cfg.name);
        assert_eq!(n, cfg.num_parameters(), "{}", cfg.name);
        assert!((lo..hi).contains(&n), "{}: {n}", cfg.name);
    }
    assert_eq!(
        SegmenterConfig::tiny().num_parameters(),
        6315,
        "the yardstick's count"
    );
}

#[test]
fn output_shapes() {
    for cfg in [SegmenterConfig::tiny(), SegmenterConfig::bundled()] {
        let (net, _) = seeded(&cfg, 3);
        let x = Tensor::randn(0f32, 1.0, (2, IN_CHANNELS, cfg.rows, cfg.cols), &DEV).unwrap();
        let y = net.forward(&x).unwrap();
        assert_eq!(y.dims(), &[2, cfg.num_classes, cfg.rows, cfg.cols]);
        let classes = pixel_classes(&y).unwrap();
        assert_eq!(classes.len(), 2);
        assert!(classes.iter().all(|c| c.len() == cfg.rows * cfg.cols));
        assert!(
            classes
                .iter()
                .flatten()
                .all(|&c| (c as usize) < cfg.num_classes)
        );
    }
}

#[test]
fn degenerate_inputs_stay_finite() {
    let cfg = SegmenterConfig::tiny();
    let (net, _) = seeded(&cfg, 4);
    let shape = (1, IN_CHANNELS, cfg.rows, cfg.cols);
    for value in [0f32, 1.0, -3.0, 1e4] {
        let x = Tensor::full(value, shape, &DEV).unwrap();
        for train in [false, true] {
            let y = net.forward_t(&x, train).unwrap();
            assert!(
                flat(&y).iter().all(|v| v.is_finite()),
                "constant {value}, train {train}"
            );
        }
    }
    // a constant input is the same in every column (the azimuth wraps), so are the logits
    let y = net
        .forward(&Tensor::full(2f32, shape, &DEV).unwrap())
        .unwrap();
    let v = flat(&y);
    for k in 0..cfg.num_classes * cfg.rows {
        let row = &v[k * cfg.cols..(k + 1) * cfg.cols];
        assert!(
            row.iter()
                .all(|x| (x - row[0]).abs() <= 1e-4 * (1.0 + row[0].abs()))
        );
    }
}

#[test]
fn bad_shapes_and_configs_are_errors() {
    let cfg = SegmenterConfig::tiny();
    let (net, _) = seeded(&cfg, 5);
    for shape in [
        (1, 5, cfg.rows, cfg.cols),
        (1, IN_CHANNELS, cfg.rows + 1, cfg.cols),
        (1, IN_CHANNELS, cfg.rows, cfg.cols / 2),
        (0, IN_CHANNELS, cfg.rows, cfg.cols),
    ] {
        let x = Tensor::zeros(shape, DType::F32, &DEV).unwrap();
        assert!(
            matches!(net.forward(&x), Err(Error::Shape { .. })),
            "{shape:?}"
        );
    }
    let edits: Vec<fn(&mut SegmenterConfig)> = vec![
        |c| c.rows = 0,
        |c| c.cols = 1 << 20,
        |c| c.num_classes = 1,
        |c| c.stages.clear(),
        |c| c.stages[0].blocks = 0,
        |c| c.stages[1].stride = [3, 1],
        |c| {
            c.stages.push(SegStage {
                channels: 1 << 20,
                blocks: 1,
                stride: [1, 1],
            })
        },
        |c| {
            c.stages = vec![
                SegStage {
                    channels: 4,
                    blocks: 1,
                    stride: [2, 2]
                };
                7
            ];
        },
        |c| c.input_std[2] = 0.0,
        |c| c.bn_eps = 0.0,
        |c| c.leaky_slope = f64::NAN,
    ];
    for (i, edit) in edits.iter().enumerate() {
        let mut c = SegmenterConfig::tiny();
        edit(&mut c);
        assert!(matches!(c.validate(), Err(Error::Config(_))), "edit {i}");
        let vm = VarMap::new();
        assert!(Segmenter::new(&c, seeded_var_builder(&vm, 0, DType::F32, &DEV)).is_err());
    }
    for c in [
        SegmenterConfig::hdl64(),
        SegmenterConfig::bundled(),
        SegmenterConfig::tiny(),
    ] {
        c.validate().unwrap();
        let back: SegmenterConfig =
            serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
        assert_eq!(back, c);
    }
}

fn small_sensor() -> LidarSensor {
    LidarSensor {
        rows: 16,
        cols: 64,
        ..LidarSensor::hdl64e()
    }
}

#[test]
fn input_channels_from_a_projected_scan() {
    let cfg = SegmenterConfig::tiny();
    let proj = Projector::new(&small_sensor(), ProjectionOptions::default()).unwrap();
    let points = vec![Vec3::new(10.0, 0.0, -0.5), Vec3::new(0.0, 7.0, 0.2)];
    let (img, _) = proj
        .project(&points, Some(&[0.5f32, 0.25][..]), None)
        .unwrap();
    let x = segmenter_input(&img, &points, &cfg, &DEV).unwrap();
    assert_eq!(x.dims(), &[1, IN_CHANNELS, cfg.rows, cfg.cols]);
    let v = flat(&x);
    let n = cfg.rows * cfg.cols;
    let valid: Vec<usize> = (0..n).filter(|&k| img.mask[k]).collect();
    assert_eq!(valid.len(), 2);
    for k in 0..n {
        assert_eq!(v[5 * n + k], if img.mask[k] { 1.0 } else { 0.0 });
        if !img.mask[k] {
            assert!((0..5).all(|c| v[c * n + k] == 0.0));
        }
    }
    for &k in &valid {
        let p = points[img.point_index[k] as usize];
        let want = [p.length(), p.x, p.y, p.z, img.intensity[k]];
        for c in 0..5 {
            let z = (want[c] - cfg.input_mean[c]) / cfg.input_std[c];
            assert!((v[c * n + k] - z).abs() < 1e-5, "channel {c}");
        }
    }
    // an image that names a point the caller does not have is an error
    assert!(matches!(
        segmenter_input(&img, &points[..1], &cfg, &DEV),
        Err(Error::Input(_))
    ));
    let wrong = RangeImage::new_empty(8, 64);
    assert!(segmenter_input(&wrong, &points, &cfg, &DEV).is_err());
}

/// RangeNet++'s vote written out directly: the whole window with off-image pixels at infinite
/// distance, a stable full sort, the first k, then the cutoff, the ignored class and the vote.
fn brute_force_labels(
    img: &RangeImage,
    classes: &[u32],
    pts: &[Option<PointPixel>],
    cfg: &KnnConfig,
) -> Vec<u32> {
    let (h, w) = (img.rows as i64, img.cols as i64);
    let s = cfg.search as i64;
    let m = (s - 1) as f64 / 2.0;
    let mut g = vec![0f64; (s * s) as usize];
    for dy in 0..s {
        for dx in 0..s {
            let d2 = (dx as f64 - m).powi(2) + (dy as f64 - m).powi(2);
            g[(dy * s + dx) as usize] = (-d2 / (2.0 * f64::from(cfg.sigma).powi(2))).exp();
        }
    }
    let total: f64 = g.iter().sum();
    pts.iter()
        .map(|p| {
            let Some(p) = p else { return IGNORED_CLASS };
            let mut all = Vec::new();
            for dy in 0..s {
                for dx in 0..s {
                    let (r, c) = (p.row as i64 + dy - s / 2, p.col as i64 + dx - s / 2);
                    let j = (dy * s + dx) as usize;
                    let weight = (1.0 - g[j] / total) as f32;
                    let (d, class) = if r < 0 || c < 0 || r >= h || c >= w {
                        (f32::INFINITY, IGNORED_CLASS)
                    } else {
                        let q = (r * w + c) as usize;
                        let range = if dy == s / 2 && dx == s / 2 {
                            p.range_m
                        } else if img.mask[q] {
                            img.range_m[q]
                        } else {
                            f32::INFINITY
                        };
                        ((range - p.range_m).abs() * weight, classes[q])
                    };
                    all.push((d, j, class));
                }
            }
            all.sort_by(|a, b| a.0.partial_cmp(&b.0).unwrap().then(a.1.cmp(&b.1)));
            let mut count: BTreeMap<u32, usize> = BTreeMap::new();
            for &(d, _, class) in &all[..cfg.k] {
                if d.is_finite() && (cfg.cutoff == 0.0 || d <= cfg.cutoff) && class != IGNORED_CLASS
                {
                    *count.entry(class).or_default() += 1;
                }
            }
            let most = count.values().copied().max();
            match most {
                // BTreeMap iterates classes in increasing order: the first with most votes
                Some(most) => *count.iter().find(|(_, n)| **n == most).unwrap().0,
                None => classes[(i64::from(p.row) * w + i64::from(p.col)) as usize],
            }
        })
        .collect()
}

/// A scan of a flat ground, a wall at 20 m and a box in front of it, sampled densely so that
/// several points share each pixel and the box hides part of the wall; true classes 1, 2, 3.
fn synthetic_scan(seed: u64) -> (Vec<Vec3>, Vec<u32>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (mut pts, mut cls) = (Vec::new(), Vec::new());
    for _ in 0..6000 {
        let (x, y) = (
            rng.random_range(2.0f32..19.0),
            rng.random_range(-15.0f32..15.0),
        );
        pts.push(Vec3::new(x, y, -1.7));
        cls.push(1);
    }
    for _ in 0..4000 {
        pts.push(Vec3::new(
            20.0,
            rng.random_range(-20.0f32..20.0),
            rng.random_range(-1.7f32..1.5),
        ));
        cls.push(2);
    }
    for _ in 0..3000 {
        let face = rng.random_range(0..2);
        let (x, y) = if face == 0 {
            (8.0, rng.random_range(-2.0f32..2.0))
        } else {
            (rng.random_range(8.0f32..10.0), 2.0)
        };
        pts.push(Vec3::new(x, y, rng.random_range(-1.7f32..0.5)));
        cls.push(3);
    }
    (pts, cls)
}

#[test]
fn knn_labels_match_brute_force_and_fix_occlusions() {
    let proj = Projector::new(&small_sensor(), ProjectionOptions::default()).unwrap();
    let (points, truth) = synthetic_scan(11);
    let (img, _) = proj.project(&points, None, None).unwrap();
    let located = knn::locate_points(&proj, &points, None).unwrap();
    assert!(located.iter().filter(|p| p.is_some()).count() > points.len() / 2);
    // the pixel classes: the winning point's true class, with 10 % of the pixels wrong or ignored
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let pixel: Vec<u32> = (0..img.num_pixels())
        .map(|k| {
            if !img.mask[k] {
                return rng.random_range(0..4);
            }
            let t = truth[img.point_index[k] as usize];
            if rng.random_range(0.0..1.0) < 0.1 {
                rng.random_range(0..4)
            } else {
                t
            }
        })
        .collect();
    for cfg in [
        KnnConfig::default(),
        KnnConfig {
            k: 3,
            search: 3,
            sigma: 0.5,
            cutoff: 0.0,
        },
        KnnConfig {
            k: 9,
            search: 7,
            sigma: 2.0,
            cutoff: 0.3,
        },
        KnnConfig {
            k: 1,
            search: 1,
            sigma: 1.0,
            cutoff: 1.0,
        },
    ] {
        let got = knn::point_labels(&img, &pixel, &located, &cfg).unwrap();
        let want = brute_force_labels(&img, &pixel, &located, &cfg);
        assert_eq!(got, want, "{cfg:?}");
    }
    // the clean-up beats taking the pixel's class on the points that lost their pixel
    let got = knn::point_labels(&img, &pixel, &located, &KnnConfig::default()).unwrap();
    let (mut naive_ok, mut knn_ok, mut hidden) = (0, 0, 0);
    for (i, p) in located.iter().enumerate() {
        let Some(p) = p else {
            assert_eq!(got[i], IGNORED_CLASS);
            continue;
        };
        let k = (p.row * img.cols + p.col) as usize;
        if img.point_index[k] as usize == i {
            continue;
        }
        hidden += 1;
        naive_ok += usize::from(pixel[k] == truth[i]);
        knn_ok += usize::from(got[i] == truth[i]);
    }
    println!("hidden points {hidden}: naive {naive_ok}, knn {knn_ok}");
    assert!(hidden > 1000);
    assert!(
        knn_ok > naive_ok,
        "naive {naive_ok}, knn {knn_ok} of {hidden}"
    );
}

#[test]
fn knn_rejects_bad_inputs() {
    let img = RangeImage::new_empty(4, 8);
    let classes = vec![1u32; 32];
    let ok = [
        Some(PointPixel {
            row: 1,
            col: 2,
            range_m: 5.0,
        }),
        None,
    ];
    assert_eq!(
        knn::point_labels(&img, &classes, &ok, &KnnConfig::default()).unwrap(),
        vec![1, IGNORED_CLASS]
    );
    let outside = [Some(PointPixel {
        row: 4,
        col: 0,
        range_m: 5.0,
    })];
    assert!(knn::point_labels(&img, &classes, &outside, &KnnConfig::default()).is_err());
    assert!(knn::point_labels(&img, &classes[..31], &ok, &KnnConfig::default()).is_err());
    for cfg in [
        KnnConfig {
            search: 4,
            ..KnnConfig::default()
        },
        KnnConfig {
            search: 33,
            ..KnnConfig::default()
        },
        KnnConfig {
            k: 0,
            ..KnnConfig::default()
        },
        KnnConfig {
            k: 26,
            ..KnnConfig::default()
        },
        KnnConfig {
            sigma: 0.0,
            ..KnnConfig::default()
        },
        KnnConfig {
            cutoff: f32::NAN,
            ..KnnConfig::default()
        },
    ] {
        assert!(
            knn::point_labels(&img, &classes, &ok, &cfg).is_err(),
            "{cfg:?}"
        );
    }
    let proj = Projector::new(&small_sensor(), ProjectionOptions::default()).unwrap();
    assert!(knn::locate_points(&proj, &[Vec3::X], Some(&[])).is_err());
    // NaN and origin points get no pixel, hence the ignored class
    let located = knn::locate_points(&proj, &[Vec3::NAN, Vec3::ZERO], None).unwrap();
    assert_eq!(located, vec![None, None]);
}
