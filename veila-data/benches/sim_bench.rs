//! Scene simulator benchmarks: LiDAR rays per second at 64x1024 and 64x2048, camera render time at
//! 1242x375 with its quality knobs (shadows, samples per pixel), and the per-frame BVH build.
//!
//! The camera knob table (printed to stderr) gives each setting's time next to its image difference
//! from the reference setting (4x4 samples with shadows): mean absolute difference in 8-bit levels
//! and PSNR.

use std::path::Path;
use std::time::{Duration, Instant};

use criterion::{BenchmarkId, Criterion, Throughput};
use veila_data::sim::{CameraRenderOptions, Scene, SceneConfig, SimCalib};
use veila_geom::LidarSensor;

fn scene() -> Scene {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/straight_road.toml");
    let cfg = SceneConfig::from_file(&path).expect("scenes/straight_road.toml");
    Scene::generate(&cfg, 0).expect("scene")
}

fn image_diff(a: &[u8], b: &[u8]) -> (f64, f64) {
    let n = a.len() as f64;
    let mad = a
        .iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs())
        .sum::<f64>()
        / n;
    let mse = a
        .iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum::<f64>()
        / n;
    let psnr = if mse > 0.0 {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    } else {
        f64::INFINITY
    };
    (mad, psnr)
}

/// LiDAR ray casting throughput (criterion reports rays per second).
pub fn bench_lidar(c: &mut Criterion) {
    let scene = scene();
    let snap = scene.snapshot(0);
    let model = scene.config().lidar.returns;
    let mut g = c.benchmark_group("sim_lidar");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(4))
        .warm_up_time(Duration::from_millis(500));
    for cols in [1024u32, 2048] {
        let sensor = LidarSensor {
            cols,
            ..LidarSensor::hdl64e()
        };
        g.throughput(Throughput::Elements(u64::from(64 * cols)));
        g.bench_with_input(
            BenchmarkId::new("rays", format!("64x{cols}")),
            &sensor,
            |b, s| b.iter(|| snap.render_lidar(s, &model).expect("scan")),
        );
    }
    g.finish();
    eprintln!(
        "sim: scene has {} triangles at frame 0",
        snap.accel.num_triangles()
    );
}

/// BVH build for one frame (static world + actors moved), the per-frame fixed cost.
pub fn bench_snapshot(c: &mut Criterion) {
    let scene = scene();
    let mut g = c.benchmark_group("sim_snapshot");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_millis(300));
    g.bench_function("bvh_build_frame", |b| b.iter(|| scene.snapshot(1)));
    g.finish();
}

/// Camera render time at 1242x375 for each knob setting, with the image difference to the reference.
pub fn bench_camera(c: &mut Criterion) {
    let scene = scene();
    let snap = scene.snapshot(0);
    let camera = SimCalib::from_config(&scene.config().camera)
        .camera()
        .expect("camera");
    let reference = snap
        .render_camera(
            &camera,
            &CameraRenderOptions {
                samples_per_axis: 4,
                shadows: true,
            },
        )
        .expect("render");
    let knobs = [(1u32, false), (1, true), (2, true), (3, true)];
    eprintln!("\nsim camera 1242x375, reference = 4x4 samples with shadows");
    eprintln!(
        "{:>8} {:>8} {:>12} {:>10} {:>10}",
        "samples", "shadows", "time_ms", "mad_8bit", "psnr_db"
    );
    for (n, shadows) in knobs {
        let opts = CameraRenderOptions {
            samples_per_axis: n,
            shadows,
        };
        let t = Instant::now();
        let img = snap.render_camera(&camera, &opts).expect("render");
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let (mad, psnr) = image_diff(&img.rgb, &reference.rgb);
        eprintln!(
            "{:>8} {:>8} {:>12.1} {:>10.3} {:>10.2}",
            format!("{n}x{n}"),
            shadows,
            ms,
            mad,
            psnr
        );
    }
    let mut g = c.benchmark_group("sim_camera_1242x375");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(5))
        .warm_up_time(Duration::from_millis(500));
    for (n, shadows) in [(1u32, false), (1, true), (2, true)] {
        let opts = CameraRenderOptions {
            samples_per_axis: n,
            shadows,
        };
        g.bench_with_input(
            BenchmarkId::new("render", format!("{n}x{n}_shadows_{shadows}")),
            &opts,
            |b, o| b.iter(|| snap.render_camera(&camera, o).expect("render")),
        );
    }
    g.finish();
}
