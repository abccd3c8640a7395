//! Atomic checkpoints.
//!
//! A checkpoint is a directory `step-<10 digits>/` holding
//!
//! * `model.safetensors`: the training weights, named as in the model's `VarMap`;
//! * `ema.safetensors`: the EMA weights under the same names (load these for sampling);
//! * `optimizer.safetensors`: AdamW moments `m.<name>`, `v.<name>`;
//! * `state.json`: [`CheckpointState`] (step, optimizer counter, RNG position, configs).
//!
//! It is written into a hidden temporary directory beside the final one and renamed into place,
//! so a crash never leaves a partial checkpoint under a `step-*` name. It is read back with the
//! reader the caller hands in ([`TensorFileReader`]), which is told the exact names and shapes
//! the model needs; the application's applies the checks a model bundle's weights get.

use std::collections::{BTreeMap, HashMap};
use std::fs;
use std::path::{Path, PathBuf};

use candle_core::Tensor;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::{TrainConfig, Trainer};
use crate::denoiser::Denoiser;
use crate::error::{Error, Result};
use crate::objective::DiffusionConfig;

const FORMAT_VERSION: u32 = 1;
pub(crate) const MODEL_FILE: &str = "model.safetensors";
/// The EMA weights' file of a checkpoint (load these for sampling).
pub const EMA_FILE: &str = "ema.safetensors";
pub(crate) const OPT_FILE: &str = "optimizer.safetensors";
pub(crate) const STATE_FILE: &str = "state.json";

/// Position of the trainer's ChaCha8 stream.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RngState {
    /// The 32-byte seed, hex encoded.
    pub seed_hex: String,
    /// Stream id.
    pub stream: u64,
    /// Word position, decimal (a `u128`).
    pub word_pos: String,
}

impl RngState {
    /// Captures `rng`.
    pub fn capture(rng: &ChaCha8Rng) -> Self {
        Self {
            seed_hex: rng.get_seed().iter().map(|b| format!("{b:02x}")).collect(),
            stream: rng.get_stream(),
            word_pos: rng.get_word_pos().to_string(),
        }
    }

    /// Rebuilds the RNG at the captured position.
    pub fn restore(&self) -> Option<ChaCha8Rng> {
        use rand::SeedableRng;
        if self.seed_hex.len() != 64 {
            return None;
        }
        let mut seed = [0u8; 32];
        for (i, b) in seed.iter_mut().enumerate() {
            *b = u8::from_str_radix(self.seed_hex.get(2 * i..2 * i + 2)?, 16).ok()?;
        }
        let mut rng = ChaCha8Rng::from_seed(seed);
        rng.set_stream(self.stream);
        rng.set_word_pos(self.word_pos.parse().ok()?);
        Some(rng)
    }
}

/// The JSON part of a checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointState {
    /// Layout version (1).
    pub format_version: u32,
    /// Updates done.
    pub step: u64,
    /// Updates skipped so far.
    pub skipped_steps: u64,
    /// AdamW step counter.
    pub optimizer_steps: usize,
    /// Trainer RNG position.
    pub rng: RngState,
    /// Training settings at save time.
    pub train_config: TrainConfig,
    /// The diffusion process (must match on resume).
    pub diffusion_config: DiffusionConfig,
    /// Wall seconds spent in [`Trainer::fit`] since step [`Self::clock_from_step`], summed over
    /// every run that resumed this one (checkpoint writing and batch assembly included).
    #[serde(default)]
    pub train_seconds: f64,
    /// The step the clock started at: 0 for a run timed from its start, later for a run
    /// begun by a build that kept no clock.
    #[serde(default)]
    pub clock_from_step: Option<u64>,
}

fn io<'a>(action: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> Error + 'a {
    move |source| Error::Io {
        action,
        path: path.to_path_buf(),
        source,
    }
}

/// Cap of the JSON a checkpoint folder holds (`run.json`, `state.json`): a few KiB in practice.
/// The same cap as `veila-data`'s for JSON metadata.
pub const MAX_STATE_JSON_BYTES: u64 = 64 << 20;

