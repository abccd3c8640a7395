//! `cargo xtask bench-model`: the CPU engine's speed on the denoiser the project trains and samples.
//!
//! Times, for `DenoiserConfig::small()` as of issue 19 (unconditional, 32 x 256, f32, seeded random
//! weights, all cores): the forward pass at batch 1 and batch 8 and one training step at batch 8
//! (forward, MSE loss, backward, AdamW). The configuration is frozen in `bench_model_small.json` so the
//! figures stay comparable when the bundled default changes; `xtask/scripts/torch_yardstick.py` times
//! the same network in PyTorch. Prints the medians as one JSON object on stdout, and the CPU time over
//! wall time of the training steps (2.0 = both cores busy on this machine).

use std::time::Instant;

use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
use clap::Args;
use serde::Serialize;
use veila_nn::{Denoiser, DenoiserConfig, seeded_var_builder};

/// `DenoiserConfig::small().unconditional()` as it was when this benchmark was written.
const BENCH_CONFIG: &str = include_str!("bench_model_small.json");

/// Arguments of `cargo xtask bench-model`.
#[derive(Debug, Args)]
pub struct BenchModelArgs {
    /// Print only the JSON object (on stdout), without the human-readable lines on stderr.
    #[arg(long)]
    json: bool,
    /// Timed repetitions of each forward measurement (after 2 warm-up runs).
    #[arg(long, default_value_t = 15)]
    forward_runs: usize,
    /// Timed training steps (after 2 warm-up steps).
    #[arg(long, default_value_t = 11)]
    train_runs: usize,
    /// Seed of the weights and inputs.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also write the network and a reference output for `xtask/scripts/torch_yardstick.py` here:
    /// `config.json`, `weights.safetensors` and `reference.safetensors` (`x`, `t`, `y`, `ray_features`).
    #[arg(long)]
    export: Option<std::path::PathBuf>,
    /// Where the network runs: `cpu` (the benchmark's machine of record), `cuda` or `cuda:N`
    /// (needs `cargo xtask build-cuda --xtask`); the clock waits for the device at every reading.
    #[arg(long, default_value = "cpu", value_parser = crate::device::parse_device)]
    device: crate::device::DeviceArg,
}

/// What `bench-model --json` prints.
#[derive(Debug, Serialize)]
struct BenchModelReport {
    forward_b1_ms: f64,
    forward_b8_ms: f64,
    train_b8_ms: f64,
    /// The training step's three phases (medians, so they need not add up to `train_b8_ms`):
    /// forward with gradient tracking and the loss, backward, AdamW.
    train_b8_forward_ms: f64,
    train_b8_backward_ms: f64,
    train_b8_optimizer_ms: f64,
    /// Process CPU time over wall time during the timed training steps.
    train_cpu_over_wall: Option<f64>,
    /// Batch-8 forward per sample over batch-1 forward (<= 1: batching helps).
    forward_b8_per_sample_over_b1: f64,
    /// Output of the batch-1 forward at the fixed input: mean and RMS (a check that nothing changed).
    forward_b1_mean: f64,
    forward_b1_rms: f64,
    threads: usize,
    params: usize,
    device: String,
}

/// The frozen benchmark configuration.
pub fn bench_config() -> Result<DenoiserConfig> {
    serde_json::from_str(BENCH_CONFIG).context("parsing bench_model_small.json")
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// User + system CPU time of this process in seconds (Linux `/proc/self/stat`, 100 ticks per second).
fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // fields after the parenthesised command name; utime and stime are fields 14 and 15 (1-based)
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ut: f64 = f.get(11)?.parse().ok()?;
    let st: f64 = f.get(12)?.parse().ok()?;
    Some((ut + st) / 100.0)
}

/// A seeded `[B, C, H, W]` standard-normal input and `[B]` times in `(0, 1)`.
fn inputs(cfg: &DenoiserConfig, b: usize, seed: u64, dev: &Device) -> Result<(Tensor, Tensor)> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let n = b * cfg.in_channels * cfg.height() * cfg.width();
    // Box-Muller keeps this free of extra dependencies
    let x: Vec<f32> = (0..n)
        .map(|_| {
            let (u1, u2): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random());
            ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
        })
        .collect();
    let t: Vec<f32> = (0..b).map(|_| rng.random_range(0.02f32..0.98)).collect();
    Ok((
        Tensor::from_vec(x, (b, cfg.in_channels, cfg.height(), cfg.width()), dev)?,
        Tensor::from_vec(t, b, dev)?,
    ))
}

fn time_forward(net: &Denoiser, x: &Tensor, t: &Tensor, runs: usize) -> Result<f64> {
    let mut times = Vec::with_capacity(runs);
    for i in 0..runs + 2 {
        x.device().synchronize()?;
        let start = Instant::now();
        let y = net.forward(x, t, None)?;
        // the work is done when the device says so (the CPU backend is synchronous)
        y.device().synchronize()?;
        if i >= 2 {
            times.push(start.elapsed().as_secs_f64() * 1e3);
        }
    }
    Ok(median(times))
}

