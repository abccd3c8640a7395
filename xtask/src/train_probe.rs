//! `cargo xtask train-probe`: how far a `train-default` run has come, scored against the zero-skill
//! baselines on held-out frames, from its newest checkpoints (the run itself is not touched, so
//! this can run beside it).
//!
//! The mean network of a residual run is scored alone (what 0 sampler steps give). Once the
//! denoiser has a checkpoint, its samples are scored too; its residual scale is then re-estimated
//! from the baseline frames (the finished run computes it on all its training frames), so the
//! samples are close to, not identical with, the finished bundle's. Every probe appends one line
//! to `probe.jsonl` in the work folder: quality against the run's own training clock.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::{DType, Device, Tensor};
use clap::Args;
use veila_diffusion::app::bundle::{
    Bundle, BundleConfig, DENOISER_FILE, DEPTH_FILE, MEAN_FILE, Method, SEMANTIC_FILE, Variant,
};
use veila_diffusion::app::{
    CameraView, GenerateOptions, Stage, TrainExample, predict_means, residual_scale, stage_config,
};
use veila_diffusion::trainer::{CheckpointState, find_latest_checkpoint};
use veila_geom::{RangeImage, Region};
use veila_nn::encoders::kind::AnyEncoder;
use veila_nn::encoders::small_cnn::SmallCnn;

use crate::simdata::{SimExample, mean_std, render_split, workspace_root};

/// Arguments of `cargo xtask train-probe`.
#[derive(Debug, Args)]
pub struct TrainProbeArgs {
    /// The run's work folder (its `run.json`, checkpoints and encoders).
    #[arg(long, default_value = "runs/default-residual")]
    work: PathBuf,
    /// The run's variant.
    #[arg(long, default_value = "full")]
    variant: Variant,
    /// The run's method.
    #[arg(long, default_value = "residual")]
    method: Method,
    /// Held-out test frames, interleaving the scene files of the held-out list (`--test-scenes`).
    #[arg(long, default_value_t = 24)]
    test_frames: usize,
    /// The held-out list the test frames come from [default: the one beside the run's training
    /// list: `scenes/test.txt` for `scenes/train.txt`, `test-v5.txt` for `train-v5.txt`].
    #[arg(long)]
    test_scenes: Option<PathBuf>,
    /// Split the probed frames come from: `test` (held out) or `train` (the first frames of the
    /// training split, which a run of at least that many frames has trained on: the gap between the
    /// two is the generalisation gap).
    #[arg(long, default_value = "test")]
    split: ProbeSplit,
    /// Training frames behind the baselines (median scan, retrieval) and the residual scale.
    #[arg(long, default_value_t = 96)]
    baseline_frames: usize,
    /// Sampler steps for the denoiser's samples.
    #[arg(long, default_value_t = 16)]
    steps: usize,
    /// Residual weights of the samples (0 = the mean network alone, 1 = a full sample); each
    /// other than 1 adds a `model_w<weight>` entry.
    #[arg(long, value_delimiter = ',', default_value = "1")]
    residual_weights: Vec<f64>,
    /// Seed of the samples.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also write the probed state as a bundle here (for `veila demo --model`). Before the
    /// denoiser has a checkpoint its denoiser is untrained and the bundle's sampler defaults to
    /// 0 steps: the mean network alone.
    #[arg(long)]
    bundle_out: Option<PathBuf>,
}

/// Where `train-probe`'s frames come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum ProbeSplit {
    /// The held-out test split.
    Test,
    /// The training split (frames the run trained on).
    Train,
}

/// Front and rear range MAE and ring spread of `scans` against the test frames.
fn score(
    name: &str,
    scans: &[RangeImage],
    tests: &[SimExample],
    cfg: &BundleConfig,
) -> serde_json::Value {
    let sensor = &cfg.denoiser.sensor;
    let mae = |region: Region| -> Vec<f64> {
        scans
            .iter()
            .zip(tests)
            .filter_map(|(g, t)| veila_metrics::range::range_mae(g, &t.range, region))
            .collect()
    };
    let (front, front_sd) = mean_std(&mae(Region::Front));
    let (rear, rear_sd) = mean_std(&mae(Region::Rear));
    let rings: Vec<f64> = scans
        .iter()
        .filter_map(|s| veila_metrics::baseline::ring_spread(s, sensor, -15.0, 0.5))
        .collect();
    let (ring, _) = mean_std(&rings);
    println!(
        "  {name:<34} {front:>6.2} ± {front_sd:<5.2} {rear:>6.2} ± {rear_sd:<5.2} {ring:>8.3}"
    );
    serde_json::json!({
        "range_mae_front_m": front, "range_mae_front_std_m": front_sd,
        "range_mae_rear_m": rear, "range_mae_rear_std_m": rear_sd,
        "ring_spread_m": ring,
    })
}

