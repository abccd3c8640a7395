//! `veila generate`: panoramic LiDAR scans from camera images with a model bundle.
//!
//! The images and their calibration give a camera rig (one view per `--image`); the bundle's frozen
//! encoders see each image resized to the bundle's input size, the denoiser samples range images on
//! the bundle's grid, and every scan is written as a KITTI `.bin`, a range-image EXR and three
//! previews. Everything goes to a staging folder first: a failure leaves no output behind.
//!
//! Calibration files carry no image size, so each camera takes the size of its image. The image must
//! be the one the calibration describes (full resolution): an image whose size puts the calibration's
//! principal point outside the central 20-80% of the image is rejected, because a resized image
//! needs a rescaled calibration.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use serde::Serialize;
use veila_data::PointCloud;
use veila_data::image::RgbImage;
use veila_data::image_io::{read_rgb_image, write_png};
use veila_data::kitti::KittiCalib;
use veila_data::nuscenes::NuScenesSample;
use veila_data::range_exr::write_range_exr;
use veila_data::scan::write_kitti_bin;
use veila_data::semantic_kitti::OdometryCalib;
use veila_data::spec::{CalibKind, detect_calib_kind};
use veila_data::vis::render::{
    BevOptions, OverlayOptions, RangePreview, render_bev, render_overlay, render_range,
};
use veila_diffusion::bundle::{Bundle, DENOISER_FILE, MANIFEST_FILE, Manifest, sha256_hex};
use veila_diffusion::pipeline::{CameraView, GenerateOptions};
use veila_diffusion::{DecodedScan, SamplerConfig, SamplerKind};
use veila_geom::{PinholeCamera, RangeImage};

use crate::{model, progress, staging};

/// Arguments of `veila generate`.
#[derive(Debug, Args)]
pub(crate) struct GenerateArgs {
    #[command(flatten)]
    pub(crate) rig: RigArgs,
    /// Model bundle folder (default: $VEILA_MODEL, else the bundled models/default).
    #[arg(long, value_name = "DIR")]
    pub(crate) checkpoint: Option<PathBuf>,
    /// Sampler (default: the bundle's, DPM-Solver++(2M) for the bundled model).
    #[arg(long, value_enum)]
    pub(crate) sampler: Option<SamplerName>,
    /// Sampler steps (network evaluations per conditioning branch, 1 to 1000; default: the
    /// bundle's).
    #[arg(long, value_name = "N")]
    pub(crate) steps: Option<usize>,
    /// Classifier-free guidance scale, 0 to 20 (1 = none; default: the bundle's).
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    pub(crate) guidance: Option<f64>,
    /// Seed of the initial noise (same inputs, model and seed give identical files).
    #[arg(long, value_name = "S", default_value_t = 0)]
    pub(crate) seed: u64,
    /// Number of scans to draw for the rig (drawn in batches of at most 8: memory does not grow
    /// with N).
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub(crate) samples: usize,
    /// Output folder (created; must be absent or empty unless --force).
    #[arg(long, value_name = "DIR")]
    pub(crate) out: PathBuf,
    /// Write into an existing, non-empty output folder (same-named files are replaced).
    #[arg(long)]
    pub(crate) force: bool,
}

/// The camera rig: images, calibration and which camera of the calibration each image is.
#[derive(Debug, Args)]
pub(crate) struct RigArgs {
    /// Camera image (PNG or JPEG); repeat once per camera of the rig.
    #[arg(long = "image", value_name = "IMG", required = true)]
    pub(crate) images: Vec<PathBuf>,
    /// Calibration: KITTI object calib/NNNNNN.txt (P2, R0_rect, Tr_velo_to_cam), KITTI odometry /
    /// SemanticKITTI calib.txt (P2, Tr) or a nuScenes per-sample JSON. Give it once for every image
    /// or once per image. Calibrations carry no image size: each camera takes its image's size, so
    /// give the original images (a resized image is rejected by a principal-point check).
    #[arg(long = "calib", value_name = "CALIB", required = true)]
    pub(crate) calibs: Vec<PathBuf>,
    /// Which camera of the calibration each image shows: the KITTI projection matrix index (0-3,
    /// default 2 = image_2) or the nuScenes channel (default CAM_FRONT). Once per image.
    #[arg(long = "camera", value_name = "N")]
    pub(crate) cameras: Vec<String>,
}

