//! Weather physics against closed forms, brute-force references written here, and the published values
//! of the reference implementations (numbers quoted in /work/shared/reference/weather-physics.md).

use glam::Vec3;
use image::RgbImage;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_data::PointCloud;
use veila_data::weather::camera::{linear_to_srgb, srgb_to_linear};
use veila_data::weather::fog::{
    FogTable, FogTableConfig, PulseModel, SPEED_OF_LIGHT_M_S, backscatter_integral_direct,
};
use veila_data::weather::rain::{RainConfig, RainOutcome, rain_point};
use veila_data::weather::snow::{
    Flake, SnowConfig, SnowField, SnowOutcome, occlusion_ratios, snow_point, waveform_peak,
};
use veila_data::weather::spec::{
    exponential_dsd_alpha_per_m, marshall_gunn, marshall_palmer, snow_equivalent_rain_rate_mm_h,
    snow_occupancy,
};
use veila_data::weather::wet::{GroundPlane, fit_ground_plane, fresnel};
use veila_data::weather::{
    BeamTable, CameraEffect, CameraInput, DepthMap, Intrinsics, LidarEffect, LidarInput,
    PointOrigin, Preset, Sensor, TimeOfDay, Weather, WeatherConfig, WeatherSim,
};

/// Brute-force backscatter integral (midpoint rule in t, written independently of the library).
fn brute_integral(alpha: f64, r: f64, r0: f64, n: usize) -> f64 {
    let tau = 20e-9;
    let dt = 2.0 * tau / n as f64;
    let mut acc = 0.0;
    for k in 0..n {
        let t = (k as f64 + 0.5) * dt;
        let rr = r - SPEED_OF_LIGHT_M_S * t / 2.0;
        if rr <= 0.9 || rr > r0 {
            continue;
        }
        let xi = ((rr - 0.9) / 0.1).min(1.0);
        let s = (std::f64::consts::PI * t / (2.0 * tau)).sin();
        acc += s * s * (-2.0 * alpha * rr).exp() * xi / (rr * rr) * dt;
    }
    acc
}

/// Brute-force peak over R (receiver range up to R0, as in the published tables).
fn brute_peak(alpha: f64, r0: f64) -> (f64, f64) {
    let hi = r0.min(12.0);
    let mut best = (0.0, 0.0);
    let mut r = 0.9;
    while r <= hi + 1e-12 {
        let v = brute_integral(alpha, r, r0, 2000);
        if v > best.1 {
            best = (r, v);
        }
        r += 0.005;
    }
    best
}

#[test]
fn fog_table_matches_direct_integration() {
    for alpha in [0.005, 0.06, 0.2] {
        let t = FogTable::new(alpha, &FogTableConfig::default()).unwrap();
        let mut worst: f64 = 0.0;
        for r0 in [1.05, 1.5, 2.77, 3.3, 4.4, 4.6, 8.0, 150.0] {
            let (rt, it) = t.lookup(r0);
            let (rb, ib) = brute_peak(alpha, r0);
            // relative to the saturated strength (the scale of every fog return), and relative to the
            // value itself away from the steep onset just above r1 = 0.9 m
            let rel_sat = (it - ib).abs() / t.saturated().1;
            worst = worst.max(rel_sat);
            assert!(
                rel_sat < 1e-3,
                "alpha {alpha} r0 {r0}: table {it:e} brute {ib:e}"
            );
            if r0 >= 1.5 {
                assert!(
                    (it - ib).abs() / ib < 2e-3,
                    "alpha {alpha} r0 {r0}: table {it:e} brute {ib:e}"
                );
            }
            assert!(
                (rt - rb).abs() < 0.03,
                "alpha {alpha} r0 {r0}: R_fog table {rt} brute {rb}"
            );
        }
        // the library's Simpson reference agrees with the midpoint brute force
        let a =
            backscatter_integral_direct(alpha, 4.6, f64::INFINITY, &PulseModel::default(), 20000);
        let b = brute_integral(alpha, 4.6, f64::INFINITY, 20000);
        assert!((a - b).abs() / b < 1e-5);
        eprintln!("alpha {alpha}: worst table error / I_sat {worst:.2e}");
    }
}

