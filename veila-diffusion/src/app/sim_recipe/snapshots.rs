//! Learning-curve snapshots of a run of the recipe ([`super::SimRun::snapshot_every`]): every so
//! many denoiser updates, a model bundle of the checkpoint's EMA weights with the encoders of
//! `encoders_from`, beside the run's checkpoints (for `cargo xtask bench-realism --model`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};

use super::SimRecipe;
use crate::app::bundle::{Bundle, BundleConfig, DENOISER_FILE, DEPTH_FILE, SEMANTIC_FILE};
use crate::error::{Error, Result, invalid};
use crate::trainer::EMA_FILE;

/// What a snapshot needs besides the checkpoint's EMA weights.
#[derive(Debug)]
pub(super) struct Snapshots {
    /// Denoiser updates between snapshots.
    pub(super) every: u64,
    dir: PathBuf,
    config: BundleConfig,
    /// The encoders' weights by bundle file (none for an unconditional model).
    encoders: HashMap<&'static str, HashMap<String, Tensor>>,
}

/// The tensors of a safetensors file, read through veila-nn's capped weights reader.
fn read_tensors(path: &Path) -> Result<HashMap<String, Tensor>> {
    let bytes = veila_nn::checkpoint::read_weights_file(path)?;
    candle_core::safetensors::load_buffer(&bytes, &Device::Cpu).map_err(|e| Error::Checkpoint {
        reason: format!("reading safetensors: {e}"),
        path: path.to_path_buf(),
    })
}

impl Snapshots {
    /// The snapshots of `recipe`'s run of `cfg` every `every` updates, into `work/snapshots`:
    /// refused for the residual method (its bundle needs the finished mean network) and for
    /// encoders trained in the run (a snapshot takes them from `encoders_from`).
    pub(super) fn plan(
        recipe: &SimRecipe,
        cfg: &BundleConfig,
        work: &Path,
        every: u64,
    ) -> Result<Self> {
        if every == 0 || !every.is_multiple_of(recipe.checkpoint_every.max(1)) {
            return Err(invalid(
                "snapshot_every",
                format!(
                    "{every} must be a positive multiple of checkpoint_every {}",
                    recipe.checkpoint_every
                ),
            ));
        }
        if cfg.residual.is_some() {
            return Err(invalid(
                "snapshot_every",
                "the residual method's bundle needs its finished mean network",
            ));
        }
        let mut encoders = HashMap::new();
        if cfg.denoiser.conditioning.is_some() {
            let Some(dir) = &recipe.encoders_from else {
                return Err(invalid(
                    "snapshot_every",
                    "a conditional model's snapshots need `encoders_from`",
                ));
            };
            for file in [SEMANTIC_FILE, DEPTH_FILE] {
                if cfg.weight_files().contains(&file) {
                    encoders.insert(file, read_tensors(&dir.join(file))?);
                }
            }
        }
        Ok(Self {
            every,
            dir: work.join("snapshots"),
            config: cfg.clone(),
            encoders,
        })
    }

    /// Writes the snapshot of update `step` from its checkpoint folder; returns the bundle folder.
    pub(super) fn write(&self, step: u64, checkpoint: &Path) -> Result<PathBuf> {
        let mut weights = self.encoders.clone();
        weights.insert(DENOISER_FILE, read_tensors(&checkpoint.join(EMA_FILE))?);
        let mut config = self.config.clone();
        config.provenance = serde_json::json!({
            "snapshot_of_step": step,
            "trained_by": "cargo xtask train-default",
        });
        let out = self.dir.join(format!("step-{step:010}"));
        Bundle::save(&out, &config, &weights)?;
        Ok(out)
    }
}