/// Sampler names on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub(crate) enum SamplerName {
    /// Ancestral DDPM (stochastic).
    Ddpm,
    /// DDIM with eta = 0 (deterministic).
    Ddim,
    /// DPM-Solver++(2M) (deterministic, good in 10-25 steps).
    Dpm,
}

/// One camera of the rig, read and checked.
#[derive(Debug, Clone)]
pub(crate) struct ViewInput {
    pub(crate) image_path: PathBuf,
    pub(crate) calib_path: PathBuf,
    pub(crate) calib_kind: &'static str,
    pub(crate) camera_name: String,
    pub(crate) image: RgbImage,
    /// The camera at the image's full resolution.
    pub(crate) camera: PinholeCamera,
}

/// Reads every image and its camera (errors name the file and the problem).
pub(crate) fn load_rig(rig: &RigArgs) -> Result<Vec<ViewInput>> {
    let n = rig.images.len();
    if rig.calibs.len() != 1 && rig.calibs.len() != n {
        bail!(
            "{} --image but {} --calib: give one calibration for all images or one per image",
            n,
            rig.calibs.len()
        );
    }
    if !rig.cameras.is_empty() && rig.cameras.len() != n {
        bail!(
            "{} --image but {} --camera: give one --camera per image (or none for the default camera)",
            n,
            rig.cameras.len()
        );
    }
    let mut views = Vec::with_capacity(n);
    for (i, image_path) in rig.images.iter().enumerate() {
        let calib_path = if rig.calibs.len() == 1 {
            &rig.calibs[0]
        } else {
            &rig.calibs[i]
        };
        let image = read_rgb_image(image_path)?;
        let (w, h) = image.dimensions();
        let kind = detect_calib_kind(calib_path)?;
        let name = rig.cameras.get(i).cloned().unwrap_or_else(|| match kind {
            CalibKind::NuScenesJson => "CAM_FRONT".to_string(),
            _ => "2".to_string(),
        });
        let (camera, kind_name) = match kind {
            CalibKind::KittiObject => (
                KittiCalib::read(calib_path)?.camera(kitti_index(&name, calib_path)?, w, h),
                "kitti-object",
            ),
            CalibKind::KittiOdometry => (
                OdometryCalib::read(calib_path)?.camera(kitti_index(&name, calib_path)?, w, h),
                "kitti-odometry",
            ),
            CalibKind::NuScenesJson => (
                NuScenesSample::read_json(calib_path)?.camera(&name, w, h),
                "nuscenes-json",
            ),
        };
        let camera = camera.with_context(|| {
            format!(
                "{}: camera {name} for the {w}x{h} image {}",
                calib_path.display(),
                image_path.display()
            )
        })?;
        check_principal_point(&camera, image_path, calib_path)?;
        views.push(ViewInput {
            image_path: image_path.clone(),
            calib_path: calib_path.clone(),
            calib_kind: kind_name,
            camera_name: name,
            image,
            camera,
        });
    }
    Ok(views)
}

fn kitti_index(name: &str, calib: &Path) -> Result<usize> {
    let digits = name
        .strip_prefix("image_")
        .or_else(|| name.strip_prefix('P'))
        .unwrap_or(name);
    match digits.parse::<usize>() {
        Ok(i) if i <= 3 => Ok(i),
        _ => bail!(
            "{}: --camera {name}: a KITTI calibration has cameras 0 to 3 (P0..P3; 2 = image_2, 3 = image_3)",
            calib.display()
        ),
    }
}

