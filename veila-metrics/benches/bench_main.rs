//! veila-metrics benchmarks. Each prints an accuracy table next to its timings (stderr).
//!
//! ```text
//! python3 veila-metrics/benches/scipy_reference.py   # optional: scipy values + timings -> scipy_reference.json
//! cargo bench -p veila-metrics                       # VEILA_BENCH_FD_4096=1 adds the 4096-d Fréchet case
//! ```
//!
//! - `chamfer_kitti`: Chamfer distance between the real KITTI scans 000000/000001 (BVH vs kiddo vs brute
//!   force on a subsample), relative error against scipy's cKDTree value.
//! - `frechet`: exact (eigendecomposition) vs Newton–Schulz at 512 / 2048 (/ 4096) dimensions on SplitMix64
//!   features generated identically by `scipy_reference.py`, relative error against scipy's `sqrtm`.
//! - `bev_mmd`: R2DM BEV MMD for 1000 x 1000 scans, dense (GEMM) vs sparse histograms.

use std::path::Path;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_metrics::{
    Region,
    bev::{BevConfig, BevHistogram, SparseBevHistogram, bev_histogram_sparse},
    chamfer, dist,
    fd::{self, FeatureStats, SqrtMethod},
    nn::nearest_brute_force,
};

fn manifest() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn scipy_reference() -> Option<serde_json::Value> {
    let s = std::fs::read_to_string(manifest().join("benches/scipy_reference.json")).ok()?;
    serde_json::from_str(&s).ok()
}

fn read_kitti(name: &str) -> Option<Vec<Vec3>> {
    let path = manifest()
        .join("../../shared/data/real/kitti/training/velodyne")
        .join(name);
    let bytes = std::fs::read(path).ok()?;
    Some(
        bytes
            .chunks_exact(16)
            .map(|c| {
                let f = |i: usize| f32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
                Vec3::new(f(0), f(4), f(8))
            })
            .collect(),
    )
}

/// Best of `reps` wall-clock runs.
fn time_best<T>(reps: usize, mut f: impl FnMut() -> T) -> (T, Duration) {
    let mut best = Duration::MAX;
    let mut out = None;
    for _ in 0..reps {
        let t = Instant::now();
        let v = f();
        best = best.min(t.elapsed());
        out = Some(v);
    }
    (out.expect("reps > 0"), best)
}

fn rel(a: f64, b: f64) -> f64 {
    ((a - b) / b).abs()
}

fn kiddo_chamfer(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    let one_way = |q: &[[f64; 3]], p: &[[f64; 3]]| -> f64 {
        let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(p).expect("kd-tree");
        let res = tree
            .query_batch(q)
            .nearest_one::<SquaredEuclidean<f64>>()
            .execute();
        res.iter().map(|r| r.distance).sum::<f64>() / q.len() as f64
    };
    one_way(a, b) + one_way(b, a)
}

fn brute_chamfer(a: &[Vec3], b: &[Vec3]) -> f64 {
    use rayon::prelude::*;
    let one_way = |q: &[Vec3], p: &[Vec3]| -> f64 {
        let s: Vec<f64> = q
            .par_iter()
            .map(|&x| nearest_brute_force(p, x).expect("non-empty").dist2)
            .collect();
        s.iter().sum::<f64>() / q.len() as f64
    };
    one_way(a, b) + one_way(b, a)
}

