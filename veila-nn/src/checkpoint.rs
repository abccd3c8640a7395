//! Checkpoints: a directory with `config.json` (the [`DenoiserConfig`]) and `model.safetensors`.
//!
//! Loading first compares the file's tensors with those the config's model needs and fails with
//! [`Error::CheckpointMismatch`] listing missing, unexpected and mis-shaped tensors by name. Saving
//! writes each file to a temporary name in the same directory and renames it, so a crash never leaves
//! a half-written checkpoint under the final names.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder, VarMap};

use crate::config::DenoiserConfig;
use crate::error::{Error, Result, TensorReport};
use crate::unet::Denoiser;

/// File name of the config inside a checkpoint directory.
pub const CONFIG_FILE: &str = "config.json";
/// File name of the weights inside a checkpoint directory.
pub const WEIGHTS_FILE: &str = "model.safetensors";

/// Records every tensor a model asks for (name and shape) and hands out zeros.
struct RecordingBackend {
    seen: Mutex<BTreeMap<String, Vec<usize>>>,
}

impl SimpleBackend for RecordingBackend {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _h: Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        if let Ok(mut seen) = self.seen.lock() {
            seen.insert(name.to_string(), s.dims().to_vec());
        }
        Tensor::zeros(s, dtype, dev)
    }
    fn get_unchecked(
        &self,
        name: &str,
        _dtype: DType,
        _dev: &Device,
    ) -> candle_core::Result<Tensor> {
        candle_core::bail!("recording backend cannot serve {name} without a shape")
    }
    fn contains_tensor(&self, _name: &str) -> bool {
        true
    }
}

/// Every parameter tensor the model of `cfg` has, by name, with its shape (sorted by name).
pub fn expected_tensors(cfg: &DenoiserConfig) -> Result<BTreeMap<String, Vec<usize>>> {
    let backend = std::sync::Arc::new(RecordingBackend {
        seen: Mutex::new(BTreeMap::new()),
    });
    struct Shared(std::sync::Arc<RecordingBackend>);
    impl SimpleBackend for Shared {
        fn get(
            &self,
            s: Shape,
            n: &str,
            h: Init,
            d: DType,
            dev: &Device,
        ) -> candle_core::Result<Tensor> {
            self.0.get(s, n, h, d, dev)
        }
        fn get_unchecked(&self, n: &str, d: DType, dev: &Device) -> candle_core::Result<Tensor> {
            self.0.get_unchecked(n, d, dev)
        }
        fn contains_tensor(&self, n: &str) -> bool {
            self.0.contains_tensor(n)
        }
    }
    // Build on a tiny-memory dtype: only shapes matter.
    let vb = VarBuilder::from_backend(Box::new(Shared(backend.clone())), DType::F32, Device::Cpu);
    Denoiser::new(cfg, vb)?;
    let seen = backend
        .seen
        .lock()
        .map_err(|_| Error::Config("poisoned lock".into()))?;
    Ok(seen.clone())
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

fn tmp_path(path: &Path) -> PathBuf {
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
    let tensors =
        candle_core::safetensors::load_buffer(&bytes, device).map_err(|e| Error::SafeTensors {
            path: path.clone(),
            message: e.to_string(),
        })?;
    let found: BTreeMap<String, Vec<usize>> = tensors
        .iter()
        .map(|(k, v)| (k.clone(), v.dims().to_vec()))
        .collect();
    let report = compare_tensors(&expected_tensors(&cfg)?, &found);
    if !report.is_clean() {
        return Err(Error::CheckpointMismatch { path, report });
    }
    let tensors = tensors
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
