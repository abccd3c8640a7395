//! Golden values from numpy / scipy (`tests/data/make_golden.py` writes `tests/data/golden.json`).

use glam::Vec3;
use serde_json::Value;
use veila_metrics::{
    Region,
    bev::{BevConfig, BevHistogram, bev_histogram, bev_histogram_sparse},
    chamfer, dist, fd,
    lidm::{LidmBevConfig, lidm_bev_occupancy, mmd_lidm},
};

fn golden() -> Value {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/golden.json");
    serde_json::from_str(&std::fs::read_to_string(path).expect("golden.json")).expect("valid json")
}

fn points(v: &Value) -> Vec<Vec3> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let a = p.as_array().unwrap();
            Vec3::new(
                a[0].as_f64().unwrap() as f32,
                a[1].as_f64().unwrap() as f32,
                a[2].as_f64().unwrap() as f32,
            )
        })
        .collect()
}

fn scans(v: &Value) -> Vec<Vec<Vec3>> {
    v.as_array().unwrap().iter().map(points).collect()
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn assert_rel(got: f64, want: f64, tol: f64, what: &str) {
    let err = (got - want).abs() / want.abs().max(1e-300);
    assert!(
        err <= tol,
        "{what}: got {got:.17e}, want {want:.17e}, rel err {err:.3e} > {tol:.0e}"
    );
}

#[test]
fn bev_histograms_and_distribution_metrics_match_numpy_scipy() {
    let g = golden();
    let bev = &g["bev"];
    let gen_scans = scans(&bev["generated"]);
    let ref_scans = scans(&bev["reference"]);
    let cfg = BevConfig::r2dm();
    for region in Region::ALL {
        let want = &bev["regions"][region.name()];
        let hg: Vec<BevHistogram> = gen_scans
            .iter()
            .map(|s| bev_histogram(s, &cfg, region, "generated").unwrap())
            .collect();
        let hr: Vec<BevHistogram> = ref_scans
            .iter()
            .map(|s| bev_histogram(s, &cfg, region, "reference").unwrap())
            .collect();
        // histograms: exact integer equality with numpy.histogramdd
        for (set, hs) in [("hist_generated", &hg), ("hist_reference", &hr)] {
            for (i, h) in hs.iter().enumerate() {
                let want_cells: Vec<(u32, u32)> = want[set][i]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|c| (c[0].as_u64().unwrap() as u32, c[1].as_u64().unwrap() as u32))
                    .collect();
                let sparse = h.to_sparse();
                let got: Vec<(u32, u32)> = sparse
                    .cells
                    .iter()
                    .copied()
                    .zip(sparse.counts.iter().copied())
                    .collect();
                assert_eq!(got, want_cells, "{region} {set} {i}");
            }
        }
        let sg: Vec<_> = gen_scans
            .iter()
            .map(|s| bev_histogram_sparse(s, &cfg, region, "g").unwrap())
            .collect();
        let sr: Vec<_> = ref_scans
            .iter()
            .map(|s| bev_histogram_sparse(s, &cfg, region, "r").unwrap())
            .collect();
        assert_eq!(sg[0].to_dense(), hg[0]);

        assert_rel(
            dist::jsd(&hg, &hr).unwrap(),
            want["jsd"].as_f64().unwrap(),
            1e-12,
            "jsd",
        );
        assert_rel(
            dist::jsd(&sg, &sr).unwrap(),
            want["jsd"].as_f64().unwrap(),
            1e-12,
            "jsd sparse",
        );
        let mmd = want["mmd_r2dm"].as_f64().unwrap();
        assert_rel(
            dist::mmd_r2dm_dense(&hg, &hr, 0.5).unwrap(),
            mmd,
            1e-9,
            "mmd r2dm dense",
        );
        assert_rel(
            dist::mmd_r2dm_sparse(&sg, &sr, 0.5).unwrap(),
            mmd,
            1e-9,
            "mmd r2dm sparse",
        );
        let mmd_lg = want["mmd_lidargen"].as_f64().unwrap();
        assert_rel(
            dist::mmd_lidargen(&hg, &hr, 0.5).unwrap(),
            mmd_lg,
            1e-9,
            "mmd lidargen",
        );

        let lcfg = LidmBevConfig::kitti();
        let og: Vec<_> = gen_scans
            .iter()
            .map(|s| lidm_bev_occupancy(s, &lcfg, region, "g").unwrap())
            .collect();
        let or: Vec<_> = ref_scans
            .iter()
            .map(|s| lidm_bev_occupancy(s, &lcfg, region, "r").unwrap())
            .collect();
        assert_rel(
            mmd_lidm(&og, &or).unwrap(),
            want["mmd_lidm"].as_f64().unwrap(),
            1e-12,
            "mmd lidm",
        );
    }
}

