//! Numerics of `veila_data::augment`: each expected value comes from a closed form computed here in
//! `f64` (sRGB, Gaussian, vignetting, noise moments), from brute force, or from an exact symmetry.

use glam::{Mat3, Mat4, Vec3};
use veila_data::augment::{
    CropZoom, CropZoomRange, LinearRgb, Photometric, PhotometricParams, SensorNoise, contrast,
    crop_zoom, exposure, gaussian_blur, hue_rotation, jpeg_round_trip, linear_to_srgb,
    linear_to_srgb_u8, rgb_image_from_raw, saturation, sensor_noise, srgb_to_linear,
    srgb_u8_to_linear, vignetting, white_balance,
};
use veila_data::image::{Rgb, RgbImage};
use veila_geom::PinholeCamera;

type R = Result<(), Box<dyn std::error::Error>>;

/// IEC 61966-2-1 decoding, `f64`.
fn ref_decode(v: f64) -> f64 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// IEC 61966-2-1 encoding, `f64`.
fn ref_encode(l: f64) -> f64 {
    if l <= 0.0031308 {
        12.92 * l
    } else {
        1.055 * l.powf(1.0 / 2.4) - 0.055
    }
}

/// A busy test image: every byte value occurs in every channel.
fn busy(w: u32, h: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| {
        Rgb([
            ((7 * x + 3 * y) % 256) as u8,
            ((5 * x + 11 * y + 17) % 256) as u8,
            ((x * y + 13 * x + 101) % 256) as u8,
        ])
    })
}

fn flat_linear(w: u32, h: u32, v: f32) -> Result<LinearRgb, veila_data::Error> {
    LinearRgb::new(w, h, vec![v; (w * h * 3) as usize])
}

