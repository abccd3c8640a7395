//! The SemanticKITTI segmentation scores: hand-counted cases, a direct per-class count on random
//! labels, and the numpy reference of `tests/data/segmentation_reference.py` on the real
//! SemanticKITTI labels of `../shared/data/real` (skipped with a message when they are absent).

use std::path::{Path, PathBuf};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_metrics::Error;
use veila_metrics::segmentation::{IouEval, LearningMap, SEMANTIC_KITTI_CLASSES};

const TOL: f64 = 1e-6;

#[test]
fn hand_counted_scores() {
    let mut e = IouEval::new(4, &[0]).unwrap();
    // truth:   1 1 1 2 2 0 0 3
    // predict: 1 1 0 2 1 2 0 1
    e.add(&[1, 1, 0, 2, 1, 2, 0, 1], &[1, 1, 1, 2, 2, 0, 0, 3])
        .unwrap();
    let s = e.scores();
    // class 1: TP 2, FP 2 (a 2 and a 3 predicted as 1), FN 1 (predicted 0)
    assert!((s.iou[1] - 2.0 / 5.0).abs() < 1e-12);
    // class 2: TP 1, FP 0 (the 2 predicted on an unlabelled point does not count), FN 1
    assert!((s.iou[2] - 0.5).abs() < 1e-12);
    // class 3: TP 0
    assert_eq!(s.iou[3], 0.0);
    assert!((s.miou - (0.4 + 0.5) / 3.0).abs() < 1e-12);
    assert_eq!(s.present, vec![1, 2, 3]);
    assert_eq!(s.included, vec![1, 2, 3]);
    // accuracy: TP 3 over the included rows' sums: 4 + 1 + 0 (the 2 on a 0 is zeroed)
    assert!((s.accuracy - 3.0 / 5.0).abs() < 1e-12);
    assert_eq!(s.points, 6);

    // a class absent from the truth and never predicted counts as 0 in the mIoU, not in the
    // mean over present classes
    let mut e = IouEval::new(4, &[0]).unwrap();
    e.add(&[1, 2], &[1, 2]).unwrap();
    let s = e.scores();
    assert!((s.miou - 2.0 / 3.0).abs() < 1e-12);
    assert!((s.miou_present - 1.0).abs() < 1e-12);
    assert_eq!(s.present, vec![1, 2]);

    // nothing added: every score 0, never NaN
    let s = IouEval::semantic_kitti().scores();
    assert_eq!(s.miou, 0.0);
    assert_eq!(s.miou_present, 0.0);
    assert_eq!(s.accuracy, 0.0);
    assert_eq!(s.iou.len(), SEMANTIC_KITTI_CLASSES);
}

#[test]
fn matches_a_direct_count_on_random_labels() {
    let mut rng = ChaCha8Rng::seed_from_u64(56);
    let n = 7;
    let ignore = [0usize, 4];
    let mut e = IouEval::new(n, &ignore).unwrap();
    let mut all = (Vec::new(), Vec::new());
    let mut halves = IouEval::new(n, &ignore).unwrap();
    for scan in 0..3 {
        let len = 500 + scan * 37;
        // class 6 never occurs in the truth, class 5 is never predicted
        let truth: Vec<u32> = (0..len).map(|_| rng.random_range(0..6)).collect();
        let pred: Vec<u32> = truth
            .iter()
            .map(|&t| {
                if rng.random_range(0..3) == 0 {
                    [0, 1, 2, 3, 4, 6][rng.random_range(0..6)]
                } else if t == 5 {
                    1
                } else {
                    t
                }
            })
            .collect();
        e.add(&pred, &truth).unwrap();
        let mut part = IouEval::new(n, &ignore).unwrap();
        part.add(&pred, &truth).unwrap();
        halves.merge(&part).unwrap();
        all.0.extend(pred);
        all.1.extend(truth);
    }
    assert_eq!(halves, e);
    let s = e.scores();
    let (pred, truth) = all;
    let counted = |c: u32| {
        let mut tp = 0usize;
        let mut fp = 0usize;
        let mut fn_ = 0usize;
        for (&p, &t) in pred.iter().zip(&truth) {
            if ignore.contains(&(t as usize)) {
                continue;
            }
            tp += usize::from(p == c && t == c);
            fp += usize::from(p == c && t != c);
            fn_ += usize::from(p != c && t == c);
        }
        (tp, fp, fn_)
    };
    let mut sum = 0.0;
    let (mut tp_all, mut pred_included) = (0usize, 0usize);
    for c in 0..n as u32 {
        let (tp, fp, fn_) = counted(c);
        let iou = tp as f64 / ((tp + fp + fn_) as f64 + 1e-15);
        assert!((s.iou[c as usize] - iou).abs() < 1e-12, "class {c}");
        tp_all += tp;
        if !ignore.contains(&(c as usize)) {
            sum += iou;
            pred_included += tp + fp;
        }
    }
    assert!((s.miou - sum / 5.0).abs() < 1e-12);
    assert!((s.accuracy - tp_all as f64 / pred_included as f64).abs() < 1e-12);
    assert_eq!(s.iou[5], 0.0);
    assert_eq!(s.present, vec![1, 2, 3, 5]);
}