/// The path of the first place where two JSON values differ (numbers compared as f32, the
/// precision of the configs).
fn first_difference(a: &serde_json::Value, b: &serde_json::Value, path: &str) -> Option<String> {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            x.keys()
                .chain(y.keys())
                .find_map(|k| match (x.get(k), y.get(k)) {
                    (Some(u), Some(v)) => first_difference(u, v, &format!("{path}.{k}")),
                    _ => Some(format!("{path}.{k}")),
                })
        }
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => x
            .iter()
            .zip(y)
            .enumerate()
            .find_map(|(i, (u, v))| first_difference(u, v, &format!("{path}[{i}]"))),
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64()? as f32, y.as_f64()? as f32);
            (x != y).then(|| format!("{path} ({x} vs {y})"))
        }
        _ => (a != b).then(|| path.to_string()),
    }
}

fn load_tensors(path: &Path) -> Result<HashMap<String, Tensor>> {
    candle_core::safetensors::load(path, &Device::Cpu)
        .with_context(|| format!("reading {}", path.display()))
}

/// The newest checkpoint in `dir` (if any): its EMA weights and its state.
fn newest(dir: &Path) -> Result<Option<(HashMap<String, Tensor>, CheckpointState)>> {
    let Some(p) = find_latest_checkpoint(dir)? else {
        return Ok(None);
    };
    let state: CheckpointState = serde_json::from_slice(
        &std::fs::read(p.join("state.json")).with_context(|| format!("reading {}", p.display()))?,
    )
    .with_context(|| format!("parsing {}/state.json", p.display()))?;
    Ok(Some((load_tensors(&p.join("ema.safetensors"))?, state)))
}

