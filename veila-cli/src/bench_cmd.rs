//! `veila bench`: how fast the denoiser trains and samples on this machine's device.
//!
//! For each network (`bundled`: the bundle's denoiser config; `paper`: `DenoiserConfig::paper()`,
//! 64 x 1024 at the paper's widths) and each precision (`f32`; `bf16`: mixed precision, bf16
//! activations on f32 master weights, as `[train] precision = "bf16"` trains), with seeded random
//! weights, random encoder features of the right shapes and the GCMA geometry of a KITTI-like
//! camera:
//!
//! - one training update at `--batch` (the condition fusion, forward, MSE loss, backward, AdamW),
//!   its median time and training samples per second;
//! - one network evaluation for sampling at batch 2 (a classifier-free guidance pair), from which
//!   a sampler of N steps costs N evaluations per scan (`--sample-steps`);
//! - for `bundled`, also the real thing: `Bundle::generate` end to end (encoders, condition, the
//!   sampler) at each step count, f32, as `veila generate` runs it.
//!
//! Prints a table, and with `--json FILE` writes one JSON object. Times are medians after two
//! warm-up runs; the device is synchronised before every clock reading. A network that does not fit
//! the device's memory at `--batch` (the paper's at batch 8 on a 141 GB H200) is a result, not an
//! abort: its row says so and the other rows are still measured.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::{DType, Device, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
use clap::Args;
use rand::{Rng, SeedableRng};
use serde::Serialize;
use veila_diffusion::Precision;
use veila_diffusion::app::{CameraView, GenerateOptions};
use veila_geom::{EpipolarConfig, PinholeCamera};
use veila_nn::{ConditionInput, Cues, DenoiserConfig, GcmaGeometry};

use crate::model;

/// Arguments of `veila bench`.
#[derive(Debug, Args)]
pub(crate) struct BenchArgs {
    /// Networks to time: `bundled` (the bundle's denoiser, --checkpoint), `paper`
    /// (DenoiserConfig::paper(): 64 x 1024, the paper's widths; slow on a CPU).
    #[arg(long, value_delimiter = ',', default_value = "bundled,paper")]
    models: Vec<String>,
    /// Precisions of the training update: f32, bf16 (mixed precision; for GPUs).
    #[arg(long, value_delimiter = ',', default_value = "f32,bf16", value_parser = parse_precision)]
    precision: Vec<Precision>,
    /// Training batch size.
    #[arg(long, value_name = "B", default_value_t = 8)]
    batch: usize,
    /// Timed training updates (after 2 warm-up updates).
    #[arg(long, value_name = "N", default_value_t = 5)]
    train_runs: usize,
    /// Timed network evaluations for sampling (after 2 warm-up runs).
    #[arg(long, value_name = "N", default_value_t = 5)]
    forward_runs: usize,
    /// Sampler step counts to cost.
    #[arg(long, value_delimiter = ',', default_value = "16,32,64")]
    sample_steps: Vec<usize>,
    /// Skip `Bundle::generate` end to end (the bundled network's real sampling).
    #[arg(long)]
    no_generate: bool,
    /// Model bundle folder of `bundled` (default: $VEILA_MODEL, else the bundled models/default).
    #[arg(long, value_name = "DIR", env = "VEILA_MODEL")]
    checkpoint: Option<PathBuf>,
    /// Seed of the weights and inputs.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also write the results as one JSON object to this file.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Replace an existing --json file.
    #[arg(long)]
    force: bool,
}

fn parse_precision(s: &str) -> std::result::Result<Precision, String> {
    s.parse::<Precision>().map_err(|e| e.to_string())
}

/// One network at one precision.
#[derive(Debug, Serialize)]
struct Row {
    model: String,
    precision: &'static str,
    grid: [usize; 2],
    params: usize,
    batch: usize,
    /// Median of one training update (condition fusion, forward, loss, backward, AdamW).
    train_step_ms: f64,
    train_samples_per_s: f64,
    /// Median of one network evaluation at batch 2 (a guidance pair), condition prepared once.
    eval_b2_ms: f64,
    /// `steps -> seconds per scan` from `eval_b2_ms` (network evaluations only).
    sample_s_per_scan: Vec<(usize, f64)>,
}

/// `Bundle::generate` end to end at each step count (f32, one scan, the bundle's sampler kind).
#[derive(Debug, Serialize)]
struct GenerateRow {
    steps: usize,
    seconds_per_scan: f64,
}

/// A measurement the device's memory could not hold.
#[derive(Debug, Serialize)]
struct OutOfMemory {
    model: String,
    precision: &'static str,
    batch: usize,
    error: String,
}