/// A calibration's principal point lies near the centre of the image it was made for (KITTI: 49% /
/// 46% of width / height, nuScenes: 50% / 50%). Outside the central 20-80% band, the image was
/// almost certainly resized (a 2x change moves it to ~25% or ~100%) or cropped without adapting the
/// calibration, and the scan would be generated for the wrong rays.
fn check_principal_point(camera: &PinholeCamera, image: &Path, calib: &Path) -> Result<()> {
    let k = camera.intrinsics;
    let (cx, cy) = (k.z_axis.x, k.z_axis.y);
    let (w, h) = (camera.width as f32, camera.height as f32);
    let (fx, fy) = (cx / w, cy / h);
    if !((0.2..=0.8).contains(&fx) && (0.2..=0.8).contains(&fy)) {
        bail!(
            "{}: the image is {}x{} but the principal point of {} is at ({cx:.1}, {cy:.1}) px, \
             {:.0}% / {:.0}% of the width / height instead of near the centre: the calibration is for \
             another image size (use the original image, or rescale the calibration with the image)",
            image.display(),
            camera.width,
            camera.height,
            calib.display(),
            100.0 * fx,
            100.0 * fy
        );
    }
    Ok(())
}

/// The sampler: the bundle's unless `name` is given; `steps` and `guidance` override.
pub(crate) fn resolve_sampler(
    bundle: &Bundle,
    name: Option<SamplerName>,
    steps: Option<usize>,
    guidance: Option<f64>,
) -> Result<SamplerConfig> {
    let base = &bundle.config.sampler;
    let steps = steps.unwrap_or(base.steps);
    if steps == 0 && bundle.config.residual.is_none() {
        bail!(
            "--steps must be at least 1 (0 steps, the mean network alone, needs a residual-diffusion bundle)"
        );
    }
    if steps != 0 {
        check_steps(steps)?;
    }
    let mut cfg = match name {
        None => SamplerConfig {
            steps,
            ..base.clone()
        },
        Some(SamplerName::Ddpm) => SamplerConfig::ddpm(steps),
        Some(SamplerName::Ddim) => SamplerConfig::ddim(steps, 0.0),
        Some(SamplerName::Dpm) => SamplerConfig::dpm_solver_pp_2m(steps),
    };
    cfg.guidance_scale = base.guidance_scale;
    if let Some(g) = guidance {
        check_guidance(g)?;
        cfg.guidance_scale = g;
    }
    if !bundle.is_conditional() && cfg.guidance_scale != 1.0 {
        if guidance.is_some() {
            eprintln!(
                "note: the model is unconditional; --guidance {} has no effect",
                cfg.guidance_scale
            );
        }
        cfg.guidance_scale = 1.0;
    }
    cfg.validate().context("sampler settings")?;
    Ok(cfg)
}

/// The most sampler steps a command accepts: far beyond any useful count (samplers converge in
/// 10-50), and it bounds the time a typo can cost.
pub(crate) const MAX_STEPS: usize = 1000;

/// The largest classifier-free guidance scale accepted. Scales beyond ~10 only amplify the
/// difference of the two branches into saturated garbage (1e300 gave a 633-point scan).
pub(crate) const MAX_GUIDANCE: f64 = 20.0;

/// Refuse a step count outside 1..=[`MAX_STEPS`].
pub(crate) fn check_steps(steps: usize) -> Result<()> {
    if !(1..=MAX_STEPS).contains(&steps) {
        bail!("--steps {steps}: must be between 1 and {MAX_STEPS}");
    }
    Ok(())
}

/// Refuse a guidance scale outside 0..=[`MAX_GUIDANCE`] (0 = the unconditional branch only,
/// 1 = no guidance; negative scales push away from the image).
pub(crate) fn check_guidance(g: f64) -> Result<()> {
    if !(g.is_finite() && (0.0..=MAX_GUIDANCE).contains(&g)) {
        bail!("--guidance {g}: must be a number between 0 and {MAX_GUIDANCE} (1 = no guidance)");
    }
    Ok(())
}

