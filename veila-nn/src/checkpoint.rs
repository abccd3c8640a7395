//! Checkpoints: a directory with `config.json` (the [`DenoiserConfig`]) and `model.safetensors`.
//!
//! Loading first compares the file's tensors with those the config's model needs and fails with
//! [`Error::CheckpointMismatch`] listing missing, unexpected and mis-shaped tensors by name. Saving
//! writes each file to a temporary name in the same directory and renames it, so a crash never leaves
//! a half-written checkpoint under the final names.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};

use crate::config::DenoiserConfig;
use crate::error::{Error, Result, TensorReport};
use crate::unet::Denoiser;

/// File name of the config inside a checkpoint directory.
pub const CONFIG_FILE: &str = "config.json";
/// File name of the weights inside a checkpoint directory.
pub const WEIGHTS_FILE: &str = "model.safetensors";

/// The tensors (name -> shape) a model builder asks its `VarBuilder` for, found by running it on a
/// recording builder that hands out zeros (see [`crate::encoders::record_tensor_specs`]).
pub fn record_tensors(
    build: impl FnOnce(VarBuilder<'static>) -> Result<()>,
) -> Result<BTreeMap<String, Vec<usize>>> {
    Ok(crate::encoders::record_tensor_specs(build)?
        .into_iter()
        .map(|s| (s.name, s.shape))
        .collect())
}

/// Every parameter tensor the model of `cfg` has, by name, with its shape (sorted by name).
pub fn expected_tensors(cfg: &DenoiserConfig) -> Result<BTreeMap<String, Vec<usize>>> {
    record_tensors(|vb| Denoiser::new(cfg, vb).map(|_| ()))
}

/// Parses safetensors bytes (`path` names them in errors), checks them against `expected` (every
/// tensor present with its shape, nothing else) and converts them to `f32`.
pub fn read_checked_bytes(
    bytes: &[u8],
    path: &Path,
    expected: &BTreeMap<String, Vec<usize>>,
    device: &Device,
) -> Result<HashMap<String, Tensor>> {
    read_checked_scoped(bytes, path, expected, |_| true, DType::F32, device)
}

/// [`read_checked_bytes`] where tensors of the file that `expected` lacks are reported only when
/// `in_scope(name)` is true (and otherwise dropped), converted to `dtype`.
pub(crate) fn read_checked_scoped(
    bytes: &[u8],
    path: &Path,
    expected: &BTreeMap<String, Vec<usize>>,
    in_scope: impl Fn(&str) -> bool,
    dtype: DType,
    device: &Device,
) -> Result<HashMap<String, Tensor>> {
    let tensors =
        candle_core::safetensors::load_buffer(bytes, device).map_err(|e| Error::SafeTensors {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
    let found: BTreeMap<String, Vec<usize>> = tensors
        .iter()
        .map(|(k, v)| (k.clone(), v.dims().to_vec()))
        .collect();
    let mut report = compare_tensors(expected, &found);
    report.unexpected.retain(|n| in_scope(n));
    if !report.is_clean() {
        return Err(Error::CheckpointMismatch {
            path: path.to_path_buf(),
            report,
        });
    }
    tensors
        .into_iter()
        .filter(|(k, _)| expected.contains_key(k))
        .map(|(k, v)| Ok((k, v.to_dtype(dtype)?)))
        .collect()
}

/// Serialises tensors as safetensors bytes, sorted by name and as contiguous `f32` on the CPU, so
/// the same weights always give the same bytes (and the same sha256). `path` names the file in
/// errors.
pub fn safetensors_bytes(tensors: &HashMap<String, Tensor>, path: &Path) -> Result<Vec<u8>> {
    let mut sorted: Vec<(String, Tensor)> = tensors
        .iter()
        .map(|(k, v)| {
            Ok((
                k.clone(),
                v.to_device(&Device::Cpu)?
                    .to_dtype(DType::F32)?
                    .contiguous()?,
            ))
        })
        .collect::<candle_core::Result<_>>()?;
    sorted.sort_by(|a, b| a.0.cmp(&b.0));
    safetensors::serialize(sorted, None).map_err(|e| Error::SafeTensors {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// Lower-case hex sha256 of `bytes` (the sums of the weight manifests).
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Compares what a model needs with what a file holds.
pub fn compare_tensors(
    expected: &BTreeMap<String, Vec<usize>>,
    found: &BTreeMap<String, Vec<usize>>,
) -> TensorReport {
    let mut r = TensorReport::default();
    for (name, shape) in expected {
        match found.get(name) {
            None => r.missing.push(name.clone()),
            Some(s) if s != shape => r.mis_shaped.push((name.clone(), shape.clone(), s.clone())),
            Some(_) => {}
        }
    }
    r.unexpected = found
        .keys()
        .filter(|k| !expected.contains_key(*k))
        .cloned()
        .collect();
    r
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

pub(crate) fn tmp_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(format!(".tmp{}", std::process::id()));
    path.with_file_name(name)
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
    let text = std::fs::read_to_string(&path).map_err(io_err(&path))?;
    let cfg: DenoiserConfig = serde_json::from_str(&text).map_err(|source| Error::Json {
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
    let bytes = std::fs::read(&path).map_err(io_err(&path))?;
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