#[test]
fn jensen_shannon_of_vectors_matches_scipy() {
    let g = golden();
    let v = &g["js_vectors"];
    let d = dist::jensen_shannon_distance(&f64s(&v["p"]), &f64s(&v["q"])).unwrap();
    assert_rel(d, v["distance"].as_f64().unwrap(), 1e-13, "jensenshannon");
}

#[test]
fn frechet_matches_mpmath_numpy_and_scipy() {
    let g = golden();
    for case in g["frechet"].as_array().unwrap() {
        let name = case["name"].as_str().unwrap();
        let dim = case["dim"].as_u64().unwrap() as usize;
        let (a, b) = (f64s(&case["a"]), f64s(&case["b"]));
        // 50-digit mpmath reference; numpy's eigh (double precision) carries sqrt(eps)-level noise on
        // singular covariances, scipy's sqrtm more
        let want = case["fd_mp"].as_f64().unwrap();
        let got = fd::frechet_distance_rows(&a, &b, dim, fd::SqrtMethod::Eigen).unwrap();
        assert_rel(got, want, 1e-11, name);
        assert_rel(got, case["fd_eigh"].as_f64().unwrap(), 1e-7, name);
        // scipy's sqrtm is itself inaccurate on singular covariances (~1e-8), so compare loosely
        assert_rel(got, case["fd_scipy_sqrtm"].as_f64().unwrap(), 1e-6, name);
        // covariance equals numpy.cov
        let stats = fd::FeatureStats::from_rows(&a, dim, "a").unwrap();
        for (x, y) in stats.covariance().unwrap().iter().zip(f64s(&case["cov_a"])) {
            assert!(
                (x - y).abs() <= 1e-12 * y.abs().max(1.0),
                "{name} cov {x} vs {y}"
            );
        }
        // streaming in uneven shards and merging gives the same distance
        let mut s1 = fd::FeatureStats::new(dim);
        let mut parts = Vec::new();
        for chunk in a.chunks(dim * 3) {
            let mut p = fd::FeatureStats::new(dim);
            p.push_rows(chunk, "shard").unwrap();
            parts.push(p);
        }
        for p in &parts {
            s1.merge(p).unwrap();
        }
        let s2 = fd::FeatureStats::from_rows(&b, dim, "b").unwrap();
        assert_rel(
            fd::frechet_distance(&s1, &s2).unwrap(),
            want,
            1e-10,
            "merged shards",
        );
    }
}

#[test]
fn chamfer_matches_scipy_ckdtree() {
    let g = golden();
    let c = &g["chamfer"];
    let (a, b) = (points(&c["a"]), points(&c["b"]));
    let got = chamfer::chamfer_distance(&a, &b).unwrap();
    assert_rel(got.a_to_b, c["a_to_b"].as_f64().unwrap(), 1e-12, "a_to_b");
    assert_rel(got.b_to_a, c["b_to_a"].as_f64().unwrap(), 1e-12, "b_to_a");
    assert_rel(got.value(), c["value"].as_f64().unwrap(), 1e-12, "chamfer");
    // [f32; 3] input works the same
    let aa: Vec<[f32; 3]> = a.iter().map(|p| p.to_array()).collect();
    let bb: Vec<[f32; 3]> = b.iter().map(|p| p.to_array()).collect();
    assert_eq!(chamfer::chamfer_distance(&aa, &bb).unwrap(), got);
}