/// The largest number of scans sampled at once by `generate` (about 45 MB each on the bundled
/// model): more are drawn in further batches, so memory does not grow with `--samples`.
pub(crate) const SAMPLE_BATCH: usize = 8;

/// The most scans one `generate` run draws (memory stays bounded either way; this bounds the
/// record and the time a typo can cost).
pub(crate) const MAX_SAMPLES: usize = 100_000;

/// The noise seed of batch `b` of a `--samples` run: batch 0 keeps `seed` (a run of up to
/// [`SAMPLE_BATCH`] samples draws exactly what one batch of all samples drew before batching), later
/// batches a SplitMix64 mix of the seed and the batch index.
pub(crate) fn batch_seed(seed: u64, batch: usize) -> u64 {
    if batch == 0 {
        return seed;
    }
    let mut z = seed ^ (batch as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Whether `name` is a file `generate` writes into its output folder (for `--force` reruns).
pub(crate) fn is_generate_output(name: &str) -> bool {
    if name == "generate.json" || name == "timings.json" {
        return true;
    }
    name.strip_prefix("scan_").is_some_and(|rest| {
        let digits = rest.bytes().take_while(u8::is_ascii_digit).count();
        digits >= 3 && rest[digits..].starts_with(['.', '_'])
    })
}

/// Short name of a sampler kind.
pub(crate) fn sampler_label(cfg: &SamplerConfig) -> String {
    match cfg.kind {
        SamplerKind::Ddpm { .. } => "ddpm".into(),
        SamplerKind::Ddim { eta } => format!("ddim (eta {eta})"),
        SamplerKind::DpmSolverPp2M => "dpm-solver++(2m)".into(),
    }
}

/// Where a bundle came from and its checksums (from its manifest).
#[derive(Debug, Clone, Serialize)]
pub(crate) struct ModelInfo {
    pub(crate) origin: String,
    pub(crate) name: String,
    pub(crate) denoiser_sha256: Option<String>,
    pub(crate) manifest_sha256: Option<String>,
    pub(crate) grid: [usize; 2],
    pub(crate) image_size: [usize; 2],
}

pub(crate) fn model_info(bundle: &Bundle, checkpoint: Option<&Path>) -> ModelInfo {
    let dir = model::model_dir(checkpoint);
    let bytes = std::fs::read(dir.join(MANIFEST_FILE)).ok();
    let manifest: Option<Manifest> = bytes.as_ref().and_then(|b| serde_json::from_slice(b).ok());
    let (rows, cols) = bundle.grid();
    ModelInfo {
        origin: std::fs::canonicalize(&bundle.origin)
            .unwrap_or_else(|_| bundle.origin.clone())
            .display()
            .to_string(),
        name: bundle.config.name.clone(),
        denoiser_sha256: manifest.and_then(|m| m.files.get(DENOISER_FILE).cloned()),
        manifest_sha256: bytes.as_deref().map(sha256_hex),
        grid: [rows, cols],
        image_size: [bundle.config.image_width, bundle.config.image_height],
    }
}

/// Input record for the JSON reports.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct InputInfo {
    pub(crate) image: String,
    pub(crate) image_size: [u32; 2],
    pub(crate) calib: String,
    pub(crate) calib_kind: &'static str,
    pub(crate) camera: String,
}

pub(crate) fn input_info(views: &[ViewInput]) -> Vec<InputInfo> {
    views
        .iter()
        .map(|v| InputInfo {
            image: v.image_path.display().to_string(),
            image_size: [v.image.width(), v.image.height()],
            calib: v.calib_path.display().to_string(),
            calib_kind: v.calib_kind,
            camera: v.camera_name.clone(),
        })
        .collect()
}

/// The views resized to the bundle's input size (bytes and cameras; borrow them as [`CameraView`]s).
pub(crate) fn prepare_views(
    bundle: &Bundle,
    views: &[ViewInput],
) -> Result<Vec<(Vec<u8>, PinholeCamera)>> {
    views
        .iter()
        .map(|v| {
            model::prepare_view(bundle, &v.image, &v.camera)
                .with_context(|| format!("{}", v.image_path.display()))
        })
        .collect()
}

/// Borrowed views of prepared images.
pub(crate) fn camera_views(prepared: &[(Vec<u8>, PinholeCamera)]) -> Vec<CameraView<'_>> {
    prepared
        .iter()
        .map(|(rgb, camera)| CameraView { rgb, camera })
        .collect()
}

