use super::*;
use crate::noise::randn;
use crate::objective::DiffusionConfig;
use crate::oracle::GaussianOracle;
use crate::prediction::{LossWeighting, Prediction, TimeInput};
use crate::schedule::{NoiseSchedule, ScheduleConfig};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn vec(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

fn rand_vec(seed: u64, n: usize, scale: f32) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    vec(&(randn(&mut rng, &[n], &Device::Cpu).unwrap() * scale as f64).unwrap())
}

fn t(v: &[f32]) -> Tensor {
    Tensor::from_vec(v.to_vec(), (1, 1, 1, v.len()), &Device::Cpu).unwrap()
}

/// Plain-Rust f64 reference of the three update rules, written from the formulas in the papers in
/// terms of ᾱ and σ² = 1 − ᾱ (both given, so the reference itself does not cancel near ᾱ = 1).
mod reference {
    /// (ᾱ, σ²) of a level.
    pub type Ab = (f64, f64);

    /// 1 − ᾱ_t/ᾱ_s = (σ_t² − σ_s²)/ᾱ_s.
    fn beta(t: Ab, s: Ab) -> f64 {
        (t.1 - s.1) / s.0
    }

    pub fn ddpm(xt: f64, x0: f64, t: Ab, s: Ab, posterior: bool, z: f64) -> f64 {
        let b = beta(t, s);
        let mean = s.0.sqrt() * b / t.1 * x0 + (t.0 / s.0).sqrt() * s.1 / t.1 * xt;
        let var = if posterior { b * s.1 / t.1 } else { b };
        mean + var.sqrt() * z
    }

    pub fn ddim(x0: f64, eps: f64, t: Ab, s: Ab, eta: f64, z: f64) -> f64 {
        let sig = eta * (s.1 / t.1 * beta(t, s)).sqrt();
        s.0.sqrt() * x0 + (s.1 - sig * sig).sqrt() * eps + sig * z
    }

    /// DPM-Solver++(2M) with λ = log(α/σ).
    pub fn dpmpp(xt: f64, x0: f64, x0_prev: Option<(f64, f64)>, t: Ab, s: Ab) -> f64 {
        let h = lam(s) - lam(t);
        let d = match x0_prev {
            None => x0,
            Some((prev, h_prev)) => {
                let r = h_prev / h;
                (1.0 + 1.0 / (2.0 * r)) * x0 - 1.0 / (2.0 * r) * prev
            }
        };
        (s.1 / t.1).sqrt() * xt - s.0.sqrt() * ((-h).exp() - 1.0) * d
    }

    pub fn lam(l: Ab) -> f64 {
        0.5 * (l.0 / l.1).ln()
    }
}

fn level_pairs() -> Vec<(NoiseLevel, NoiseLevel)> {
    let lin = NoiseSchedule::new(&ScheduleConfig::ddpm_linear()).unwrap();
    let cos = NoiseSchedule::new(&ScheduleConfig::cosine()).unwrap();
    let con = NoiseSchedule::new(&ScheduleConfig::cosine_logsnr()).unwrap();
    vec![
        (lin.level(1.0), lin.level(0.95)),
        (lin.level(0.5), lin.level(0.499)),
        (lin.level(0.002), lin.level(0.001)),
        (cos.level(1.0), cos.level(0.999)),
        (cos.level(0.3), cos.level(0.2)),
        (con.level(1.0), con.level(0.9)),
        (con.level(0.6), con.level(0.55)),
        (con.level(0.05), con.level(0.0)),
    ]
}

fn rel_close(got: f32, want: f64, what: &str) {
    let tol = 2e-5 * want.abs().max(1.0);
    assert!(
        (got as f64 - want).abs() <= tol,
        "{what}: f32 {got} vs f64 {want}"
    );
}

