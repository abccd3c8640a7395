//! veila-geom benchmarks: `cargo bench -p veila-geom`.
//!
//! - `project_kitti/*`: projecting a real KITTI scan (000000, 115,384 points) into 64 x 1024 with the
//!   exact and the fast angle paths, on 1 and 2 threads. Prints the "what accuracy costs in time" table:
//!   largest angular error of the polynomial atan2 / asin over the scan against `f64`, and how many
//!   points the fast path puts into another pixel than the exact path. Falls back to a synthetic scan
//!   (with a note) when ../shared/data/real is absent.
//! - `epipolar_build/K*`: building the GCMA epipolar tables at 64 x 1024 for K = 8 and K = 32, with the
//!   memory of the table and of one bilinear gather.
//!
//! The numpy reference for the projection is `benches/numpy_reference.py`.

use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::{Mat3, Vec3};
use veila_geom::fastmath::{asin_approx, atan2_approx};
use veila_geom::{
    AngleMethod, DepthSpacing, EpipolarConfig, EpipolarTable, LidarSensor, PinholeCamera,
    ProjectionOptions, Projector, RayTable,
};

/// KITTI 000000, or a synthetic KITTI-like scan (ground plane and walls seen by a 64 x 1800 spinning
/// sensor) when the real data is absent.
fn load_scan() -> (Vec<Vec3>, String) {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real/kitti/training/velodyne/000000.bin");
    if let Ok(bytes) = std::fs::read(&p) {
        let f = |c: &[u8], i: usize| {
            f32::from_le_bytes([c[4 * i], c[4 * i + 1], c[4 * i + 2], c[4 * i + 3]])
        };
        let pts = bytes
            .chunks_exact(16)
            .map(|c| Vec3::new(f(c, 0), f(c, 1), f(c, 2)))
            .collect();
        return (pts, "KITTI 000000".into());
    }
    eprintln!(
        "note: {} not found, benchmarking a synthetic scan instead",
        p.display()
    );
    let mut pts = Vec::new();
    for r in 0..64 {
        let el = (2.0f64 - r as f64 * 26.9 / 63.0).to_radians();
        for c in 0..1800 {
            let az = c as f64 / 1800.0 * std::f64::consts::TAU;
            let dir = Vec3::new(
                (el.cos() * az.cos()) as f32,
                (el.cos() * az.sin()) as f32,
                el.sin() as f32,
            );
            // ground at z = -1.73, walls at |y| = 8 and x = 40
            let mut t = 80.0f32;
            if dir.z < 0.0 {
                t = t.min(-1.73 / dir.z);
            }
            if dir.y.abs() > 1e-3 {
                t = t.min(8.0 / dir.y.abs());
            }
            if dir.x > 1e-3 {
                t = t.min(40.0 / dir.x);
            }
            pts.push(dir * t * (1.0 + 0.001 * ((r * 7 + c) % 13) as f32));
        }
    }
    (pts, "synthetic 64x1800 scan".into())
}

/// Median wall time of `f` over `n` runs, milliseconds.
fn median_ms(n: usize, mut f: impl FnMut()) -> f64 {
    let mut t: Vec<f64> = (0..n)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[n / 2]
}

fn bench_project(c: &mut Criterion) {
    let (pts, name) = load_scan();
    let sensor = LidarSensor::hdl64e();
    let exact = Projector::new(&sensor, ProjectionOptions::default()).unwrap();
    let fast = Projector::new(
        &sensor,
        ProjectionOptions {
            angles: AngleMethod::Fast,
            ..Default::default()
        },
    )
    .unwrap();

    // accuracy of the fast path over this scan
    let (mut err_atan2, mut err_asin) = (0.0f64, 0.0f64);
    for p in &pts {
        let (x, y, z) = (p.x as f64, p.y as f64, p.z as f64);
        let e = (atan2_approx(p.y, p.x) as f64 - y.atan2(x)).abs();
        err_atan2 = err_atan2.max(e.min((e - std::f64::consts::TAU).abs()));
        let d = (x * x + y * y + z * z).sqrt();
        if d > 0.0 {
            let s = (p.z / (d as f32)).clamp(-1.0, 1.0);
            err_asin = err_asin.max((asin_approx(s) as f64 - (z / d).asin()).abs());
        }
    }
    let moved = pts
        .iter()
        .filter(|p| fast.try_pixel(**p, None) != exact.try_pixel(**p, None))
        .count();

    let mut g = c.benchmark_group("project_kitti");
    g.throughput(Throughput::Elements(pts.len() as u64));
    let mut rows = Vec::new();
    for (label, pr) in [("exact", &exact), ("fast", &fast)] {
        for threads in [1usize, 2] {
            let pr = pr.clone().with_threads(threads);
            g.bench_function(format!("{label}_{threads}t"), |b| {
                b.iter(|| pr.project(black_box(&pts), None, None).unwrap())
            });
            let ms = median_ms(30, || {
                black_box(pr.project(black_box(&pts), None, None).unwrap());
            });
            rows.push((label, threads, ms));
        }
    }
    g.finish();
    eprintln!(
        "\nwhat accuracy costs in time: projecting {name} ({} points) into 64x1024",
        pts.len()
    );
    eprintln!(
        "{:<6} {:>7} {:>10} {:>12} {:>22} {:>22}",
        "path", "threads", "ms/scan", "Mpoints/s", "max angle error (rad)", "points in other pixel"
    );
    for (label, threads, ms) in rows {
        let (err, moved) = if label == "exact" {
            ("0 (exact)".to_string(), "0 (reference)".to_string())
        } else {
            (
                format!("atan2 {err_atan2:.1e}, asin {err_asin:.1e}"),
                format!("{moved}"),
            )
        };
        eprintln!(
            "{label:<6} {threads:>7} {ms:>10.3} {:>12.1} {err:>22} {moved:>22}",
            pts.len() as f64 / ms / 1e3
        );
    }
}

