//! `cargo xtask bench-augment`: the augmentation benchmark (`veila_diffusion::app::augment`): a
//! segmenter trained on 1 %, 10 % and 20 % of a split's labels, alone and with scans the bundle
//! generates from the other frames' images, pseudo-labelled by a teacher, next to the true-scan,
//! mean-network and retrieval controls; `report.md` and `report.json`. The benchmark, its work
//! folder (resumable) and its report are the library's; this driver parses the flags.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use veila_diffusion::app::augment::AugmentOptions;
use veila_diffusion::app::segment::{ClassWeighting, SegTrainSettings};

use crate::progress::{Terminal, in_workspace, workspace_root};

/// Arguments of `cargo xtask bench-augment`.
#[derive(Debug, Args)]
pub struct BenchAugmentArgs {
    /// The conditional bundle that generates.
    #[arg(long, default_value = "models/default")]
    model: PathBuf,
    /// The first frames of the bundle's training list (the ones it trained on): skipped by the
    /// split, and the retrieval database.
    #[arg(long, default_value_t = 960)]
    pool_frames: usize,
    /// Frames of the split, after the pool.
    #[arg(long, default_value_t = 600)]
    split_frames: usize,
    /// Held-out frames of the test list (`scenes/test-v5.txt` has 400).
    #[arg(long, default_value_t = 400)]
    test_frames: usize,
    /// Labelled fractions of the split (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "0.01,0.1,0.2")]
    fractions: Vec<f64>,
    /// Training seeds (comma-separated; every row at each).
    #[arg(long, value_delimiter = ',', default_value = "0,1")]
    seeds: Vec<u64>,
    /// Updates of every segmenter run.
    #[arg(long, default_value_t = 300)]
    steps: u64,
    /// Frames per update.
    #[arg(long, default_value_t = 8)]
    batch: usize,
    /// Peak learning rate (cosine to a twentieth of it).
    #[arg(long, default_value_t = 3e-3)]
    lr: f64,
    /// Sampler steps of the generated scans [default: the bundle's].
    #[arg(long)]
    sampler_steps: Option<usize>,
    /// The work folder: each source's scans, each run's checkpoints and result (a rerun resumes;
    /// workers started on the same folder take a run each and split the table between them).
    #[arg(long, default_value = "target/bench-augment")]
    work: PathBuf,
    /// Output folder of the report.
    #[arg(long, default_value = "docs/bench-augment")]
    out: PathBuf,
    /// Write the report from the results in the work folder and stop: renders and trains
    /// nothing; shows a run in progress.
    #[arg(long)]
    report_only: bool,
}

/// Runs the benchmark and writes the report.
pub fn run(args: BenchAugmentArgs) -> Result<()> {
    let root = workspace_root();
    let sampler = match args.sampler_steps {
        None => None,
        Some(steps) => {
            let b = veila_diffusion::app::Bundle::from_dir(
                &root.join(&args.model),
                &candle_core::Device::Cpu,
            )?;
            Some(veila_diffusion::SamplerConfig {
                steps,
                ..b.config.sampler
            })
        }
    };
    let options = AugmentOptions {
        root,
        model: args.model,
        pool_frames: args.pool_frames,
        split_frames: args.split_frames,
        test_frames: args.test_frames,
        fractions: args.fractions,
        seeds: args.seeds,
        train: SegTrainSettings {
            steps: args.steps,
            batch: args.batch,
            lr: args.lr,
            min_lr: args.lr / 20.0,
            warmup_steps: (args.steps / 12).max(1),
            weight_decay: 1e-4,
            seed: 0,
            augment: true,
            checkpoint_every: 40,
            keep_checkpoints: Some(1),
            eval_every: None,
        },
        class_weighting: ClassWeighting::InverseSqrtFrequency,
        sampler,
        work: args.work,
        out: args.out,
        command: crate::progress::command_line(),
    };
    let report = match args.report_only {
        true => veila_diffusion::app::augment::report_from_work(&options)?,
        false => veila_diffusion::app::augment::run(&options, &Terminal::default())?,
    };
    for f in &report.fractions {
        if let Some(v) = &f.generated_vs_supervised {
            println!(
                "{}% labelled, generated scans against supervised only: {} ({:+.1} mIoU points)",
                veila_diffusion::app::augment::pct(f.fraction),
                v.word,
                100.0 * v.mean
            );
        }
    }
    println!(
        "wrote {}",
        in_workspace(&options.out).join("report.md").display()
    );
    Ok(())
}
