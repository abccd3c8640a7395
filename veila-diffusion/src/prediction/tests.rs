use super::*;
use candle_core::{Device, Tensor};
use rand::SeedableRng;

fn rand_t(seed: u64) -> Tensor {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    crate::noise::randn(&mut rng, &[3, 2, 4, 5], &Device::Cpu).unwrap()
}

fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

fn coeffs(log_snrs: &[f64]) -> (Tensor, Tensor) {
    let a: Vec<f32> = log_snrs
        .iter()
        .map(|&l| NoiseLevel::from_log_snr(0.0, l).alpha() as f32)
        .collect();
    let s: Vec<f32> = log_snrs
        .iter()
        .map(|&l| NoiseLevel::from_log_snr(0.0, l).sigma() as f32)
        .collect();
    (
        Tensor::from_vec(a, (3, 1, 1, 1), &Device::Cpu).unwrap(),
        Tensor::from_vec(s, (3, 1, 1, 1), &Device::Cpu).unwrap(),
    )
}

#[test]
fn conversions_are_mutually_consistent() {
    let x0 = rand_t(1);
    let eps = rand_t(2);
    let (a, s) = coeffs(&[-6.0, 0.3, 6.0]);
    let x_t = (x0.broadcast_mul(&a).unwrap() + eps.broadcast_mul(&s).unwrap()).unwrap();
    let v = v_from_x0_eps(&x0, &eps, &a, &s).unwrap();
    assert!(
        max_diff(&x0_from_eps(&x_t, &eps, &a, &s).unwrap(), &x0) < 2e-3,
        "x0 from eps"
    );
    assert!(
        max_diff(&eps_from_x0(&x_t, &x0, &a, &s).unwrap(), &eps) < 2e-3,
        "eps from x0"
    );
    assert!(
        max_diff(&eps_from_v(&x_t, &v, &a, &s).unwrap(), &eps) < 1e-5,
        "eps from v"
    );
    assert!(
        max_diff(&x0_from_v(&x_t, &v, &a, &s).unwrap(), &x0) < 1e-5,
        "x0 from v"
    );
    for p in [Prediction::Epsilon, Prediction::V, Prediction::Sample] {
        let target = p.target(&x0, &eps, &a, &s).unwrap();
        let want = match p {
            Prediction::Epsilon => &eps,
            Prediction::V => &v,
            Prediction::Sample => &x0,
        };
        assert!(max_diff(&target, want) < 1e-6);
        // the exact target converts back to the true x0 and eps
        assert!(
            max_diff(&p.x0_from_output(&x_t, &target, &a, &s).unwrap(), &x0) < 2e-3,
            "{p:?}"
        );
        assert!(
            max_diff(&p.eps_from_output(&x_t, &target, &a, &s).unwrap(), &eps) < 2e-3,
            "{p:?}"
        );
    }
}

#[test]
fn v_definition_matches_elementwise_reference() {
    let x0 = rand_t(3);
    let eps = rand_t(4);
    let (a, s) = coeffs(&[1.0, -2.0, 0.0]);
    let v = v_from_x0_eps(&x0, &eps, &a, &s)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let x0v = x0.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let ev = eps.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let per = 2 * 4 * 5;
    for (i, vi) in v.iter().enumerate() {
        let l = NoiseLevel::from_log_snr(0.0, [1.0, -2.0, 0.0][i / per]);
        let want = l.alpha() * ev[i] as f64 - l.sigma() * x0v[i] as f64;
        assert!((*vi as f64 - want).abs() < 1e-6);
    }
}

#[test]
fn min_snr_weights_match_their_definition() {
    let gamma = 5.0;
    let w = LossWeighting::MinSnr { gamma };
    for l in [
        -20.0,
        -3.0,
        0.0,
        1.0,
        gamma.ln() - 1e-9,
        gamma.ln() + 1e-9,
        2.0,
        8.0,
        20.0,
    ] {
        let lv = NoiseLevel::from_log_snr(0.5, l);
        let snr = l.exp();
        let m = snr.min(gamma);
        let cases = [
            (Prediction::Epsilon, m / snr),
            (Prediction::V, m / (snr + 1.0)),
            (Prediction::Sample, m),
        ];
        for (p, want) in cases {
            let got = w.weight(&lv, p);
            assert!(got.is_finite() && got > 0.0);
            assert!(
                (got - want).abs() <= 1e-12 * want.max(1e-300),
                "{p:?} at λ={l}: {got} vs {want}"
            );
        }
        assert_eq!(LossWeighting::Uniform.weight(&lv, Prediction::V), 1.0);
    }
}

#[test]
fn time_input_round_trips() {
    use crate::schedule::ScheduleConfig;
    let d = NoiseSchedule::new(&ScheduleConfig::cosine()).unwrap();
    let c = NoiseSchedule::new(&ScheduleConfig::cosine_logsnr()).unwrap();
    for ti in [
        TimeInput::Unit,
        TimeInput::Scaled { scale: 1000.0 },
        TimeInput::LogSnr,
    ] {
        for sch in [&d, &c] {
            for t in [0.001, 0.25, 0.731, 1.0] {
                let l = sch.level(t);
                let back = ti.level(ti.value(&l), sch);
                assert!((back.log_snr - l.log_snr).abs() < 1e-9, "{ti:?} t={t}");
            }
        }
    }
}
