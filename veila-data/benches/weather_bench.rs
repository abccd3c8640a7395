//! Weather benchmarks: each effect's cost per ~120k-point scan (the real KITTI 000001 scan when present,
//! else a synthetic one), the fog table's resolution against its largest error versus direct
//! integration, snow particle density against time, and the camera effects at 1242x375.
//!
//! Accuracy tables are printed to stderr next to the times.

use std::path::Path;
use std::time::{Duration, Instant};

use criterion::{BenchmarkId, Criterion, Throughput};
use glam::Vec3;
use image::RgbImage;
use veila_data::PointCloud;
use veila_data::weather::fog::{FogTable, FogTableConfig, PulseModel, backscatter_peak_direct};
use veila_data::weather::{
    BeamTable, CameraInput, DepthMap, Intrinsics, LidarInput, Preset, TimeOfDay, Weather,
    WeatherConfig, WeatherSim,
};

fn scan() -> (PointCloud, &'static str) {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real/kitti/training/velodyne/000001.bin");
    if let Ok(l) = veila_data::scan::read_points(&p) {
        return (l.cloud, "KITTI 000001 (120,268 points)");
    }
    // synthetic: 64 rings x 1875 columns, ground and a wall
    let beams = BeamTable::hdl64e();
    let mut c = PointCloud::default();
    for el in &beams.elevations_rad {
        for k in 0..1875 {
            let az = k as f32 / 1875.0 * std::f32::consts::TAU;
            let d = Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
            let t = if d.z < -0.02 {
                (1.73 / -d.z).min(60.0)
            } else {
                40.0
            };
            c.xyz.push(d * t);
            c.intensity.push(0.05 + 0.4 * ((k * 7) % 10) as f32 / 10.0);
        }
    }
    (c, "synthetic (120,000 points)")
}

fn quick(c: &mut Criterion) -> criterion::BenchmarkGroup<'_, criterion::measurement::WallTime> {
    let mut g = c.benchmark_group("weather");
    g.sample_size(10)
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(2));
    g
}

/// Each LiDAR effect on its own (plus the full KITTI-Weather presets).
pub fn bench_lidar_effects(c: &mut Criterion) {
    let (cloud, what) = scan();
    eprintln!("weather LiDAR effects on {what}");
    let beams = BeamTable::hdl64e();
    let cases: Vec<(&str, Weather)> = vec![
        ("fog_mor50", Preset::FogHeavy.weather()),
        (
            "rain10_no_wet",
            Weather {
                rain_rate_mm_h: 10.0,
                ..Weather::clear()
            },
        ),
        (
            "wet_ground_1mm",
            Weather {
                water_depth_mm: 1.0,
                ..Weather::clear()
            },
        ),
        ("snow_moderate", Preset::SnowModerate.weather()),
        ("snow_heavy", Preset::SnowHeavy.weather()),
        ("clear_identity", Weather::clear()),
    ];
    let mut g = quick(c);
    g.throughput(Throughput::Elements(cloud.len() as u64));
    for (name, w) in cases {
        let sim = WeatherSim::new(&w.with_seed(1), &WeatherConfig::default()).expect("weather");
        let input = LidarInput {
            cloud: &cloud,
            ground_mask: None,
            beams: Some(&beams),
        };
        let out = sim.apply_lidar(input).expect("apply");
        eprintln!(
            "  {name:<16} records {}",
            serde_json::to_string(
                &out.records
                    .iter()
                    .map(|r| (&r.effect, &r.counts))
                    .collect::<Vec<_>>()
            )
            .unwrap_or_default()
        );
        g.bench_function(BenchmarkId::new("lidar", name), |b| {
            b.iter(|| sim.apply_lidar(input).expect("apply"))
        });
    }
    // start-up cost of fog (table build) apart
    g.bench_function("fog_table_build_default", |b| {
        b.iter(|| FogTable::new(0.06, &FogTableConfig::default()).expect("table"))
    });
    g.finish();
}

/// Fog table resolution: build time and largest error against direct integration.
pub fn bench_fog_table(c: &mut Criterion) {
    let alpha = 0.06;
    let pulse = PulseModel::default();
    // reference: direct Simpson quadrature, receiver-range step 1 mm, at R0 in [0.95, 6] m
    let r0s: Vec<f64> = (0..=50).map(|k| 0.95 + k as f64 * 0.101).collect();
    let t0 = Instant::now();
    let reference: Vec<(f64, f64)> = r0s
        .iter()
        .map(|&r0| backscatter_peak_direct(alpha, r0, &pulse, 1e-3, 2000))
        .collect();
    let sat = reference.iter().map(|r| r.1).fold(0.0, f64::max);
    eprintln!(
        "fog table, alpha = {alpha}: reference by direct integration at {} ranges took {:.1} s",
        r0s.len(),
        t0.elapsed().as_secs_f64()
    );
    eprintln!("  r0_step_m  r_step_m  entries  build_ms  max|dI|/I_sat  max|dR_fog| m");
    let knobs = [
        (0.2, 0.05),
        (0.1, 0.02),
        (0.05, 0.01),
        (0.02, 0.01),
        (0.01, 0.005),
    ];
    let mut g = quick(c);
    for (r0_step, r_step) in knobs {
        let cfg = FogTableConfig {
            r0_step_m: r0_step,
            r_step_m: r_step,
            ..FogTableConfig::default()
        };
        let t = Instant::now();
        let table = FogTable::new(alpha, &cfg).expect("table");
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let (mut ei, mut er) = (0.0f64, 0.0f64);
        for (r0, (rr, ir)) in r0s.iter().zip(&reference) {
            let (rt, it) = table.lookup(*r0);
            ei = ei.max((it - ir).abs() / sat);
            if *ir > 0.0 {
                er = er.max((rt - rr).abs());
            }
        }
        eprintln!(
            "  {r0_step:>9} {r_step:>9} {:>8} {ms:>9.2} {ei:>14.2e} {er:>13.4}",
            table.len()
        );
        g.bench_function(
            BenchmarkId::new("fog_table_build", format!("r0_step_{r0_step}")),
            |b| b.iter(|| FogTable::new(alpha, &cfg).expect("table")),
        );
    }
    g.finish();
}

