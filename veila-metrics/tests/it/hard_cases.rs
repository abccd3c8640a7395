//! Degenerate and extreme inputs: identical sets, disjoint supports, singular covariances, single scans,
//! empty windows, huge coordinates, empty and non-finite inputs.

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_metrics::{
    Error, MetricReport, MetricValue, Protocol, Region,
    bev::{BevConfig, BevHistogram, bev_histogram, bev_histogram_sparse},
    chamfer, dist, fd,
    lidm::{LidmBevConfig, lidm_bev_occupancy, mmd_lidm},
};

fn random_scan(rng: &mut ChaCha8Rng, n: usize) -> Vec<Vec3> {
    (0..n)
        .map(|_| {
            let r: f32 = rng.random_range(2.0..75.0);
            let t: f32 = rng.random_range(-std::f32::consts::PI..std::f32::consts::PI);
            Vec3::new(r * t.cos(), r * t.sin(), rng.random_range(-2.0..1.0))
        })
        .collect()
}

fn hists(scans: &[Vec<Vec3>]) -> Vec<BevHistogram> {
    scans
        .iter()
        .map(|s| bev_histogram(s, &BevConfig::r2dm(), Region::All, "scan").unwrap())
        .collect()
}

#[test]
fn identical_sets_give_exactly_zero_everywhere() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let scans: Vec<Vec<Vec3>> = (0..4).map(|_| random_scan(&mut rng, 500)).collect();
    let h = hists(&scans);
    let s: Vec<_> = h.iter().map(|x| x.to_sparse()).collect();
    assert_eq!(dist::jsd(&h, &h).unwrap(), 0.0);
    assert_eq!(dist::mmd_r2dm_dense(&h, &h, 0.5).unwrap(), 0.0);
    assert_eq!(dist::mmd_r2dm_sparse(&s, &s, 0.5).unwrap(), 0.0);
    assert_eq!(dist::mmd_lidargen(&h, &h, 0.5).unwrap(), 0.0);
    let occ: Vec<_> = scans
        .iter()
        .map(|p| lidm_bev_occupancy(p, &LidmBevConfig::kitti(), Region::All, "s").unwrap())
        .collect();
    assert_eq!(mmd_lidm(&occ, &occ).unwrap(), 0.0);
    assert_eq!(
        chamfer::chamfer_distance(&scans[0], &scans[0])
            .unwrap()
            .value(),
        0.0
    );
    let feats: Vec<f32> = (0..40 * 6).map(|_| rng.random_range(-1.0..1.0)).collect();
    assert_eq!(
        fd::frechet_distance_rows(&feats, &feats, 6, fd::SqrtMethod::Eigen).unwrap(),
        0.0
    );
    // same distribution, different row order: not bitwise identical statistics, still >= 0 and tiny
    let mut rev = feats
        .chunks(6)
        .rev()
        .flatten()
        .copied()
        .collect::<Vec<f32>>();
    let v = fd::frechet_distance_rows(&feats, &rev, 6, fd::SqrtMethod::Eigen).unwrap();
    assert!((0.0..1e-12).contains(&v), "{v}");
    rev.clear();
}

#[test]
fn disjoint_supports_give_sqrt_ln2() {
    let a = vec![Vec3::new(10.0, 10.0, 0.0); 7];
    let b = vec![Vec3::new(-30.0, 20.0, 0.0), Vec3::new(50.0, -5.0, 1.0)];
    let d = dist::jsd(&hists(&[a]), &hists(&[b])).unwrap();
    assert!((d - std::f64::consts::LN_2.sqrt()).abs() < 1e-15, "{d}");
}

#[test]
fn single_scan_mmd_matches_closed_form() {
    // one scan per set: MMD = 2 - 2 exp(-||p - q||^2 / (2 sigma^2))
    let a = vec![
        Vec3::new(10.0, 10.0, 0.0),
        Vec3::new(10.0, 10.0, 0.0),
        Vec3::new(-20.0, 5.0, 0.0),
    ];
    let b = vec![Vec3::new(10.0, 10.0, 0.0), Vec3::new(40.0, 5.0, 0.0)];
    let (ha, hb) = (hists(&[a]), hists(&[b]));
    // p = (2/3 at c1, 1/3 at c2), q = (1/2 at c1, 1/2 at c3)
    let d2 = (2.0f64 / 3.0 - 0.5).powi(2) + (1.0f64 / 3.0).powi(2) + 0.25;
    let want = 2.0 - 2.0 * (-d2 / (2.0 * 0.25)).exp();
    let got = dist::mmd_r2dm_dense(&ha, &hb, 0.5).unwrap();
    assert!((got - want).abs() < 1e-15, "{got} vs {want}");
    let sa: Vec<_> = ha.iter().map(|h| h.to_sparse()).collect();
    let sb: Vec<_> = hb.iter().map(|h| h.to_sparse()).collect();
    assert!((dist::mmd_r2dm_sparse(&sa, &sb, 0.5).unwrap() - want).abs() < 1e-15);
}

