//! `cargo xtask bench-report`: Veila against the unconditional baseline and every ablation on a
//! held-out simulator test split, and what generation quality costs in time (sampler x steps).
//! The benchmark is `veila_diffusion::app::bench_report`; this driver parses the flags, resolves
//! the paths in the workspace and shows the run.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use clap::Args;
use veila_diffusion::SamplerName;
use veila_diffusion::app::bench_report::{BenchReportOptions, Protocol};
use veila_diffusion::app::bundle::Variant;

use crate::bench_real::{protocol_parser, sampler_parser};
use crate::progress::{Terminal, in_workspace, workspace_root};

/// Arguments of `cargo xtask bench-report`.
#[derive(Debug, Args)]
pub struct BenchReportArgs {
    /// Output folder (report.md, report.json, *.png).
    #[arg(long, default_value = "target/bench-report")]
    out: PathBuf,
    /// The bundle whose encoders every variant shares (and whose denoiser the sampler sweep uses).
    #[arg(long, default_value = "models/default")]
    model: PathBuf,
    /// Held-out test frames (from --test-scenes, interleaving its scene files), split into
    /// `--folds` disjoint folds: every metric is computed per fold (and seed), and the spread is
    /// over folds and seeds.
    #[arg(long, default_value_t = 120)]
    test_frames: usize,
    /// Scene list of the held-out test frames [default: the one beside the bundle's training list:
    /// `scenes/test.txt` for `scenes/train.txt`, `test-v5.txt` for `train-v5.txt`]. The baselines
    /// are built from the bundle's own training list.
    #[arg(long)]
    test_scenes: Option<PathBuf>,
    /// Disjoint folds of the test frames.
    #[arg(long, default_value_t = 3)]
    folds: usize,
    /// Training frames (the bundle's training list) behind the baselines: their per-pixel median scan, and
    /// the retrieval database.
    #[arg(long, default_value_t = 480)]
    baseline_frames: usize,
    /// Sample seeds per variant (the spread is over seeds).
    #[arg(long, default_value_t = 3)]
    seeds: u64,
    /// How the variants are trained: `finetune` starts every variant from the bundled model's
    /// denoiser (weights whose names and shapes still match) and trains it `--train-steps` more with
    /// its switch flipped, the full model included as the control; `scratch` trains every variant
    /// from a seeded initialisation (the paper's protocol; as long as `cargo xtask train-default`
    /// per variant).
    #[arg(long, default_value = "finetune", value_parser = protocol_parser())]
    protocol: Protocol,
    /// Denoiser training steps of every variant.
    #[arg(long, default_value_t = 300)]
    train_steps: u64,
    /// Training frames of every variant.
    #[arg(long, default_value_t = 480)]
    train_frames: usize,
    /// Sampler of the model rows (the bundled model, its variants and the residual-weight
    /// sweep): ddpm, ddim (η = 0) or dpm (DPM-Solver++(2M), the bundle's default).
    #[arg(long, default_value = "dpm", value_parser = sampler_parser())]
    sampler: SamplerName,
    /// Sampler steps of the model rows.
    #[arg(long, default_value_t = 16)]
    steps: usize,
    /// Variants to compare (comma-separated; default all).
    #[arg(long, value_delimiter = ',')]
    variants: Option<Vec<Variant>>,
    /// No ablation variants: only the bundled model as shipped (and, under `finetune`, its own
    /// unconditional branch, which needs no training) next to the baselines and the floor.
    #[arg(long, conflicts_with = "variants")]
    shipped_only: bool,
    /// Residual weights of the sweep for a residual-diffusion bundle (0 = its mean network alone,
    /// 1 = full samples), with `--sampler` at `--steps` steps.
    #[arg(long, value_delimiter = ',', default_value = "0,0.25,0.5,0.75")]
    sweep_residual_weights: Vec<f64>,
    /// Test frames for the sampler sweep.
    #[arg(long, default_value_t = 8)]
    sweep_frames: usize,
    /// Step counts of the sampler sweep.
    #[arg(long, value_delimiter = ',', default_value = "4,8,16,32")]
    sweep_steps: Vec<usize>,
    /// Where trained variants are kept between runs.
    #[arg(long, default_value = "target/bench-report")]
    work: PathBuf,
    /// A small, fast configuration (12 test frames, 2 seeds, 40 training steps, sweep on 3 frames
    /// with 4/8/16 steps): a smoke run whose numbers show the pipeline, not converged models.
    #[arg(long)]
    quick: bool,
    /// Leave out the real frames of `../shared/data/real`.
    #[arg(long)]
    no_real: bool,
    /// Samples per real frame.
    #[arg(long, default_value_t = 4)]
    real_seeds: usize,
}

/// Runs the benchmark and writes the report.
pub fn run(args: BenchReportArgs) -> Result<()> {
    let t_all = Instant::now();
    let options = BenchReportOptions {
        root: workspace_root(),
        out: in_workspace(&args.out),
        model: in_workspace(&args.model),
        work: in_workspace(&args.work),
        command: crate::progress::command_line(),
        test_frames: args.test_frames,
        test_scenes: args.test_scenes,
        folds: args.folds,
        baseline_frames: args.baseline_frames,
        seeds: args.seeds,
        protocol: args.protocol,
        train_steps: args.train_steps,
        train_frames: args.train_frames,
        sampler: args.sampler,
        steps: args.steps,
        variants: args.variants,
        shipped_only: args.shipped_only,
        sweep_residual_weights: args.sweep_residual_weights,
        sweep_frames: args.sweep_frames,
        sweep_steps: args.sweep_steps,
        quick: args.quick,
        no_real: args.no_real,
        real_seeds: args.real_seeds,
    };
    let out = options.out.clone();
    veila_diffusion::app::bench_report::run(options, &Terminal::default())?;
    println!(
        "wrote {} in {:.0} s",
        out.display(),
        t_all.elapsed().as_secs_f64()
    );
    Ok(())
}
