//! `cargo xtask train-default`: trains the bundled model (`models/default`) from a fixed seed on
//! the simulator's train split: the two small CNN encoders first (semantics, depth), then the
//! denoiser on their frozen features. Resumable: denoiser checkpoints go to `--work` and a rerun
//! picks up the newest one (the encoders are retrained, which is deterministic).

use std::collections::HashMap;
use std::ops::ControlFlow;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use candle_core::Device;
use candle_nn::VarMap;
use clap::Args;
use veila_diffusion::bundle::{
    Bundle, BundleConfig, DENOISER_FILE, DEPTH_FILE, MEAN_FILE, Method, SEMANTIC_FILE, Variant,
};
use veila_diffusion::pipeline::{
    BundleFit, Stage, TrainExample, fit_bundle, train_small_cnn, varmap_tensors,
};
use veila_diffusion::{StepStats, TrainConfig, TrainObserver};
use veila_nn::encoders::small_cnn::SmallCnn;

use crate::simdata::{SimExample, render_split, workspace_root};

/// Arguments of `cargo xtask train-default`.
#[derive(Debug, Args, Clone)]
pub struct TrainDefaultArgs {
    /// Output bundle folder.
    #[arg(long, default_value = "models/default")]
    pub out: PathBuf,
    /// Model variant (the ablations of the paper; `full` is the bundled model).
    #[arg(long, default_value = "full")]
    pub variant: Variant,
    /// Generative method: eps, v, residual, flow or regression.
    #[arg(long, default_value = "residual")]
    pub method: Method,
    /// Training steps of the mean network (residual method; default: --steps).
    #[arg(long)]
    pub mean_steps: Option<u64>,
    /// Simulated training frames (from scenes/train.txt).
    #[arg(long, default_value_t = 480)]
    pub frames: usize,
    /// Training steps of each encoder.
    #[arg(long, default_value_t = 150)]
    pub encoder_steps: usize,
    /// Denoiser training steps.
    #[arg(long, default_value_t = 1000)]
    pub steps: u64,
    /// Denoiser batch size.
    #[arg(long, default_value_t = 2)]
    pub batch: usize,
    /// Peak learning rate of the denoiser.
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Seed of everything.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Updates between checkpoints (both networks).
    #[arg(long, default_value_t = 250)]
    pub checkpoint_every: u64,
    /// Folder for resumable checkpoints (default: target/train-default/VARIANT-METHOD).
    #[arg(long)]
    pub work: Option<PathBuf>,
    /// Reuse the encoders of this bundle instead of training them (bench-report uses the default
    /// model's encoders for every ablation).
    #[arg(long)]
    pub encoders_from: Option<PathBuf>,
    /// Start the denoiser from this bundle's denoiser weights wherever names and shapes match
    /// (bench-report's fine-tuned ablations); the rest keeps its seeded initialisation.
    #[arg(long)]
    pub init_from: Option<PathBuf>,
}

struct Progress {
    bar: indicatif::ProgressBar,
    ema_loss: Option<f64>,
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}

impl<M: veila_diffusion::Denoiser> TrainObserver<M> for Progress {
    fn on_step(&mut self, s: &StepStats) -> ControlFlow<()> {
        if s.loss.is_finite() {
            self.ema_loss = Some(match self.ema_loss {
                None => s.loss,
                Some(e) => 0.98 * e + 0.02 * s.loss,
            });
        }
        self.bar.set_position(s.step);
        self.bar.set_message(format!(
            "loss {:.4} (avg {:.4}) lr {:.2e} {:.2} s/step",
            s.loss,
            self.ema_loss.unwrap_or(f64::NAN),
            s.lr,
            s.step_secs
        ));
        if self.bar.is_hidden() && (s.step.is_multiple_of(50) || s.step == 1) {
            eprintln!(
                "  step {} loss {:.4} (avg {:.4}) lr {:.2e} {:.2} s/step",
                s.step,
                s.loss,
                self.ema_loss.unwrap_or(f64::NAN),
                s.lr,
                s.step_secs
            );
        }
        ControlFlow::Continue(())
    }
}