fn bench_chamfer(c: &mut Criterion) {
    let (Some(a), Some(b)) = (read_kitti("000000.bin"), read_kitti("000001.bin")) else {
        eprintln!("skipping chamfer_kitti: KITTI scans not found under ../shared/data/real");
        return;
    };
    let a64: Vec<[f64; 3]> = a.iter().map(|p| p.as_dvec3().to_array()).collect();
    let b64: Vec<[f64; 3]> = b.iter().map(|p| p.as_dvec3().to_array()).collect();
    let scipy = scipy_reference().and_then(|v| {
        let c = &v["chamfer_kitti"];
        Some((c["value"].as_f64()?, c["seconds"].as_f64()?))
    });

    let (bvh, t_bvh) = time_best(5, || {
        chamfer::chamfer_distance(&a, &b).expect("chamfer").value()
    });
    let (kd, t_kd) = time_best(5, || kiddo_chamfer(&a64, &b64));
    eprintln!(
        "\nchamfer_kitti: {} x {} points (build + both directions)",
        a.len(),
        b.len()
    );
    eprintln!(
        "{:<28} {:>22} {:>14} {:>10} {:>12}",
        "method", "value (m^2)", "rel err scipy", "time", "vs scipy"
    );
    let row = |name: &str, v: f64, t: Duration| {
        let (err, speed) = match scipy {
            Some((s, secs)) => (
                format!("{:.2e}", rel(v, s)),
                format!("{:.1}x", secs / t.as_secs_f64()),
            ),
            None => ("n/a".into(), "n/a".into()),
        };
        eprintln!(
            "{name:<28} {v:>22.15e} {err:>14} {:>8.1}ms {speed:>12}",
            t.as_secs_f64() * 1e3
        );
    };
    if let Some((s, secs)) = scipy {
        eprintln!(
            "{:<28} {s:>22.15e} {:>14} {:>8.1}ms {:>12}",
            "scipy cKDTree (reference)",
            "0",
            secs * 1e3,
            "1.0x"
        );
    }
    row("veila BVH (obvhs)", bvh, t_bvh);
    row("kiddo ImmutableKdTree f64", kd, t_kd);

    // subsample: brute force is the exact reference
    let sa: Vec<Vec3> = a.iter().step_by(8).copied().collect();
    let sb: Vec<Vec3> = b.iter().step_by(8).copied().collect();
    let sa64: Vec<[f64; 3]> = sa.iter().map(|p| p.as_dvec3().to_array()).collect();
    let sb64: Vec<[f64; 3]> = sb.iter().map(|p| p.as_dvec3().to_array()).collect();
    let (bf, t_bf) = time_best(1, || brute_chamfer(&sa, &sb));
    let (sbvh, t_sbvh) = time_best(5, || {
        chamfer::chamfer_distance(&sa, &sb)
            .expect("chamfer")
            .value()
    });
    let (skd, t_skd) = time_best(5, || kiddo_chamfer(&sa64, &sb64));
    eprintln!(
        "subsample every 8th point: {} x {} points",
        sa.len(),
        sb.len()
    );
    eprintln!(
        "{:<28} {:>22} {:>14} {:>10}",
        "method", "value (m^2)", "rel err brute", "time"
    );
    for (name, v, t) in [
        ("brute force f64", bf, t_bf),
        ("veila BVH", sbvh, t_sbvh),
        ("kiddo", skd, t_skd),
    ] {
        eprintln!(
            "{name:<28} {v:>22.15e} {:>14.2e} {:>8.1}ms",
            rel(v, bf),
            t.as_secs_f64() * 1e3
        );
    }

    let mut g = c.benchmark_group("chamfer_kitti");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_millis(500));
    g.bench_function("bvh_full", |bch| {
        bch.iter(|| chamfer::chamfer_distance(&a, &b).expect("chamfer"))
    });
    g.bench_function("kiddo_full", |bch| bch.iter(|| kiddo_chamfer(&a64, &b64)));
    g.bench_function("bvh_subsample8", |bch| {
        bch.iter(|| chamfer::chamfer_distance(&sa, &sb).expect("chamfer"))
    });
    g.finish();
}

/// SplitMix64 uniform in [0, 1): identical to `splitmix_uniform` in scipy_reference.py.
fn splitmix_uniform(seed: u64, k: u64) -> f64 {
    let mut z = (seed << 32)
        .wrapping_add(k)
        .wrapping_add(1)
        .wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

/// Same as `features` in scipy_reference.py.
fn features(seed: u64, n: usize, d: usize, decay: f64) -> Vec<f64> {
    let mut x = vec![0.0; n * d];
    for i in 0..n {
        let shared = splitmix_uniform(seed, (i * d) as u64) - 0.5;
        for j in 0..d {
            let u = splitmix_uniform(seed, (i * d + j) as u64);
            x[i * d + j] = (u - 0.5) * (1.0 + j as f64).powf(-decay) + 0.3 * shared;
        }
    }
    x
}

fn bench_frechet(c: &mut Criterion) {
    let scipy = scipy_reference();
    let mut dims = vec![512usize, 2048];
    if std::env::var("VEILA_BENCH_FD_4096").is_ok_and(|v| v == "1") {
        dims.push(4096);
    }
    let mut g = c.benchmark_group("frechet");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(5))
        .warm_up_time(Duration::from_millis(200));
    for d in dims {
        let n = 2 * d;
        let (fa, fb) = (features(1, n, d, 0.25), features(2, n, d, 0.20));
        let t = Instant::now();
        let sa = FeatureStats::from_rows(&fa, d, "a").expect("stats");
        let sb = FeatureStats::from_rows(&fb, d, "b").expect("stats");
        let t_stats = t.elapsed();
        drop((fa, fb));
        let reference = scipy.as_ref().and_then(|v| {
            v["frechet"]
                .as_array()?
                .iter()
                .find(|e| e["dim"].as_u64() == Some(d as u64))
                .and_then(|e| Some((e["value"].as_f64()?, e["seconds"].as_f64()?)))
        });
        let (exact, t_exact) = time_best(2, || fd::frechet_distance(&sa, &sb).expect("fd"));
        eprintln!(
            "\nfrechet d={d}, n={n} rows per set (statistics of both sets: {:.2} s)",
            t_stats.as_secs_f64()
        );
        eprintln!(
            "{:<22} {:>22} {:>14} {:>14} {:>10} {:>10}",
            "method", "FD", "rel err exact", "rel err scipy", "time", "vs scipy"
        );
        let row = |name: String, v: f64, t: Duration| {
            let (es, sp) = match reference {
                Some((s, secs)) => (
                    format!("{:.2e}", rel(v, s)),
                    format!("{:.1}x", secs / t.as_secs_f64()),
                ),
                None => ("n/a".into(), "n/a".into()),
            };
            eprintln!(
                "{name:<22} {v:>22.15e} {:>14.2e} {es:>14} {:>9.3}s {sp:>10}",
                rel(v, exact),
                t.as_secs_f64()
            );
        };
        if let Some((s, secs)) = reference {
            eprintln!(
                "{:<22} {s:>22.15e} {:>14.2e} {:>14} {:>9.3}s {:>10}",
                "scipy sqrtm",
                rel(s, exact),
                "0",
                secs,
                "1.0x"
            );
        }
        row("exact (eigh)".into(), exact, t_exact);
        let iters: &[usize] = if d <= 2048 { &[5, 10, 20] } else { &[5, 10] };
        for &k in iters {
            let m = SqrtMethod::NewtonSchulz { iterations: k };
            let (v, t) = time_best(1, || fd::frechet_distance_with(&sa, &sb, m).expect("fd"));
            row(format!("newton-schulz k={k}"), v, t);
        }
        if d <= 2048 {
            g.bench_function(format!("eigen_{d}"), |bch| {
                bch.iter(|| fd::frechet_distance(&sa, &sb).expect("fd"))
            });
        }
        if d <= 512 {
            g.bench_function(format!("newton_schulz10_{d}"), |bch| {
                bch.iter(|| {
                    fd::frechet_distance_with(&sa, &sb, SqrtMethod::NewtonSchulz { iterations: 10 })
                        .expect("fd")
                })
            });
        }
    }
    g.finish();
}