#[test]
fn dense_and_sparse_mmd_agree_on_random_scans() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let g: Vec<Vec<Vec3>> = (0..6).map(|_| random_scan(&mut rng, 800)).collect();
    let r: Vec<Vec<Vec3>> = (0..5).map(|_| random_scan(&mut rng, 600)).collect();
    let (hg, hr) = (hists(&g), hists(&r));
    let sg: Vec<_> = g
        .iter()
        .map(|s| bev_histogram_sparse(s, &BevConfig::r2dm(), Region::All, "g").unwrap())
        .collect();
    let sr: Vec<_> = r
        .iter()
        .map(|s| bev_histogram_sparse(s, &BevConfig::r2dm(), Region::All, "r").unwrap())
        .collect();
    let d = dist::mmd_r2dm_dense(&hg, &hr, 0.5).unwrap();
    let s = dist::mmd_r2dm_sparse(&sg, &sr, 0.5).unwrap();
    assert!(d > 0.0 && ((d - s) / d).abs() < 1e-10, "{d} vs {s}");
}

#[test]
fn scans_without_points_in_the_window() {
    // everything closer than 3 m or farther than 70 m
    let empty = vec![
        Vec3::new(1.0, 0.0, 0.0),
        Vec3::new(100.0, 0.0, 0.0),
        Vec3::new(0.0, 0.0, 2.9),
    ];
    let ok = vec![Vec3::new(10.0, 0.0, 0.0)];
    let (he, ho) = (
        hists(std::slice::from_ref(&empty)),
        hists(std::slice::from_ref(&ok)),
    );
    assert_eq!(he[0].total, 0);
    // MMD normalises per scan: a scan without points is an error naming it
    match dist::mmd_r2dm_dense(&ho, &[ho[0].clone(), he[0].clone()], 0.5) {
        Err(Error::NoPointsInWindow { what, .. }) => assert_eq!(what, "reference scan 1"),
        other => panic!("{other:?}"),
    }
    // JSD sums first: one empty scan is fine, an all-empty set is an error
    assert!(dist::jsd(&[ho[0].clone(), he[0].clone()], &ho).unwrap() == 0.0);
    assert!(matches!(
        dist::jsd(&he, &ho),
        Err(Error::NoPointsInWindow { .. })
    ));
    // LiDM window is |x|, |y| < 50 m
    let far = vec![Vec3::new(60.0, 0.0, 0.0)];
    let o = lidm_bev_occupancy(&far, &LidmBevConfig::kitti(), Region::All, "far").unwrap();
    assert!(matches!(
        mmd_lidm(std::slice::from_ref(&o), std::slice::from_ref(&o)),
        Err(Error::NoPointsInWindow { .. })
    ));
}

#[test]
fn regions_split_at_x_zero() {
    let pts = vec![
        Vec3::new(10.0, 0.0, 0.0),
        Vec3::new(0.0, 10.0, 0.0),
        Vec3::new(-10.0, 0.0, 0.0),
    ];
    let f = bev_histogram(&pts, &BevConfig::r2dm(), Region::Front, "s").unwrap();
    let r = bev_histogram(&pts, &BevConfig::r2dm(), Region::Rear, "s").unwrap();
    let a = bev_histogram(&pts, &BevConfig::r2dm(), Region::All, "s").unwrap();
    assert_eq!((f.total, r.total, a.total), (1, 2, 3));
}

