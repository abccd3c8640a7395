//! Snowflake returns of veila's LiDAR snowfall on a real KITTI scan, per modelling switch, over seeds:
//! the veila side of `veila-data/tests/data/snow_reference/` (issue 20). Run by hand:
//! `cargo run --release -p veila-data --features weather --example snow_vs_reference -- [SCAN] [SEEDS]`
//! (default: KITTI object 000000 from ../shared/data/real, seeds 0..5). Prints one JSON line per
//! (snowfall rate, variant) with the mean and sample standard deviation of flake returns.

use std::path::PathBuf;
use std::time::Instant;

use veila_data::weather::{BeamTable, LidarInput, PointOrigin, Weather, WeatherConfig, WeatherSim};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real");
    let scan = std::env::args()
        .nth(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join("kitti/training/velodyne/000000.bin"));
    let seeds: u64 = std::env::args()
        .nth(2)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(5);
    let cloud = veila_data::scan::read_points(&scan)?.cloud;
    let beams = BeamTable::hdl64e();
    let input = LidarInput {
        cloud: &cloud,
        ground_mask: None,
        beams: Some(&beams),
    };
    // (name, snow extinction on LiDAR returns, reference's never-reset power constant)
    let variants = [
        ("veila", false, false),
        ("lidar_extinction", true, false),
        ("reference_power_quirk", false, true),
        ("lidar_extinction+reference_power_quirk", true, true),
    ];
    for rate in [1.0, 2.5] {
        for (name, ext, quirk) in variants {
            let mut cfg = WeatherConfig::default();
            cfg.lidar.snow.lidar_extinction = ext;
            cfg.lidar.snow.reference_power_quirk = quirk;
            let weather = Weather {
                snowfall_rate_mm_h: rate,
                snow_terminal_velocity_m_s: 1.6,
                ..Weather::clear()
            };
            let sim = WeatherSim::new(&weather, &cfg)?;
            let t = Instant::now();
            let mut counts = Vec::new();
            let mut changed = Vec::new();
            for seed in 0..seeds {
                let out = sim.with_seed(seed).apply_lidar(input)?;
                counts.push(
                    out.origin
                        .iter()
                        .filter(|o| **o == PointOrigin::Snow)
                        .count() as f64,
                );
                let rec = out.records.iter().find(|r| r.effect == "snow");
                changed.push(rec.map_or(0, |r| r.counts["intensity_changed"]) as f64);
            }
            let n = counts.len() as f64;
            let mean = counts.iter().sum::<f64>() / n;
            let sd = (counts.iter().map(|c| (c - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0))
                .sqrt();
            let changed_mean = changed.iter().sum::<f64>() / n;
            println!(
                "{{\"snowfall_mm_h\": {rate}, \"variant\": \"{name}\", \"seeds\": {seeds}, \
                 \"flake_returns_mean\": {mean:.1}, \"flake_returns_sd\": {sd:.1}, \
                 \"intensity_changed_mean\": {changed_mean:.1}, \"lidar_alpha_per_m\": {:.3e}, \
                 \"ms_per_scan\": {:.0}}}",
                sim.lidar_alpha_per_m(),
                t.elapsed().as_secs_f64() * 1e3 / n
            );
        }
    }
    Ok(())
}