#[derive(Debug, Serialize)]
struct Report {
    device: String,
    threads: usize,
    rows: Vec<Row>,
    /// Networks and precisions that ran out of device memory.
    out_of_memory: Vec<OutOfMemory>,
    generate: Vec<GenerateRow>,
}

/// Whether an error is the device running out of memory (candle's CUDA and CPU allocators word it
/// differently; both say "out of memory").
fn is_out_of_memory(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        let m = c.to_string().to_ascii_lowercase();
        m.contains("out_of_memory") || m.contains("out of memory")
    })
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// A KITTI-like front camera (KITTI object 000000's intrinsics, 1242 x 375) resized to `w x h`.
fn kitti_camera(w: usize, h: usize) -> Result<PinholeCamera> {
    let k = [
        [721.54, 0.0, 609.56, 44.86],
        [0.0, 721.54, 172.85, 0.22],
        [0.0, 0.0, 1.0, 0.003],
    ];
    // LiDAR x forward, y left, z up -> camera x right, y down, z forward, 8 cm behind, 27 cm below
    let cam_from_lidar = glam::Mat4::from_cols_array_2d(&[
        [0.0, 0.0, 1.0, 0.0],
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, -0.08, -0.27, 1.0],
    ]);
    let cam = PinholeCamera::new(k, cam_from_lidar, 1242, 375)
        .context("the benchmark's KITTI-like camera")?;
    cam.resized(w as u32, h as u32)
        .with_context(|| format!("resizing the benchmark's camera to {w} x {h}"))
}

fn rand_tensor(rng: &mut rand_chacha::ChaCha8Rng, shape: &[usize], dev: &Device) -> Result<Tensor> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect();
    Ok(Tensor::from_vec(v, shape, dev)?)
}

/// Random encoder features for `cfg` at batch `b`.
fn features(
    cfg: &DenoiserConfig,
    b: usize,
    rng: &mut rand_chacha::ChaCha8Rng,
    dev: &Device,
) -> Result<ConditionInput> {
    let Some(cc) = cfg.conditioning.as_ref() else {
        return Ok(ConditionInput::default());
    };
    let n = b * cc.num_views;
    let (mut sem, mut dep) = (Vec::new(), Vec::new());
    for i in 0..cc.num_scales() {
        let [h, w] = cc.feature_sizes[i];
        sem.push(rand_tensor(rng, &[n, cc.semantic_channels[i], h, w], dev)?);
        dep.push(rand_tensor(rng, &[n, cc.depth_channels[i], h, w], dev)?);
    }
    Ok(ConditionInput {
        semantic: (cc.cues != Cues::DepthOnly).then_some(sem),
        depth: (cc.cues != Cues::SemanticOnly).then_some(dep),
        keep: None,
    })
}