fn mean_var(xs: &[f32]) -> (f64, f64) {
    let n = xs.len() as f64;
    let m = xs.iter().map(|&x| f64::from(x)).sum::<f64>() / n;
    let v = xs.iter().map(|&x| (f64::from(x) - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, v)
}

// ---------------------------------------------------------------- sRGB

#[test]
fn srgb_u8_round_trip_is_exact_for_all_256_values() {
    let mut prev = -1.0f32;
    for v in 0..=255u8 {
        let l = srgb_u8_to_linear(v);
        assert!(l > prev, "decoding not strictly increasing at {v}");
        prev = l;
        assert_eq!(linear_to_srgb_u8(l), v, "u8 round trip at {v}");
        let e = f32::from(v) / 255.0;
        assert!(
            (linear_to_srgb(srgb_to_linear(e)) - e).abs() < 2e-6,
            "f32 round trip at {v}"
        );
        assert!((f64::from(l) - ref_decode(f64::from(v) / 255.0)).abs() < 1e-7);
    }
    assert_eq!(linear_to_srgb_u8(-0.5), 0);
    assert_eq!(linear_to_srgb_u8(7.0), 255);
    assert_eq!(linear_to_srgb_u8(f32::NAN), 0);
}

#[test]
fn srgb_matches_the_iec_closed_form() {
    for v in [0.0, 0.01, 0.04045, 0.0405, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0] {
        assert!(
            (f64::from(srgb_to_linear(v as f32)) - ref_decode(v)).abs() < 1e-6,
            "decode {v}"
        );
    }
    for l in [0.0, 0.001, 0.0031308, 0.0032, 0.05, 0.18, 0.5, 0.8, 1.0] {
        assert!(
            (f64::from(linear_to_srgb(l as f32)) - ref_encode(l)).abs() < 1e-6,
            "encode {l}"
        );
    }
    // published values: 18 % grey is sRGB 0.4613561; sRGB 128 is 0.2158605 linear; white stays white
    assert!((linear_to_srgb(0.18) - 0.461_356_1).abs() < 1e-6);
    assert!((srgb_u8_to_linear(128) - 0.215_860_5).abs() < 1e-6);
    assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
}

// ---------------------------------------------------------------- blur

#[test]
fn blur_sigma_zero_is_the_identity() -> R {
    let img = busy(37, 23);
    assert_eq!(gaussian_blur(&img, 0.0)?, img);
    let lin = LinearRgb::from_srgb(&img)?;
    assert_eq!(lin.gaussian_blur(0.0)?, lin);
    Ok(())
}

#[test]
fn blur_keeps_a_constant_image_constant() -> R {
    let lin = flat_linear(19, 11, 0.3)?.gaussian_blur(2.5)?;
    assert!(lin.data().iter().all(|&v| (v - 0.3).abs() < 1e-6));
    let img = RgbImage::from_pixel(19, 11, Rgb([10, 128, 250]));
    assert_eq!(gaussian_blur(&img, 3.7)?, img);
    Ok(())
}

/// The normalised sampled Gaussian on `|t| <= ceil(4 sigma)`.
fn ref_kernel(sigma: f64) -> Vec<f64> {
    let r = (4.0 * sigma).ceil() as i64;
    let g: Vec<f64> = (-r..=r)
        .map(|t| (-((t * t) as f64) / (2.0 * sigma * sigma)).exp())
        .collect();
    let s: f64 = g.iter().sum();
    g.into_iter().map(|v| v / s).collect()
}

#[test]
fn blur_impulse_response_is_the_normalised_gaussian() -> R {
    for sigma in [0.8f64, 2.0, 3.3] {
        let n = 61u32;
        let c = 30usize;
        let mut data = vec![0.0f32; (n * n * 3) as usize];
        data[3 * (c * n as usize + c) + 1] = 1.0; // green channel only
        let out = LinearRgb::new(n, n, data)?.gaussian_blur(sigma as f32)?;
        let k = ref_kernel(sigma);
        let r = (k.len() / 2) as i64;
        let (mut sum, mut var_x, mut var_y) = (0.0f64, 0.0f64, 0.0f64);
        for y in 0..n as usize {
            for x in 0..n as usize {
                let px = &out.data()[3 * (y * n as usize + x)..][..3];
                assert_eq!((px[0], px[2]), (0.0, 0.0), "channels mix at ({x}, {y})");
                let (dx, dy) = (x as i64 - c as i64, y as i64 - c as i64);
                let want = if dx.abs() <= r && dy.abs() <= r {
                    k[(dx + r) as usize] * k[(dy + r) as usize]
                } else {
                    0.0
                };
                let got = f64::from(px[1]);
                assert!(
                    (got - want).abs() < 1e-6,
                    "sigma {sigma} at ({dx}, {dy}): {got} vs {want}"
                );
                sum += got;
                var_x += got * (dx * dx) as f64;
                var_y += got * (dy * dy) as f64;
            }
        }
        assert!((sum - 1.0).abs() < 1e-5, "sigma {sigma}: sum {sum}");
        for v in [var_x, var_y] {
            let rel = (v / (sigma * sigma) - 1.0).abs();
            // sigma 0.8 is coarsely sampled (its sampled variance is 1 % off), the others to 0.2 %
            assert!(rel < 0.03, "sigma {sigma}: variance {v}");
        }
    }
    Ok(())
}

// ---------------------------------------------------------------- noise

#[test]
fn read_noise_has_the_configured_sigma_in_linear_light() -> R {
    let sigma = 0.01f32;
    let noise = SensorNoise {
        shot_gain: 0.0,
        read_sigma: sigma,
    };
    let out = flat_linear(256, 256, 0.18)?.sensor_noise(&noise, 1)?;
    let (m, v) = mean_var(out.data());
    let n = out.data().len() as f64;
    assert!(
        (m - 0.18).abs() < 4.0 * f64::from(sigma) / n.sqrt(),
        "mean {m}"
    );
    assert!(
        (v.sqrt() / f64::from(sigma) - 1.0).abs() < 0.03,
        "std {}",
        v.sqrt()
    );

    // through 8 bits: decoded back to linear light the std is still sigma (quantisation adds ~0.5 %)
    let grey = RgbImage::from_pixel(256, 256, Rgb([128; 3]));
    let noisy = sensor_noise(&grey, &noise, 2)?;
    let lin: Vec<f32> = noisy
        .as_raw()
        .iter()
        .map(|&b| srgb_u8_to_linear(b))
        .collect();
    let (m8, v8) = mean_var(&lin);
    assert!(
        (m8 - f64::from(srgb_u8_to_linear(128))).abs() < 2e-4,
        "mean {m8}"
    );
    assert!(
        (v8.sqrt() / f64::from(sigma) - 1.0).abs() < 0.05,
        "std {}",
        v8.sqrt()
    );
    Ok(())
}

#[test]
fn shot_noise_variance_is_gain_times_signal() -> R {
    let gain = 1e-3f32;
    let noise = SensorNoise {
        shot_gain: gain,
        read_sigma: 0.0,
    };
    let mut vars = Vec::new();
    for (x, seed) in [(0.05f32, 3u64), (0.4, 4)] {
        let out = flat_linear(256, 256, x)?.sensor_noise(&noise, seed)?;
        let (m, v) = mean_var(out.data());
        let want = f64::from(gain) * f64::from(x);
        assert!((m / f64::from(x) - 1.0).abs() < 0.003, "mean {m} at {x}");
        assert!(
            (v / want - 1.0).abs() < 0.04,
            "variance {v} vs {want} at {x}"
        );
        vars.push(v);
    }
    assert!((vars[1] / vars[0] / 8.0 - 1.0).abs() < 0.06);

    // low light: outputs are whole photo-electron counts times the gain, mean kept
    let x = 0.002f32;
    let out = flat_linear(128, 128, x)?.sensor_noise(&noise, 5)?;
    for &v in out.data() {
        let n = v / gain;
        assert!(
            (n - n.round()).abs() < 1e-3 && n >= 0.0,
            "{v} is not a count"
        );
    }
    let (m, v) = mean_var(out.data());
    assert!((m / f64::from(x) - 1.0).abs() < 0.03, "mean {m}");
    // Poisson: variance equals mean (in counts)
    assert!(
        (v / (f64::from(gain) * m) - 1.0).abs() < 0.05,
        "variance {v}"
    );
    Ok(())
}

#[test]
fn noise_depends_on_the_seed_only() -> R {
    let img = busy(64, 40);
    let noise = SensorNoise {
        shot_gain: 5e-4,
        read_sigma: 0.01,
    };
    let a = sensor_noise(&img, &noise, 9)?;
    assert_eq!(a, sensor_noise(&img, &noise, 9)?);
    assert_ne!(a, sensor_noise(&img, &noise, 10)?);
    let lin = LinearRgb::from_srgb(&img)?;
    let run = |threads: usize| -> Result<LinearRgb, Box<dyn std::error::Error>> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()?;
        Ok(pool.install(|| lin.sensor_noise(&noise, 9))?)
    };
    let one = run(1)?;
    let two = run(2)?;
    let bits = |l: &LinearRgb| l.data().iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&one), bits(&two));
    assert_eq!(one.to_srgb(), a);
    Ok(())
}

