//! `veila demo`: the main job on the bundled default model.
//!
//! It simulates a scene of the test split (camera image + LiDAR scan with ground-truth depth and
//! semantics), generates the panoramic scan from the camera image alone with the bundled model
//! (`models/default`, or `--model`), and writes to one folder the input image, the generated and
//! the true range images and BEV views side by side, the generated points drawn on the image, PLY /
//! EXR / KITTI `.bin` files, and the metrics of this scene (JSON and a printed table). `--weather`
//! degrades the input image with a weather preset (camera effects only: the true scan stays the
//! reference), to see how generation holds up under adverse conditions.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use serde::Serialize;
use veila_data::PointCloud;
use veila_data::image::RgbImage;
use veila_data::sim::{Scene, SceneConfig, SimFrame};
use veila_data::vis::render::{self, BevOptions, OverlayOptions, RangePreview};
use veila_data::weather::{
    CameraInput, DepthMap, Intrinsics, Preset, Weather, WeatherConfig, WeatherSim,
};
use veila_diffusion::SamplerConfig;
use veila_diffusion::app::{GenerateOptions, RigImage, SamplerChoice, ScanPipeline};
use veila_geom::{ProjectionOptions, Projector, RangeImage, Region};
use veila_metrics::bev::{BevConfig, bev_histogram};
use veila_metrics::crossmodal::{DepthAlignment, Map2d, ProjectionFilter, cm_depth_consistency};
use veila_metrics::texture::TextureSummary;
use veila_metrics::{MetricReport, MetricValue, Protocol, chamfer, dist};

use crate::{generation, model, progress, staging};

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
    /// Scene seed, 0 to 18446744073709551615.
    #[arg(long, value_name = "S", default_value_t = DEFAULT_SEED)]
    seed: u64,
    /// Model bundle folder (default: $VEILA_MODEL, else the bundled models/default;
    /// `--checkpoint` is an alias).
    #[arg(long, value_name = "DIR", env = "VEILA_MODEL", alias = "checkpoint")]
    model: Option<PathBuf>,
    // the help names the bundled model's sampler as its bundle.json does
    #[arg(long, value_parser = generation::sampler_parser(), help = generation::sampler_help())]
    sampler: Option<veila_diffusion::SamplerName>,
    /// Where the sampler's steps lie on the noise schedule (default: the bundle's).
    #[arg(long, value_parser = crate::generation::spacing_parser())]
    spacing: Option<veila_diffusion::Spacing>,
    /// Sampler steps, 1 to 1000 (default: the bundle's).
    #[arg(long, value_name = "N", value_parser = crate::bounds::steps())]
    steps: Option<usize>,
    /// Classifier-free guidance scale, 0 to 20 (default: the bundle's).
    #[arg(long, value_name = "S", allow_negative_numbers = true, value_parser = crate::bounds::guidance())]
    guidance: Option<f64>,
    /// Bundles with a prior mean network: the level the draw starts from, 0.001 to 1, from the
    /// mean network's scan with that much noise (1 = pure noise; default: the bundle's).
    /// Lower follows the image more closely and takes fewer steps; higher keeps more texture.
    #[arg(long, value_name = "T", value_parser = crate::bounds::start_level())]
    start_t: Option<f64>,
    /// Residual-diffusion bundles: how much of the sampled residual goes on top of the mean
    /// network's scan, 0 to 1. 1 is a full sample (the data's texture); 0 is the smooth
    /// conditional mean, the smallest pixel error.
    #[arg(
        long,
        value_name = "W",
        default_value_t = 1.0,
        allow_negative_numbers = true,
        value_parser = crate::bounds::unit()
    )]
    residual_weight: f64,
    /// Seed of the generation noise, 0 to 18446744073709551615.
    #[arg(long, value_name = "S", default_value_t = 0)]
    sample_seed: u64,
    /// Weather preset applied to the input camera image only (clear, kitti-night, kitti-fog,
    /// fog-moderate, rain-heavy, snow-light, ...). `clear` leaves the image untouched.
    #[arg(long, value_name = "PRESET", default_value = "clear", value_parser = weather_preset)]
    weather: String,
    /// Training frames of the same scene file behind the zero-skill baselines printed next to the
    /// model (their per-pixel median scan, and the one whose image is nearest to the input in the
    /// frozen encoders' feature space), 0 to 200; 0 leaves the baselines out.
    #[arg(long, value_name = "N", default_value_t = 24, value_parser = crate::bounds::int::<usize>(0, 200))]
    baseline_frames: usize,
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
    camera_effects: Vec<String>,
    model: String,
    sampler: &'a veila_diffusion::SamplerConfig,
    sample_seed: u64,
    grid: [usize; 2],
    points_true: usize,
    points_generated: usize,
    range_pixels_true: usize,
    range_pixels_generated: usize,
    metrics: &'a [MetricValue],
    /// Ring spread (median IQR of range in 0.5° bands below −15°, m) of each scan.
    ring_spread_m: BTreeMap<&'static str, Option<f64>>,
    /// Texture figures of each scan against the true scan (`veila_metrics::texture`): depth
    /// edges in the upper half, smooth ground in the lower half, the step distribution's distance.
    texture: BTreeMap<&'static str, TextureSummary>,
    /// The zero-skill baselines' metrics against the same true scan.
    baselines: Vec<BaselineSummary>,
}

