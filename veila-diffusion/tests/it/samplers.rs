//! Sampler behaviour against analytic answers.

use candle_core::{DType, Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_diffusion::noise::randn;
use veila_diffusion::oracle::GaussianOracle;
use veila_diffusion::{
    Diffusion, DiffusionConfig, LossWeighting, Prediction, RepaintConfig, Sampler, SamplerConfig,
    SamplerKind, ScheduleConfig, Spacing, TimeInput, inpaint,
};

use crate::common::{CondOracle, TinyConfig, TinyNet, all_finite, stats};

const MU: f64 = 0.2;
const STD: f64 = 0.5;

fn diffusion(schedule: ScheduleConfig, prediction: Prediction) -> Diffusion {
    Diffusion::new(DiffusionConfig {
        schedule,
        prediction,
        time_input: TimeInput::default(),
        loss_weighting: LossWeighting::Uniform,
        objective: Default::default(),
        train_levels: Default::default(),
    })
    .unwrap()
}

/// Max error of a deterministic sampler against the exact probability-flow ODE solution.
fn ode_error(d: &Diffusion, cfg: SamplerConfig) -> f64 {
    let oracle = GaussianOracle::new(MU, STD, d.clone()).unwrap();
    let sampler = Sampler::new(d, cfg).unwrap();
    let x_t = randn(
        &mut ChaCha8Rng::seed_from_u64(3),
        &[1, 1, 16, 16],
        &Device::Cpu,
    )
    .unwrap();
    let start = sampler.levels()[0];
    let xs = x_t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let out = sampler
        .sample_from(
            &oracle,
            x_t,
            None,
            &mut ChaCha8Rng::seed_from_u64(0),
            |_| {},
        )
        .unwrap();
    let ys = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    xs.iter()
        .zip(&ys)
        .map(|(&x, &y)| (oracle.pf_ode_solution(x as f64, &start) - y as f64).abs())
        .fold(0.0, f64::max)
}

#[test]
fn deterministic_samplers_converge_to_the_exact_ode_solution() {
    for (sc, pred) in [
        (ScheduleConfig::cosine_logsnr(), Prediction::Epsilon),
        (ScheduleConfig::cosine_logsnr(), Prediction::V),
        (ScheduleConfig::ddpm_linear(), Prediction::Epsilon),
    ] {
        let d = diffusion(sc.clone(), pred);
        let run = |kind: SamplerKind, steps: usize, spacing: Spacing| {
            ode_error(
                &d,
                SamplerConfig {
                    kind,
                    steps,
                    spacing,
                    guidance_scale: 1.0,
                    clip_x0: None,
                    start_t: None,
                },
            )
        };
        let ddim = SamplerKind::Ddim { eta: 0.0 };
        let dpm = SamplerKind::DpmSolverPp2M;
        let e: Vec<(f64, f64)> = [20, 40, 80]
            .iter()
            .map(|&n| (run(ddim, n, Spacing::LogSnr), run(dpm, n, Spacing::LogSnr)))
            .collect();
        eprintln!("{sc:?} {pred:?}: (ddim, dpm++2m) at 20/40/80 steps: {e:?}");
        // DDIM (first order): the error halves with twice the steps
        for w in e.windows(2) {
            let r = w[0].0 / w[1].0;
            assert!((1.7..2.4).contains(&r), "DDIM order: ratio {r}");
        }
        // DPM-Solver++(2M) (second order): at least 3x from 40 to 80 steps, always below DDIM
        let r = e[1].1 / e[2].1;
        assert!(r > 3.0, "DPM-Solver++ order: ratio {r}");
        assert!(
            e.iter().all(|(a, b)| b < a),
            "second order beats first order"
        );
        assert!(e[2].1 < 5e-3, "{}", e[2].1);
        for n in [10, 20] {
            assert!(run(dpm, n, Spacing::Trailing) < run(ddim, n, Spacing::Trailing));
        }
    }
}

#[test]
fn ddpm_samples_the_data_distribution() {
    let d = diffusion(ScheduleConfig::ddpm_linear(), Prediction::Epsilon);
    let oracle = GaussianOracle::new(MU, STD, d.clone()).unwrap();
    let s = Sampler::new(
        &d,
        SamplerConfig {
            clip_x0: None,
            start_t: None,
            ..SamplerConfig::ddpm(250)
        },
    )
    .unwrap();
    let x = s
        .sample(
            &oracle,
            &[1, 1, 64, 64],
            &Device::Cpu,
            None,
            &mut ChaCha8Rng::seed_from_u64(1),
        )
        .unwrap();
    let (m, v) = stats(&x);
    // 4096 samples: the standard error of the mean is 0.5/64 ≈ 0.008
    assert!((m - MU).abs() < 0.03, "mean {m}");
    assert!((v / (STD * STD) - 1.0).abs() < 0.1, "variance {v}");
    // DDIM with eta = 0 is deterministic in x_T: same seed, same result; different seed differs
    let s = Sampler::new(&d, SamplerConfig::ddim(20, 0.0)).unwrap();
    let a = s
        .sample(
            &oracle,
            &[1, 1, 8, 8],
            &Device::Cpu,
            None,
            &mut ChaCha8Rng::seed_from_u64(5),
        )
        .unwrap();
    let b = s
        .sample(
            &oracle,
            &[1, 1, 8, 8],
            &Device::Cpu,
            None,
            &mut ChaCha8Rng::seed_from_u64(5),
        )
        .unwrap();
    let c = s
        .sample(
            &oracle,
            &[1, 1, 8, 8],
            &Device::Cpu,
            None,
            &mut ChaCha8Rng::seed_from_u64(6),
        )
        .unwrap();
    let diff = |p: &Tensor, q: &Tensor| {
        (p - q)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    };
    assert_eq!(diff(&a, &b), 0.0);
    assert!(diff(&a, &c) > 0.1);
}

#[test]
fn full_runs_from_noise_stay_finite_at_the_schedule_extremes() {
    let (net, _vm) = TinyNet::build(
        TinyConfig {
            channels: 3,
            hidden: 8,
            cond_dim: 0,
            pos: None,
        },
        "net",
    );
    let schedules = [
        ScheduleConfig::cosine_logsnr(),
        ScheduleConfig::CosineLogSnr {
            logsnr_min: -30.0,
            logsnr_max: 30.0,
            shift: 0.0,
        },
        ScheduleConfig::cosine(),
        ScheduleConfig::ddpm_linear(),
    ];
    for sc in schedules {
        for pred in [Prediction::Epsilon, Prediction::V, Prediction::Sample] {
            let d = diffusion(sc.clone(), pred);
            for kind in [
                SamplerKind::Ddpm {
                    variance: Default::default(),
                },
                SamplerKind::Ddim { eta: 0.5 },
                SamplerKind::DpmSolverPp2M,
            ] {
                for clip in [None, Some(1.0)] {
                    let cfg = SamplerConfig {
                        kind,
                        steps: 12,
                        spacing: Spacing::Trailing,
                        guidance_scale: 1.0,
                        clip_x0: clip,
                        start_t: None,
                    };
                    let s = Sampler::new(&d, cfg).unwrap();
                    let mut rng = ChaCha8Rng::seed_from_u64(2);
                    let x = s
                        .sample(&net, &[1, 3, 4, 16], &Device::Cpu, None, &mut rng)
                        .unwrap();
                    assert!(all_finite(&x), "{sc:?} {pred:?} {kind:?} clip {clip:?}");
                    if clip.is_some() {
                        let m = x
                            .abs()
                            .unwrap()
                            .max_all()
                            .unwrap()
                            .to_scalar::<f32>()
                            .unwrap();
                        assert!(m <= 1.0 + 1e-5, "clipped x0 bounds the final sample: {m}");
                    }
                }
            }
        }
    }
}

#[test]
fn classifier_free_guidance_extrapolates_the_condition() {
    let d = diffusion(ScheduleConfig::cosine(), Prediction::Epsilon);
    let oracle = CondOracle::new(STD, d.clone());
    let b = 2;
    let cond = Tensor::full(0.3f32, (b, 1, 1, 1), &Device::Cpu).unwrap();
    let shape = [b, 1, 32, 32];
    let run = |scale: f64, cond: &Tensor| {
        let s = Sampler::new(
            &d,
            SamplerConfig {
                guidance_scale: scale,
                clip_x0: None,
                start_t: None,
                ..SamplerConfig::ddim(50, 0.0)
            },
        )
        .unwrap();
        s.sample(
            &oracle,
            &shape,
            &Device::Cpu,
            Some(cond),
            &mut ChaCha8Rng::seed_from_u64(4),
        )
        .unwrap()
    };
    // the guided denoiser of two equal-variance Gaussians is the denoiser of mean u + s(c - u)
    let zero = cond.zeros_like().unwrap();
    for (scale, want_mean) in [(1.0, 0.3), (0.0, 0.0), (2.0, 0.6), (3.0, 0.9)] {
        let x = run(scale, &cond);
        let (m, _) = stats(&x);
        assert!(
            (m - want_mean).abs() < 0.05,
            "scale {scale}: mean {m}, want {want_mean}"
        );
    }
    // scale 0 equals sampling with the null conditioning, exactly up to rounding
    let a = run(0.0, &cond);
    let z = run(1.0, &zero);
    let diff = (a - z)
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    assert!(diff < 1e-4, "{diff}");
    // guidance doubles the network evaluations
    oracle.calls.set(0);
    let _ = run(2.0, &cond);
    assert_eq!(oracle.calls.get(), 100);
    oracle.calls.set(0);
    let _ = run(1.0, &cond);
    assert_eq!(oracle.calls.get(), 50);
}

#[test]
fn inpainting_keeps_known_pixels_and_fills_the_rest() {
    let d = diffusion(ScheduleConfig::cosine(), Prediction::Epsilon);
    let oracle = CondOracle::new(STD, d.clone());
    let cond = Tensor::full(MU as f32, (1, 1, 1, 1), &Device::Cpu).unwrap();
    let (h, w) = (32, 64);
    // known: a constant 0.9 (far from the prior mean) on the left half
    let known = Tensor::full(0.9f32, (1, 2, h, w), &Device::Cpu).unwrap();
    let left: Vec<f32> = (0..h * w)
        .map(|i| if i % w < w / 2 { 1.0 } else { 0.0 })
        .collect();
    let mask = Tensor::from_vec(left, (1, 1, h, w), &Device::Cpu).unwrap();
    for (kind, repaint, expected_calls) in [
        (
            SamplerKind::Ddpm {
                variance: Default::default(),
            },
            RepaintConfig {
                jump_length: 5,
                jump_n_sample: 1,
            },
            40,
        ),
        (
            SamplerKind::Ddim { eta: 0.0 },
            RepaintConfig {
                jump_length: 5,
                jump_n_sample: 3,
            },
            // jump points 1, 6, 11, ..., 31 (31 + 5 <= 40): 7 points, 2 extra passes of 5 steps
            40 + 7 * 2 * 5,
        ),
    ] {
        let s = Sampler::new(
            &d,
            SamplerConfig {
                kind,
                clip_x0: None,
                start_t: None,
                ..SamplerConfig::ddpm(40)
            },
        )
        .unwrap();
        oracle.calls.set(0);
        let x = inpaint(
            &s,
            &oracle,
            &known,
            &mask,
            Some(&cond),
            &repaint,
            &mut ChaCha8Rng::seed_from_u64(8),
        )
        .unwrap();
        assert_eq!(oracle.calls.get(), expected_calls, "{kind:?}");
        let xv = x.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let (mut kept, mut generated) = (Vec::new(), Vec::new());
        for (i, v) in xv.iter().enumerate() {
            if i % w < w / 2 {
                kept.push(*v)
            } else {
                generated.push(*v as f64)
            }
        }
        assert!(
            kept.iter().all(|&v| v == 0.9),
            "known pixels are kept exactly"
        );
        let n = generated.len() as f64;
        let m = generated.iter().sum::<f64>() / n;
        let var = generated.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n;
        assert!((m - MU).abs() < 0.05, "{kind:?}: generated mean {m}");
        if matches!(kind, SamplerKind::Ddpm { .. }) {
            assert!(
                (var / (STD * STD) - 1.0).abs() < 0.15,
                "generated variance {var}"
            );
        }
    }
    // a multistep solver cannot jump
    let s = Sampler::new(&d, SamplerConfig::dpm_solver_pp_2m(10)).unwrap();
    assert!(
        inpaint(
            &s,
            &oracle,
            &known,
            &mask,
            Some(&cond),
            &RepaintConfig::default(),
            &mut ChaCha8Rng::seed_from_u64(0)
        )
        .is_err()
    );
    // a mask that cannot broadcast is an error
    let bad = Tensor::ones((1, 1, 3, 3), DType::F32, &Device::Cpu).unwrap();
    let s = Sampler::new(&d, SamplerConfig::ddpm(5)).unwrap();
    assert!(
        inpaint(
            &s,
            &oracle,
            &known,
            &bad,
            Some(&cond),
            &RepaintConfig::default(),
            &mut ChaCha8Rng::seed_from_u64(0)
        )
        .is_err()
    );
}

/// With the exact denoiser of a finite data set, every sampler must end on the data points
/// themselves (not on their mean, which the noisiest steps predict) and reach every one of them.
#[test]
fn samplers_end_on_the_points_of_a_finite_data_set() {
    use veila_diffusion::oracle::EmpiricalOracle;
    const K: usize = 4;
    const D: usize = 32;
    let points: Vec<Vec<f64>> = (0..K)
        .map(|k| {
            let x = randn(
                &mut ChaCha8Rng::seed_from_u64(100 + k as u64),
                &[D],
                &Device::Cpu,
            );
            let v = x.unwrap().to_vec1::<f32>().unwrap();
            v.iter().map(|&e| 0.5 * e as f64).collect()
        })
        .collect();
    let centre: Vec<f64> = (0..D)
        .map(|i| points.iter().map(|p| p[i]).sum::<f64>() / K as f64)
        .collect();
    let rms = |a: &[f64], b: &[f64]| {
        (a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / D as f64).sqrt()
    };
    let centre_to_points = points
        .iter()
        .map(|p| rms(p, &centre))
        .fold(f64::INFINITY, f64::min);
    assert!(
        centre_to_points > 0.2,
        "the points' mean must lie away from them"
    );
    for pred in [Prediction::Epsilon, Prediction::V] {
        let d = diffusion(ScheduleConfig::cosine_logsnr(), pred);
        let oracle = EmpiricalOracle::new(points.clone(), d.clone()).unwrap();
        for (kind, steps) in [
            (
                SamplerKind::Ddpm {
                    variance: Default::default(),
                },
                100,
            ),
            (SamplerKind::Ddim { eta: 0.0 }, 50),
            (SamplerKind::DpmSolverPp2M, 25),
        ] {
            let cfg = SamplerConfig {
                kind,
                steps,
                spacing: Spacing::default(),
                guidance_scale: 1.0,
                clip_x0: None,
                start_t: None,
            };
            let sampler = Sampler::new(&d, cfg).unwrap();
            let x = sampler
                .sample(
                    &oracle,
                    &[24, 1, 4, 8],
                    &Device::Cpu,
                    None,
                    &mut ChaCha8Rng::seed_from_u64(5),
                )
                .unwrap();
            let xs = x.to_dtype(DType::F64).unwrap().flatten_all().unwrap();
            let xs = xs.to_vec1::<f64>().unwrap();
            let mut hits = [0usize; K];
            let mut worst: f64 = 0.0;
            for s in xs.chunks(D) {
                let (k, e) = points
                    .iter()
                    .enumerate()
                    .map(|(k, p)| (k, rms(s, p)))
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .unwrap();
                hits[k] += 1;
                worst = worst.max(e);
            }
            eprintln!("{pred:?} {kind:?} x{steps}: worst distance {worst:.2e}, hits {hits:?}");
            assert!(
                worst < 1e-2 * centre_to_points,
                "{pred:?} {kind:?}: {worst}"
            );
            assert!(
                hits.iter().all(|&h| h > 0),
                "{pred:?} {kind:?}: modes {hits:?}"
            );
        }
    }
}
