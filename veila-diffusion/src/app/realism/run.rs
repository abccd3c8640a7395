//! A whole run of the realism benchmark ([`run`], `cargo xtask bench-realism`): the judge's test
//! frames and training pool simulated, the baselines and the floor, then every model row at each
//! sampler setting ([`RealismOptions`]); the report written by `report.rs`.

use std::path::PathBuf;

use candle_core::Device;
use veila_nn::feature_nets::FeatureNets;

use super::report::{RealismReport, Row};
use super::{Degradation, RealismBench, RowSpec};
use crate::app::bundle::Bundle;
use crate::app::progress::{Bar, Progress};
use crate::app::sim_examples::{RenderStyle, render_split_shown, test_list_for, train_split_of};
use crate::error::{Error, Result, invalid};
use crate::{SamplerConfig, SamplerName, Spacing};

/// The options of one run (`cargo xtask bench-realism`'s flags). Paths are relative to `root`
/// (or absolute); a model row's label names its bundle as given.
#[derive(Debug, Clone, PartialEq)]
pub struct RealismOptions {
    /// The workspace: the scene lists and `models/feature-nets` are found in it.
    pub root: PathBuf,
    /// Model bundles to score (none: the baselines and the floor alone).
    pub models: Vec<PathBuf>,
    /// The conditional bundle whose encoder heads judge the image agreement and whose features
    /// retrieve; its training list gives the test list, the baselines and the memorisation pool.
    pub judge: PathBuf,
    /// Samplers of the model rows, every one at every step count (none: each bundle's own).
    pub samplers: Vec<SamplerName>,
    /// Step counts of the model rows (none: each bundle's own).
    pub steps: Vec<usize>,
    /// Spacings of the sampler's steps, every one at every step count (none: the sampler's own).
    pub spacings: Vec<Spacing>,
    /// Guidance scales of the conditional model rows (none: each bundle's own).
    pub guidance: Vec<f64>,
    /// Start levels of the rows of bundles with a prior mean network
    /// ([`SamplerConfig::start_t`]; none: each bundle's own).
    pub start_t: Vec<f64>,
    /// Calibration rows: the data floor's true scans put through each degradation and scored
    /// like a generator's (none: no calibration rows).
    pub calibrations: Vec<Degradation>,
    /// Held-out test frames, split into `folds` folds of equal size.
    pub test_frames: usize,
    /// Folds of the test frames.
    pub folds: usize,
    /// Sample seeds per frame (2 or more also give the diversity).
    pub seeds: usize,
    /// Training frames of the judge's list: the mean scan, the retrieval database and the
    /// memorisation pool.
    pub train_frames: usize,
    /// Output folder.
    pub out: PathBuf,
    /// The command line the report states.
    pub command: String,
}