/// What was written for one scan.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct ScanRecord {
    pub(crate) file: String,
    pub(crate) points: usize,
    pub(crate) range_pixels: usize,
    pub(crate) points_in_first_image: usize,
}

/// The range preview scaled to the encoding's range.
pub(crate) fn range_preview(bundle: &Bundle) -> RangePreview {
    RangePreview {
        far_m: bundle.config.encoding.max_range_m.max(2.0),
        ..RangePreview::default()
    }
}

/// Writes `STEM.bin`, `STEM.exr`, `STEM_range.png`, `STEM_bev.png` and `STEM_overlay.png` (points on
/// `first` view's full-resolution image) into `dir`.
pub(crate) fn write_scan(
    dir: &Path,
    stem: &str,
    bundle: &Bundle,
    scan: &DecodedScan,
    first: &ViewInput,
) -> Result<(ScanRecord, RangeImage, PointCloud)> {
    let range = model::to_range_image(scan);
    let cloud = model::to_points(bundle, &range)?;
    let sensor = &bundle.config.denoiser.sensor;
    let bin = format!("{stem}.bin");
    write_kitti_bin(&dir.join(&bin), &cloud)?;
    write_range_exr(&dir.join(format!("{stem}.exr")), sensor, &range)?;
    write_png(
        &dir.join(format!("{stem}_range.png")),
        &render_range(&range, &range_preview(bundle)),
    )?;
    write_png(
        &dir.join(format!("{stem}_bev.png")),
        &render_bev(&cloud, &BevOptions::default())?,
    )?;
    let overlay = render_overlay(
        &first.image,
        &first.camera,
        &cloud.xyz,
        &OverlayOptions::default(),
    )?;
    write_png(&dir.join(format!("{stem}_overlay.png")), &overlay.image)?;
    Ok((
        ScanRecord {
            file: bin,
            points: cloud.len(),
            range_pixels: range.num_valid(),
            points_in_first_image: overlay.drawn,
        },
        range,
        cloud,
    ))
}

#[derive(Debug, Serialize)]
struct GenerateReport<'a> {
    command: &'static str,
    veila_version: &'static str,
    inputs: Vec<InputInfo>,
    model: ModelInfo,
    sampler: &'a SamplerConfig,
    sampler_name: String,
    steps: usize,
    guidance: f64,
    seed: u64,
    samples: usize,
    sample_batch: usize,
    scans: Vec<ScanRecord>,
}

/// Wall-clock times of a run: in their own `timings.json`, so that every other output of two
/// identical runs is byte-identical.
#[derive(Debug, Serialize)]
pub(crate) struct Seconds {
    pub(crate) load: f64,
    pub(crate) sampling: f64,
    pub(crate) per_scan: f64,
    pub(crate) writing: f64,
}

fn round3(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}