/// The text of a checkpoint's JSON file `path` (`kind` names it in errors), read the way
/// `veila-data`'s `read_capped` reads metadata, which this crate's core does not depend on: only a
/// regular file after following links (a link to `/dev/zero` or a FIFO would never end), checked
/// before it is opened and again on the open file, at most [`MAX_STATE_JSON_BYTES`] of it.
fn read_state_text(path: &Path, kind: &str) -> Result<String> {
    use std::io::Read;
    let refuse = |what: String| bad(path, format!("{kind} {what}"));
    let check = |meta: &fs::Metadata| {
        if !meta.is_file() {
            return Err(refuse("is not a regular file".into()));
        }
        if meta.len() > MAX_STATE_JSON_BYTES {
            return Err(refuse(format!(
                "has {} bytes, more than the cap of {MAX_STATE_JSON_BYTES}",
                meta.len()
            )));
        }
        Ok(())
    };
    check(&fs::metadata(path).map_err(io("reading", path))?)?;
    let file = fs::File::open(path).map_err(io("reading", path))?;
    check(&file.metadata().map_err(io("reading", path))?)?;
    let mut text = String::new();
    file.take(MAX_STATE_JSON_BYTES + 1)
        .read_to_string(&mut text)
        .map_err(io("reading", path))?;
    if text.len() as u64 > MAX_STATE_JSON_BYTES {
        return Err(refuse("grew past its cap while it was read".into()));
    }
    Ok(text)
}

fn bad(path: &Path, reason: impl Into<String>) -> Error {
    Error::Checkpoint {
        reason: reason.into(),
        path: path.to_path_buf(),
    }
}

pub(crate) fn save_tensors(map: &HashMap<String, Tensor>, path: &Path) -> Result<()> {
    // a failed write (a full disk) is an I/O error, not a bad checkpoint
    candle_core::safetensors::save(map, path).map_err(|e| match e {
        candle_core::Error::Io(source) => io("writing checkpoint", path)(source),
        e => io("writing checkpoint", path)(std::io::Error::other(e.to_string())),
    })?;
    fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(io("syncing", path))
}

/// Reads one tensor file of a checkpoint: the file at `path` must hold exactly `expected`
/// (name -> shape), its values converted to `dtype` on `device`. The generic core takes the reader
/// from its caller, which decides how strictly a file is checked; the application's is
/// `app::nn::read_checkpoint_tensors` (the checks a model bundle's weights get). A missing
/// file should be an [`Error::Checkpoint`] saying so.
pub type TensorFileReader = fn(
    &Path,
    &BTreeMap<String, Vec<usize>>,
    candle_core::DType,
    &candle_core::Device,
) -> Result<HashMap<String, Tensor>>;

/// The checkpoint directory name for `step`.
/// Name of the run record [`claim_checkpoint_dir`] keeps in a checkpoint folder.
pub const RUN_RECORD_FILE: &str = "run.json";

/// Ties a checkpoint folder to one run: the first call writes `settings` (pretty JSON) to
/// `dir/run.json`; later calls succeed only with the same settings, so resuming never mixes
/// checkpoints of different models, data or schedules. Compared as text (the same serializer on
/// both sides): no parse, so nothing depends on how floats read back.
pub fn claim_checkpoint_dir<T: Serialize>(dir: &Path, settings: &T) -> Result<()> {
    let path = dir.join(RUN_RECORD_FILE);
    let text = serde_json::to_string_pretty(settings).map_err(|source| Error::Json {
        path: path.clone(),
        source,
    })?;
    match read_state_text(&path, "the run record") {
        Ok(old) if old == text => Ok(()),
        Ok(_) => Err(bad(
            dir,
            format!(
                "its checkpoints were made with other settings (see {RUN_RECORD_FILE}); use another folder or delete this one"
            ),
        )),
        Err(Error::Io { source, .. }) if source.kind() == std::io::ErrorKind::NotFound => {
            fs::create_dir_all(dir).map_err(io("creating checkpoint folder", dir))?;
            let tmp = dir.join(format!(".{RUN_RECORD_FILE}.tmp-{}", std::process::id()));
            fs::write(&tmp, text).map_err(io("writing run record", &tmp))?;
            fs::rename(&tmp, &path).map_err(io("writing run record", &path))
        }
        Err(e) => Err(e),
    }
}

pub(crate) fn checkpoint_name(step: u64) -> String {
    format!("step-{step:010}")
}

