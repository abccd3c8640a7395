//! `cargo xtask bench-realism`: generators judged as generators on held-out simulated frames
//! (`veila_diffusion::app::realism`): every model row at each sampler setting next to the mean
//! scan, retrieval and the data floor; realism, texture, faithfulness, memorisation, diversity and
//! seconds per scan; `report.md`, `report.json` and `frontier.png` (realism against faithfulness).

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{Context, Result};
use candle_core::Device;
use clap::Args;
use serde::Serialize;
use veila_data::vis::plot::{Plot, Series, SeriesStyle};
use veila_diffusion::app::bundle::Bundle;
use veila_diffusion::app::realism::{RealismBench, RowSpec};
use veila_diffusion::app::scoring::{SetMetrics, Stat, metric_stats};
use veila_diffusion::app::sim_examples::{RenderStyle, test_list_for, train_split_of};
use veila_nn::feature_nets::FeatureNets;

use crate::bench_real::{sampler_for, sampler_parser};
use crate::progress::{progress_bar, render_split, workspace_root};
use veila_diffusion::SamplerName;

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

#[derive(Debug, Serialize)]
struct Row {
    label: String,
    kind: &'static str,
    seconds_per_scan: Option<f64>,
    /// metric -> region -> stat over folds (x seeds)
    metrics: BTreeMap<String, BTreeMap<String, Stat>>,
}

#[derive(Debug, Serialize)]
struct Report {
    command: String,
    date_utc: String,
    machine: String,
    test_split: String,
    folds: usize,
    fold_size: usize,
    seeds: usize,
    train_frames: usize,
    rows: Vec<Row>,
}

fn stats_row(
    label: String,
    kind: &'static str,
    secs: Option<f64>,
    sets: &[SetMetrics],
    extra: &[SetMetrics],
    n: usize,
) -> Row {
    let mut metrics = metric_stats(sets, n);
    if !extra.is_empty() {
        metrics.extend(metric_stats(extra, n));
    }
    Row {
        label,
        kind,
        seconds_per_scan: secs,
        metrics,
    }
}

