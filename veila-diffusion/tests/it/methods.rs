//! The objectives beside Gaussian diffusion: rectified flow (its Euler sampler against the exact
//! transport of Gaussian data) and one-pass regression (its loss and its single pass), and the
//! per-element loss weights every objective accepts.

use candle_core::{Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_diffusion::noise::randn;
use veila_diffusion::{Denoiser, Diffusion, DiffusionConfig, Objective, Sampler, SamplerConfig};

/// The exact velocity field of rectified flow for i.i.d. Gaussian data `x₀ ~ N(μ, s²)`:
/// `x_t = (1 − t)·x₀ + t·ε` is Gaussian with mean `(1 − t)·μ` and variance `(1 − t)²·s² + t²`, and
/// `E[ε − x₀ | x_t] = (t − (1 − t)·s²)/var · (x_t − (1 − t)·μ) − μ`.
struct FlowOracle {
    mean: f64,
    std: f64,
}

impl Denoiser for FlowOracle {
    type Cond = ();
    fn forward(&self, x_t: &Tensor, t: &Tensor, _cond: Option<&()>) -> candle_core::Result<Tensor> {
        // TimeInput::Unit: the network sees t itself (one value per sample)
        let ts = t.to_vec1::<f32>()?;
        let (mu, s2) = (self.mean, self.std * self.std);
        let mut rows = Vec::with_capacity(ts.len());
        for (i, &t) in ts.iter().enumerate() {
            let t = f64::from(t);
            let var = (1.0 - t).powi(2) * s2 + t * t;
            let k = (t - (1.0 - t) * s2) / var;
            let xi = x_t.get(i)?;
            rows.push(((xi - (1.0 - t) * mu)?.affine(k, -mu))?);
        }
        Tensor::stack(&rows, 0)
    }
}

fn flow() -> Diffusion {
    Diffusion::new(DiffusionConfig {
        objective: Objective::rectified_flow(),
        ..DiffusionConfig::default()
    })
    .unwrap()
}

/// Max error of `steps` Euler steps against the exact transport `x₀ = μ + s·x₁`.
fn euler_error(steps: usize, clip: Option<f64>) -> f64 {
    let d = flow();
    let (mean, std) = (0.3, 0.2);
    let sampler = Sampler::new(
        &d,
        SamplerConfig {
            clip_x0: clip,
            ..SamplerConfig::ddim(steps, 0.0)
        },
    )
    .unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let x1 = randn(&mut rng, &[4, 1, 2, 8], &Device::Cpu).unwrap();
    let x0 = sampler
        .sample_from(
            &FlowOracle { mean, std },
            x1.clone(),
            None,
            &mut rng,
            |_| {},
        )
        .unwrap();
    let exact = x1.affine(std, mean).unwrap();
    (x0 - exact)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap() as f64
}

#[test]
fn rectified_flow_euler_converges_to_the_exact_transport() {
    let e4 = euler_error(4, None);
    let e16 = euler_error(16, None);
    let e64 = euler_error(64, None);
    // measured: 0.24, 0.069, 0.018 (the data are far from the straight-path regime: s = 0.2)
    assert!(e64 < 0.03, "64 Euler steps: error {e64}");
    // first order: four times the steps, about a quarter of the error
    assert!(
        e16 < e4 * 0.35 && e64 < e16 * 0.35 && e64 > e16 * 0.15,
        "{e4} {e16} {e64}"
    );
    // clipping far outside the data changes nothing
    assert!((euler_error(16, Some(50.0)) - e16).abs() < 1e-5);
}

/// A "network" that outputs a fixed tensor whatever it is fed, and records its time input.
struct Constant(Tensor);

impl Denoiser for Constant {
    type Cond = ();
    fn forward(&self, x_t: &Tensor, t: &Tensor, _cond: Option<&()>) -> candle_core::Result<Tensor> {
        // regression feeds zeros at t = 1
        assert_eq!(x_t.abs()?.sum_all()?.to_scalar::<f32>()?, 0.0);
        assert!(t.to_vec1::<f32>()?.iter().all(|&v| v > 0.9999));
        self.0.broadcast_as(x_t.shape())?.contiguous()
    }
}

#[test]
fn regression_is_a_weighted_l1_fit_and_samples_in_one_pass() {
    let d = Diffusion::new(DiffusionConfig {
        objective: Objective::Regression,
        ..DiffusionConfig::default()
    })
    .unwrap();
    let dev = Device::Cpu;
    let x0 = Tensor::new(
        &[[[[1.0f32, -2.0, 0.5, 4.0]]], [[[0.0, 0.0, 3.0, -1.0]]]],
        &dev,
    )
    .unwrap();
    let out = Tensor::new(&[[[[0.5f32, 0.0, 0.5, 1.0]]]], &dev).unwrap();
    let model = Constant(out.clone());
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let loss = |w: Option<&Tensor>, rng: &mut ChaCha8Rng| -> f64 {
        d.training_loss_weighted(&model, &x0, w, None, None, rng)
            .unwrap()
            .loss
            .to_scalar::<f32>()
            .unwrap() as f64
    };
    // |out - x0|: sample 0 = (0.5 + 2 + 0 + 3)/4, sample 1 = (0.5 + 0 + 2.5 + 2)/4
    let plain = loss(None, &mut rng);
    assert!(
        (plain - (5.5 / 4.0 + 5.0 / 4.0) / 2.0).abs() < 1e-6,
        "{plain}"
    );
    // weights 0 leave those elements out of the per-sample weighted mean
    let w = Tensor::new(
        &[[[[1.0f32, 0.0, 1.0, 0.0]]], [[[0.0, 1.0, 1.0, 1.0]]]],
        &dev,
    )
    .unwrap();
    let weighted = loss(Some(&w), &mut rng);
    assert!(
        (weighted - (0.5 / 2.0 + 4.5 / 3.0) / 2.0).abs() < 1e-6,
        "{weighted}"
    );
    // sampling is the single pass (clamped to [-1, 1])
    let sampler = Sampler::new(&d, SamplerConfig::dpm_solver_pp_2m(8)).unwrap();
    assert_eq!(sampler.levels().len(), 1);
    let x = sampler
        .sample_from(
            &model,
            randn(&mut rng, &[2, 1, 1, 4], &dev).unwrap(),
            None,
            &mut rng,
            |_| {},
        )
        .unwrap();
    let want = out
        .broadcast_as((2, 1, 1, 4))
        .unwrap()
        .clamp(-1f32, 1f32)
        .unwrap();
    assert_eq!(
        x.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        want.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    );
}

/// A network that predicts the flow target from a remembered `(x₀, ε)` pair is scored 0, and any
/// other output by its mean squared error: the flow loss is the MSE to `ε − x₀`.
#[test]
fn rectified_flow_loss_is_the_mse_to_the_velocity() {
    let d = flow();
    let dev = Device::Cpu;
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let x0 = randn(&mut rng, &[3, 2, 2, 4], &dev).unwrap();
    // zero output: loss = E[(ε − x₀)²] over the batch, whatever t is; with the same rng stream
    // the noise is reproduced by drawing the times first (one normal per sample), then ε
    struct Zero;
    impl Denoiser for Zero {
        type Cond = ();
        fn forward(&self, x: &Tensor, _t: &Tensor, _c: Option<&()>) -> candle_core::Result<Tensor> {
            x.zeros_like()
        }
    }
    let mut a = ChaCha8Rng::seed_from_u64(9);
    let got = d
        .training_loss(&Zero, &x0, None, None, &mut a)
        .unwrap()
        .loss
        .to_scalar::<f32>()
        .unwrap() as f64;
    let mut b = ChaCha8Rng::seed_from_u64(9);
    for _ in 0..3 {
        let _: f64 = rand::Rng::sample(&mut b, rand_distr::StandardNormal);
    }
    let eps = randn(&mut b, x0.dims(), &dev).unwrap();
    let want = (eps - &x0)
        .unwrap()
        .sqr()
        .unwrap()
        .mean_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap() as f64;
    assert!((got - want).abs() < 1e-5 * want.max(1.0), "{got} vs {want}");
}