pub(crate) fn run(args: GenerateArgs) -> Result<()> {
    if !(1..=MAX_SAMPLES).contains(&args.samples) {
        bail!(
            "--samples {}: must be between 1 and {MAX_SAMPLES}",
            args.samples
        );
    }
    // 0 steps is checked against the bundle (residual bundles only) once it is loaded
    if let Some(steps) = args.steps.filter(|&s| s != 0) {
        check_steps(steps)?;
    }
    if let Some(g) = args.guidance {
        check_guidance(g)?;
    }
    let t0 = Instant::now();
    let mut inputs = staging::Inputs::new();
    inputs.extend(&args.rig.images).extend(&args.rig.calibs);
    // the model first: whether 0 sampler steps are allowed depends on it
    let device = model::device()?;
    let bundle = model::load_bundle(args.checkpoint.as_deref(), &device)?;
    let sampler = resolve_sampler(&bundle, args.sampler, args.steps, args.guidance)?;
    let views = load_rig(&args.rig)?;
    let prepared = prepare_views(&bundle, &views)?;
    // inputs are good: only now does the output folder get a staging directory
    let staging = staging::stage_checked(&args.out, args.force, &inputs)?;
    let load_secs = t0.elapsed().as_secs_f64();

    let batches = args.samples.div_ceil(SAMPLE_BATCH);
    let pb = progress::bar((sampler.steps * batches) as u64, "generate"); // <= 1000 * 12500
    pb.set_message(format!(
        "{} scan(s), {}",
        args.samples,
        sampler_label(&sampler)
    ));
    let (mut sampling_secs, mut writing_secs) = (0.0, 0.0);
    let mut records = Vec::new();
    for b in 0..batches {
        let first = b * SAMPLE_BATCH;
        let count = SAMPLE_BATCH.min(args.samples - first);
        let options = GenerateOptions {
            sampler: sampler.clone(),
            samples: count,
            seed: batch_seed(args.seed, b),
            unconditional: false,
        };
        let t = Instant::now();
        let scans = bundle
            .generate(&camera_views(&prepared), &options, |done, total| {
                pb.set_length((total * batches) as u64);
                pb.set_position((b * total + done) as u64);
            })
            .context("sampling")?;
        sampling_secs += t.elapsed().as_secs_f64();
        // each batch is written and dropped before the next is drawn
        let t = Instant::now();
        for (j, scan) in scans.iter().enumerate() {
            let (rec, _, _) = write_scan(
                staging.path(),
                &format!("scan_{:03}", first + j),
                &bundle,
                scan,
                &views[0],
            )?;
            records.push(rec);
        }
        writing_secs += t.elapsed().as_secs_f64();
    }
    pb.finish_and_clear();
    let report = GenerateReport {
        command: "generate",
        veila_version: env!("CARGO_PKG_VERSION"),
        inputs: input_info(&views),
        model: model_info(&bundle, args.checkpoint.as_deref()),
        sampler: &sampler,
        sampler_name: sampler_label(&sampler),
        steps: sampler.steps,
        guidance: sampler.guidance_scale,
        seed: args.seed,
        samples: args.samples,
        sample_batch: SAMPLE_BATCH,
        scans: records,
    };
    let timings = Seconds {
        load: round3(load_secs),
        sampling: round3(sampling_secs),
        per_scan: round3(sampling_secs / args.samples as f64),
        writing: round3(writing_secs),
    };
    veila_data::atomic::write_atomic(
        &staging.path().join("generate.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    veila_data::atomic::write_atomic(
        &staging.path().join("timings.json"),
        serde_json::to_string_pretty(&timings)?.as_bytes(),
    )?;
    staging.commit_owning(is_generate_output)?;

    println!(
        "generated {} scan(s) on the {}x{} grid of model `{}` from {} view(s): {} x {} steps, guidance {}, seed {}",
        args.samples,
        report.model.grid[0],
        report.model.grid[1],
        report.model.name,
        views.len(),
        report.sampler_name,
        sampler.steps,
        sampler.guidance_scale,
        args.seed
    );
    for r in &report.scans {
        println!(
            "  {}: {} points ({} in the first image)",
            r.file, r.points, r.points_in_first_image
        );
    }
    println!(
        "{:.2} s per scan (sampling {:.2} s, loading {:.2} s, writing {:.2} s); wrote {}",
        sampling_secs / args.samples as f64,
        sampling_secs,
        load_secs,
        writing_secs,
        args.out.display()
    );
    Ok(())
}
