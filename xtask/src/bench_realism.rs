//! `cargo xtask bench-realism`: generators judged as generators on held-out simulated frames
//! (`veila_diffusion::app::realism`): every model row at each sampler setting next to the mean
//! scan, retrieval and the data floor; realism, texture, faithfulness, memorisation, diversity and
//! seconds per scan; `report.md`, `report.json` and `frontier.png` (realism against faithfulness).
//! The benchmark and its report are the library's; this driver parses the flags and shows the run.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use veila_diffusion::SamplerName;
use veila_diffusion::app::realism::{Degradation, RealismOptions};

use crate::bench_real::sampler_parser;
use crate::progress::{Terminal, in_workspace, workspace_root};

/// Arguments of `cargo xtask bench-realism`.
#[derive(Debug, Args)]
pub struct BenchRealismArgs {
    /// Model bundles to score (repeat the flag; none: the baselines and the floor alone).
    #[arg(long = "model")]
    models: Vec<PathBuf>,
    /// The conditional bundle whose encoder heads judge the image agreement (CM-DC, CM-SC) and
    /// whose features retrieve; its training list gives the test list, the baselines and the
    /// memorisation pool.
    #[arg(long, default_value = "models/default")]
    judge: PathBuf,
    /// Samplers of the model rows: ddpm, ddim, dpm (comma-separated; every one at every step
    /// count) [default: each bundle's own].
    #[arg(long, value_delimiter = ',', value_parser = sampler_parser())]
    sampler: Vec<SamplerName>,
    /// Sampler step counts of the model rows [default: each bundle's own].
    #[arg(long, value_delimiter = ',')]
    steps: Vec<usize>,
    /// Where the sampler's steps lie on the schedule: trailing, leading, linspace, log_snr
    /// (comma-separated; every one at every step count) [default: each bundle's own].
    #[arg(long, value_delimiter = ',', value_parser = crate::bench_real::spacing_parser())]
    spacing: Vec<veila_diffusion::Spacing>,
    /// Guidance scales of the conditional model rows [default: each bundle's own].
    #[arg(long, value_delimiter = ',')]
    guidance: Vec<f64>,
    /// Start levels of the rows of bundles with a prior mean network, each above 0 and at most 1
    /// (comma-separated) [default: each bundle's own].
    #[arg(long, value_delimiter = ',')]
    start_t: Vec<f64>,
    /// Calibration rows: the data floor's true scans degraded and scored like a generator's,
    /// noise:P (P % of range noise, above 0 to 100) or blur:K (a K x K window of log range, K odd,
    /// 3 to 15; blur:K:LO-HI blurs only the pixels whose range is LO to HI metres),
    /// comma-separated [default: none].
    #[arg(long, value_delimiter = ',')]
    calibrate: Vec<Degradation>,
    /// Held-out test frames (from the first model's test list), split into --folds folds of
    /// equal size.
    #[arg(long, default_value_t = 402)]
    test_frames: usize,
    /// Folds of the test frames (the spread is over folds and seeds).
    #[arg(long, default_value_t = 3)]
    folds: usize,
    /// Sample seeds per frame (2 or more also give the diversity).
    #[arg(long, default_value_t = 2)]
    seeds: usize,
    /// Training frames of the first model's list: the mean scan, the retrieval database and the
    /// memorisation pool (the first frames of the list, the ones the bundled model trained on).
    #[arg(long, default_value_t = 960)]
    train_frames: usize,
    /// Output folder.
    #[arg(long, default_value = "docs/bench-realism")]
    out: PathBuf,
}

/// Runs the benchmark and writes the report.
pub fn run(args: BenchRealismArgs) -> Result<()> {
    let options = RealismOptions {
        root: workspace_root(),
        models: args.models,
        judge: args.judge,
        samplers: args.sampler,
        steps: args.steps,
        spacings: args.spacing,
        guidance: args.guidance,
        start_t: args.start_t,
        calibrations: args.calibrate,
        test_frames: args.test_frames,
        folds: args.folds,
        seeds: args.seeds,
        train_frames: args.train_frames,
        out: args.out,
        command: crate::progress::command_line(),
    };
    veila_diffusion::app::realism::run(&options, &Terminal::default())?;
    println!("wrote {}", in_workspace(&options.out).display());
    Ok(())
}
