//! Finding and loading model bundles, and the glue between images / scans on disk and the
//! generation pipeline (`veila_diffusion::pipeline`).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use candle_core::Device;
use veila_data::PointCloud;
use veila_data::image::{RgbImage, imageops};
use veila_diffusion::DecodedScan;
use veila_diffusion::bundle::Bundle;
use veila_geom::{PinholeCamera, RangeImage, RayTable};

/// Environment variable naming the default bundle folder.
pub(crate) const MODEL_ENV: &str = "VEILA_MODEL";

/// The bundled default model in the source tree this binary was built from.
pub(crate) fn bundled_model_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/default")
}

/// Where the model comes from: `--checkpoint`, else `$VEILA_MODEL`, else the bundled default.
pub(crate) fn model_dir(checkpoint: Option<&Path>) -> PathBuf {
    if let Some(p) = checkpoint {
        return p.to_path_buf();
    }
    if let Some(p) = std::env::var_os(MODEL_ENV).filter(|v| !v.is_empty()) {
        return PathBuf::from(p);
    }
    bundled_model_dir()
}

/// The compute device: CUDA 0 when built with `--features cuda` and a GPU is present, else the CPU.
pub(crate) fn device() -> Result<Device> {
    #[cfg(feature = "cuda")]
    {
        if let Ok(d) = Device::new_cuda(0) {
            return Ok(d);
        }
    }
    Ok(Device::Cpu)
}

/// Loads and verifies (sha256 manifest, tensor names and shapes) a bundle.
pub(crate) fn load_bundle(checkpoint: Option<&Path>, device: &Device) -> Result<Bundle> {
    let dir = model_dir(checkpoint);
    if !dir.join(veila_diffusion::bundle::MANIFEST_FILE).exists() {
        bail!(
            "no model bundle at {} (expected bundle.json, manifest.json and weights; pass --checkpoint DIR or set {MODEL_ENV})",
            dir.display()
        );
    }
    Bundle::from_dir(&dir, device).with_context(|| format!("loading model {}", dir.display()))
}

/// An image and its camera resized to the bundle's input size (triangle filter, antialiased).
pub(crate) fn prepare_view(
    bundle: &Bundle,
    image: &RgbImage,
    camera: &PinholeCamera,
) -> Result<(Vec<u8>, PinholeCamera)> {
    let (w, h) = (
        bundle.config.image_width as u32,
        bundle.config.image_height as u32,
    );
    if (image.width(), image.height()) != (camera.width, camera.height) {
        bail!(
            "the image is {}x{} but the calibration's camera is {}x{}",
            image.width(),
            image.height(),
            camera.width,
            camera.height
        );
    }
    let small = imageops::resize(image, w, h, imageops::FilterType::Triangle);
    let cam = camera
        .resized(w, h)
        .context("the model's image size has a zero dimension")?;
    Ok((small.into_raw(), cam))
}

/// A decoded scan as a range image on the bundle's grid.
pub(crate) fn to_range_image(scan: &DecodedScan) -> RangeImage {
    scan.clone().into_range_image()
}

/// The points of a generated range image in the LiDAR frame (one per return).
pub(crate) fn to_points(bundle: &Bundle, range: &RangeImage) -> Result<PointCloud> {
    let rays = RayTable::new(&bundle.config.denoiser.sensor)?;
    let un = rays.unproject(range)?;
    Ok(PointCloud {
        xyz: un.points,
        intensity: un.intensity,
        ring: None,
        label: None,
    })
}