// ---------------------------------------------------------------- vignetting

#[test]
fn vignetting_follows_one_minus_k_r_squared() -> R {
    let (w, h, k) = (101u32, 81u32, 0.6f64);
    let (cx, cy) = (50.0f64, 40.0f64);
    let half_diag = 0.5 * f64::from(w * w + h * h).sqrt();
    let factor = |x: u32, y: u32| {
        let r2 = ((f64::from(x) - cx).powi(2) + (f64::from(y) - cy).powi(2)) / half_diag.powi(2);
        1.0 - k * r2
    };
    // linear light: every pixel to float precision
    let lin = flat_linear(w, h, 0.5)?.vignetting(k as f32)?;
    for y in 0..h {
        for x in 0..w {
            let got = f64::from(lin.data()[3 * (y * w + x) as usize]);
            assert!((got - 0.5 * factor(x, y)).abs() < 1e-6, "({x}, {y})");
        }
    }
    // 8 bits: the centre is unchanged, the corners fall off by the formula up to rounding
    let img = RgbImage::from_pixel(w, h, Rgb([200, 120, 60]));
    let out = vignetting(&img, k as f32)?;
    assert_eq!(out.get_pixel(50, 40), img.get_pixel(50, 40));
    for (x, y) in [
        (0, 0),
        (w - 1, 0),
        (0, h - 1),
        (w - 1, h - 1),
        (50, 0),
        (0, 40),
    ] {
        for c in 0..3 {
            let v_in = img.get_pixel(x, y)[c];
            let want = ref_decode(f64::from(v_in) / 255.0) * factor(x, y);
            let got_u8 = out.get_pixel(x, y)[c];
            let got = ref_decode(f64::from(got_u8) / 255.0);
            // half of the local 8-bit step in linear light
            let step = ref_decode(f64::from(got_u8.saturating_add(1)) / 255.0) - got;
            assert!(
                (got - want).abs() <= 0.5 * step + 1e-6,
                "({x}, {y}) channel {c}"
            );
        }
    }
    Ok(())
}

// ---------------------------------------------------------------- exposure and white balance

