//! The engine's speed on one denoiser ([`measure`], `cargo xtask bench-model`): the forward pass
//! at batch 1 and batch 8 and one training step at batch 8 (forward and MSE loss, backward, AdamW),
//! on seeded weights and inputs, each the median of timed runs after two warm-up runs, the device
//! synchronised at every reading. Optionally the network is exported first for the PyTorch
//! yardstick ([`crate::export::write_export`]).

use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
use serde::Serialize;

use crate::export::{reference_tensors, seeded_inputs, write_export};
use crate::{Denoiser, DenoiserConfig, Result, seeded_var_builder};

/// What [`measure`] found (`bench-model --json` prints it).
#[derive(Debug, Clone, Serialize)]
pub struct SpeedReport {
    /// Forward pass at batch 1 (median, ms).
    pub forward_b1_ms: f64,
    /// Forward pass at batch 8 (median, ms).
    pub forward_b8_ms: f64,
    /// A training step at batch 8 (median, ms).
    pub train_b8_ms: f64,
    /// The training step's three phases (medians, so they need not add up to `train_b8_ms`):
    /// forward with gradient tracking and the loss, backward, AdamW.
    pub train_b8_forward_ms: f64,
    /// Backward (median, ms).
    pub train_b8_backward_ms: f64,
    /// AdamW (median, ms).
    pub train_b8_optimizer_ms: f64,
    /// Process CPU time over wall time during the timed training steps.
    pub train_cpu_over_wall: Option<f64>,
    /// Batch-8 forward per sample over batch-1 forward (<= 1: batching helps).
    pub forward_b8_per_sample_over_b1: f64,
    /// Output of the batch-1 forward at the fixed input: mean and RMS (a check that nothing changed).
    pub forward_b1_mean: f64,
    /// RMS of that output.
    pub forward_b1_rms: f64,
    /// Rayon's threads.
    pub threads: usize,
    /// Parameters of the network.
    pub params: usize,
    /// Where it ran (`cpu`, `cuda:0`).
    pub device: String,
}

/// How [`measure`] runs.
#[derive(Debug, Clone, Copy)]
pub struct SpeedOptions<'a> {
    /// Timed forward passes of each batch (at least 1).
    pub forward_runs: usize,
    /// Timed training steps (at least 1).
    pub train_runs: usize,
    /// Seed of the weights and inputs.
    pub seed: u64,
    /// Where the network runs, and its name in the report.
    pub device: (&'a Device, &'a str),
    /// Also write the network and its batch-1 reference output here (`config.json`,
    /// `weights.safetensors`, `reference.safetensors`).
    pub export: Option<&'a Path>,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Milliseconds since `a` at `b`.
fn ms(a: Instant, b: Instant) -> f64 {
    (b - a).as_secs_f64() * 1e3
}

/// The median of `runs` forward passes of `net` on `(x, t)`, after two warm-up passes.
fn time_forward(net: &Denoiser, x: &Tensor, t: &Tensor, runs: usize) -> Result<f64> {
    let mut times = Vec::with_capacity(runs);
    for i in 0..runs + 2 {
        x.device().synchronize()?;
        let start = Instant::now();
        let y = net.forward(x, t, None)?;
        // the work is done when the device says so (the CPU backend is synchronous)
        y.device().synchronize()?;
        if i >= 2 {
            times.push(ms(start, Instant::now()));
        }
    }
    Ok(median(times))
}

/// Times the denoiser of `cfg` with seeded weights as [`SpeedOptions`] say.
pub fn measure(cfg: &DenoiserConfig, opts: &SpeedOptions<'_>) -> Result<SpeedReport> {
    let (dev, device_name) = opts.device;
    let varmap = VarMap::new();
    let net = Denoiser::new(cfg, seeded_var_builder(&varmap, opts.seed, DType::F32, dev))?;
    let params: usize = varmap.all_vars().iter().map(|v| v.elem_count()).sum();
    let runs = opts.forward_runs.max(1);
    let (x1, t1) = seeded_inputs(cfg, 1, opts.seed, dev)?;
    let (x8, t8) = seeded_inputs(cfg, 8, opts.seed + 1, dev)?;
    let y1 = net.forward(&x1, &t1, None)?;
    let forward_b1_mean = f64::from(y1.mean_all()?.to_scalar::<f32>()?);
    let forward_b1_rms = f64::from(y1.sqr()?.mean_all()?.sqrt()?.to_scalar::<f32>()?);
    if let Some(dir) = opts.export {
        let reference = reference_tensors(&net, x1.clone(), t1.clone(), y1.clone());
        write_export(dir, cfg, &varmap, &reference, None)?;
    }
    let forward_b1_ms = time_forward(&net, &x1, &t1, runs)?;
    let forward_b8_ms = time_forward(&net, &x8, &t8, runs)?;

    let params_adamw = ParamsAdamW {
        lr: 1e-4,
        ..Default::default()
    };
    let mut opt = AdamW::new(varmap.all_vars(), params_adamw)?;
    let noise = seeded_inputs(cfg, 8, opts.seed + 2, dev)?.0;
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
        Ok([ms(t0, t1), ms(t1, t2), ms(t2, t3)])
    };
    step()?;
    step()?;
    let train_runs = opts.train_runs.max(1);
    let mut times = Vec::with_capacity(train_runs);
    let mut phases: [Vec<f64>; 3] = Default::default();
    let cpu0 = crate::process::cpu_seconds();
    let wall0 = Instant::now();
    for _ in 0..train_runs {
        let start = Instant::now();
        let p = step()?;
        times.push(ms(start, Instant::now()));
        for (all, t) in phases.iter_mut().zip(p) {
            all.push(t);
        }
    }
    let [forward, backward, optimizer] = phases.map(median);
    let wall = wall0.elapsed().as_secs_f64();
    let train_cpu_over_wall = match (cpu0, crate::process::cpu_seconds()) {
        (Some(a), Some(b)) if wall > 0.0 => Some((b - a) / wall),
        _ => None,
    };
    Ok(SpeedReport {
        forward_b1_ms,
        forward_b8_ms,
        train_b8_ms: median(times),
        train_b8_forward_ms: forward,
        train_b8_backward_ms: backward,
        train_b8_optimizer_ms: optimizer,
        train_cpu_over_wall,
        forward_b8_per_sample_over_b1: forward_b8_ms / 8.0 / forward_b1_ms,
        forward_b1_mean,
        forward_b1_rms,
        threads: rayon::current_num_threads(),
        params,
        device: device_name.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tiny_network_is_timed_and_its_output_checked() {
        let mut cfg = DenoiserConfig::tiny().unconditional();
        cfg.sensor.rows = 8;
        cfg.sensor.cols = 64;
        let opts = SpeedOptions {
            forward_runs: 1,
            train_runs: 1,
            seed: 0,
            device: (&Device::Cpu, "cpu"),
            export: None,
        };
        let r = measure(&cfg, &opts).unwrap();
        for ms in [r.forward_b1_ms, r.forward_b8_ms, r.train_b8_ms] {
            assert!(ms.is_finite() && ms > 0.0, "{r:?}");
        }
        assert!(r.forward_b1_rms > 0.0 && r.params > 0, "{r:?}");
        // seeded: the same output again
        let again = measure(&cfg, &opts).unwrap();
        assert_eq!(again.forward_b1_mean, r.forward_b1_mean);
    }
}
