//! Training a segmenter ([`fit_segmenter`]): per-pixel cross-entropy over the train ids, each
//! class weighted ([`super::frames::class_weights`]; empty pixels and the ignored classes weigh
//! 0), normalised by the batch's total weight as PyTorch's weighted `NLLLoss` is; AdamW (the
//! trainer's, [`crate::trainer::AdamW`]) with a linear warm-up and a cosine decay
//! ([`crate::trainer::LrSchedule`]); BatchNorm in training mode.
//!
//! **Exact resume.** The batch of step `s` is a function of the seed and `s` alone: sample `p = s
//! batch + j` is entry `p mod n` of epoch `p / n`'s seeded permutation of the `n` frames, turned
//! and mirrored ([`super::frames::SegFrame::augmented`]) by a draw seeded by `p`. A checkpoint
//! (`step-N/` in the checkpoint folder, written as the trainer writes its own: a hidden
//! temporary folder renamed into place) holds the weights with the BatchNorm running
//! statistics, the AdamW moments and step count, and the seconds spent; so a run stopped and
//! resumed from its newest checkpoint ends with the bytes of an uninterrupted one. The folder is
//! claimed for one run ([`crate::claim_checkpoint_dir`]): other settings or data are refused.
//!
//! The held-out scans, when given, are scored during training as `veila segment eval` scores
//! point labels: the pixel classes carried to every point by the kNN clean-up, SemanticKITTI's
//! IoU over the points ([`veila_metrics::segmentation::IouEval`]).

use std::collections::{BTreeMap, HashMap};
use std::ops::ControlFlow;
use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use veila_metrics::segmentation::{IouEval, SegmentationScores};
use veila_nn::feature_nets::train::masked_cross_entropy;
use veila_nn::segmenter::{Segmenter, SegmenterConfig};

use super::frames::{GridScan, SegFrame, batch_tensors};
use super::model::{SegmenterModel, SegmenterModelConfig};
use crate::error::{Error, Result, invalid};
use crate::trainer::{
    AdamW, LrSchedule, MODEL_FILE, OPT_FILE, ParamsAdamW, STATE_FILE, find_latest_checkpoint,
    read_state_json, save_tensors, write_checkpoint_dir, write_state_json,
};

/// The most frames of a batch.
pub const MAX_SEG_BATCH: usize = 1024;

/// How a segmenter trains.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SegTrainSettings {
    /// Updates.
    pub steps: u64,
    /// Frames per update.
    pub batch: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Learning rate at the end of the cosine decay.
    pub min_lr: f64,
    /// Updates of the linear warm-up.
    pub warmup_steps: u64,
    /// AdamW's decoupled weight decay.
    pub weight_decay: f64,
    /// Seed of the initial weights, the frame order and the augmentation.
    pub seed: u64,
    /// Turn every frame by a random whole number of columns and mirror half of them.
    pub augment: bool,
    /// A checkpoint every this many updates (and at the last one, and where the run is stopped).
    pub checkpoint_every: u64,
    /// Keep only the newest this many checkpoints (`None`: all).
    pub keep_checkpoints: Option<usize>,
    /// Score the held-out scans every this many updates (and after the last one).
    pub eval_every: Option<u64>,
}

impl SegTrainSettings {
    /// Checks every field.
    pub fn validate(&self) -> Result<()> {
        if self.steps == 0 || self.batch == 0 || self.batch > MAX_SEG_BATCH {
            return Err(invalid(
                "train",
                format!(
                    "steps ({}) must be at least 1 and batch ({}) in 1..={MAX_SEG_BATCH}",
                    self.steps, self.batch
                ),
            ));
        }
        let finite_pos = |v: f64| v.is_finite() && v > 0.0;
        if !(finite_pos(self.lr) && finite_pos(self.min_lr) && self.min_lr <= self.lr) {
            return Err(invalid(
                "lr",
                format!(
                    "lr {} and min_lr {} must be finite, > 0, min_lr <= lr",
                    self.lr, self.min_lr
                ),
            ));
        }
        if !(self.weight_decay.is_finite() && self.weight_decay >= 0.0) {
            return Err(invalid("weight_decay", "must be finite and >= 0"));
        }
        if self.checkpoint_every == 0
            || self.eval_every == Some(0)
            || self.keep_checkpoints == Some(0)
        {
            return Err(invalid(
                "train",
                "checkpoint_every, eval_every and keep_checkpoints must be at least 1",
            ));
        }
        Ok(())
    }

