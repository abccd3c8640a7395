//! `veila bench`'s arguments, its plan of rows and the records a row and the report are made of.

use std::path::PathBuf;

use clap::Args;
use serde::{Deserialize, Serialize};
use veila_diffusion::ActivationCheckpointing;
use veila_diffusion::Precision;

/// Arguments of `veila bench`.
#[derive(Debug, Args)]
pub(crate) struct BenchArgs {
    /// Networks to time: `bundled` (the bundle's denoiser, --model), `paper`
    /// (DenoiserConfig::paper(): 64 x 1024, the paper's widths; slow on a CPU).
    #[arg(long, value_delimiter = ',', default_value = "bundled,paper")]
    pub(super) models: Vec<String>,
    /// Precisions of the training update: f32, bf16 (mixed precision; for GPUs).
    #[arg(long, value_delimiter = ',', default_value = "f32,bf16", value_parser = parse_precision)]
    pub(super) precision: Vec<Precision>,
    /// Training batch sizes, 1 to 4096, comma-separated: each is a row; two or more also give
    /// the per-sample training memory.
    #[arg(long, value_name = "B", value_delimiter = ',', default_value = "8", value_parser = crate::bounds::int::<usize>(1, 4096))]
    pub(super) batch: Vec<usize>,
    /// Activation checkpointing of the training update: none, block (each residual block, GCMA
    /// and PFC layer recomputed in the backward pass: less memory, one more forward pass).
    #[arg(long, value_delimiter = ',', default_value = "none", value_parser = parse_checkpointing)]
    pub(super) activation_checkpointing: Vec<ActivationCheckpointing>,
    /// Time and measure the training update alone: no sampling evaluation, no end-to-end
    /// generation.
    #[arg(long)]
    pub(super) no_eval: bool,
    /// Timed training updates, 1 to 1000 (after 2 warm-up updates).
    #[arg(long, value_name = "N", default_value_t = 5, value_parser = crate::bounds::int::<usize>(1, 1000))]
    pub(super) train_runs: usize,
    /// Timed network evaluations for sampling, 1 to 1000 (after 2 warm-up runs).
    #[arg(long, value_name = "N", default_value_t = 5, value_parser = crate::bounds::int::<usize>(1, 1000))]
    pub(super) forward_runs: usize,
    /// Sampler step counts to cost, 1 to 10000 each, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "16,32,64", value_parser = crate::bounds::int::<usize>(1, 10_000))]
    pub(super) sample_steps: Vec<usize>,
    /// Skip `Bundle::generate` end to end (the bundled network's real sampling).
    #[arg(long)]
    pub(super) no_generate: bool,
    /// Model bundle folder of `bundled` (default: $VEILA_MODEL, else the bundled models/default;
    /// `--checkpoint` is an alias).
    #[arg(long, value_name = "DIR", env = "VEILA_MODEL", alias = "checkpoint")]
    pub(super) model: Option<PathBuf>,
    /// Seed of the weights and inputs, 0 to 18446744073709551615.
    #[arg(long, default_value_t = 0)]
    pub(super) seed: u64,
    /// Also write the results as one JSON object to this file.
    #[arg(long, value_name = "FILE")]
    pub(super) json: Option<PathBuf>,
    /// Replace an existing --json file.
    #[arg(long)]
    pub(super) force: bool,
    /// Internal: measure row N of the plan in this process and print it as one JSON line (every
    /// row runs in a fresh process).
    #[arg(long, hide = true, value_name = "N")]
    pub(super) worker_row: Option<usize>,
}

pub(super) fn parse_precision(s: &str) -> std::result::Result<Precision, String> {
    s.parse::<Precision>().map_err(|e| e.to_string())
}

pub(super) fn parse_checkpointing(s: &str) -> std::result::Result<ActivationCheckpointing, String> {
    s.parse::<ActivationCheckpointing>()
        .map_err(|e| e.to_string())
}

/// The first line of a worker's JSON row on its standard output.
pub(super) const ROW_MARKER: &str = "veila-bench-row ";

/// One measured row: a network at one precision, checkpointing mode and batch.
#[derive(Debug, Serialize, Deserialize)]
pub(super) struct Row {
    pub(super) model: String,
    pub(super) precision: String,
    pub(super) activation_checkpointing: String,
    pub(super) grid: [usize; 2],
    pub(super) params: usize,
    pub(super) batch: usize,
    /// Median of one training update (condition fusion, forward, loss, backward, AdamW).
    pub(super) train_step_ms: f64,
    pub(super) train_samples_per_s: f64,
    /// Median of one network evaluation at batch 2 (a guidance pair), condition prepared once,
    /// on detached weights (`None` with `--no-eval`).
    pub(super) eval_b2_ms: Option<f64>,
    /// `steps -> seconds per scan` from `eval_b2_ms` (network evaluations only).
    pub(super) sample_s_per_scan: Vec<(usize, f64)>,
    /// Peak memory of the row in MiB (see the module doc; `None` where it cannot be read).
    pub(super) peak_memory_mib: Option<f64>,
    /// What `peak_memory_mib` is: `VmHWM` (host) or `nvidia-smi` (device).
    pub(super) peak_memory_source: String,
}

/// `Bundle::generate` end to end at each step count (f32, one scan, the bundle's sampler kind).
#[derive(Debug, Serialize)]
pub(super) struct GenerateRow {
    pub(super) steps: usize,
    pub(super) seconds_per_scan: f64,
}

/// A row the memory could not hold.
#[derive(Debug, Serialize)]
pub(super) struct OutOfMemory {
    pub(super) model: String,
    pub(super) precision: &'static str,
    pub(super) activation_checkpointing: &'static str,
    pub(super) batch: usize,
    pub(super) error: String,
}

/// Training memory per extra sample: the slope of the peak between two batch sizes.
#[derive(Debug, Serialize)]
pub(super) struct PerSample {
    pub(super) model: String,
    pub(super) precision: String,
    pub(super) activation_checkpointing: String,
    pub(super) batches: [usize; 2],
    pub(super) mib_per_sample: f64,
}

#[derive(Debug, Serialize)]
pub(super) struct Report {
    pub(super) device: String,
    pub(super) threads: usize,
    pub(super) rows: Vec<Row>,
    /// Rows that ran out of host or device memory.
    pub(super) out_of_memory: Vec<OutOfMemory>,
    pub(super) per_sample_memory: Vec<PerSample>,
    pub(super) generate: Vec<GenerateRow>,
}

/// One row of the plan.
#[derive(Debug, Clone, Copy)]
pub(super) struct Spec<'a> {
    pub(super) model: &'a str,
    pub(super) precision: Precision,
    pub(super) checkpointing: ActivationCheckpointing,
    pub(super) batch: usize,
}

/// Every row, in the order measured: network, precision, checkpointing, batch.
pub(super) fn plan(args: &BenchArgs) -> Vec<Spec<'_>> {
    let mut out = Vec::new();
    for m in &args.models {
        for &precision in &args.precision {
            for &checkpointing in &args.activation_checkpointing {
                for &batch in &args.batch {
                    out.push(Spec {
                        model: m,
                        precision,
                        checkpointing,
                        batch,
                    });
                }
            }
        }
    }
    out
}
