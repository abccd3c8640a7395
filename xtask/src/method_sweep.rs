//! `cargo xtask method-sweep`: the generative methods at equal training compute: quality against
//! training seconds for direct diffusion (ε and v), residual diffusion, rectified flow and
//! one-pass regression, on the same frames, frozen encoders, batch and seed.
//!
//! Every method trains for the same wall-clock budget at a constant learning rate (after a short
//! warm-up), and its EMA weights are evaluated on held-out test frames at fixed points of training
//! time (the evaluations are not counted). Residual diffusion spends the first half of its budget
//! on its mean network, which is the regression run itself at half its budget (the same seeded
//! run: with a constant learning rate the regression state at `budget / 2` is that mean network),
//! and the second half on the residual denoiser. Writes `report.md`, `report.json` and
//! `methods.png` to `--out`.

use std::collections::HashMap;
use std::ops::ControlFlow;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use candle_core::{Device, Tensor};
use clap::Args;
use serde::Serialize;
use veila_data::vis::plot::{Plot, Series, SeriesStyle};
use veila_diffusion::app::bundle::{Bundle, BundleConfig, Method, Variant};
use veila_diffusion::app::{
    CameraView, DenoiserFit, GenerateOptions, Stage, TrainExample, fit_denoiser, predict_means,
    residual_scale,
};
use veila_diffusion::{Diffusion, SamplerConfig, StepStats, TrainConfig, TrainObserver};
use veila_geom::{RangeImage, RayTable, Region};
use veila_metrics::bev::{BevConfig, bev_histogram};

use crate::simdata::{SimExample, render_split, workspace_root};

/// Arguments of `cargo xtask method-sweep`.
#[derive(Debug, Args)]
pub struct MethodSweepArgs {
    /// Output folder.
    #[arg(long, default_value = "docs/method-sweep")]
    out: PathBuf,
    /// Methods (comma-separated; residual needs regression, which is run for it).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "eps,v,flow,regression,residual"
    )]
    methods: Vec<Method>,
    /// Training frames (scenes/train.txt).
    #[arg(long, default_value_t = 240)]
    frames: usize,
    /// Held-out evaluation frames (scenes/test.txt).
    #[arg(long, default_value_t = 24)]
    val_frames: usize,
    /// Training seconds per method.
    #[arg(long, default_value_t = 600.0)]
    budget_secs: f64,
    /// Evaluations per method, evenly spaced in training time.
    #[arg(long, default_value_t = 4)]
    evals: usize,
    /// Batch size.
    #[arg(long, default_value_t = 8)]
    batch: usize,
    /// Learning rate (constant after a 50-step warm-up).
    #[arg(long, default_value_t = 1e-3)]
    lr: f64,
    /// Sampler steps of the sampling methods at evaluation.
    #[arg(long, default_value_t = 16)]
    steps: usize,
    /// The bundle whose frozen encoders every method uses.
    #[arg(long, default_value = "models/default")]
    encoders_from: PathBuf,
    /// Seed of everything.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Rewrite report.md and the plots from an existing report.json (no training).
    #[arg(long)]
    replot: bool,
}

#[derive(Debug, Clone, Serialize, serde::Deserialize)]
struct Point {
    method: String,
    step: u64,
    train_secs: f64,
    samples: u64,
    range_mae_front_m: f64,
    range_mae_rear_m: f64,
    range_mae_front_std_m: f64,
    jsd_all: f64,
    ring_spread_m: f64,
    seconds_per_scan: f64,
}

/// What the evaluation needs: the frames, the frozen encoders and the metric references.
struct Eval<'a> {
    base: &'a Bundle,
    val: &'a [SimExample],
    steps: usize,
    seed: u64,
    points: Vec<Point>,
}

