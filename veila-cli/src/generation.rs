//! What `generate` and `edit` share: the camera-rig and sampler arguments, the model and input
//! records of their JSON reports, and the files written per scan. A shared CLI module, so that no
//! command imports another.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
use serde::Serialize;
use veila_data::image_io::write_png;
use veila_data::ply::write_ply_rgb;
use veila_data::range_exr::write_range_exr;
use veila_data::scan::write_kitti_bin;
use veila_data::vis::render::{
    BevOptions, OverlayOptions, RangePreview, render_bev, render_overlay, render_range,
};
use veila_diffusion::app::bundle::{Bundle, DENOISER_FILE, Manifest, sha256_hex};
use veila_diffusion::app::{
    GenerateOptions, RigView, SamplerChoice, Scan, load_view, point_colours,
};
use veila_diffusion::{SamplerConfig, SamplerName, Spacing};

use crate::model;

/// The camera rig: images, calibration and which camera of the calibration each image is.
#[derive(Debug, Args)]
pub(crate) struct RigArgs {
    /// Camera image (PNG or JPEG); repeat once per camera of the rig.
    // required: each command says so with a group (`generate --frames` takes a folder instead)
    #[arg(long = "image", value_name = "IMG", requires = "calibs")]
    pub(crate) images: Vec<PathBuf>,
    /// Calibration: KITTI object calib/NNNNNN.txt (P2, R0_rect, Tr_velo_to_cam), KITTI odometry /
    /// SemanticKITTI calib.txt (P2, Tr) or a nuScenes per-sample JSON. Give it once for every image
    /// or once per image. Calibrations carry no image size: each camera takes its image's size, so
    /// give the original images (a resized image is rejected by a principal-point check).
    #[arg(long = "calib", value_name = "CALIB", requires = "images")]
    pub(crate) calibs: Vec<PathBuf>,
    /// Which camera of the calibration each image shows: the KITTI projection matrix index (0-3,
    /// default 2 = image_2) or the nuScenes channel (default CAM_FRONT). Once per image.
    #[arg(long = "camera", value_name = "N")]
    pub(crate) cameras: Vec<String>,
}

/// `--sampler`'s parser: the choices (with their help) are the library's one list,
/// [`SamplerName::ALL`].
pub(crate) fn sampler_parser() -> impl TypedValueParser<Value = SamplerName> {
    PossibleValuesParser::new(
        SamplerName::ALL.map(|n| PossibleValue::new(n.as_str()).help(n.help())),
    )
    .try_map(|name| name.parse::<SamplerName>())
}

/// `--spacing`'s parser: the choices (with their help) are the library's one list,
/// [`Spacing::ALL`].
pub(crate) fn spacing_parser() -> impl TypedValueParser<Value = Spacing> {
    PossibleValuesParser::new(Spacing::ALL.map(|s| PossibleValue::new(s.as_str()).help(s.help())))
        .try_map(|name| name.parse::<Spacing>())
}

/// Reads every image and its camera (errors name the file and the problem).
pub(crate) fn load_rig(rig: &RigArgs) -> Result<Vec<RigView>> {
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
        views.push(load_view(
            image_path,
            calib_path,
            rig.cameras.get(i).map(String::as_str),
        )?);
    }
    Ok(views)
}

/// The sampler: the bundle's unless `--sampler` is given; `--spacing`, `--steps`, `--guidance`
/// and `--start-t` override (the library's [`SamplerChoice::resolve`], which the Python door and
/// the benchmarks share; a bundle's start level stays with another sampler). The flags' parsers
/// hold them to the library's bounds, and the bundle's own values were checked against the same
/// bounds when it was loaded (an error there names `bundle.json` and the field); what depends on
/// the bundle is checked by [`GenerateOptions::check`](veila_diffusion::app::GenerateOptions::check).
pub(crate) fn resolve_sampler(bundle: &Bundle, flags: SamplerChoice) -> SamplerConfig {
    if flags.ignores_guidance(bundle) {
        eprintln!(
            "note: the model is unconditional; --guidance {} has no effect",
            flags.guidance.unwrap_or(1.0)
        );
    }
    flags.resolve(bundle)
}