    /// The settings that decide the result (not how often it is saved or scored), as a resumed
    /// run must find them.
    fn fingerprint(&self) -> serde_json::Value {
        serde_json::json!({
            "steps": self.steps,
            "batch": self.batch,
            "lr": self.lr,
            "min_lr": self.min_lr,
            "warmup_steps": self.warmup_steps,
            "weight_decay": self.weight_decay,
            "seed": self.seed,
            "augment": self.augment,
        })
    }
}

/// A held-out scan: on the grid, with the true train id of each point.
#[derive(Debug, Clone)]
pub struct HeldOutScan {
    /// The scan on the segmenter's grid.
    pub scan: GridScan,
    /// The true train id of each point.
    pub truth: Vec<u32>,
}

/// What [`fit_segmenter`] trains on.
#[derive(Debug)]
pub struct SegTrainInput<'a> {
    /// The model being trained: its network, sensor, clean-up and classes (its provenance is not
    /// read).
    pub model: &'a SegmenterModelConfig,
    /// The training frames.
    pub frames: &'a [SegFrame],
    /// The loss weight of each class.
    pub class_weights: &'a [f32],
    /// The classes left out of the held-out scores.
    pub ignored: &'a [usize],
    /// Held-out scans scored during training (may be empty).
    pub held_out: &'a [HeldOutScan],
    /// The checkpoint folder.
    pub ck_dir: &'a Path,
    /// What identifies the data (a shard manifest's sum, a scene list and its draw), claimed for
    /// the checkpoint folder with the network, the settings and the class weights.
    pub data: serde_json::Value,
}

/// What [`fit_segmenter`] reports as it goes; the callback's `Break` after a step stops the run
/// after a checkpoint (what it answers to the other events is not read).
#[derive(Debug)]
pub enum SegEvent<'a> {
    /// The run continues from a checkpoint.
    Resumed {
        /// The checkpoint.
        path: &'a Path,
        /// Its step.
        step: u64,
    },
    /// An update was made.
    Step {
        /// Updates done.
        step: u64,
        /// Of this many.
        steps: u64,
        /// The batch's loss.
        loss: f32,
        /// The learning rate of the update.
        lr: f64,
        /// Seconds of the update.
        seconds: f64,
    },
    /// The held-out scans were scored.
    HeldOut {
        /// After this many updates.
        step: u64,
        /// The scores.
        scores: &'a SegmentationScores,
    },
    /// A checkpoint was written.
    Checkpoint {
        /// After this many updates.
        step: u64,
        /// Its folder.
        path: &'a Path,
    },
}

/// What a training run ends with.
#[derive(Debug)]
pub struct SegFitOutcome {
    /// Updates done (the settings' `steps` when the run finished).
    pub step: u64,
    /// The weights, BatchNorm statistics included.
    pub weights: HashMap<String, Tensor>,
    /// Seconds of training over every run that resumed this one.
    pub train_seconds: f64,
    /// The last held-out scores of this run.
    pub held_out: Option<SegmentationScores>,
}

/// `state.json` of a segmenter checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SegState {
    format: String,
    step: u64,
    optimizer_steps: usize,
    train_seconds: f64,
}

const STATE_FORMAT: &str = "veila-segmenter-checkpoint/1";

fn is_running_stat(name: &str) -> bool {
    name.ends_with(".running_mean") || name.ends_with(".running_var")
}

/// The frames of a run in their seeded order (module docs), one epoch's permutation at a time.
struct Order {
    seed: u64,
    n: u64,
    epoch: Option<u64>,
    perm: Vec<usize>,
}

impl Order {
    fn index(&mut self, p: u64) -> usize {
        let epoch = p / self.n;
        if self.epoch != Some(epoch) {
            let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
            rng.set_stream(epoch);
            self.perm = (0..self.n as usize).collect();
            self.perm.shuffle(&mut rng);
            self.epoch = Some(epoch);
        }
        self.perm[(p % self.n) as usize]
    }
}

