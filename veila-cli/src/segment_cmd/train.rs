//! `veila segment train --config CONFIG.toml`: the run folder `[output] dir` is train's own
//! (`crate::staging`'s `train_run`: new, empty or a training run's, none of the inputs), holds the
//! checkpoints (`checkpoints/`), the log (`train_log.jsonl`: one line per update, one per
//! held-out score) and, once the last step is done, the model (`segmenter/`, read back to
//! verify). A finished run's model is replaced only with `--force`.

use std::io::Write;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use veila_data::read_capped::{MAX_CONFIG_BYTES, read_metadata_string};
use veila_diffusion::app::segment::{
    SegEvent, SegTrainFile, SegmenterModel, load_training_data, train_from_file,
};
use veila_metrics::segmentation::SegmentationScores;

use crate::staging::{self, SEGMENTER, TrainInputs};
use crate::{model, progress};

/// Arguments of `veila segment train`.
#[derive(Debug, Args)]
pub(crate) struct TrainArgs {
    /// Training config (TOML: `[data]` scenes or shards, `[model]` preset, `[train]` steps,
    /// batch, lr, seed, class_weights, checkpoint_every, `[output]` dir); relative paths are
    /// relative to this file.
    #[arg(long, value_name = "CONFIG.toml")]
    config: PathBuf,
    /// Stop after this many updates of this run, 1 to 1000000000 (a checkpoint is written; rerun
    /// the same command to continue).
    #[arg(long, value_name = "N", value_parser = crate::bounds::int::<u64>(1, 1_000_000_000))]
    stop_after: Option<u64>,
    /// Replace the model of a finished run in `[output] dir` (`OUTPUT/segmenter`).
    #[arg(long)]
    force: bool,
}

fn read_config(path: &Path) -> Result<SegTrainFile> {
    let text = read_metadata_string(path, MAX_CONFIG_BYTES, "a segmenter training config")?;
    let mut cfg: SegTrainFile = toml::from_str(&text).map_err(|e| {
        anyhow::anyhow!(
            "{}: not a valid segmenter training config: {e}",
            path.display()
        )
    })?;
    cfg.resolve_and_check(path)?;
    Ok(cfg)
}

/// `OUTPUT/train_log.jsonl`, appended to (a resumed run continues it), flushed per line.
struct Log(std::io::LineWriter<std::fs::File>, PathBuf);

impl Log {
    fn line(&mut self, value: serde_json::Value) {
        if writeln!(self.0, "{value}").is_err() {
            tracing::warn!("{}: cannot write the training log", self.1.display());
        }
    }
}

fn held_out_line(s: &SegmentationScores) -> String {
    format!(
        "held-out mIoU {:.4} (over the {} classes present {:.4}), accuracy {:.4}",
        s.miou,
        s.present.len(),
        s.miou_present,
        s.accuracy
    )
}

pub(crate) fn run(args: TrainArgs) -> Result<()> {
    let t_all = Instant::now();
    let file = read_config(&args.config)?;
    let out = &file.output.dir;
    let mut inputs = TrainInputs::default();
    inputs.file("training config", &args.config);
    for (what, p) in [
        ("[data] shards folder", &file.data.shards),
        ("[data] scenes list", &file.data.scenes),
        ("[data] held_out_scenes list", &file.data.held_out_scenes),
    ] {
        if let Some(p) = p {
            if p.is_dir() {
                inputs.folder(what, p);
            } else {
                inputs.file(what, p);
            }
        }
    }
    if let Some(p) = &file.data.label_map {
        inputs.file("[data] label_map", p);
    }
    let _lock = staging::claim_train_run(out, SEGMENTER, 1, &inputs)?;
    staging::check_train_bundle(out, SEGMENTER, args.force)?;
    let device = model::device()?;

    let t_data = Instant::now();
    let items = if file.data.shards.is_some() {
        file.data.max_frames.unwrap_or(0) as u64
    } else {
        (file.data.scene_count + file.data.held_out_count) as u64
    };
    let pb = progress::bar(items, "data");
    let data = load_training_data(&file, &|| pb.inc(1))?;
    pb.finish_and_clear();
    println!(
        "data: {} training frames, {} held-out scans ({:.0} s)",
        data.frames.len(),
        data.held_out.len(),
        t_data.elapsed().as_secs_f64()
    );

    let log_path = out.join("train_log.jsonl");
    let log_file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .with_context(|| format!("{}: cannot open the training log", log_path.display()))?;
    let mut log = Log(std::io::LineWriter::new(log_file), log_path);
    let steps = file.train.steps;
    let pb = progress::bar(steps, "segmenter");
    let mut run_steps = 0u64;
    let mut loss_avg: Option<f32> = None;
    let trained = train_from_file(&file, &data, &device, |event| {
        match event {
            SegEvent::Resumed { path, step } => {
                pb.set_position(step);
                pb.println(format!("resumed from {} (step {step})", path.display()));
            }
            SegEvent::Step {
                step,
                loss,
                lr,
                seconds,
                ..
            } => {
                run_steps += 1;
                let avg = loss_avg.map_or(loss, |a| 0.95 * a + 0.05 * loss);
                loss_avg = Some(avg);
                pb.set_position(step);
                pb.set_message(format!("loss {avg:.4}"));
                log.line(serde_json::json!({
                    "stage": "segmenter", "step": step, "loss": loss, "lr": lr, "step_s": seconds,
                }));
                if args.stop_after.is_some_and(|n| run_steps >= n) {
                    return ControlFlow::Break(());
                }
            }
            SegEvent::HeldOut { step, scores } => {
                pb.println(format!("step {step}: {}", held_out_line(scores)));
                log.line(serde_json::json!({
                    "stage": "held-out", "step": step, "miou": scores.miou,
                    "miou_present": scores.miou_present, "accuracy": scores.accuracy,
                    "iou": scores.iou, "present": scores.present,
                }));
            }
            SegEvent::Checkpoint { .. } => {}
        }
        ControlFlow::Continue(())
    })
    .with_context(|| {
        format!(
            "training (checkpoints in {})",
            out.join("checkpoints").display()
        )
    })?;
    pb.finish_and_clear();
    let o = &trained.outcome;
    if o.step < steps {
        println!(
            "stopped at step {} of {steps}; checkpoint in {}: rerun `veila segment train --config {}` to continue",
            o.step,
            out.join("checkpoints").display(),
            args.config.display()
        );
        return Ok(());
    }
    let dir = out.join(SEGMENTER);
    SegmenterModel::save(&dir, &trained.config, &o.weights)?;
    SegmenterModel::from_dir(&dir, &device)
        .with_context(|| format!("re-reading {}", dir.display()))?;
    if let Some(s) = &o.held_out {
        println!("{}", held_out_line(s));
    }
    println!(
        "wrote {} in {:.0} s ({:.0} s of training over every run; {} parameters); label scans with `veila segment predict --model {} ...`",
        dir.display(),
        t_all.elapsed().as_secs_f64(),
        o.train_seconds,
        trained.config.network.num_parameters(),
        dir.display()
    );
    if let Some(mib) = progress::peak_host_mib() {
        println!("peak host memory: {mib:.0} MiB");
    }
    Ok(())
}