#[test]
fn fog_table_reproduces_the_published_lookup_tables() {
    // saturated I_int of Hahner et al.'s pickles (alpha -> s m^-2), and 3.8155e-9 at R = 4.602 for 0.06
    let published = [
        (0.005, 4.568e-9),
        (0.01, 4.493e-9),
        (0.02, 4.347e-9),
        (0.03, 4.206e-9),
        (0.06, 3.816e-9),
        (0.1, 3.362e-9),
        (0.12, 3.158e-9),
        (0.15, 2.879e-9),
        (0.2, 2.476e-9),
    ];
    for (alpha, want) in published {
        let t = FogTable::new(alpha, &FogTableConfig::default()).unwrap();
        let (r, i) = t.lookup(30.0);
        // the pickles searched R on a 0.1 m grid, so they can only be at or below the true peak
        assert!(
            i >= want * 0.999 && i <= want * 1.004,
            "alpha {alpha}: {i:e} vs {want:e}"
        );
        assert!((4.4..4.8).contains(&r), "alpha {alpha}: R_fog {r}");
    }
    let v = brute_integral(0.06, 4.602, 30.0, 20000);
    assert!((v - 3.8155e-9).abs() / 3.8155e-9 < 1e-3, "{v:e}");
    // below saturation the published R_fog is R0 - 0.1 (grid) and no return exists for R0 <= 1 m
    let t = FogTable::new(0.06, &FogTableConfig::default()).unwrap();
    assert_eq!(t.lookup(0.8), (0.0, 0.0));
    let (r, _) = t.lookup(3.0);
    assert!((r - 3.0).abs() < 0.011, "{r}");
}

#[test]
fn fog_hard_returns_follow_exp_minus_two_alpha_r_exactly() {
    let vis = 80.0;
    let alpha = 20f64.ln() / vis;
    let pts: Vec<Vec3> = (0..200)
        .map(|k| Vec3::new(2.0 + k as f32 * 0.5, 0.3, -0.5))
        .collect();
    let c = PointCloud {
        xyz: pts.clone(),
        intensity: vec![0.37; pts.len()],
        ring: None,
        label: None,
    };
    let w = Weather {
        fog_visibility_m: Some(vis),
        seed: 1,
        ..Weather::clear()
    };
    let out = WeatherSim::new(&w, &WeatherConfig::default())
        .unwrap()
        .apply_lidar(LidarInput::new(&c))
        .unwrap();
    let mut hard = 0;
    let mut fog = 0;
    for k in 0..pts.len() {
        let r = pts[k].as_dvec3().length();
        match out.origin[k] {
            PointOrigin::Target => {
                hard += 1;
                assert_eq!(out.cloud.xyz[k], pts[k]);
                assert_eq!(
                    out.cloud.intensity[k],
                    (0.37f32 as f64 * (-2.0 * alpha * r).exp()) as f32
                );
            }
            PointOrigin::Fog => {
                fog += 1;
                let nr = out.cloud.xyz[k].as_dvec3().length();
                assert!(nr < r && nr > 1.0, "{nr}");
                // the fog return is stronger than the attenuated hard target would have been
                assert!(out.cloud.intensity[k] as f64 > 0.37 * (-2.0 * alpha * r).exp());
            }
            o => panic!("{o:?}"),
        }
    }
    // near points keep their hard return, far ones become fog returns
    assert!(hard > 10 && fog > 10, "hard {hard} fog {fog}");
    assert_eq!(out.origin[0], PointOrigin::Target);
    assert_eq!(out.origin[199], PointOrigin::Fog);
}

fn simpson(f: impl Fn(f64) -> f64, a: f64, b: f64, n: usize) -> f64 {
    let h = (b - a) / n as f64;
    let mut s = f(a) + f(b);
    for k in 1..n {
        s += if k % 2 == 1 { 4.0 } else { 2.0 } * f(a + k as f64 * h);
    }
    s * h / 3.0
}

