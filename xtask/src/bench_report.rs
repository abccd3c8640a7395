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
use glam::Vec3;
use serde::Serialize;
use veila_data::vis::plot::{BarChart, BarGroup, Plot, Series, SeriesStyle};
use veila_diffusion::SamplerConfig;
use veila_diffusion::app::bundle::{Bundle, Variant};
use veila_diffusion::app::{CameraView, GenerateOptions};
use veila_geom::{RangeImage, RayTable, Region};
use veila_metrics::bev::{BevConfig, BevHistogram, bev_histogram};
use veila_metrics::crossmodal::{
    DepthAlignment, Map2d, ProjectionFilter, cm_depth_consistency, cm_semantic_consistency,
};
use veila_metrics::dist;
use veila_metrics::fd::{self, FeatureStats};
use veila_nn::encoders::small_cnn::SmallCnn;
use veila_nn::feature_nets::FeatureNets;

use crate::bench_real::sampler_for;
use crate::simdata::{SimExample, render_split, workspace_root};
use crate::train_default::{self, TrainDefaultArgs};

/// Arguments of `cargo xtask bench-report`.
#[derive(Debug, Args)]
pub struct BenchReportArgs {
    /// Output folder (report.md, report.json, *.png).
    #[arg(long, default_value = "docs/bench-report")]
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
    #[arg(long, default_value = "dpm", value_parser = ["ddpm", "ddim", "dpm"])]
    sampler: String,
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

/// A metric over several sets of scans (folds of the test frames, times sample seeds for a
/// model): mean and standard deviation over the sets.
#[derive(Debug, Clone, Serialize)]
struct Stat {
    mean: f64,
    std: f64,
    sets: usize,
    scans_per_set: usize,
}

fn stat(values: &[f64], scans_per_set: usize) -> Stat {
    let finite: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    let n = finite.len().max(1) as f64;
    let mean = finite.iter().sum::<f64>() / n;
    let var = if finite.len() > 1 {
        finite.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    Stat {
        mean: if finite.is_empty() { f64::NAN } else { mean },
        std: var.sqrt(),
        sets: values.len(),
        scans_per_set,
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
    real: Option<crate::bench_real::RealReport>,
    notes: Vec<String>,
}

/// Judges shared by every variant: the bundled model's encoder heads (depth for CM-DC, semantics
/// for CM-SC) and everything about the reference scans, computed once for all variants and seeds.
struct Judges {
    depth_pred: Vec<Vec<f32>>,
    label_pred: Vec<Vec<u32>>,
    /// Per region, in `Region::ALL` order.
    reference: Vec<RegionReference>,
}

/// The reference side of the set metrics of one region.
struct RegionReference {
    histograms: Vec<BevHistogram>,
    /// FRD and FPD feature rows (flattened), when the feature networks are present.
    features: Option<(Vec<f32>, Vec<f32>)>,
}

fn make_judges(
    bundle: &Bundle,
    tests: &[SimExample],
    nets: Option<&FeatureNets>,
    device: &Device,
) -> Result<Judges> {
    let (h, w) = (bundle.config.image_height, bundle.config.image_width);
    let mut depth_pred = Vec::new();
    let mut label_pred = Vec::new();
    let rays = RayTable::new(&bundle.config.denoiser.sensor)?;
    let mut reference_points = Vec::new();
    let mut reference_intensity = Vec::new();
    // each judge's input: the image, and its camera's ground prior when the judge takes one
    let input = |net: &SmallCnn, ex: &SimExample| -> Result<candle_core::Tensor> {
        Ok(net
            .config()
            .input_tensor(&ex.rgb, h, w, Some(&ex.camera), device)?)
    };
    for ex in tests {
        let d = match &bundle.depth {
            Some(net) => {
                let net = net
                    .as_small_cnn()
                    .context("the judge bundle's depth encoder is not a small CNN")?;
                net.predict_maps(&input(net, ex)?)?[0].depth_m.clone()
            }
            None => None,
        };
        depth_pred.push(d.context("the judge bundle has no depth head")?);
        let l = match &bundle.semantic {
            Some(net) => {
                let net = net
                    .as_small_cnn()
                    .context("the judge bundle's semantic encoder is not a small CNN")?;
                net.predict_maps(&input(net, ex)?)?[0].labels.clone()
            }
            None => None,
        };
        label_pred.push(l.context("the judge bundle has no semantic head")?);
        let un = rays.unproject(&ex.range)?;
        reference_points.push(un.points);
        reference_intensity.push(un.intensity);
    }
    let cfg = BevConfig::r2dm();
    let reference = Region::ALL
        .into_iter()
        .map(|region| {
            let histograms = reference_points
                .iter()
                .map(|p| bev_histogram(p, &cfg, region, "reference scan"))
                .collect::<std::result::Result<Vec<_>, _>>()?;
            let features = nets
                .map(|n| region_features(n, &reference_points, &reference_intensity, region))
                .transpose()?;
            Ok(RegionReference {
                histograms,
                features,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Judges {
        depth_pred,
        label_pred,
        reference,
    })
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
        let n = crate::simdata::views_of(&bundle.config);
        let mut views = vec![CameraView {
            rgb: &ex.rgb,
            camera: &ex.camera,
        }];
        views.extend(ex.extra_views.iter().take(n - 1).map(|v| CameraView {
            rgb: &v.rgb,
            camera: &v.camera,
        }));
        let mut scans = bundle.generate(&views, &opts, |_, _| {})?;
        out.push(scans.swap_remove(0));
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok((out, t.elapsed().as_secs_f64()))
}

fn region_name(r: Region) -> &'static str {
    r.name()
}

/// Per-seed metric values: name -> region -> value.
fn seed_metrics(
    bundle: &Bundle,
    generated: &[RangeImage],
    tests: &[SimExample],
    judges: &Judges,
    nets: Option<&FeatureNets>,
) -> Result<BTreeMap<String, BTreeMap<String, f64>>> {
    let rays = RayTable::new(&bundle.config.denoiser.sensor)?;
    let unprojected = generated
        .iter()
        .map(|r| Ok(rays.unproject(r)?))
        .collect::<Result<Vec<_>>>()?;
    let gen_points: Vec<Vec<Vec3>> = unprojected.iter().map(|u| u.points.clone()).collect();
    let gen_intensity: Vec<Vec<f32>> = unprojected.iter().map(|u| u.intensity.clone()).collect();
    let mut m: BTreeMap<String, BTreeMap<String, f64>> = BTreeMap::new();
    let cfg = BevConfig::r2dm();
    for (region, reference) in Region::ALL.into_iter().zip(&judges.reference) {
        let hg = gen_points
            .iter()
            .map(|p| bev_histogram(p, &cfg, region, "generated scan"))
            .collect::<std::result::Result<Vec<_>, _>>()?;
        let hr = &reference.histograms;
        let rn = region_name(region).to_string();
        m.entry("jsd".into())
            .or_default()
            .insert(rn.clone(), or_nan("jsd", dist::jsd(&hg, hr)));
        m.entry("mmd (x1e4)".into()).or_default().insert(
            rn.clone(),
            1e4 * or_nan("mmd", dist::mmd_r2dm_dense(&hg, hr, 0.5)),
        );
        if let (Some(nets), Some(reference)) = (nets, &reference.features) {
            let (frd, fpd) = frd_fpd(nets, &gen_points, &gen_intensity, reference, region)
                .unwrap_or_else(|e| {
                    eprintln!("  frd / fpd ({rn}): {e:#}; reported as n/a");
                    (f64::NAN, f64::NAN)
                });
            m.entry("frd".into()).or_default().insert(rn.clone(), frd);
            m.entry("fpd".into()).or_default().insert(rn.clone(), fpd);
        }
        let mut sum = 0.0;
        let mut n = 0usize;
        for (g, ex) in generated.iter().zip(tests) {
            if let Some(v) = veila_metrics::range::range_mae(g, &ex.range, region) {
                sum += v;
                n += 1;
            }
        }
        m.entry("range mae (m)".into())
            .or_default()
            .insert(rn, if n > 0 { sum / n as f64 } else { f64::NAN });
    }
    // cross-modal consistency in the camera's field of view, against the encoder heads
    let filter = ProjectionFilter::default();
    let (mut dc, mut sc, mut nd, mut ns) = (0.0, 0.0, 0usize, 0usize);
    for (i, ex) in tests.iter().enumerate() {
        let (w, h) = (ex.camera.width, ex.camera.height);
        let depth = Map2d::new(w, h, &judges.depth_pred[i])?;
        if let Ok(c) = cm_depth_consistency(
            &gen_points[i],
            &ex.camera,
            &depth,
            DepthAlignment::None,
            &filter,
        ) && c.abs_rel.is_finite()
        {
            dc += c.abs_rel;
            nd += 1;
        }
        // CM-SC: the classes the range segmentation net gives the generated points against the
        // image semantic head's classes where they project
        if let Some(nets) = nets {
            let (pts, labels) = nets.segment_points(&gen_points[i], Some(&gen_intensity[i]))?;
            let pred = Map2d::new(w, h, &judges.label_pred[i])?;
            let filter = ProjectionFilter {
                ignore_label: Some(0),
                ..ProjectionFilter::default()
            };
            if let Ok(c) = cm_semantic_consistency(&pts, &labels, &ex.camera, &pred, &filter)
                && c.percent.is_finite()
            {
                sc += c.percent;
                ns += 1;
            }
        }
    }
    let front = region_name(Region::Front).to_string();
    m.entry("cm-dc (abs rel)".into()).or_default().insert(
        front.clone(),
        if nd > 0 { dc / nd as f64 } else { f64::NAN },
    );
    m.entry("cm-sc (%)".into())
        .or_default()
        .insert(front, if ns > 0 { sc / ns as f64 } else { f64::NAN });
    Ok(m)
}

/// A metric's value, or NaN (reported as n/a) when it cannot be computed for this set, e.g. when a
/// poorly trained variant generates no return inside the BEV window.
fn or_nan<E: std::fmt::Display>(what: &str, r: std::result::Result<f64, E>) -> f64 {
    r.unwrap_or_else(|e| {
        eprintln!("  {what}: {e}; reported as n/a");
        f64::NAN
    })
}

/// Points of `region` (and their intensities).
fn in_region(points: &[Vec3], intensity: &[f32], region: Region) -> (Vec<Vec3>, Vec<f32>) {
    points
        .iter()
        .zip(intensity)
        .filter(|(p, _)| region.contains(**p))
        .map(|(p, i)| (*p, *i))
        .unzip()
}

/// FRD and FPD feature rows (flattened) of the scans' points in `region`.
fn region_features(
    nets: &FeatureNets,
    points: &[Vec<Vec3>],
    intensity: &[Vec<f32>],
    region: Region,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let scans: Vec<(Vec<Vec3>, Vec<f32>)> = points
        .iter()
        .zip(intensity)
        .map(|(p, i)| in_region(p, i, region))
        .filter(|(p, _)| !p.is_empty())
        .collect();
    let range_in: Vec<(&[Vec3], Option<&[f32]>)> = scans
        .iter()
        .map(|(p, i)| (p.as_slice(), Some(i.as_slice())))
        .collect();
    let rf = nets.scan_range_features(&range_in)?;
    let point_in: Vec<&[Vec3]> = scans.iter().map(|(p, _)| p.as_slice()).collect();
    let pf = nets.point_features(&point_in)?;
    Ok((rf.concat(), pf.concat()))
}

/// FRD and FPD of generated scans in `region` against the reference features of that region, with
/// the shipped feature networks.
fn frd_fpd(
    nets: &FeatureNets,
    points: &[Vec<Vec3>],
    intensity: &[Vec<f32>],
    (rr, rpf): &(Vec<f32>, Vec<f32>),
    region: Region,
) -> Result<(f64, f64)> {
    let (gr, gpf) = region_features(nets, points, intensity, region)?;
    let rd = nets.rangenet().config().feature_dim();
    let pd = nets.pointnet().config().feature_dim();
    let fd = |a: &[f32], b: &[f32], d: usize| -> Result<f64> {
        if a.len() < 2 * d || b.len() < 2 * d {
            return Ok(f64::NAN);
        }
        Ok(fd::frechet_distance(
            &FeatureStats::from_rows(a, d, "generated features")?,
            &FeatureStats::from_rows(b, d, "reference features")?,
        )?)
    };
    Ok((fd(&gr, rr, rd)?, fd(&gpf, rpf, pd)?))
}

/// Segments a scan with the range net's semantic head: the points that won a range pixel and the
/// class (learning map, 0 = unlabelled) of their pixel.
/// A result row from per-set metric values (name -> region -> value per set).
fn row(
    kind: &str,
    name: &str,
    label: &str,
    model: &str,
    per_set: &[BTreeMap<String, BTreeMap<String, f64>>],
    scans_per_set: usize,
) -> VariantResult {
    let mut metrics: BTreeMap<String, BTreeMap<String, Stat>> = BTreeMap::new();
    if let Some(first) = per_set.first() {
        for (m, regions) in first {
            for region in regions.keys() {
                let vals: Vec<f64> = per_set.iter().map(|x| x[m][region]).collect();
                metrics
                    .entry(m.clone())
                    .or_default()
                    .insert(region.clone(), stat(&vals, scans_per_set));
            }
        }
    }
    VariantResult {
        kind: kind.into(),
        variant: name.into(),
        label: label.into(),
        model: model.into(),
        train_steps: 0,
        seconds_per_scan: 0.0,
        metrics,
    }
}

/// The data floor: the set metrics between the true scans of two disjoint folds (fold `f`
/// against fold `f + 1`), what a perfect generator of this many scans would score.
fn data_floor(folds: &[std::ops::Range<usize>], judges: &[Judges]) -> VariantResult {
    let k = judges.len();
    let per_set: Vec<BTreeMap<String, BTreeMap<String, f64>>> = (0..k)
        .map(|f| {
            let (a, b) = (&judges[f], &judges[(f + 1) % k]);
            let mut m: BTreeMap<String, BTreeMap<String, f64>> = BTreeMap::new();
            for (region, (ra, rb)) in Region::ALL
                .into_iter()
                .zip(a.reference.iter().zip(&b.reference))
            {
                let rn = region_name(region).to_string();
                m.entry("jsd".into()).or_default().insert(
                    rn.clone(),
                    or_nan("jsd", dist::jsd(&ra.histograms, &rb.histograms)),
                );
                m.entry("mmd (x1e4)".into()).or_default().insert(
                    rn,
                    1e4 * or_nan(
                        "mmd",
                        dist::mmd_r2dm_dense(&ra.histograms, &rb.histograms, 0.5),
                    ),
                );
            }
            m
        })
        .collect();
    row(
        "floor",
        "data-floor",
        "data floor (true scans of one fold vs another)",
        "-",
        &per_set,
        folds.first().map_or(0, |r| r.len()),
    )
}

/// Runs the benchmark and writes the report.
pub fn run(mut args: BenchReportArgs) -> Result<()> {
    if args.quick {
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
    if let Some(w) = args
        .sweep_residual_weights
        .iter()
        .find(|w| !(0.0..=1.0).contains(*w))
    {
        bail!("--sweep-residual-weights: {w} is not between 0 and 1");
    }
    let t_all = Instant::now();
    let root = workspace_root();
    let device = Device::Cpu;
    let abs = |p: &Path| {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            root.join(p)
        }
    };
    let model_dir = abs(&args.model);
    let out = abs(&args.out);
    let work = abs(&args.work);
    let base = Bundle::from_dir(&model_dir, &device)
        .with_context(|| format!("loading {}", model_dir.display()))?;
    // the baselines and every fine-tuned variant draw from the bundle's own training list
    let train_list = crate::simdata::train_split_of(&base.config);
    let test_list = args
        .test_scenes
        .clone()
        .unwrap_or_else(|| crate::simdata::test_list_for(&train_list));
    // frames carry as many cameras as the most-viewed variant takes (three-cameras: 3); every
    // other model reads the first
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
    let tests = render_split(
        &root.join(&test_list),
        args.test_frames,
        &rig_config,
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
    // contiguous folds: the test list interleaves its scene files, so every fold holds all of them
    let folds: Vec<std::ops::Range<usize>> = (0..args.folds)
        .map(|f| f * tests.len() / args.folds..(f + 1) * tests.len() / args.folds)
        .collect();
    let fold_judges = folds
        .iter()
        .map(|r| make_judges(&base, &tests[r.clone()], nets.as_ref(), &device))
        .collect::<Result<Vec<_>>>()?;
    let fold_size = folds[0].len();
    let per_fold = |bundle: &Bundle,
                    generated: &[RangeImage]|
     -> Result<Vec<BTreeMap<String, BTreeMap<String, f64>>>> {
        folds
            .iter()
            .zip(&fold_judges)
            .map(|(r, j)| {
                seed_metrics(
                    bundle,
                    &generated[r.clone()],
                    &tests[r.clone()],
                    j,
                    nets.as_ref(),
                )
            })
            .collect()
    };
    let mut results = Vec::new();

    // the zero-skill baselines and the data floor
    let baseline_train = render_split(
        &root.join(&train_list),
        args.baseline_frames,
        &base.config,
        "simulating baseline train frames",
    )?;
    let refs: Vec<&RangeImage> = baseline_train.iter().map(|e| &e.range).collect();
    let median = veila_metrics::baseline::median_scan(&refs)?;
    results.push(row(
        "baseline",
        "mean-scan",
        &format!(
            "mean training scan (per-pixel median of {} train frames)",
            baseline_train.len()
        ),
        "-",
        &per_fold(&base, &vec![median.clone(); tests.len()])?,
        fold_size,
    ));
    if base.is_conditional() {
        let retrieved = crate::simdata::retrieval_baseline(&base, &baseline_train, &tests)?;
        results.push(row(
            "baseline",
            "retrieval",
            "retrieval (train scan with the nearest image in the frozen encoders' features)",
            "-",
            &per_fold(&base, &retrieved)?,
            fold_size,
        ));
    }
    results.push(data_floor(&folds, &fold_judges));

    // the bundled model as shipped: its own sampler settings, no further training
    {
        let sampler = sampler_for(
            &args.sampler,
            args.steps,
            base.config.sampler.guidance_scale,
        )?;
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
        for (name, label, weight, seeds) in shipped {
            let mut per_set = Vec::new();
            let mut secs = 0.0;
            for seed in 0..seeds {
                let (generated, s) = generate_all(
                    &base,
                    &tests,
                    &sampler,
                    false,
                    weight,
                    seed,
                    &format!("{name} seed {seed}"),
                )?;
                secs += s;
                per_set.extend(per_fold(&base, &generated)?);
            }
            let per_scan = secs / (seeds as f64 * tests.len() as f64);
            println!("  {label}: {per_scan:.2} s/scan");
            results.push(VariantResult {
                seconds_per_scan: per_scan,
                ..row(
                    "model",
                    name,
                    &label,
                    &model_dir.display().to_string(),
                    &per_set,
                    fold_size,
                )
            });
        }
    }

    let variants = if args.shipped_only {
        match args.protocol {
            Protocol::Finetune if base.is_conditional() => vec![Variant::Unconditional],
            _ => Vec::new(),
        }
    } else {
        args.variants
            .clone()
            .unwrap_or_else(|| Variant::ALL.to_vec())
    };
    let needs_training = variants
        .iter()
        .any(|v| !(args.protocol == Protocol::Finetune && *v == Variant::Unconditional));
    // the variants train on images drawn as the bundle's own were (its provenance)
    let train_style = crate::simdata::TrainImages::style_of_bundle(&base.config);
    let train_images = crate::simdata::TrainImages::of_bundle(&base.config);
    // and with the bundle's depth features wherever a variant has the depth encoder
    let depth_features = base.config.depth_features();
    let train_frames = if needs_training {
        crate::simdata::render_split_styled(
            &root.join(&train_list),
            args.train_frames,
            &rig_config,
            &train_style,
            "simulating train frames",
        )?
    } else {
        Vec::new()
    };
    for v in variants {
        // under fine-tuning the unconditional baseline is the bundled network's own unconditional
        // branch (trained by condition dropout): no extra training
        let drop_condition = args.protocol == Protocol::Finetune && v == Variant::Unconditional;
        let tag = match args.protocol {
            Protocol::Finetune => "ft",
            Protocol::Scratch => "scratch",
        };
        let dir = if drop_condition {
            model_dir.clone()
        } else {
            work.join(format!("{}-{tag}-{}steps", v.name(), args.train_steps))
        };
        if !drop_condition && Bundle::from_dir(&dir, &device).is_err() {
            println!(
                "training variant {} ({} steps, {tag})",
                v.name(),
                args.train_steps
            );
            train_default::run_with(
                TrainDefaultArgs {
                    out: dir.clone(),
                    variant: v,
                    method: base.config.method(),
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
                    work: Some(work.join(format!("ckpt-{}-{tag}-{}", v.name(), args.train_steps))),
                    encoders_from: Some(model_dir.clone()),
                    init_from: (args.protocol == Protocol::Finetune).then(|| model_dir.clone()),
                    images: train_images,
                    randomize_share: train_style.share,
                    wide_facades: (train_style.wide_facade_share > 0.0)
                        .then_some(train_style.wide_facade_share),
                    augment_encoders: false,
                    ground_prior: false,
                    sky_depth: false,
                    depth_features: depth_features
                        && veila_diffusion::app::BundleConfig::cpu_default(v)
                            .depth_encoder
                            .is_some(),
                    scenes: train_list.clone(),
                    encoder_scenes: None,
                    device: crate::device::DeviceArg::Cpu,
                },
                Some(&train_frames),
            )?;
        }
        let bundle = Bundle::from_dir(&dir, &device)?;
        let guidance = if bundle.is_conditional() && !drop_condition {
            base.config.sampler.guidance_scale
        } else {
            1.0
        };
        let sampler = sampler_for(&args.sampler, args.steps, guidance)?;
        let mut per_set: Vec<BTreeMap<String, BTreeMap<String, f64>>> = Vec::new();
        let mut secs = 0.0;
        for seed in 0..args.seeds {
            let (generated, s) = generate_all(
                &bundle,
                &tests,
                &sampler,
                drop_condition,
                1.0,
                seed,
                &format!("{} seed {seed}", v.name()),
            )?;
            secs += s;
            per_set.extend(per_fold(&bundle, &generated)?);
        }
        let r = row(
            "model",
            v.name(),
            v.label(),
            &dir.display().to_string(),
            &per_set,
            fold_size,
        );
        println!(
            "  {}: {:.2} s/scan",
            v.label(),
            secs / (args.seeds as f64 * tests.len() as f64)
        );
        results.push(VariantResult {
            train_steps: args.train_steps,
            seconds_per_scan: secs / (args.seeds as f64 * tests.len() as f64),
            ..r
        });
    }

    // sampler sweep on the bundled model
    let sweep_tests = &tests[..args.sweep_frames.min(tests.len())];
    let sweep_judges = make_judges(&base, sweep_tests, nets.as_ref(), &device)?;
    // (sampler, steps, residual weight, label): every sampler at every step count, then for a
    // residual bundle the texture's price in pixel error at the variants' step count
    let mut points: Vec<(&str, usize, f64, String)> = Vec::new();
    for name in ["ddpm", "ddim", "dpm"] {
        for &steps in &args.sweep_steps {
            points.push((name, steps, 1.0, format!("{name:>4} x {steps:>3}")));
        }
    }
    if base.config.residual.is_some() {
        for &weight in &args.sweep_residual_weights {
            points.push((
                args.sampler.as_str(),
                args.steps,
                weight,
                format!("residual weight {weight}"),
            ));
        }
    }
    let mut sweep = Vec::new();
    for (name, steps, weight, label) in points {
        let sampler = sampler_for(name, steps, base.config.sampler.guidance_scale)?;
        let (generated, secs) =
            generate_all(&base, sweep_tests, &sampler, false, weight, 0, &label)?;
        let m = seed_metrics(&base, &generated, sweep_tests, &sweep_judges, nets.as_ref())?;
        let p = SweepPoint {
            sampler: name.into(),
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

    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let real = if args.no_real {
        None
    } else {
        let sampler = sampler_for(
            &args.sampler,
            args.steps,
            base.config.sampler.guidance_scale,
        )?;
        let street_scan =
            crate::bench_real::reference_mean_scan(&base.config, baseline_train.len())?;
        Some(crate::bench_real::evaluate(
            &base,
            &crate::bench_real::RealOptions {
                sampler: &sampler,
                sampler_label: format!("{} {} steps", sampler.kind.title(), args.steps),
                seeds: args.real_seeds,
                mean_scan: &median,
                reference_mean_scan: street_scan.as_ref(),
            },
            &out,
        )?)
    };
    let report = Report {
        command: std::iter::once("cargo xtask".to_string())
            .chain(std::env::args().skip(1))
            .collect::<Vec<_>>()
            .join(" "),
        date_utc: veila_data::stamp::report_time(),
        machine: format!("{} CPU cores (CPU only)", std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)),
        test_split: test_list.display().to_string(),
        test_frames: tests.len(),
        folds: args.folds,
        baseline_frames: baseline_train.len(),
        seeds: args.seeds,
        train_steps: args.train_steps,
        train_frames: args.train_frames,
        protocol: args.protocol,
        sampler: args.sampler.clone(),
        sampler_steps: args.steps,
        quick: args.quick,
        shipped_only: args.shipped_only,
        variants: results,
        sweep,
        real,
        notes: vec![
            match args.protocol {
                Protocol::Finetune => format!("Protocol `finetune`: every variant starts from the bundled model's denoiser and is trained {} more steps with its switch flipped (weights that no longer fit are freshly initialised); `Veila` is the bundled model fine-tuned the same way (the control). The unconditional row is the bundled network's own unconditional branch (trained by 10% condition dropout), not a separately trained model.", args.train_steps),
                Protocol::Scratch => format!("Protocol `scratch`: every variant is trained from the same seeded initialisation for {} steps.", args.train_steps),
            },
            "All variants share the data, seed, step budget and the frozen encoders of the bundled model; differences smaller than the spread over seeds are not significant.".into(),
            "Reference scans are the true simulated scans projected onto the same range-image grid as the generated ones.".into(),
            "CM-DC: mean absolute relative difference between each generated point's camera depth and the bundled depth encoder's depth head where it projects. CM-SC: percentage of generated points whose class from the shipped range segmentation net (rangenet-small) agrees with the bundled semantic encoder's head where they project (unlabelled excluded). Both over the camera's field of view.".into(),
            "FRD / FPD use the shipped feature networks trained on simulator data (models/feature-nets), per region on the points of that region; with a dozen scans per side the covariances are rank-deficient, so read them as relative numbers between rows, not as converged distances or as comparable to published values.".into(),
        ],
    };
    write_report(&out, &report)?;
    println!(
        "wrote {} in {:.0} s",
        out.display(),
        t_all.elapsed().as_secs_f64()
    );
    Ok(())
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

fn write_report(out: &Path, r: &Report) -> Result<()> {
    use std::fmt::Write as _;
    let json = serde_json::to_string_pretty(r)?;
    veila_data::atomic::write_atomic(&out.join("report.json"), json.as_bytes())?;
    let mut md = String::new();
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
        SamplerConfig::named(&r.sampler, 1).map_or_else(|_| r.sampler.clone(), |s| s.kind.title()),
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
    if let Some(real) = &r.real {
        writeln!(md, "{}", crate::bench_real::markdown(real))?;
    }
    writeln!(md, "## Notes")?;
    writeln!(md)?;
    for n in &r.notes {
        writeln!(md, "- {n}")?;
    }
    veila_data::atomic::write_atomic(&out.join("report.md"), md.as_bytes())?;

    // plots
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
    .write_png(&out.join("variants.png"), 960, 480)?;
    let mut series = Vec::new();
    for name in ["ddpm", "ddim", "dpm"] {
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
    .write_png(&out.join("sampler_tradeoff.png"), 800, 500)?;
    Ok(())
}