#[test]
fn empty_and_non_finite_inputs_are_typed_errors() {
    let none: Vec<BevHistogram> = vec![];
    let one = hists(&[vec![Vec3::new(10.0, 0.0, 0.0)]]);
    assert!(matches!(dist::jsd(&none, &one), Err(Error::Empty { .. })));
    assert!(matches!(
        dist::mmd_r2dm_dense(&one, &none, 0.5),
        Err(Error::Empty { .. })
    ));
    assert!(matches!(
        dist::mmd_r2dm_dense(&one, &one, 0.0),
        Err(Error::InvalidParameter { .. })
    ));
    let empty: Vec<Vec3> = vec![];
    assert!(matches!(
        chamfer::chamfer_distance(&empty, &[Vec3::ONE]),
        Err(Error::Empty { .. })
    ));
    let nan = [Vec3::ONE, Vec3::new(f32::NAN, 0.0, 0.0)];
    match chamfer::chamfer_distance(&nan, &[Vec3::ONE]) {
        Err(Error::NonFinite { index, .. }) => assert_eq!(index, 1),
        other => panic!("{other:?}"),
    }
    assert!(matches!(
        bev_histogram(
            &[Vec3::new(f32::INFINITY, 0.0, 0.0)],
            &BevConfig::r2dm(),
            Region::All,
            "s"
        ),
        Err(Error::NonFinite { .. })
    ));
    // Fréchet: one row has no covariance; mismatched dimensions; NaN features
    assert!(matches!(
        fd::frechet_distance_rows(
            &[1.0f64, 2.0],
            &[1.0, 2.0, 3.0, 4.0],
            2,
            fd::SqrtMethod::Eigen
        ),
        Err(Error::TooFewSamples { .. })
    ));
    let a = fd::FeatureStats::from_rows(&[1.0f64, 2.0, 3.0, 4.0], 2, "a").unwrap();
    let b = fd::FeatureStats::from_rows(&[1.0f64, 2.0, 3.0, 4.0, 5.0, 6.0], 3, "b").unwrap();
    assert!(matches!(
        fd::frechet_distance(&a, &b),
        Err(Error::ShapeMismatch { .. })
    ));
    assert!(matches!(
        fd::FeatureStats::from_rows(&[1.0f64, f64::NAN], 2, "a"),
        Err(Error::NonFinite { index: 1, .. })
    ));
    assert!(matches!(
        fd::FeatureStats::from_rows(&[1.0f64, 2.0, 3.0], 2, "a"),
        Err(Error::ShapeMismatch { .. })
    ));
}

#[test]
fn huge_coordinates() {
    // Chamfer in f64: (2e18)^2 = 4e36 each way, far beyond f32 range
    let a = [Vec3::new(1e18, 0.0, 0.0)];
    let b = [Vec3::new(-1e18, 0.0, 0.0)];
    let cd = chamfer::chamfer_distance(&a, &b).unwrap();
    let x = 1e18f32 as f64; // the f32 nearest to 1e18
    assert_eq!(cd.value(), 2.0 * (2.0 * x) * (2.0 * x));
    assert!(cd.value() > 7.9e36);
    // BVH with box distances that overflow f32 still finds the exact neighbour
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let pts: Vec<Vec3> = (0..200)
        .map(|_| {
            Vec3::new(
                rng.random_range(-3e30..3e30),
                rng.random_range(-3e30..3e30),
                rng.random_range(-1.0..1.0),
            )
        })
        .collect();
    let idx = veila_metrics::nn::PointIndex::build(&pts, "huge").unwrap();
    for _ in 0..50 {
        let q = Vec3::new(
            rng.random_range(-3e30..3e30),
            rng.random_range(-3e30..3e30),
            0.0,
        );
        let got = idx.nearest(q);
        let want = veila_metrics::nn::nearest_brute_force(&pts, q).unwrap();
        assert_eq!(got.dist2, want.dist2);
    }
    // Fréchet distance scales with the square of the features
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let fa: Vec<f64> = (0..30 * 4).map(|_| rng.random_range(-1.0..1.0)).collect();
    let fb: Vec<f64> = (0..25 * 4).map(|_| rng.random_range(-0.5..1.5)).collect();
    let base = fd::frechet_distance_rows(&fa, &fb, 4, fd::SqrtMethod::Eigen).unwrap();
    let c = 1e12;
    let fa2: Vec<f64> = fa.iter().map(|v| v * c).collect();
    let fb2: Vec<f64> = fb.iter().map(|v| v * c).collect();
    let big = fd::frechet_distance_rows(&fa2, &fb2, 4, fd::SqrtMethod::Eigen).unwrap();
    assert!(
        ((big / (c * c)) - base).abs() / base < 1e-10,
        "{big} vs {base}"
    );
    // Large offset: streaming statistics stay accurate (naive sum of outer products would not)
    let off = 1e9;
    let fa3: Vec<f64> = fa.iter().map(|v| v + off).collect();
    let fb3: Vec<f64> = fb.iter().map(|v| v + off).collect();
    let mut sa = fd::FeatureStats::new(4);
    for ch in fa3.chunks(8) {
        sa.push_rows(ch, "a").unwrap();
    }
    let sb = fd::FeatureStats::from_rows(&fb3, 4, "b").unwrap();
    let shifted = fd::frechet_distance(&sa, &sb).unwrap();
    assert!((shifted - base).abs() / base < 1e-6, "{shifted} vs {base}");
}