#[derive(Debug, Serialize)]
struct BaselineSummary {
    name: &'static str,
    description: String,
    metrics: Vec<MetricValue>,
}

/// `--weather`: a preset name, checked by the parser (kept as given, for the summary).
fn weather_preset(s: &str) -> std::result::Result<String, String> {
    s.parse::<Preset>()
        .map(|_| s.to_string())
        .map_err(|e| e.to_string())
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
    let device = model::device()?;
    let bundle = model::load_bundle(args.model.as_deref(), &device)?;
    let sampler = generation::resolve_sampler(
        &bundle,
        SamplerChoice {
            name: args.sampler,
            spacing: args.spacing,
            steps: args.steps,
            guidance: args.guidance,
            start_t: args.start_t,
        },
    );
    let options = GenerateOptions {
        sampler: sampler.clone(),
        samples: 1,
        seed: args.sample_seed,
        unconditional: false,
        residual_weight: args.residual_weight,
    };
    generation::check_options(&options, &bundle)?;
    let mut inputs = staging::Inputs::new();
    inputs.add_opt(args.scene.as_ref());
    let staging = staging::stage_checked(
        &args.out,
        args.force || is_earlier_demo_output(&args.out),
        &inputs,
    )?;
    let out = staging.path().to_path_buf();

    let pb = progress::bar(sampler.steps as u64 + 3, "demo");
    pb.set_message("simulating the scene");
    let scene = Scene::generate(&config, args.seed)?;
    let frame = scene.render_frame(0)?;
    let mut rgb = frame.image.to_rgb_image()?;
    let mut camera_effects = Vec::new();
    if preset != Preset::Clear {
        let weather = Weather::preset(preset).with_seed(args.seed);
        let sim = WeatherSim::new(&weather, &WeatherConfig::default())?;
        let depth = depth_map(&frame);
        let cam_out = sim.apply_camera(CameraInput {
            image: &rgb,
            depth: Some(&depth),
            intrinsics: Some(Intrinsics::from_camera(&frame.camera)),
        })?;
        camera_effects = cam_out
            .records
            .iter()
            .map(|r| r.effect.to_string())
            .collect();
        rgb = cam_out.image;
    }
    pb.inc(1);

    pb.set_message("generating");
    let t = Instant::now();
    let pipeline = ScanPipeline::new(
        &bundle,
        &[RigImage {
            image: &rgb,
            camera: &frame.camera,
        }],
    )?;
    let scans = pipeline.generate(&options, |_, _| pb.inc(1))?;
    let seconds_generation = t.elapsed().as_secs_f64();
    let scan = scans
        .into_iter()
        .next()
        .context("the model returned no scan")?;
    let (generated, generated_range) = (scan.points, scan.range);

    pb.set_message("writing views and metrics");
    let truth = &frame.scan.points;
    let grid = &bundle.config.denoiser.sensor;
    let true_range = project(&Projector::new(grid, ProjectionOptions::default())?, truth)?;
    write_outputs(
        &out,
        &frame,
        &rgb,
        &generated,
        &generated_range,
        &true_range,
        grid,
    )?;
    let metrics = demo_metrics(&frame, truth, &generated, &generated_range, &true_range)?;
    pb.set_message("baselines");
    let baselines = baseline_scans(&pipeline, &config, args.baseline_frames)?;
    let mut baseline_rows = Vec::new();
    let mut ring_spread_m = BTreeMap::new();
    let spread = |r: &RangeImage| veila_metrics::baseline::ring_spread(r, grid, -15.0, 0.5);
    ring_spread_m.insert("generated", spread(&generated_range));
    ring_spread_m.insert("true", spread(&true_range));
    let mut texture = BTreeMap::new();
    texture.insert(
        "generated",
        TextureSummary::of(&generated_range, &true_range)?,
    );
    texture.insert("true", TextureSummary::of(&true_range, &true_range)?);
    for (name, description, range) in &baselines {
        let points = model::to_points(&bundle, range)?;
        let m = demo_metrics(&frame, truth, &points, range, &true_range)?;
        ring_spread_m.insert(name, spread(range));
        texture.insert(name, TextureSummary::of(range, &true_range)?);
        baseline_rows.push(BaselineSummary {
            name,
            description: description.clone(),
            metrics: m.metrics,
        });
    }
    // the sample next to the model's own mean network (a residual's or a prior's; 0 steps):
    // what the texture costs in error
    if bundle.config.mean_net().is_some() && sampler.steps > 0 && args.residual_weight > 0.0 {
        let mean_only = pipeline.generate(
            &GenerateOptions {
                sampler: SamplerConfig {
                    steps: 0,
                    start_t: None,
                    ..options.sampler.clone()
                },
                residual_weight: 1.0,
                ..options.clone()
            },
            |_, _| {},
        )?;
        let scan = mean_only
            .into_iter()
            .next()
            .context("the model returned no scan")?;
        let (points, range) = (scan.points, scan.range);
        let m = demo_metrics(&frame, truth, &points, &range, &true_range)?;
        ring_spread_m.insert("mean net", spread(&range));
        texture.insert("mean net", TextureSummary::of(&range, &true_range)?);
        baseline_rows.push(BaselineSummary {
            name: "mean net",
            description: "the model's own mean network alone (a residual bundle's --residual-weight 0): the smooth conditional mean, the smallest pixel error".into(),
            metrics: m.metrics,
        });
    }
    pb.inc(1);

    let summary = DemoSummary {
        scene: &scene_name,
        seed: args.seed,
        weather: &args.weather,
        camera_effects,
        model: bundle.origin.display().to_string(),
        sampler: &sampler,
        sample_seed: args.sample_seed,
        grid: [grid.rows as usize, grid.cols as usize],
        points_true: truth.len(),
        points_generated: generated.len(),
        range_pixels_true: true_range.num_valid(),
        range_pixels_generated: generated_range.num_valid(),
        metrics: &metrics.metrics,
        ring_spread_m,
        texture,
        baselines: baseline_rows,
    };
    veila_data::atomic::write_atomic(
        &out.join("metrics.json"),
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )?;
    // wall-clock time apart, so metrics.json of identical runs is byte-identical
    veila_data::atomic::write_atomic(
        &out.join("timings.json"),
        serde_json::json!({ "seconds_generation": (seconds_generation * 1000.0).round() / 1000.0 })
            .to_string()
            .as_bytes(),
    )?;
    pb.inc(1);
    pb.finish_and_clear();

    // files first, then the report: a reader that goes away early (`| head`) cannot cost the output
    staging.commit()?;
    println!(
        "scene {scene_name}, seed {}: generated a {}x{} scan ({} returns; the true scan has {} on this grid) from the camera image in {:.1} s ({sampler})",
        args.seed,
        grid.rows,
        grid.cols,
        summary.range_pixels_generated,
        summary.range_pixels_true,
        seconds_generation,
    );
    if !summary.camera_effects.is_empty() {
        println!(
            "input image degraded by '{}': [{}]",
            args.weather,
            summary.camera_effects.join(", ")
        );
    }
    let columns: Vec<(&str, &[MetricValue])> = summary
        .baselines
        .iter()
        .map(|b| (b.name, b.metrics.as_slice()))
        .collect();
    crate::demo_table::print_table(&metrics.metrics, &columns, &summary.ring_spread_m);
    crate::demo_table::print_texture(&columns, &summary.texture);
    for b in &summary.baselines {
        println!("  {}: {}", b.name, b.description);
    }
    println!("wrote {}", args.out.display());
    Ok(())
}