#[test]
fn one_step_in_f32_matches_f64_reference() -> Result<()> {
    let n = 64;
    let xt = rand_vec(1, n, 1.0);
    let x0 = rand_vec(2, n, 0.8);
    let eps = rand_vec(3, n, 1.0);
    let z = rand_vec(4, n, 1.0);
    for (from, to) in level_pairs() {
        let d = Denoised {
            x0: t(&x0),
            eps: t(&eps),
        };
        let (ab_t, ab_s) = ((from.alpha_bar, from.sigma2), (to.alpha_bar, to.sigma2));
        for (variance, posterior) in [(DdpmVariance::Posterior, true), (DdpmVariance::Beta, false)]
        {
            let got = vec(&ddpm_step(&t(&xt), &d, &from, &to, variance, Some(&t(&z)))?);
            for i in 0..n {
                let want = reference::ddpm(
                    xt[i] as f64,
                    x0[i] as f64,
                    ab_t,
                    ab_s,
                    posterior,
                    z[i] as f64,
                );
                rel_close(got[i], want, &format!("ddpm {variance:?} {from:?}->{to:?}"));
            }
        }
        for eta in [0.0, 0.5, 1.0] {
            let got = vec(&ddim_step(&d, &from, &to, eta, Some(&t(&z)))?);
            for i in 0..n {
                let want =
                    reference::ddim(x0[i] as f64, eps[i] as f64, ab_t, ab_s, eta, z[i] as f64);
                rel_close(got[i], want, &format!("ddim eta={eta} {from:?}->{to:?}"));
            }
        }
        // DPM-Solver++: first-order step, then a second-order step from `to` onwards
        let mut solver = DpmSolverPp2M::default();
        let got = vec(&solver.step(&t(&xt), &t(&x0), &from, &to)?);
        for i in 0..n {
            let want = reference::dpmpp(xt[i] as f64, x0[i] as f64, None, ab_t, ab_s);
            rel_close(got[i], want, &format!("dpm++ 1st {from:?}->{to:?}"));
        }
        let next = NoiseLevel::from_log_snr(
            0.0,
            to.log_snr + 0.7 * (to.log_snr - from.log_snr).max(0.05),
        );
        let x0b = rand_vec(5, n, 0.8);
        let got2 = vec(&solver.step(&t(&got), &t(&x0b), &to, &next)?);
        let h_prev = reference::lam(ab_s) - reference::lam(ab_t);
        for i in 0..n {
            let want = reference::dpmpp(
                got[i] as f64,
                x0b[i] as f64,
                Some((x0[i] as f64, h_prev)),
                ab_s,
                (next.alpha_bar, next.sigma2),
            );
            rel_close(got2[i], want, &format!("dpm++ 2nd {to:?}->{next:?}"));
        }
    }
    Ok(())
}

#[test]
fn final_step_to_clean_returns_the_clean_estimate() -> Result<()> {
    let lin = NoiseSchedule::new(&ScheduleConfig::ddpm_linear()).unwrap();
    let from = lin.level(0.001);
    let d = Denoised {
        x0: t(&[0.25, -0.5]),
        eps: t(&[1.0, 2.0]),
    };
    let z = t(&[5.0, 5.0]);
    for out in [
        ddpm_step(
            &t(&[0.3, 0.1]),
            &d,
            &from,
            &NoiseLevel::CLEAN,
            DdpmVariance::Beta,
            Some(&z),
        )?,
        ddim_step(&d, &from, &NoiseLevel::CLEAN, 1.0, Some(&z))?,
        DpmSolverPp2M::default().step(&t(&[0.3, 0.1]), &d.x0, &from, &NoiseLevel::CLEAN)?,
    ] {
        let v = vec(&out);
        assert!(
            (v[0] - 0.25).abs() < 1e-6 && (v[1] + 0.5).abs() < 1e-6,
            "{v:?}"
        );
    }
    // steps must go towards less noise
    assert!(ddim_step(&d, &NoiseLevel::CLEAN, &from, 0.0, None).is_err());
    assert!(ddim_step(&d, &lin.level(0.1), &lin.level(0.5), 0.0, None).is_err());
    Ok(())
}