#[test]
fn exposure_and_white_balance_scale_linear_channel_means() -> R {
    // linear values in [0.01, 0.4]: no clipping under gains up to 2.4
    let img = RgbImage::from_fn(80, 60, |x, y| {
        let enc = |l: f64| (ref_encode(l) * 255.0).round() as u8;
        Rgb([
            enc(0.01 + 0.39 * f64::from(x) / 79.0),
            enc(0.01 + 0.39 * f64::from(y) / 59.0),
            enc(0.01 + 0.39 * f64::from((x + y) % 37) / 36.0),
        ])
    });
    let means = |im: &RgbImage| {
        let mut m = [0.0f64; 3];
        for p in im.pixels() {
            for c in 0..3 {
                m[c] += f64::from(srgb_u8_to_linear(p[c]));
            }
        }
        m.map(|v| v / f64::from(im.width() * im.height()))
    };
    let m0 = means(&img);
    let gains = [1.3f32, 0.9, 2.4];
    let m1 = means(&white_balance(&img, gains)?);
    for c in 0..3 {
        let ratio = m1[c] / m0[c];
        assert!(
            (ratio / f64::from(gains[c]) - 1.0).abs() < 0.005,
            "channel {c}: {ratio}"
        );
    }
    let m2 = means(&exposure(&img, 1.7)?);
    for c in 0..3 {
        assert!((m2[c] / m0[c] / 1.7 - 1.0).abs() < 0.005, "channel {c}");
    }
    // in linear light exactly
    let lin = LinearRgb::from_srgb(&img)?;
    let wb = lin.white_balance(gains)?;
    for (i, (a, b)) in lin.data().iter().zip(wb.data()).enumerate() {
        assert_eq!(*b, a * gains[i % 3]);
    }
    Ok(())
}

// ---------------------------------------------------------------- JPEG

fn psnr(a: &RgbImage, b: &RgbImage) -> f64 {
    let mse = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
        .sum::<f64>()
        / a.as_raw().len() as f64;
    10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10()
}

#[test]
fn jpeg_quality_orders_the_error() -> R {
    let img = RgbImage::from_fn(96, 64, |x, y| {
        let edge = if (x / 16 + y / 16) % 2 == 0 { 40 } else { 0 };
        Rgb([
            (2 * x + edge) as u8,
            (3 * y + edge) as u8,
            (128 + (x as i32 - y as i32)).clamp(0, 255) as u8,
        ])
    });
    let q100 = jpeg_round_trip(&img, 100)?;
    let q50 = jpeg_round_trip(&img, 50)?;
    let q10 = jpeg_round_trip(&img, 10)?;
    for out in [&q100, &q50, &q10] {
        assert_eq!(out.dimensions(), img.dimensions());
    }
    let (p100, p50, p10) = (psnr(&img, &q100), psnr(&img, &q50), psnr(&img, &q10));
    assert!(p100 > 38.0, "q100 PSNR {p100}");
    assert!(p100 > p50 && p50 > p10 + 3.0, "PSNR {p100} {p50} {p10}");
    assert_eq!(q10, jpeg_round_trip(&img, 10)?, "deterministic");
    Ok(())
}

// ---------------------------------------------------------------- colour jitter

#[test]
fn neutral_colour_jitter_is_the_identity() -> R {
    let img = busy(64, 64);
    assert_eq!(hue_rotation(&img, 0.0)?, img);
    assert_eq!(hue_rotation(&img, 360.0)?, img);
    assert_eq!(saturation(&img, 1.0)?, img);
    assert_eq!(contrast(&img, 1.0)?, img);
    Ok(())
}

#[test]
fn colour_jitter_extremes() -> R {
    let img = busy(64, 64);
    // saturation 0: grey pixels at the Rec. 709 luma
    let grey = saturation(&img, 0.0)?;
    for (p, q) in img.pixels().zip(grey.pixels()) {
        assert!(q[0] == q[1] && q[1] == q[2], "{q:?} is not grey");
        let y = (0.2126 * f64::from(p[0]) + 0.7152 * f64::from(p[1]) + 0.0722 * f64::from(p[2]))
            .round();
        assert!((f64::from(q[0]) - y).abs() <= 1.0, "{p:?} -> {q:?}");
    }
    // a third of a turn about the grey axis permutes the channels
    let turned = hue_rotation(&img, 120.0)?;
    for (p, q) in img.pixels().zip(turned.pixels()) {
        assert_eq!(q.0, [p[2], p[0], p[1]]);
    }
    // contrast 0: mid-grey everywhere; contrast 2 doubles the distance from mid-grey
    assert!(contrast(&img, 0.0)?.as_raw().iter().all(|&b| b == 128));
    let c2 = contrast(&img, 2.0)?;
    for (&a, &b) in img.as_raw().iter().zip(c2.as_raw()) {
        let want = (127.5 + 2.0 * (f64::from(a) - 127.5)).clamp(0.0, 255.0);
        assert!((f64::from(b) - want).abs() <= 0.5 + 1e-3, "{a} -> {b}");
    }
    Ok(())
}