fn bench_epipolar(c: &mut Criterion) {
    let sensor = LidarSensor::hdl64e();
    let rays = RayTable::new(&sensor).unwrap();
    // KITTI 000001's camera (P2, R0_rect, Tr_velo_to_cam), 1242 x 375
    let p2 = [
        [721.5377, 0.0, 609.5593, 44.85728],
        [0.0, 721.5377, 172.854, 0.2163791],
        [0.0, 0.0, 1.0, 0.002745884],
    ];
    let r0 = Mat3::from_cols_array_2d(&[
        [0.9999239, 0.00983776, -0.007445048],
        [-0.009869795, 0.9999421, -0.004278459],
        [0.007402527, 0.004351614, 0.9999631],
    ])
    .transpose();
    let tr = [
        [0.007533745, -0.9999714, -0.000616602, -0.004069766],
        [0.01480249, 0.0007280733, -0.9998902, -0.07631618],
        [0.9998621, 0.00752379, 0.01480755, -0.2717806],
    ];
    let cam = PinholeCamera::from_kitti(p2, r0, tr, 1242, 375).unwrap();
    let mut g = c.benchmark_group("epipolar_build");
    let mut rows = Vec::new();
    for k in [8usize, 32] {
        let cfg = EpipolarConfig {
            num_samples: k,
            near_m: 2.0,
            far_m: 80.0,
            spacing: DepthSpacing::Log,
            tau_m: 40.0,
        };
        g.bench_function(format!("K{k}"), |b| {
            b.iter(|| EpipolarTable::build(&rays, &cam, black_box(&cfg)).unwrap())
        });
        let t = EpipolarTable::build(&rays, &cam, &cfg).unwrap();
        let n = t.grid.len();
        // grid [f32; 2] + valid bool + weight f32 per sample, plus the copied unit rays (Vec3)
        let table_bytes = n * (8 + 1 + 4) + rays.dirs().len() * 12 + k * 4;
        let (fh, fw) = (375 / 4, 1242 / 4);
        g.bench_function(format!("K{k}_gather_{fh}x{fw}"), |b| {
            b.iter(|| t.bilinear_gather(black_box(fh), fw))
        });
        let gather = t.bilinear_gather(fh, fw);
        let gather_bytes = gather.indices.len() * 16 + gather.weights.len() * 16;
        let build_ms = median_ms(5, || {
            black_box(EpipolarTable::build(&rays, &cam, &cfg).unwrap());
        });
        let gather_ms = median_ms(5, || {
            black_box(t.bilinear_gather(fh, fw));
        });
        let valid = t.valid.iter().filter(|v| **v).count();
        rows.push((
            k,
            n,
            valid,
            build_ms,
            table_bytes,
            gather_ms,
            gather_bytes,
            (fh, fw),
        ));
    }
    g.finish();
    eprintln!("\nepipolar tables at 64x1024 (KITTI 000001 camera, 1242x375, depths 2..80 m log)");
    eprintln!(
        "{:>3} {:>10} {:>10} {:>10} {:>12} {:>22} {:>12}",
        "K", "samples", "valid", "build ms", "table MiB", "gather ms (feat map)", "gather MiB"
    );
    for (k, n, valid, ms, tb, gms, gb, (fh, fw)) in rows {
        eprintln!(
            "{k:>3} {n:>10} {valid:>10} {ms:>10.1} {:>12.1} {:>22} {:>12.1}",
            tb as f64 / (1 << 20) as f64,
            format!("{gms:.1} ({fh}x{fw})"),
            gb as f64 / (1 << 20) as f64
        );
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .sample_size(10)
        .measurement_time(Duration::from_secs(2))
        .warm_up_time(Duration::from_millis(300));
    targets = bench_project, bench_epipolar
}
criterion_main!(benches);