#[test]
fn hydrometeor_extinction_matches_integrals_and_fits() {
    for rate in [1.0, 2.5, 10.0, 30.0, 100.0] {
        let (n0, l) = marshall_palmer(rate);
        let closed = exponential_dsd_alpha_per_m(n0, l);
        // (pi/4) 1e-6 * int D^2 Q_ext N(D) dD with Q_ext = 2, D in mm
        let numeric = simpson(
            |d| std::f64::consts::FRAC_PI_4 * 1e-6 * d * d * 2.0 * n0 * (-l * d).exp(),
            0.0,
            40.0,
            20000,
        );
        assert!((closed - numeric).abs() / numeric < 1e-6);
        let fit = 3.65e-4 * rate.powf(0.63);
        assert!(
            (closed - fit).abs() / fit < 0.01,
            "rain {rate}: {closed} vs {fit}"
        );
        let w = Weather {
            rain_rate_mm_h: rate,
            ..Weather::clear()
        };
        assert_eq!(w.extinction().rain_per_m, closed);
    }
    for r in [0.5, 2.0, 8.0] {
        let (n0, l) = marshall_gunn(r);
        let a = exponential_dsd_alpha_per_m(n0, l);
        let fit = 1.44e-3 * f64::powf(r, 0.57);
        assert!((a - fit).abs() / fit < 0.01, "snow {r}: {a} vs {fit}");
    }
    // one alpha: fog + rain + snow add up
    let w = Weather {
        fog_visibility_m: Some(200.0),
        rain_rate_mm_h: 5.0,
        snowfall_rate_mm_h: 1.0,
        ..Weather::clear()
    };
    let e = w.extinction();
    assert_eq!(e.total_per_m(), e.fog_per_m + e.rain_per_m + e.snow_per_m);
    assert!((e.fog_per_m - 2.995_732 / 200.0).abs() < 1e-8);
}

#[test]
fn snowfall_parameters_match_the_published_particle_files() {
    // (S, v_t) -> (R_eq, rho_occ, flakes per channel) of Robo3D's light / moderate / heavy files
    for (s, vt, r_eq, occ, per_channel) in [
        (0.5, 2.0, 2.238, 6.94e-7, 39_921.0),
        (1.0, 1.6, 8.848, 1.74e-6, 26_244.0),
        (2.5, 1.6, 34.97, 4.34e-6, 17_622.0),
    ] {
        assert!((snow_equivalent_rain_rate_mm_h(s, vt) - r_eq).abs() / r_eq < 1e-3);
        assert!((snow_occupancy(s, vt) - occ).abs() / occ < 3e-3);
        let w = Weather {
            snowfall_rate_mm_h: s,
            snow_terminal_velocity_m_s: vt,
            seed: 4,
            ..Weather::clear()
        };
        let field = SnowField::sample(&w, 4, &SnowConfig::default()).unwrap();
        let got = field.num_flakes() as f64 / 4.0;
        assert!(
            (got - per_channel).abs() / per_channel < 0.04,
            "S {s}: {got} flakes per channel vs {per_channel}"
        );
    }
}

#[test]
fn fresnel_conserves_energy_and_has_brewster_angle() {
    let (n1, n2) = (1.0003, 1.33);
    let (rs, rp, ts, tp) = fresnel(n1, n2, 0.0);
    let r0 = ((n1 - n2) / (n1 + n2)).powi(2);
    assert!((rs - r0).abs() < 1e-12 && (rp - r0).abs() < 1e-12);
    for k in 0..89 {
        let th = (k as f64).to_radians();
        let (rs, rp, ts, tp) = fresnel(n1, n2, th);
        assert!(
            (rs + ts - 1.0).abs() < 1e-12 && (rp + tp - 1.0).abs() < 1e-12,
            "theta {k}"
        );
        let (rs, rp, ts, tp) = fresnel(n2, n1, th.min(0.84));
        assert!(
            (rs + ts - 1.0).abs() < 1e-12 && (rp + tp - 1.0).abs() < 1e-12,
            "theta {k} (water to air)"
        );
    }
    let brewster = (n2 / n1).atan();
    assert!(fresnel(n1, n2, brewster).1 < 1e-20);
    let _ = (ts, tp);
}

