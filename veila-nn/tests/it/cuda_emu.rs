//! The CUDA kernels of `src/fused/cuda/kernels.cu`, run on the host (`tests/cuda_emu/`: each CUDA
//! thread an OS thread, `__syncthreads` a barrier), against independent references: GroupNorm +
//! scale/shift + SiLU and its gradient against the candle composition in f64, the scaled residual
//! sum against candle's ops, and the fused AdamW bit for bit against `candle_nn::AdamW`. A GPU
//! runs the same source (`cargo xtask check-cuda` compares there). Skips, saying so, where no C++
//! compiler is installed.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{Optimizer, ParamsAdamW};
use rand::Rng;
use veila_nn::fused::{AdamScalars, group_norm_act_grad_reference, group_norm_act_reference};

use crate::common::rng;

/// The compiled harness, or `None` (with a message) where there is no C++ compiler.
fn harness() -> Option<&'static Path> {
    static H: OnceLock<Option<PathBuf>> = OnceLock::new();
    H.get_or_init(|| {
        let cxx = std::env::var("CXX").unwrap_or_else(|_| "c++".into());
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/cuda_emu/harness.cpp");
        let out = Path::new(env!("CARGO_TARGET_TMPDIR"))
            .join(format!("veila-cuda-emu-{}", std::process::id()));
        let res = Command::new(&cxx)
            .args(["-std=c++20", "-O2", "-ffp-contract=off", "-pthread"])
            .arg(&src)
            .arg("-o")
            .arg(&out)
            .output();
        match res {
            Err(e) => {
                eprintln!("skipping the CUDA kernel emulation: no C++ compiler ({cxx}: {e})");
                None
            }
            Ok(o) if !o.status.success() => panic!(
                "{} does not compile with {cxx}:\n{}",
                src.display(),
                String::from_utf8_lossy(&o.stderr)
            ),
            Ok(_) => Some(out),
        }
    })
    .as_deref()
}

/// Runs `op` on `inputs` (name, raw bytes) with `args`, returning the named outputs' bytes.
fn run(
    exe: &Path,
    op: &str,
    args: &str,
    inputs: &[(&str, Vec<u8>)],
    outputs: &[&str],
) -> Vec<Vec<u8>> {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("args.txt"), args).unwrap();
    for (name, bytes) in inputs {
        std::fs::write(dir.path().join(format!("{name}.bin")), bytes).unwrap();
    }
    let o = Command::new(exe).arg(op).arg(dir.path()).output().unwrap();
    assert!(
        o.status.success(),
        "harness {op}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    outputs
        .iter()
        .map(|n| std::fs::read(dir.path().join(format!("{n}.out"))).unwrap())
        .collect()
}

/// The raw little-endian bytes of `t` in `dtype`.
fn bytes(t: &Tensor, dtype: DType) -> Vec<u8> {
    let t = t.to_dtype(dtype).unwrap().flatten_all().unwrap();
    match dtype {
        DType::F32 => t
            .to_vec1::<f32>()
            .unwrap()
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect(),
        DType::BF16 => t
            .to_vec1::<half::bf16>()
            .unwrap()
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect(),
        DType::F16 => t
            .to_vec1::<half::f16>()
            .unwrap()
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect(),
        d => panic!("no bytes for {d:?}"),
    }
}