impl Eval<'_> {
    /// Generates one scan per frame with `bundle` and scores it.
    fn run(&mut self, bundle: &Bundle, method: Method, step: u64, train_secs: f64, batch: usize) {
        match self.score(bundle, method, step, train_secs, batch) {
            Ok(p) => {
                println!(
                    "  {:>10} step {:>5} ({:>6.0} s): MAE front {:.2} m, rear {:.2} m, JSD {:.4}, ring spread {:.3} m, {:.2} s/scan",
                    p.method,
                    p.step,
                    p.train_secs,
                    p.range_mae_front_m,
                    p.range_mae_rear_m,
                    p.jsd_all,
                    p.ring_spread_m,
                    p.seconds_per_scan
                );
                self.points.push(p);
            }
            Err(e) => eprintln!(
                "  evaluation of {} at step {step} failed: {e:#}",
                method.name()
            ),
        }
    }

    fn score(
        &self,
        bundle: &Bundle,
        method: Method,
        step: u64,
        train_secs: f64,
        batch: usize,
    ) -> Result<Point> {
        let sampler = match method {
            Method::Regression => SamplerConfig {
                steps: 1,
                guidance_scale: 1.0,
                ..bundle.config.sampler.clone()
            },
            _ => SamplerConfig {
                steps: self.steps,
                ..bundle.config.sampler.clone()
            },
        };
        let t = Instant::now();
        let mut generated: Vec<RangeImage> = Vec::with_capacity(self.val.len());
        for (i, ex) in self.val.iter().enumerate() {
            let mut scans = bundle.generate(
                &[CameraView {
                    rgb: &ex.rgb,
                    camera: &ex.camera,
                }],
                &GenerateOptions {
                    sampler: sampler.clone(),
                    samples: 1,
                    seed: self.seed.wrapping_add(i as u64),
                    unconditional: false,
                    residual_weight: 1.0,
                },
                |_, _| {},
            )?;
            generated.push(scans.swap_remove(0));
        }
        let secs = t.elapsed().as_secs_f64() / self.val.len().max(1) as f64;
        let sensor = &self.base.config.denoiser.sensor;
        let mae = |region: Region| -> Vec<f64> {
            generated
                .iter()
                .zip(self.val)
                .filter_map(|(g, ex)| veila_metrics::range::range_mae(g, &ex.range, region))
                .collect()
        };
        let (fm, fstd) = crate::simdata::mean_std(&mae(Region::Front));
        let (rear_mean, _) = crate::simdata::mean_std(&mae(Region::Rear));
        let rays = RayTable::new(sensor)?;
        let cfg = BevConfig::r2dm();
        let hist = |imgs: &mut dyn Iterator<Item = &RangeImage>| -> Result<Vec<_>> {
            imgs.map(|r| {
                let p = rays.unproject(r)?.points;
                Ok(bev_histogram(&p, &cfg, Region::All, "scan")?)
            })
            .collect()
        };
        let hg = hist(&mut generated.iter())?;
        let hr = hist(&mut self.val.iter().map(|e| &e.range))?;
        let jsd = veila_metrics::dist::jsd(&hg, &hr).unwrap_or(f64::NAN);
        let spreads: Vec<f64> = generated
            .iter()
            .filter_map(|g| veila_metrics::baseline::ring_spread(g, sensor, -15.0, 0.5))
            .collect();
        Ok(Point {
            method: method.name().into(),
            step,
            train_secs,
            samples: step * batch as u64,
            range_mae_front_m: fm,
            range_mae_rear_m: rear_mean,
            range_mae_front_std_m: fstd,
            jsd_all: jsd,
            ring_spread_m: crate::simdata::mean_std(&spreads).0,
            seconds_per_scan: secs,
        })
    }
}

/// Stops training at `budget` seconds (counting `offset` seconds spent before this run) and
/// evaluates the EMA weights at the given training times.
struct Observer<'e, 'a> {
    eval: &'e mut Eval<'a>,
    cfg: BundleConfig,
    method: Method,
    /// The mean network for residual evaluation.
    mean: Option<veila_nn::Denoiser>,
    secs: f64,
    /// Training seconds already spent before this run (the residual denoiser's offset).
    offset: f64,
    budget: f64,
    next_eval: usize,
    eval_at: Vec<f64>,
    step: u64,
    /// Updates already spent before this run (the residual method's mean network).
    offset_steps: u64,
    batch: usize,
}