#[test]
fn snow_occlusion_and_waveform_match_brute_force() {
    let w = 1.5e-3;
    // (distance, a, b) sorted nearest first, overlapping
    let iv = [
        (1.0, -2e-3, -1e-3),
        (2.0, -1.2e-3, 0.2e-3),
        (3.0, -0.5e-3, 1.0e-3),
        (4.0, 0.9e-3, 2e-3),
    ];
    let mut ratios = Vec::new();
    let rest = occlusion_ratios(w, &iv, &mut ratios);
    let n = 200_000;
    let mut brute = [0.0f64; 5];
    for k in 0..n {
        let x = -w + (k as f64 + 0.5) / n as f64 * 2.0 * w;
        let j = iv
            .iter()
            .position(|&(_, a, b)| x >= a && x < b)
            .unwrap_or(4);
        brute[j] += 1.0 / n as f64;
    }
    for j in 0..4 {
        assert!(
            (ratios[j] - brute[j]).abs() < 1e-4,
            "{j}: {} vs {}",
            ratios[j],
            brute[j]
        );
    }
    assert!((rest - brute[4]).abs() < 1e-4);
    assert!((ratios.iter().sum::<f64>() + rest - 1.0).abs() < 1e-12);

    let len = 2.998;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    use rand::Rng;
    for _ in 0..50 {
        let k = rng.random_range(1..6);
        let contrib: Vec<(f64, f64)> = (0..k)
            .map(|_| (rng.random_range(1.0..8.0), rng.random_range(0.01..1.0)))
            .collect();
        let (r, v) = waveform_peak(&contrib, len);
        let eval = |x: f64| -> f64 {
            contrib
                .iter()
                .filter(|(rj, _)| x >= *rj && x <= rj + len)
                .map(|(rj, a)| a * (std::f64::consts::PI * (x - rj) / len).sin().powi(2))
                .sum()
        };
        let mut best: f64 = 0.0;
        let mut x = 0.0;
        while x < 12.0 {
            best = best.max(eval(x));
            x += 1e-4;
        }
        assert!(v >= best - 1e-12 && v <= best + 1e-6, "{v} vs {best}");
        assert!((eval(r) - v).abs() < 1e-12);
    }
}

#[test]
fn lisa_range_noise_has_the_documented_sigma() {
    let cfg = RainConfig::default();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let (r, rho) = (10.0, 0.5);
    let mut xs = Vec::new();
    for _ in 0..20_000 {
        // a vanishing rain rate: no drop can win, only noise
        match rain_point(&mut rng, &cfg, 1e-9, 0.0, 3e-3, r, rho) {
            RainOutcome::Target { range_m } => xs.push(range_m),
            o => panic!("{o:?}"),
        }
    }
    let mean = xs.iter().sum::<f64>() / xs.len() as f64;
    let sd = (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (xs.len() - 1) as f64).sqrt();
    let want = 0.09 / (2.0 * (rho / (r * r)) / cfg.p_min()).sqrt();
    assert!((sd - want).abs() / want < 0.03, "{sd} vs {want}");
    assert!((mean - r).abs() < 4.0 * want / (xs.len() as f64).sqrt());
    // a weak far target in heavy rain is lost, a strong near one never is
    let mut lost = 0;
    for _ in 0..200 {
        if rain_point(
            &mut rng,
            &cfg,
            50.0,
            0.0043,
            3e-3,
            150.0,
            0.9 * (-2.0 * 0.0043 * 150.0f64).exp(),
        ) == RainOutcome::Lost
        {
            lost += 1;
        }
        assert_ne!(
            rain_point(&mut rng, &cfg, 50.0, 0.0043, 3e-3, 5.0, 0.5),
            RainOutcome::Lost
        );
    }
    assert!(lost > 150, "{lost}");
}