fn step_batch(
    frames: &[SegFrame],
    order: &mut Order,
    cfg: &SegmenterConfig,
    s: &SegTrainSettings,
    step: u64,
) -> Vec<SegFrame> {
    (0..s.batch as u64)
        .map(|j| {
            let p = step * s.batch as u64 + j;
            let f = &frames[order.index(p)];
            if !s.augment {
                return f.clone();
            }
            let mut rng = ChaCha8Rng::seed_from_u64(s.seed ^ 0xa6_a6a6);
            rng.set_stream(p);
            let shift = rng.random_range(0..cfg.cols);
            let mirror = rng.random_bool(0.5);
            f.augmented(cfg, shift, mirror)
        })
        .collect()
}

/// Every variable of `varmap` by name (BatchNorm statistics included), sorted.
fn named_vars(varmap: &VarMap) -> Result<Vec<(String, Var)>> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| Error::Data("the VarMap lock is poisoned".into()))?;
    let mut v: Vec<(String, Var)> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(v)
}

fn weights_of(vars: &[(String, Var)]) -> HashMap<String, Tensor> {
    vars.iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect()
}

/// Scores `scans` with the network of `model` on the weights of `vars`: point labels, IoU.
fn score_held_out(
    model: &SegmenterModelConfig,
    vars: &[(String, Var)],
    scans: &[HeldOutScan],
    ignored: &[usize],
    device: &Device,
) -> Result<SegmentationScores> {
    let weights: HashMap<String, Tensor> = vars
        .iter()
        .map(|(k, v)| Ok((k.clone(), v.as_tensor().copy()?)))
        .collect::<Result<_>>()?;
    let seg = SegmenterModel::new(model.clone(), weights, Path::new("<training>"), device)?;
    let mut eval = IouEval::new(model.network.num_classes, ignored)?;
    for chunk in scans.chunks(4) {
        let grid: Vec<GridScan> = chunk.iter().map(|h| h.scan.clone()).collect();
        for (pred, h) in seg.predict(&grid)?.iter().zip(chunk) {
            eval.add(pred, &h.truth)?;
        }
    }
    Ok(eval.scores())
}