/// `bytes` of `dtype` as an f64 tensor of `shape`.
fn tensor(bytes: &[u8], dtype: DType, shape: &[usize]) -> Tensor {
    let v: Vec<f64> = match dtype {
        DType::F32 => bytes
            .chunks_exact(4)
            .map(|c| f64::from(f32::from_le_bytes(c.try_into().unwrap())))
            .collect(),
        DType::BF16 => bytes
            .chunks_exact(2)
            .map(|c| half::bf16::from_le_bytes(c.try_into().unwrap()).to_f64())
            .collect(),
        DType::F16 => bytes
            .chunks_exact(2)
            .map(|c| half::f16::from_le_bytes(c.try_into().unwrap()).to_f64())
            .collect(),
        d => panic!("no values for {d:?}"),
    };
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

/// max |a - b| / max |b|.
fn rel_err(a: &Tensor, b: &Tensor) -> f64 {
    let d = crate::common::max_abs(&(a - b).unwrap());
    d / crate::common::max_abs(b).max(1e-300)
}

fn uniform(r: &mut rand_chacha::ChaCha8Rng, shape: &[usize], lo: f64, hi: f64) -> Tensor {
    let n: usize = shape.iter().product();
    let v: Vec<f64> = (0..n).map(|_| r.random_range(lo..hi)).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

struct GnCase {
    dtype: DType,
    b: usize,
    c: usize,
    n: usize,
    groups: usize,
    silu: bool,
    /// Added to every input value (a large offset tests the statistics' cancellation).
    offset: f64,
    /// Half-width of the inputs' spread (0: a constant group, zero variance).
    spread: f64,
}

/// The emulated kernels' (y, dx, dscale, dshift) relative errors against the f64 composition on
/// the same (rounded) inputs.
fn gn_errors(exe: &Path, k: &GnCase, seed: u64) -> [f64; 4] {
    let mut r = rng(seed);
    let shape = [k.b, k.c, k.n];
    let x = (uniform(&mut r, &shape, -k.spread, k.spread + 1e-300) + k.offset).unwrap();
    let scale = uniform(&mut r, &[k.b, k.c], 0.5, 1.5);
    let shift = uniform(&mut r, &[k.b, k.c], -0.3, 0.3);
    let g = uniform(&mut r, &shape, -1.0, 1.0);
    // the reference sees the inputs as the kernels do: rounded to the dtype
    let round = |t: &Tensor| tensor(&bytes(t, k.dtype), k.dtype, t.dims());
    let (x, scale, shift, g) = (round(&x), round(&scale), round(&shift), round(&g));
    let eps = 1e-5;
    let y_ref = group_norm_act_reference(&x, &scale, &shift, k.groups, eps, k.silu).unwrap();
    let (dx_ref, ds_ref, dt_ref) =
        group_norm_act_grad_reference(&x, &scale, &shift, k.groups, eps, k.silu, &g).unwrap();
    let sfx = match k.dtype {
        DType::F32 => "f32",
        DType::BF16 => "bf16",
        _ => "f16",
    };
    let args = format!(
        "{} {} {} {} {eps} {}",
        k.b, k.c, k.n, k.groups, k.silu as i32
    );
    let out = run(
        exe,
        &format!("gn_{sfx}"),
        &args,
        &[
            ("x", bytes(&x, k.dtype)),
            ("scale", bytes(&scale, k.dtype)),
            ("shift", bytes(&shift, k.dtype)),
            ("g", bytes(&g, k.dtype)),
        ],
        &["y", "dx", "dscale", "dshift"],
    );
    let y = tensor(&out[0], k.dtype, &shape);
    let dx = tensor(&out[1], k.dtype, &shape);
    let ds = tensor(&out[2], DType::F32, &[k.b, k.c]);
    let dt = tensor(&out[3], DType::F32, &[k.b, k.c]);
    for t in [&y, &dx, &ds, &dt] {
        assert!(crate::common::max_abs(t).is_finite(), "non-finite output");
    }
    [
        rel_err(&y, &y_ref),
        rel_err(&dx, &dx_ref),
        rel_err(&ds, &ds_ref),
        rel_err(&dt, &dt_ref),
    ]
}

#[test]
fn the_group_norm_kernels_on_the_host_equal_the_f64_composition() {
    let Some(exe) = harness() else { return };
    // largest relative errors seen: f32 y 1.7e-7, gradients 7.3e-7; bf16 y and dx 3.3e-3 (their
    // 8-bit rounding), f16 4.3e-4 (11 bits); dscale and dshift are f32 sums in every dtype (1.3e-7)
    for (dtype, tol_out, tol_sums) in [
        (DType::F32, 1e-6, 1e-6),
        (DType::BF16, 5e-3, 1e-6),
        (DType::F16, 6e-4, 1e-6),
    ] {
        for (n, groups) in [(300, 3), (37, 6), (1, 2)] {
            for silu in [true, false] {
                let case = GnCase {
                    dtype,
                    b: 2,
                    c: 6,
                    n,
                    groups,
                    silu,
                    offset: 0.2,
                    spread: 2.0,
                };
                let e = gn_errors(exe, &case, 7 + n as u64);
                let what = format!("{dtype:?} n {n} groups {groups} silu {silu}");
                for (k, name, tol) in [
                    (0, "y", tol_out),
                    (1, "dx", tol_out),
                    (2, "dscale", tol_sums),
                    (3, "dshift", tol_sums),
                ] {
                    assert!(e[k] < tol, "{what}: {name} off by {:e}", e[k]);
                }
            }
        }
    }
}

#[test]
fn the_group_norm_kernels_stay_finite_and_accurate_on_hard_groups() {
    let Some(exe) = harness() else { return };
    // a mean of 100 over a spread of 1 (the f32 sum of squares of raw values would cancel), and a
    // constant group (zero variance: 1 / sqrt(eps) stays finite, x̂ is exactly 0); largest errors
    // seen 4.0e-6 and 3.1e-7
    for (offset, spread, tol) in [(100.0, 1.0, 1e-5), (3.0, 0.0, 1e-6)] {
        for silu in [true, false] {
            let case = GnCase {
                dtype: DType::F32,
                b: 1,
                c: 4,
                n: 500,
                groups: 2,
                silu,
                offset,
                spread,
            };
            let e = gn_errors(exe, &case, 11);
            for (k, name) in ["y", "dx", "dscale", "dshift"].iter().enumerate() {
                assert!(
                    e[k] < tol,
                    "offset {offset} spread {spread} silu {silu}: {name} off by {:e}",
                    e[k]
                );
            }
        }
    }
}

#[test]
fn the_add_scaled_kernel_on_the_host_equals_candle() {
    let Some(exe) = harness() else { return };
    let mut r = rng(3);
    let n = 1000;
    let a = uniform(&mut r, &[n], -2.0, 2.0);
    let b = uniform(&mut r, &[n], -2.0, 2.0);
    let s = std::f64::consts::FRAC_1_SQRT_2;
    for dtype in [DType::F32, DType::BF16, DType::F16] {
        let sfx = match dtype {
            DType::F32 => "f32",
            DType::BF16 => "bf16",
            _ => "f16",
        };
        let (ad, bd) = (a.to_dtype(dtype).unwrap(), b.to_dtype(dtype).unwrap());
        let out = run(
            exe,
            &format!("add_scaled_{sfx}"),
            &format!("{n} {}", s as f32),
            &[("a", bytes(&ad, dtype)), ("b", bytes(&bd, dtype))],
            &["y"],
        );
        let y = tensor(&out[0], dtype, &[n]);
        if dtype == DType::F32 {
            // the same two roundings as candle's (a + b) then * s
            let want = ((&ad + &bd).unwrap() * s)
                .unwrap()
                .to_dtype(DType::F64)
                .unwrap();
            assert_eq!(rel_err(&y, &want), 0.0, "f32 not bit-identical");
        } else {
            // one rounding to the half type at the end (candle rounds the sum too)
            let exact = ((ad.to_dtype(DType::F64).unwrap() + bd.to_dtype(DType::F64).unwrap())
                .unwrap()
                * f64::from(s as f32))
            .unwrap();
            let tol = if dtype == DType::BF16 { 4e-3 } else { 5e-4 };
            assert!(rel_err(&y, &exact) < tol, "{dtype:?}");
        }
    }
}

#[test]
fn the_fused_adamw_kernel_on_the_host_is_bit_identical_to_candle_nn() {
    let Some(exe) = harness() else { return };
    let mut r = rng(5);
    // two chunks and a tail, a tiny tensor, exactly one chunk
    let sizes = [5000usize, 17, 4096];
    let params = ParamsAdamW {
        lr: 3e-3,
        weight_decay: 0.01,
        ..ParamsAdamW::default()
    };
    let init: Vec<Vec<f32>> = sizes
        .iter()
        .map(|&n| (0..n).map(|_| r.random_range(-1.0f32..1.0)).collect())
        .collect();
    let vars: Vec<Var> = init
        .iter()
        .map(|v| Var::from_tensor(&Tensor::new(v.as_slice(), &Device::Cpu).unwrap()).unwrap())
        .collect();
    let mut theirs = candle_nn::AdamW::new(vars.clone(), params.clone()).unwrap();
    let flat = |vs: &[Vec<f32>]| -> Vec<u8> {
        vs.iter().flatten().flat_map(|v| v.to_le_bytes()).collect()
    };
    let mut p = flat(&init);
    let zeros: Vec<u8> = vec![0; p.len()];
    let (mut m, mut v) = (zeros.clone(), zeros);
    let args = format!(
        "{} {}",
        sizes.len(),
        sizes
            .iter()
            .map(|n| n.to_string())
            .collect::<Vec<_>>()
            .join(" ")
    );
    for (step, grad_scale) in [(1usize, 1.0f64), (2, 1.0), (3, 0.37), (4, 1.0)] {
        let grads: Vec<Vec<f32>> = sizes
            .iter()
            .map(|&n| {
                (0..n)
                    .map(|_| r.random_range(-0.5f32..0.5) * step as f32)
                    .collect()
            })
            .collect();
        // candle-nn: the loss sum(var * g) has exactly g as its gradient; the clipping factor is
        // applied to g first, as the trainer's AdamW does
        let mut loss = Tensor::new(0f32, &Device::Cpu).unwrap();
        for (var, g) in vars.iter().zip(&grads) {
            let g = (Tensor::new(g.as_slice(), &Device::Cpu).unwrap() * grad_scale).unwrap();
            loss = (loss + (var.as_tensor() * g).unwrap().sum_all().unwrap()).unwrap();
        }
        theirs.step(&loss.backward().unwrap()).unwrap();
        let scalars = AdamScalars::new(&params, step, grad_scale);
        let sc: Vec<u8> = scalars
            .to_array()
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let out = run(
            exe,
            "adamw",
            &args,
            &[
                ("p", p.clone()),
                ("g", flat(&grads)),
                ("m", m.clone()),
                ("v", v.clone()),
                ("scalars", sc),
            ],
            &["p", "m", "v"],
        );
        [p, m, v] = [out[0].clone(), out[1].clone(), out[2].clone()];
        let want: Vec<u8> = vars
            .iter()
            .flat_map(|var| var.as_tensor().to_vec1::<f32>().unwrap())
            .flat_map(|x| x.to_le_bytes())
            .collect();
        let differing = p
            .chunks_exact(4)
            .zip(want.chunks_exact(4))
            .filter(|(a, b)| a != b)
            .count();
        assert_eq!(
            differing, 0,
            "step {step}: {differing} parameters differ from candle-nn's"
        );
    }
    // the moments themselves: m after 4 steps is finite and not zero (the kernel wrote them)
    let m_vals: Vec<f32> = m
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert!(m_vals.iter().all(|x| x.is_finite()) && m_vals.iter().any(|x| *x != 0.0));
}
