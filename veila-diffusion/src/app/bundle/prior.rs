//! A prior for a direct-diffusion bundle: another bundle's mean network, attached so that the
//! sampler starts from its scan ([`BundleConfig::prior`], [`crate::SamplerConfig::start_t`]).
//!
//! The mean network reads the same image features as the denoiser, so the two bundles must share
//! their encoders bit for bit: a conditional model trained on a residual bundle's frozen encoders
//! (`train-default --encoders-from`) takes that bundle's mean network as it is.

use std::path::{Path, PathBuf};

use candle_core::Device;

use super::{
    Bundle, BundleConfig, CONFIG_FILE, DEPTH_FILE, MEAN_FILE, ManifestFolder, PriorConfig,
    SEMANTIC_FILE, read_folder_file,
};
use crate::error::{Error, Result};

/// Writes the bundle folder `out`: the direct-diffusion bundle of `dir` with the mean network of
/// the bundle in `mean_from` (a residual bundle's, or another prior's) as its prior, and
/// `start_t` as its sampler's start level. Returns the new config.
///
/// # Errors
/// `out` is one of the inputs (they are never changed), a bundle does not load, `dir` is a
/// residual or non-diffusion bundle or has an encoder outside its folder, `mean_from` has no mean
/// network, the two differ in their encoders (configs or weights), image size, range grid,
/// range encoding or epipolar sampling, or `start_t` is not in `(0, 1]`. Nothing is written then.
pub fn attach_prior(
    dir: &Path,
    mean_from: &Path,
    start_t: f64,
    out: &Path,
) -> Result<BundleConfig> {
    for input in [dir, mean_from] {
        if same_folder(input, out) {
            return Err(Error::Output {
                path: out.to_path_buf(),
                reason: format!(
                    "is the input bundle {}: write the new bundle to another folder",
                    input.display()
                ),
            });
        }
    }
    let target = Bundle::from_dir(dir, &Device::Cpu)?;
    let source = Bundle::from_dir(mean_from, &Device::Cpu)?;
    let refuse = |path: &Path, reason: String| Error::Checkpoint {
        reason,
        path: path.join(CONFIG_FILE),
    };
    let cfg = &target.config;
    if cfg.residual.is_some() {
        return Err(refuse(
            dir,
            "a residual bundle's denoiser draws residuals, not scans: a prior needs a \
             direct-diffusion bundle"
                .into(),
        ));
    }
    if !cfg.diffusion.objective.is_diffusion() {
        return Err(refuse(
            dir,
            format!(
                "its process is {}: a start level needs a diffusion objective",
                cfg.diffusion.objective.name()
            ),
        ));
    }
    let Some(mean_net) = source.config.mean_net() else {
        return Err(refuse(
            mean_from,
            "has no mean network to attach (neither `residual` nor `prior`)".into(),
        ));
    };
    check_shared(cfg, &source.config).map_err(|what| {
        refuse(
            mean_from,
            format!(
                "its {what} differs from {}'s: the mean network would read other features or \
                 draw on another grid",
                dir.display()
            ),
        )
    })?;
    let mut config = cfg.clone();
    config.prior = Some(PriorConfig {
        mean_net: mean_net.clone(),
    });
    config.sampler.start_t = Some(start_t);
    if let Some(p) = config.provenance.as_object_mut() {
        p.insert(
            "prior".into(),
            serde_json::json!({
                "mean_from": mean_from.display().to_string(),
                "mean_from_manifest_sha256": source.manifest_sha256,
            }),
        );
    }
    config.check(out)?;
    // the encoders' weights must be the same bytes, not only the same shapes
    let mut files: Vec<(&str, Vec<u8>)> = Vec::new();
    for name in config.weight_files() {
        let from = if name == MEAN_FILE { mean_from } else { dir };
        let bytes = read_folder_file(from, name, "bundle")?;
        if [SEMANTIC_FILE, DEPTH_FILE].contains(&name)
            && read_folder_file(mean_from, name, "bundle")? != bytes
        {
            return Err(refuse(
                mean_from,
                format!(
                    "its `{name}` differs from {}'s: the mean network was trained on other \
                     encoder weights",
                    dir.display()
                ),
            ));
        }
        files.push((name, bytes));
    }
    let json = serde_json::to_vec_pretty(&config).map_err(|source| Error::Json {
        path: out.join(CONFIG_FILE),
        source,
    })?;
    let mut folder = ManifestFolder::new(out)?;
    folder.put(CONFIG_FILE, &json)?;
    for (name, bytes) in &files {
        folder.put(name, bytes)?;
    }
    folder.finish()?;
    Ok(config)
}

/// What the mean network shares with the denoiser, by name, when it differs (`Err(name)`).
fn check_shared(a: &BundleConfig, b: &BundleConfig) -> std::result::Result<(), &'static str> {
    let inside = |c: &BundleConfig| {
        [&c.semantic_encoder, &c.depth_encoder]
            .into_iter()
            .flatten()
            .all(|e| !e.kind.is_pretrained())
    };
    if !inside(a) || !inside(b) {
        return Err("encoders (a pretrained one is not attached; small CNNs only)");
    }
    if a.semantic_encoder != b.semantic_encoder {
        return Err("semantic encoder");
    }
    if a.depth_encoder != b.depth_encoder {
        return Err("depth encoder");
    }
    if (a.image_height, a.image_width) != (b.image_height, b.image_width) {
        return Err("image size");
    }
    if a.encoding != b.encoding {
        return Err("range encoding");
    }
    if a.epipolar != b.epipolar {
        return Err("epipolar sampling");
    }
    if a.denoiser.sensor != b.denoiser.sensor {
        return Err("range grid (sensor)");
    }
    Ok(())
}

/// Whether `a` and `b` name the same folder (`b` need not exist).
fn same_folder(a: &Path, b: &Path) -> bool {
    let canon = |p: &Path| -> PathBuf { p.canonicalize().unwrap_or_else(|_| p.to_path_buf()) };
    canon(a) == canon(b)
}
