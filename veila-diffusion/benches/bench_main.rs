//! Sampling benchmarks: time against the number of steps, with the accuracy of every sampler and
//! step count printed next to its time.
//!
//! Accuracy uses the analytic denoiser of Gaussian data (`x_0 ~ N(0.2, 0.5²)` per element), for
//! which the probability-flow ODE has an exact solution: deterministic samplers (DDIM η = 0,
//! DPM-Solver++(2M)) report the max error against it; stochastic ones (DDPM, DDIM η = 1) report
//! the error of the sampled mean and the relative error of the sampled variance.
//!
//! `cargo bench -p veila-diffusion`

use std::hint::black_box;
use std::time::{Duration, Instant};

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, Linear, VarBuilder, VarMap, conv2d, linear};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_diffusion::noise::randn;
use veila_diffusion::oracle::GaussianOracle;
use veila_diffusion::{
    Denoiser, Diffusion, DiffusionConfig, LossWeighting, Prediction, Sampler, SamplerConfig,
    SamplerKind, ScheduleConfig, Spacing, TimeInput,
};

const MU: f64 = 0.2;
const STD: f64 = 0.5;
const SHAPE: [usize; 4] = [1, 3, 32, 512];
const STEPS: [usize; 4] = [10, 20, 50, 100];

fn diffusion() -> Diffusion {
    Diffusion::new(DiffusionConfig {
        schedule: ScheduleConfig::cosine_logsnr(),
        prediction: Prediction::Epsilon,
        time_input: TimeInput::default(),
        loss_weighting: LossWeighting::Uniform,
        objective: Default::default(),
        train_levels: Default::default(),
    })
    .unwrap()
}

fn configs() -> Vec<(&'static str, SamplerKind, Spacing)> {
    vec![
        (
            "ddpm",
            SamplerKind::Ddpm {
                variance: Default::default(),
            },
            Spacing::Trailing,
        ),
        (
            "ddim_eta1",
            SamplerKind::Ddim { eta: 1.0 },
            Spacing::Trailing,
        ),
        (
            "ddim_eta0",
            SamplerKind::Ddim { eta: 0.0 },
            Spacing::Trailing,
        ),
        (
            "ddim_eta0_logsnr",
            SamplerKind::Ddim { eta: 0.0 },
            Spacing::LogSnr,
        ),
        (
            "dpmpp2m_trailing",
            SamplerKind::DpmSolverPp2M,
            Spacing::Trailing,
        ),
        (
            "dpmpp2m_logsnr",
            SamplerKind::DpmSolverPp2M,
            Spacing::LogSnr,
        ),
    ]
}

fn cfg(kind: SamplerKind, steps: usize, spacing: Spacing) -> SamplerConfig {
    SamplerConfig {
        kind,
        steps,
        spacing,
        guidance_scale: 1.0,
        clip_x0: None,
        start_t: None,
    }
}

/// Accuracy of one run: ("ode max err", value) or ("mean err / var rel err", ...).
fn accuracy(
    d: &Diffusion,
    oracle: &GaussianOracle,
    kind: SamplerKind,
    steps: usize,
    spacing: Spacing,
) -> String {
    let s = Sampler::new(d, cfg(kind, steps, spacing)).unwrap();
    let x_t = randn(&mut ChaCha8Rng::seed_from_u64(1), &SHAPE, &Device::Cpu).unwrap();
    let xs = x_t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let out = s
        .sample_from(oracle, x_t, None, &mut ChaCha8Rng::seed_from_u64(2), |_| {})
        .unwrap();
    let ys = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let deterministic = matches!(
        kind,
        SamplerKind::DpmSolverPp2M | SamplerKind::Ddim { eta: 0.0 }
    );
    if deterministic {
        let start = s.levels()[0];
        let e = xs
            .iter()
            .zip(&ys)
            .map(|(&x, &y)| (oracle.pf_ode_solution(x as f64, &start) - y as f64).abs())
            .fold(0.0, f64::max);
        format!("ode max err {e:.2e}")
    } else {
        let n = ys.len() as f64;
        let m = ys.iter().map(|&y| y as f64).sum::<f64>() / n;
        let v = ys.iter().map(|&y| (y as f64 - m).powi(2)).sum::<f64>() / (n - 1.0);
        format!(
            "mean err {:.1e}, var rel err {:.1e}",
            (m - MU).abs(),
            (v / (STD * STD) - 1.0).abs()
        )
    }
}

/// Mean wall time of `n` runs after one warm-up run.
fn time_per_sample(f: impl Fn(), n: u32) -> Duration {
    f();
    let t0 = Instant::now();
    for _ in 0..n {
        f();
    }
    t0.elapsed() / n
}