#[test]
fn camera_fog_uses_the_distance_along_the_ray_not_z() {
    let (w, h) = (41u32, 21u32);
    let grey = 60u8;
    let img = RgbImage::from_pixel(w, h, image::Rgb([grey; 3]));
    let z = 40.0f32;
    let depth = DepthMap {
        width: w,
        height: h,
        z_m: vec![z; (w * h) as usize],
    };
    let k = Intrinsics {
        fx: 20.0,
        fy: 20.0,
        cx: 20.0,
        cy: 10.0,
    };
    let vis = 60.0;
    let alpha = 20f64.ln() / vis;
    let air = 0.9f32;
    let mut cfg = WeatherConfig::default();
    cfg.camera.airlight = Some([air; 3]);
    let sim = WeatherSim::new(
        &Weather {
            fog_visibility_m: Some(vis),
            ..Weather::clear()
        },
        &cfg,
    )
    .unwrap();
    let out = sim
        .apply_camera(CameraInput {
            image: &img,
            depth: Some(&depth),
            intrinsics: Some(k),
        })
        .unwrap();
    let j = srgb_to_linear(grey) as f64;
    let expect = |u: f64, v: f64| {
        let l = z as f64 * (((u - 20.0) / 20.0).powi(2) + ((v - 10.0) / 20.0).powi(2) + 1.0).sqrt();
        let t = (-alpha * l).exp();
        linear_to_srgb((j * t + air as f64 * (1.0 - t)) as f32)
    };
    for (u, v) in [(0u32, 0u32), (20, 10), (40, 20), (5, 15)] {
        assert_eq!(
            out.image.get_pixel(u, v).0[0],
            expect(u as f64, v as f64),
            "pixel ({u}, {v})"
        );
    }
    // z alone would give the corner the centre's value: the test can tell the two apart
    assert_ne!(
        out.image.get_pixel(0, 0).0[0],
        out.image.get_pixel(20, 10).0[0]
    );
}

#[test]
fn planner_routes_each_effect_to_its_sensors() {
    let cam = veila_data::weather::CameraConfig::default();
    let plan = |p: Preset| veila_data::weather::Plan::new(&p.weather(), &cam).unwrap();
    let night = plan(Preset::KittiNight);
    assert!(night.lidar.is_empty(), "a LiDAR makes its own light");
    assert_eq!(
        night.camera,
        vec![CameraEffect::Darken, CameraEffect::SensorNoise]
    );
    let fog = plan(Preset::KittiFog);
    assert_eq!(fog.lidar, vec![LidarEffect::Fog]);
    assert_eq!(fog.camera, vec![CameraEffect::Veil]);
    let snow = plan(Preset::KittiSnow);
    assert_eq!(snow.lidar, vec![LidarEffect::Extinction, LidarEffect::Snow]);
    assert_eq!(
        snow.camera,
        vec![CameraEffect::Veil, CameraEffect::Snowflakes]
    );
    let rain = plan(Preset::RainModerate);
    assert_eq!(
        rain.lidar,
        vec![
            LidarEffect::WetGround,
            LidarEffect::Extinction,
            LidarEffect::Rain
        ]
    );
    assert_eq!(
        rain.camera,
        vec![CameraEffect::Veil, CameraEffect::RainStreaks]
    );
    let wet = veila_data::weather::Plan::new(
        &Weather {
            water_depth_mm: 0.5,
            ..Weather::clear()
        },
        &cam,
    )
    .unwrap();
    assert_eq!(wet.lidar, vec![LidarEffect::WetGround]);
    assert!(wet.camera.is_empty());
    assert!(plan(Preset::KittiClean).is_identity());
    // presets parse by name and serialise with serde
    for p in Preset::ALL {
        assert_eq!(p.name().parse::<Preset>().unwrap(), p);
        let w = p.weather();
        let back: Weather = toml::from_str(&toml::to_string(&w).unwrap()).unwrap();
        assert_eq!(back, w);
    }
    assert!("fog-dense".parse::<Preset>().is_err());
    assert_eq!("night".parse::<TimeOfDay>().unwrap(), TimeOfDay::Night);
}

