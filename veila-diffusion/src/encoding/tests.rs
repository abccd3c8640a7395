use super::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Closed form written independently of the implementation (f64).
fn r2dm_expected(r: f64, r_max: f64) -> f64 {
    2.0 * ((r.min(r_max) + 1.0).ln() / (r_max + 1.0).ln()) - 1.0
}

#[test]
fn range_encoding_matches_closed_form_and_round_trips() {
    let e = RangeEncoding::kitti();
    for &r in &[1e-3f32, 0.5, 1.45, 2.0, 5.3, 17.0, 42.42, 79.9, 80.0] {
        let v = e.encode_range(r);
        let want = r2dm_expected(r as f64, 80.0);
        assert!(
            (v as f64 - want).abs() < 1e-6,
            "encode({r}) = {v}, want {want}"
        );
        let back = e.decode_range(v);
        assert!(
            (back - r).abs() <= 2e-5 * r.max(1.0),
            "round trip {r} -> {v} -> {back}"
        );
    }
    assert_eq!(e.encode_range(80.0), 1.0);
    assert_eq!(e.encode_range(500.0), 1.0, "ranges beyond r_max clamp");
    assert_eq!(e.encode_range(0.0), -1.0);
    assert_eq!(e.encode_range(-3.0), -1.0);
    assert_eq!(e.encode_range(f32::NAN), -1.0);
    assert_eq!(e.encode_range(f32::INFINITY), -1.0);
    assert_eq!(e.decode_range(-1.0), 0.0);
    assert!((e.decode_range(1.0) - 80.0).abs() < 1e-4);
    assert!(
        (e.decode_range(7.0) - 80.0).abs() < 1e-4,
        "decode clamps to [-1, 1]"
    );
    assert!(e.decode_range(f32::NAN).is_nan());
}

#[test]
fn intensity_encoding_round_trips_and_clamps() {
    let e = RangeEncoding {
        intensity_max: 255.0,
        ..RangeEncoding::kitti()
    };
    for &i in &[0.0f32, 1.0, 100.0, 254.0, 255.0] {
        let v = e.encode_intensity(i);
        assert!((v - (2.0 * i / 255.0 - 1.0)).abs() < 1e-6);
        assert!((e.decode_intensity(v) - i).abs() < 1e-3);
    }
    assert_eq!(e.encode_intensity(1000.0), 1.0);
    assert_eq!(e.encode_intensity(-5.0), -1.0);
    assert_eq!(e.encode_intensity(f32::NAN), -1.0);
    assert_eq!(e.decode_intensity(f32::NAN), 0.0);
}

fn random_scan(rows: usize, cols: usize, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<bool>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n = rows * cols;
    let mut range = Vec::with_capacity(n);
    let mut inten = Vec::with_capacity(n);
    let mut mask = Vec::with_capacity(n);
    for _ in 0..n {
        range.push(rng.random_range(1.5f32..80.0));
        inten.push(rng.random_range(0.0f32..1.0));
        mask.push(rng.random::<f32>() > 0.2);
    }
    (range, inten, mask)
}

fn image(
    rows: usize,
    cols: usize,
    range: &[f32],
    intensity: &[f32],
    mask: &[bool],
) -> veila_geom::RangeImage {
    let mut img = veila_geom::RangeImage::new_empty(rows as u32, cols as u32);
    img.range_m = range.to_vec();
    img.intensity = intensity.to_vec();
    img.mask = mask.to_vec();
    img
}

#[test]
fn scan_round_trip_keeps_mask_range_and_intensity() -> Result<()> {
    let (rows, cols) = (4, 16);
    let e = RangeEncoding::kitti();
    let (range, inten, mask) = random_scan(rows, cols, 1);
    let (range2, inten2, mask2) = random_scan(rows, cols, 2);
    let scans = [
        image(rows, cols, &range, &inten, &mask),
        image(rows, cols, &range2, &inten2, &mask2),
    ];
    let x = e.encode_batch(&[&scans[0], &scans[1]], &Device::Cpu)?;
    assert_eq!(x.dims(), &[2, 3, rows, cols]);
    let v = x.flatten_all()?.to_vec1::<f32>()?;
    assert!(v.iter().all(|x| (-1.0..=1.0).contains(x)));
    let dec = e.decode_batch(&x)?;
    for (s, (r, i, m)) in dec
        .iter()
        .zip([(&range, &inten, &mask), (&range2, &inten2, &mask2)])
    {
        assert_eq!(&s.mask, m);
        for p in 0..rows * cols {
            if m[p] {
                assert!((s.range_m[p] - r[p]).abs() < 1e-4 * r[p], "range px {p}");
                assert!((s.intensity[p] - i[p]).abs() < 1e-5, "intensity px {p}");
            } else {
                assert_eq!((s.range_m[p], s.intensity[p]), (0.0, 0.0));
            }
        }
    }
    Ok(())
}

