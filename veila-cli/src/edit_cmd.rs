//! `veila edit`: scene editing by inpainting (RePaint). A scan is projected onto the bundle's grid,
//! the pixels chosen by a mask image or a 3D box are regenerated consistent with the rest of the scan
//! and the camera views, and every other pixel is kept.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::{ArgGroup, Args};
use glam::Vec3;
use serde::Serialize;
use veila_data::image::{GrayImage, RgbImage, imageops};
use veila_data::image_io::write_png;
use veila_data::range_exr::read_range_exr;
use veila_data::scan::{PointFormat, read_points};
use veila_data::vis::render::{self, render_range};
use veila_diffusion::app::bundle::Bundle;
use veila_diffusion::app::{GenerateOptions, SamplerChoice, ScanPipeline};
use veila_diffusion::{RepaintConfig, SamplerConfig, SamplerKind, SamplerName};
use veila_geom::{ProjectionOptions, Projector, RangeImage, RayTable};

use crate::generation::{
    InputInfo, ModelInfo, RigArgs, SAMPLE_BATCH, ScanRecord, Seconds, check_options,
    inpainting_sampler_help, input_info, load_rig, model_info, range_preview, resolve_sampler,
    sampler_parser, write_scan,
};
use crate::{model, progress, staging};

/// Arguments of `veila edit`.
#[derive(Debug, Args)]
#[command(group(ArgGroup::new("region").required(true).args(["mask", "remove_box"])))]
#[command(group(ArgGroup::new("rig_images").required(true).args(["images"])))]
pub(crate) struct EditArgs {
    #[command(flatten)]
    rig: RigArgs,
    /// The scan to edit: KITTI .bin, nuScenes .pcd.bin, .ply or a range .exr; projected onto the
    /// model's range-image grid (an .exr on that grid is taken as is).
    #[arg(long, value_name = "SCAN")]
    scan: PathBuf,
    /// Region to regenerate as an image (white = regenerate, black = keep), rows x cols of the model
    /// grid or any size (resized with nearest neighbour).
    #[arg(long, value_name = "MASK.png")]
    mask: Option<PathBuf>,
    /// Region to regenerate as a box in the LiDAR frame, metres: the pixels whose points fall inside
    /// are regenerated (e.g. to remove a car: "5,-2,-2,10,2,1").
    #[arg(
        long,
        value_name = "XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
        allow_hyphen_values = true
    )]
    remove_box: Option<String>,
    /// Model bundle folder (default: $VEILA_MODEL, else the bundled models/default;
    /// `--checkpoint` is an alias).
    #[arg(long, value_name = "DIR", env = "VEILA_MODEL", alias = "checkpoint")]
    model: Option<PathBuf>,
    // the help names the bundled model's sampler as its bundle.json does
    #[arg(long, value_parser = sampler_parser(), help = inpainting_sampler_help())]
    sampler: Option<SamplerName>,
    /// Where the sampler's steps lie on the noise schedule (default: the bundle's).
    #[arg(long, value_parser = crate::generation::spacing_parser())]
    spacing: Option<veila_diffusion::Spacing>,
    /// Sampler steps, 1 to 1000 (default: the bundle's).
    #[arg(long, value_name = "N", value_parser = crate::bounds::steps())]
    steps: Option<usize>,
    /// Classifier-free guidance scale, 0 to 20 (default: the bundle's).
    #[arg(long, value_name = "S", allow_negative_numbers = true, value_parser = crate::bounds::guidance())]
    guidance: Option<f64>,
    /// Seed, 0 to 18446744073709551615.
    #[arg(long, value_name = "S", default_value_t = 0)]
    seed: u64,
    /// Number of edited versions to draw, 1 to 8 (drawn in one batch).
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = crate::bounds::int::<usize>(1, SAMPLE_BATCH as u64))]
    samples: usize,
    /// RePaint: levels each resampling jump goes back up, 1 to 1000.
    #[arg(long, value_name = "N", default_value_t = 10, value_parser = crate::bounds::int::<usize>(1, 1000))]
    jump_length: usize,
    /// RePaint: times each jump segment is traversed, 1 to 100 (1 = no resampling; 10 in the
    /// paper, slower).
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = crate::bounds::int::<usize>(1, 100))]
    jump_n_sample: usize,
    /// Output folder (created; must be absent or empty unless --force).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Write into an existing, non-empty output folder.
    #[arg(long)]
    force: bool,
}

/// A box in the LiDAR frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
struct Aabb {
    min_m: [f32; 3],
    max_m: [f32; 3],
}