// ---------------------------------------------------------------- pipeline

#[test]
fn pipeline_off_is_an_exact_identity() -> R {
    let img = busy(50, 30);
    for seed in [0u64, 1, 42, u64::MAX] {
        assert_eq!(Photometric::identity().augment(&img, seed)?, img);
    }
    assert_eq!(PhotometricParams::identity().apply(&img)?, img);
    let lin = LinearRgb::from_srgb(&img)?;
    assert_eq!(PhotometricParams::identity().apply_linear(&lin)?, img);
    Ok(())
}

#[test]
fn default_pipeline_is_deterministic_per_seed() -> R {
    let img = busy(48, 32);
    let cfg = Photometric::default();
    let mut distinct = std::collections::HashSet::new();
    for seed in 0..8u64 {
        let a = cfg.augment(&img, seed)?;
        assert_eq!(a, cfg.augment(&img, seed)?);
        assert_eq!(a.dimensions(), img.dimensions());
        assert_eq!(cfg.draw(seed)?, cfg.draw(seed)?);
        distinct.insert(a.into_raw());
    }
    assert!(
        distinct.len() >= 6,
        "only {} distinct outputs",
        distinct.len()
    );
    Ok(())
}

#[test]
fn draws_stay_in_their_ranges() -> R {
    let cfg = Photometric {
        exposure_p: 1.0,
        vignetting_p: 1.0,
        blur_p: 1.0,
        white_balance_p: 1.0,
        noise_p: 1.0,
        contrast_p: 1.0,
        saturation_p: 1.0,
        hue_p: 1.0,
        jpeg_p: 1.0,
        ..Photometric::default()
    };
    let within = |v: f32, [lo, hi]: [f32; 2]| lo <= v && v <= hi;
    for seed in 0..300u64 {
        let p = cfg.draw(seed)?;
        let stops = p.exposure_gain.log2();
        assert!(within(
            stops,
            [cfg.exposure_stops[0] - 1e-5, cfg.exposure_stops[1] + 1e-5]
        ));
        assert!(within(p.vignetting_strength, cfg.vignetting_strength));
        assert!(within(p.blur_sigma_px, cfg.blur_sigma_px));
        let w = cfg.white_balance_stops + 1e-5;
        assert_eq!(p.white_balance_gains[1], 1.0);
        assert!(within(p.white_balance_gains[0].log2(), [-w, w]));
        assert!(within(p.white_balance_gains[2].log2(), [-w, w]));
        assert!(within(p.noise.shot_gain, cfg.noise_shot_gain));
        assert!(within(p.noise.read_sigma, cfg.noise_read_sigma));
        assert!(within(p.contrast, cfg.contrast));
        assert!(within(p.saturation, cfg.saturation));
        assert!(within(p.hue_deg, cfg.hue_deg));
        let q = p.jpeg_quality.ok_or("jpeg off")?;
        assert!((cfg.jpeg_quality[0]..=cfg.jpeg_quality[1]).contains(&q));
    }
    // probabilities are honoured: about half of the draws change the exposure by default
    let d = Photometric::default();
    let on = (0..1000u64)
        .filter(|&s| d.draw(s).map(|p| p.exposure_gain != 1.0).unwrap_or(false))
        .count();
    assert!((430..=570).contains(&on), "{on} of 1000 with p = 0.5");
    Ok(())
}

#[test]
fn config_serde() -> R {
    let d = Photometric::default();
    let json = serde_json::to_string(&d)?;
    assert_eq!(serde_json::from_str::<Photometric>(&json)?, d);
    let partial: Photometric = toml::from_str("blur_p = 1.0\nblur_sigma_px = [0.5, 2.0]\n")?;
    assert_eq!(
        partial,
        Photometric {
            blur_p: 1.0,
            blur_sigma_px: [0.5, 2.0],
            ..d
        }
    );
    assert!(toml::from_str::<Photometric>("blur_sigma = [0.5, 2.0]\n").is_err());
    let crop: CropZoomRange = toml::from_str("p = 1.0")?;
    assert_eq!(crop.scale, CropZoomRange::default().scale);
    Ok(())
}