/// Trains the network of `input.model` (module docs), continuing from the newest checkpoint of
/// `input.ck_dir` when there is one; `on_event` sees every step, score and checkpoint.
pub fn fit_segmenter(
    input: &SegTrainInput<'_>,
    settings: &SegTrainSettings,
    device: &Device,
    mut on_event: impl FnMut(SegEvent<'_>) -> ControlFlow<()>,
) -> Result<SegFitOutcome> {
    settings.validate()?;
    let model = input.model;
    let cfg = &model.network;
    model.check(input.ck_dir)?;
    if input.frames.is_empty() {
        return Err(Error::Data("no training frames".into()));
    }
    if input.class_weights.len() != cfg.num_classes {
        return Err(Error::Data(format!(
            "{} class weights for {} classes",
            input.class_weights.len(),
            cfg.num_classes
        )));
    }
    crate::claim_checkpoint_dir(
        input.ck_dir,
        &serde_json::json!({
            "network": cfg,
            "sensor": model.sensor,
            "settings": settings.fingerprint(),
            "class_weights": input.class_weights,
            "data": input.data,
        }),
    )?;
    let varmap = VarMap::new();
    let net = Segmenter::new(
        cfg,
        veila_nn::seeded_var_builder(&varmap, settings.seed, DType::F32, device),
    )?;
    let vars = named_vars(&varmap)?;
    let trainable: Vec<(String, Var)> = vars
        .iter()
        .filter(|(k, _)| !is_running_stat(k))
        .cloned()
        .collect();
    let mut opt = AdamW::new(
        trainable,
        ParamsAdamW {
            lr: settings.lr,
            weight_decay: settings.weight_decay,
            ..Default::default()
        },
    )?;
    let mut step = 0u64;
    let mut train_seconds = 0f64;
    if let Some(path) = find_latest_checkpoint(input.ck_dir)? {
        let state = resume(&path, &vars, &mut opt, device)?;
        step = state.step.min(settings.steps);
        train_seconds = state.train_seconds;
        let _ = on_event(SegEvent::Resumed { path: &path, step });
    }
    let schedule = LrSchedule {
        base_lr: settings.lr,
        warmup_steps: settings.warmup_steps,
        total_steps: settings.steps,
        min_lr: settings.min_lr,
    };
    let mut order = Order {
        seed: settings.seed,
        n: input.frames.len() as u64,
        epoch: None,
        perm: Vec::new(),
    };
    let mut held_out = None;
    while step < settings.steps {
        let t0 = Instant::now();
        let frames = step_batch(input.frames, &mut order, cfg, settings, step);
        let (x, y, w) = batch_tensors(&frames, input.class_weights, cfg, device)?;
        let lr = schedule.lr_at(step);
        opt.set_learning_rate(lr);
        let logits = net.forward_t(&x, true)?;
        let k = logits.dim(1)?;
        let flat = logits.permute((0, 2, 3, 1))?.reshape(((), k))?;
        let loss = masked_cross_entropy(&flat, &y, &w)?;
        let l = loss.to_scalar::<f32>()?;
        if !l.is_finite() {
            return Err(Error::NonFinite { what: "loss", step });
        }
        let grads = loss.backward()?;
        opt.step(&grads, 1.0)?;
        step += 1;
        let seconds = t0.elapsed().as_secs_f64();
        train_seconds += seconds;
        let flow = on_event(SegEvent::Step {
            step,
            steps: settings.steps,
            loss: l,
            lr,
            seconds,
        });
        let last = step == settings.steps;
        if !input.held_out.is_empty()
            && (last || settings.eval_every.is_some_and(|e| step.is_multiple_of(e)))
        {
            let scores = score_held_out(model, &vars, input.held_out, input.ignored, device)?;
            let _ = on_event(SegEvent::HeldOut {
                step,
                scores: &scores,
            });
            held_out = Some(scores);
        }
        if last || flow.is_break() || step.is_multiple_of(settings.checkpoint_every) {
            let path =
                write_checkpoint_dir(input.ck_dir, step, settings.keep_checkpoints, |tmp| {
                    save_tensors(&weights_of(&vars), &tmp.join(MODEL_FILE))?;
                    save_tensors(&opt.state_tensors(), &tmp.join(OPT_FILE))?;
                    write_state_json(
                        &tmp.join(STATE_FILE),
                        &SegState {
                            format: STATE_FORMAT.into(),
                            step,
                            optimizer_steps: opt.step_count(),
                            train_seconds,
                        },
                    )
                })?;
            let _ = on_event(SegEvent::Checkpoint { step, path: &path });
        }
        if flow.is_break() {
            break;
        }
    }
    if held_out.is_none() && step == settings.steps && !input.held_out.is_empty() {
        // a run resumed after its last update still reports its scores
        held_out = Some(score_held_out(
            model,
            &vars,
            input.held_out,
            input.ignored,
            device,
        )?);
    }
    Ok(SegFitOutcome {
        step,
        weights: weights_of(&vars),
        train_seconds,
        held_out,
    })
}

/// Restores `vars` and `opt` from the checkpoint folder `path`; every file is read and checked
/// (names, shapes, finite values) before anything is set.
fn resume(
    path: &Path,
    vars: &[(String, Var)],
    opt: &mut AdamW,
    device: &Device,
) -> Result<SegState> {
    let state: SegState = read_state_json(&path.join(STATE_FILE), "the checkpoint state")?;
    if state.format != STATE_FORMAT {
        return Err(Error::Checkpoint {
            reason: format!("format `{}`, expected `{STATE_FORMAT}`", state.format),
            path: path.to_path_buf(),
        });
    }
    let shapes: BTreeMap<String, Vec<usize>> = vars
        .iter()
        .map(|(k, v)| (k.clone(), v.dims().to_vec()))
        .collect();
    let moments: BTreeMap<String, Vec<usize>> = shapes
        .iter()
        .filter(|(k, _)| !is_running_stat(k))
        .flat_map(|(k, d)| ["m", "v"].map(|p| (format!("{p}.{k}"), d.clone())))
        .collect();
    let read = crate::app::nn::read_checkpoint_tensors;
    let weights = read(&path.join(MODEL_FILE), &shapes, DType::F32, device)?;
    let opt_path = path.join(OPT_FILE);
    let moment_tensors = read(&opt_path, &moments, DType::F32, device)?;
    opt.load_state(&moment_tensors, state.optimizer_steps)
        .map_err(|e| Error::Checkpoint {
            reason: e.to_string(),
            path: opt_path.clone(),
        })?;
    for (k, v) in vars {
        let t = weights.get(k).ok_or_else(|| Error::Checkpoint {
            reason: format!("tensor {k} vanished"),
            path: path.to_path_buf(),
        })?;
        v.set(t)?;
    }
    Ok(state)
}