/// `options` checked against `bundle` before any work (the library's check; its error names the
/// field, this the flags and the model).
pub(crate) fn check_options(options: &GenerateOptions, bundle: &Bundle) -> Result<()> {
    options.check(bundle).with_context(|| {
        format!(
            "the sampler and residual-weight flags with model `{}`",
            bundle.origin.display()
        )
    })
}

/// The largest number of scans sampled at once by `generate` (about 45 MB each on the bundled
/// model): more are drawn in further batches (`GenerateOptions::batches`), so memory does not grow
/// with `--samples`.
pub(crate) const SAMPLE_BATCH: usize = 8;

/// The most scans one `generate` run draws (memory stays bounded either way; this bounds the
/// record and the time a typo can cost).
pub(crate) const MAX_SAMPLES: usize = 100_000;

/// The bundled model's sampler in words (`ddpm, 16 steps, guidance 1`), read from the bundle
/// this binary embeds, so that the help texts say what the bundle says.
fn bundled_sampler_words() -> Option<String> {
    let s = model::bundled_config()?.sampler;
    Some(format!(
        "{}, {} steps, guidance {}",
        s.kind, s.steps, s.guidance_scale
    ))
}

/// `--help` of `generate`'s `--sampler`.
pub(crate) fn sampler_help() -> String {
    match bundled_sampler_words() {
        Some(w) => format!("Sampler (default: the bundle's; the bundled model's is {w})"),
        None => "Sampler (default: the bundle's)".into(),
    }
}

/// `--help` of `edit`'s `--sampler`: inpainting takes the bundle's sampler too, with DDIM in place
/// of a multistep solver.
pub(crate) fn inpainting_sampler_help() -> String {
    let bundled = bundled_sampler_words()
        .map(|w| format!("; the bundled model's is {w}"))
        .unwrap_or_default();
    format!(
        "Sampler: ddpm or ddim (default: the bundle's{bundled}). A bundle that samples with dpm, a multistep solver that cannot follow RePaint's jumps, inpaints with ddim (eta 0) instead"
    )
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
    let bytes = model::manifest_bytes(checkpoint);
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

pub(crate) fn input_info(views: &[RigView]) -> Vec<InputInfo> {
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

/// Writes `STEM.bin`, `STEM.ply` (binary little-endian: x, y, z, intensity, and red, green, blue
/// from the `first` view's image where a point falls in it, else a grey of its intensity),
/// `STEM.exr`, `STEM_range.png`, `STEM_bev.png` and `STEM_overlay.png` (points on `first` view's
/// full-resolution image) of `scan` into `dir`.
pub(crate) fn write_scan(
    dir: &Path,
    stem: &str,
    bundle: &Bundle,
    scan: &Scan,
    first: &RigView,
) -> Result<ScanRecord> {
    let (cloud, range) = (&scan.points, &scan.range);
    let sensor = &bundle.config.denoiser.sensor;
    let bin = format!("{stem}.bin");
    write_kitti_bin(&dir.join(&bin), cloud)?;
    write_ply_rgb(
        &dir.join(format!("{stem}.ply")),
        cloud,
        &point_colours(first, cloud),
    )?;
    write_range_exr(&dir.join(format!("{stem}.exr")), sensor, range)?;
    write_png(
        &dir.join(format!("{stem}_range.png")),
        &render_range(range, &range_preview(bundle)),
    )?;
    write_png(
        &dir.join(format!("{stem}_bev.png")),
        &render_bev(cloud, &BevOptions::default())?,
    )?;
    let overlay = render_overlay(
        &first.image,
        &first.camera,
        &cloud.xyz,
        &OverlayOptions::default(),
    )?;
    write_png(&dir.join(format!("{stem}_overlay.png")), &overlay.image)?;
    Ok(ScanRecord {
        file: bin,
        points: cloud.len(),
        range_pixels: range.num_valid(),
        points_in_first_image: overlay.drawn,
    })
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

pub(crate) fn round3(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}
