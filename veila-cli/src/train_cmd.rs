//! `veila train --config CONFIG.toml`: trains a model bundle on converted training shards
//! (`veila convert`).
//!
//! The image encoders are trained first (or taken from another bundle), with sparse supervision
//! from the LiDAR: each return of a shard's range image is projected into the camera image, giving
//! a metric depth and, when the shards carry train ids, a semantic class at that pixel. Then the
//! denoiser is trained on the frozen encoder features. The run is resumable: the trained encoders
//! and the denoiser checkpoints live in `OUTPUT/checkpoints`, and rerunning the same config picks
//! up the newest checkpoint (the result is bit-identical to an uninterrupted run). The finished
//! bundle is written to `OUTPUT/bundle` (verified by reading it back). Every update appends a line
//! to `OUTPUT/train_log.jsonl` (stage, step, loss, learning rate, samples/s). `OUTPUT` must be new,
//! empty or train's own run folder, and none of the run's inputs; a finished run's bundle is
//! replaced only with `--force` (`crate::staging`'s `train_run`).
//!
//! Data-parallel: started by a launcher as several processes (torchrun's `RANK` / `WORLD_SIZE` /
//! `LOCAL_RANK` / `MASTER_ADDR` / `MASTER_PORT`, or Slurm's `SLURM_PROCID` / `SLURM_NTASKS` /
//! `SLURM_LOCALID` with `MASTER_ADDR` / `MASTER_PORT` exported), the ranks meet at rank 0 over TCP
//! ([`crate::dist`]), each trains on its share of every global batch of `[train] batch`, the
//! gradients are averaged before each update, and rank 0 alone writes checkpoints, the log and the
//! bundle (the other ranks log to `train_log.rank-N.jsonl`). The output folder must be shared.
//!
//! The config's schema and what it gives (the bundle config, the recipe settings) are
//! `veila_diffusion::app::train_config`; the shards become examples in
//! `veila_diffusion::app::train_data`. This module reads the TOML, draws the progress and writes
//! the log.

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use veila_data::read_capped::{
    MAX_CONFIG_BYTES, MAX_JSON_METADATA_BYTES, read_metadata, read_metadata_string,
};
use veila_data::shard::Manifest;
use veila_diffusion::app::bundle::{Bundle, sha256_hex};
use veila_diffusion::app::train_config::{RunFingerprint, TrainFile};
use veila_diffusion::app::train_data::{Prepared, ShardSource, load_prepared};
use veila_diffusion::app::{
    EncoderData, EncoderEvent, EncoderSource, ExampleSource, Examples, RecipeInput, Stage,
    TrainExample, run_recipe,
};
use veila_diffusion::trainer::distributed::{Parallel, ProcessGroup};
use veila_diffusion::{LossAverage, Precision, StepStats, TrainObserver};

use crate::{model, progress};

/// Arguments of `veila train`.
#[derive(Debug, Args)]
pub(crate) struct TrainArgs {
    /// Training config (TOML: `[data]` shards, `[model]` variant, `[train]` steps, batch, lr, seed,
    /// encoder_steps, checkpoint_every, `[output]` dir); relative paths are relative to this file.
    #[arg(long, value_name = "CONFIG.toml")]
    config: PathBuf,
    /// Stop after this many training steps of this run, the mean network's and the denoiser's
    /// together, 1 to 1000000000 (a checkpoint is written; rerun the same command to continue).
    #[arg(long, value_name = "N", value_parser = crate::bounds::int::<u64>(1, 1_000_000_000))]
    stop_after: Option<u64>,
    /// Replace the bundle of a finished run in `[output] dir` (`OUTPUT/bundle`) with this run's.
    /// The folder itself must still be empty, new or train's own run.
    #[arg(long)]
    force: bool,
}

const ENCODER_DIR: &str = "encoders";

/// The config file at `path`, its relative paths resolved and its values checked.
fn read_config(path: &Path) -> Result<TrainFile> {
    let text = read_metadata_string(path, MAX_CONFIG_BYTES, "a training config")?;
    let mut cfg: TrainFile = toml::from_str(&text)
        .map_err(|e| anyhow::anyhow!("{}: not a valid training config: {e}", path.display()))?;
    cfg.resolve_and_check(path)?;
    Ok(cfg)
}