fn oracle_setup(schedule: ScheduleConfig, pred: Prediction) -> (Diffusion, GaussianOracle) {
    let diffusion = Diffusion::new(DiffusionConfig {
        schedule,
        prediction: pred,
        time_input: TimeInput::default(),
        loss_weighting: LossWeighting::Uniform,
        objective: Default::default(),
        train_levels: Default::default(),
    })
    .unwrap();
    let oracle = GaussianOracle::new(0.2, 0.5, diffusion.clone()).unwrap();
    (diffusion, oracle)
}

#[test]
fn ddim_eta_one_matches_ddpm_posterior_step_by_step() -> Result<()> {
    let (diffusion, oracle) = oracle_setup(
        ScheduleConfig::Linear {
            num_timesteps: 200,
            beta_start: 1e-4,
            beta_end: 0.04,
        },
        Prediction::Epsilon,
    );
    let mut cfg_ddpm = SamplerConfig::ddpm(200);
    cfg_ddpm.clip_x0 = None;
    let mut cfg_ddim = SamplerConfig::ddim(200, 1.0);
    cfg_ddim.clip_x0 = None;
    let ddpm = Sampler::new(&diffusion, cfg_ddpm)?;
    let ddim = Sampler::new(&diffusion, cfg_ddim)?;
    let shape = [2, 1, 4, 8];
    let x_t = randn(&mut ChaCha8Rng::seed_from_u64(9), &shape, &Device::Cpu)?;
    let mut a = Vec::new();
    let mut b = Vec::new();
    // same seed: both draw one noise tensor per non-final step, so the noise is shared
    let out_a = ddpm.sample_from(
        &oracle,
        x_t.clone(),
        None,
        &mut ChaCha8Rng::seed_from_u64(1),
        |s| a.push(vec(s.x)),
    )?;
    let out_b = ddim.sample_from(&oracle, x_t, None, &mut ChaCha8Rng::seed_from_u64(1), |s| {
        b.push(vec(s.x))
    })?;
    assert_eq!(a.len(), 200);
    assert_eq!(b.len(), 200);
    for (i, (sa, sb)) in a.iter().zip(&b).enumerate() {
        let m = sa
            .iter()
            .zip(sb)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(m < 1e-4, "step {i}: max diff {m}");
    }
    let m = vec(&(&out_a - out_b)?.abs()?)
        .into_iter()
        .fold(0.0f32, f32::max);
    assert!(m < 1e-4);
    // the comparison can fail: DDIM with eta = 0.5 takes a different path from the same noise
    let mut cfg_half = SamplerConfig::ddim(200, 0.5);
    cfg_half.clip_x0 = None;
    let x_t = randn(&mut ChaCha8Rng::seed_from_u64(9), &shape, &Device::Cpu)?;
    let out_c = Sampler::new(&diffusion, cfg_half)?.sample_from(
        &oracle,
        x_t,
        None,
        &mut ChaCha8Rng::seed_from_u64(1),
        |_| {},
    )?;
    let m = vec(&(out_a - out_c)?.abs()?)
        .into_iter()
        .fold(0.0f32, f32::max);
    assert!(m > 1e-2, "{m}");
    Ok(())
}

