//! The report's contents, in the shape of `report.json`: its rows ([`VariantResult`]), the
//! sampler sweep's points ([`SweepPoint`]) and what was run ([`Report`]).

use std::collections::BTreeMap;

use serde::Serialize;

use super::options::Protocol;
use crate::app::real_frames::RealReport;
use crate::app::scoring::{SetMetrics, Stat, metric_stats};

/// One row: a model, a baseline or the data floor.
#[derive(Debug, Clone, Serialize)]
pub struct VariantResult {
    /// `model`, `baseline` or `floor`.
    pub kind: String,
    /// The row's short name (`shipped`, a variant's name, `mean-scan`, ...).
    pub variant: String,
    /// The row's label in the tables.
    pub label: String,
    /// The bundle folder of a model row (`-` otherwise).
    pub model: String,
    /// Denoiser training steps of a trained variant (0 otherwise).
    pub train_steps: u64,
    /// Seconds per generated scan (0 for rows that generate nothing).
    pub seconds_per_scan: f64,
    /// metric name -> region -> stat
    pub metrics: BTreeMap<String, BTreeMap<String, Stat>>,
}

impl VariantResult {
    /// A row from per-set metric values (untrained, untimed: set those fields after).
    pub(super) fn new(
        kind: &str,
        name: &str,
        label: &str,
        model: &str,
        per_set: &[SetMetrics],
        scans_per_set: usize,
    ) -> Self {
        VariantResult {
            kind: kind.into(),
            variant: name.into(),
            label: label.into(),
            model: model.into(),
            train_steps: 0,
            seconds_per_scan: 0.0,
            metrics: metric_stats(per_set, scans_per_set),
        }
    }
}

/// One setting of the sampler sweep.
#[derive(Debug, Clone, Serialize)]
pub struct SweepPoint {
    /// The sampler (ddpm, ddim, dpm).
    pub sampler: String,
    /// Its steps (0 for the mean network alone).
    pub steps: usize,
    /// Residual bundles: the residual weight (1 = full samples).
    pub residual_weight: f64,
    /// Seconds per scan.
    pub seconds_per_scan: f64,
    /// BEV JSD over the whole scan.
    pub jsd_all: f64,
    /// Range MAE of the front half (m).
    pub range_mae_front_m: f64,
    /// Scans behind the point.
    pub scans: usize,
}

/// The whole report (`report.json`).
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// The command line that ran it.
    pub command: String,
    /// When (UTC).
    pub date_utc: String,
    /// Where.
    pub machine: String,
    /// The test frames' scene list.
    pub test_split: String,
    /// Test frames.
    pub test_frames: usize,
    /// Disjoint folds of the test frames.
    pub folds: usize,
    /// Training frames behind the baselines.
    pub baseline_frames: usize,
    /// Sample seeds per model.
    pub seeds: u64,
    /// Denoiser training steps of every variant.
    pub train_steps: u64,
    /// Training frames of every variant.
    pub train_frames: usize,
    /// How the variants were trained.
    pub protocol: Protocol,
    /// `--sampler` (ddpm, ddim or dpm).
    pub sampler: String,
    /// Its steps.
    pub sampler_steps: usize,
    /// A smoke run.
    pub quick: bool,
    /// The bundled model alone, no ablation variants.
    pub shipped_only: bool,
    /// The rows.
    pub variants: Vec<VariantResult>,
    /// The sampler sweep.
    pub sweep: Vec<SweepPoint>,
    /// The bundle on the real frames (issue 18), `None` with `no_real`.
    pub real: Option<RealReport>,
    /// Notes on the protocol and the metrics.
    pub notes: Vec<String>,
}