/// A synthetic LiDAR-like scan: 64 rings on a ground plane, random walls, a random yaw.
fn synthetic_scan(rng: &mut ChaCha8Rng) -> Vec<Vec3> {
    let mut pts = Vec::with_capacity(20_000);
    let walls: Vec<(f32, f32, f32)> = (0..6)
        .map(|_| {
            (
                rng.random_range(5.0..40.0),
                rng.random_range(-3.2..3.2),
                rng.random_range(0.3..1.2),
            )
        })
        .collect();
    for ring in 0..32 {
        let elev = -0.03 - 0.012 * ring as f32;
        for k in 0..600 {
            let az = k as f32 / 600.0 * std::f32::consts::TAU - std::f32::consts::PI;
            let mut r = (1.73 / -elev.tan()).min(120.0) * rng.random_range(0.97..1.03);
            for &(wr, wa, ww) in &walls {
                let da = (az - wa + std::f32::consts::PI).rem_euclid(std::f32::consts::TAU)
                    - std::f32::consts::PI;
                if da.abs() < ww * 0.5 && wr < r {
                    r = wr;
                }
            }
            pts.push(Vec3::new(r * az.cos(), r * az.sin(), r * elev.sin()));
        }
    }
    pts
}

fn bench_bev_mmd(c: &mut Criterion) {
    let n = 1000;
    let cfg = BevConfig::r2dm();
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let t = Instant::now();
    let make = |rng: &mut ChaCha8Rng| -> Vec<SparseBevHistogram> {
        (0..n)
            .map(|_| {
                bev_histogram_sparse(&synthetic_scan(rng), &cfg, Region::All, "scan").expect("hist")
            })
            .collect()
    };
    let sg = make(&mut rng);
    let sr = make(&mut rng);
    let dg: Vec<BevHistogram> = sg.iter().map(|s| s.to_dense()).collect();
    let dr: Vec<BevHistogram> = sr.iter().map(|s| s.to_dense()).collect();
    let nnz = sg.iter().map(|s| s.cells.len()).sum::<usize>() as f64 / n as f64;
    eprintln!(
        "\nbev_mmd: {n} x {n} synthetic scans, {nnz:.0} occupied cells per scan on average (setup {:.1} s)",
        t.elapsed().as_secs_f64()
    );
    let (vd, td) = time_best(1, || dist::mmd_r2dm_dense(&dg, &dr, 0.5).expect("mmd"));
    let (vs, ts) = time_best(1, || dist::mmd_r2dm_sparse(&sg, &sr, 0.5).expect("mmd"));
    eprintln!(
        "{:<22} {:>22} {:>12} {:>10}",
        "histograms", "MMD (raw)", "x 1e4", "time"
    );
    eprintln!(
        "{:<22} {vd:>22.15e} {:>12.6} {:>9.3}s",
        "dense (GEMM)",
        vd * 1e4,
        td.as_secs_f64()
    );
    eprintln!(
        "{:<22} {vs:>22.15e} {:>12.6} {:>9.3}s",
        "sparse",
        vs * 1e4,
        ts.as_secs_f64()
    );
    eprintln!("relative difference dense vs sparse: {:.2e}", rel(vs, vd));

    let mut g = c.benchmark_group("bev_mmd_1000x1000");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(10))
        .warm_up_time(Duration::from_millis(100));
    g.bench_function("dense", |bch| {
        bch.iter(|| dist::mmd_r2dm_dense(&dg, &dr, 0.5).expect("mmd"))
    });
    g.bench_function("sparse", |bch| {
        bch.iter(|| dist::mmd_r2dm_sparse(&sg, &sr, 0.5).expect("mmd"))
    });
    g.finish();
}

criterion_group!(benches, bench_chamfer, bench_frechet, bench_bev_mmd);
criterion_main!(benches);
