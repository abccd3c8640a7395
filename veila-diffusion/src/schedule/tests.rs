use super::*;

#[test]
fn linear_alpha_bar_is_the_product_of_one_minus_beta() {
    let s = DiscreteSchedule::linear(1000, 1e-4, 0.02).unwrap();
    assert_eq!(s.num_timesteps(), 1000);
    assert!((s.betas()[0] - 1e-4).abs() < 1e-15);
    assert!((s.betas()[999] - 0.02).abs() < 1e-15);
    assert!((s.betas()[500] - (1e-4 + (0.02 - 1e-4) * 500.0 / 999.0)).abs() < 1e-15);
    let mut prod = 1.0f64;
    for k in 1..=1000 {
        prod *= 1.0 - s.betas()[k - 1];
        let l = s.level_at_index(k);
        assert!(
            (l.alpha_bar - prod).abs() <= 1e-12 * prod.max(1e-300),
            "k={k}"
        );
        assert!((l.alpha_bar + l.sigma2 - 1.0).abs() < 1e-14);
    }
    // DDPM's known value: alpha_bar_T ~ 4.04e-5
    assert!((s.level_at_index(1000).alpha_bar - 4.0358e-5).abs() < 1e-8);
}

#[test]
fn cosine_schedule_follows_closed_form_with_float_division() {
    let t_total = 1000usize;
    let sch = DiscreteSchedule::cosine(t_total, 0.008, 0.999).unwrap();
    let f = |k: f64| {
        (((k / t_total as f64) + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2)
            .cos()
            .powi(2)
    };
    for k in [1usize, 2, 10, 100, 500, 900, 990] {
        let want = f(k as f64) / f(0.0);
        let got = sch.level_at_index(k).alpha_bar;
        assert!((got - want).abs() <= 1e-10 * want, "k={k}: {got} vs {want}");
    }
    let b = sch.betas();
    // candle-transformers' integer-division bug gives [0, ..., 0, 0.999]: not here
    assert!(b[0] > 1e-5 && b[0] < 1e-4, "beta_1 = {}", b[0]);
    assert!(b[500] > 1e-3 && b[500] < 1e-2, "beta_501 = {}", b[500]);
    assert_eq!(b[t_total - 1], 0.999, "last beta is clipped");
    assert!(b.iter().all(|&x| x > 0.0 && x < 1.0));
    assert!(b.windows(2).all(|w| w[1] >= w[0]), "cosine betas increase");
}

#[test]
fn discrete_ends_never_divide_by_zero_or_one() {
    for sch in [
        NoiseSchedule::new(&ScheduleConfig::ddpm_linear()).unwrap(),
        NoiseSchedule::new(&ScheduleConfig::cosine()).unwrap(),
    ] {
        let t_total = sch.num_timesteps().unwrap();
        let first = sch.level(1.0 / t_total as f64);
        let last = sch.level(1.0);
        for l in [first, last] {
            assert!(l.alpha_bar > 0.0 && l.alpha_bar < 1.0, "{l:?}");
            assert!(l.sigma2 > 0.0 && l.sigma2 < 1.0, "{l:?}");
            assert!(l.log_snr.is_finite());
            // as f32 too (the tensors the samplers build)
            assert!(l.alpha() as f32 > 0.0 && l.sigma() as f32 > 0.0);
            // eps -> x0 -> eps at this level stays finite
            let (a, s) = (l.alpha(), l.sigma());
            let x0 = (0.5 - s * 0.3) / a;
            assert!(x0.is_finite() && ((0.5 - a * x0) / s).is_finite());
        }
        // first step: sigma^2 = beta_1 computed without cancellation
        let b1 = match &sch {
            NoiseSchedule::Discrete(d) => d.betas()[0],
            _ => unreachable!(),
        };
        assert!((first.sigma2 - b1).abs() < 1e-15 * b1.max(1e-4) * 1e3);
        assert!(sch.level(0.0).is_clean());
        assert_eq!(
            sch.level(f64::NAN),
            last,
            "NaN time is treated as the noisiest level"
        );
    }
}

#[test]
fn continuous_log_snr_hits_its_clipped_ends() {
    let c = CosineLogSnr::new(-20.0, 20.0, 0.0).unwrap();
    assert!((c.log_snr(0.0) - 20.0).abs() < 1e-9);
    assert!((c.log_snr(1.0) + 20.0).abs() < 1e-9);
    assert!(
        (c.log_snr(0.5)).abs() < 1e-9,
        "symmetric clipping puts lambda = 0 at t = 0.5"
    );
    assert_eq!(c.log_snr(-3.0), c.log_snr(0.0));
    assert_eq!(c.log_snr(7.0), c.log_snr(1.0));
    let mut prev = f64::INFINITY;
    for i in 0..=1000 {
        let t = i as f64 / 1000.0;
        let l = c.log_snr(t);
        assert!(l < prev, "strictly decreasing at t = {t}");
        prev = l;
        let back = c.time_of_log_snr(l);
        assert!((back - t).abs() < 1e-9, "inverse at t = {t}: {back}");
    }
    // unclipped cosine: lambda = -2 log tan(pi t / 2)
    let wide = CosineLogSnr::new(-1e3, 1e3, 0.0).unwrap();
    for t in [0.1, 0.3, 0.7, 0.9] {
        let want = -2.0 * (std::f64::consts::FRAC_PI_2 * t).tan().ln();
        assert!((wide.log_snr(t) - want).abs() < 1e-9);
    }
    let shifted = CosineLogSnr::new(-20.0, 20.0, -1.5).unwrap();
    assert!((shifted.log_snr(0.3) - (c.log_snr(0.3) - 1.5)).abs() < 1e-12);
    assert!((shifted.time_of_log_snr(shifted.log_snr(0.3)) - 0.3).abs() < 1e-9);
}

#[test]
fn continuous_extremes_are_finite_and_strictly_inside_zero_one() {
    let sch = NoiseSchedule::new(&ScheduleConfig::cosine_logsnr()).unwrap();
    for t in [0.0, 1e-12, 0.5, 1.0 - 1e-12, 1.0] {
        let l = sch.level(t);
        assert!(l.alpha_bar > 0.0 && l.alpha_bar < 1.0, "t={t}: {l:?}");
        assert!(l.sigma2 > 0.0 && l.sigma2 < 1.0, "t={t}: {l:?}");
        assert!((l.alpha_bar + l.sigma2 - 1.0).abs() < 1e-15);
        assert!(
            l.alpha() as f32 > 0.0 && l.sigma() as f32 > 0.0,
            "f32 alpha and sigma stay positive"
        );
    }
    // sigma at t = 0 is sqrt(sigmoid(-20)) = 4.54e-5, not 0, even though 1 - alpha_bar underflows in f32
    let l0 = sch.level(0.0);
    let want = (1.0 / (1.0 + 20f64.exp())).sqrt();
    assert!((l0.sigma() - want).abs() < 1e-15);
    assert_eq!(
        1.0f32 - l0.alpha_bar as f32,
        0.0,
        "the f32 difference would have been 0"
    );
}

#[test]
fn noise_level_from_extreme_log_snr_is_finite() {
    for l in [-800.0, -40.0, -1e-9, 0.0, 1e-9, 40.0, 800.0] {
        let n = NoiseLevel::from_log_snr(0.5, l);
        assert!(n.alpha_bar.is_finite() && n.sigma2.is_finite(), "{n:?}");
        assert!((0.0..=1.0).contains(&n.alpha_bar) && (0.0..=1.0).contains(&n.sigma2));
        assert!(n.log_alpha_bar().is_finite() && n.log_alpha_bar() <= 0.0);
    }
    let n = NoiseLevel::from_log_snr(0.5, 40.0);
    assert!(
        (n.sigma2 - (-40f64).exp()).abs() < 1e-30,
        "sigma^2 accurate far below f64 epsilon"
    );
    assert_eq!(NoiseLevel::CLEAN.log_alpha_bar(), 0.0);
    // log alpha-bar through log-SNR agrees with the discrete cumulative sum
    let d = DiscreteSchedule::cosine(1000, 0.008, 0.999).unwrap();
    for k in [1, 10, 500, 999, 1000] {
        let l = d.level_at_index(k);
        assert!(
            (l.log_alpha_bar() - l.alpha_bar.ln()).abs() < 1e-9 * l.alpha_bar.ln().abs().max(1e-9)
        );
    }
}

#[test]
fn sampling_levels_spacings() {
    let sch = NoiseSchedule::new(&ScheduleConfig::ddpm_linear()).unwrap();
    let idx = |v: Vec<NoiseLevel>| {
        v.iter()
            .map(|l| (l.t * 1000.0).round() as usize)
            .collect::<Vec<_>>()
    };
    assert_eq!(
        idx(sch.sampling_levels(4, Spacing::Trailing).unwrap()),
        vec![1000, 750, 500, 250]
    );
    assert_eq!(
        idx(sch.sampling_levels(4, Spacing::Leading).unwrap()),
        vec![751, 501, 251, 1]
    );
    assert_eq!(
        idx(sch.sampling_levels(4, Spacing::Linspace).unwrap()),
        vec![1000, 667, 334, 1]
    );
    assert_eq!(
        sch.sampling_levels(1000, Spacing::Trailing).unwrap().len(),
        1000
    );
    let all = idx(sch.sampling_levels(1000, Spacing::Trailing).unwrap());
    assert_eq!(all, (1..=1000).rev().collect::<Vec<_>>());
    assert!(sch.sampling_levels(1001, Spacing::Trailing).is_err());
    assert!(sch.sampling_levels(0, Spacing::Trailing).is_err());
    let ls = sch.sampling_levels(10, Spacing::LogSnr).unwrap();
    assert!(ls.windows(2).all(|w| w[1].log_snr > w[0].log_snr));
    assert_eq!(idx(vec![ls[0]]), vec![1000]);
    // roughly uniform in log-SNR
    let gaps: Vec<f64> = ls.windows(2).map(|w| w[1].log_snr - w[0].log_snr).collect();
    let mean = gaps.iter().sum::<f64>() / gaps.len() as f64;
    assert!(
        gaps.iter().all(|g| (g - mean).abs() < 0.2 * mean),
        "{gaps:?}"
    );

    let c = NoiseSchedule::new(&ScheduleConfig::cosine_logsnr()).unwrap();
    let lv = c.sampling_levels(5, Spacing::Trailing).unwrap();
    let ts: Vec<f64> = lv.iter().map(|l| l.t).collect();
    for (t, want) in ts.iter().zip([1.0, 0.8, 0.6, 0.4, 0.2]) {
        assert!((t - want).abs() < 1e-12, "{ts:?}");
    }
    let lv = c.sampling_levels(5, Spacing::LogSnr).unwrap();
    assert!((lv[0].log_snr + 20.0).abs() < 1e-9);
    let gaps: Vec<f64> = lv.windows(2).map(|w| w[1].log_snr - w[0].log_snr).collect();
    assert!(gaps.iter().all(|g| (g - gaps[0]).abs() < 1e-6), "{gaps:?}");
}

#[test]
fn level_of_log_snr_picks_nearest_grid_point() {
    let sch = NoiseSchedule::new(&ScheduleConfig::cosine()).unwrap();
    let NoiseSchedule::Discrete(d) = &sch else {
        unreachable!()
    };
    for k in [1usize, 2, 37, 500, 999, 1000] {
        let l = d.level_at_index(k);
        assert_eq!(sch.level_of_log_snr(l.log_snr), l);
        assert_eq!(sch.level_of_log_snr(l.log_snr + 1e-9), l);
    }
    assert_eq!(sch.level_of_log_snr(1e9), d.level_at_index(1));
    assert_eq!(sch.level_of_log_snr(-1e9), d.level_at_index(1000));
}

#[test]
fn bad_configs_are_rejected() {
    for cfg in [
        ScheduleConfig::Linear {
            num_timesteps: 0,
            beta_start: 1e-4,
            beta_end: 0.02,
        },
        ScheduleConfig::Linear {
            num_timesteps: 10,
            beta_start: 0.0,
            beta_end: 0.02,
        },
        ScheduleConfig::Linear {
            num_timesteps: 10,
            beta_start: 1e-4,
            beta_end: 1.0,
        },
        ScheduleConfig::Cosine {
            num_timesteps: 10,
            s: 0.008,
            max_beta: 1.0,
        },
        ScheduleConfig::CosineLogSnr {
            logsnr_min: 5.0,
            logsnr_max: -5.0,
            shift: 0.0,
        },
        ScheduleConfig::CosineLogSnr {
            logsnr_min: f64::NEG_INFINITY,
            logsnr_max: 5.0,
            shift: 0.0,
        },
    ] {
        assert!(NoiseSchedule::new(&cfg).is_err(), "{cfg:?}");
    }
}

#[test]
fn training_levels_cover_the_grid() {
    use rand::SeedableRng;
    let sch = NoiseSchedule::new(&ScheduleConfig::Linear {
        num_timesteps: 10,
        beta_start: 1e-4,
        beta_end: 0.02,
    })
    .unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut seen = [0usize; 11];
    for _ in 0..2000 {
        let l = sch.sample_train_level(&mut rng);
        seen[(l.t * 10.0).round() as usize] += 1;
    }
    assert_eq!(seen[0], 0, "never trains on clean data");
    assert!(seen[1..].iter().all(|&c| c > 150), "{seen:?}");
}

/// Every spacing's name parses back to it, matches its serialized name (one spelling in
/// bundles and on command lines), and an unknown name is refused with the list.
#[test]
fn spacing_names_round_trip_and_match_serde() {
    for s in Spacing::ALL {
        assert_eq!(s.as_str().parse::<Spacing>().unwrap(), s);
        assert_eq!(
            serde_json::to_string(&s).unwrap(),
            format!("\"{}\"", s.as_str())
        );
    }
    let err = "log-snr".parse::<Spacing>().unwrap_err().to_string();
    assert!(err.contains("log_snr"), "{err}");
}

/// Uniform time stays the exact stream it always was (runs resume to the same draws); a clean
/// share puts that share of the draws uniformly in its log-SNR range, and the rest where uniform
/// time puts them: the share above `λ = 6` is `share + (1 − share)·t(6)` (closed form on the
/// cosine schedule, `λ ≥ 6` exactly when `t ≤ t(6)`).
#[test]
fn clean_share_draws_its_share_uniformly_in_log_snr() {
    use rand::SeedableRng;
    let sch = NoiseSchedule::new(&ScheduleConfig::cosine_logsnr()).unwrap();
    let rng = || rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let (mut a, mut b) = (rng(), rng());
    for _ in 0..100 {
        assert_eq!(
            TrainLevels::UniformTime.draw(&sch, &mut a),
            sch.sample_train_level(&mut b)
        );
    }
    let n = 40_000;
    let draws = |levels: TrainLevels| -> Vec<f64> {
        let mut r = rng();
        (0..n).map(|_| levels.draw(&sch, &mut r).log_snr).collect()
    };
    // all at the clean levels: inside the range, uniform (its mean and quartiles)
    let mut all = draws(TrainLevels::clean_share(1.0));
    assert!(all.iter().all(|l| (6.0 - 1e-9..=18.0 + 1e-9).contains(l)));
    all.sort_by(f64::total_cmp);
    let mean = all.iter().sum::<f64>() / n as f64;
    // the standard error of a uniform's mean over a width of 12 is 12 / sqrt(12 n)
    assert!(
        (mean - 12.0).abs() < 4.0 * 12.0 / (12.0 * n as f64).sqrt(),
        "{mean}"
    );
    for (q, want) in [(0.25, 9.0), (0.5, 12.0), (0.75, 15.0)] {
        let got = all[(q * n as f64) as usize];
        assert!((got - want).abs() < 0.15, "quantile {q}: {got}");
    }
    // a quarter: the share above λ = 6 against its closed form
    let t6 = match &sch {
        NoiseSchedule::Continuous(c) => c.time_of_log_snr(6.0),
        NoiseSchedule::Discrete(_) => unreachable!(),
    };
    let want = 0.25 + 0.75 * t6;
    let got = draws(TrainLevels::clean_share(0.25))
        .iter()
        .filter(|&&l| l >= 6.0)
        .count() as f64
        / n as f64;
    let se = (want * (1.0 - want) / n as f64).sqrt();
    assert!((got - want).abs() < 4.0 * se, "{got} against {want}");
    // uniform time alone puts about 1 draw in 200 above λ = 10
    let above_10 = match &sch {
        NoiseSchedule::Continuous(c) => c.time_of_log_snr(10.0),
        NoiseSchedule::Discrete(_) => unreachable!(),
    };
    assert!((0.003..0.007).contains(&above_10), "{above_10}");
}

#[test]
fn bad_clean_shares_are_refused_and_the_default_is_left_out_of_a_config() {
    for bad in [
        TrainLevels::clean_share(1.5),
        TrainLevels::clean_share(f64::NAN),
        TrainLevels::CleanShare {
            share: 0.5,
            log_snr_min: 10.0,
            log_snr_max: 10.0,
        },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
        let cfg = crate::DiffusionConfig {
            train_levels: bad,
            ..Default::default()
        };
        assert!(crate::Diffusion::new(cfg).is_err());
    }
    let plain = serde_json::to_value(crate::DiffusionConfig::default()).unwrap();
    assert!(plain.get("train_levels").is_none(), "{plain}");
    let cfg = crate::DiffusionConfig {
        train_levels: TrainLevels::clean_share(0.25),
        ..Default::default()
    };
    let json = serde_json::to_string(&cfg).unwrap();
    assert_eq!(
        serde_json::from_str::<crate::DiffusionConfig>(&json).unwrap(),
        cfg
    );
}