/// Times one network (`image_hw`: the encoders' input size its feature sizes come from).
fn bench_network(
    name: &str,
    cfg: &DenoiserConfig,
    image_hw: (usize, usize),
    args: &BenchArgs,
    dev: &Device,
) -> Result<(Vec<Row>, Vec<OutOfMemory>)> {
    let vm = VarMap::new();
    let net = veila_nn::Denoiser::new(
        cfg,
        veila_nn::seeded_var_builder(&vm, args.seed, DType::F32, dev),
    )
    .with_context(|| format!("building the {name} network"))?;
    let params: usize = vm.all_vars().iter().map(|v| v.elem_count()).sum();
    let geom = match cfg.conditioning.as_ref().and_then(|c| c.gcma.as_ref()) {
        Some(_) => {
            let views = cfg.conditioning.as_ref().map_or(1, |c| c.num_views);
            let cams = vec![kitti_camera(image_hw.1, image_hw.0)?; views];
            Some(GcmaGeometry::new(
                cfg,
                &cams,
                &EpipolarConfig::default(),
                dev,
            )?)
        }
        None => None,
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
    let (c, h, w) = (cfg.in_channels, cfg.height(), cfg.width());
    let b = args.batch;
    let x = rand_tensor(&mut rng, &[b, c, h, w], dev)?;
    let target = rand_tensor(&mut rng, &[b, cfg.out_channels, h, w], dev)?;
    let t = rand_tensor(&mut rng, &[b], dev)?.affine(0.45, 0.5)?;
    let cond = features(cfg, b, &mut rng, dev)?;
    let x2 = rand_tensor(&mut rng, &[2, c, h, w], dev)?;
    let t2 = Tensor::new(&[0.5f32, 0.5], dev)?;
    let cond2 = features(cfg, 2, &mut rng, dev)?;
    let conditional = cfg.conditioning.is_some();
    let mut rows = Vec::new();
    let mut oom = Vec::new();
    for &precision in &args.precision {
        let measured = (|| -> Result<Row> {
            let dt = precision.dtype();
            let mut opt = AdamW::new(
                vm.all_vars(),
                ParamsAdamW {
                    lr: 1e-5,
                    ..ParamsAdamW::default()
                },
            )?;
            let mut train = Vec::new();
            for i in 0..args.train_runs + 2 {
                dev.synchronize()?;
                let start = Instant::now();
                let prepared = conditional
                    .then(|| net.prepare_condition(&cond, geom.as_ref()))
                    .transpose()?;
                let y = net.forward(&x.to_dtype(dt)?, &t, prepared.as_ref())?;
                let loss = (y.to_dtype(DType::F32)? - &target)?.sqr()?.mean_all()?;
                let grads = loss.backward()?;
                opt.step(&grads)?;
                dev.synchronize()?;
                if i >= 2 {
                    train.push(start.elapsed().as_secs_f64());
                }
            }
            let prepared = conditional
                .then(|| net.prepare_condition(&cond2, geom.as_ref()))
                .transpose()?;
            let x2 = x2.to_dtype(dt)?;
            let mut eval = Vec::new();
            for i in 0..args.forward_runs + 2 {
                dev.synchronize()?;
                let start = Instant::now();
                let y = net.forward(&x2, &t2, prepared.as_ref())?.detach();
                dev.synchronize()?;
                drop(y);
                if i >= 2 {
                    eval.push(start.elapsed().as_secs_f64());
                }
            }
            let (train_s, eval_s) = (median(train), median(eval));
            Ok(Row {
                model: name.to_string(),
                precision: precision.name(),
                grid: [h, w],
                params,
                batch: b,
                train_step_ms: train_s * 1e3,
                train_samples_per_s: b as f64 / train_s,
                eval_b2_ms: eval_s * 1e3,
                sample_s_per_scan: args
                    .sample_steps
                    .iter()
                    .map(|&n| (n, n as f64 * eval_s))
                    .collect(),
            })
        })();
        match measured {
            Ok(row) => {
                eprintln!(
                    "{name} {}: training update {:.1} ms at batch {b}, evaluation {:.1} ms at batch 2",
                    row.precision, row.train_step_ms, row.eval_b2_ms
                );
                rows.push(row);
            }
            Err(e) if is_out_of_memory(&e) => {
                eprintln!(
                    "{name} {}: out of device memory at batch {b} (try a smaller --batch)",
                    precision.name()
                );
                oom.push(OutOfMemory {
                    model: name.to_string(),
                    precision: precision.name(),
                    batch: b,
                    // the message without the backtrace candle may attach
                    error: format!("{e:#}")
                        .lines()
                        .next()
                        .unwrap_or_default()
                        .to_string(),
                });
            }
            Err(e) => {
                return Err(e.context(format!("timing the {name} network in {}", precision.name())));
            }
        }
    }
    Ok((rows, oom))
}

/// `Bundle::generate` end to end at each step count.
fn bench_generate(
    bundle: &veila_diffusion::app::bundle::Bundle,
    args: &BenchArgs,
    dev: &Device,
) -> Result<Vec<GenerateRow>> {
    let (ih, iw) = (bundle.config.image_height, bundle.config.image_width);
    let cam = kitti_camera(iw, ih)?;
    let rgb: Vec<u8> = (0..ih * iw * 3)
        .map(|i| ((i * 7 + i / (iw * 3) * 13) % 256) as u8)
        .collect();
    let views = vec![
        CameraView {
            rgb: &rgb,
            camera: &cam,
        };
        bundle
            .config
            .denoiser
            .conditioning
            .as_ref()
            .map_or(1, |c| c.num_views)
    ];
    let mut out = Vec::new();
    for &steps in &args.sample_steps {
        let mut sampler = bundle.config.sampler.clone();
        sampler.steps = steps;
        let mut opts = GenerateOptions::new(sampler);
        opts.seed = args.seed;
        let mut times = Vec::new();
        for i in 0..3 {
            dev.synchronize()?;
            let start = Instant::now();
            bundle.generate(&views, &opts, |_, _| {})?;
            dev.synchronize()?;
            if i >= 1 {
                times.push(start.elapsed().as_secs_f64());
            }
        }
        out.push(GenerateRow {
            steps,
            seconds_per_scan: median(times),
        });
    }
    Ok(out)
}

pub(crate) fn run(args: BenchArgs) -> Result<()> {
    if args.batch == 0 || args.train_runs == 0 || args.forward_runs == 0 {
        bail!("--batch, --train-runs and --forward-runs must be at least 1");
    }
    if args.batch > 4096 || args.train_runs > 1000 || args.forward_runs > 1000 {
        bail!("--batch is at most 4096, --train-runs and --forward-runs at most 1000");
    }
    if args.sample_steps.iter().any(|&n| n == 0 || n > 10_000) {
        bail!("--sample-steps must be in 1..=10000");
    }
    for m in &args.models {
        if m != "bundled" && m != "paper" {
            bail!("--models: unknown network `{m}` (bundled, paper)");
        }
    }
    let mut inputs = crate::staging::Inputs::new();
    inputs.add_opt(args.checkpoint.as_ref());
    if let Some(path) = &args.json {
        // refuse the output before the minutes of timing
        crate::staging::check_outputs(&[path.as_path()], &inputs, args.force, false)?;
    }
    let dev = model::device()?;
    if args.precision.contains(&Precision::Bf16) && dev.is_cpu() {
        eprintln!(
            "note: bf16 on the CPU runs candle's reference ops and widens its matrix products to \
             f32, so it is slower than f32 here; it is meant for GPUs (--device cuda)"
        );
    }
    let mut report = Report {
        device: format!("{dev:?}"),
        threads: rayon::current_num_threads(),
        rows: Vec::new(),
        out_of_memory: Vec::new(),
        generate: Vec::new(),
    };
    for m in &args.models {
        if m == "bundled" {
            let bundle = model::load_bundle(args.checkpoint.as_deref(), &dev)?;
            let hw = (bundle.config.image_height, bundle.config.image_width);
            let (rows, oom) = bench_network("bundled", &bundle.config.denoiser, hw, &args, &dev)?;
            report.rows.extend(rows);
            report.out_of_memory.extend(oom);
            if !args.no_generate {
                report.generate = bench_generate(&bundle, &args, &dev)?;
            }
        } else {
            let (rows, oom) =
                bench_network("paper", &DenoiserConfig::paper(), (384, 1248), &args, &dev)?;
            report.rows.extend(rows);
            report.out_of_memory.extend(oom);
        }
    }
    println!(
        "veila bench on {} ({} threads), medians:",
        report.device, report.threads
    );
    println!(
        "| network | grid | params | precision | training update, batch {} (ms) | samples / s | evaluation, batch 2 (ms) | {} |",
        args.batch,
        args.sample_steps
            .iter()
            .map(|n| format!("s / scan, {n} steps"))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    for r in &report.rows {
        println!(
            "| {} | {} x {} | {} | {} | {:.1} | {:.3} | {:.1} | {} |",
            r.model,
            r.grid[0],
            r.grid[1],
            r.params,
            r.precision,
            r.train_step_ms,
            r.train_samples_per_s,
            r.eval_b2_ms,
            r.sample_s_per_scan
                .iter()
                .map(|(_, s)| format!("{s:.3}"))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    }
    for o in &report.out_of_memory {
        println!(
            "| {} | | | {} | out of device memory at batch {} | | | |",
            o.model, o.precision, o.batch
        );
    }
    if !report.generate.is_empty() {
        println!("bundled model end to end (Bundle::generate, f32, one scan):");
        for g in &report.generate {
            println!("  {} steps: {:.3} s", g.steps, g.seconds_per_scan);
        }
    }
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&report)?;
        crate::staging::publish_files(
            &[(path.clone(), text.into_bytes())],
            &inputs,
            args.force,
            false,
        )?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn out_of_memory_is_told_from_other_errors_through_contexts() {
        // the words of candle's CUDA backend on an H200 (2026-11-26) and of a host allocator
        let cuda = anyhow::anyhow!("DriverError(CUDA_ERROR_OUT_OF_MEMORY, \"out of memory\")");
        assert!(is_out_of_memory(&cuda.context("timing the paper network")));
        assert!(is_out_of_memory(&anyhow::anyhow!(
            "memory allocation of 4096 bytes failed: Out of memory"
        )));
        assert!(!is_out_of_memory(&anyhow::anyhow!(
            "shape mismatch in conv2d, lhs: [8, 3, 64, 1024], rhs: [16, 4, 3, 3]"
        )));
        assert!(!is_out_of_memory(
            &anyhow::anyhow!("no such GPU").context("--device cuda:3")
        ));
    }
}