/// Files an earlier `veila demo` writes (so running the README's command twice refreshes its output
/// instead of failing, and nothing else can be overwritten).
const DEMO_FILES: &[&str] = &[
    "metrics.json",
    "timings.json",
    "camera.png",
    "range_generated_vs_true.png",
    "bev_generated_vs_true.png",
    "overlay_generated_vs_true.png",
    "generated.exr",
    "generated.ply",
    "generated.bin",
    "true.exr",
    "true.ply",
    "true.bin",
];

/// Whether `dir` holds nothing but the files an earlier `veila demo` wrote.
fn is_earlier_demo_output(dir: &Path) -> bool {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    let names: Vec<String> = entries
        .filter_map(|e| e.ok().map(|e| e.file_name().to_string_lossy().into_owned()))
        .filter(|n| n != crate::staging::MANIFEST)
        .collect();
    names.iter().any(|n| n == "metrics.json")
        && names.iter().all(|n| DEMO_FILES.contains(&n.as_str()))
}

/// Input image, side-by-side views, and both scans as EXR, PLY and KITTI `.bin`.
fn write_outputs(
    dir: &Path,
    frame: &SimFrame,
    rgb: &RgbImage,
    generated: &PointCloud,
    generated_range: &RangeImage,
    true_range: &RangeImage,
    grid: &veila_geom::LidarSensor,
) -> Result<()> {
    use veila_data::{image_io::write_png, range_exr::write_range_exr, scan::write_points};
    let truth = &frame.scan.points;
    write_png(&dir.join("camera.png"), rgb)?;
    let preview = RangePreview::default();
    write_png(
        &dir.join("range_generated_vs_true.png"),
        &render::stack_vertical(&[
            render::render_range(generated_range, &preview),
            render::render_range(true_range, &preview),
        ]),
    )?;
    let bev = BevOptions::default();
    write_png(
        &dir.join("bev_generated_vs_true.png"),
        &render::stack_horizontal(&[
            render::render_bev(generated, &bev)?,
            render::render_bev(truth, &bev)?,
        ]),
    )?;
    let ov = OverlayOptions::default();
    let gen_overlay = render::render_overlay(rgb, &frame.camera, &generated.xyz, &ov)?;
    let true_overlay = render::render_overlay(rgb, &frame.camera, &truth.xyz, &ov)?;
    write_png(
        &dir.join("overlay_generated_vs_true.png"),
        &render::stack_vertical(&[gen_overlay.image, true_overlay.image]),
    )?;
    write_range_exr(&dir.join("generated.exr"), grid, generated_range)?;
    write_range_exr(&dir.join("true.exr"), grid, true_range)?;
    write_points(&dir.join("generated.ply"), generated)?;
    write_points(&dir.join("generated.bin"), generated)?;
    write_points(&dir.join("true.ply"), truth)?;
    write_points(&dir.join("true.bin"), truth)?;
    Ok(())
}