/// Trains and writes a bundle; returns the bundle config written.
pub fn run(args: TrainDefaultArgs) -> Result<BundleConfig> {
    run_with(args, None)
}

/// [`run`] on already simulated training frames (`None`: simulate `args.frames` of them).
pub fn run_with(args: TrainDefaultArgs, frames: Option<&[SimExample]>) -> Result<BundleConfig> {
    let t_all = Instant::now();
    let device = Device::Cpu;
    let root = workspace_root();
    let mut cfg = BundleConfig::cpu_default(args.variant);
    cfg = cfg.with_method(args.method);
    let method = cfg.method();
    println!(
        "train-default: variant {} ({}), method {} ({}), {} frames, encoders {} steps, denoiser {} steps x batch {}, seed {}",
        args.variant.name(),
        args.variant.label(),
        method.name(),
        method.label(),
        args.frames,
        args.encoder_steps,
        args.steps,
        args.batch,
        args.seed
    );
    let t = Instant::now();
    let rendered;
    let examples: &[SimExample] = match frames {
        Some(f) => f,
        None => {
            rendered = render_split(
                &root.join("scenes/train.txt"),
                args.frames,
                &cfg,
                "simulating train frames",
            )?;
            &rendered
        }
    };
    let sim_secs = t.elapsed().as_secs_f64();
    println!("  simulated {} frames in {sim_secs:.1} s", examples.len());

    let work = args.work.clone().unwrap_or_else(|| {
        root.join("target/train-default")
            .join(format!("{}-{}", args.variant.name(), method.name()))
    });

    // 1. encoders
    let hw = (cfg.image_height, cfg.image_width);
    let images: Vec<Vec<u8>> = examples.iter().map(|e| e.rgb.clone()).collect();
    let labels: Vec<Vec<u32>> = examples.iter().map(|e| e.labels.clone()).collect();
    let depths: Vec<Vec<f32>> = examples.iter().map(|e| e.depth_m.clone()).collect();
    let t = Instant::now();
    let mut weights: HashMap<&str, HashMap<String, candle_core::Tensor>> = HashMap::new();
    let mut semantic: Option<SmallCnn> = None;
    let mut depth: Option<SmallCnn> = None;
    if let Some(dir) = &args.encoders_from {
        let b = Bundle::from_dir(dir, &device)
            .with_context(|| format!("loading encoders from {}", dir.display()))?;
        if cfg.semantic_encoder.is_some() {
            let s = b
                .semantic
                .clone()
                .context("that bundle has no semantic encoder")?;
            weights.insert(SEMANTIC_FILE, load_tensors(&dir.join(SEMANTIC_FILE))?);
            semantic = Some(s);
        }
        if cfg.depth_encoder.is_some() {
            let d = b
                .depth
                .clone()
                .context("that bundle has no depth encoder")?;
            weights.insert(DEPTH_FILE, load_tensors(&dir.join(DEPTH_FILE))?);
            depth = Some(d);
        }
    } else {
        let train_cnn = |which: &str,
                         c: &veila_nn::encoders::small_cnn::SmallCnnConfig,
                         seed: u64|
         -> Result<(SmallCnn, VarMap)> {
            let bar = crate::progress::progress_bar(args.encoder_steps as u64, which);
            let mut last = f32::NAN;
            let r = train_small_cnn(
                c,
                &images,
                c.semantic_head.then_some(labels.as_slice()),
                c.depth_head.then_some(depths.as_slice()),
                hw,
                args.encoder_steps,
                8,
                2e-3,
                seed,
                &device,
                |s| {
                    last = s.loss;
                    bar.set_position(s.step as u64);
                    bar.set_message(format!("loss {:.4}", s.loss));
                },
            )?;
            bar.finish_and_clear();
            println!("  {which}: final batch loss {last:.4}");
            Ok(r)
        };
        // trained encoders are kept in the work folder, so a resumed run does not train them
        // again (their training is deterministic: the same seed gives the same weights)
        let enc_dir = work.join(format!(
            "encoders-seed{}-steps{}-frames{}",
            args.seed,
            args.encoder_steps,
            examples.len()
        ));
        for (which, c, file, salt) in [
            (
                "semantic encoder",
                cfg.semantic_encoder.clone(),
                SEMANTIC_FILE,
                0x5e,
            ),
            ("depth encoder", cfg.depth_encoder.clone(), DEPTH_FILE, 0xde),
        ] {
            let Some(c) = c else { continue };
            let saved = enc_dir.join(file);
            let tensors = if saved.is_file() {
                println!("  {which}: reusing {}", saved.display());
                load_tensors(&saved)?
            } else {
                let (_, vm) = train_cnn(which, &c, args.seed ^ salt)?;
                let tensors = varmap_tensors(&vm)?;
                std::fs::create_dir_all(&enc_dir)
                    .with_context(|| format!("creating {}", enc_dir.display()))?;
                let bytes = veila_nn::checkpoint::safetensors_bytes(&tensors, &saved)?;
                veila_data::atomic::write_atomic(&saved, &bytes)?;
                tensors
            };
            let net = SmallCnn::new(
                &c,
                candle_nn::VarBuilder::from_tensors(
                    tensors.clone(),
                    candle_core::DType::F32,
                    &device,
                ),
            )?;
            weights.insert(file, tensors);
            if file == SEMANTIC_FILE {
                semantic = Some(net);
            } else {
                depth = Some(net);
            }
        }
    }
    let enc_secs = t.elapsed().as_secs_f64();

    // 2. denoiser
    let t = Instant::now();
    let init = args
        .init_from
        .as_ref()
        .map(|dir| {
            Bundle::from_dir(dir, &device)
                .map(|b| b.weights)
                .with_context(|| format!("loading initial weights from {}", dir.display()))
        })
        .transpose()?;
    let train_examples: Vec<TrainExample> = examples
        .iter()
        .map(|e| e.train_example(&cfg))
        .collect::<Result<_>>()?;
    let tc = TrainConfig {
        seed: args.seed,
        lr: args.lr,
        min_lr: args.lr * 0.05,
        warmup_steps: (args.steps / 20).max(1),
        total_steps: args.steps,
        ema_decay: 0.995,
        cond_drop_prob: if cfg.denoiser.conditioning.is_some() {
            0.1
        } else {
            0.0
        },
        checkpoint_every: Some(args.checkpoint_every.max(1)),
        keep_checkpoints: Some(2),
        ..TrainConfig::default()
    };
    let mean_steps = args.mean_steps.unwrap_or(args.steps);
    let mean_tc = TrainConfig {
        seed: args.seed ^ 0x3ea,
        total_steps: mean_steps,
        warmup_steps: (mean_steps / 20).max(1),
        ..tc.clone()
    };
    // a work folder resumes only the run it was made for: same model, diffusion and training
    // settings, same data
    let run_key = serde_json::json!({
        "denoiser": cfg.denoiser,
        "diffusion": cfg.diffusion,
        "residual": cfg.residual.as_ref().map(|r| &r.mean_net),
        "encoding": cfg.encoding,
        "train": tc,
        "mean_train": cfg.residual.as_ref().map(|_| &mean_tc),
        "frames": examples.len(),
        "batch": args.batch,
        "encoders_from": args.encoders_from,
        "init_from": args.init_from,
    });
    veila_diffusion::claim_checkpoint_dir(&work, &run_key)
        .with_context(|| "pass another --work to start a separate run")?;
    let outcome = fit_bundle(
        &mut cfg,
        BundleFit {
            semantic: semantic.as_ref(),
            depth: depth.as_ref(),
            examples: &train_examples,
            batch_size: args.batch,
            train: &tc,
            mean_train: Some(&mean_tc),
            work_dir: &work,
            init: init.as_ref(),
        },
        &device,
        |stage, p, step| println!("  {stage:?}: resumed from {} (step {step})", p.display()),
        |stage, total| Progress {
            bar: crate::progress::progress_bar(
                total,
                match stage {
                    Stage::Mean => "mean network",
                    Stage::Denoiser => "denoiser",
                },
            ),
            ema_loss: None,
        },
    )?;
    let den = outcome
        .denoiser
        .context("the mean network's run stopped early")?;
    if let Some(dir) = &args.init_from {
        println!(
            "  initialised {} of {} denoiser tensors from {}",
            den.initialised,
            den.ema_weights.len(),
            dir.display()
        );
    }
    let summary = den.summary;
    let den_secs = t.elapsed().as_secs_f64();
    // the runs' own clocks, summed over every resumed session (this process's seconds are below)
    let clock = |c: veila_diffusion::Clock| serde_json::json!({ "seconds": c.seconds.round(), "from_step": c.from_step });
    let train_clock = serde_json::json!({
        "mean": outcome.mean.as_ref().map(|m| clock(m.summary.clock)),
        "denoiser": clock(summary.clock),
    });
    if let Some(m) = &outcome.mean {
        println!(
            "  mean network: {} steps this run, mean loss {:.4}, {:.0} s; residual scale {:?}",
            m.summary.steps_run,
            m.summary.mean_loss,
            outcome.seconds[0],
            cfg.residual.as_ref().map(|r| &r.scale)
        );
    }
    println!(
        "  denoiser: {} steps this run, mean loss {:.4}, {} skipped, {:.0} s",
        summary.steps_run, summary.mean_loss, summary.skipped, outcome.seconds[1]
    );
    if let Some(m) = outcome.mean {
        weights.insert(MEAN_FILE, m.ema_weights);
    }
    weights.insert(DENOISER_FILE, den.ema_weights);

    cfg.provenance = serde_json::json!({
        "trained_by": "cargo xtask train-default",
        "variant": args.variant.name(),
        "method": method.name(),
        "seed": args.seed,
        "train_split": "scenes/train.txt",
        "frames": examples.len(),
        "encoder_steps": if args.encoders_from.is_some() { 0 } else { args.encoder_steps },
        "encoders_from": args.encoders_from.as_ref().map(|p| p.display().to_string()),
        "denoiser_steps": args.steps,
        "mean_steps": cfg.residual.as_ref().map(|_| mean_steps),
        "training_samples": (args.steps + cfg.residual.as_ref().map_or(0, |_| mean_steps)) * args.batch as u64,
        "batch": args.batch,
        "lr": args.lr,
        "ema_decay": tc.ema_decay,
        "cond_drop_prob": tc.cond_drop_prob,
        "final_mean_loss": summary.mean_loss,
        "train_wall_seconds": train_clock,
        "seconds": {
            "simulation": sim_secs.round(),
            "encoders": enc_secs.round(),
            "mean": outcome.seconds[0].round(),
            "denoiser": outcome.seconds[1].round(),
            "total": (sim_secs + enc_secs + den_secs).round(),
        },
    });
    Bundle::save(&args.out, &cfg, &weights)?;
    // read back through the verifying loader
    Bundle::from_dir(&args.out, &device)
        .with_context(|| format!("re-reading {}", args.out.display()))?;
    println!(
        "wrote {} in {:.0} s ({} parameters in the denoiser)",
        args.out.display(),
        t_all.elapsed().as_secs_f64(),
        veila_nn::checkpoint::parameter_count(&cfg.denoiser)?
    );
    Ok(cfg)
}

fn load_tensors(path: &std::path::Path) -> Result<HashMap<String, candle_core::Tensor>> {
    candle_core::safetensors::load(path, &Device::Cpu)
        .with_context(|| format!("reading {}", path.display()))
}
