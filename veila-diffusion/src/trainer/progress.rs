//! What a training run reports: each update's [`StepStats`], the [`TrainObserver`] callbacks,
//! the run's [`FitSummary`] and [`Clock`].

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use crate::denoiser::Denoiser;
use crate::error::Result;
use crate::objective::Diffusion;

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepStats {
    /// Number of updates done after this one.
    pub step: u64,
    /// Weighted loss of the batch.
    pub loss: f64,
    /// Learning rate used.
    pub lr: f64,
    /// Global gradient norm before clipping (NaN when the loss was non-finite).
    pub grad_norm: f64,
    /// Whether clipping scaled the gradient.
    pub clipped: bool,
    /// Whether the update was skipped (non-finite loss or gradient).
    pub skipped: bool,
    /// Batch size.
    pub batch_size: usize,
    /// Wall time of this step in seconds (data loading excluded).
    pub step_secs: f64,
    /// Samples per second of this step.
    pub samples_per_sec: f64,
}

/// The loss of a run's updates averaged for progress lines: an exponential moving average
/// (weight 0.02 per update) of the finite losses.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LossAverage(Option<f64>);

impl LossAverage {
    /// The average (NaN before the first finite loss).
    pub fn value(&self) -> f64 {
        self.0.unwrap_or(f64::NAN)
    }

    /// Takes in update `s` and returns its progress line:
    /// `loss L (avg A) lr R S s/step`.
    pub fn line(&mut self, s: &StepStats) -> String {
        if s.loss.is_finite() {
            self.0 = Some(match self.0 {
                None => s.loss,
                Some(e) => 0.98 * e + 0.02 * s.loss,
            });
        }
        format!(
            "loss {:.4} (avg {:.4}) lr {:.2e} {:.2} s/step",
            s.loss,
            self.value(),
            s.lr,
            s.step_secs
        )
    }
}

/// Callbacks from [`Trainer::fit`](super::Trainer::fit); every method has a no-op default.
pub trait TrainObserver<M: Denoiser> {
    /// After every update (draw the progress bar here). Return `Break` to stop early.
    fn on_step(&mut self, _stats: &StepStats) -> ControlFlow<()> {
        ControlFlow::Continue(())
    }

    /// Every `preview_every` steps, with the EMA weights loaded into `model` (restored afterwards).
    fn on_preview(&mut self, _step: u64, _model: &M, _diffusion: &Diffusion) -> Result<()> {
        Ok(())
    }

    /// After a checkpoint was written.
    fn on_checkpoint(&mut self, _step: u64, _path: &Path) {}
}

/// The do-nothing observer.
impl<M: Denoiser> TrainObserver<M> for () {}

/// Summary of a [`Trainer::fit`](super::Trainer::fit) call.
#[derive(Debug, Clone, PartialEq)]
pub struct FitSummary {
    /// Updates performed in this call.
    pub steps_run: u64,
    /// The trainer's step afterwards.
    pub final_step: u64,
    /// Mean loss over this call's non-skipped updates (NaN if none).
    pub mean_loss: f64,
    /// Skipped updates in this call.
    pub skipped: u64,
    /// Whether the observer stopped the run.
    pub stopped_early: bool,
    /// Checkpoints written in this call.
    pub checkpoints: Vec<PathBuf>,
    /// The run's training clock afterwards (all resumed runs together).
    pub clock: Clock,
}

impl FitSummary {
    /// [`mean_loss`](Self::mean_loss) for a log line: four decimals, or `-` when this call ran no
    /// update (a run resumed at its last step), instead of NaN.
    pub fn mean_loss_text(&self) -> String {
        if self.steps_run == 0 {
            "- (no update this run)".to_string()
        } else {
            format!("{:.4}", self.mean_loss)
        }
    }
}

/// Wall time a training run has spent in [`Trainer::fit`](super::Trainer::fit), carried through its checkpoints.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Clock {
    /// Seconds counted.
    pub seconds: f64,
    /// The step counting began at (0 unless the run began in a build that kept no clock).
    pub from_step: u64,
}