/// Generated scan against the true one: BEV JSD / MMD (R2DM protocol) and Chamfer per region; range
/// error on pixels where both have a return; the cross-modal depth consistency of both scans with
/// the simulator's true depth map (the true scan's value is the floor the metric can reach).
fn demo_metrics(
    frame: &SimFrame,
    truth: &PointCloud,
    generated: &PointCloud,
    generated_range: &RangeImage,
    true_range: &RangeImage,
) -> Result<MetricReport> {
    let mut metrics = Vec::new();
    let cfg = BevConfig::r2dm();
    let one = |name: &str, protocol: Protocol, region: Region, value: f64| MetricValue {
        name: name.to_string(),
        protocol,
        region,
        value,
        generated: 1,
        reference: 1,
        paper_scale: None,
    };
    for region in Region::ALL {
        let ht = bev_histogram(&truth.xyz, &cfg, region, "true scan")?;
        let hg = bev_histogram(&generated.xyz, &cfg, region, "generated scan")?;
        metrics.push(one(
            "jsd",
            Protocol::R2dm,
            region,
            dist::jsd(std::slice::from_ref(&hg), std::slice::from_ref(&ht))?,
        ));
        let mmd = dist::mmd_r2dm_dense(&[hg], &[ht], 0.5)?;
        metrics.push(MetricValue {
            paper_scale: Some(1e4),
            ..one("mmd", Protocol::R2dm, region, mmd)
        });
        let a = veila_metrics::filter_region(&generated.xyz, region);
        let b = veila_metrics::filter_region(&truth.xyz, region);
        if !a.is_empty() && !b.is_empty() {
            metrics.push(one(
                "chamfer",
                Protocol::Pytorch3d,
                region,
                chamfer::chamfer_distance(&a, &b)?.value(),
            ));
        }
        if let Some(mae) = veila_metrics::range::range_mae(generated_range, true_range, region) {
            metrics.push(one(
                "range mae (m, both valid)",
                Protocol::Veila,
                region,
                mae,
            ));
        }
    }
    let img = &frame.image;
    let depth = Map2d::new(img.width, img.height, &img.depth_m)?;
    let filter = ProjectionFilter::default();
    for (which, cloud) in [("generated", generated), ("true", truth)] {
        let dc = cm_depth_consistency(
            &cloud.xyz,
            &frame.camera,
            &depth,
            DepthAlignment::None,
            &filter,
        )?;
        metrics.push(one(
            &format!("cm-dc ({which} scan vs true depth)"),
            Protocol::Veila,
            Region::Front,
            dc.abs_rel,
        ));
    }
    Ok(MetricReport { metrics })
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

/// The zero-skill baselines of the demo scene, from `k` training frames of the same scene file
/// (seeds `0..k` of the train split, rendered in parallel): their per-pixel median scan, and the
/// frame whose image is nearest to the input's (`query`, the rig the demo generates from) in the
/// bundle's frozen encoder features (conditional bundles only).
fn baseline_scans(
    query: &ScanPipeline<'_>,
    config: &SceneConfig,
    k: usize,
) -> Result<Vec<(&'static str, String, RangeImage)>> {
    use rayon::prelude::*;
    if k == 0 {
        return Ok(Vec::new());
    }
    let bundle = query.bundle();
    let grid = &bundle.config.denoiser.sensor;
    let projector = Projector::new(grid, ProjectionOptions::default())?;
    let frames = config.frames.count.max(1) as u64;
    let rendered: Vec<(RangeImage, RgbImage, veila_geom::PinholeCamera)> = (0..k as u64)
        .into_par_iter()
        .map(|seed| -> Result<_> {
            let scene = Scene::generate(config, seed)?;
            let f = scene.render_frame((seed % frames) as u32)?;
            let range = project(&projector, &f.scan.points)?;
            Ok((range, f.image.to_rgb_image()?, f.camera))
        })
        .collect::<Result<_>>()?;
    let refs: Vec<&RangeImage> = rendered.iter().map(|(r, _, _)| r).collect();
    let median = veila_metrics::baseline::median_scan(&refs)?;
    let mut out = vec![(
        "mean scan",
        format!(
            "per-pixel median range and majority ray drop of {k} training frames of this scene file (no image used)"
        ),
        median,
    )];
    let q = query.image_descriptor()?;
    if !q.is_empty() {
        let keys = rendered
            .iter()
            .map(|(_, image, camera)| {
                Ok(ScanPipeline::new(bundle, &[RigImage { image, camera }])?.image_descriptor()?)
            })
            .collect::<Result<Vec<_>>>()?;
        let i = veila_metrics::baseline::nearest(&q, &keys)?;
        out.push((
            "retrieval",
            format!("the scan of training seed {i} of those {k}, whose image is nearest to the input in the frozen encoders' features"),
            rendered[i].0.clone(),
        ));
    }
    Ok(out)
}
