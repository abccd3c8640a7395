//! What a training run shows and keeps: the progress bars and `OUTPUT/train_log.jsonl`.

use std::ops::ControlFlow;
use std::path::PathBuf;

use anyhow::{Context, Result};
use veila_diffusion::app::{EncoderEvent, Stage};
use veila_diffusion::{LossAverage, StepStats, TrainObserver};

use crate::progress;

pub(super) struct Progress {
    pub(super) bar: indicatif::ProgressBar,
    pub(super) loss: LossAverage,
    pub(super) stop_after: Option<u64>,
    /// Steps run by this invocation, over all stages.
    pub(super) run: std::rc::Rc<std::cell::Cell<u64>>,
    pub(super) stage: Stage,
    /// `OUTPUT/train_log.jsonl`, appended to (a resumed run continues it).
    pub(super) log: std::rc::Rc<TrainLog>,
}

/// `OUTPUT/train_log.jsonl`: one JSON object per update (stage, step, loss, learning rate,
/// samples/s), flushed per line, so a killed run keeps every step it logged.
pub(super) struct TrainLog {
    path: PathBuf,
    file: std::cell::RefCell<std::io::LineWriter<std::fs::File>>,
    failed: std::cell::Cell<bool>,
}

/// The log file's name inside `[output] dir`.
pub(super) const TRAIN_LOG: &str = "train_log.jsonl";

impl TrainLog {
    pub(super) fn open(path: PathBuf) -> Result<Self> {
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .with_context(|| format!("{}: cannot open the training log", path.display()))?;
        Ok(TrainLog {
            path,
            file: std::cell::RefCell::new(std::io::LineWriter::new(file)),
            failed: std::cell::Cell::new(false),
        })
    }

    fn step(&self, stage: Stage, s: &StepStats) {
        use std::io::Write;
        let line = serde_json::json!({
            "stage": match stage {
                Stage::Mean => "mean",
                Stage::Denoiser => "denoiser",
            },
            "step": s.step,
            "loss": s.loss.is_finite().then_some(s.loss),
            "lr": s.lr,
            "samples_per_s": s.samples_per_sec,
            "step_s": s.step_secs,
        });
        if writeln!(self.file.borrow_mut(), "{line}").is_err() && !self.failed.replace(true) {
            tracing::warn!("{}: cannot write the training log", self.path.display());
        }
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}

impl<M: veila_diffusion::Denoiser> TrainObserver<M> for Progress {
    fn on_step(&mut self, s: &StepStats) -> ControlFlow<()> {
        self.run.set(self.run.get() + 1);
        self.log.step(self.stage, s);
        self.bar.set_position(s.step);
        self.bar.set_message(self.loss.line(s));
        match self.stop_after {
            Some(n) if self.run.get() >= n => ControlFlow::Break(()),
            _ => ControlFlow::Continue(()),
        }
    }
}

/// The encoders' stage as it goes: a bar per encoder trained, and a note of what each did.
#[derive(Default)]
pub(super) struct EncoderProgress {
    /// `NAME resumed; NAME: final batch loss L; ...`.
    pub(super) note: String,
    bar: Option<indicatif::ProgressBar>,
}

impl EncoderProgress {
    pub(super) fn event(&mut self, event: EncoderEvent<'_>) {
        match event {
            EncoderEvent::Reused(which, _) => {
                self.note.push_str(&format!("{} resumed; ", which.name()))
            }
            EncoderEvent::Step(which, s, total) => {
                let bar = self
                    .bar
                    .get_or_insert_with(|| progress::bar(total as u64, which.name()));
                bar.set_position(s.step as u64);
                bar.set_message(format!("loss {:.4}", s.loss));
            }
            EncoderEvent::Trained(which, last) => {
                if let Some(bar) = self.bar.take() {
                    bar.finish_and_clear();
                }
                self.note
                    .push_str(&format!("{}: final batch loss {last:.4}; ", which.name()));
            }
        }
    }
}