impl<'g> TrainObserver<veila_diffusion::VeilaDenoiser<'g>> for Observer<'_, '_> {
    fn on_step(&mut self, s: &StepStats) -> ControlFlow<()> {
        self.secs += s.step_secs;
        self.step = s.step;
        if self.offset + self.secs >= self.budget {
            // the last evaluation happens in on_preview of this step
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    }

    fn on_preview(
        &mut self,
        step: u64,
        model: &veila_diffusion::VeilaDenoiser<'g>,
        _d: &Diffusion,
    ) -> veila_diffusion::Result<()> {
        let t = self.offset + self.secs;
        // an evaluation point reached, or the end of the whole budget (not an intermediate stop)
        let total = self.eval_at.last().copied().unwrap_or(self.budget);
        let due = self.eval_at.get(self.next_eval).is_some_and(|&at| t >= at)
            || (t >= self.budget && self.budget >= total);
        if due && self.next_eval < self.eval_at.len() {
            self.next_eval += 1;
            let bundle = Bundle {
                config: self.cfg.clone(),
                semantic: self.eval.base.semantic.clone(),
                depth: self.eval.base.depth.clone(),
                denoiser: model.net().clone(),
                weights: HashMap::new(),
                mean: self.mean.clone().map(|m| (m, HashMap::new())),
                origin: PathBuf::from("(training)"),
            };
            let (method, batch) = (self.method, self.batch);
            self.eval
                .run(&bundle, method, self.offset_steps + step, t, batch);
        }
        Ok(())
    }
}

/// Runs the sweep.
pub fn run(args: MethodSweepArgs) -> Result<()> {
    let root = workspace_root();
    if args.replot {
        let p = root.join(&args.out).join("report.json");
        let v: serde_json::Value = serde_json::from_slice(
            &std::fs::read(&p).with_context(|| format!("reading {}", p.display()))?,
        )?;
        let points: Vec<Point> = serde_json::from_value(v["points"].clone())?;
        return write(&args, &points, &root.join(&args.out));
    }
    let device = Device::Cpu;
    let enc_dir = if args.encoders_from.is_absolute() {
        args.encoders_from.clone()
    } else {
        root.join(&args.encoders_from)
    };
    let base = Bundle::from_dir(&enc_dir, &device)
        .with_context(|| format!("loading encoders from {}", enc_dir.display()))?;
    let proto = BundleConfig::cpu_default(Variant::Full);
    let train = render_split(
        &root.join("scenes/train.txt"),
        args.frames,
        &proto,
        "simulating train frames",
    )?;
    let val = render_split(
        &root.join("scenes/test.txt"),
        args.val_frames,
        &proto,
        "simulating test frames",
    )?;
    let examples: Vec<TrainExample> = train
        .iter()
        .map(|e| e.train_example(&proto))
        .collect::<Result<_>>()?;
    let mut eval = Eval {
        base: &base,
        val: &val,
        steps: args.steps,
        seed: args.seed,
        points: Vec::new(),
    };
    let eval_at: Vec<f64> = (1..=args.evals.max(1))
        .map(|k| args.budget_secs * k as f64 / args.evals.max(1) as f64)
        .collect();
    let tc = |total: u64| TrainConfig {
        seed: args.seed,
        lr: args.lr,
        min_lr: args.lr,
        warmup_steps: 50,
        total_steps: total,
        ema_decay: 0.995,
        cond_drop_prob: 0.1,
        checkpoint_every: None,
        preview_every: Some(1),
        ..TrainConfig::default()
    };
    // every run: the same frames, frozen encoders, batch and (constant) learning rate
    let train_cfg = tc(1_000_000);
    let work = root.join("target/method-sweep");
    let mut methods = args.methods.clone();
    // residual reuses the regression run: run regression first
    methods.sort_by_key(|m| (*m == Method::Residual, *m != Method::Regression));
    let mut mean_snapshot: Option<HashMap<String, Tensor>> = None;
    let mut mean_steps = 0u64;
    for method in methods {
        println!("method {} ({})", method.name(), method.label());
        let mut cfg = proto.clone().with_method(method);
        let dir = work.join(method.name());
        let _ = std::fs::remove_dir_all(&dir);
        let fit = DenoiserFit {
            semantic: base.semantic.as_ref(),
            depth: base.depth.as_ref(),
            examples: (&examples).into(),
            stage: Stage::Denoiser,
            means: None,
            mean_weights: None,
            batch_size: args.batch,
            train: &train_cfg,
            checkpoint_dir: &dir,
            init: None,
            parallel: None,
        };
        match method {
            Method::Residual => {
                let Some(mean_w) = mean_snapshot.clone() else {
                    println!("  residual needs the regression run: add `regression` to --methods");
                    continue;
                };
                let means = predict_means(
                    &cfg,
                    base.semantic.as_ref(),
                    base.depth.as_ref(),
                    &mean_w,
                    &examples,
                    16,
                    &device,
                )?;
                let (h, w) = (cfg.denoiser.height(), cfg.denoiser.width());
                let x0: Vec<Vec<f32>> = examples.iter().map(|e| e.x0.clone()).collect();
                let scale = residual_scale(&cfg.encoding, &x0, &means, h * w);
                if let Some(r) = cfg.residual.as_mut() {
                    r.scale = scale;
                }
                let r = cfg.residual.clone().context("residual config")?;
                let mean_net = veila_nn::Denoiser::new(
                    &r.mean_net,
                    candle_nn::VarBuilder::from_tensors(
                        mean_w.clone(),
                        candle_core::DType::F32,
                        &device,
                    ),
                )?;
                // the first half of the budget went into the mean network: evaluate it there
                let half = args.budget_secs / 2.0;
                let mut obs = Observer {
                    eval: &mut eval,
                    cfg: cfg.clone(),
                    method,
                    mean: Some(mean_net),
                    secs: 0.0,
                    offset: half,
                    budget: args.budget_secs,
                    next_eval: eval_at.iter().filter(|&&t| t < half + 1e-9).count(),
                    eval_at: eval_at.clone(),
                    step: 0,
                    offset_steps: mean_steps,
                    batch: args.batch,
                };
                fit_denoiser(
                    &cfg,
                    DenoiserFit {
                        means: Some(&means),
                        ..fit
                    },
                    &device,
                    |_, _| {},
                    &mut obs,
                )?;
            }
            _ => {
                // regression stops once at half its budget (a checkpoint: the residual method's
                // mean network), then resumes exactly from that checkpoint to the full budget
                let stops: Vec<f64> = if method == Method::Regression {
                    vec![args.budget_secs / 2.0, args.budget_secs]
                } else {
                    vec![args.budget_secs]
                };
                let (mut offset, mut next_eval) = (0.0, 0);
                for stop in stops {
                    let mut obs = Observer {
                        eval: &mut eval,
                        cfg: cfg.clone(),
                        method,
                        mean: None,
                        secs: 0.0,
                        offset,
                        budget: stop,
                        next_eval,
                        eval_at: eval_at.clone(),
                        step: 0,
                        offset_steps: 0,
                        batch: args.batch,
                    };
                    let out = fit_denoiser(&cfg, fit, &device, |_, _| {}, &mut obs)?;
                    offset += obs.secs;
                    next_eval = obs.next_eval;
                    if method == Method::Regression && mean_snapshot.is_none() {
                        mean_steps = out.step;
                        mean_snapshot = Some(out.ema_weights);
                    }
                }
                if method == Method::Regression {
                    // the residual curve starts with the mean network's points
                    let half: Vec<Point> = eval
                        .points
                        .iter()
                        .filter(|p| {
                            p.method == "regression"
                                && p.train_secs <= args.budget_secs / 2.0 + 1e-6
                        })
                        .map(|p| Point {
                            method: "residual".into(),
                            ..p.clone()
                        })
                        .collect();
                    eval.points.extend(half);
                }
            }
        }
    }
    write(&args, &eval.points, &root.join(&args.out))
}

fn write(args: &MethodSweepArgs, points: &[Point], out: &std::path::Path) -> Result<()> {
    use std::fmt::Write as _;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let json = serde_json::json!({
        "command": std::iter::once("cargo xtask".to_string()).chain(std::env::args().skip(1)).collect::<Vec<_>>().join(" "),
        "date_utc": veila_data::stamp::report_time(),
        "train_frames": args.frames,
        "val_frames": args.val_frames,
        "budget_secs": args.budget_secs,
        "batch": args.batch,
        "lr": args.lr,
        "sampler_steps": args.steps,
        "points": points,
    });
    veila_data::atomic::write_atomic(
        &out.join("report.json"),
        serde_json::to_string_pretty(&json)?.as_bytes(),
    )?;
    let mut md = String::new();
    writeln!(md, "# Generative methods at equal training compute")?;
    writeln!(md)?;
    writeln!(
        md,
        "`{}` on {}: {} training frames, {} held-out test frames, batch {}, constant learning rate {} after 50 warm-up steps, {} s of training per method, the bundled model's frozen encoders; sampling methods use {} sampler steps (DPM-Solver++(2M) for diffusion, Euler for rectified flow). Residual diffusion spends its first half on the mean network (the regression run at half its budget; those points are the mean alone, 0 sampler steps), the second half on the residual denoiser. MAE is over the frames (± std over frames); JSD is the BEV JSD of the set (R2DM protocol).",
        json["command"].as_str().unwrap_or(""),
        json["date_utc"].as_str().unwrap_or(""),
        args.frames,
        args.val_frames,
        args.batch,
        args.lr,
        args.budget_secs,
        args.steps
    )?;
    writeln!(md)?;
    writeln!(
        md,
        "| method | step | training samples | training s | range MAE front (m) | range MAE rear (m) | JSD (all) | ring spread (m) | s / scan |"
    )?;
    writeln!(md, "|---|---|---|---|---|---|---|---|---|")?;
    for p in points {
        writeln!(
            md,
            "| {} | {} | {} | {:.0} | {:.2} ± {:.2} | {:.2} | {:.4} | {:.3} | {:.2} |",
            p.method,
            p.step,
            p.samples,
            p.train_secs,
            p.range_mae_front_m,
            p.range_mae_front_std_m,
            p.range_mae_rear_m,
            p.jsd_all,
            p.ring_spread_m,
            p.seconds_per_scan
        )?;
    }
    writeln!(md)?;
    writeln!(md, "![range MAE against training time](methods.png)")?;
    writeln!(md)?;
    writeln!(md, "![JSD against training time](methods_jsd.png)")?;
    veila_data::atomic::write_atomic(&out.join("report.md"), md.as_bytes())?;
    let mut names: Vec<&str> = points.iter().map(|p| p.method.as_str()).collect();
    names.dedup();
    names.sort_unstable();
    names.dedup();
    let curve = |pick: &dyn Fn(&Point) -> f64| -> Vec<Series> {
        names
            .iter()
            .map(|n| {
                let mut pts: Vec<(f64, f64)> = points
                    .iter()
                    .filter(|p| p.method == *n)
                    .map(|p| (p.train_secs, pick(p)))
                    .collect();
                pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                Series::new(*n, pts, SeriesStyle::LineMarkers)
            })
            .collect()
    };
    Plot {
        title: "Front range MAE against training time (lower is better)".into(),
        x_label: "training seconds (2 CPU cores)".into(),
        y_label: "range MAE front (m, log)".into(),
        y_log: true,
        series: curve(&|p| p.range_mae_front_m),
        ..Plot::default()
    }
    .write_png(&out.join("methods.png"), 800, 500)?;
    Plot {
        title: "BEV JSD against training time (lower is better)".into(),
        x_label: "training seconds (2 CPU cores)".into(),
        y_label: "JSD (all)".into(),
        series: curve(&|p| p.jsd_all),
        ..Plot::default()
    }
    .write_png(&out.join("methods_jsd.png"), 800, 500)?;
    println!("wrote {}", out.display());
    Ok(())
}