impl Aabb {
    fn contains(&self, p: Vec3) -> bool {
        (0..3).all(|k| p[k] >= self.min_m[k] && p[k] <= self.max_m[k])
    }
}

fn parse_box(s: &str) -> Result<Aabb> {
    let vals: Vec<f32> = s
        .split(',')
        .map(|t| {
            t.trim()
                .parse::<f32>()
                .ok()
                .filter(|v| v.is_finite())
                .with_context(|| format!("--remove-box {s}: `{}` is not a finite number", t.trim()))
        })
        .collect::<Result<_>>()?;
    if vals.len() != 6 {
        bail!(
            "--remove-box {s}: expected 6 numbers xmin,ymin,zmin,xmax,ymax,zmax, got {}",
            vals.len()
        );
    }
    let b = Aabb {
        min_m: [vals[0], vals[1], vals[2]],
        max_m: [vals[3], vals[4], vals[5]],
    };
    if (0..3).any(|k| b.min_m[k] > b.max_m[k]) {
        bail!("--remove-box {s}: every minimum must be <= its maximum");
    }
    Ok(b)
}

/// The scan on the bundle's grid.
fn scan_on_grid(bundle: &Bundle, path: &Path) -> Result<RangeImage> {
    let sensor = &bundle.config.denoiser.sensor;
    let loaded = read_points(path)?;
    if loaded.format == PointFormat::RangeExr && loaded.sensor.as_ref() == Some(sensor) {
        return Ok(read_range_exr(path)?.image);
    }
    let mut cloud = loaded.cloud;
    if loaded.format == PointFormat::NuScenesPcdBin && bundle.config.encoding.intensity_max <= 1.0 {
        // nuScenes stores 0..255; the model's intensity is 0..1
        for i in &mut cloud.intensity {
            *i /= 255.0;
        }
    }
    // returns nearer than the encoding's minimum range cannot be represented (they decode as
    // dropped rays) and would occlude the real returns behind them (nuScenes' ego-vehicle points)
    let min_r = bundle.config.encoding.min_range_m;
    let (xyz, intensity): (Vec<Vec3>, Vec<f32>) = cloud
        .xyz
        .iter()
        .zip(&cloud.intensity)
        .filter(|(p, _)| p.length() >= min_r)
        .map(|(p, i)| (*p, *i))
        .unzip();
    let projector = Projector::new(sensor, ProjectionOptions::default())?;
    let (img, _) = projector
        .project(&xyz, Some(&intensity), None)
        .with_context(|| format!("{}: projecting onto the model grid", path.display()))?;
    Ok(img)
}

/// `true` = regenerate, from a mask image (white = regenerate).
fn mask_from_image(path: &Path, rows: usize, cols: usize) -> Result<Vec<bool>> {
    // read strictly (a truncated PNG or JPEG is an error naming the file)
    let img: GrayImage = veila_data::image_io::read_image(path)
        .context("not a readable mask image")?
        .into_luma8();
    let img = if img.dimensions() == (cols as u32, rows as u32) {
        img
    } else {
        imageops::resize(
            &img,
            cols as u32,
            rows as u32,
            imageops::FilterType::Nearest,
        )
    };
    Ok(img.pixels().map(|p| p.0[0] >= 128).collect())
}

/// `true` = regenerate: the returns whose points lie in the box.
fn mask_from_box(bundle: &Bundle, known: &RangeImage, b: &Aabb) -> Result<Vec<bool>> {
    let rays = RayTable::new(&bundle.config.denoiser.sensor)?;
    let cols = known.cols;
    Ok((0..known.range_m.len())
        .map(|k| {
            let (row, col) = (k as u32 / cols, k as u32 % cols);
            known.mask[k] && b.contains(rays.dir(row, col) * known.range_m[k])
        })
        .collect())
}

/// The range preview of `before` with the regenerated region tinted red.
fn region_preview(bundle: &Bundle, before: &RangeImage, regen: &[bool]) -> RgbImage {
    let mut img = render_range(before, &range_preview(bundle));
    let cols = before.cols;
    let scale = (img.height() / before.rows.max(1)).max(1);
    for (x, y, p) in img.enumerate_pixels_mut() {
        let k = (y / scale) as usize * cols as usize + x as usize;
        if regen.get(k).copied().unwrap_or(false) {
            p.0 = [(p.0[0] as u16 / 2 + 128) as u8, p.0[1] / 2, p.0[2] / 2];
        }
    }
    img
}