#[test]
fn repaint_schedule_shapes() -> Result<()> {
    let none = repaint_schedule(
        5,
        &RepaintConfig {
            jump_length: 2,
            jump_n_sample: 1,
        },
    )?;
    assert_eq!(none, vec![5, 4, 3, 2, 1, 0]);
    let s = repaint_schedule(
        6,
        &RepaintConfig {
            jump_length: 2,
            jump_n_sample: 3,
        },
    )?;
    // jump points: 1 and 3 (1 + 2 <= 6, 3 + 2 <= 6; 5 + 2 > 6), each taken twice
    assert_eq!(
        s,
        vec![
            6, 5, 4, 3, 4, 5, 4, 3, 4, 5, 4, 3, 2, 1, 2, 3, 2, 1, 2, 3, 2, 1, 0
        ]
    );
    assert!(s.windows(2).all(|w| w[0].abs_diff(w[1]) == 1));
    // RePaint's published setting: 250 levels, jumps of 10, 10 samples
    let big = repaint_schedule(
        250,
        &RepaintConfig {
            jump_length: 10,
            jump_n_sample: 10,
        },
    )?;
    let down = big.windows(2).filter(|w| w[1] < w[0]).count();
    assert_eq!(down, 250 + 24 * 9 * 10);
    assert!(
        repaint_schedule(
            3,
            &RepaintConfig {
                jump_length: 0,
                jump_n_sample: 1
            }
        )
        .is_err()
    );
    Ok(())
}

#[test]
fn sampler_config_validation() {
    let d = Diffusion::new(DiffusionConfig::default()).unwrap();
    for bad in [
        SamplerConfig::ddim(0, 0.0),
        SamplerConfig::ddim(10, -1.0),
        SamplerConfig {
            guidance_scale: f64::NAN,
            ..SamplerConfig::ddpm(10)
        },
        SamplerConfig {
            clip_x0: Some(0.0),
            ..SamplerConfig::ddpm(10)
        },
    ] {
        assert!(Sampler::new(&d, bad).is_err());
    }
    let s = Sampler::new(&d, SamplerConfig::dpm_solver_pp_2m(12)).unwrap();
    assert_eq!(s.levels().len(), 12);
}

/// Per-element bounds replace the symmetric clip: a denoiser whose every `x̂₀` lies above all of
/// them (the Gaussian oracle of data at 3) is held at each element's own upper bound at every
/// step, and the sample ends on them; with the symmetric clip alone it ends on 1.
#[test]
fn x0_bounds_clamp_each_element_to_its_own_interval() {
    let d = Diffusion::new(DiffusionConfig::default()).unwrap();
    let oracle = GaussianOracle::new(3.0, 0.1, d.clone()).unwrap();
    let lo = t(&[-1.0, 0.0, 0.5, -2.0]);
    let hi = t(&[1.0, 2.0, 0.7, -1.5]);
    for kind in [
        SamplerConfig::ddim(10, 0.0),
        SamplerConfig::dpm_solver_pp_2m(10),
    ] {
        let x_t = t(&rand_vec(7, 4, 1.0));
        let s = Sampler::new(&d, kind.clone())
            .unwrap()
            .with_x0_bounds(lo.clone(), hi.clone());
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut steps = 0;
        let out = s
            .sample_from(&oracle, x_t.clone(), None, &mut rng, |info| {
                assert_eq!(vec(info.x0), vec(&hi), "step {}", info.index);
                steps += 1;
            })
            .unwrap();
        assert_eq!(steps, 10);
        for (a, b) in vec(&out).iter().zip(vec(&hi)) {
            assert!((a - b).abs() < 1e-5, "{:?}: {a} against {b}", kind.kind);
        }
        let plain = Sampler::new(&d, kind.clone()).unwrap();
        let out = plain
            .sample_from(&oracle, x_t, None, &mut rng, |_| {})
            .unwrap();
        assert!(
            vec(&out).iter().all(|v| (v - 1.0).abs() < 1e-5),
            "{:?}",
            kind.kind
        );
    }
}

