//! `cargo xtask check-kernels`: the fused ops of `veila_nn::fused` against their candle
//! compositions on one device, with the time of each. On a GPU (a `cuda` build: `cargo xtask
//! build-cuda --xtask`) it checks the CUDA kernels where the host emulation
//! (`veila-nn/tests/it/cuda_emu.rs`) cannot: the real compiler (fused multiply-adds), the real
//! launch code in `fused/cuda.rs`, the real sizes.
//!
//! * GroupNorm + per-sample scale/shift + SiLU, forward and gradient, f32 / bf16 / f16: relative
//!   error (max |kernel - reference| / max |reference|) against the composition in f64 on the same
//!   device and rounded inputs, and milliseconds of the kernels and of the composition the device
//!   ran before them;
//! * the scaled residual sum, the same way;
//! * AdamW over a whole network's parameters: the trainer's step (one fused launch on a GPU) against
//!   `candle_nn::AdamW` on the CPU for two steps, counting the parameters whose bits differ, and the
//!   milliseconds of a step fused and unfused (`candle_nn::AdamW` on the device).
//!
//! Prints one JSON object (also to `--json`); exits non-zero when an error exceeds its bound.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{Optimizer, ParamsAdamW, VarMap};
use clap::{Args, ValueEnum};
use serde::Serialize;
use veila_nn::fused::{
    add_scaled, group_norm_act, group_norm_act_grad, group_norm_act_grad_reference,
    group_norm_act_reference, is_half,
};
use veila_nn::{Denoiser, DenoiserConfig, seeded_var_builder};

use crate::device::DeviceArg;

/// Arguments of `cargo xtask check-kernels`.
#[derive(Debug, Args)]
pub struct CheckKernelsArgs {
    /// Where the ops run: `cpu` (the CPU kernels) or `cuda` / `cuda:N` (the CUDA kernels).
    #[arg(long, default_value = "cpu", value_parser = crate::device::parse_device)]
    device: DeviceArg,
    /// GroupNorm input `B,C,N` (default: a paper-network block at batch 8: 128 channels of
    /// 64 x 1024).
    #[arg(long, default_value = "8,128,65536", value_parser = parse_shape)]
    shape: Shape3,
    /// GroupNorm groups.
    #[arg(long, default_value_t = 32)]
    groups: usize,
    /// Timed repetitions of each op (after one warm-up run).
    #[arg(long, default_value_t = 10)]
    runs: usize,
    /// Whose parameters the AdamW check updates.
    #[arg(long, value_enum, default_value_t = AdamNetwork::Paper)]
    adamw_network: AdamNetwork,
    /// Also write the JSON object here.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// `B,C,N`.
#[derive(Debug, Clone, Copy)]
pub struct Shape3([usize; 3]);

fn parse_shape(s: &str) -> std::result::Result<Shape3, String> {
    let v: Vec<usize> = s
        .split(',')
        .map(|p| p.trim().parse::<usize>().map_err(|e| format!("{s}: {e}")))
        .collect::<std::result::Result<_, _>>()?;
    match v.as_slice() {
        [b, c, n] if *b > 0 && *c > 0 && *n > 0 => Ok(Shape3([*b, *c, *n])),
        _ => Err(format!("{s}: expected three positive sizes B,C,N")),
    }
}

/// The network whose parameters the AdamW check updates.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum AdamNetwork {
    /// `DenoiserConfig::paper()` (76 M parameters).
    Paper,
    /// `DenoiserConfig::small()`.
    Small,
}

#[derive(Debug, Serialize)]
struct GnRow {
    dtype: String,
    shape: [usize; 3],
    groups: usize,
    silu: bool,
    /// Relative errors of y, dx, dscale, dshift.
    rel_err: [f64; 4],
    /// Bounds of y and dx, and of dscale and dshift.
    bound_out: f64,
    bound_sums: f64,
    /// Forward + gradient, the fused path (kernels on this device) and the composition.
    fused_ms: f64,
    composition_ms: f64,
    pass: bool,
}

#[derive(Debug, Serialize)]
struct AddRow {
    dtype: String,
    rel_err: f64,
    bound: f64,
    fused_ms: f64,
    composition_ms: f64,
    pass: bool,
}

#[derive(Debug, Serialize)]
struct AdamRow {
    network: String,
    tensors: usize,
    parameters: usize,
    /// Whether the trainer's step ran as one fused launch on this device.
    fused: bool,
    /// Parameters whose bits differ from `candle_nn::AdamW` on the CPU after two steps.
    differing_from_candle_cpu: usize,
    step_ms: f64,
    candle_nn_step_ms: f64,
    pass: bool,
}