#[derive(Debug, Serialize)]
struct EditScan {
    #[serde(flatten)]
    record: ScanRecord,
    /// Returns inside the regenerated region after the edit.
    region_returns_after: usize,
    /// Regenerated pixels whose return or range changed (> 1 mm).
    region_changed_pixels: usize,
    /// Largest range change over the kept pixels (encode/decode round-off), metres.
    kept_max_range_change_m: f32,
}

#[derive(Debug, Serialize)]
struct EditReport {
    command: &'static str,
    veila_version: &'static str,
    inputs: Vec<InputInfo>,
    scan: String,
    region: serde_json::Value,
    model: ModelInfo,
    sampler: SamplerConfig,
    sampler_name: String,
    repaint: RepaintConfig,
    seed: u64,
    samples: usize,
    regenerated_pixels: usize,
    kept_pixels: usize,
    region_returns_before: usize,
    /// Quarter turns from the calibration's LiDAR frame into the model's (1 for nuScenes): the
    /// scan and the region are inpainted there and written back in the LiDAR frame.
    model_frame_quarter_turns: i32,
    scans: Vec<EditScan>,
}

pub(crate) fn run(args: EditArgs) -> Result<()> {
    // the parsers hold every flag to its range; what depends on the model is checked once it is
    // loaded, before the output folder is staged
    if args.sampler == Some(SamplerName::Dpm) {
        bail!(
            "--sampler dpm: inpainting needs ddpm or ddim (a multistep solver cannot follow RePaint's jumps)"
        );
    }
    let region_box = args.remove_box.as_deref().map(parse_box).transpose()?;
    let t0 = Instant::now();
    let mut inputs = staging::Inputs::new();
    inputs
        .extend(&args.rig.images)
        .extend(&args.rig.calibs)
        .add(&args.scan)
        .add_opt(args.mask.as_ref());
    let views = load_rig(&args.rig)?;
    let device = model::device()?;
    let bundle = model::load_bundle(args.model.as_deref(), &device)?;
    let mut sampler = resolve_sampler(
        &bundle,
        SamplerChoice {
            name: args.sampler,
            spacing: args.spacing,
            steps: args.steps,
            guidance: args.guidance,
            start_t: None,
        },
    );
    if matches!(sampler.kind, SamplerKind::DpmSolverPp2M) {
        // the bundle's default: keep steps and guidance, switch to deterministic DDIM
        sampler = SamplerConfig {
            kind: SamplerKind::Ddim { eta: 0.0 },
            ..sampler
        };
    }
    let options = GenerateOptions {
        sampler: sampler.clone(),
        samples: args.samples,
        seed: args.seed,
        unconditional: false,
        residual_weight: 1.0,
    };
    check_options(&options, &bundle)?;
    let (rows, cols) = bundle.grid();
    let before = scan_on_grid(&bundle, &args.scan)?;
    let regen = match (&args.mask, &region_box) {
        (Some(p), _) => mask_from_image(p, rows, cols)?,
        (None, Some(b)) => mask_from_box(&bundle, &before, b)?,
        (None, None) => bail!("give --mask or --remove-box"),
    };
    let regenerated = regen.iter().filter(|&&r| r).count();
    if regenerated == 0 {
        match (&args.mask, &args.remove_box) {
            (Some(p), _) => bail!(
                "{}: the mask selects no pixel (white = regenerate)",
                p.display()
            ),
            (_, Some(b)) => bail!(
                "--remove-box {b}: no return of {} falls inside the box (LiDAR frame: x forward, y left, z up)",
                args.scan.display()
            ),
            _ => bail!("nothing to regenerate"),
        }
    }
    // inpainted in the model's frame (camera along +x), like `generate`; the scan, the region and
    // the results stay in the calibration's LiDAR frame
    let pipeline = ScanPipeline::from_views(&bundle, &views)?;
    let turns = pipeline.quarter_turns();
    let staging = staging::stage_checked(&args.out, args.force, &inputs)?;
    let load_secs = t0.elapsed().as_secs_f64();

    let keep: Vec<bool> = regen.iter().map(|r| !r).collect();
    let repaint = RepaintConfig {
        jump_length: args.jump_length,
        jump_n_sample: args.jump_n_sample,
    };
    let t = Instant::now();
    let pb = progress::bar(args.samples as u64, "edit");
    pb.set_message(format!(
        "inpainting {regenerated} pixels, {} x {} steps",
        sampler.kind, sampler.steps
    ));
    pb.enable_steady_tick(Duration::from_millis(250));
    let scans = pipeline
        .inpaint(&before, &keep, &options, &repaint)
        .context("inpainting")?;
    pb.finish_and_clear();
    let sampling_secs = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let out = staging.path();
    let preview = range_preview(&bundle);
    let marked = region_preview(&bundle, &before, &regen);
    let mask_png = GrayImage::from_fn(cols as u32, rows as u32, |x, y| {
        veila_data::image::Luma([if regen[y as usize * cols + x as usize] {
            255
        } else {
            0
        }])
    });
    mask_png
        .save_with_format(out.join("mask.png"), veila_data::image::ImageFormat::Png)
        .with_context(|| format!("{}: cannot write", out.join("mask.png").display()))?;
    write_png(
        &out.join("before_range.png"),
        &render_range(&before, &preview),
    )?;
    let enc = &bundle.config.encoding;
    let mut records = Vec::with_capacity(scans.len());
    for (i, after) in scans.iter().enumerate() {
        let stem = format!("scan_{i:03}");
        let record = write_scan(out, &stem, &bundle, after, &views[0])?;
        let after = &after.range;
        write_png(
            &out.join(format!("{stem}_before_after.png")),
            &render::stack_vertical(&[
                render_range(&before, &preview),
                marked.clone(),
                render_range(after, &preview),
            ]),
        )?;
        let mut changed = 0;
        let mut returns_after = 0;
        let mut kept_max = 0.0f32;
        for k in 0..regen.len() {
            if regen[k] {
                returns_after += usize::from(after.mask[k]);
                if after.mask[k] != before.mask[k]
                    || (after.range_m[k] - before.range_m[k]).abs() > 1e-3
                {
                    changed += 1;
                }
            } else if before.mask[k]
                && (enc.min_range_m..=enc.max_range_m).contains(&before.range_m[k])
            {
                let d = if after.mask[k] {
                    (after.range_m[k] - before.range_m[k]).abs()
                } else {
                    f32::INFINITY
                };
                kept_max = kept_max.max(d);
            }
        }
        records.push(EditScan {
            record,
            region_returns_after: returns_after,
            region_changed_pixels: changed,
            kept_max_range_change_m: kept_max,
        });
    }
    let writing_secs = t.elapsed().as_secs_f64();
    let region = match (&args.mask, &region_box) {
        (Some(p), _) => serde_json::json!({ "mask": p.display().to_string() }),
        (_, Some(b)) => serde_json::json!({ "remove_box": b }),
        _ => serde_json::Value::Null,
    };
    let round3 = |x: f64| (x * 1000.0).round() / 1000.0;
    let report = EditReport {
        command: "edit",
        veila_version: env!("CARGO_PKG_VERSION"),
        inputs: input_info(&views),
        scan: args.scan.display().to_string(),
        region,
        model: model_info(&bundle, args.model.as_deref()),
        sampler_name: sampler.kind.to_string(),
        sampler,
        repaint,
        seed: args.seed,
        samples: args.samples,
        regenerated_pixels: regenerated,
        kept_pixels: regen.len() - regenerated,
        region_returns_before: regen
            .iter()
            .zip(&before.mask)
            .filter(|(r, m)| **r && **m)
            .count(),
        model_frame_quarter_turns: turns,
        scans: records,
    };
    // wall-clock times apart, so edit.json of identical runs is byte-identical
    let timings = Seconds {
        load: round3(load_secs),
        sampling: round3(sampling_secs),
        per_scan: round3(sampling_secs / args.samples as f64),
        writing: round3(writing_secs),
    };
    veila_data::atomic::write_atomic(
        &out.join("edit.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    veila_data::atomic::write_atomic(
        &out.join("timings.json"),
        serde_json::to_string_pretty(&timings)?.as_bytes(),
    )?;
    staging.commit()?;

    println!(
        "edited {}: regenerated {} of {} pixels ({} returns before) with {} x {} steps (RePaint jumps {} x {}), seed {}",
        args.scan.display(),
        report.regenerated_pixels,
        regen.len(),
        report.region_returns_before,
        report.sampler_name,
        report.sampler.steps,
        repaint.jump_length,
        repaint.jump_n_sample,
        args.seed
    );
    for s in &report.scans {
        println!(
            "  {}: {} points, {} returns in the region, {} region pixels changed, kept pixels within {:.1e} m",
            s.record.file,
            s.record.points,
            s.region_returns_after,
            s.region_changed_pixels,
            s.kept_max_range_change_m
        );
    }
    println!(
        "{:.2} s per scan; wrote {}",
        sampling_secs / args.samples as f64,
        args.out.display()
    );
    Ok(())
}
