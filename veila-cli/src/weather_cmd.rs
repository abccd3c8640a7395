//! `veila weather`: physical weather on a real scan (and optionally its camera image).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

use crate::staging::{self, Inputs};
use clap::{Args, Subcommand};
use veila_data::weather::files::{FrameFiles, compute_frame, output_image_name, output_scan_name};
use veila_data::weather::{
    Headlights, Preset, Sensor, TimeOfDay, Weather, WeatherConfig, WeatherSim,
};

/// Weather commands.
#[derive(Debug, Subcommand)]
pub enum WeatherCmd {
    /// Apply physical weather (fog, rain, snow, wet road, night) to a LiDAR scan and optionally its
    /// camera image. Only the effects asked for run; with none, the outputs are byte-identical copies.
    /// Writes `OUT/<scan name>` (input format), `OUT/<image stem>.png` and `OUT/effects.json`.
    Weather(WeatherArgs),
}

/// Arguments of `veila weather`.
#[derive(Debug, Args)]
pub struct WeatherArgs {
    /// The scan: KITTI .bin, nuScenes .pcd.bin or PLY.
    pub scan: PathBuf,
    /// The camera image (PNG or JPEG) seen with the scan.
    #[arg(long)]
    pub image: Option<PathBuf>,
    /// Calibration (KITTI calib/NNNNNN.txt, odometry calib.txt or a nuScenes per-sample JSON;
    /// camera image_2 / CAM_FRONT): intrinsics and the depth map that camera fog, particles and
    /// headlights need.
    #[arg(long)]
    pub calib: Option<PathBuf>,
    /// SemanticKITTI .label file: the road mask for wet ground (else a plane fit).
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// Start from a preset (clear, fog-light|moderate|heavy, rain-*, snow-*, kitti-clean|night|fog|snow);
    /// the options below override its fields.
    #[arg(long, value_parser = parse_preset)]
    pub preset: Option<Preset>,
    /// Fog visibility (meteorological optical range), metres, 10 to 1000000.
    #[arg(long, value_name = "M", value_parser = crate::bounds::float(10.0, 1e6))]
    pub fog_visibility: Option<f64>,
    /// Rain rate, mm/h, 0 to 300.
    #[arg(long, value_name = "MM_H", value_parser = crate::bounds::float(0.0, 300.0))]
    pub rain_rate: Option<f64>,
    /// Snowfall rate, mm/h, 0 to 50.
    #[arg(long, value_name = "MM_H", value_parser = crate::bounds::float(0.0, 50.0))]
    pub snowfall_rate: Option<f64>,
    /// Snowflake terminal velocity, m/s, 0.05 to 20 (default 1.6).
    #[arg(long, value_name = "M_S", value_parser = crate::bounds::float(0.05, 20.0))]
    pub snow_terminal_velocity: Option<f64>,
    /// Water film depth on the road, mm, 0 to 20.
    #[arg(long, value_name = "MM", value_parser = crate::bounds::float(0.0, 20.0))]
    pub wet_ground_mm: Option<f64>,
    /// Time of day (camera only): day, dusk or night.
    #[arg(long, value_parser = parse_time)]
    pub time_of_day: Option<TimeOfDay>,
    /// Switch the ego vehicle's headlights on at dusk / night.
    #[arg(long)]
    pub headlights: bool,
    /// Seed of every random draw, 0 to 18446744073709551615.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output folder (created if missing; may hold other files).
    #[arg(long)]
    pub out: PathBuf,
    /// Replace output files that exist in the output folder.
    #[arg(long)]
    pub force: bool,
}

fn parse_preset(s: &str) -> Result<Preset, String> {
    s.parse().map_err(|e: veila_data::Error| e.to_string())
}

fn parse_time(s: &str) -> Result<TimeOfDay, String> {
    s.parse().map_err(|e: veila_data::Error| e.to_string())
}

/// Build the weather from the preset and the overrides.
pub fn weather_from_args(a: &WeatherArgs) -> Weather {
    let mut w = a.preset.map(Preset::weather).unwrap_or_default();
    if let Some(v) = a.fog_visibility {
        w.fog_visibility_m = Some(v);
    }
    if let Some(v) = a.rain_rate {
        w.rain_rate_mm_h = v;
    }
    if let Some(v) = a.snowfall_rate {
        w.snowfall_rate_mm_h = v;
    }
    if let Some(v) = a.snow_terminal_velocity {
        w.snow_terminal_velocity_m_s = v;
    }
    if let Some(v) = a.wet_ground_mm {
        w.water_depth_mm = v;
    }
    if let Some(t) = a.time_of_day {
        w.time_of_day = t;
    }
    w.seed = a.seed;
    w
}

/// Run a weather command.
pub fn run(cmd: WeatherCmd) -> Result<()> {
    match cmd {
        WeatherCmd::Weather(a) => run_weather(&a),
    }
}

fn run_weather(a: &WeatherArgs) -> Result<()> {
    let weather = weather_from_args(a);
    let mut cfg = WeatherConfig::default();
    if a.headlights {
        cfg.camera.headlights = Some(Headlights::default());
    }
    let sim = WeatherSim::new(&weather, &cfg).context("invalid weather")?;
    if a.image.is_none() && a.calib.is_some() {
        bail!("--calib is only used with --image");
    }
    // every output is checked before any work: none may be an input (whatever its spelling: `.`,
    // `./`, an absolute path, a link) and none is replaced without --force
    let mut inputs = Inputs::new();
    inputs
        .add(&a.scan)
        .add_opt(a.image.as_ref())
        .add_opt(a.calib.as_ref())
        .add_opt(a.labels.as_ref());
    let scan_out = a.out.join(output_scan_name(&a.scan)?);
    let image_out = a
        .image
        .as_deref()
        .map(output_image_name)
        .transpose()?
        .map(|n| a.out.join(n));
    let effects_out = a.out.join("effects.json");
    if a.out.exists() && !a.out.is_dir() {
        bail!("--out {}: exists and is not a directory", a.out.display());
    }
    let mut dests = vec![scan_out.as_path(), effects_out.as_path()];
    dests.extend(image_out.as_deref());
    staging::check_outputs(&dests, &inputs, a.force, true)?;
    let files = FrameFiles {
        scan: a.scan.clone(),
        image: a.image.clone(),
        calib: a.calib.clone(),
        labels: a.labels.clone(),
    };
    // all inputs read and every output computed before anything is created
    let frame = compute_frame(&sim, &files, &scan_out)?;
    let report = frame.report;
    let json = report.to_json()?;
    let mut outputs = vec![(scan_out, frame.scan)];
    if let (Some(p), Some(bytes)) = (image_out, frame.image) {
        outputs.push((p, bytes));
    }
    outputs.push((effects_out, json.into_bytes()));
    // scan, image and effects.json appear together or not at all
    staging::publish_files(&outputs, &inputs, a.force, true)?;
    let show = |s: Sensor| {
        let n = report.names(s);
        if n.is_empty() {
            "none (identity)".to_string()
        } else {
            n.join(", ")
        }
    };
    eprintln!(
        "alpha {:.3e} 1/m; lidar: {}; camera: {}",
        report.alpha_total_per_m,
        show(Sensor::Lidar),
        if a.image.is_some() {
            show(Sensor::Camera)
        } else {
            "no image".into()
        }
    );
    eprintln!("wrote {}", a.out.display());
    Ok(())
}