/// Runs the benchmark of `opts` and writes its report (`report.md`, `report.json`,
/// `frontier.png`) into `out`; `progress` shows the run.
pub fn run(opts: &RealismOptions, progress: &dyn Progress) -> Result<RealismReport> {
    let device = Device::Cpu;
    let load = |p: &PathBuf| Bundle::from_dir(&opts.root.join(p), &device);
    let bundles = opts.models.iter().map(load).collect::<Result<Vec<_>>>()?;
    let judge = &load(&opts.judge)?;
    if !judge.is_conditional() {
        return Err(invalid(
            "judge",
            format!("{}: the judge must be conditional", opts.judge.display()),
        ));
    }
    let train_list = train_split_of(&judge.config);
    let test_list = test_list_for(&opts.root, &train_list);
    let render = |list: &std::path::Path, n: usize, label: &str| {
        let style = RenderStyle::default();
        render_split_shown(&opts.root, list, n, &judge.config, &style, label, progress)
    };
    let tests = render(&test_list, opts.test_frames, "simulating test frames")?;
    let pool = render(&train_list, opts.train_frames, "simulating train frames")?;
    let nets = FeatureNets::from_dir(&opts.root.join("models/feature-nets"), &device)
        .map_err(|e| Error::Data(format!("FRD / FPD / CM-SC need models/feature-nets: {e}")))?;
    let bench = RealismBench::new(judge, tests, opts.folds, &pool, Some(nets), &device)?;
    let n = bench.fold_size();
    progress.line(&format!(
        "{} folds of {n} frames, {} training scans in the pool",
        bench.num_folds(),
        pool.len()
    ));
    let (mean, retrieval) = bench.baselines(judge, &pool)?;
    let mut rows = vec![
        Row::new(
            format!(
                "mean scan (per-pixel median of {} train frames)",
                pool.len()
            ),
            "baseline",
            None,
            (&mean, &[]),
            n,
        ),
        Row::new(
            "retrieval (train scan of the nearest image)".into(),
            "baseline",
            None,
            (&retrieval, &[]),
            n,
        ),
        Row::new(
            "data floor (true scans of another fold; diversity: of the nearest image)".into(),
            "floor",
            None,
            (&bench.floor()?, &bench.diversity_floors(judge)?),
            n,
        ),
    ];
    for &d in &opts.calibrations {
        let sets = bench.calibration(judge, d)?;
        rows.push(Row::new(d.label(), "calibration", None, (&sets, &[]), n));
    }
    for (bundle, dir) in bundles.iter().zip(&opts.models) {
        for (spec, label) in row_specs(bundle, opts) {
            let label = format!("{} {label}", dir.display());
            let mut bar: Option<Box<dyn Bar + '_>> = None;
            let r = bench.run_model(bundle, &spec, |done, total| {
                bar.get_or_insert_with(|| progress.bar(&label, total as u64))
                    .set(done as u64, "");
            })?;
            drop(bar);
            progress.line(&format!("  {label}: {:.2} s/scan", r.seconds_per_scan));
            let sets = (r.sets.as_slice(), r.diversity.as_slice());
            rows.push(Row::new(label, "model", Some(r.seconds_per_scan), sets, n));
        }
    }
    let report = RealismReport {
        command: opts.command.clone(),
        date_utc: veila_data::stamp::report_time(),
        machine: veila_nn::process::cpu_cores_phrase(),
        test_split: test_list.display().to_string(),
        folds: bench.num_folds(),
        fold_size: n,
        seeds: opts.seeds,
        train_frames: pool.len(),
        rows,
    };
    report.write(&opts.root.join(&opts.out))?;
    Ok(report)
}

/// Each of `asked`, or `None` alone (the bundle's own) when nothing is asked.
fn each_or_own<T: Copy>(asked: &[T]) -> Vec<Option<T>> {
    if asked.is_empty() {
        vec![None]
    } else {
        asked.iter().copied().map(Some).collect()
    }
}

/// The model rows of one bundle: every sampler at every spacing, step count, guidance scale and
/// (with a prior) start level (a bundle with a mean network, a residual's or a prior's, also
/// gets that network alone).
fn row_specs(bundle: &Bundle, opts: &RealismOptions) -> Vec<(RowSpec, String)> {
    let own = &bundle.config.sampler;
    let steps = if opts.steps.is_empty() {
        vec![own.steps]
    } else {
        opts.steps.clone()
    };
    let guidance = if opts.guidance.is_empty() || !bundle.is_conditional() {
        vec![own.guidance_scale]
    } else {
        opts.guidance.clone()
    };
    let starts = if opts.start_t.is_empty() || bundle.config.prior.is_none() {
        vec![own.start_t]
    } else {
        opts.start_t.iter().copied().map(Some).collect()
    };
    // `None`: the bundle's own sampler; the sampler's own spacing
    let samplers = each_or_own(&opts.samplers);
    let spacings = each_or_own(&opts.spacings);
    let mut out = Vec::new();
    for name in samplers {
        for &spacing in &spacings {
            for &s in &steps {
                for (&g, &start_t) in guidance
                    .iter()
                    .flat_map(|g| starts.iter().map(move |t| (g, t)))
                {
                    let sampler = crate::app::SamplerChoice {
                        name,
                        spacing,
                        steps: Some(s),
                        guidance: Some(g),
                        start_t,
                    }
                    .resolve(bundle);
                    let mut label = format!(
                        "{} x {s} ({} spacing), guidance {g}",
                        sampler.kind.title(),
                        sampler.spacing
                    );
                    if let Some(t) = start_t {
                        label.push_str(&format!(", from the mean network at t = {t}"));
                    }
                    let seeds = opts.seeds;
                    let spec = RowSpec {
                        sampler,
                        seeds,
                        residual_weight: 1.0,
                    };
                    out.push((spec, label));
                }
            }
        }
    }
    if bundle.config.mean_net().is_some() {
        // 0 steps: the mean network's scan, a residual's or a prior's
        let spec = RowSpec {
            sampler: SamplerConfig {
                steps: 0,
                start_t: None,
                ..own.clone()
            },
            seeds: 1,
            residual_weight: 1.0,
        };
        out.push((spec, "mean network alone".into()));
    }
    out
}