#[test]
fn bad_inputs_are_errors() {
    let mut e = IouEval::semantic_kitti();
    assert!(matches!(
        e.add(&[1, 2], &[1]),
        Err(Error::ShapeMismatch { .. })
    ));
    assert!(matches!(
        e.add(&[1, 20], &[1, 1]),
        Err(Error::LabelSpace { index: 1, .. })
    ));
    assert!(matches!(
        e.add(&[1, 1], &[99, 1]),
        Err(Error::LabelSpace { .. })
    ));
    assert_eq!(e, IouEval::semantic_kitti(), "nothing counted");
    assert!(IouEval::new(0, &[]).is_err());
    assert!(IouEval::new(1 << 20, &[]).is_err());
    assert!(IouEval::new(3, &[3]).is_err());
    assert!(e.merge(&IouEval::new(20, &[]).unwrap()).is_err());
    assert!(LearningMap::from_pairs([(1 << 16, 1)], 20).is_err());
    assert!(LearningMap::from_pairs([(10, 20)], 20).is_err());
    assert!(LearningMap::from_pairs([(10, 1), (10, 2)], 20).is_err());
    let map = LearningMap::from_pairs([(10, 1), (10, 1), (40, 9)], 20).unwrap();
    // the instance bits are dropped, unknown raw ids are 0
    assert_eq!(map.train_id((7 << 16) | 10), 1);
    assert_eq!(map.train_id(41), 0);
    let mut e = IouEval::new(10, &[0]).unwrap();
    e.add_raw(&[1, 9, 0], &[(3 << 16) | 10, 40, 41], &map)
        .unwrap_err();
    let mut e = IouEval::new(20, &[0]).unwrap();
    e.add_raw(&[1, 9, 0], &[(3 << 16) | 10, 40, 41], &map)
        .unwrap();
    assert_eq!(e.confusion()[20 + 1], 1);
    assert_eq!(e.confusion()[9 * 20 + 9], 1);
    assert_eq!(e.confusion()[0], 1);
}

fn real_root() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/semantickitti");
    p.join("semantic-kitti.yaml").is_file().then_some(p)
}

/// The prediction of the reference script: see its docstring.
fn perturb(truth: &[u32]) -> Vec<u32> {
    truth
        .iter()
        .enumerate()
        .map(|(i, &t)| {
            let r = ((i as u64 * 2_654_435_761) % (1 << 32)) % 100;
            let p = if r < 12 {
                ((7 * u64::from(t) + i as u64) % 20) as u32
            } else if r < 15 {
                0
            } else {
                t
            };
            if p == 19 { 18 } else { p }
        })
        .collect()
}

#[test]
fn matches_numpy_on_real_semantic_kitti_labels() {
    let Some(root) = real_root() else {
        println!("skipped: ../shared/data/real/semantickitti is absent");
        return;
    };
    let reference: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/segmentation_reference.json"),
        )
        .expect("segmentation_reference.json"),
    )
    .unwrap();
    let pairs: Vec<(u32, u32)> = reference["learning_map"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| (p[0].as_u64().unwrap() as u32, p[1].as_u64().unwrap() as u32))
        .collect();
    let map = LearningMap::from_pairs(pairs, SEMANTIC_KITTI_CLASSES).unwrap();
    let mut eval = IouEval::semantic_kitti();
    for (scan, n) in reference["scans"]
        .as_array()
        .unwrap()
        .iter()
        .zip(reference["points"].as_array().unwrap())
    {
        let bytes = std::fs::read(root.join(scan.as_str().unwrap())).unwrap();
        let raw: Vec<u32> = bytes
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        assert_eq!(raw.len() as u64, n.as_u64().unwrap());
        let truth: Vec<u32> = raw.iter().map(|&r| map.train_id(r)).collect();
        eval.add_raw(&perturb(&truth), &raw, &map).unwrap();
    }
    let conf: Vec<u64> = reference["confusion"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|row| row.as_array().unwrap().iter().map(|v| v.as_u64().unwrap()))
        .collect();
    assert_eq!(eval.confusion(), conf.as_slice(), "confusion matrix");
    let s = eval.scores();
    let num = |k: &str| reference[k].as_f64().unwrap();
    let mut worst = 0f64;
    for (c, want) in reference["iou"].as_array().unwrap().iter().enumerate() {
        worst = worst.max((s.iou[c] - want.as_f64().unwrap()).abs());
    }
    for (got, key) in [
        (s.miou, "miou"),
        (s.miou_present, "miou_present"),
        (s.accuracy, "accuracy"),
    ] {
        worst = worst.max((got - num(key)).abs());
    }
    let present: Vec<usize> = reference["present"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    assert_eq!(s.present, present);
    println!(
        "SemanticKITTI reference: mIoU {:.6} (present {:.6}), accuracy {:.6}; largest difference from numpy {worst:.1e}",
        s.miou, s.miou_present, s.accuracy
    );
    assert!(worst <= TOL, "largest difference {worst:e}");
    assert!(
        s.miou > 0.1 && s.miou < 0.9,
        "the perturbation leaves a non-trivial score"
    );
}