#[derive(Debug, Serialize)]
struct Report {
    device: String,
    kernels_on: bool,
    group_norm: Vec<GnRow>,
    add_scaled: Vec<AddRow>,
    adamw: AdamRow,
    pass: bool,
}

/// Runs the command.
pub fn run(args: CheckKernelsArgs) -> Result<()> {
    let dev = args.device.open()?;
    let mut group_norm = Vec::new();
    let mut adds = Vec::new();
    // bounds: f32 a few times the host emulation's largest errors (1.7e-7 for y, 7.3e-7 for the
    // gradients; the GPU compiler fuses multiply-adds); half dtypes two roundings of the dtype
    // (the outputs and dscale / dshift come back in it)
    for (dtype, bound_out, bound_sums) in [
        (DType::F32, 5e-6, 5e-6),
        (DType::BF16, 8e-3, 8e-3),
        (DType::F16, 1e-3, 1e-3),
    ] {
        for silu in [true, false] {
            group_norm.push(check_group_norm(
                &args, &dev, dtype, silu, bound_out, bound_sums,
            )?);
        }
        adds.push(check_add_scaled(&args, &dev, dtype)?);
    }
    let adamw = check_adamw(&args, &dev)?;
    let pass = group_norm.iter().all(|r| r.pass) && adds.iter().all(|r| r.pass) && adamw.pass;
    let report = Report {
        device: args.device.name(),
        kernels_on: veila_nn::fused::kernels_enabled(),
        group_norm,
        add_scaled: adds,
        adamw,
        pass,
    };
    let text = serde_json::to_string_pretty(&report)?;
    println!("{text}");
    if let Some(p) = &args.json {
        std::fs::write(p, &text).with_context(|| format!("writing {}", p.display()))?;
    }
    if !pass {
        bail!(
            "a fused op is off its reference by more than its bound (see the rows with \"pass\": false)"
        );
    }
    Ok(())
}

/// Milliseconds per call of `f` (one warm-up call, then `runs`), waiting for the device.
fn time_ms(dev: &Device, runs: usize, mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    f()?;
    dev.synchronize()?;
    let t0 = Instant::now();
    for _ in 0..runs.max(1) {
        f()?;
    }
    dev.synchronize()?;
    Ok(t0.elapsed().as_secs_f64() * 1e3 / runs.max(1) as f64)
}

/// max |a - b| / max |b|, in f64.
fn rel_err(a: &Tensor, b: &Tensor) -> Result<f64> {
    let a = a.to_dtype(DType::F64)?;
    let b = b.to_dtype(DType::F64)?;
    let d = (a - &b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f64>()?;
    let m = b.abs()?.flatten_all()?.max(0)?.to_scalar::<f64>()?;
    Ok(d / m.max(1e-300))
}

/// Uniform in `[lo, hi)` of `shape` on `dev` in `dtype`, drawn in f32 on the CPU from `seed`
/// (the same values on every device).
fn uniform(
    dev: &Device,
    shape: &[usize],
    (lo, hi): (f32, f32),
    dtype: DType,
    seed: u64,
) -> Result<Tensor> {
    use rand::{Rng, SeedableRng};
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| lo + (hi - lo) * r.random::<f32>()).collect();
    Ok(Tensor::from_vec(v, shape, &Device::Cpu)?
        .to_dtype(dtype)?
        .to_device(dev)?)
}