#[test]
fn singular_covariance_and_more_dims_than_samples() {
    // b is a copy of a in a 3-D subspace of 10-D; FD(a, a) = 0, FD(a, a + t) = |t|^2 exactly
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let dim = 10;
    let basis: Vec<f64> = (0..3 * dim).map(|_| rng.random_range(-1.0..1.0)).collect();
    let rows = 6; // fewer samples than dimensions
    let mut a = vec![0.0f64; rows * dim];
    for i in 0..rows {
        let c: [f64; 3] = [
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ];
        for j in 0..dim {
            a[i * dim + j] = (0..3).map(|k| c[k] * basis[k * dim + j]).sum();
        }
    }
    let t: Vec<f64> = (0..dim).map(|j| 0.1 * j as f64).collect();
    let b: Vec<f64> = a.iter().enumerate().map(|(k, v)| v + t[k % dim]).collect();
    let want: f64 = t.iter().map(|x| x * x).sum();
    let got = fd::frechet_distance_rows(&a, &b, dim, fd::SqrtMethod::Eigen).unwrap();
    assert!(
        (got - want).abs() < 1e-12 * want.max(1.0),
        "{got} vs {want}"
    );
}

#[test]
fn newton_schulz_converges_on_a_well_conditioned_problem() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let dim = 8;
    let a: Vec<f64> = (0..200 * dim)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let b: Vec<f64> = (0..150 * dim)
        .map(|_| rng.random_range(-0.8..1.3))
        .collect();
    let exact = fd::frechet_distance_rows(&a, &b, dim, fd::SqrtMethod::Eigen).unwrap();
    let ns =
        fd::frechet_distance_rows(&a, &b, dim, fd::SqrtMethod::NewtonSchulz { iterations: 30 })
            .unwrap();
    let few =
        fd::frechet_distance_rows(&a, &b, dim, fd::SqrtMethod::NewtonSchulz { iterations: 2 })
            .unwrap();
    assert!(((ns - exact) / exact).abs() < 1e-9, "{ns} vs {exact}");
    assert!(
        ((few - exact) / exact).abs() > 1e-6,
        "two iterations should not be converged"
    );
}

#[test]
fn metric_json_shape() {
    let report = MetricReport {
        metrics: vec![MetricValue {
            name: "jsd".into(),
            protocol: Protocol::R2dm,
            region: Region::Front,
            value: 0.0123,
            generated: 10,
            reference: 10,
            paper_scale: None,
        }],
    };
    let s = serde_json::to_string(&report).unwrap();
    assert_eq!(
        s,
        r#"{"metrics":[{"name":"jsd","protocol":"r2dm","region":"front","value":0.0123,"generated":10,"reference":10}]}"#
    );
    let back: MetricReport = serde_json::from_str(&s).unwrap();
    assert_eq!(back, report);
}

#[test]
fn newton_schulz_divergence_is_an_error_not_a_perfect_score() {
    // 5 samples in 16 dimensions: both covariances have rank 4, Σ₁Σ₂ is singular and the coupled
    // iteration blows up; the exact method still gives the right, positive value
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let dim = 16;
    let a: Vec<f64> = (0..5 * dim).map(|_| rng.random_range(-1.0..1.0)).collect();
    let b: Vec<f64> = (0..5 * dim).map(|_| rng.random_range(-1.0..1.0)).collect();
    let exact = fd::frechet_distance_rows(&a, &b, dim, fd::SqrtMethod::Eigen).unwrap();
    assert!(exact > 0.1, "{exact}");
    let err = fd::frechet_distance_rows(
        &a,
        &b,
        dim,
        fd::SqrtMethod::NewtonSchulz { iterations: 100 },
    )
    .unwrap_err();
    assert!(
        matches!(&err, veila_metrics::Error::Linalg(m) if m.contains("Newton–Schulz diverged")),
        "{err}"
    );
}
