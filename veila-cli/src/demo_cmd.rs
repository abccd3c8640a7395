//! `veila demo`: the main job on the bundled default scene.
//!
//! It simulates a scene of the test split (camera image + LiDAR scan with ground-truth labels and depth),
//! projects the scan into a range image, runs the weather simulator on both sensors, and writes every
//! view and file to one output folder together with the metrics between the clear and the adverse-weather
//! scan. Everything runs from the binary alone: the default scene file is compiled in.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use serde::Serialize;
use veila_data::PointCloud;
use veila_data::image::{RgbImage, imageops};
use veila_data::render::{self, BevOptions, OverlayOptions, RangePreview};
use veila_data::sim::{Scene, SceneConfig, SimFrame};
use veila_data::weather::{
    CameraInput, DepthMap, Intrinsics, LidarInput, Preset, Weather, WeatherConfig, WeatherSim,
};
use veila_geom::{ProjectionOptions, Projector, RangeImage, Region};
use veila_metrics::bev::{BevConfig, bev_histogram};
use veila_metrics::crossmodal::{
    DepthAlignment, Map2d, ProjectionFilter, cm_depth_consistency, cm_semantic_consistency,
};
use veila_metrics::{MetricReport, MetricValue, Protocol, chamfer, dist};

use crate::{progress, staging};

/// The default scene: the first scene of the test split (`scenes/test.txt`), compiled in.
const DEFAULT_SCENE_TOML: &str = include_str!("../../scenes/straight_road.toml");
/// The first seed of that scene's test range.
const DEFAULT_SEED: u64 = 100_000;

/// Arguments of `veila demo`.
#[derive(Debug, Args)]
pub(crate) struct DemoArgs {
    /// Output folder (created; replaced files only with --force).
    #[arg(long, value_name = "DIR", default_value = "out/demo")]
    out: PathBuf,
    /// Scene file (default: the bundled straight road of the test split).
    #[arg(long, value_name = "SCENE.toml")]
    scene: Option<PathBuf>,
    /// Scene seed.
    #[arg(long, value_name = "S", default_value_t = DEFAULT_SEED)]
    seed: u64,
    /// Weather preset applied to both sensors (clear, fog-light, fog-moderate, fog-heavy, rain-*,
    /// snow-*, kitti-night, kitti-fog, kitti-snow, ...).
    #[arg(long, value_name = "PRESET", default_value = "kitti-fog")]
    weather: String,
    /// Write into an existing, non-empty output folder. Not needed to refresh a folder that holds
    /// only an earlier demo's output: that is replaced.
    #[arg(long)]
    force: bool,
}

#[derive(Debug, Serialize)]
struct DemoSummary<'a> {
    scene: &'a str,
    seed: u64,
    weather: &'a str,
    points_clear: usize,
    points_weather: usize,
    range_pixels_clear: usize,
    range_pixels_weather: usize,
    lidar_effects: Vec<String>,
    camera_effects: Vec<String>,
    metrics: &'a [MetricValue],
}