/// Runs the benchmark.
pub fn run(args: BenchModelArgs) -> Result<()> {
    let dev: Device = args.device.open()?;
    let cfg = bench_config()?;
    let varmap = VarMap::new();
    let net = Denoiser::new(
        &cfg,
        seeded_var_builder(&varmap, args.seed, DType::F32, &dev),
    )?;
    let params: usize = varmap.all_vars().iter().map(|v| v.elem_count()).sum();
    let runs = args.forward_runs.max(1);
    let (x1, t1) = inputs(&cfg, 1, args.seed, &dev)?;
    let (x8, t8) = inputs(&cfg, 8, args.seed + 1, &dev)?;
    let y1 = net.forward(&x1, &t1, None)?;
    let forward_b1_mean = f64::from(y1.mean_all()?.to_scalar::<f32>()?);
    let forward_b1_rms = f64::from(y1.sqr()?.mean_all()?.sqrt()?.to_scalar::<f32>()?);
    if let Some(dir) = &args.export {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        std::fs::write(dir.join("config.json"), serde_json::to_string_pretty(&cfg)?)?;
        varmap
            .save(dir.join("weights.safetensors"))
            .with_context(|| format!("writing {}", dir.join("weights.safetensors").display()))?;
        let mut reference = std::collections::HashMap::new();
        reference.insert("x".to_string(), x1.clone());
        reference.insert("t".to_string(), t1.clone());
        reference.insert("y".to_string(), y1.clone());
        if let Some(rf) = net.ray_features() {
            reference.insert("ray_features".to_string(), rf.clone());
        }
        candle_core::safetensors::save(&reference, dir.join("reference.safetensors"))?;
        eprintln!("wrote the yardstick inputs to {}", dir.display());
    }
    let forward_b1_ms = time_forward(&net, &x1, &t1, runs)?;
    let forward_b8_ms = time_forward(&net, &x8, &t8, runs)?;

    let mut opt = AdamW::new(
        varmap.all_vars(),
        ParamsAdamW {
            lr: 1e-4,
            ..Default::default()
        },
    )?;
    let noise = inputs(&cfg, 8, args.seed + 2, &dev)?.0;
    // one step, timed by phase: [forward + loss, backward, optimizer] in ms
    let mut step = || -> Result<[f64; 3]> {
        dev.synchronize()?;
        let t0 = Instant::now();
        let pred = net.forward(&x8, &t8, None)?;
        let loss = (pred - &noise)?.sqr()?.mean_all()?;
        dev.synchronize()?;
        let t1 = Instant::now();
        let grads = loss.backward()?;
        dev.synchronize()?;
        let t2 = Instant::now();
        opt.step(&grads)?;
        dev.synchronize()?;
        let t3 = Instant::now();
        let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
        Ok([ms(t0, t1), ms(t1, t2), ms(t2, t3)])
    };
    step()?;
    step()?;
    let train_runs = args.train_runs.max(1);
    let mut times = Vec::with_capacity(train_runs);
    let mut phases: [Vec<f64>; 3] = Default::default();
    let cpu0 = process_cpu_s();
    let wall0 = Instant::now();
    for _ in 0..train_runs {
        let start = Instant::now();
        let p = step()?;
        times.push(start.elapsed().as_secs_f64() * 1e3);
        for (all, t) in phases.iter_mut().zip(p) {
            all.push(t);
        }
    }
    let [
        train_b8_forward_ms,
        train_b8_backward_ms,
        train_b8_optimizer_ms,
    ] = phases.map(median);
    let wall = wall0.elapsed().as_secs_f64();
    let train_cpu_over_wall = match (cpu0, process_cpu_s()) {
        (Some(a), Some(b)) if wall > 0.0 => Some((b - a) / wall),
        _ => None,
    };
    let train_b8_ms = median(times);
    let report = BenchModelReport {
        forward_b1_ms,
        forward_b8_ms,
        train_b8_ms,
        train_b8_forward_ms,
        train_b8_backward_ms,
        train_b8_optimizer_ms,
        train_cpu_over_wall,
        forward_b8_per_sample_over_b1: forward_b8_ms / 8.0 / forward_b1_ms,
        forward_b1_mean,
        forward_b1_rms,
        threads: rayon::current_num_threads(),
        params,
        device: args.device.name(),
    };
    if !args.json {
        eprintln!(
            "DenoiserConfig::small() unconditional {}x{}, f32, {} params, {} threads, on {}",
            cfg.height(),
            cfg.width(),
            params,
            report.threads,
            report.device
        );
        eprintln!("forward b1   {forward_b1_ms:8.1} ms (median of {runs})");
        eprintln!(
            "forward b8   {forward_b8_ms:8.1} ms (median of {runs}; {:.2}x batch 1 per sample)",
            report.forward_b8_per_sample_over_b1
        );
        eprintln!(
            "train b8     {train_b8_ms:8.1} ms (median of {train_runs}; forward + backward + AdamW)"
        );
        eprintln!(
            "  phases     {train_b8_forward_ms:.1} ms forward + loss, {train_b8_backward_ms:.1} ms backward, {train_b8_optimizer_ms:.1} ms AdamW (medians)"
        );
        if let Some(r) = train_cpu_over_wall {
            eprintln!("train CPU time / wall time {r:.2}");
        }
    }
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frozen_config_is_the_small_unconditional_model() {
        let cfg = bench_config().unwrap();
        assert_eq!((cfg.height(), cfg.width()), (32, 256));
        assert!(cfg.conditioning.is_none());
        assert_eq!(cfg.base_channels, 16);
        cfg.validate().unwrap();
    }
}
