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
    Bundle, BundleConfig, DENOISER_FILE, DEPTH_FILE, SEMANTIC_FILE, Variant,
};
use veila_diffusion::pipeline::{
    DenoiserFit, TrainExample, fit_denoiser, train_small_cnn, varmap_tensors,
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
    /// Folder for resumable denoiser checkpoints (default: target/train-default/VARIANT).
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
    println!(
        "train-default: variant {} ({}), {} frames, encoders {} steps, denoiser {} steps x batch {}, seed {}",
        args.variant.name(),
        args.variant.label(),
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
            let bar = crate::progress_bar(args.encoder_steps as u64, which);
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
        if let Some(c) = cfg.semantic_encoder.clone() {
            let (net, vm) = train_cnn("semantic encoder", &c, args.seed ^ 0x5e)?;
            weights.insert(SEMANTIC_FILE, varmap_tensors(&vm)?);
            semantic = Some(net);
        }
        if let Some(c) = cfg.depth_encoder.clone() {
            let (net, vm) = train_cnn("depth encoder", &c, args.seed ^ 0xde)?;
            weights.insert(DEPTH_FILE, varmap_tensors(&vm)?);
            depth = Some(net);
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
        checkpoint_every: Some(250),
        keep_checkpoints: Some(2),
        ..TrainConfig::default()
    };
    let work = args
        .work
        .clone()
        .unwrap_or_else(|| root.join("target/train-default").join(args.variant.name()));
    // a work folder resumes only the run it was made for: same model, diffusion and training
    // settings, same data
    let run_key = serde_json::json!({
        "denoiser": cfg.denoiser,
        "diffusion": cfg.diffusion,
        "encoding": cfg.encoding,
        "train": tc,
        "frames": examples.len(),
        "batch": args.batch,
        "encoders_from": args.encoders_from,
        "init_from": args.init_from,
    });
    veila_diffusion::claim_checkpoint_dir(&work, &run_key)
        .with_context(|| "pass another --work to start a separate run")?;
    let mut progress = Progress {
        bar: crate::progress_bar(args.steps, "denoiser"),
        ema_loss: None,
    };
    let bar = progress.bar.clone();
    let outcome = fit_denoiser(
        &cfg,
        DenoiserFit {
            semantic: semantic.as_ref(),
            depth: depth.as_ref(),
            examples: &train_examples,
            batch_size: args.batch,
            train: &tc,
            checkpoint_dir: &work,
            init: init.as_ref(),
        },
        &device,
        |p, step| {
            println!("  resumed from {} (step {step})", p.display());
            bar.set_position(step);
        },
        &mut progress,
    )?;
    progress.bar.finish_and_clear();
    if let Some(dir) = &args.init_from {
        println!(
            "  initialised {} of {} denoiser tensors from {}",
            outcome.initialised,
            outcome.ema_weights.len(),
            dir.display()
        );
    }
    let summary = outcome.summary;
    let den_secs = t.elapsed().as_secs_f64();
    println!(
        "  denoiser: {} steps this run, mean loss {:.4}, {} skipped, {:.0} s",
        summary.steps_run, summary.mean_loss, summary.skipped, den_secs
    );
    weights.insert(DENOISER_FILE, outcome.ema_weights);

    cfg.provenance = serde_json::json!({
        "trained_by": "cargo xtask train-default",
        "variant": args.variant.name(),
        "seed": args.seed,
        "train_split": "scenes/train.txt",
        "frames": examples.len(),
        "encoder_steps": if args.encoders_from.is_some() { 0 } else { args.encoder_steps },
        "encoders_from": args.encoders_from.as_ref().map(|p| p.display().to_string()),
        "denoiser_steps": args.steps,
        "batch": args.batch,
        "lr": args.lr,
        "ema_decay": tc.ema_decay,
        "cond_drop_prob": tc.cond_drop_prob,
        "final_mean_loss": summary.mean_loss,
        "seconds": {
            "simulation": sim_secs.round(),
            "encoders": enc_secs.round(),
            "denoiser": den_secs.round(),
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