struct Progress {
    bar: indicatif::ProgressBar,
    loss: LossAverage,
    stop_after: Option<u64>,
    /// Steps run by this invocation, over all stages.
    run: std::rc::Rc<std::cell::Cell<u64>>,
    stage: Stage,
    /// `OUTPUT/train_log.jsonl`, appended to (a resumed run continues it).
    log: std::rc::Rc<TrainLog>,
}

/// `OUTPUT/train_log.jsonl`: one JSON object per update (stage, step, loss, learning rate,
/// samples/s), flushed per line, so a killed run keeps every step it logged.
struct TrainLog {
    path: PathBuf,
    file: std::cell::RefCell<std::io::LineWriter<std::fs::File>>,
    failed: std::cell::Cell<bool>,
}

/// The log file's name inside `[output] dir`.
const TRAIN_LOG: &str = "train_log.jsonl";

impl TrainLog {
    fn open(path: PathBuf) -> Result<Self> {
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

fn print_denoiser_summary(d: &veila_diffusion::app::DenoiserFitOutcome, steps: u64, secs: f64) {
    let s = &d.summary;
    println!(
        "  denoiser: {} steps this run (now at {} of {steps}), mean loss {}, {} skipped, {secs:.1} s",
        s.steps_run,
        s.final_step,
        s.mean_loss_text(),
        s.skipped
    );
}

pub(crate) fn run(args: TrainArgs) -> Result<()> {
    let t_all = Instant::now();
    let file = read_config(&args.config)?;
    let mut cfg = file.bundle_config(&args.config)?;
    let device = model::device()?;
    let t = &file.train;
    if t.precision == Precision::Bf16 && device.is_cpu() {
        eprintln!(
            "note: precision = \"bf16\" on the CPU runs slower than f32 (candle's CPU backend has \
             no bf16 convolution or matrix kernels); it is meant for GPUs (--device cuda)"
        );
    }
    // data-parallel when a launcher (torchrun, srun) started several of us
    let group = ProcessGroup::from_env()?;
    let parallel = if group.world_size > 1 {
        if t.batch < group.world_size {
            bail!(
                "{}: [train] batch {} is smaller than the {} ranks (the batch is the global one, shared by the ranks)",
                args.config.display(),
                t.batch,
                group.world_size
            );
        }
        let tcp = crate::dist::TcpGroup::connect(&group, std::time::Duration::from_secs(300))?;
        // on GPUs of an NCCL build the gradients go over NCCL (the TCP group only bootstraps it)
        #[cfg(feature = "nccl")]
        let comm: Box<dyn veila_diffusion::trainer::distributed::Communicator> = if device.is_cuda()
        {
            let mut tcp = tcp;
            Box::new(crate::dist_nccl::NcclGroup::connect(&device, &mut tcp)?)
        } else {
            Box::new(tcp)
        };
        #[cfg(not(feature = "nccl"))]
        let comm: Box<dyn veila_diffusion::trainer::distributed::Communicator> = Box::new(tcp);
        eprintln!(
            "train: rank {} of {} (local rank {})",
            group.rank, group.world_size, group.local_rank
        );
        Some(Parallel::new(group.clone(), comm)?)
    } else {
        None
    };

    // the run folder: train's own, none of its inputs, locked for the whole run; a killed earlier
    // run's partial files go, checkpoints stay
    let out = &file.output.dir;
    let _run_lock = if group.is_main() {
        let mut inputs = crate::staging::TrainInputs::default();
        inputs
            .folder("[data] shards folder", &file.data.shards)
            .file("training config", &args.config);
        let m = &file.model;
        if let Some(p) = &m.encoders_from {
            inputs.folder("[model] encoders_from bundle", p);
        }
        for (what, p) in [
            ("[model] bundle", &m.bundle),
            ("[model] semantic_weights", &m.semantic_weights),
            ("[model] depth_weights", &m.depth_weights),
        ] {
            if let Some(p) = p {
                inputs.file(what, p);
            }
        }
        Some(crate::staging::claim_train_run(
            out,
            group.world_size,
            &inputs,
        )?)
    } else {
        None
    };

    // 1. data
    let shards = &file.data.shards;
    let manifest_path = shards.join("manifest.json");
    if !manifest_path.exists() {
        bail!(
            "{}: no manifest.json: [data] shards must be a folder written by `veila convert`",
            shards.display()
        );
    }
    let manifest = Manifest::read(&manifest_path)?;
    if manifest.count == 0 {
        bail!("{}: the manifest lists no samples", manifest_path.display());
    }
    if file.data.verify {
        manifest.verify(shards)?;
    }
    let want = file
        .data
        .max_frames
        .unwrap_or(manifest.count)
        .min(manifest.count);
    // the camera is needed by conditional models and to train encoders
    let needs_camera = cfg.denoiser.conditioning.is_some()
        || (file.model.encoders_from.is_none()
            && (cfg.semantic_encoder.is_some() || cfg.depth_encoder.is_some()));
    let conditional = cfg.denoiser.conditioning.is_some();
    let mut prepared: Vec<Prepared> = Vec::new();
    let mut stream: Option<Arc<dyn ExampleSource>> = None;
    let mut first_has_labels = false;
    if file.data.stream {
        let source = ShardSource::new(
            shards,
            &manifest,
            want,
            &cfg,
            needs_camera,
            conditional,
            file.data.unify_cameras,
        )?;
        first_has_labels = source.first_sample()?.train_ids.is_some();
        stream = Some(Arc::new(source));
    } else {
        let bar = progress::bar(want as u64, "loading");
        prepared = load_prepared(
            shards,
            &manifest,
            want,
            &cfg,
            needs_camera,
            file.data.unify_cameras,
            || bar.inc(1),
        )?;
        bar.finish_and_clear();
    }
    let samples = stream.as_ref().map_or(prepared.len(), |s| s.len());
    println!(
        "train: {} samples from {}{} ({} sensor {}x{} -> model grid {}x{}), model `{}`",
        samples,
        shards.display(),
        if stream.is_some() {
            format!(", streamed (prefetch {})", file.data.prefetch)
        } else {
            String::new()
        },
        crate::out::untrusted(&manifest.dataset),
        manifest.sensor.rows,
        manifest.sensor.cols,
        cfg.denoiser.sensor.rows,
        cfg.denoiser.sensor.cols,
        crate::out::untrusted(&cfg.name)
    );

    // 2. resumability: the run's fingerprint
    let ck_dir = out.join("checkpoints");
    let manifest_bytes =
        read_metadata(&manifest_path, MAX_JSON_METADATA_BYTES, "a shard manifest")?;
    let fingerprint = RunFingerprint {
        bundle: cfg.clone(),
        train: serde_json::to_value(t)?,
        data_manifest_sha256: sha256_hex(&manifest_bytes),
        samples,
        encoders_from: file
            .model
            .encoders_from
            .as_ref()
            .map(|p| p.display().to_string()),
    };
    if group.is_main() {
        veila_diffusion::claim_checkpoint_dir(&ck_dir, &fingerprint).with_context(|| {
            format!(
                "{}: model, [train] or data changed since these checkpoints; use another [output] dir",
                out.display()
            )
        })?;
        // a finished run's bundle is replaced only with --force (checked before the work)
        crate::staging::check_train_bundle(out, args.force)?;
    }
    if let Some(p) = &parallel {
        // the others wait for rank 0's claim (and learn whether it failed: a zero sum)
        let mut ok = [1f32];
        p.communicator().all_reduce_sum(&mut ok)?;
        if ok[0] < group.world_size as f32 {
            bail!("rank {}: another rank failed to start", group.rank);
        }
    }

    // 3. encoders and 4. networks: the shared recipe
    let settings = t.recipe_settings();
    let mean_steps = settings.mean_steps();
    let enc_dir = ck_dir.join(ENCODER_DIR);
    let images: Vec<Vec<u8>> = prepared.iter().map(|p| p.rgb.clone()).collect();
    let depths: Vec<Vec<f32>> = prepared.iter().map(|p| p.depth_m.clone()).collect();
    let cameras: Vec<veila_geom::PinholeCamera> = prepared.iter().map(|p| p.camera).collect();
    let labels: Option<Vec<Vec<u32>>> = prepared.iter().map(|p| p.labels.clone()).collect();
    let encoders = match &file.model.encoders_from {
        Some(dir) => EncoderSource::Bundle(dir),
        None => {
            if cfg
                .semantic_encoder
                .as_ref()
                .is_some_and(|e| e.small_cnn_config().is_some())
                && (if stream.is_some() {
                    !first_has_labels
                } else {
                    labels.is_none()
                })
            {
                bail!(
                    "{}: the shards carry no semantic train ids (`label`), so the semantic encoder cannot be trained: \
                     convert with a label map (SemanticKITTI) or set [model] encoders_from = \"models/default\"",
                    shards.display()
                );
            }
            EncoderSource::Train {
                data: match &stream {
                    Some(source) => EncoderData::Stream(source),
                    None => EncoderData::Memory {
                        images: &images,
                        labels: labels.as_deref(),
                        depth_m: &depths,
                        cameras: Some(&cameras),
                    },
                },
                dir: &enc_dir,
            }
        }
    };
    let examples: Vec<TrainExample> = prepared
        .into_iter()
        .map(|p| TrainExample {
            rgb: p.rgb,
            camera: p.camera,
            x0: p.x0,
            extra_views: p.extra_views,
        })
        .collect();
    let t_den = Instant::now();
    let mut encoder_note = String::new();
    let mut enc_bar: Option<indicatif::ProgressBar> = None;
    let run = std::rc::Rc::new(std::cell::Cell::new(0u64));
    let log_path = if group.is_main() {
        out.join(TRAIN_LOG)
    } else {
        out.join(format!("train_log.rank-{}.jsonl", group.rank))
    };
    let log = std::rc::Rc::new(TrainLog::open(log_path)?);
    let outcome = run_recipe(
        &mut cfg,
        RecipeInput {
            encoders,
            examples: match &stream {
                Some(source) => Examples::Stream {
                    source,
                    prefetch: file.data.prefetch.max(1),
                },
                None => (&examples).into(),
            },
            work_dir: &ck_dir,
            init: None,
            mean_init: None,
            parallel: parallel.as_ref(),
        },
        &settings,
        &device,
        |event| match event {
            EncoderEvent::Reused(which, _) => {
                encoder_note.push_str(&format!("{} resumed; ", which.name()))
            }
            EncoderEvent::Step(which, s, total) => {
                let bar = enc_bar.get_or_insert_with(|| progress::bar(total as u64, which.name()));
                bar.set_position(s.step as u64);
                bar.set_message(format!("loss {:.4}", s.loss));
            }
            EncoderEvent::Trained(which, last) => {
                if let Some(bar) = enc_bar.take() {
                    bar.finish_and_clear();
                }
                encoder_note.push_str(&format!("{}: final batch loss {last:.4}; ", which.name()));
            }
        },
        |stage, p, step| {
            println!(
                "  {}: resumed from {} (step {step})",
                stage.name(),
                p.display()
            )
        },
        |stage, total| Progress {
            bar: progress::bar(total, stage.name()),
            loss: LossAverage::default(),
            stop_after: args.stop_after,
            run: run.clone(),
            stage,
            log: log.clone(),
        },
    )
    // only a failure to load `[model] encoders_from` is blamed on it; the others say what failed
    .map_err(|e| match e {
        e @ veila_diffusion::Error::EncodersFrom { .. } => anyhow::Error::new(e)
            .context(format!("{}: [model] encoders_from", args.config.display())),
        e => {
            anyhow::Error::new(e).context(format!("training (checkpoints in {})", ck_dir.display()))
        }
    })?;
    if let Some(dir) = &file.model.encoders_from {
        encoder_note = format!("from {}", dir.display());
    }
    let enc_secs = outcome.encoder_seconds;
    if !encoder_note.is_empty() {
        println!("  encoders: {}", encoder_note.trim_end_matches("; "));
    }
    let den_secs = t_den.elapsed().as_secs_f64() - enc_secs;
    if let Some(m) = &outcome.fit.mean {
        println!(
            "  mean network: {} steps this run (now at {} of {mean_steps}), mean loss {}, {:.1} s",
            m.summary.steps_run,
            m.summary.final_step,
            m.summary.mean_loss_text(),
            outcome.fit.seconds[0]
        );
    }
    let den = match &outcome.fit.denoiser {
        Some(d) if d.step >= t.steps => d,
        Some(d) => {
            print_denoiser_summary(d, t.steps, outcome.fit.seconds[1]);
            println!(
                "stopped at step {} of {}; checkpoint in {}: rerun `veila train --config {}` to continue",
                d.step,
                t.steps,
                ck_dir.display(),
                args.config.display()
            );
            return Ok(());
        }
        None => {
            let at = outcome.fit.mean.as_ref().map_or(0, |m| m.step);
            println!(
                "stopped the mean network at step {at} of {mean_steps}; checkpoint in {}: rerun `veila train --config {}` to continue",
                ck_dir.join("mean").display(),
                args.config.display()
            );
            return Ok(());
        }
    };
    print_denoiser_summary(den, t.steps, outcome.fit.seconds[1]);
    if !group.is_main() {
        println!("rank {}: done; rank 0 writes the bundle", group.rank);
        return Ok(());
    }
    let summary = den.summary.clone();
    let weights = outcome.into_weights();

    // 5. the bundle
    cfg.provenance = serde_json::json!({
        "trained_by": "veila train",
        "config": args.config.display().to_string(),
        "data": shards.display().to_string(),
        "dataset": manifest.dataset,
        "data_manifest_sha256": fingerprint.data_manifest_sha256,
        "samples": fingerprint.samples,
        "encoders_from": fingerprint.encoders_from,
        "train": fingerprint.train,
        "ranks": group.world_size,
        "final_mean_loss_this_run": summary.mean_loss,
        "seconds_this_run": {
            "encoders": enc_secs.round(),
            "denoiser": den_secs.round(),
        },
    });
    let bundle_dir = out.join("bundle");
    Bundle::save(&bundle_dir, &cfg, &weights)?;
    Bundle::from_dir(&bundle_dir, &device)
        .with_context(|| format!("re-reading {}", bundle_dir.display()))?;
    println!(
        "wrote {} in {:.0} s ({} denoiser parameters); generate with `veila generate --model {} ...`",
        bundle_dir.display(),
        t_all.elapsed().as_secs_f64(),
        veila_nn::checkpoint::parameter_count(&cfg.denoiser)?,
        bundle_dir.display()
    );
    if let Some(mib) = peak_host_mib() {
        println!("peak host memory: {mib:.0} MiB");
    }
    Ok(())
}

/// The process's peak resident set (`VmHWM` of `/proc/self/status`, Linux) in MiB.
fn peak_host_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(unix)]
    #[test]
    fn a_train_config_linked_to_dev_zero_is_refused_naming_it() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("train.toml");
        std::os::unix::fs::symlink("/dev/zero", &p).unwrap();
        let e = format!("{:#}", read_config(&p).err().unwrap());
        assert!(
            e.contains("train.toml") && e.contains("not a regular file (a character device)"),
            "{e}"
        );
    }

    #[test]
    fn a_sparse_train_config_over_the_cap_is_refused_unread() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("train.toml");
        std::fs::File::create(&p)
            .unwrap()
            .set_len(MAX_CONFIG_BYTES + 1)
            .unwrap();
        let e = format!("{:#}", read_config(&p).err().unwrap());
        assert!(
            e.contains("train.toml")
                && e.contains(&format!(
                    "{} bytes, more than the cap of {MAX_CONFIG_BYTES} bytes for a training config",
                    MAX_CONFIG_BYTES + 1
                )),
            "{e}"
        );
    }
}