/// Snow: particle density against time per scan (field sampling included).
pub fn bench_snow_density(c: &mut Criterion) {
    let (cloud, what) = scan();
    let beams = BeamTable::hdl64e();
    eprintln!("snow (1.0 mm/h, 1.6 m/s) density scale vs time on {what}");
    eprintln!("  density  flakes(64 rings)  flake_returns  intensity_changed  ms/scan  field_ms");
    let mut g = quick(c);
    let w = Preset::SnowModerate.weather().with_seed(1);
    let scfg = veila_data::weather::snow::SnowConfig::default();
    g.bench_function("snow_field_sample_64_rings", |b| {
        b.iter(|| veila_data::weather::snow::SnowField::sample(&w, 64, &scfg).expect("field"))
    });
    for scale in [0.25, 0.5, 1.0, 2.0, 4.0] {
        let mut cfg = WeatherConfig::default();
        cfg.lidar.snow.density_scale = scale;
        let sim =
            WeatherSim::new(&Preset::SnowModerate.weather().with_seed(1), &cfg).expect("weather");
        let input = LidarInput {
            cloud: &cloud,
            ground_mask: None,
            beams: Some(&beams),
        };
        let t = Instant::now();
        let out = sim.apply_lidar(input).expect("apply");
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let scfg = veila_data::weather::snow::SnowConfig {
            density_scale: scale,
            ..Default::default()
        };
        let t = Instant::now();
        let field = veila_data::weather::snow::SnowField::sample(&w, 64, &scfg).expect("field");
        let field_ms = t.elapsed().as_secs_f64() * 1e3;
        drop(field);
        let r = out
            .records
            .iter()
            .find(|r| r.effect == "snow")
            .expect("snow record");
        eprintln!(
            "  {scale:>7} {:>17} {:>14} {:>18} {ms:>8.1} {field_ms:>9.1}",
            r.counts["flakes"], r.counts["flake_returns"], r.counts["intensity_changed"]
        );
        g.bench_function(BenchmarkId::new("snow_density", scale), |b| {
            b.iter(|| sim.apply_lidar(input).expect("apply"))
        });
    }
    g.finish();
}

/// Camera effects at 1242x375 (KITTI image and calibration when present, else synthetic).
pub fn bench_camera_effects(c: &mut Criterion) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/kitti/training");
    let (img, depth, k) = match (
        veila_data::image_io::read_rgb_image(&root.join("image_2/000001.png")),
        veila_data::scan::read_points(&root.join("velodyne/000001.bin")),
    ) {
        (Ok(img), Ok(scan)) => {
            let cam = veila_data::spec::read_calib_camera(
                &root.join("calib/000001.txt"),
                None,
                img.width(),
                img.height(),
            )
            .expect("calib")
            .camera;
            let depth = veila_data::weather::files::depth_from_scan(&scan.cloud, &cam);
            (img, depth, Intrinsics::from_camera(&cam))
        }
        _ => {
            let (w, h) = (1242u32, 375u32);
            let img = RgbImage::from_fn(w, h, |x, y| {
                image::Rgb([(x % 256) as u8, (y % 256) as u8, 120])
            });
            let z = (0..w * h)
                .map(|i| {
                    if i / w < 120 {
                        f32::INFINITY
                    } else {
                        400.0 / (1.0 + (i / w) as f32 - 120.0)
                    }
                })
                .collect();
            (
                img,
                DepthMap {
                    width: w,
                    height: h,
                    z_m: z,
                },
                Intrinsics {
                    fx: 721.5,
                    fy: 721.5,
                    cx: 609.6,
                    cy: 172.9,
                },
            )
        }
    };
    let mut g = quick(c);
    let input = CameraInput {
        image: &img,
        depth: Some(&depth),
        intrinsics: Some(k),
    };
    let mut lights = WeatherConfig::default();
    lights.camera.headlights = Some(Default::default());
    for (name, w, cfg) in [
        (
            "fog_veil",
            Preset::FogHeavy.weather(),
            WeatherConfig::default(),
        ),
        (
            "night",
            Preset::KittiNight.weather(),
            WeatherConfig::default(),
        ),
        (
            "night_headlights",
            Weather {
                time_of_day: TimeOfDay::Night,
                ..Weather::clear()
            },
            lights,
        ),
        (
            "rain10",
            Weather {
                rain_rate_mm_h: 10.0,
                ..Weather::clear()
            },
            WeatherConfig::default(),
        ),
        (
            "snow_moderate",
            Preset::SnowModerate.weather(),
            WeatherConfig::default(),
        ),
    ] {
        let sim = WeatherSim::new(&w, &cfg).expect("weather");
        g.bench_function(BenchmarkId::new("camera_1242x375", name), |b| {
            b.iter(|| sim.apply_camera(input).expect("apply"))
        });
    }
    g.finish();
}