fn check_group_norm(
    args: &CheckKernelsArgs,
    dev: &Device,
    dtype: DType,
    silu: bool,
    bound_out: f64,
    bound_sums: f64,
) -> Result<GnRow> {
    let [b, c, n] = args.shape.0;
    let g = args.groups;
    let x = uniform(dev, &[b, c, n], (-1.8, 2.2), dtype, 1)?;
    let scale = uniform(dev, &[b, c], (0.5, 1.5), dtype, 2)?;
    let shift = uniform(dev, &[b, c], (-0.3, 0.3), dtype, 3)?;
    let grad = uniform(dev, &[b, c, n], (-1.0, 1.0), dtype, 4)?;
    let eps = 1e-5;
    let y = group_norm_act(&x, &scale, &shift, g, eps, silu)?;
    let (dx, ds, dt) = group_norm_act_grad(&x, &scale, &shift, g, eps, silu, &grad)?;
    // the truth: the composition in f64 on the same (rounded) inputs
    let f64s = |t: &Tensor| t.to_dtype(DType::F64);
    let (x64, s64, t64, g64) = (f64s(&x)?, f64s(&scale)?, f64s(&shift)?, f64s(&grad)?);
    let y_ref = group_norm_act_reference(&x64, &s64, &t64, g, eps, silu)?;
    let (dx_ref, ds_ref, dt_ref) =
        group_norm_act_grad_reference(&x64, &s64, &t64, g, eps, silu, &g64)?;
    let rel = [
        rel_err(&y, &y_ref)?,
        rel_err(&dx, &dx_ref)?,
        rel_err(&ds, &ds_ref)?,
        rel_err(&dt, &dt_ref)?,
    ];
    drop((x64, s64, t64, g64, y_ref, dx_ref, ds_ref, dt_ref));
    let fused_ms = time_ms(dev, args.runs, || {
        let y = group_norm_act(&x, &scale, &shift, g, eps, silu)?;
        let grads = group_norm_act_grad(&x, &scale, &shift, g, eps, silu, &grad)?;
        drop((y, grads));
        Ok(())
    })?;
    // what the device ran without the kernels: the composition, f32 inside for half dtypes
    let composition_ms = time_ms(dev, args.runs, || {
        let y = if is_half(dtype) {
            let f = |t: &Tensor| t.to_dtype(DType::F32);
            group_norm_act_reference(&f(&x)?, &f(&scale)?, &f(&shift)?, g, eps, silu)?
                .to_dtype(dtype)?
        } else {
            group_norm_act_reference(&x, &scale, &shift, g, eps, silu)?
        };
        let grads = group_norm_act_grad_reference(&x, &scale, &shift, g, eps, silu, &grad)?;
        drop((y, grads));
        Ok(())
    })?;
    let pass = rel[0] < bound_out
        && rel[1] < bound_out
        && rel[2] < bound_sums
        && rel[3] < bound_sums
        && rel.iter().all(|e| e.is_finite());
    let row = GnRow {
        dtype: format!("{dtype:?}"),
        shape: args.shape.0,
        groups: g,
        silu,
        rel_err: rel,
        bound_out,
        bound_sums,
        fused_ms,
        composition_ms,
        pass,
    };
    eprintln!(
        "group norm {dtype:?} silu {silu}: errors {:.1e} {:.1e} {:.1e} {:.1e}, {:.2} ms fused, {:.2} ms composed{}",
        rel[0],
        rel[1],
        rel[2],
        rel[3],
        fused_ms,
        composition_ms,
        if pass { "" } else { "  FAIL" }
    );
    Ok(row)
}

fn check_add_scaled(args: &CheckKernelsArgs, dev: &Device, dtype: DType) -> Result<AddRow> {
    let shape = args.shape.0;
    let a = uniform(dev, &shape, (-2.0, 2.0), dtype, 5)?;
    let b = uniform(dev, &shape, (-2.0, 2.0), dtype, 6)?;
    let s = std::f64::consts::FRAC_1_SQRT_2;
    let y = add_scaled(&a, &b, s)?;
    let truth = ((a.to_dtype(DType::F64)? + b.to_dtype(DType::F64)?)? * f64::from(s as f32))?;
    let rel = rel_err(&y, &truth)?;
    // two roundings of the dtype (the composition rounds the sum, then the product)
    let bound = match dtype {
        DType::BF16 => 2f64.powi(-7),
        DType::F16 => 2f64.powi(-10),
        _ => 2f64.powi(-22),
    };
    let fused_ms = time_ms(dev, args.runs, || {
        drop(add_scaled(&a, &b, s)?);
        Ok(())
    })?;
    let composition_ms = time_ms(dev, args.runs, || {
        drop(((&a + &b)? * s)?);
        Ok(())
    })?;
    let pass = rel < bound;
    eprintln!(
        "add_scaled {dtype:?}: error {rel:.1e}, {fused_ms:.2} ms fused, {composition_ms:.2} ms composed{}",
        if pass { "" } else { "  FAIL" }
    );
    Ok(AddRow {
        dtype: format!("{dtype:?}"),
        rel_err: rel,
        bound,
        fused_ms,
        composition_ms,
        pass,
    })
}

