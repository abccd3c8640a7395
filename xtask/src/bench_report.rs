//! `cargo xtask bench-report`: Veila against the unconditional baseline and every ablation on a
//! held-out simulator test split, and what generation quality costs in time (sampler x steps).
//!
//! Writes `report.md`, `report.json` and PNG plots to `--out`. Every variant's denoiser is trained
//! here with the same budget, data, seed and the same (frozen) encoders of the bundled model, so the
//! variants differ only in the switch under test. Metrics are computed per sample seed; the report
//! gives the mean and the standard deviation over seeds, and the number of scans behind each value.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::Device;
use clap::Args;
use serde::Serialize;
use veila_data::vis::plot::{BarChart, BarGroup, Plot, Series, SeriesStyle};
use veila_diffusion::app::GenerateOptions;
use veila_diffusion::app::bundle::{Bundle, Variant};
use veila_diffusion::app::scoring::{
    Judges, SetMetrics, Stat, data_floor, metric_stats, set_metrics,
};
use veila_diffusion::app::sim_examples::{
    RenderStyle, SimExample, TrainImages, retrieval_baseline, test_list_for, train_split_of,
};
use veila_diffusion::{SamplerConfig, SamplerName};
use veila_geom::RangeImage;
use veila_nn::feature_nets::FeatureNets;

use crate::bench_real::{sampler_for, sampler_parser};
use crate::progress::{render_split, workspace_root};
use crate::train_default::{self, TrainDefaultArgs};

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
    #[arg(long, value_enum, default_value = "finetune")]
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

/// How ablation variants are trained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
enum Protocol {
    /// From the bundled model's weights.
    Finetune,
    /// From a seeded initialisation.
    Scratch,
}

impl Protocol {
    /// The protocol's tag in the variants' folder names.
    fn tag(self) -> &'static str {
        match self {
            Protocol::Finetune => "ft",
            Protocol::Scratch => "scratch",
        }
    }
}

#[derive(Debug, Serialize)]
struct VariantResult {
    /// `model`, `baseline` or `floor`.
    kind: String,
    variant: String,
    label: String,
    model: String,
    train_steps: u64,
    seconds_per_scan: f64,
    /// metric name -> region -> stat
    metrics: BTreeMap<String, BTreeMap<String, Stat>>,
}

#[derive(Debug, Serialize)]
struct SweepPoint {
    sampler: String,
    steps: usize,
    /// Residual bundles: the residual weight (1 = full samples).
    residual_weight: f64,
    seconds_per_scan: f64,
    jsd_all: f64,
    range_mae_front_m: f64,
    scans: usize,
}

#[derive(Debug, Serialize)]
struct Report {
    command: String,
    date_utc: String,
    machine: String,
    test_split: String,
    test_frames: usize,
    folds: usize,
    baseline_frames: usize,
    seeds: u64,
    train_steps: u64,
    train_frames: usize,
    protocol: Protocol,
    /// `--sampler` (ddpm, ddim or dpm).
    sampler: String,
    sampler_steps: usize,
    quick: bool,
    shipped_only: bool,
    variants: Vec<VariantResult>,
    sweep: Vec<SweepPoint>,
    /// The bundle on the real frames (issue 18), `None` with `--no-real`.
    real: Option<veila_diffusion::app::real_frames::RealReport>,
    notes: Vec<String>,
}