#[test]
fn missing_inputs_fail_loudly_or_use_the_documented_fallback() {
    let pts: Vec<Vec3> = (0..500)
        .map(|k| Vec3::new(3.0 + (k % 50) as f32, (k / 50) as f32 - 5.0, -1.73))
        .collect();
    let c = PointCloud {
        xyz: pts,
        intensity: vec![0.2; 500],
        ring: None,
        label: None,
    };
    let sim = WeatherSim::new(&Preset::SnowModerate.weather(), &WeatherConfig::default()).unwrap();
    let err = sim.apply_lidar(LidarInput::new(&c)).unwrap_err();
    assert!(
        matches!(&err, veila_data::Error::MissingInput { effect, input } if effect == "snow" && input.contains("ring")),
        "{err}"
    );
    let beams = BeamTable::hdl64e();
    let out = sim
        .apply_lidar(LidarInput {
            cloud: &c,
            ground_mask: None,
            beams: Some(&beams),
        })
        .unwrap();
    let snow = out.records.iter().find(|r| r.effect == "snow").unwrap();
    assert!(
        snow.notes.iter().any(|n| n.contains("beam elevations")),
        "{:?}",
        snow.notes
    );

    // camera fog without depth / intrinsics
    let img = RgbImage::new(4, 3);
    let sim = WeatherSim::new(&Preset::FogModerate.weather(), &WeatherConfig::default()).unwrap();
    let err = sim
        .apply_camera(CameraInput {
            image: &img,
            depth: None,
            intrinsics: None,
        })
        .unwrap_err();
    assert!(
        matches!(&err, veila_data::Error::MissingInput { effect, .. } if effect == "veil"),
        "{err}"
    );
    assert!(err.to_string().contains("depth map"), "{err}");
    let depth = DepthMap {
        width: 3,
        height: 3,
        z_m: vec![1.0; 9],
    };
    let k = Intrinsics {
        fx: 1.0,
        fy: 1.0,
        cx: 1.0,
        cy: 1.0,
    };
    let err = sim
        .apply_camera(CameraInput {
            image: &img,
            depth: Some(&depth),
            intrinsics: Some(k),
        })
        .unwrap_err();
    assert!(err.to_string().contains("4x3"), "{err}");

    // wet ground: mask of the wrong length is an error; labels are used when present; else a plane fit
    let wet = WeatherSim::new(
        &Weather {
            water_depth_mm: 1.0,
            ..Weather::clear()
        },
        &WeatherConfig::default(),
    )
    .unwrap();
    let bad = vec![true; 3];
    assert!(
        wet.apply_lidar(LidarInput {
            cloud: &c,
            ground_mask: Some(&bad),
            beams: None
        })
        .is_err()
    );
    let mut labelled = c.clone();
    labelled.label = Some((0..500).map(|k| if k % 2 == 0 { 40 } else { 50 }).collect());
    let out = wet.apply_lidar(LidarInput::new(&labelled)).unwrap();
    assert!(out.records[0].notes.iter().any(|n| n.contains("labels")));
    assert_eq!(out.records[0].counts["ground_points"], 250);
    let out = wet.apply_lidar(LidarInput::new(&c)).unwrap();
    assert!(
        out.records[0].notes.iter().any(|n| n.contains("plane fit")),
        "{:?}",
        out.records[0].notes
    );
}