pub(crate) fn run(args: DemoArgs) -> Result<()> {
    let (config, scene_name) = match &args.scene {
        Some(path) => (SceneConfig::from_file(path)?, path.display().to_string()),
        None => (
            SceneConfig::from_toml_str(DEFAULT_SCENE_TOML, Path::new("scenes/straight_road.toml"))?,
            "scenes/straight_road.toml (bundled)".to_string(),
        ),
    };
    let preset: Preset = args
        .weather
        .parse()
        .map_err(|e| anyhow::anyhow!("--weather {}: {e}", args.weather))?;
    let weather = Weather::preset(preset).with_seed(args.seed);
    let staging = staging::stage(&args.out, args.force || is_earlier_demo_output(&args.out))?;
    let out = staging.path().to_path_buf();
    for sub in ["clear", "weather"] {
        std::fs::create_dir_all(out.join(sub))
            .with_context(|| format!("{}: cannot create", out.display()))?;
    }

    let pb = progress::bar(6, "demo");
    pb.set_message("simulating the scene");
    let scene = Scene::generate(&config, args.seed)?;
    let frame = scene.render_frame(0)?;
    pb.inc(1);

    pb.set_message("projecting and rendering the clear scan");
    let projector = Projector::new(&frame.sensor, ProjectionOptions::default())?;
    let clear_rgb = frame.image.to_rgb_image()?;
    let clear = &frame.scan.points;
    let clear_range = project(&projector, clear)?;
    write_views(&out.join("clear"), &frame, &clear_rgb, clear, &clear_range)?;
    pb.inc(1);

    pb.set_message(format!("weather: {}", args.weather));
    let sim = WeatherSim::new(&weather, &WeatherConfig::default())?;
    let lidar_out = sim.apply_lidar(LidarInput::new(clear))?;
    let depth = depth_map(&frame);
    let cam_out = sim.apply_camera(CameraInput {
        image: &clear_rgb,
        depth: Some(&depth),
        intrinsics: Some(Intrinsics::from_camera(&frame.camera)),
    })?;
    let report = sim.report(lidar_out.records.clone(), cam_out.records.clone());
    let weather_range = project(&projector, &lidar_out.cloud)?;
    write_views(
        &out.join("weather"),
        &frame,
        &cam_out.image,
        &lidar_out.cloud,
        &weather_range,
    )?;
    veila_data::atomic::write_atomic(
        &out.join("weather").join("effects.json"),
        report.to_json()?.as_bytes(),
    )?;
    pb.inc(1);

    pb.set_message("side-by-side views");
    let preview = RangePreview::default();
    let stacked = stack_vertical(&[
        render::render_range(&clear_range, &preview),
        render::render_range(&weather_range, &preview),
    ]);
    veila_data::image_io::write_png(&out.join("range_clear_vs_weather.png"), &stacked)?;
    let bev = BevOptions::default();
    let side = stack_horizontal(&[
        render::render_bev(clear, &bev)?,
        render::render_bev(&lidar_out.cloud, &bev)?,
    ]);
    veila_data::image_io::write_png(&out.join("bev_clear_vs_weather.png"), &side)?;
    let cams = stack_vertical(&[clear_rgb.clone(), cam_out.image.clone()]);
    veila_data::image_io::write_png(&out.join("camera_clear_vs_weather.png"), &cams)?;
    pb.inc(1);

    pb.set_message("metrics");
    let metrics = demo_metrics(&frame, clear, &lidar_out.cloud)?;
    pb.inc(1);

    let summary = DemoSummary {
        scene: &scene_name,
        seed: args.seed,
        weather: &args.weather,
        points_clear: clear.len(),
        points_weather: lidar_out.cloud.len(),
        range_pixels_clear: clear_range.num_valid(),
        range_pixels_weather: weather_range.num_valid(),
        lidar_effects: report.lidar.iter().map(|r| r.effect.to_string()).collect(),
        camera_effects: report.camera.iter().map(|r| r.effect.to_string()).collect(),
        metrics: &metrics.metrics,
    };
    veila_data::atomic::write_atomic(
        &out.join("metrics.json"),
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )?;
    pb.inc(1);
    pb.finish_and_clear();

    // files first, then the report: a reader that goes away early (`| head`) cannot cost the output
    staging.commit()?;
    println!(
        "scene {scene_name}, seed {}: {} LiDAR points ({} range pixels); weather '{}' ran [{}] on the LiDAR and [{}] on the camera: {} points left",
        args.seed,
        summary.points_clear,
        summary.range_pixels_clear,
        args.weather,
        summary.lidar_effects.join(", "),
        summary.camera_effects.join(", "),
        summary.points_weather
    );
    print_table(&metrics.metrics);
    println!("wrote {}", args.out.display());
    Ok(())
}

/// Whether `dir` holds nothing but the files an earlier `veila demo` wrote (so running the README's
/// command twice refreshes its output instead of failing, and nothing else can be overwritten).
fn is_earlier_demo_output(dir: &Path) -> bool {
    const DEMO_FILES: &[&str] = &[
        "metrics.json",
        "clear",
        "weather",
        "range_clear_vs_weather.png",
        "bev_clear_vs_weather.png",
        "camera_clear_vs_weather.png",
    ];
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    let names: Vec<String> = entries
        .filter_map(|e| e.ok().map(|e| e.file_name().to_string_lossy().into_owned()))
        .collect();
    names.iter().any(|n| n == "metrics.json")
        && names.iter().all(|n| DEMO_FILES.contains(&n.as_str()))
}

fn project(projector: &Projector, cloud: &PointCloud) -> Result<RangeImage> {
    let (mut image, _) = projector.project(&cloud.xyz, Some(&cloud.intensity), None)?;
    if let Some(labels) = &cloud.label {
        image.gather_labels(labels)?;
    }
    Ok(image)
}

/// The simulator's camera depth (0 = sky) as the weather simulator's depth map (+inf = sky).
fn depth_map(frame: &SimFrame) -> DepthMap {
    DepthMap {
        width: frame.image.width,
        height: frame.image.height,
        z_m: frame
            .image
            .depth_m
            .iter()
            .map(|z| if *z > 0.0 { *z } else { f32::INFINITY })
            .collect(),
    }
}