/// Writes checkpoint `step` into `dir` (created if needed) and returns its path: `write` fills a
/// hidden temporary folder beside the final one (`.step-N.tmp-PID`), which is then renamed into
/// place as `step-N` (a checkpoint of the same step is replaced), so a crash never leaves a
/// partial checkpoint under a `step-*` name; then only the newest `keep` checkpoints stay. The
/// folder must end up holding a `state.json` ([`STATE_FILE`]) to count as complete.
pub(crate) fn write_checkpoint_dir(
    dir: &Path,
    step: u64,
    keep: Option<usize>,
    write: impl FnOnce(&Path) -> Result<()>,
) -> Result<PathBuf> {
    fs::create_dir_all(dir).map_err(io("creating checkpoint directory", dir))?;
    let final_path = dir.join(checkpoint_name(step));
    let tmp = dir.join(format!(
        ".{}.tmp-{}",
        checkpoint_name(step),
        std::process::id()
    ));
    if tmp.exists() {
        fs::remove_dir_all(&tmp).map_err(io("removing stale temporary checkpoint", &tmp))?;
    }
    fs::create_dir(&tmp).map_err(io("creating temporary checkpoint", &tmp))?;
    if let Err(e) = write(&tmp) {
        let _ = fs::remove_dir_all(&tmp);
        return Err(e);
    }
    if final_path.exists() {
        let old = dir.join(format!(
            ".{}.old-{}",
            checkpoint_name(step),
            std::process::id()
        ));
        fs::rename(&final_path, &old).map_err(io("replacing checkpoint", &final_path))?;
        fs::rename(&tmp, &final_path).map_err(io("renaming checkpoint into place", &final_path))?;
        let _ = fs::remove_dir_all(&old);
    } else {
        fs::rename(&tmp, &final_path).map_err(io("renaming checkpoint into place", &final_path))?;
    }
    if let Ok(d) = fs::File::open(dir) {
        let _ = d.sync_all();
    }
    if let Some(keep) = keep {
        let all = list_checkpoints(dir)?;
        if all.len() > keep {
            for (_, p) in &all[..all.len() - keep] {
                fs::remove_dir_all(p).map_err(io("pruning old checkpoint", p))?;
            }
        }
    }
    Ok(final_path)
}

/// Writes `value` as pretty JSON to `path` and syncs it (a checkpoint's `state.json`).
pub(crate) fn write_state_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let json = serde_json::to_vec_pretty(value).map_err(|source| Error::Json {
        path: path.to_path_buf(),
        source,
    })?;
    fs::write(path, json).map_err(io("writing", path))?;
    fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(io("syncing", path))
}

/// Reads and parses a checkpoint's JSON file `path` (capped, as [`read_state_text`]).
pub(crate) fn read_state_json<T: serde::de::DeserializeOwned>(
    path: &Path,
    kind: &str,
) -> Result<T> {
    let text = read_state_text(path, kind)?;
    serde_json::from_str(&text).map_err(|source| Error::Json {
        path: path.to_path_buf(),
        source,
    })
}

/// The newest complete checkpoint (`step-*` directory with a `state.json`) in `dir`, if any.
pub fn find_latest_checkpoint(dir: &Path) -> Result<Option<PathBuf>> {
    Ok(list_checkpoints(dir)?.pop().map(|(_, p)| p))
}

fn list_checkpoints(dir: &Path) -> Result<Vec<(u64, PathBuf)>> {
    if !dir.exists() {
        return Ok(Vec::new());
    }
    let mut out = Vec::new();
    for entry in fs::read_dir(dir).map_err(io("listing checkpoints", dir))? {
        let entry = entry.map_err(io("listing checkpoints", dir))?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let Some(step) = name
            .strip_prefix("step-")
            .and_then(|s| s.parse::<u64>().ok())
        else {
            continue;
        };
        let p = entry.path();
        if p.join(STATE_FILE).is_file() {
            out.push((step, p));
        }
    }
    out.sort();
    Ok(out)
}