#[test]
fn ground_plane_fit_recovers_a_tilted_road() {
    // z = 0.02 x - 0.01 y - 1.7 plus clutter above it
    let mut pts = Vec::new();
    for i in 0..60 {
        for j in 0..12 {
            let (x, y) = (4.0 + i as f32, -5.5 + j as f32);
            pts.push(Vec3::new(x, y, 0.02 * x - 0.01 * y - 1.7));
        }
    }
    for i in 0..200 {
        pts.push(Vec3::new(
            5.0 + (i % 40) as f32,
            3.0,
            -1.2 + (i / 40) as f32 * 0.05,
        ));
    }
    let pl = fit_ground_plane(&pts, 1.73, 0).unwrap();
    let n = glam::DVec3::new(-0.02, 0.01, 1.0).normalize();
    assert!((pl.normal - n).length() < 1e-5, "{:?}", pl.normal);
    assert!((pl.d - 1.7 * n.z).abs() < 1e-4, "{}", pl.d);
    assert!(
        pl.normal.z > 0.0,
        "the normal points up (the reference's fallback had it upside down)"
    );
    assert!(fit_ground_plane(&pts[..10], 1.73, 0).is_none());
    assert_eq!(
        GroundPlane::flat(1.73).distance(glam::DVec3::new(5.0, 0.0, -1.73)),
        0.0
    );
}

#[test]
fn night_darkens_only_the_camera_and_headlights_light_the_near_road() {
    let (w, h) = (64u32, 32u32);
    let img = RgbImage::from_pixel(w, h, image::Rgb([180, 170, 160]));
    let depth = DepthMap {
        width: w,
        height: h,
        z_m: (0..w * h)
            .map(|i| {
                if i / w < 10 {
                    f32::INFINITY
                } else {
                    4.0 + (h - i / w) as f32
                }
            })
            .collect(),
    };
    let k = Intrinsics {
        fx: 40.0,
        fy: 40.0,
        cx: 31.5,
        cy: 12.0,
    };
    let input = CameraInput {
        image: &img,
        depth: Some(&depth),
        intrinsics: Some(k),
    };
    let night = Weather {
        time_of_day: TimeOfDay::Night,
        seed: 2,
        ..Weather::clear()
    };
    let sim = WeatherSim::new(&night, &WeatherConfig::default()).unwrap();
    assert!(sim.plan().lidar.is_empty());
    let dark = sim.apply_camera(input).unwrap();
    let mean_lin = |im: &RgbImage| {
        im.as_raw()
            .iter()
            .map(|&v| srgb_to_linear(v) as f64)
            .sum::<f64>()
            / im.as_raw().len() as f64
    };
    let m0 = mean_lin(&img);
    let m1 = mean_lin(&dark.image);
    assert!((m1 / m0 - 0.05).abs() < 0.01, "{m1} / {m0}");
    let mut cfg = WeatherConfig::default();
    cfg.camera.headlights = Some(Default::default());
    let lit = WeatherSim::new(&night, &cfg)
        .unwrap()
        .apply_camera(input)
        .unwrap();
    assert_eq!(
        lit.records
            .iter()
            .map(|r| r.effect.as_str())
            .collect::<Vec<_>>(),
        ["darken", "headlights", "sensor_noise"]
    );
    // bottom rows (near road) brighter with headlights; sky rows unchanged up to noise
    let row_mean = |im: &RgbImage, r: u32| {
        (0..w).map(|c| im.get_pixel(c, r).0[0] as f64).sum::<f64>() / w as f64
    };
    assert!(row_mean(&lit.image, h - 1) > row_mean(&dark.image, h - 1) + 5.0);
    assert!((row_mean(&lit.image, 0) - row_mean(&dark.image, 0)).abs() < 1e-9);
    let _ = Sensor::Camera;
}