// ---------------------------------------------------------------- bad input

#[test]
fn bad_input_is_an_error_not_a_panic() -> R {
    assert!(rgb_image_from_raw(4, 3, vec![0; 35]).is_err());
    assert!(rgb_image_from_raw(0, 3, vec![]).is_err());
    assert!(rgb_image_from_raw(4, 3, vec![0; 36]).is_ok());
    assert!(LinearRgb::new(4, 3, vec![0.0; 35]).is_err());
    assert!(LinearRgb::new(2, 1, vec![0.0, 0.0, f32::NAN, 0.0, 0.0, 0.0]).is_err());

    let empty = RgbImage::new(0, 0);
    let noise = SensorNoise {
        shot_gain: 0.0,
        read_sigma: 0.01,
    };
    assert!(exposure(&empty, 1.0).is_err());
    assert!(white_balance(&empty, [1.0; 3]).is_err());
    assert!(vignetting(&empty, 0.1).is_err());
    assert!(gaussian_blur(&empty, 1.0).is_err());
    assert!(sensor_noise(&empty, &noise, 0).is_err());
    assert!(contrast(&empty, 1.0).is_err());
    assert!(saturation(&empty, 1.0).is_err());
    assert!(hue_rotation(&empty, 0.0).is_err());
    assert!(jpeg_round_trip(&empty, 90).is_err());
    assert!(Photometric::identity().augment(&empty, 0).is_err());
    assert!(Photometric::default().augment(&empty, 0).is_err());

    let img = busy(8, 6);
    assert!(exposure(&img, f32::NAN).is_err());
    assert!(exposure(&img, -1.0).is_err());
    assert!(white_balance(&img, [1.0, f32::INFINITY, 1.0]).is_err());
    assert!(vignetting(&img, 1.5).is_err());
    assert!(gaussian_blur(&img, -0.1).is_err());
    assert!(gaussian_blur(&img, f32::NAN).is_err());
    assert!(gaussian_blur(&img, 1e9).is_err());
    let bad_noise = SensorNoise {
        shot_gain: -1.0,
        read_sigma: 0.0,
    };
    assert!(sensor_noise(&img, &bad_noise, 0).is_err());
    assert!(contrast(&img, f32::NAN).is_err());
    assert!(saturation(&img, -1.0).is_err());
    assert!(hue_rotation(&img, f32::INFINITY).is_err());
    assert!(jpeg_round_trip(&img, 0).is_err());
    assert!(jpeg_round_trip(&img, 101).is_err());
    let bad_cfg = Photometric {
        blur_p: 2.0,
        ..Photometric::default()
    };
    assert!(bad_cfg.draw(0).is_err());
    let bad_cfg = Photometric {
        jpeg_quality: [0, 50],
        ..Photometric::default()
    };
    assert!(bad_cfg.augment(&img, 0).is_err());

    // crop-and-zoom
    assert!(CropZoom::new(8, 6, 0.5, [0.0, 0.0]).is_err());
    assert!(CropZoom::new(8, 6, f32::NAN, [0.0, 0.0]).is_err());
    assert!(CropZoom::new(8, 6, f32::INFINITY, [0.0, 0.0]).is_err());
    assert!(CropZoom::new(8, 6, 100.0, [0.0, 0.0]).is_err());
    assert!(CropZoom::new(8, 6, 2.0, [4.5, 0.0]).is_err());
    assert!(CropZoom::new(8, 6, 2.0, [-1.0, 0.0]).is_err());
    assert!(CropZoom::new(8, 6, 2.0, [0.0, f32::NAN]).is_err());
    assert!(CropZoom::new(0, 6, 1.0, [0.0, 0.0]).is_err());
    assert!(CropZoom::draw(8, 6, [0.9, 1.2], 0).is_err());
    assert!(CropZoom::draw(8, 6, [1.3, 1.2], 0).is_err());
    let crop = CropZoom::new(8, 6, 2.0, [4.0, 3.0])?;
    assert!(crop.resample_nearest(&[0u16; 47], 8, 6).is_err());
    assert!(crop.resample_rgb(&busy(9, 6)).is_err());
    let cam = camera(8, 6)?;
    assert!(crop.camera(&camera(9, 6)?).is_err());
    assert!(crop_zoom(&img, &cam, Some(&[0; 10]), None, &crop).is_err());
    assert!(crop_zoom(&img, &cam, None, Some(&[0.0; 49]), &crop).is_err());
    let unchecked = CropZoom {
        scale: -3.0,
        ..crop
    };
    assert!(unchecked.resample_rgb(&img).is_err());
    Ok(())
}