fn bench_oracle(c: &mut Criterion) {
    let d = diffusion();
    let oracle = GaussianOracle::new(MU, STD, d.clone()).unwrap();
    eprintln!(
        "\nveila-diffusion sampling, analytic Gaussian denoiser, shape {SHAPE:?} (sampler cost without a network)"
    );
    eprintln!(
        "{:<18} {:>5} {:>11}  accuracy",
        "sampler", "steps", "ms/sample"
    );
    let mut group = c.benchmark_group("sample_oracle_32x512");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(2))
        .warm_up_time(Duration::from_millis(300));
    for (name, kind, spacing) in configs() {
        for steps in STEPS {
            let s = Sampler::new(&d, cfg(kind, steps, spacing)).unwrap();
            let run = || {
                let mut rng = ChaCha8Rng::seed_from_u64(3);
                black_box(
                    s.sample(&oracle, &SHAPE, &Device::Cpu, None, &mut rng)
                        .unwrap(),
                );
            };
            let t = time_per_sample(run, 3);
            let acc = accuracy(&d, &oracle, kind, steps, spacing);
            eprintln!(
                "{name:<18} {steps:>5} {:>11.2}  {acc}",
                t.as_secs_f64() * 1e3
            );
            if steps == 10 || steps == 100 {
                group.bench_with_input(BenchmarkId::new(name, steps), &steps, |b, _| b.iter(run));
            }
        }
    }
    group.finish();
}

/// A small conv net standing in for the denoiser, to show how sampling time scales with steps
/// when each step costs one network evaluation.
struct TinyConv {
    a: Conv2d,
    b: Conv2d,
    c: Conv2d,
    t: Linear,
}

impl TinyConv {
    fn new(vb: VarBuilder<'_>) -> candle_core::Result<Self> {
        let p = Conv2dConfig {
            padding: 1,
            ..Default::default()
        };
        Ok(Self {
            a: conv2d(3, 16, 3, p, vb.pp("a"))?,
            b: conv2d(16, 16, 3, p, vb.pp("b"))?,
            c: conv2d(16, 3, 3, p, vb.pp("c"))?,
            t: linear(1, 16, vb.pp("t"))?,
        })
    }
}

impl Denoiser for TinyConv {
    type Cond = ();
    fn forward(&self, x: &Tensor, t: &Tensor, _c: Option<&()>) -> candle_core::Result<Tensor> {
        let temb = self
            .t
            .forward(&t.unsqueeze(1)?)?
            .unsqueeze(2)?
            .unsqueeze(3)?;
        let h = self.a.forward(x)?.broadcast_add(&temb)?.silu()?;
        let h = self.b.forward(&h)?.silu()?;
        self.c.forward(&h)
    }
}

fn bench_convnet(c: &mut Criterion) {
    let d = diffusion();
    let vm = VarMap::new();
    let net = TinyConv::new(VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu)).unwrap();
    let x = randn(&mut ChaCha8Rng::seed_from_u64(0), &SHAPE, &Device::Cpu).unwrap();
    let t = Tensor::new(&[500f32], &Device::Cpu).unwrap();
    let fwd = time_per_sample(
        || {
            black_box(net.forward(&x, &t, None).unwrap());
        },
        5,
    );
    eprintln!(
        "\nveila-diffusion sampling with a 3-conv net (16 ch) at {SHAPE:?}: one forward {:.2} ms",
        fwd.as_secs_f64() * 1e3
    );
    eprintln!(
        "{:<18} {:>5} {:>11} {:>14}",
        "sampler", "steps", "ms/sample", "ms/step"
    );
    let mut group = c.benchmark_group("sample_convnet_32x512");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_millis(300));
    for (name, kind) in [
        (
            "ddpm",
            SamplerKind::Ddpm {
                variance: Default::default(),
            },
        ),
        ("dpmpp2m", SamplerKind::DpmSolverPp2M),
    ] {
        for steps in [10, 20, 50] {
            let s = Sampler::new(&d, cfg(kind, steps, Spacing::Trailing)).unwrap();
            let run = || {
                let mut rng = ChaCha8Rng::seed_from_u64(3);
                black_box(
                    s.sample(&net, &SHAPE, &Device::Cpu, None, &mut rng)
                        .unwrap(),
                );
            };
            let tm = time_per_sample(run, 1);
            eprintln!(
                "{name:<18} {steps:>5} {:>11.1} {:>14.2}",
                tm.as_secs_f64() * 1e3,
                tm.as_secs_f64() * 1e3 / steps as f64
            );
            if steps == 10 {
                group.bench_with_input(BenchmarkId::new(name, steps), &steps, |b, _| b.iter(run));
            }
        }
    }
    group.finish();
}

criterion_group!(benches, bench_oracle, bench_convnet);
criterion_main!(benches);