/// Runs the benchmark and writes the report.
pub fn run(args: BenchRealismArgs) -> Result<()> {
    let root = workspace_root();
    let device = Device::Cpu;
    let abs = |p: &PathBuf| crate::progress::in_workspace(p);
    let load = |p: &PathBuf| {
        Bundle::from_dir(&abs(p), &device).with_context(|| format!("loading {}", p.display()))
    };
    let bundles = args.models.iter().map(load).collect::<Result<Vec<_>>>()?;
    let judge = &load(&args.judge)?;
    anyhow::ensure!(
        judge.is_conditional(),
        "--judge {}: the judge must be conditional",
        args.judge.display()
    );
    let train_list = train_split_of(&judge.config);
    let test_list = test_list_for(&root, &train_list);
    let tests = render_split(
        &test_list,
        args.test_frames,
        &judge.config,
        &RenderStyle::default(),
        "simulating test frames",
    )?;
    let pool = render_split(
        &train_list,
        args.train_frames,
        &judge.config,
        &RenderStyle::default(),
        "simulating train frames",
    )?;
    let nets = FeatureNets::from_dir(&root.join("models/feature-nets"), &device).ok();
    anyhow::ensure!(
        nets.is_some(),
        "models/feature-nets is needed for FRD / FPD / CM-SC"
    );
    let bench = RealismBench::new(judge, tests, args.folds, &pool, nets, &device)?;
    let n = bench.fold_size();
    println!(
        "{} folds of {n} frames, {} training scans in the pool",
        bench.num_folds(),
        pool.len()
    );
    let mut rows = Vec::new();
    let (mean, retrieval) = bench.baselines(judge, &pool)?;
    rows.push(stats_row(
        format!(
            "mean scan (per-pixel median of {} train frames)",
            pool.len()
        ),
        "baseline",
        None,
        &mean,
        &[],
        n,
    ));
    rows.push(stats_row(
        "retrieval (train scan of the nearest image)".into(),
        "baseline",
        None,
        &retrieval,
        &[],
        n,
    ));
    rows.push(stats_row(
        "data floor (true scans of another fold; diversity: of the nearest image)".into(),
        "floor",
        None,
        &bench.floor()?,
        &bench.diversity_floors(judge)?,
        n,
    ));
    for (bundle, dir) in bundles.iter().zip(&args.models) {
        for spec_label in row_specs(bundle, &args)? {
            let (spec, label) = spec_label;
            let label = format!("{} {label}", dir.display());
            let bar = progress_bar((bench.num_folds() * n) as u64, &label);
            let r = bench.run_model(bundle, &spec, |done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            })?;
            bar.finish_and_clear();
            println!("  {label}: {:.2} s/scan", r.seconds_per_scan);
            rows.push(stats_row(
                label,
                "model",
                Some(r.seconds_per_scan),
                &r.sets,
                &r.diversity,
                n,
            ));
        }
    }
    let out = abs(&args.out);
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let report = Report {
        command: crate::progress::command_line(),
        date_utc: veila_data::stamp::report_time(),
        machine: format!("{} CPU cores", crate::progress::cpu_cores()),
        test_split: test_list.display().to_string(),
        folds: bench.num_folds(),
        fold_size: n,
        seeds: args.seeds,
        train_frames: pool.len(),
        rows,
    };
    std::fs::write(
        out.join("report.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    std::fs::write(out.join("report.md"), markdown(&report))?;
    // a legend that fits no free corner stacks above the axes: grow the canvas with the rows so
    // the axes keep their height either way
    let plot = frontier(&report);
    let height = 420 + 26 * plot.series.len() as u32;
    plot.write_png(&out.join("frontier.png"), 900, height)?;
    println!("wrote {}", out.display());
    Ok(())
}

/// The model rows of one bundle: every sampler at every step count and guidance scale (a
/// residual bundle also gets its mean network alone).
fn row_specs(bundle: &Bundle, args: &BenchRealismArgs) -> Result<Vec<(RowSpec, String)>> {
    let own = &bundle.config.sampler;
    let steps = if args.steps.is_empty() {
        vec![own.steps]
    } else {
        args.steps.clone()
    };
    let guidance = if args.guidance.is_empty() || !bundle.is_conditional() {
        vec![own.guidance_scale]
    } else {
        args.guidance.clone()
    };
    let mut out = Vec::new();
    // `None`: the bundle's own sampler
    let samplers: Vec<Option<SamplerName>> = if args.sampler.is_empty() {
        vec![None]
    } else {
        args.sampler.iter().copied().map(Some).collect()
    };
    // `None`: the sampler's own spacing
    let spacings: Vec<Option<veila_diffusion::Spacing>> = if args.spacing.is_empty() {
        vec![None]
    } else {
        args.spacing.iter().copied().map(Some).collect()
    };
    for name in samplers {
        for &spacing in &spacings {
            for &s in &steps {
                for &g in &guidance {
                    let mut sampler = match name {
                        None => veila_diffusion::SamplerConfig {
                            steps: s,
                            guidance_scale: g,
                            ..own.clone()
                        },
                        Some(name) => sampler_for(name, s, g),
                    };
                    if let Some(spacing) = spacing {
                        sampler.spacing = spacing;
                    }
                    let label = format!(
                        "{} x {s} ({} spacing), guidance {g}",
                        sampler.kind.title(),
                        sampler.spacing
                    );
                    out.push((
                        RowSpec {
                            sampler,
                            seeds: args.seeds,
                            residual_weight: 1.0,
                        },
                        label,
                    ));
                }
            }
        }
    }
    if bundle.config.residual.is_some() {
        out.push((
            RowSpec {
                sampler: own.clone(),
                seeds: 1,
                residual_weight: 0.0,
            },
            "mean network alone".into(),
        ));
    }
    Ok(out)
}

/// A metric and the regions it is shown for.
type Column = (&'static str, &'static [&'static str]);

/// The report's tables: one per group of metrics, a column per metric and region.
fn markdown(r: &Report) -> String {
    let mut s = format!(
        "# Realism benchmark\n\n`{}` on {} ({}): {} folds of {} frames of `{}`, {} sample seeds per frame; baselines and the memorisation pool from the first {} frames of the training list. Mean ± std over folds (x seeds). Lower is better except the shares and the diversity, which should match the floor.\n\n",
        r.command,
        r.date_utc,
        r.machine,
        r.folds,
        r.fold_size,
        r.test_split,
        r.seeds,
        r.train_frames
    );
    let groups: [(&str, &[Column]); 4] = [
        (
            "Realism",
            &[
                ("fpd", &["all", "front", "rear"]),
                ("frd", &["all", "front", "rear"]),
                ("jsd", &["all", "front", "rear"]),
                ("mmd (x1e4)", &["all", "front", "rear"]),
            ],
        ),
        (
            "Texture",
            &[
                ("texture along rows (w1, decades)", &["view", "outside"]),
                ("texture across rows (w1, decades)", &["view", "outside"]),
                ("depth edges (%)", &["view", "outside"]),
                ("smooth pairs (%)", &["view", "outside"]),
                ("ray drop per row (abs diff)", &["all"]),
            ],
        ),
        (
            "Faithfulness",
            &[
                ("range mae (m)", &["view", "front", "rear"]),
                ("cm-dc (abs rel)", &["front"]),
                ("cm-sc (%)", &["front"]),
            ],
        ),
        (
            "Diversity and memorisation",
            &[
                ("diversity (range mae, m)", &["front", "rear"]),
                ("nearest train scan (log2 m)", &["all"]),
            ],
        ),
    ];
    for (title, cols) in groups {
        s += &format!("## {title}\n\n| row | s / scan |");
        for (m, regions) in cols {
            for reg in *regions {
                s += &format!(" {m} {reg} |");
            }
        }
        s += "\n|---|---|";
        for (_, regions) in cols {
            s += &"---|".repeat(regions.len());
        }
        s += "\n";
        for row in &r.rows {
            let name = if row.kind == "model" {
                row.label.clone()
            } else {
                format!("*{}*", row.label)
            };
            s += &format!(
                "| {name} | {} |",
                row.seconds_per_scan
                    .map(|t| format!("{t:.3}"))
                    .unwrap_or_default()
            );
            for (m, regions) in cols {
                for reg in *regions {
                    let cell = row
                        .metrics
                        .get(*m)
                        .and_then(|x| x.get(*reg))
                        .map(fmt_stat)
                        .unwrap_or_else(|| "–".into());
                    s += &format!(" {cell} |");
                }
            }
            s += "\n";
        }
        s += "\n";
    }
    s += "![realism against faithfulness](frontier.png)\n";
    s
}

fn fmt_stat(st: &Stat) -> String {
    if !st.mean.is_finite() {
        return "n/a".into();
    }
    let digits = |v: f64| match v.abs() {
        a if a >= 100.0 => 1,
        a if a >= 1.0 => 2,
        a if a >= 0.01 => 3,
        _ => 4,
    };
    let d = digits(st.mean);
    format!("{:.d$} ± {:.d$}", st.mean, st.std)
}

/// FPD (all) against the range MAE in the camera's view, every row that has both.
fn frontier(r: &Report) -> Plot {
    let get =
        |row: &Row, m: &str, reg: &str| row.metrics.get(m).and_then(|x| x.get(reg)).map(|s| s.mean);
    let series = r
        .rows
        .iter()
        .filter_map(|row| {
            let x = get(row, "range mae (m)", "view")?;
            let y = get(row, "fpd", "all")?;
            Some(Series::new(
                row.label.clone(),
                vec![(x, y)],
                SeriesStyle::Markers,
            ))
        })
        .collect();
    Plot {
        title: "Realism against faithfulness (every row)".into(),
        x_label: "range MAE in the camera's view (m)".into(),
        y_label: "FPD, whole panorama (log)".into(),
        y_log: true,
        series,
        ..Plot::default()
    }
}