// ---------------------------------------------------------------- crop and zoom

/// A KITTI-like camera (`P2` with a translation column) scaled to `w x h`, with a rotated extrinsic.
fn camera(w: u32, h: u32) -> Result<PinholeCamera, veila_geom::GeomError> {
    let f = 0.9 * w as f32;
    let p2 = [
        [f, 0.0, 0.52 * w as f32, 44.857_28],
        [0.0, f, 0.47 * h as f32, 0.216_379_1],
        [0.0, 0.0, 1.0, 0.002_745_884],
    ];
    // LiDAR x forward, y left, z up -> camera x right, y down, z forward
    let rot = Mat3::from_cols(
        Vec3::new(0.0, 0.0, 1.0),
        Vec3::new(-1.0, 0.0, 0.0),
        Vec3::new(0.0, -1.0, 0.0),
    );
    let t = Mat4::from_mat3(rot) * Mat4::from_rotation_z(0.05);
    PinholeCamera::new(p2, t, w, h)
}

#[test]
fn crop_identity_is_exact() -> R {
    let (w, h) = (40u32, 30u32);
    let img = busy(w, h);
    let cam = camera(w, h)?;
    let labels: Vec<u32> = (0..w * h).collect();
    let depth: Vec<f32> = (0..w * h).map(|i| (i % 7) as f32 * 1.5).collect();
    let out = crop_zoom(
        &img,
        &cam,
        Some(&labels),
        Some(&depth),
        &CropZoom::identity(w, h),
    )?;
    assert_eq!(out.image, img);
    assert_eq!(out.camera, cam);
    assert_eq!(out.labels.as_deref(), Some(&labels[..]));
    assert_eq!(out.depth_m.as_deref(), Some(&depth[..]));
    let never = CropZoomRange::identity().draw(w, h, 5)?;
    assert_eq!(never, CropZoom::identity(w, h));
    Ok(())
}

/// Intensity-weighted centroid of the red channel.
fn centroid(img: &RgbImage) -> (f64, f64) {
    let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for (x, y, p) in img.enumerate_pixels() {
        let v = f64::from(p[0]);
        s += v;
        sx += v * f64::from(x);
        sy += v * f64::from(y);
    }
    (sx / s, sy / s)
}

#[test]
fn a_point_lands_where_the_new_camera_projects_it() -> R {
    let (w, h) = (160u32, 120u32);
    let cam = camera(w, h)?;
    let points = [
        Vec3::new(12.0, 0.5, -0.4),
        Vec3::new(8.0, -1.2, 0.3),
        Vec3::new(20.0, 1.0, 0.6),
        Vec3::new(15.0, -0.2, -0.5),
        Vec3::new(10.0, 0.0, 0.0),
        Vec3::new(10.0, 3.0, 0.0),
        Vec3::new(12.0, 2.5, -0.3),
    ];
    for (scale, offset) in [
        (1.6f32, [23.3f32, 17.8f32]),
        (3.0, [50.0, 30.0]),
        (2.2, [0.0, 20.0]),
    ] {
        let crop = CropZoom::new(w, h, scale, offset)?;
        let new_cam = crop.camera(&cam)?;
        assert_eq!(new_cam.cam_from_lidar, cam.cam_from_lidar);
        let mut tested = 0;
        for &p in &points {
            let old = cam
                .try_project_in_image(p)
                .ok_or("point outside the old image")?;
            let new = cam_project(&new_cam, p)?;
            assert_eq!(old.depth_m, new.depth_m);
            // the zoomed dot must lie well inside the new image for its centroid to be unbiased
            let margin = 5.0 * 1.5 * scale;
            if new.u_px < margin
                || new.v_px < margin
                || new.u_px > w as f32 - 1.0 - margin
                || new.v_px > h as f32 - 1.0 - margin
            {
                continue;
            }
            tested += 1;
            // a Gaussian dot (sigma 1.5 px) at the old projection, sub-pixel
            let img = RgbImage::from_fn(w, h, |x, y| {
                let d2 = (x as f32 - old.u_px).powi(2) + (y as f32 - old.v_px).powi(2);
                let v = (255.0 * (-d2 / (2.0 * 1.5 * 1.5)).exp()).round() as u8;
                Rgb([v, 0, 0])
            });
            let (u0, v0) = centroid(&img);
            assert!(
                (u0 - f64::from(old.u_px)).abs() < 0.1 && (v0 - f64::from(old.v_px)).abs() < 0.1
            );
            let (u1, v1) = centroid(&crop.resample_rgb(&img)?);
            // within a fifth of a pixel (the brief asks for half; a pixel-centre slip of
            // (s - 1) / 2 would show here)
            assert!(
                (u1 - f64::from(new.u_px)).abs() < 0.2 && (v1 - f64::from(new.v_px)).abs() < 0.2,
                "scale {scale}: dot at ({u1}, {v1}), new camera says ({}, {})",
                new.u_px,
                new.v_px
            );
        }
        assert!(tested >= 2, "scale {scale}: only {tested} points tested");
    }
    Ok(())
}

