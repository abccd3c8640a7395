//! Finding and loading model bundles, and the glue between images / scans on disk and the
//! generation pipeline (`veila_diffusion::app`).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use candle_core::Device;
use veila_data::PointCloud;
use veila_data::read_capped::{MAX_JSON_METADATA_BYTES, read_metadata};
use veila_diffusion::app::BundleConfig;
use veila_diffusion::app::bundle::{Bundle, CONFIG_FILE, MANIFEST_FILE};
use veila_diffusion::app::segment::SegmenterModel;
use veila_geom::RangeImage;

/// Environment variable naming the default bundle folder.
pub(crate) const MODEL_ENV: &str = "VEILA_MODEL";

mod embedded {
    // written by build.rs: the files of models/default at build time (empty without the folder)
    include!(concat!(env!("OUT_DIR"), "/embedded_model.rs"));
}

/// The bundled default model in the source tree this binary was built from.
pub(crate) fn bundled_model_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/default")
}

/// The label of the embedded default model (its `origin`).
const EMBEDDED_ORIGIN: &str = "<embedded models/default>";

/// Where a model comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum ModelSource {
    /// A bundle folder.
    Dir(PathBuf),
    /// The default bundle embedded in the binary at build time.
    Embedded,
}

/// Where the model comes from: `--model` (which clap also fills from `$VEILA_MODEL`), else
/// `$VEILA_MODEL`, else the source tree's `models/default` while it exists (a retrained model is
/// used at once), else the copy embedded in the binary (an installed `veila` works anywhere).
/// Embedding was chosen over a folder beside the binary because `cargo install` copies only the
/// binary; the model is a few MiB.
pub(crate) fn model_source(checkpoint: Option<&Path>) -> ModelSource {
    if let Some(p) = checkpoint {
        return ModelSource::Dir(p.to_path_buf());
    }
    if let Some(p) = std::env::var_os(MODEL_ENV).filter(|v| !v.is_empty()) {
        return ModelSource::Dir(PathBuf::from(p));
    }
    let dir = bundled_model_dir();
    if dir.join(MANIFEST_FILE).is_file() || embedded::EMBEDDED_MODEL.is_empty() {
        ModelSource::Dir(dir)
    } else {
        ModelSource::Embedded
    }
}

/// The bytes of the model's `manifest.json`, when it has one.
pub(crate) fn manifest_bytes(checkpoint: Option<&Path>) -> Option<Vec<u8>> {
    match model_source(checkpoint) {
        ModelSource::Dir(dir) => read_metadata(
            &dir.join(MANIFEST_FILE),
            MAX_JSON_METADATA_BYTES,
            "a bundle's manifest.json",
        )
        .ok(),
        ModelSource::Embedded => embedded::EMBEDDED_MODEL
            .iter()
            .find(|(n, _)| *n == MANIFEST_FILE)
            .map(|(_, b)| b.to_vec()),
    }
}

/// The config of the default model embedded in this binary (`None` when it was built without
/// one): what the help texts describe as "the bundled model".
pub(crate) fn bundled_config() -> Option<BundleConfig> {
    let (_, bytes) = embedded::EMBEDDED_MODEL
        .iter()
        .find(|(n, _)| *n == CONFIG_FILE)?;
    serde_json::from_slice(bytes).ok()
}

/// `--device`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum DeviceArg {
    /// The CPU.
    Cpu,
    /// A GPU: `None` for GPU 0, or the launcher's `LOCAL_RANK` in a data-parallel run.
    Cuda(Option<usize>),
}

/// Parses `cpu`, `cuda`, `cuda:N`.
pub(crate) fn parse_device(s: &str) -> std::result::Result<DeviceArg, String> {
    match s {
        "cpu" => Ok(DeviceArg::Cpu),
        "cuda" | "gpu" => Ok(DeviceArg::Cuda(None)),
        _ => s
            .strip_prefix("cuda:")
            .and_then(|n| n.parse::<usize>().ok())
            .map(|n| DeviceArg::Cuda(Some(n)))
            .ok_or_else(|| format!("`{s}`: expected cpu, cuda or cuda:N")),
    }
}

static DEVICE: std::sync::OnceLock<Option<DeviceArg>> = std::sync::OnceLock::new();

/// Records `--device` (once, at start-up).
pub(crate) fn set_device(d: Option<DeviceArg>) {
    let _ = DEVICE.set(d);
}

/// The compute device: `--device` when given; otherwise the first GPU of a CUDA build when one is
/// present, else the CPU. `cuda` in a data-parallel run means the launcher's `LOCAL_RANK`.
pub(crate) fn device() -> Result<Device> {
    let local_rank = || {
        std::env::var("LOCAL_RANK")
            .or_else(|_| std::env::var("SLURM_LOCALID"))
            .ok()
            .and_then(|v| v.parse::<usize>().ok())
    };
    match DEVICE.get().copied().flatten() {
        Some(DeviceArg::Cpu) => Ok(Device::Cpu),
        Some(DeviceArg::Cuda(n)) => {
            let n = n.or_else(local_rank).unwrap_or(0);
            if !cfg!(feature = "cuda") {
                bail!(
                    "--device cuda:{n}: this veila was built without CUDA; build one with `cargo xtask build-cuda` (or `cargo build --release --features cuda` with a CUDA toolkit)"
                );
            }
            Device::new_cuda(n).with_context(|| format!("--device cuda:{n}: no such GPU"))
        }
        None => {
            #[cfg(feature = "cuda")]
            {
                if let Ok(d) = Device::new_cuda(local_rank().unwrap_or(0)) {
                    return Ok(d);
                }
            }
            Ok(Device::Cpu)
        }
    }
}