#[test]
fn dropped_rays_are_minus_one_everywhere() -> Result<()> {
    let e = RangeEncoding::kitti();
    let range = [10.0, f32::NAN, 0.0, 20.0];
    let mask = [false, true, true, true];
    let v = e.encode_to_vec(&image(1, 4, &range, &[0.0; 4], &mask))?;
    // pixel 0: masked out; 1: NaN range; 2: zero range -> dropped; 3: valid with zero intensity
    for c in 0..3 {
        for p in 0..3 {
            assert_eq!(v[c * 4 + p], -1.0, "channel {c} pixel {p}");
        }
    }
    assert_eq!(v[2 * 4 + 3], 1.0);
    assert_eq!(v[4 + 3], -1.0, "intensity 0 encodes to -1");
    Ok(())
}

#[test]
fn decode_uses_raydrop_threshold_and_survives_nan() -> Result<()> {
    let e = RangeEncoding::kitti();
    let n = 5;
    // range, intensity, raydrop channels
    let range = [0.5f32, 0.5, f32::NAN, -1.0, 0.5];
    let inten = [0.0f32, f32::NAN, 0.0, 0.0, 0.0];
    let drop = [0.3f32, 0.01, 1.0, 1.0, -0.2];
    let data: Vec<f32> = range.iter().chain(&inten).chain(&drop).copied().collect();
    let x = Tensor::from_vec(data, (1, 3, 1, n), &Device::Cpu)?;
    let s = &e.decode_batch(&x)?[0];
    // NaN range -> missing; range -1 -> 0 m < min range -> missing; ray-drop <= 0 -> missing
    assert_eq!(s.mask, vec![true, true, false, false, false]);
    assert!(s.range_m.iter().all(|r| r.is_finite()));
    assert!(s.intensity.iter().all(|r| r.is_finite()));
    assert_eq!(s.intensity[1], 0.0, "NaN intensity decodes to 0");
    Ok(())
}

#[test]
fn without_raydrop_channel_short_ranges_are_drops() -> Result<()> {
    let e = RangeEncoding {
        raydrop: false,
        intensity: false,
        ..RangeEncoding::kitti()
    };
    assert_eq!(e.num_channels(), 1);
    let vals = [
        e.encode_range(1.0),
        e.encode_range(1.5),
        e.encode_range(30.0),
        -1.0,
    ];
    let x = Tensor::from_vec(vals.to_vec(), (1, 1, 1, 4), &Device::Cpu)?;
    let s = &e.decode_batch(&x)?[0];
    assert_eq!(s.mask, vec![false, true, true, false]);
    Ok(())
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let e = RangeEncoding::kitti();
    let mut short = veila_geom::RangeImage::new_empty(2, 2);
    short.range_m.pop();
    let err = e.encode_to_vec(&short).unwrap_err();
    assert!(err.to_string().contains("range_m"), "{err}");
    let x = Tensor::zeros((1, 2, 2, 2), candle_core::DType::F32, &Device::Cpu).unwrap();
    assert!(matches!(e.decode_batch(&x), Err(Error::Shape { .. })));
    assert!(e.encode_batch(&[], &Device::Cpu).is_err());
    for bad in [
        RangeEncoding {
            max_range_m: 0.0,
            ..RangeEncoding::kitti()
        },
        RangeEncoding {
            min_range_m: 90.0,
            ..RangeEncoding::kitti()
        },
        RangeEncoding {
            intensity_max: f32::NAN,
            ..RangeEncoding::kitti()
        },
        RangeEncoding {
            raydrop_threshold: 1.0,
            ..RangeEncoding::kitti()
        },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
    }
}

#[test]
fn geom_range_image_round_trip() -> Result<()> {
    let mut img = veila_geom::RangeImage::new_empty(2, 8);
    for (p, r) in [(0usize, 5.0f32), (3, 12.5), (9, 70.0), (15, 2.0)] {
        img.range_m[p] = r;
        img.intensity[p] = 0.25;
        img.mask[p] = true;
    }
    let e = RangeEncoding::kitti();
    let x = e.encode_batch(&[&img], &Device::Cpu)?;
    let back = e.decode_batch(&x)?.remove(0);
    assert_eq!(back.mask, img.mask);
    assert_eq!(back.num_valid(), 4);
    assert!(back.point_index.iter().all(|&i| i == veila_geom::NO_POINT));
    for p in 0..16 {
        assert!((back.range_m[p] - img.range_m[p]).abs() < 1e-4 * img.range_m[p].max(1.0));
        assert!((back.intensity[p] - img.intensity[p]).abs() < 1e-6);
    }
    Ok(())
}