/// Camera image, range preview, BEV, overlay, and the scan as EXR, PLY and KITTI `.bin`.
fn write_views(
    dir: &Path,
    frame: &SimFrame,
    rgb: &RgbImage,
    cloud: &PointCloud,
    range: &RangeImage,
) -> Result<()> {
    use veila_data::{image_io::write_png, range_exr::write_range_exr, scan::write_points};
    write_png(&dir.join("camera.png"), rgb)?;
    write_png(
        &dir.join("range.png"),
        &render::render_range(range, &RangePreview::default()),
    )?;
    write_png(
        &dir.join("bev.png"),
        &render::render_bev(cloud, &BevOptions::default())?,
    )?;
    let overlay =
        render::render_overlay(rgb, &frame.camera, &cloud.xyz, &OverlayOptions::default())?;
    write_png(&dir.join("overlay.png"), &overlay.image)?;
    write_range_exr(&dir.join("range.exr"), &frame.sensor, range)?;
    write_points(&dir.join("points.ply"), cloud)?;
    write_points(&dir.join("points.bin"), cloud)?;
    Ok(())
}

fn stack_vertical(images: &[RgbImage]) -> RgbImage {
    let w = images.iter().map(|i| i.width()).max().unwrap_or(0);
    let h = images.iter().map(|i| i.height()).sum();
    let mut out = RgbImage::new(w, h);
    let mut y = 0;
    for img in images {
        imageops::replace(&mut out, img, 0, i64::from(y));
        y += img.height();
    }
    out
}

fn stack_horizontal(images: &[RgbImage]) -> RgbImage {
    let w = images.iter().map(|i| i.width()).sum();
    let h = images.iter().map(|i| i.height()).max().unwrap_or(0);
    let mut out = RgbImage::new(w, h);
    let mut x = 0;
    for img in images {
        imageops::replace(&mut out, img, i64::from(x), 0);
        x += img.width();
    }
    out
}

/// Clear scan as reference, adverse-weather scan as "generated": BEV JSD / MMD (R2DM), Chamfer per
/// region; and the cross-modal consistency of both scans with the simulator's ground-truth depth and
/// semantic maps.
fn demo_metrics(
    frame: &SimFrame,
    clear: &PointCloud,
    weather: &PointCloud,
) -> Result<MetricReport> {
    let mut metrics = Vec::new();
    let cfg = BevConfig::r2dm();
    for region in Region::ALL {
        let hc = bev_histogram(&clear.xyz, &cfg, region, "clear scan")?;
        let hw = bev_histogram(&weather.xyz, &cfg, region, "weather scan")?;
        let value = |name: &str, protocol: Protocol, value: f64| MetricValue {
            name: name.to_string(),
            protocol,
            region,
            value,
            generated: 1,
            reference: 1,
            paper_scale: None,
        };
        metrics.push(value(
            "jsd",
            Protocol::R2dm,
            dist::jsd(std::slice::from_ref(&hw), std::slice::from_ref(&hc))?,
        ));
        let mmd = dist::mmd_r2dm_dense(&[hw], &[hc], 0.5)?;
        metrics.push(MetricValue {
            paper_scale: Some(1e4),
            ..value("mmd", Protocol::R2dm, mmd)
        });
        let a = veila_metrics::filter_region(&weather.xyz, region);
        let b = veila_metrics::filter_region(&clear.xyz, region);
        if !a.is_empty() && !b.is_empty() {
            metrics.push(value(
                "chamfer",
                Protocol::Pytorch3d,
                chamfer::chamfer_distance(&a, &b)?.value(),
            ));
        }
    }
    let img = &frame.image;
    let depth = Map2d::new(img.width, img.height, &img.depth_m)?;
    let semantic = Map2d::new(img.width, img.height, &img.semantic)?;
    let filter = ProjectionFilter::default();
    for (which, cloud) in [("clear", clear), ("weather", weather)] {
        let dc = cm_depth_consistency(
            &cloud.xyz,
            &frame.camera,
            &depth,
            DepthAlignment::None,
            &filter,
        )?;
        metrics.push(MetricValue {
            name: format!("cm-dc ({which} scan vs true depth)"),
            protocol: Protocol::Veila,
            region: Region::Front,
            value: dc.abs_rel,
            generated: 1,
            reference: 1,
            paper_scale: None,
        });
        let labels: Vec<u32> = cloud
            .label
            .as_ref()
            .map_or_else(Vec::new, |l| l.iter().map(|v| v & 0xFFFF).collect());
        if labels.len() == cloud.len() {
            let sc =
                cm_semantic_consistency(&cloud.xyz, &labels, &frame.camera, &semantic, &filter)?;
            metrics.push(MetricValue {
                name: format!("cm-sc ({which} scan vs true semantics)"),
                protocol: Protocol::Veila,
                region: Region::Front,
                value: sc.percent,
                generated: 1,
                reference: 1,
                paper_scale: None,
            });
        }
    }
    Ok(MetricReport { metrics })
}

fn print_table(metrics: &[MetricValue]) {
    println!(
        "{:<38} {:<10} {:<6} {:>14}",
        "metric", "protocol", "region", "value"
    );
    for m in metrics {
        println!(
            "{:<38} {:<10} {:<6} {:>14.6}",
            m.name,
            m.protocol.name(),
            m.region.name(),
            m.value
        );
    }
}