/// Loads and verifies (sha256 manifest, tensor names and shapes) a bundle.
pub(crate) fn load_bundle(checkpoint: Option<&Path>, device: &Device) -> Result<Bundle> {
    let dir = match model_source(checkpoint) {
        ModelSource::Embedded => {
            return Bundle::from_files(
                embedded::EMBEDDED_MODEL,
                Path::new(EMBEDDED_ORIGIN),
                device,
            )
            .context("loading the embedded default model");
        }
        ModelSource::Dir(dir) => dir,
    };
    // `exists()` is false for any error: a link loop (ELOOP) or a folder that cannot be read
    // (EACCES) would read "no model bundle"; only a missing file is that, the others say why
    match std::fs::metadata(dir.join(MANIFEST_FILE)) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            bail!(
                "cannot read the model bundle at {}: {e} (reading {MANIFEST_FILE})",
                dir.display()
            );
        }
        Ok(_) => {}
        Err(_) => return Err(no_bundle(checkpoint, &dir)),
    }
    Bundle::from_dir(&dir, device).with_context(|| format!("loading model {}", dir.display()))
}

/// The error for a model folder without a `manifest.json`.
fn no_bundle(checkpoint: Option<&Path>, dir: &Path) -> anyhow::Error {
    if checkpoint.is_none() && std::env::var_os(MODEL_ENV).is_none_or(|v| v.is_empty()) {
        return anyhow::anyhow!(
            "no model: this veila was built without models/default embedded and {} does not exist; \
             pass --model DIR or set {MODEL_ENV} to a bundle folder (bundle.json, manifest.json, weights)",
            dir.display()
        );
    }
    anyhow::anyhow!(
        "no model bundle at {} (expected bundle.json, manifest.json and weights; pass --model DIR or set {MODEL_ENV})",
        dir.display()
    )
}

/// The bundled segmenter in the source tree this binary was built from.
pub(crate) fn bundled_segmenter_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/segmenter")
}

/// Loads and verifies a segmenter folder: `dir` when given, else the source tree's
/// `models/segmenter` while it exists, else the copy embedded in the binary.
pub(crate) fn load_segmenter(dir: Option<&Path>, device: &Device) -> Result<SegmenterModel> {
    let dir = match dir {
        Some(d) => d.to_path_buf(),
        None => {
            let d = bundled_segmenter_dir();
            if !d.join(MANIFEST_FILE).is_file() && !embedded::EMBEDDED_SEGMENTER.is_empty() {
                return SegmenterModel::from_files(
                    embedded::EMBEDDED_SEGMENTER,
                    Path::new("<embedded models/segmenter>"),
                    device,
                )
                .context("loading the embedded segmenter");
            }
            d
        }
    };
    match std::fs::metadata(dir.join(MANIFEST_FILE)) {
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => bail!(
            "no segmenter at {} (expected segmenter.json, segmenter.safetensors and manifest.json; pass --model DIR)",
            dir.display()
        ),
        Err(e) => bail!(
            "cannot read the segmenter at {}: {e} (reading {MANIFEST_FILE})",
            dir.display()
        ),
    }
    SegmenterModel::from_dir(&dir, device)
        .with_context(|| format!("loading segmenter {}", dir.display()))
}

/// The points of a range image on the bundle's grid, in its frame (one per return): for scans that
/// are not generated (the demo's baselines); generated scans come with their points.
pub(crate) fn to_points(bundle: &Bundle, range: &RangeImage) -> Result<PointCloud> {
    Ok(veila_diffusion::app::scan_points(&bundle.config, range)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_model_is_the_source_trees_default() {
        let dir = bundled_model_dir();
        if !dir.join(MANIFEST_FILE).is_file() {
            assert!(embedded::EMBEDDED_MODEL.is_empty());
            return;
        }
        // every file of the folder is embedded byte for byte (build.rs reran on changes)
        let manifest: veila_diffusion::app::bundle::Manifest =
            serde_json::from_slice(&std::fs::read(dir.join(MANIFEST_FILE)).unwrap()).unwrap();
        for name in manifest
            .files
            .keys()
            .map(String::as_str)
            .chain([MANIFEST_FILE])
        {
            let (_, bytes) = embedded::EMBEDDED_MODEL
                .iter()
                .find(|(n, _)| *n == name)
                .unwrap_or_else(|| panic!("{name} is not embedded"));
            assert_eq!(*bytes, std::fs::read(dir.join(name)).unwrap(), "{name}");
        }
        let b = Bundle::from_files(
            embedded::EMBEDDED_MODEL,
            Path::new(EMBEDDED_ORIGIN),
            &Device::Cpu,
        )
        .unwrap();
        assert_eq!(b.config.name, "default");
        // the help texts' "bundled model" is this one
        assert_eq!(bundled_config().unwrap().sampler, b.config.sampler);
        assert_eq!(manifest_bytes(Some(&dir)), manifest_bytes(None));
    }

    #[test]
    fn the_embedded_segmenter_is_the_source_trees() {
        let dir = bundled_segmenter_dir();
        if !dir.join(MANIFEST_FILE).is_file() {
            assert!(embedded::EMBEDDED_SEGMENTER.is_empty());
            return;
        }
        for (name, bytes) in embedded::EMBEDDED_SEGMENTER {
            assert_eq!(*bytes, std::fs::read(dir.join(name)).unwrap(), "{name}");
        }
        assert_eq!(embedded::EMBEDDED_SEGMENTER.len(), 3);
        let m = SegmenterModel::from_files(
            embedded::EMBEDDED_SEGMENTER,
            Path::new("<embedded>"),
            &Device::Cpu,
        )
        .unwrap();
        assert_eq!(m.config.network.rows, 32);
        assert_eq!(m.config.network.cols, 256);
    }
}
