//! The benchmark report (feature `sim`; `cargo xtask bench-report` drives it): Veila against the
//! zero-skill baselines, the data floor and every ablation on a held-out simulator test split, what
//! generation quality costs in time (sampler x steps), and the bundle on the real frames.
//!
//! [`run`] writes `report.md`, `report.json` and PNG plots to [`BenchReportOptions::out`]. Every
//! variant's denoiser is trained with the same budget, data, seed and the same (frozen) encoders
//! of the bundled model ([`Protocol`]), so the variants differ only in the switch under test.
//! Metrics are computed per fold of the test frames and sample seed; the report gives the mean and
//! the standard deviation over them, and the number of scans behind each value.
//!
//! * `options.rs`: what a run measures ([`BenchReportOptions`], [`Protocol`]);
//! * `bench.rs`: the fixed side (the bundle, the test frames, their folds and judges) and how a
//!   bundle's scans are made and scored;
//! * `baselines.rs`: the rows without a model, and the real frames' section;
//! * `variants.rs`: the bundle as shipped and the trained ablation variants;
//! * `sweep.rs`: the sampler sweep;
//! * `report.rs`, `markdown.rs`, `plots.rs`: the report's contents and how they are written.

use std::path::Path;

use crate::app::progress::Progress;
use crate::app::report_files::write_report_files;
use crate::error::Result;

mod baselines;
mod bench;
mod markdown;
mod options;
mod plots;
mod report;
mod sweep;
mod variants;

pub use options::{BenchReportOptions, Protocol};
pub use report::{Report, SweepPoint, VariantResult};

/// Runs the benchmark of `options` (shrunk first when `quick`) and writes its report; `progress`
/// shows the run.
pub fn run(mut options: BenchReportOptions, progress: &dyn Progress) -> Result<Report> {
    if options.quick {
        options.shrink_for_quick();
    }
    options.check()?;
    let bench = bench::Bench::prepare(options, progress)?;
    let mut baselines = bench.baselines()?;
    let mut rows = std::mem::take(&mut baselines.rows);
    rows.extend(bench.shipped()?);
    rows.extend(bench.variants()?);
    let sweep = bench.sweep()?;
    let real = bench.real_frames(&baselines)?;
    let opts = &bench.opts;
    let report = Report {
        command: opts.command.clone(),
        date_utc: veila_data::stamp::report_time(),
        machine: format!("{} (CPU only)", veila_nn::process::cpu_cores_phrase()),
        test_split: bench.test_list.display().to_string(),
        test_frames: bench.tests.len(),
        folds: opts.folds,
        baseline_frames: baselines.train_frames,
        seeds: opts.seeds,
        train_steps: opts.train_steps,
        train_frames: opts.train_frames,
        protocol: opts.protocol,
        sampler: opts.sampler.to_string(),
        sampler_steps: opts.steps,
        quick: opts.quick,
        shipped_only: opts.shipped_only,
        variants: rows,
        sweep,
        real,
        notes: opts.notes(),
    };
    write_report(&opts.out, &report)?;
    Ok(report)
}

/// Writes `report.json`, `report.md` and the plots to `out` (created if need be).
pub fn write_report(out: &Path, r: &Report) -> Result<()> {
    write_report_files(out, r, &markdown::markdown(r))?;
    plots::plot_variants(&out.join("variants.png"), r)?;
    plots::plot_sweep(&out.join("sampler_tradeoff.png"), r)
}