fn check_adamw(args: &CheckKernelsArgs, dev: &Device) -> Result<AdamRow> {
    let cfg = match args.adamw_network {
        AdamNetwork::Paper => DenoiserConfig::paper(),
        AdamNetwork::Small => DenoiserConfig::small(),
    };
    let vm = VarMap::new();
    Denoiser::new(&cfg, seeded_var_builder(&vm, 0, DType::F32, dev))?;
    let mut named: Vec<(String, Var)> = vm
        .data()
        .lock()
        .expect("varmap")
        .clone()
        .into_iter()
        .collect();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    let parameters: usize = named.iter().map(|(_, v)| v.elem_count()).sum();
    let params = ParamsAdamW {
        lr: 1e-3,
        weight_decay: 0.01,
        ..ParamsAdamW::default()
    };
    // the same parameters on the CPU for candle-nn's reference steps
    let cpu_vars: Vec<Var> = named
        .iter()
        .map(|(_, v)| Var::from_tensor(&v.as_tensor().to_device(&Device::Cpu)?))
        .collect::<candle_core::Result<_>>()?;
    let mut ours = veila_diffusion::trainer::AdamW::new(named.clone(), params.clone())?;
    ours.set_fused(Some(veila_diffusion::app::nn::fused_adamw()));
    let mut theirs_cpu = candle_nn::AdamW::new(cpu_vars.clone(), params.clone())?;
    // gradients: the loss sum(var * g) has exactly g as its gradient
    let grads_for = |vars: &[Var], gs: &[Tensor]| -> Result<candle_core::backprop::GradStore> {
        let mut loss = Tensor::new(0f32, vars[0].device())?;
        for (v, g) in vars.iter().zip(gs) {
            loss = (loss + (v.as_tensor() * g)?.sum_all()?)?;
        }
        Ok(loss.backward()?)
    };
    for step in 0..2 {
        let w = 0.1 * (step + 1) as f32;
        let gs: Vec<Tensor> = named
            .iter()
            .enumerate()
            .map(|(k, (_, v))| uniform(dev, v.dims(), (-w, w), DType::F32, (100 * step + k) as u64))
            .collect::<Result<_>>()?;
        let gs_cpu: Vec<Tensor> = gs
            .iter()
            .map(|g| g.to_device(&Device::Cpu))
            .collect::<candle_core::Result<_>>()?;
        let dev_vars: Vec<Var> = named.iter().map(|(_, v)| v.clone()).collect();
        ours.step(&grads_for(&dev_vars, &gs)?, 1.0)?;
        theirs_cpu.step(&grads_for(&cpu_vars, &gs_cpu)?)?;
    }
    let mut differing = 0usize;
    for ((_, v), c) in named.iter().zip(&cpu_vars) {
        let a = v
            .as_tensor()
            .flatten_all()?
            .to_device(&Device::Cpu)?
            .to_vec1::<f32>()?;
        let b = c.as_tensor().flatten_all()?.to_vec1::<f32>()?;
        differing += a
            .iter()
            .zip(&b)
            .filter(|(p, q)| p.to_bits() != q.to_bits())
            .count();
    }
    // timing: one step of each on the device, with one set of gradients
    let dev_vars: Vec<Var> = named.iter().map(|(_, v)| v.clone()).collect();
    let gs: Vec<Tensor> = named
        .iter()
        .enumerate()
        .map(|(k, (_, v))| uniform(dev, v.dims(), (-0.1, 0.1), DType::F32, 7_000 + k as u64))
        .collect::<Result<_>>()?;
    let grads = grads_for(&dev_vars, &gs)?;
    let step_ms = time_ms(dev, args.runs, || Ok(ours.step(&grads, 1.0)?))?;
    let mut theirs_dev = candle_nn::AdamW::new(dev_vars.clone(), params)?;
    let candle_nn_step_ms = time_ms(dev, args.runs, || Ok(theirs_dev.step(&grads)?))?;
    let fused = veila_nn::fused::adamw_fused_supported(named[0].1.as_tensor());
    let pass = differing == 0;
    eprintln!(
        "AdamW ({} tensors, {parameters} parameters, fused {fused}): {differing} differ from candle-nn on the CPU; {step_ms:.2} ms a step, candle-nn {candle_nn_step_ms:.2} ms{}",
        named.len(),
        if pass { "" } else { "  FAIL" }
    );
    Ok(AdamRow {
        network: format!("{:?}", args.adamw_network).to_lowercase(),
        tensors: named.len(),
        parameters,
        fused,
        differing_from_candle_cpu: differing,
        step_ms,
        candle_nn_step_ms,
        pass,
    })
}