/// The LiDAR leaves the snow's extinction to the sampled flakes (issue 20) unless `lidar_extinction` is
/// set; fog and rain keep theirs, and the camera keeps the full alpha.
#[test]
fn snow_extinction_on_the_lidar_is_carried_by_the_flakes_unless_asked() {
    let w = Preset::SnowModerate.weather().with_seed(5);
    let e = w.extinction();
    assert!(e.snow_per_m > 4e-3, "{e:?}");
    let off = WeatherSim::new(&w, &WeatherConfig::default()).unwrap();
    assert_eq!(off.plan().lidar, vec![LidarEffect::Snow]);
    assert_eq!(off.lidar_alpha_per_m(), 0.0);
    assert!(off.plan().camera.contains(&CameraEffect::Veil));
    let mut cfg = WeatherConfig::default();
    cfg.lidar.snow.lidar_extinction = true;
    let on = WeatherSim::new(&w, &cfg).unwrap();
    assert_eq!(
        on.plan().lidar,
        vec![LidarEffect::Extinction, LidarEffect::Snow]
    );
    assert_eq!(on.lidar_alpha_per_m(), e.total_per_m());
    let wet = Weather {
        rain_rate_mm_h: 10.0,
        ..w.clone()
    };
    let rain = WeatherSim::new(&wet, &WeatherConfig::default()).unwrap();
    assert_eq!(rain.lidar_alpha_per_m(), wet.extinction().rain_per_m);
    assert_eq!(rain.plan().lidar[0], LidarEffect::Extinction);

    // 4,000 points at 2..12 m: most beams meet no flake and keep their intensity bit for bit without the
    // snow extinction, and lose exactly exp(-2 alpha R) with it
    let n = 4000;
    let cloud = PointCloud {
        xyz: (0..n)
            .map(|k| {
                let az = k as f32 * 0.0157;
                let r = 2.0 + (k % 11) as f32;
                Vec3::new(r * az.cos(), r * az.sin(), 0.0)
            })
            .collect(),
        intensity: vec![0.5; n],
        ring: Some((0..n).map(|k| (k % 4) as u16).collect()),
        label: None,
    };
    let a = off.apply_lidar(LidarInput::new(&cloud)).unwrap();
    let b = on.apply_lidar(LidarInput::new(&cloud)).unwrap();
    let same = |out: &veila_data::weather::LidarOutput| {
        out.cloud.intensity.iter().filter(|i| **i == 0.5).count()
    };
    assert!(same(&a) > n * 7 / 10, "{}", same(&a));
    assert_eq!(same(&b), 0);
    let alpha = e.total_per_m();
    let mut checked = 0;
    for (k, (p, i)) in b.cloud.xyz.iter().zip(&b.cloud.intensity).enumerate() {
        if a.cloud.intensity[k] == 0.5 {
            let want = 0.5 * (-2.0 * alpha * p.as_dvec3().length()).exp();
            assert!((*i as f64 - want).abs() < 1e-6, "{i} vs {want}");
            checked += 1;
        }
    }
    assert!(checked > n / 2);
}

/// `reference_power_quirk` scales the hard target like a flake (`0.9 i_max rho / R^2`) once a flake is
/// in the beam, as the reference's never-reset power constant does.
#[test]
fn reference_power_quirk_lets_a_small_flake_beat_a_bright_target() {
    // a 1 mm flake at 5 m covers 2 * 0.001 / 5 / 3e-3 = 13.3 % of the beam
    let field = SnowField::from_flakes(
        vec![vec![Flake {
            range_m: 5.0,
            azimuth_rad: 0.0,
            radius_m: 0.001,
        }]],
        64,
    );
    let mut scratch = Default::default();
    let cfg = SnowConfig::default();
    let rho = 2.0 * (0.001f64 / 5.0).asin() / 3e-3;
    match snow_point(
        &field,
        &cfg,
        0.0,
        3e-3,
        1.0,
        0,
        0.0,
        30.0,
        0.5,
        &mut scratch,
    ) {
        // the target, 0.5 * (1 - rho), beats the flake, 0.9 * rho / 25
        SnowOutcome::Intensity(v) => assert!((v - 0.5 * (1.0 - rho)).abs() < 1e-6, "{v}"),
        o => panic!("{o:?}"),
    }
    let quirk = SnowConfig {
        reference_power_quirk: true,
        ..cfg
    };
    match snow_point(
        &field,
        &quirk,
        0.0,
        3e-3,
        1.0,
        0,
        0.0,
        30.0,
        0.5,
        &mut scratch,
    ) {
        // the target becomes 0.9 * (1 - rho) / 900 and the flake wins
        SnowOutcome::Flake { range_m, intensity } => {
            assert!((range_m - 5.0).abs() < 1e-6, "{range_m}");
            assert!((intensity - 0.9 * rho / 25.0).abs() < 1e-6, "{intensity}");
        }
        o => panic!("{o:?}"),
    }
}