/// Generates one scan per test frame with `bundle` and `sampler` and seed; returns range images and
/// the seconds spent.
fn generate_all(
    bundle: &Bundle,
    tests: &[SimExample],
    sampler: &SamplerConfig,
    unconditional: bool,
    residual_weight: f64,
    seed: u64,
    label: &str,
) -> Result<(Vec<RangeImage>, f64)> {
    let bar = crate::progress::progress_bar(tests.len() as u64, label);
    let t = Instant::now();
    let mut out = Vec::with_capacity(tests.len());
    for (i, ex) in tests.iter().enumerate() {
        let opts = GenerateOptions {
            sampler: sampler.clone(),
            samples: 1,
            seed: seed.wrapping_mul(1_000_003).wrapping_add(i as u64),
            unconditional,
            residual_weight,
        };
        let views = ex.views(bundle.config.num_views());
        let mut scans = bundle.generate(&views, &opts, |_, _| {})?;
        out.push(scans.swap_remove(0));
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok((out, t.elapsed().as_secs_f64()))
}

/// A result row from per-set metric values.
fn row(
    kind: &str,
    name: &str,
    label: &str,
    model: &str,
    per_set: &[SetMetrics],
    scans_per_set: usize,
) -> VariantResult {
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

/// Runs the benchmark and writes the report.
pub fn run(mut args: BenchReportArgs) -> Result<()> {
    if args.quick {
        shrink_for_quick(&mut args);
    }
    if let Some(w) = args
        .sweep_residual_weights
        .iter()
        .find(|w| !(0.0..=1.0).contains(*w))
    {
        bail!("--sweep-residual-weights: {w} is not between 0 and 1");
    }
    let t_all = Instant::now();
    let bench = Bench::prepare(args)?;
    let mut baselines = bench.baselines()?;
    let mut results = std::mem::take(&mut baselines.rows);
    results.extend(bench.shipped()?);
    results.extend(bench.variants()?);
    let sweep = bench.sweep()?;
    let out = &bench.out;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let real = bench.real_frames(&baselines)?;
    let report = bench.report(&baselines, results, sweep, real);
    write_report(out, &report)?;
    println!(
        "wrote {} in {:.0} s",
        out.display(),
        t_all.elapsed().as_secs_f64()
    );
    Ok(())
}

/// `--quick`: a small benchmark for trying the pipeline.
fn shrink_for_quick(args: &mut BenchReportArgs) {
    args.test_frames = 12;
    args.folds = 2;
    args.baseline_frames = 48;
    args.seeds = 2;
    args.train_steps = 40;
    args.train_frames = 96;
    args.steps = 8;
    args.sweep_frames = 3;
    args.sweep_steps = vec![4, 8, 16];
}

/// The zero-skill baselines and the data floor, with what the real-frame evaluation reuses.
struct Baselines {
    rows: Vec<VariantResult>,
    /// Frames the baselines were drawn from.
    train_frames: usize,
    /// The per-pixel median of those frames' scans.
    median: RangeImage,
}

/// What every part of the benchmark shares: the bundled model, the test frames, their folds and
/// judges.
struct Bench {
    args: BenchReportArgs,
    root: PathBuf,
    device: Device,
    model_dir: PathBuf,
    out: PathBuf,
    work: PathBuf,
    base: Bundle,
    train_list: PathBuf,
    test_list: PathBuf,
    /// The bundle's config with as many views as the most-viewed variant takes.
    rig_config: veila_diffusion::app::BundleConfig,
    tests: Vec<SimExample>,
    nets: Option<FeatureNets>,
    /// Contiguous folds of the test frames: the test list interleaves its scene files, so every
    /// fold holds all of them.
    folds: Vec<std::ops::Range<usize>>,
    fold_judges: Vec<Judges>,
}

impl Bench {
    /// Loads the bundle and the feature networks, simulates the test frames and splits them into
    /// folds.
    fn prepare(args: BenchReportArgs) -> Result<Self> {
        let root = workspace_root();
        let device = Device::Cpu;
        let abs = |p: &Path| crate::progress::in_workspace(p);
        let model_dir = abs(&args.model);
        let base = Bundle::from_dir(&model_dir, &device)
            .with_context(|| format!("loading {}", model_dir.display()))?;
        // the baselines and every fine-tuned variant draw from the bundle's own training list
        let train_list = train_split_of(&base.config);
        let test_list = args
            .test_scenes
            .clone()
            .unwrap_or_else(|| test_list_for(&root, &train_list));
        let rig_config = rig_config(&args, &base);
        let tests = render_split(
            &test_list,
            args.test_frames,
            &rig_config,
            &RenderStyle::default(),
            "simulating test frames",
        )?;
        let nets_dir = root.join("models/feature-nets");
        let nets = match FeatureNets::from_dir(&nets_dir, &device) {
            Ok(n) => Some(n),
            Err(e) => {
                println!("FRD / FPD / CM-SC skipped: {e}");
                None
            }
        };
        if args.folds == 0 || tests.len() < 2 * args.folds {
            bail!(
                "{} test frames cannot make {} folds of at least 2 frames",
                tests.len(),
                args.folds
            );
        }
        let folds: Vec<std::ops::Range<usize>> = (0..args.folds)
            .map(|f| f * tests.len() / args.folds..(f + 1) * tests.len() / args.folds)
            .collect();
        let fold_judges = folds
            .iter()
            .map(|r| Judges::new(&base, &tests[r.clone()], nets.as_ref(), &device))
            .collect::<veila_diffusion::Result<Vec<_>>>()?;
        Ok(Self {
            out: abs(&args.out),
            work: abs(&args.work),
            args,
            root,
            device,
            model_dir,
            base,
            train_list,
            test_list,
            rig_config,
            tests,
            nets,
            folds,
            fold_judges,
        })
    }

    fn fold_size(&self) -> usize {
        self.folds[0].len()
    }

    /// The metrics of `generated` (one scan per test frame), fold by fold.
    fn per_fold(&self, bundle: &Bundle, generated: &[RangeImage]) -> Result<Vec<SetMetrics>> {
        let sets = self.folds.iter().zip(&self.fold_judges).map(|(r, j)| {
            let (g, t) = (&generated[r.clone()], &self.tests[r.clone()]);
            set_metrics(bundle, g, t, j, self.nets.as_ref())
        });
        Ok(sets.collect::<veila_diffusion::Result<_>>()?)
    }

    /// `bundle`'s scans of every test frame for `seeds` seeds, scored fold by fold; with the
    /// seconds per scan.
    fn score_seeds(
        &self,
        bundle: &Bundle,
        sampler: &SamplerConfig,
        (unconditional, residual_weight): (bool, f64),
        seeds: u64,
        name: &str,
    ) -> Result<(Vec<SetMetrics>, f64)> {
        let mut per_set = Vec::new();
        let mut secs = 0.0;
        for seed in 0..seeds {
            let (generated, s) = generate_all(
                bundle,
                &self.tests,
                sampler,
                unconditional,
                residual_weight,
                seed,
                &format!("{name} seed {seed}"),
            )?;
            secs += s;
            per_set.extend(self.per_fold(bundle, &generated)?);
        }
        Ok((per_set, secs / (seeds as f64 * self.tests.len() as f64)))
    }

    /// The zero-skill baselines (the median training scan, retrieval for a conditional bundle)
    /// and the data floor.
    fn baselines(&self) -> Result<Baselines> {
        let base = &self.base;
        let fold_size = self.fold_size();
        let baseline_train = render_split(
            &self.train_list,
            self.args.baseline_frames,
            &base.config,
            &RenderStyle::default(),
            "simulating baseline train frames",
        )?;
        let refs: Vec<&RangeImage> = baseline_train.iter().map(|e| &e.range).collect();
        let median = veila_metrics::baseline::median_scan(&refs)?;
        let mut rows = vec![row(
            "baseline",
            "mean-scan",
            &format!(
                "mean training scan (per-pixel median of {} train frames)",
                baseline_train.len()
            ),
            "-",
            &self.per_fold(base, &vec![median.clone(); self.tests.len()])?,
            fold_size,
        )];
        if base.is_conditional() {
            let retrieved = retrieval_baseline(base, &baseline_train, &self.tests)?;
            rows.push(row(
                "baseline",
                "retrieval",
                "retrieval (train scan with the nearest image in the frozen encoders' features)",
                "-",
                &self.per_fold(base, &retrieved)?,
                fold_size,
            ));
        }
        rows.push(row(
            "floor",
            "data-floor",
            "data floor (true scans of one fold vs another)",
            "-",
            &data_floor(&self.fold_judges, self.nets.as_ref()),
            fold_size,
        ));
        Ok(Baselines {
            rows,
            train_frames: baseline_train.len(),
            median,
        })
    }

    /// The bundled model as shipped: its own sampler settings, no further training (and a
    /// residual bundle's mean network alone).
    fn shipped(&self) -> Result<Vec<VariantResult>> {
        let (args, base) = (&self.args, &self.base);
        let sampler = sampler_for(args.sampler, args.steps, base.config.sampler.guidance_scale);
        let mut shipped: Vec<(&str, String, f64, u64)> = vec![(
            "shipped",
            format!(
                "Veila, the bundled model as shipped ({} {} steps)",
                args.steps,
                sampler.kind.title()
            ),
            1.0,
            args.seeds,
        )];
        if base.config.residual.is_some() {
            // deterministic: one seed
            shipped.push((
                "shipped-mean-net",
                "its mean network alone (residual weight 0: the smooth conditional mean)".into(),
                0.0,
                1,
            ));
        }
        let mut rows = Vec::new();
        for (name, label, weight, seeds) in shipped {
            let (per_set, per_scan) =
                self.score_seeds(base, &sampler, (false, weight), seeds, name)?;
            println!("  {label}: {per_scan:.2} s/scan");
            rows.push(VariantResult {
                seconds_per_scan: per_scan,
                ..row(
                    "model",
                    name,
                    &label,
                    &self.model_dir.display().to_string(),
                    &per_set,
                    self.fold_size(),
                )
            });
        }
        Ok(rows)
    }

    /// The variants to compare: every one asked for (all by default); with `--shipped-only`, only
    /// the fine-tuning protocol's unconditional branch of a conditional bundle.
    fn variant_list(&self) -> Vec<Variant> {
        let args = &self.args;
        if args.shipped_only {
            match args.protocol {
                Protocol::Finetune if self.base.is_conditional() => vec![Variant::Unconditional],
                _ => Vec::new(),
            }
        } else {
            args.variants
                .clone()
                .unwrap_or_else(|| Variant::ALL.to_vec())
        }
    }

    /// Every variant trained (unless its bundle is in `--work` already) and scored.
    fn variants(&self) -> Result<Vec<VariantResult>> {
        let args = &self.args;
        let variants = self.variant_list();
        let needs_training = variants
            .iter()
            .any(|v| !(args.protocol == Protocol::Finetune && *v == Variant::Unconditional));
        // the variants train on images drawn as the bundle's own were (its provenance)
        let train_style = TrainImages::style_of_bundle(&self.base.config);
        let train_frames = if needs_training {
            render_split(
                &self.train_list,
                args.train_frames,
                &self.rig_config,
                &train_style,
                "simulating train frames",
            )?
        } else {
            Vec::new()
        };
        let mut rows = Vec::new();
        for v in variants {
            rows.push(self.variant(v, &train_style, &train_frames)?);
        }
        Ok(rows)
    }

    /// One variant: its bundle (trained from `train_frames` when not there yet), scored.
    fn variant(
        &self,
        v: Variant,
        train_style: &RenderStyle,
        train_frames: &[SimExample],
    ) -> Result<VariantResult> {
        let args = &self.args;
        // under fine-tuning the unconditional baseline is the bundled network's own unconditional
        // branch (trained by condition dropout): no extra training
        let drop_condition = args.protocol == Protocol::Finetune && v == Variant::Unconditional;
        let dir = if drop_condition {
            self.model_dir.clone()
        } else {
            self.work.join(format!(
                "{}-{}-{}steps",
                v.name(),
                self.args.protocol.tag(),
                args.train_steps
            ))
        };
        if !drop_condition && Bundle::from_dir(&dir, &self.device).is_err() {
            self.train_variant(v, &dir, train_style, train_frames)?;
        }
        let bundle = Bundle::from_dir(&dir, &self.device)?;
        let guidance = if bundle.is_conditional() && !drop_condition {
            self.base.config.sampler.guidance_scale
        } else {
            1.0
        };
        let sampler = sampler_for(args.sampler, args.steps, guidance);
        let (per_set, per_scan) = self.score_seeds(
            &bundle,
            &sampler,
            (drop_condition, 1.0),
            args.seeds,
            v.name(),
        )?;
        println!("  {}: {per_scan:.2} s/scan", v.label());
        Ok(VariantResult {
            train_steps: args.train_steps,
            seconds_per_scan: per_scan,
            ..row(
                "model",
                v.name(),
                v.label(),
                &dir.display().to_string(),
                &per_set,
                self.fold_size(),
            )
        })
    }

    /// Trains variant `v` into `dir` with the benchmark's budget, from the bundled model's
    /// encoders (and weights, under fine-tuning).
    fn train_variant(
        &self,
        v: Variant,
        dir: &Path,
        train_style: &RenderStyle,
        train_frames: &[SimExample],
    ) -> Result<()> {
        let args = &self.args;
        let tag = args.protocol.tag();
        let model_dir = &self.model_dir;
        let base = &self.base.config;
        println!(
            "training variant {} ({} steps, {tag})",
            v.name(),
            args.train_steps
        );
        train_default::run_with(
            TrainDefaultArgs {
                out: dir.to_path_buf(),
                variant: v,
                method: base.method(),
                mean_steps: None,
                checkpoint_every: 250,
                frames: args.train_frames,
                encoder_steps: 0,
                steps: args.train_steps,
                batch: 2,
                lr: match args.protocol {
                    Protocol::Finetune => 2e-4,
                    Protocol::Scratch => 1e-3,
                },
                seed: 0,
                work: Some(
                    self.work
                        .join(format!("ckpt-{}-{tag}-{}", v.name(), args.train_steps)),
                ),
                encoders_from: Some(model_dir.clone()),
                init_from: (args.protocol == Protocol::Finetune).then(|| model_dir.clone()),
                images: TrainImages::of_bundle(base),
                randomize_share: train_style.share,
                wide_facades: (train_style.wide_facade_share > 0.0)
                    .then_some(train_style.wide_facade_share),
                augment_encoders: false,
                ground_prior: false,
                sky_depth: false,
                // with the bundle's depth features wherever a variant has the depth encoder
                depth_features: base.depth_features()
                    && veila_diffusion::app::BundleConfig::cpu_default(v)
                        .depth_encoder
                        .is_some(),
                scenes: self.train_list.clone(),
                encoder_scenes: None,
                device: crate::device::DeviceArg::Cpu,
                base_channels: None,
                res_blocks: None,
                channel_mults: None,
                ema_decay: veila_diffusion::app::sim_recipe::RECIPE_EMA_DECAY,
                loss_weighting: "min-snr".into(),
                snapshot_every: None,
            },
            Some(train_frames),
        )?;
        Ok(())
    }

    /// The sampler sweep on the bundled model: every sampler at every step count, then for a
    /// residual bundle the texture's price in pixel error at the variants' step count.
    fn sweep(&self) -> Result<Vec<SweepPoint>> {
        let (args, base) = (&self.args, &self.base);
        let sweep_tests = &self.tests[..args.sweep_frames.min(self.tests.len())];
        let sweep_judges = Judges::new(base, sweep_tests, self.nets.as_ref(), &self.device)?;
        // (sampler, steps, residual weight, label)
        let mut points: Vec<(SamplerName, usize, f64, String)> = Vec::new();
        for name in SamplerName::ALL {
            for &steps in &args.sweep_steps {
                points.push((name, steps, 1.0, format!("{name:>4} x {steps:>3}")));
            }
        }
        if base.config.residual.is_some() {
            for &weight in &args.sweep_residual_weights {
                points.push((
                    args.sampler,
                    args.steps,
                    weight,
                    format!("residual weight {weight}"),
                ));
            }
        }
        let mut sweep = Vec::new();
        for (name, steps, weight, label) in points {
            let sampler = sampler_for(name, steps, base.config.sampler.guidance_scale);
            let (generated, secs) =
                generate_all(base, sweep_tests, &sampler, false, weight, 0, &label)?;
            let m = set_metrics(
                base,
                &generated,
                sweep_tests,
                &sweep_judges,
                self.nets.as_ref(),
            )?;
            let p = SweepPoint {
                sampler: name.to_string(),
                steps: if weight == 0.0 { 0 } else { steps },
                residual_weight: weight,
                seconds_per_scan: secs / sweep_tests.len() as f64,
                jsd_all: m["jsd"]["all"],
                range_mae_front_m: m["range mae (m)"]["front"],
                scans: sweep_tests.len(),
            };
            println!(
                "  {label}: {:.2} s/scan, jsd {:.4}, range mae front {:.2} m",
                p.seconds_per_scan, p.jsd_all, p.range_mae_front_m
            );
            sweep.push(p);
        }
        Ok(sweep)
    }

    /// The bundle on the real frames (issue 18); `None` with `--no-real`.
    fn real_frames(
        &self,
        baselines: &Baselines,
    ) -> Result<Option<veila_diffusion::app::real_frames::RealReport>> {
        use veila_diffusion::app::real_frames::{RealOptions, evaluate, real_root};
        let (args, base) = (&self.args, &self.base);
        if args.no_real {
            return Ok(None);
        }
        let sampler = sampler_for(args.sampler, args.steps, base.config.sampler.guidance_scale);
        let street_scan =
            crate::bench_real::reference_mean_scan(&base.config, baselines.train_frames)?;
        Ok(Some(evaluate(
            base,
            &RealOptions {
                root: &real_root(&self.root),
                sampler: &sampler,
                sampler_label: format!("{} {} steps", sampler.kind.title(), args.steps),
                seeds: args.real_seeds,
                mean_scan: &baselines.median,
                reference_mean_scan: street_scan.as_ref(),
            },
            &self.out,
        )?))
    }

    /// The report of the rows, the sweep and the real frames.
    fn report(
        &self,
        baselines: &Baselines,
        variants: Vec<VariantResult>,
        sweep: Vec<SweepPoint>,
        real: Option<veila_diffusion::app::real_frames::RealReport>,
    ) -> Report {
        let args = &self.args;
        Report {
            command: crate::progress::command_line(),
            date_utc: veila_data::stamp::report_time(),
            machine: format!("{} CPU cores (CPU only)", crate::progress::cpu_cores()),
            test_split: self.test_list.display().to_string(),
            test_frames: self.tests.len(),
            folds: args.folds,
            baseline_frames: baselines.train_frames,
            seeds: args.seeds,
            train_steps: args.train_steps,
            train_frames: args.train_frames,
            protocol: args.protocol,
            sampler: args.sampler.to_string(),
            sampler_steps: args.steps,
            quick: args.quick,
            shipped_only: args.shipped_only,
            variants,
            sweep,
            real,
            notes: report_notes(args),
        }
    }
}

/// The bundle's config with as many views as the most-viewed variant takes (three-cameras: 3):
/// the frames carry that many cameras, and every other model reads the first.
fn rig_config(args: &BenchReportArgs, base: &Bundle) -> veila_diffusion::app::BundleConfig {
    let rig_views = if args.shipped_only {
        1
    } else {
        args.variants
            .clone()
            .unwrap_or_else(|| Variant::ALL.to_vec())
            .iter()
            .map(|v| v.views())
            .max()
            .unwrap_or(1)
    };
    let mut rig_config = base.config.clone();
    if let Some(c) = rig_config.denoiser.conditioning.as_mut() {
        c.num_views = c.num_views.max(rig_views);
    }
    rig_config
}

/// The report's notes on the protocol and the metrics.
fn report_notes(args: &BenchReportArgs) -> Vec<String> {
    vec![
        match args.protocol {
            Protocol::Finetune => format!("Protocol `finetune`: every variant starts from the bundled model's denoiser and is trained {} more steps with its switch flipped (weights that no longer fit are freshly initialised); `Veila` is the bundled model fine-tuned the same way (the control). The unconditional row is the bundled network's own unconditional branch (trained by 10% condition dropout), not a separately trained model.", args.train_steps),
            Protocol::Scratch => format!("Protocol `scratch`: every variant is trained from the same seeded initialisation for {} steps.", args.train_steps),
        },
        "All variants share the data, seed, step budget and the frozen encoders of the bundled model; differences smaller than the spread over seeds are not significant.".into(),
        "Reference scans are the true simulated scans projected onto the same range-image grid as the generated ones.".into(),
        "CM-DC: mean absolute relative difference between each generated point's camera depth and the bundled depth encoder's depth head where it projects. CM-SC: percentage of generated points whose class from the shipped range segmentation net (rangenet-small) agrees with the bundled semantic encoder's head where they project (unlabelled excluded). Both over the camera's field of view.".into(),
        "FRD / FPD use the shipped feature networks trained on simulator data (models/feature-nets), per region on the points of that region; with a dozen scans per side the covariances are rank-deficient, so read them as relative numbers between rows, not as converged distances or as comparable to published values.".into(),
    ]
}

fn fmt_stat(s: &Stat) -> String {
    if !s.mean.is_finite() {
        return "n/a".into();
    }
    let digits = if s.mean.abs() >= 100.0 {
        1
    } else if s.mean.abs() >= 1.0 {
        2
    } else {
        4
    };
    format!("{:.*} ± {:.*}", digits, s.mean, digits, s.std)
}

/// Writes `report.json`, `report.md` and the plots to `out`.
fn write_report(out: &Path, r: &Report) -> Result<()> {
    let json = serde_json::to_string_pretty(r)?;
    veila_data::atomic::write_atomic(&out.join("report.json"), json.as_bytes())?;
    let mut md = String::new();
    md_header(&mut md, r)?;
    md_region_tables(&mut md, r)?;
    md_sweep(&mut md, r)?;
    md_real_and_notes(&mut md, r)?;
    veila_data::atomic::write_atomic(&out.join("report.md"), md.as_bytes())?;
    plot_variants(&out.join("variants.png"), r)?;
    plot_sweep(&out.join("sampler_tradeoff.png"), r)
}

/// The report's title and what was run.
fn md_header(md: &mut String, r: &Report) -> Result<()> {
    use std::fmt::Write as _;
    writeln!(md, "# Veila benchmark report")?;
    writeln!(md)?;
    writeln!(
        md,
        "Generated by `{}` on {} ({}). Held-out split: `{}` ({} frames); {} sample seeds per model; {}; sampler {} with {} steps.",
        r.command,
        r.date_utc,
        r.machine,
        r.test_split,
        r.test_frames,
        r.seeds,
        if r.shipped_only {
            "the bundled model as shipped, no ablation variants trained".to_string()
        } else {
            format!(
                "every ablation variant's denoiser trained for {} steps on {} training frames",
                r.train_steps, r.train_frames
            )
        },
        r.sampler
            .parse::<SamplerName>()
            .map_or_else(|_| r.sampler.clone(), |n| n.config(1).kind.title()),
        r.sampler_steps
    )?;
    if r.quick {
        writeln!(md)?;
        writeln!(
            md,
            "**Quick run:** the variants are trained for only {} steps, so this report shows that the benchmark runs end to end and how large the spread is, not converged differences between the variants.",
            r.train_steps
        )?;
    }
    writeln!(md)?;
    writeln!(
        md,
        "Values are mean ± standard deviation over {} disjoint folds of the test frames (times {} sample seeds for the models). Lower is better except CM-SC. Rows in italics need no camera image (the mean training scan) or no model (retrieval from {} training frames; the data floor compares true scans of two folds: what a perfect generator would score).",
        r.folds, r.seeds, r.baseline_frames
    )?;
    Ok(())
}

/// One table per region: every row's metrics.
fn md_region_tables(md: &mut String, r: &Report) -> Result<()> {
    use std::fmt::Write as _;
    let metric_names: Vec<String> = r
        .variants
        .first()
        .map(|v| v.metrics.keys().cloned().collect())
        .unwrap_or_default();
    for region in ["all", "front", "rear"] {
        let names: Vec<&String> = metric_names
            .iter()
            .filter(|n| {
                r.variants[0]
                    .metrics
                    .get(*n)
                    .is_some_and(|m| m.contains_key(region))
            })
            .collect();
        if names.is_empty() {
            continue;
        }
        writeln!(md)?;
        writeln!(md, "## Region: {region}")?;
        writeln!(md)?;
        write!(md, "| row |")?;
        for n in &names {
            write!(md, " {n} |")?;
        }
        writeln!(md)?;
        write!(md, "|---|")?;
        for _ in &names {
            write!(md, "---|")?;
        }
        writeln!(md)?;
        for v in &r.variants {
            let label = match v.kind.as_str() {
                "model" => v.label.clone(),
                _ => format!("*{}*", v.label),
            };
            write!(md, "| {label} |")?;
            for n in &names {
                match v.metrics.get(*n).and_then(|m| m.get(region)) {
                    Some(st) => write!(md, " {} |", fmt_stat(st))?,
                    None => write!(md, " – |")?,
                }
            }
            writeln!(md)?;
        }
    }
    Ok(())
}

/// The sampler sweep's table.
fn md_sweep(md: &mut String, r: &Report) -> Result<()> {
    use std::fmt::Write as _;
    writeln!(md)?;
    writeln!(md, "![variants](variants.png)")?;
    writeln!(md)?;
    writeln!(md, "## What accuracy costs in time (bundled model)")?;
    writeln!(md)?;
    writeln!(
        md,
        "| sampler | steps | residual weight | s / scan | JSD (all) | range MAE front (m) |"
    )?;
    writeln!(md, "|---|---|---|---|---|---|")?;
    for p in &r.sweep {
        let num = |v: f64, d: usize| {
            if v.is_finite() {
                format!("{v:.d$}")
            } else {
                "n/a".to_string()
            }
        };
        writeln!(
            md,
            "| {} | {} | {} | {:.2} | {} | {} |",
            p.sampler,
            p.steps,
            p.residual_weight,
            p.seconds_per_scan,
            num(p.jsd_all, 4),
            num(p.range_mae_front_m, 2)
        )?;
    }
    writeln!(md)?;
    writeln!(md, "![sampler trade-off](sampler_tradeoff.png)")?;
    writeln!(md)?;
    Ok(())
}

/// The real frames' section and the notes.
fn md_real_and_notes(md: &mut String, r: &Report) -> Result<()> {
    use std::fmt::Write as _;
    if let Some(real) = &r.real {
        writeln!(md, "{}", real.markdown())?;
    }
    writeln!(md, "## Notes")?;
    writeln!(md)?;
    for n in &r.notes {
        writeln!(md, "- {n}")?;
    }
    Ok(())
}

/// `variants.png`: every row's BEV JSD by region.
fn plot_variants(path: &Path, r: &Report) -> Result<()> {
    let jsd_key = "jsd".to_string();
    let categories: Vec<String> = ["all", "front", "rear"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    let groups: Vec<BarGroup> = r
        .variants
        .iter()
        .map(|v| BarGroup {
            name: v.label.clone(),
            values: categories
                .iter()
                .map(|c| {
                    v.metrics
                        .get(&jsd_key)
                        .and_then(|m| m.get(c))
                        .map_or(f64::NAN, |s| s.mean)
                })
                .collect(),
            errors: Some(
                categories
                    .iter()
                    .map(|c| {
                        v.metrics
                            .get(&jsd_key)
                            .and_then(|m| m.get(c))
                            .map_or(f64::NAN, |s| s.std)
                    })
                    .collect(),
            ),
        })
        .collect();
    BarChart {
        title: "BEV JSD by region (lower is better; bars: seed std)".into(),
        y_label: "JSD".into(),
        categories,
        groups,
    }
    .write_png(path, 960, 480)?;
    Ok(())
}

/// `sampler_tradeoff.png`: quality against time per scan, one line per sampler.
fn plot_sweep(path: &Path, r: &Report) -> Result<()> {
    let mut series = Vec::new();
    for name in SamplerName::ALL.map(SamplerName::as_str) {
        let pts: Vec<(f64, f64)> = r
            .sweep
            .iter()
            .filter(|p| p.sampler == name && p.residual_weight == 1.0)
            .map(|p| (p.seconds_per_scan, p.jsd_all))
            .collect();
        series.push(Series::new(name, pts, SeriesStyle::LineMarkers));
    }
    Plot {
        title: "Generation: quality vs time per scan (points: step counts)".into(),
        x_label: "seconds per scan (log)".into(),
        y_label: "BEV JSD (all)".into(),
        x_log: true,
        series,
        ..Plot::default()
    }
    .write_png(path, 800, 500)?;
    Ok(())
}
