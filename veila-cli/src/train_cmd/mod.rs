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
//! ([`crate::transport::tcp`]), each trains on its share of every global batch of `[train] batch`, the
//! gradients are averaged before each update, and rank 0 alone writes checkpoints, the log and the
//! bundle (the other ranks log to `train_log.rank-N.jsonl`). The output folder must be shared.
//!
//! The config's schema and what it gives (the bundle config, the recipe settings) are
//! `veila_diffusion::app::train_config`; the shards become examples in
//! `veila_diffusion::app::train_data`. This module reads the TOML, draws the progress and writes
//! the log.

mod data;
mod log;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::Device;
use clap::Args;
use veila_data::read_capped::{
    MAX_CONFIG_BYTES, MAX_JSON_METADATA_BYTES, read_metadata, read_metadata_string,
};
use veila_diffusion::app::bundle::{Bundle, sha256_hex};
use veila_diffusion::app::train_config::{RunFingerprint, TrainFile};
use veila_diffusion::app::{
    BundleConfig, EncoderData, EncoderSource, Examples, RecipeInput, RecipeOutcome, TrainExample,
    run_recipe,
};
use veila_diffusion::trainer::distributed::{Parallel, ProcessGroup};
use veila_diffusion::{LossAverage, Precision};

use self::data::{EncoderMemory, TrainData, load_data};
use self::log::{EncoderProgress, Progress, TRAIN_LOG, TrainLog};
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
    note_bf16_on_cpu(file.train.precision, &device);
    // data-parallel when a launcher (torchrun, srun) started several of us
    let group = ProcessGroup::from_env()?;
    let parallel = join_ranks(&args.config, file.train.batch, &group, &device)?;
    let run = TrainRun {
        ck_dir: file.output.dir.join("checkpoints"),
        args,
        file,
        device,
        group,
        parallel,
    };
    let _run_lock = run.claim_folder()?;
    let mut data = load_data(&run.file, &cfg)?;
    let fingerprint = run.claim_checkpoints(&cfg, &data)?;
    let trained = run.train(&mut cfg, &mut data)?;
    let Some(mean_loss) = run.report_fit(&trained.outcome) else {
        return Ok(());
    };
    cfg.provenance = run.provenance(&data, &fingerprint, mean_loss, &trained);
    run.write_bundle(&cfg, trained.outcome, t_all)
}

/// bf16 on the CPU is slower than f32: a note says so.
fn note_bf16_on_cpu(precision: Precision, device: &Device) {
    if precision == Precision::Bf16 && device.is_cpu() {
        eprintln!(
            "note: precision = \"bf16\" on the CPU runs slower than f32 (candle's CPU backend has \
             no bf16 convolution or matrix kernels); it is meant for GPUs (--device cuda)"
        );
    }
}

/// The other ranks met over TCP (and NCCL on GPUs of an NCCL build) when a launcher started
/// several processes; `None` for one process. `batch` is the global batch of the config at
/// `config`.
fn join_ranks(
    config: &Path,
    batch: usize,
    group: &ProcessGroup,
    device: &Device,
) -> Result<Option<Parallel>> {
    if group.world_size <= 1 {
        return Ok(None);
    }
    if batch < group.world_size {
        bail!(
            "{}: [train] batch {} is smaller than the {} ranks (the batch is the global one, shared by the ranks)",
            config.display(),
            batch,
            group.world_size
        );
    }
    let tcp = crate::transport::tcp::TcpGroup::connect(group, std::time::Duration::from_secs(300))?;
    // on GPUs of an NCCL build the gradients go over NCCL (the TCP group only bootstraps it)
    #[cfg(feature = "nccl")]
    let comm: Box<dyn veila_diffusion::trainer::distributed::Communicator> = if device.is_cuda() {
        let mut tcp = tcp;
        Box::new(crate::transport::nccl::NcclGroup::connect(
            device, &mut tcp,
        )?)
    } else {
        Box::new(tcp)
    };
    #[cfg(not(feature = "nccl"))]
    let comm: Box<dyn veila_diffusion::trainer::distributed::Communicator> = {
        let _ = device;
        Box::new(tcp)
    };
    eprintln!(
        "train: rank {} of {} (local rank {})",
        group.rank, group.world_size, group.local_rank
    );
    Ok(Some(Parallel::new(group.clone(), comm)?))
}

