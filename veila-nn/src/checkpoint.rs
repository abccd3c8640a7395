//! Checkpoints: a directory with `config.json` (the [`DenoiserConfig`]) and `model.safetensors`.
//!
//! Loading first compares the file's tensors with those the config's model needs and fails with
//! [`Error::CheckpointMismatch`] listing missing, unexpected and mis-shaped tensors by name. Saving
//! writes each file to a temporary name in the same directory and renames it, so a crash never leaves
//! a half-written checkpoint under the final names.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};

use crate::config::DenoiserConfig;
use crate::error::{Error, Result};
use crate::unet::Denoiser;
use crate::weights::tmp_path;
pub use crate::weights::{
    MAX_WEIGHTS_FILE_BYTES, compare_tensors, read_checked_bytes, read_checked_float_bytes,
    read_weights_file, record_tensors, safetensors_bytes, sha256_hex,
};

/// File name of the config inside a checkpoint directory.
pub const CONFIG_FILE: &str = "config.json";
/// File name of the weights inside a checkpoint directory.
pub const WEIGHTS_FILE: &str = "model.safetensors";

/// Every parameter tensor the model of `cfg` has, by name, with its shape (sorted by name).
pub fn expected_tensors(cfg: &DenoiserConfig) -> Result<BTreeMap<String, Vec<usize>>> {
    record_tensors(|vb| Denoiser::new(cfg, vb).map(|_| ()))
}

/// Number of scalar parameters of the model of `cfg`.
pub fn parameter_count(cfg: &DenoiserConfig) -> Result<usize> {
    Ok(expected_tensors(cfg)?
        .values()
        .map(|s| s.iter().product::<usize>())
        .sum())
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Writes `cfg` and `tensors` into the checkpoint directory `dir` (created if needed), atomically per
/// file. The tensors must match the config's model exactly (checked before anything is written).
pub fn save_checkpoint(
    dir: &Path,
    cfg: &DenoiserConfig,
    tensors: &HashMap<String, Tensor>,
) -> Result<()> {
    let found: BTreeMap<String, Vec<usize>> = tensors
        .iter()
        .map(|(k, v)| (k.clone(), v.dims().to_vec()))
        .collect();
    let report = compare_tensors(&expected_tensors(cfg)?, &found);
    let weights = dir.join(WEIGHTS_FILE);
    if !report.is_clean() {
        return Err(Error::CheckpointMismatch {
            path: weights,
            report,
        });
    }
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let config = dir.join(CONFIG_FILE);
    let json = serde_json::to_string_pretty(cfg).map_err(|source| Error::Json {
        path: config.clone(),
        source,
    })?;
    let tmp_w = tmp_path(&weights);
    let contiguous: HashMap<String, Tensor> = tensors
        .iter()
        .map(|(k, v)| Ok((k.clone(), v.contiguous()?)))
        .collect::<candle_core::Result<_>>()?;
    candle_core::safetensors::save(&contiguous, &tmp_w).map_err(|e| Error::SafeTensors {
        path: weights.clone(),
        message: e.to_string(),
    })?;
    let tmp_c = tmp_path(&config);
    std::fs::write(&tmp_c, json).map_err(io_err(&config))?;
    std::fs::rename(&tmp_w, &weights).map_err(io_err(&weights))?;
    std::fs::rename(&tmp_c, &config).map_err(io_err(&config))?;
    Ok(())
}

/// Saves the variables of a [`VarMap`] (e.g. a model being trained) as a checkpoint.
pub fn save_varmap(dir: &Path, cfg: &DenoiserConfig, varmap: &VarMap) -> Result<()> {
    let tensors: HashMap<String, Tensor> = {
        let data = varmap
            .data()
            .lock()
            .map_err(|_| Error::Config("poisoned varmap lock".into()))?;
        data.iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect()
    };
    save_checkpoint(dir, cfg, &tensors)
}

/// Reads `config.json` of a checkpoint directory.
pub fn read_config(dir: &Path) -> Result<DenoiserConfig> {
    let path = dir.join(CONFIG_FILE);
    let text = crate::weights::read_capped(
        &path,
        crate::weights::MAX_MODEL_JSON_BYTES,
        "a checkpoint config",
    )?;
    let cfg: DenoiserConfig = serde_json::from_slice(&text).map_err(|source| Error::Json {
        path: path.clone(),
        source,
    })?;
    cfg.validate()
        .map_err(|e| Error::Config(format!("{e} (in {})", path.display())))?;
    Ok(cfg)
}

/// Reads and verifies a checkpoint: its config and its tensors (on `device`, converted to `dtype`).
/// Fails with [`Error::CheckpointMismatch`] when the tensors do not fit the config's model.
pub fn read_checkpoint(
    dir: &Path,
    dtype: DType,
    device: &Device,
) -> Result<(DenoiserConfig, HashMap<String, Tensor>)> {
    let cfg = read_config(dir)?;
    let path = dir.join(WEIGHTS_FILE);
    let bytes = read_weights_file(&path)?;
    let tensors = read_checked_bytes(&bytes, &path, &expected_tensors(&cfg)?, device)?
        .into_iter()
        .map(|(k, v)| Ok((k, v.to_dtype(dtype)?)))
        .collect::<candle_core::Result<HashMap<_, _>>>()?;
    Ok((cfg, tensors))
}

/// Loads a checkpoint directory into a ready-to-run [`Denoiser`].
pub fn load_denoiser(dir: &Path, dtype: DType, device: &Device) -> Result<Denoiser> {
    let (cfg, tensors) = read_checkpoint(dir, dtype, device)?;
    Denoiser::new(&cfg, VarBuilder::from_tensors(tensors, dtype, device))
}

/// Loads a checkpoint's weights into the trainable variables of `varmap` (which must already hold the
/// config's model, e.g. built with [`crate::seeded_var_builder`]), for resuming training.
pub fn load_into_varmap(
    dir: &Path,
    cfg: &DenoiserConfig,
    varmap: &mut VarMap,
    device: &Device,
) -> Result<()> {
    let (file_cfg, tensors) = read_checkpoint(dir, DType::F32, device)?;
    if &file_cfg != cfg {
        return Err(Error::Config(format!(
            "the checkpoint's config differs from the model's: {}",
            dir.join(CONFIG_FILE).display()
        )));
    }
    for (k, v) in tensors {
        varmap.set_one(&k, &v)?;
    }
    Ok(())
}