impl<M: Denoiser> Trainer<M> {
    /// Writes a checkpoint of the current state into `dir` (created if needed) and returns its path.
    /// Applies `keep_checkpoints`.
    pub fn save_checkpoint(&self, dir: &Path) -> Result<PathBuf> {
        write_checkpoint_dir(dir, self.step, self.config.keep_checkpoints, |tmp| {
            save_tensors(&self.weights()?, &tmp.join(MODEL_FILE))?;
            save_tensors(&self.ema_weights(), &tmp.join(EMA_FILE))?;
            save_tensors(&self.opt.state_tensors(), &tmp.join(OPT_FILE))?;
            let state = CheckpointState {
                format_version: FORMAT_VERSION,
                step: self.step,
                skipped_steps: self.skipped,
                optimizer_steps: self.opt.step_count(),
                rng: RngState::capture(&self.rng),
                train_config: self.config.clone(),
                diffusion_config: self.diffusion.config().clone(),
                train_seconds: self.clock.seconds,
                clock_from_step: Some(self.clock.from_step),
            };
            write_state_json(&tmp.join(STATE_FILE), &state)
        })
    }

    /// Restores weights, EMA, optimizer, step and RNG from a checkpoint directory written by
    /// [`Self::save_checkpoint`]. Every tensor must match the model's variables by name and shape;
    /// the diffusion configuration must define the network this trainer trains
    /// ([`DiffusionConfig::same_network`]: its loss weighting and training levels may differ).
    /// The trainer's current [`TrainConfig`] and diffusion configuration are kept (so a run can be
    /// continued with, e.g., more steps or a share of the draws at the clean levels). Nothing is
    /// modified when validation fails.
    /// Each tensor file is read by `read`, told the names and shapes it must hold.
    pub fn load_checkpoint(&mut self, path: &Path, read: TensorFileReader) -> Result<()> {
        let state_path = path.join(STATE_FILE);
        let state: CheckpointState = read_state_json(&state_path, "the checkpoint state")?;
        if state.format_version != FORMAT_VERSION {
            return Err(bad(
                path,
                format!("unsupported format_version {}", state.format_version),
            ));
        }
        if !state.diffusion_config.same_network(self.diffusion.config()) {
            return Err(bad(
                path,
                "its diffusion process (schedule, prediction, time input or objective) differs from the trainer's",
            ));
        }
        let rng = state
            .rng
            .restore()
            .ok_or_else(|| bad(&state_path, "unreadable rng state"))?;
        let device = self
            .vars
            .first()
            .map(|v| v.device().clone())
            .unwrap_or(candle_core::Device::Cpu);
        // read in the variables' own dtype (an f64 model resumes exactly)
        let dtype = self
            .vars
            .first()
            .map(|v| v.dtype())
            .unwrap_or(candle_core::DType::F32);
        let weights: BTreeMap<String, Vec<usize>> = self
            .names
            .iter()
            .zip(&self.vars)
            .map(|(n, v)| (n.clone(), v.dims().to_vec()))
            .collect();
        let moments: BTreeMap<String, Vec<usize>> = weights
            .iter()
            .flat_map(|(n, d)| ["m", "v"].map(|p| (format!("{p}.{n}"), d.clone())))
            .collect();
        // every file validated before anything is touched
        let model = read(&path.join(MODEL_FILE), &weights, dtype, &device)?;
        let ema = read(&path.join(EMA_FILE), &weights, dtype, &device)?;
        let opt_path = path.join(OPT_FILE);
        let opt = read(&opt_path, &moments, dtype, &device)?;
        self.opt
            .load_state(&opt, state.optimizer_steps)
            .map_err(|e| bad(&opt_path, e.to_string()))?;
        for (i, n) in self.names.iter().enumerate() {
            let (Some(w), Some(e)) = (model.get(n), ema.get(n)) else {
                return Err(bad(path, format!("tensor {n} vanished")));
            };
            let v = &self.vars[i];
            v.set(&w.to_dtype(v.dtype())?)?;
            self.ema[i] = e.to_dtype(v.dtype())?.detach();
        }
        self.step = state.step;
        self.skipped = state.skipped_steps;
        self.rng = rng;
        self.clock = match state.clock_from_step {
            Some(from_step) => super::Clock {
                seconds: state.train_seconds,
                from_step,
            },
            None => super::Clock {
                seconds: 0.0,
                from_step: state.step,
            },
        };
        Ok(())
    }

    /// Loads the newest checkpoint in `dir`, if any, and returns its path.
    pub fn resume_latest(&mut self, dir: &Path, read: TensorFileReader) -> Result<Option<PathBuf>> {
        match find_latest_checkpoint(dir)? {
            Some(p) => {
                self.load_checkpoint(&p, read)?;
                Ok(Some(p))
            }
            None => Ok(None),
        }
    }
}