#[test]
fn sampling_from_a_level_follows_the_gaussians_probability_flow_in_closed_form() -> Result<()> {
    // x₀ ~ N(μ, s²): the probability-flow ODE from level (α, σ) is the monotone linear map
    // x₀ = μ + s·(x_t − α·μ) / √(α²s² + σ²), which a fine deterministic solver must follow
    let (mu, s) = (0.2f64, 0.5f64);
    let (diffusion, oracle) = oracle_setup(ScheduleConfig::cosine_logsnr(), Prediction::V);
    let mut cfg = SamplerConfig::dpm_solver_pp_2m(200);
    cfg.spacing = Spacing::LogSnr;
    cfg.clip_x0 = None;
    let sampler = Sampler::new(&diffusion, cfg)?;
    let shape = [1, 1, 4, 16];
    let x_t = randn(&mut ChaCha8Rng::seed_from_u64(3), &shape, &Device::Cpu)?;
    let xs = vec(&x_t);
    for t0 in [1.0, 0.7, 0.3, 0.05] {
        let start = diffusion.schedule().level(t0);
        let mut steps = 0;
        let got = vec(&sampler.sample_from_level(
            &oracle,
            x_t.clone(),
            start,
            None,
            &mut ChaCha8Rng::seed_from_u64(1),
            |_| steps += 1,
        )?);
        let n_below = sampler.levels().iter().filter(|l| l.t < t0).count();
        assert_eq!(steps, 1 + n_below, "t0 = {t0}");
        let (a, sd) = (start.alpha(), start.sigma());
        let spread = (a * a * s * s + sd * sd).sqrt();
        for (g, x) in got.iter().zip(&xs) {
            let want = mu + s * (*x as f64 - a * mu) / spread;
            assert!(
                (*g as f64 - want).abs() < 2e-3,
                "t0 = {t0}: {g} against {want}"
            );
        }
        // the start level matters: read as pure noise, the same x_t lands elsewhere
        if t0 < 0.5 {
            let as_noise = vec(&sampler.sample_from(
                &oracle,
                x_t.clone(),
                None,
                &mut ChaCha8Rng::seed_from_u64(1),
                |_| {},
            )?);
            let m = as_noise
                .iter()
                .zip(&got)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0f32, f32::max);
            assert!(m > 0.05, "t0 = {t0}: {m}");
        }
    }
    Ok(())
}

#[test]
fn sampling_from_the_first_level_is_sampling_from_noise() -> Result<()> {
    let (diffusion, oracle) = oracle_setup(ScheduleConfig::cosine_logsnr(), Prediction::V);
    // DDPM draws noise at every step: the same draws in the same order give the same bits
    let sampler = Sampler::new(&diffusion, SamplerConfig::ddpm(12))?;
    let x_t = randn(
        &mut ChaCha8Rng::seed_from_u64(5),
        &[2, 1, 4, 8],
        &Device::Cpu,
    )?;
    let a = sampler.sample_from(
        &oracle,
        x_t.clone(),
        None,
        &mut ChaCha8Rng::seed_from_u64(2),
        |_| {},
    )?;
    let first = sampler.levels()[0];
    let b = sampler.sample_from_level(
        &oracle,
        x_t,
        first,
        None,
        &mut ChaCha8Rng::seed_from_u64(2),
        |_| {},
    )?;
    assert_eq!(vec(&a), vec(&b));
    // no clean or out-of-range start, and no start for a process without levels
    let clean = NoiseLevel::CLEAN;
    let x = Tensor::zeros((1, 1, 2, 2), candle_core::DType::F32, &Device::Cpu)?;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let e = sampler
        .sample_from_level(&oracle, x.clone(), clean, None, &mut rng, |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("noisy level"), "{e}");
    let flow = Diffusion::new(DiffusionConfig {
        objective: Objective::rectified_flow(),
        ..DiffusionConfig::default()
    })?;
    let e = Sampler::new(&flow, SamplerConfig::ddim(4, 0.0))?
        .sample_from_level(&oracle, x, first, None, &mut rng, |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("diffusion objective"), "{e}");
    Ok(())
}

#[test]
fn a_sampler_names_its_start_level_in_its_summary() {
    let mut c = SamplerName::Dpm.guided(16, 1.5);
    assert_eq!(c.to_string(), "dpm-solver++(2m) x 16 steps, guidance 1.5");
    c.start_t = Some(0.2);
    assert_eq!(
        c.to_string(),
        "dpm-solver++(2m) x 16 steps, guidance 1.5, from the mean network's scan at t = 0.2"
    );
}