/// What the run trained: the recipe's outcome and the seconds of its networks.
struct Trained {
    outcome: RecipeOutcome,
    /// Seconds of the mean network and the denoiser together.
    networks_secs: f64,
}

/// One `veila train` run: what its steps share.
struct TrainRun {
    args: TrainArgs,
    file: TrainFile,
    device: Device,
    group: ProcessGroup,
    parallel: Option<Parallel>,
    /// `OUTPUT/checkpoints`.
    ck_dir: PathBuf,
}

impl TrainRun {
    /// The run folder: train's own, none of its inputs, locked for the whole run (rank 0); a
    /// killed earlier run's partial files go, checkpoints stay.
    fn claim_folder(&self) -> Result<Option<crate::staging::FolderLock>> {
        if !self.group.is_main() {
            return Ok(None);
        }
        let file = &self.file;
        let mut inputs = crate::staging::TrainInputs::default();
        inputs
            .folder("[data] shards folder", &file.data.shards)
            .file("training config", &self.args.config);
        let m = &file.model;
        if let Some(p) = &m.encoders_from {
            inputs.folder("[model] encoders_from bundle", p);
        }
        if let Some(p) = &m.init_from {
            inputs.folder("[model] init_from bundle", p);
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
        Ok(Some(crate::staging::claim_train_run(
            &file.output.dir,
            crate::staging::BUNDLE,
            self.group.world_size,
            &inputs,
        )?))
    }

    /// Step 2, resumability: the run's fingerprint, claimed for the checkpoint folder by rank 0
    /// (the others wait for its claim).
    fn claim_checkpoints(&self, cfg: &BundleConfig, data: &TrainData) -> Result<RunFingerprint> {
        let file = &self.file;
        let manifest_bytes = read_metadata(
            &data.manifest_path,
            MAX_JSON_METADATA_BYTES,
            "a shard manifest",
        )?;
        let fingerprint = RunFingerprint {
            bundle: cfg.clone(),
            train: serde_json::to_value(&file.train)?,
            data_manifest_sha256: sha256_hex(&manifest_bytes),
            samples: data.samples,
            encoders_from: file
                .model
                .encoders_from
                .as_ref()
                .map(|p| p.display().to_string()),
            init_from: file
                .model
                .init_from
                .as_ref()
                .map(|p| p.display().to_string()),
        };
        let out = &file.output.dir;
        if self.group.is_main() {
            veila_diffusion::claim_checkpoint_dir(&self.ck_dir, &fingerprint).with_context(|| {
                format!(
                    "{}: model, [train] or data changed since these checkpoints; use another [output] dir",
                    out.display()
                )
            })?;
            // a finished run's bundle is replaced only with --force (checked before the work)
            crate::staging::check_train_bundle(out, crate::staging::BUNDLE, self.args.force)?;
        }
        if let Some(p) = &self.parallel {
            // the others wait for rank 0's claim (and learn whether it failed: a zero sum)
            let mut ok = [1f32];
            p.communicator().all_reduce_sum(&mut ok)?;
            if ok[0] < self.group.world_size as f32 {
                bail!("rank {}: another rank failed to start", self.group.rank);
            }
        }
        Ok(fingerprint)
    }

    /// Where the encoders come from: `[model] encoders_from`, or trained on the data (which then
    /// needs semantic train ids for a small-CNN semantic encoder).
    fn encoder_source<'a>(
        &'a self,
        cfg: &BundleConfig,
        data: &'a TrainData,
        memory: &'a EncoderMemory,
        enc_dir: &'a Path,
    ) -> Result<EncoderSource<'a>> {
        if let Some(dir) = &self.file.model.encoders_from {
            return Ok(EncoderSource::Bundle(dir));
        }
        let has_labels = if data.stream.is_some() {
            data.first_has_labels
        } else {
            memory.labels.is_some()
        };
        if cfg
            .semantic_encoder
            .as_ref()
            .is_some_and(|e| e.small_cnn_config().is_some())
            && !has_labels
        {
            bail!(
                "{}: the shards carry no semantic train ids (`label`), so the semantic encoder cannot be trained: \
                 convert with a label map (SemanticKITTI) or set [model] encoders_from = \"models/default\"",
                self.file.data.shards.display()
            );
        }
        Ok(EncoderSource::Train {
            data: match &data.stream {
                Some(source) => EncoderData::Stream(source),
                None => EncoderData::Memory {
                    images: &memory.images,
                    labels: memory.labels.as_deref(),
                    depth_m: &memory.depths,
                    cameras: Some(&memory.cameras),
                },
            },
            dir: enc_dir,
        })
    }

    /// Steps 3 and 4, the encoders and the networks: the shared recipe, with progress bars and
    /// the training log. The in-memory examples are used up.
    fn train(&self, cfg: &mut BundleConfig, data: &mut TrainData) -> Result<Trained> {
        let settings = self.file.train.recipe_settings();
        let enc_dir = self.ck_dir.join(ENCODER_DIR);
        let prepared = std::mem::take(&mut data.prepared);
        let data = &*data;
        let memory = EncoderMemory::of(&prepared);
        let encoders = self.encoder_source(cfg, data, &memory, &enc_dir)?;
        let init = match &self.file.model.init_from {
            Some(dir) => Some(Bundle::from_dir(dir, &self.device).with_context(|| {
                format!(
                    "{}: [model] init_from {}",
                    self.args.config.display(),
                    dir.display()
                )
            })?),
            None => None,
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
        let mut encoder_progress = EncoderProgress::default();
        let run = std::rc::Rc::new(std::cell::Cell::new(0u64));
        let log = std::rc::Rc::new(TrainLog::open(self.log_path())?);
        let outcome = run_recipe(
            cfg,
            RecipeInput {
                encoders,
                examples: match &data.stream {
                    Some(source) => Examples::Stream {
                        source,
                        prefetch: self.file.data.prefetch.max(1),
                    },
                    None => (&examples).into(),
                },
                work_dir: &self.ck_dir,
                init: init.as_ref().map(|b| &b.weights),
                mean_init: init.as_ref().and_then(|b| b.mean.as_ref().map(|(_, w)| w)),
                parallel: self.parallel.as_ref(),
            },
            &settings,
            &self.device,
            |event| encoder_progress.event(event),
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
                stop_after: self.args.stop_after,
                run: run.clone(),
                stage,
                log: log.clone(),
            },
        )
        .map_err(|e| self.blame(e))?;
        let mut encoder_note = encoder_progress.note;
        if let Some(dir) = &self.file.model.encoders_from {
            encoder_note = format!("from {}", dir.display());
        }
        if !encoder_note.is_empty() {
            println!("  encoders: {}", encoder_note.trim_end_matches("; "));
        }
        if let Some(dir) = &self.file.model.init_from {
            let fit = &outcome.fit;
            for (what, f) in [("mean-network", &fit.mean), ("denoiser", &fit.denoiser)] {
                if let Some(f) = f {
                    let (n, of) = (f.initialised, f.ema_weights.len());
                    println!(
                        "  {what}: {n} of {of} tensors started from {}",
                        dir.display()
                    );
                }
            }
        }
        let networks_secs = t_den.elapsed().as_secs_f64() - outcome.encoder_seconds;
        Ok(Trained {
            outcome,
            networks_secs,
        })
    }

    /// `OUTPUT/train_log.jsonl` for rank 0, `train_log.rank-N.jsonl` for the others.
    fn log_path(&self) -> PathBuf {
        let out = &self.file.output.dir;
        if self.group.is_main() {
            out.join(TRAIN_LOG)
        } else {
            out.join(format!("train_log.rank-{}.jsonl", self.group.rank))
        }
    }

    /// A training error in context: only a failure to load `[model] encoders_from` is blamed on
    /// it, and only weights that do not fit on `[model] init_from`; the others say what failed.
    fn blame(&self, e: veila_diffusion::Error) -> anyhow::Error {
        match e {
            e @ veila_diffusion::Error::EncodersFrom { .. } => anyhow::Error::new(e).context(
                format!("{}: [model] encoders_from", self.args.config.display()),
            ),
            e @ veila_diffusion::Error::InvalidConfig { field: "init", .. } => {
                let dir = self
                    .file
                    .model
                    .init_from
                    .as_deref()
                    .unwrap_or(Path::new("?"));
                anyhow::Error::new(e).context(format!(
                    "{}: [model] init_from {}",
                    self.args.config.display(),
                    dir.display()
                ))
            }
            e => anyhow::Error::new(e).context(format!(
                "training (checkpoints in {})",
                self.ck_dir.display()
            )),
        }
    }

    /// Prints what the mean network and the denoiser did. The denoiser's mean loss of this run
    /// when the bundle is to be written; `None` when the run stopped early (rerun to continue) or
    /// this rank does not write the bundle.
    fn report_fit(&self, outcome: &RecipeOutcome) -> Option<f64> {
        let steps = self.file.train.steps;
        let mean_steps = self.file.train.recipe_settings().mean_steps();
        let config = self.args.config.display();
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
            Some(d) if d.step >= steps => d,
            Some(d) => {
                print_denoiser_summary(d, steps, outcome.fit.seconds[1]);
                println!(
                    "stopped at step {} of {steps}; checkpoint in {}: rerun `veila train --config {config}` to continue",
                    d.step,
                    self.ck_dir.display(),
                );
                return None;
            }
            None => {
                let at = outcome.fit.mean.as_ref().map_or(0, |m| m.step);
                println!(
                    "stopped the mean network at step {at} of {mean_steps}; checkpoint in {}: rerun `veila train --config {config}` to continue",
                    self.ck_dir.join("mean").display(),
                );
                return None;
            }
        };
        print_denoiser_summary(den, steps, outcome.fit.seconds[1]);
        if !self.group.is_main() {
            println!("rank {}: done; rank 0 writes the bundle", self.group.rank);
            return None;
        }
        Some(den.summary.mean_loss)
    }

    /// Step 5: how the bundle was made, for its config's `provenance`.
    fn provenance(
        &self,
        data: &TrainData,
        fingerprint: &RunFingerprint,
        mean_loss: f64,
        trained: &Trained,
    ) -> serde_json::Value {
        serde_json::json!({
            "trained_by": "veila train",
            "config": self.args.config.display().to_string(),
            "data": self.file.data.shards.display().to_string(),
            "dataset": data.manifest.dataset,
            "data_manifest_sha256": fingerprint.data_manifest_sha256,
            "samples": fingerprint.samples,
            "encoders_from": fingerprint.encoders_from,
            "init_from": fingerprint.init_from,
            "train": fingerprint.train,
            "ranks": self.group.world_size,
            "final_mean_loss_this_run": mean_loss,
            "seconds_this_run": {
                "encoders": trained.outcome.encoder_seconds.round(),
                "denoiser": trained.networks_secs.round(),
            },
        })
    }

    /// Writes `OUTPUT/bundle` and reads it back.
    fn write_bundle(
        &self,
        cfg: &BundleConfig,
        outcome: RecipeOutcome,
        t_all: Instant,
    ) -> Result<()> {
        let bundle_dir = self.file.output.dir.join("bundle");
        Bundle::save(&bundle_dir, cfg, &outcome.into_weights())?;
        Bundle::from_dir(&bundle_dir, &self.device)
            .with_context(|| format!("re-reading {}", bundle_dir.display()))?;
        println!(
            "wrote {} in {:.0} s ({} denoiser parameters); generate with `veila generate --model {} ...`",
            bundle_dir.display(),
            t_all.elapsed().as_secs_f64(),
            veila_nn::checkpoint::parameter_count(&cfg.denoiser)?,
            bundle_dir.display()
        );
        if let Some(mib) = progress::peak_host_mib() {
            println!("peak host memory: {mib:.0} MiB");
        }
        Ok(())
    }
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
