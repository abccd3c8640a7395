//! IO benchmarks: read + project + write one training shard (scans per second, peak memory), and PNG
//! preview rendering. Uses the real KITTI scans in `../shared/data/real` when present (cycled to fill a
//! shard), synthetic scans of the same size otherwise.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput};
use veila_data::convert::{ConvertOptions, convert, frame_to_sample};
use veila_data::dataset::Dataset;
use veila_data::image::RgbImage;
use veila_data::image_io::encode_png;
use veila_data::kitti::KittiObjectDataset;
use veila_data::shard::write_shard;
use veila_data::vis::render::{
    BevOptions, OverlayOptions, RangePreview, render_bev, render_overlay, render_range,
};
use veila_geom::{LidarSensor, ProjectionOptions, Projector};

const FRAMES_PER_SHARD: usize = 8;

fn real_kitti() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/kitti/training");
    p.join("velodyne/000000.bin").is_file().then_some(p)
}

/// A KITTI tree of `n` frames in `dir`: symlinks to the real files (cycled), or synthetic scans of
/// 120k points with a 1242x375 image.
fn make_tree(dir: &Path, n: usize) {
    for d in ["velodyne", "image_2", "calib"] {
        std::fs::create_dir_all(dir.join(d)).unwrap();
    }
    let real = real_kitti();
    for i in 0..n {
        let id = format!("{i:06}");
        if let Some(r) = &real {
            let src = format!("{:06}", i % 2);
            for (d, ext) in [("velodyne", "bin"), ("image_2", "png"), ("calib", "txt")] {
                std::os::unix::fs::symlink(
                    r.join(format!("{d}/{src}.{ext}")),
                    dir.join(format!("{d}/{id}.{ext}")),
                )
                .unwrap();
            }
        } else {
            let bytes: Vec<u8> = (0..120_000)
                .flat_map(|k| {
                    let a = k as f32 * 0.0137;
                    let el = -0.4 + (k % 64) as f32 * 0.007;
                    let r = 5.0 + (k % 97) as f32 * 0.5;
                    [
                        r * a.cos() * el.cos(),
                        r * a.sin() * el.cos(),
                        r * el.sin(),
                        0.5,
                    ]
                })
                .flat_map(|v| v.to_le_bytes())
                .collect();
            std::fs::write(dir.join(format!("velodyne/{id}.bin")), bytes).unwrap();
            RgbImage::from_pixel(1242, 375, veila_data::image::Rgb([90, 90, 90]))
                .save(dir.join(format!("image_2/{id}.png")))
                .unwrap();
            std::fs::write(
                dir.join(format!("calib/{id}.txt")),
                "P0: 721 0 609 0 0 721 172 0 0 0 1 0\nP1: 721 0 609 0 0 721 172 0 0 0 1 0\nP2: 721 0 609 44 0 721 172 0.2 0 0 1 0.003\nP3: 721 0 609 0 0 721 172 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27\n",
            )
            .unwrap();
        }
    }
}

/// Peak resident set size (VmHWM) in MiB, after optionally resetting it (Linux `clear_refs` = 5).
fn peak_rss_mib(reset: bool) -> Option<f64> {
    if reset {
        std::fs::write("/proc/self/clear_refs", "5").ok()?;
    }
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

pub fn bench_shard(c: &mut Criterion) {
    let tmp = tempfile::tempdir().unwrap();
    let tree = tmp.path().join("kitti");
    make_tree(&tree, 64);
    let ds = KittiObjectDataset::open(&tree).unwrap();
    let sensor = LidarSensor::hdl64e();
    let projector = Projector::new(&sensor, ProjectionOptions::default()).unwrap();
    let source = if real_kitti().is_some() {
        "real KITTI scans"
    } else {
        "synthetic 120k-point scans"
    };

    // peak memory of whole conversions: 64 frames in shards of 4 / 16 / 64 frames (one worker,
    // both cores). Memory follows the shard size, not the dataset size.
    eprintln!(
        "\nveila-data shard conversion, {source}, 64 frames, hdl64e 64x1024, images included"
    );
    eprintln!(
        "{:>16} {:>12} {:>14} {:>16}",
        "frames/shard", "time s", "scans/s", "peak RSS MiB"
    );
    for fps in [4usize, 16, 64] {
        let out = tmp.path().join(format!("out{fps}"));
        let mut opts = ConvertOptions::new(&out, sensor.clone());
        opts.frames_per_shard = fps;
        let base = peak_rss_mib(true);
        let t0 = Instant::now();
        let s = convert(&ds, None, &opts, &|_| {}).unwrap();
        let dt = t0.elapsed().as_secs_f64();
        let peak = peak_rss_mib(false);
        assert_eq!(s.frames, 64);
        let fmt = |v: Option<f64>| v.map_or("n/a".to_string(), |v| format!("{v:.0}"));
        eprintln!(
            "{fps:>16} {dt:>12.2} {:>14.1} {:>16} (before: {})",
            64.0 / dt,
            fmt(peak),
            fmt(base)
        );
        std::fs::remove_dir_all(&out).unwrap();
    }

    let mut g = c.benchmark_group("veila_data_shard");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(6))
        .warm_up_time(Duration::from_secs(1));
    g.throughput(Throughput::Elements(FRAMES_PER_SHARD as u64));
    let out = tmp.path().join("bench.safetensors");
    g.bench_function("read_project_write_8_scans_serial", |b| {
        b.iter(|| {
            let samples: Vec<_> = (0..FRAMES_PER_SHARD)
                .map(|i| {
                    frame_to_sample(&ds.load(i).unwrap(), &projector, 1.0, None, true)
                        .unwrap()
                        .0
                })
                .collect();
            write_shard(&out, &sensor, "kitti", &samples).unwrap()
        })
    });
    g.finish();
}

pub fn bench_previews(c: &mut Criterion) {
    let tmp = tempfile::tempdir().unwrap();
    let tree = tmp.path().join("kitti");
    make_tree(&tree, 1);
    let ds = KittiObjectDataset::open(&tree).unwrap();
    let frame = ds.load(0).unwrap();
    let sensor = LidarSensor::hdl64e();
    let projector = Projector::new(&sensor, ProjectionOptions::default()).unwrap();
    let (img, _) = projector
        .project(&frame.points.xyz, Some(&frame.points.intensity), None)
        .unwrap();
    let camera = frame.camera.unwrap();
    let image = frame.image.unwrap();

    let mut g = c.benchmark_group("veila_data_preview");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_millis(500));
    g.bench_function("range_64x1024_render_png", |b| {
        b.iter(|| encode_png(&render_range(&img, &RangePreview::default())).unwrap())
    });
    g.bench_function("bev_1000x1000_render_png", |b| {
        b.iter(|| encode_png(&render_bev(&frame.points, &BevOptions::default()).unwrap()).unwrap())
    });
    g.bench_function("overlay_image_2_render_png", |b| {
        b.iter(|| {
            encode_png(
                &render_overlay(
                    &image,
                    &camera,
                    &frame.points.xyz,
                    &OverlayOptions::default(),
                )
                .unwrap()
                .image,
            )
            .unwrap()
        })
    });
    g.finish();
}