pub fn run(args: TrainProbeArgs) -> Result<()> {
    let t_all = Instant::now();
    let device = Device::Cpu;
    let root = workspace_root();
    let work = if args.work.is_absolute() {
        args.work.clone()
    } else {
        root.join(&args.work)
    };
    let mut cfg = BundleConfig::cpu_default(args.variant).with_method(args.method);
    // the run must be the one this config describes
    let run_path = work.join("run.json");
    let run: serde_json::Value = serde_json::from_slice(
        &std::fs::read(&run_path).with_context(|| format!("reading {}", run_path.display()))?,
    )
    .with_context(|| format!("parsing {}", run_path.display()))?;
    for (key, ours) in [
        ("denoiser", serde_json::to_value(&cfg.denoiser)?),
        ("diffusion", serde_json::to_value(&cfg.diffusion)?),
    ] {
        if let Some(at) = first_difference(&run[key], &ours, key) {
            bail!(
                "{} is not a {} / {} run of this build's configuration (it differs at {at})",
                run_path.display(),
                args.variant.name(),
                args.method.name()
            );
        }
    }
    // the encoders the run trained (its encoders-* folder), or the bundle it took them from
    // (`train-default --encoders-from`, recorded in run.json)
    let enc_dir = match std::fs::read_dir(&work)
        .with_context(|| format!("listing {}", work.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("encoders-"))
        }) {
        Some(dir) => dir,
        None => match run.get("encoders_from").and_then(|v| v.as_str()) {
            Some(from) => root.join(from),
            None => bail!(
                "no encoders-* folder in {}, and its run.json names no --encoders-from bundle",
                work.display()
            ),
        },
    };
    // the run's training list (run.json records it when it is not the shipped one), and the
    // held-out list beside it
    let train_list = PathBuf::from(
        run.get("scenes")
            .and_then(|v| v.as_str())
            .unwrap_or(crate::simdata::DEFAULT_SCENES),
    );
    let mut files: HashMap<&str, HashMap<String, Tensor>> = HashMap::new();
    let mut encoder =
        |file: &'static str, c: &Option<veila_diffusion::app::bundle::EncoderSpec>| {
            c.as_ref()
                .map(|spec| -> Result<AnyEncoder> {
                    let c = spec
                        .small_cnn_config()
                        .context("train-probe reads small-CNN encoders only")?;
                    let w = load_tensors(&enc_dir.join(file))?;
                    files.insert(file, w.clone());
                    Ok(SmallCnn::new(
                        c,
                        candle_nn::VarBuilder::from_tensors(w, DType::F32, &device),
                    )?
                    .into())
                })
                .transpose()
        };
    let semantic = encoder(SEMANTIC_FILE, &cfg.semantic_encoder)?;
    let depth = encoder(DEPTH_FILE, &cfg.depth_encoder)?;

    let mean_ckpt = if cfg.residual.is_some() {
        newest(&work.join("mean"))?
    } else {
        None
    };
    let den_ckpt = newest(&work)?;
    if mean_ckpt.is_none() && den_ckpt.is_none() {
        bail!("no checkpoint in {} yet", work.display());
    }
    let test_list = match args.split {
        ProbeSplit::Test => args
            .test_scenes
            .clone()
            .unwrap_or_else(|| crate::simdata::test_list_for(&train_list)),
        ProbeSplit::Train => train_list.clone(),
    };
    let tests = render_split(
        &root.join(&test_list),
        args.test_frames,
        &cfg,
        "simulating test frames",
    )?;
    let train = render_split(
        &root.join(&train_list),
        args.baseline_frames,
        &cfg,
        "simulating baseline train frames",
    )?;
    let den_cfg = stage_config(&cfg, Stage::Denoiser)?.0;
    let mean_cfg = cfg
        .residual
        .as_ref()
        .map(|_| stage_config(&cfg, Stage::Mean).map(|c| c.0))
        .transpose()?;
    let net = |w: &HashMap<String, Tensor>, stage: Stage| -> Result<veila_nn::Denoiser> {
        let c = match stage {
            Stage::Denoiser => &den_cfg,
            Stage::Mean => mean_cfg.as_ref().context("not a residual run")?,
        };
        Ok(veila_nn::Denoiser::new(
            c,
            candle_nn::VarBuilder::from_tensors(w.clone(), DType::F32, &device),
        )?)
    };
    // the denoiser of a mean-only probe is never run (0 steps): its seeded initialisation
    // stands in for it
    let denoiser_trained = den_ckpt.is_some() && (cfg.residual.is_none() || mean_ckpt.is_some());
    let den_w = match &den_ckpt {
        Some((w, _)) if denoiser_trained => w.clone(),
        _ => {
            let vm = candle_nn::VarMap::new();
            veila_nn::Denoiser::new(
                &den_cfg,
                veila_nn::seeded_var_builder(&vm, args.seed, DType::F32, &device),
            )?;
            veila_diffusion::app::varmap_tensors(&vm)?
        }
    };
    let den_net = net(&den_w, Stage::Denoiser)?;
    if let (Some((mw, _)), Some(_)) = (&mean_ckpt, &den_ckpt) {
        let examples: Vec<TrainExample> = train
            .iter()
            .map(|e| e.train_example(&cfg))
            .collect::<Result<_>>()?;
        let means = predict_means(
            &cfg,
            semantic.as_ref(),
            depth.as_ref(),
            mw,
            &examples,
            16,
            &device,
        )?;
        let x0: Vec<Vec<f32>> = examples.iter().map(|e| e.x0.clone()).collect();
        let hw = cfg.denoiser.height() * cfg.denoiser.width();
        let scale = residual_scale(&cfg.encoding, &x0, &means, hw);
        if let Some(r) = cfg.residual.as_mut() {
            r.scale = scale;
        }
    }
    let mean = match &mean_ckpt {
        Some((w, _)) => Some((net(w, Stage::Mean)?, w.clone())),
        None => None,
    };
    let bundle = Bundle {
        config: cfg.clone(),
        semantic,
        depth,
        denoiser: den_net,
        weights: den_w.clone(),
        mean,
        origin: work.clone(),
    };
    let generate = |steps: usize, residual_weight: f64| -> Result<Vec<RangeImage>> {
        tests
            .iter()
            .enumerate()
            .map(|(i, ex)| {
                let mut scans = bundle.generate(
                    &[CameraView {
                        rgb: &ex.rgb,
                        camera: &ex.camera,
                    }],
                    &GenerateOptions {
                        sampler: veila_diffusion::SamplerConfig {
                            steps,
                            ..cfg.sampler.clone()
                        },
                        samples: 1,
                        seed: args.seed.wrapping_add(i as u64),
                        unconditional: false,
                        residual_weight,
                    },
                    |_, _| {},
                )?;
                Ok(scans.swap_remove(0))
            })
            .collect()
    };
    let clock = |s: &CheckpointState| {
        serde_json::json!({"step": s.step, "train_seconds": s.train_seconds.round(),
            "clock_from_step": s.clock_from_step})
    };
    println!(
        "train-probe of {}: {} test frames, baselines from {} train frames",
        work.display(),
        tests.len(),
        train.len()
    );
    println!(
        "  {:<34} {:>14} {:>14} {:>8}",
        "", "front MAE (m)", "rear MAE (m)", "ring (m)"
    );
    let mut line = serde_json::json!({
        "test_frames": tests.len(),
        "split": format!("{:?}", args.split).to_lowercase(),
        "test_scenes": test_list.display().to_string(),
        "train_scenes": train_list.display().to_string(),
        "baseline_frames": train.len(),
        "mean": mean_ckpt.as_ref().map(|(_, s)| clock(s)),
        "denoiser": den_ckpt.as_ref().map(|(_, s)| clock(s)),
    });
    let truth: Vec<RangeImage> = tests.iter().map(|t| t.range.clone()).collect();
    line["true"] = score("true scan", &truth, &tests, &cfg);
    let refs: Vec<&RangeImage> = train.iter().map(|e| &e.range).collect();
    let median = veila_metrics::baseline::median_scan(&refs)?;
    line["mean_scan"] = score(
        "mean scan (baseline)",
        &vec![median; tests.len()],
        &tests,
        &cfg,
    );
    let retrieved = crate::simdata::retrieval_baseline(&bundle, &train, &tests)?;
    line["retrieval"] = score("retrieval (baseline)", &retrieved, &tests, &cfg);
    if let Some((_, s)) = &mean_ckpt {
        let t = Instant::now();
        let scans = generate(0, 1.0)?;
        let name = format!("mean network, step {}", s.step);
        line["mean_net"] = score(&name, &scans, &tests, &cfg);
        line["mean_net"]["seconds_per_scan"] =
            (t.elapsed().as_secs_f64() / tests.len().max(1) as f64).into();
    }
    if let Some((_, s)) = &den_ckpt
        && denoiser_trained
    {
        for &w in &args.residual_weights {
            let t = Instant::now();
            let scans = generate(args.steps, w)?;
            let (name, key) = if w == 1.0 {
                (
                    format!("model, step {}, {} steps", s.step, args.steps),
                    "model".to_string(),
                )
            } else {
                (
                    format!("model, step {}, {} steps, w {w}", s.step, args.steps),
                    format!("model_w{w}"),
                )
            };
            line[&key] = score(&name, &scans, &tests, &cfg);
            line[&key]["seconds_per_scan"] =
                (t.elapsed().as_secs_f64() / tests.len().max(1) as f64).into();
        }
    }
    if let Some(out) = &args.bundle_out {
        let mut config = cfg.clone();
        if !denoiser_trained {
            config.sampler.steps = 0;
        }
        config.provenance = serde_json::json!({
            "trained_by": "cargo xtask train-probe (an unfinished run)",
            "work": work.display().to_string(),
            "train_split": train_list.display().to_string(),
            "probe": line.clone(),
            "denoiser": if denoiser_trained { "the newest checkpoint's EMA weights" }
                else { "untrained (the mean network alone: 0 sampler steps)" },
        });
        files.insert(DENOISER_FILE, den_w.clone());
        if let Some((w, _)) = &mean_ckpt {
            files.insert(MEAN_FILE, w.clone());
        }
        Bundle::save(out, &config, &files)?;
        Bundle::from_dir(out, &device).with_context(|| format!("re-reading {}", out.display()))?;
        println!("wrote the probed bundle to {}", out.display());
    }
    let log = work.join("probe.jsonl");
    let mut text = std::fs::read_to_string(&log).unwrap_or_default();
    text.push_str(&serde_json::to_string(&line)?);
    text.push('\n');
    veila_data::atomic::write_atomic(&log, text.as_bytes())?;
    println!(
        "appended to {} ({:.0} s)",
        log.display(),
        t_all.elapsed().as_secs_f64()
    );
    Ok(())
}