fn cam_project(
    cam: &PinholeCamera,
    p: Vec3,
) -> Result<veila_geom::ImagePoint, Box<dyn std::error::Error>> {
    Ok(cam.try_project(p).ok_or("point behind the camera")?)
}

#[test]
fn labels_and_depth_follow_the_new_camera() -> R {
    let (w, h) = (96u32, 64u32);
    let cam = camera(w, h)?;
    let labels: Vec<u32> = (0..w * h).collect();
    let depth: Vec<f32> = (0..w * h)
        .map(|i| {
            if i % 13 == 0 {
                0.0
            } else {
                4.0 + (i % 17) as f32
            }
        })
        .collect();
    let img = busy(w, h);
    for seed in 0..6u64 {
        let crop = CropZoom::draw(w, h, [1.0, 2.5], seed)?;
        let out = crop_zoom(&img, &cam, Some(&labels), Some(&depth), &crop)?;
        let (lab, dep) = (out.labels.ok_or("labels")?, out.depth_m.ok_or("depth")?);
        for j in 0..h {
            for i in 0..w {
                let k = (j * w + i) as usize;
                let src = lab[k];
                // depth values are copied from the source pixel, never mixed or rescaled
                assert_eq!(dep[k].to_bits(), depth[src as usize].to_bits());
                let (sx, sy) = ((src % w) as f32, (src / w) as f32);
                // back-project through the new camera, project through the old one: the source pixel
                // is the nearest one
                let d = if dep[k] > 0.0 { dep[k] } else { 10.0 };
                let p = out
                    .camera
                    .try_back_project(i as f32, j as f32, d)
                    .ok_or("back-project")?;
                let q = cam.try_project(p).ok_or("project")?;
                let tol = 0.5 + 2e-3;
                let (cu, cv) = (
                    q.u_px.clamp(0.0, (w - 1) as f32),
                    q.v_px.clamp(0.0, (h - 1) as f32),
                );
                assert!(
                    (cu - sx).abs() <= tol && (cv - sy).abs() <= tol,
                    "seed {seed}, pixel ({i}, {j}): source ({sx}, {sy}), old camera ({}, {})",
                    q.u_px,
                    q.v_px
                );
            }
        }
        // u16 maps work the same way
        let l16: Vec<u16> = labels.iter().map(|&l| l as u16).collect();
        let r16 = crop.resample_nearest(&l16, w, h)?;
        assert!(r16.iter().zip(&lab).all(|(&a, &b)| u32::from(a) == b));
    }
    Ok(())
}

#[test]
fn crop_draws_are_valid_and_seeded() -> R {
    let (w, h) = (97u32, 41u32);
    let range = [1.1f32, 1.9];
    for seed in 0..200u64 {
        let c = CropZoom::draw(w, h, range, seed)?;
        assert_eq!(c, CropZoom::draw(w, h, range, seed)?);
        assert!(range[0] <= c.scale && c.scale <= range[1]);
        c.validate()?;
        assert!(c.offset_px[0] >= 0.0 && c.offset_px[0] <= w as f32 - w as f32 / c.scale);
        assert!(c.offset_px[1] >= 0.0 && c.offset_px[1] <= h as f32 - h as f32 / c.scale);
    }
    assert_ne!(
        CropZoom::draw(w, h, range, 1)?,
        CropZoom::draw(w, h, range, 2)?
    );
    let always = CropZoomRange {
        p: 1.0,
        scale: range,
    };
    assert!(always.draw(w, h, 3)?.scale >= 1.1);
    Ok(())
}
