//! The BVH nearest-neighbour query against brute force.

use glam::Vec3;
use proptest::prelude::*;
use veila_metrics::{
    chamfer,
    nn::{PointIndex, nearest_brute_force},
};

fn brute_chamfer(a: &[Vec3], b: &[Vec3]) -> f64 {
    let ab: f64 = a
        .iter()
        .map(|&p| nearest_brute_force(b, p).unwrap().dist2)
        .sum::<f64>()
        / a.len() as f64;
    let ba: f64 = b
        .iter()
        .map(|&p| nearest_brute_force(a, p).unwrap().dist2)
        .sum::<f64>()
        / b.len() as f64;
    ab + ba
}

fn point(scale: f32) -> impl Strategy<Value = Vec3> {
    (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0).prop_map(move |(x, y, z)| Vec3::new(x, y, z) * scale)
}

fn cloud() -> impl Strategy<Value = Vec<Vec3>> {
    prop_oneof![
        // spread out
        (1usize..300).prop_flat_map(|n| prop::collection::vec(point(50.0), n)),
        // clustered with exact duplicates
        (1usize..100)
            .prop_flat_map(|n| prop::collection::vec(point(0.01), n))
            .prop_map(|mut v| {
                let k = v.len();
                v.extend_from_within(..k / 2);
                v
            }),
        // on a plane (degenerate boxes)
        (1usize..200).prop_flat_map(|n| prop::collection::vec(
            point(20.0).prop_map(|p| Vec3::new(p.x, p.y, -1.7)),
            n
        )),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn nearest_equals_brute_force(pts in cloud(), queries in prop::collection::vec(point(60.0), 1..60)) {
        let idx = PointIndex::build(&pts, "cloud").unwrap();
        prop_assert_eq!(idx.len(), pts.len());
        for &q in &queries {
            let got = idx.nearest(q);
            let want = nearest_brute_force(&pts, q).unwrap();
            prop_assert_eq!(got.dist2, want.dist2);
            // the index points at a point at that distance (ties may pick another index)
            let p = pts[got.index];
            let d = (p.x as f64 - q.x as f64).powi(2) + (p.y as f64 - q.y as f64).powi(2) + (p.z as f64 - q.z as f64).powi(2);
            prop_assert_eq!(d, want.dist2);
        }
        // query the indexed points themselves: all at distance 0
        let all = idx.nearest_dist2_all(&pts);
        prop_assert!(all.iter().all(|&d| d == 0.0));
        // batch queries agree with single ones
        let batch = idx.nearest_dist2_all(&queries);
        for (q, d) in queries.iter().zip(batch) {
            prop_assert_eq!(d, idx.nearest(*q).dist2);
        }
    }

    #[test]
    fn chamfer_equals_brute_force(a in cloud(), b in cloud()) {
        let got = chamfer::chamfer_distance(&a, &b).unwrap().value();
        let want = brute_chamfer(&a, &b);
        prop_assert!((got - want).abs() <= 1e-12 * want.max(1e-300), "{} vs {}", got, want);
    }
}

#[test]
fn single_point_index() {
    let idx = PointIndex::build(&[Vec3::new(1.0, 2.0, 3.0)], "one").unwrap();
    let n = idx.nearest(Vec3::ZERO);
    assert_eq!((n.dist2, n.index), (14.0, 0));
}

#[test]
fn real_kitti_scan_subsample_matches_brute_force() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real/kitti/training/velodyne");
    let read = |name: &str| -> Option<Vec<Vec3>> {
        let bytes = std::fs::read(dir.join(name)).ok()?;
        Some(
            bytes
                .chunks_exact(16)
                .map(|c| {
                    let f = |i: usize| f32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
                    Vec3::new(f(0), f(4), f(8))
                })
                .collect(),
        )
    };
    let (Some(a), Some(b)) = (read("000000.bin"), read("000001.bin")) else {
        eprintln!("skipping: {} not found", dir.display());
        return;
    };
    let idx = PointIndex::build(&b, "000001").unwrap();
    for q in a.iter().step_by(97) {
        assert_eq!(
            idx.nearest(*q).dist2,
            nearest_brute_force(&b, *q).unwrap().dist2
        );
    }
}
