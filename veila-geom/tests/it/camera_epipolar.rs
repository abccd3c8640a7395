//! Cameras on real KITTI calibration, epipolar tables against brute force, bilinear taps, depth
//! spacing closed forms, frustum mask, Fourier encoding and sensor (de)serialisation.

use crate::common::*;
use glam::{Mat4, Vec3};
use veila_geom::{
    BeamLayout, DepthSpacing, EpipolarConfig, EpipolarTable, FourierEncoding, GeomError,
    LidarSensor, PinholeCamera, RayTable, Region, RowSource,
};

fn kitti_image_count(idx: &str, width: u32, height: u32) {
    let (Some(scan), Some(calib)) = (
        real_file(&format!("kitti/training/velodyne/{idx}.bin")),
        real_file(&format!("kitti/training/calib/{idx}.txt")),
    ) else {
        return;
    };
    let (pts, _) = read_kitti_bin(&scan);
    let c = read_kitti_calib(&calib);
    let cam =
        PinholeCamera::from_kitti(c.p2_f32(), c.r0_mat3(), c.tr_f32(), width, height).unwrap();
    let got = pts
        .iter()
        .filter(|p| cam.try_project_in_image(**p).is_some())
        .count();
    // brute force in f64: w > near, pixel inside [-0.5, W - 0.5) x [-0.5, H - 0.5)
    let mut expected = 0;
    let mut borderline = 0;
    for p in &pts {
        let (u, v, w) = c.project_f64(*p);
        if w <= cam.near_m as f64 {
            continue;
        }
        let (u, v) = (u / w, v / w);
        let inside = u >= -0.5 && v >= -0.5 && u < width as f64 - 0.5 && v < height as f64 - 0.5;
        expected += usize::from(inside);
        // f32 vs f64 matrices may disagree within ~1e-3 px of the border
        let margin = (u + 0.5)
            .abs()
            .min((v + 0.5).abs())
            .min((u - width as f64 + 0.5).abs())
            .min((v - height as f64 + 0.5).abs());
        borderline += usize::from(margin < 1e-2);
    }
    println!(
        "KITTI {idx}: {got} of {} points in image_2 ({width}x{height}), f64 brute force {expected}",
        pts.len()
    );
    assert!(
        got.abs_diff(expected) <= borderline,
        "{got} vs {expected} (borderline {borderline})"
    );
    // the data README says "about 19-20k"; the exact counts are 20,259 (000000) and 18,608 (000001)
    // (also reproduced with numpy: P2 @ R0 @ Tr in float64, w > 0.1, same pixel bounds)
    assert!(
        (18_000..=21_000).contains(&got),
        "about 19-20k points expected, got {got}"
    );
}

#[test]
fn kitti_000000_about_20k_points_in_image_2() {
    kitti_image_count("000000", 1224, 370);
}

#[test]
fn kitti_000001_about_20k_points_in_image_2() {
    kitti_image_count("000001", 1242, 375);
}

fn test_camera() -> PinholeCamera {
    // camera looking along LiDAR +x, 0.3 m above and 0.2 m behind the LiDAR, 320 x 96
    let base = Mat4::from_cols_array_2d(&[
        [0.0, 0.0, 1.0, 0.0],
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]);
    let t = base * Mat4::from_translation(Vec3::new(0.2, 0.0, -0.3));
    PinholeCamera::new(
        [
            [160.0, 0.0, 159.5, 0.0],
            [0.0, 160.0, 47.5, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
        t,
        320,
        96,
    )
    .unwrap()
}

#[test]
fn epipolar_grid_matches_brute_force_projection() {
    let sensor = LidarSensor {
        rows: 16,
        cols: 256,
        ..LidarSensor::hdl64e()
    };
    let rays = RayTable::new(&sensor).unwrap();
    let cam = test_camera();
    let cfg = EpipolarConfig {
        num_samples: 6,
        near_m: 1.0,
        far_m: 60.0,
        spacing: DepthSpacing::Log,
        tau_m: 20.0,
    };
    let t = EpipolarTable::build(&rays, &cam, &cfg).unwrap();
    assert_eq!(t.grid.len(), 16 * 256 * 6);
    let (k34, tt) = (cam.intrinsics.as_dmat4(), cam.cam_from_lidar.as_dmat4());
    let mut n_valid = 0;
    for row in 0..16 {
        for col in 0..256 {
            for k in 0..6 {
                let i = t.sample_idx(row, col, k);
                let p = t.sample_point_lidar(row, col, k);
                assert!(
                    (p.as_dvec3() - rays.dir(row, col).as_dvec3() * t.depths_m[k] as f64).length()
                        < 1e-4
                );
                // brute force in f64
                let pc = tt * p.as_dvec3().extend(1.0);
                let q = k34 * pc;
                let (u, v) = (q.x / q.z, q.y / q.z);
                let valid = q.z > cam.near_m as f64
                    && pc.z > 0.0
                    && u >= -0.5
                    && v >= -0.5
                    && u < 319.5
                    && v < 95.5;
                let border = (u + 0.5)
                    .abs()
                    .min((u - 319.5).abs())
                    .min((v + 0.5).abs())
                    .min((v - 95.5).abs())
                    < 1e-3;
                if border {
                    continue;
                }
                assert_eq!(t.valid[i], valid, "({row}, {col}, {k})");
                let w_expected = if valid {
                    (-(t.depths_m[k] as f64) / 20.0).exp()
                } else {
                    0.0
                };
                assert!((t.weight[i] as f64 - w_expected).abs() < 1e-6);
                if valid {
                    n_valid += 1;
                    // align_corners = false: x_n = (2u + 1) / W - 1
                    let (xn, yn) = ((2.0 * u + 1.0) / 320.0 - 1.0, (2.0 * v + 1.0) / 96.0 - 1.0);
                    assert!(
                        (t.grid[i][0] as f64 - xn).abs() < 1e-4
                            && (t.grid[i][1] as f64 - yn).abs() < 1e-4
                    );
                    assert!(t.grid[i][0].abs() <= 1.0 && t.grid[i][1].abs() <= 1.0);
                } else {
                    assert!(t.grid[i][0].is_finite() && t.grid[i][1].is_finite());
                }
            }
        }
    }
    assert!(
        n_valid > 1000,
        "the test camera must see a good part of the samples: {n_valid}"
    );
}

#[test]
fn frustum_mask_matches_far_samples() {
    // a pixel's ray seen by the camera at infinity is seen at a very far sample (the offset of the
    // camera is negligible there), and vice versa, except within a hair of the image border
    let sensor = LidarSensor {
        rows: 16,
        cols: 256,
        ..LidarSensor::hdl64e()
    };
    let rays = RayTable::new(&sensor).unwrap();
    let cam = test_camera();
    let mask = cam.frustum_mask(&rays);
    let far = EpipolarConfig {
        num_samples: 1,
        near_m: 1e5,
        far_m: 2e5,
        spacing: DepthSpacing::Uniform,
        tau_m: 1.0,
    };
    let t = EpipolarTable::build(&rays, &cam, &far).unwrap();
    let disagree = mask.iter().zip(&t.valid).filter(|(a, b)| a != b).count();
    assert!(disagree <= 2, "{disagree} pixels disagree");
    assert!(mask.iter().filter(|m| **m).count() > 100);
    // rays seen by the camera point forward
    for (k, m) in mask.iter().enumerate() {
        if *m {
            assert!(rays.dirs()[k].x > 0.0);
        }
    }
}

#[test]
fn bilinear_gather_weights_and_linear_reproduction() {
    let sensor = LidarSensor {
        rows: 8,
        cols: 128,
        ..LidarSensor::hdl64e()
    };
    let rays = RayTable::new(&sensor).unwrap();
    let cam = test_camera();
    let cfg = EpipolarConfig {
        num_samples: 5,
        near_m: 2.0,
        far_m: 40.0,
        spacing: DepthSpacing::Inverse,
        tau_m: 30.0,
    };
    let t = EpipolarTable::build(&rays, &cam, &cfg).unwrap();
    for (fh, fw) in [(24usize, 80usize), (12, 40), (96, 320)] {
        let g = t.bilinear_gather(fh, fw);
        // feature map f(x, y) = 3 x - 2 y + 5 at pixel centres (x, y integer indices)
        let f = |idx: u32| {
            let (y, x) = ((idx as usize / fw) as f64, (idx as usize % fw) as f64);
            3.0 * x - 2.0 * y + 5.0
        };
        let mut interior = 0;
        for (i, (idx, w)) in g.indices.iter().zip(&g.weights).enumerate() {
            if !t.valid[i] {
                assert_eq!(*w, [0.0; 4]);
                continue;
            }
            let x = ((t.grid[i][0] as f64 + 1.0) * fw as f64 - 1.0) / 2.0;
            let y = ((t.grid[i][1] as f64 + 1.0) * fh as f64 - 1.0) / 2.0;
            let sum: f64 = w.iter().map(|v| *v as f64).sum();
            assert!(w.iter().all(|v| *v >= 0.0) && sum <= 1.0 + 1e-5);
            if x >= 0.0 && y >= 0.0 && x <= (fw - 1) as f64 && y <= (fh - 1) as f64 {
                interior += 1;
                assert!((sum - 1.0).abs() < 1e-5, "interior weights sum to {sum}");
                let interp: f64 = idx.iter().zip(w).map(|(k, w)| f(*k) * *w as f64).sum();
                let exact = 3.0 * x - 2.0 * y + 5.0;
                assert!(
                    (interp - exact).abs() < 1e-3 * (1.0 + exact.abs()),
                    "{interp} vs {exact}"
                );
            }
        }
        assert!(interior > 100);
    }
}

#[test]
fn depth_spacings_follow_their_closed_forms() {
    let (n, f, k) = (2.0f64, 80.0f64, 9usize);
    for spacing in [
        DepthSpacing::Uniform,
        DepthSpacing::Log,
        DepthSpacing::Inverse,
    ] {
        let cfg = EpipolarConfig {
            num_samples: k,
            near_m: n as f32,
            far_m: f as f32,
            spacing,
            tau_m: 10.0,
        };
        let d = cfg.depths_m();
        assert_eq!(d.len(), k);
        for (i, di) in d.iter().enumerate() {
            let t = i as f64 / (k - 1) as f64;
            let expected = match spacing {
                DepthSpacing::Uniform => n + t * (f - n),
                DepthSpacing::Log => n * (f / n).powf(t),
                DepthSpacing::Inverse => 1.0 / ((1.0 - t) / n + t / f),
            };
            assert!(
                (*di as f64 - expected).abs() < 1e-5 * expected,
                "{spacing:?} {i}: {di} vs {expected}"
            );
        }
        assert!(d.windows(2).all(|w| w[1] > w[0]));
        // log: constant ratio; inverse: constant step in 1/d; uniform: constant step
        let steps: Vec<f64> = d
            .windows(2)
            .map(|w| match spacing {
                DepthSpacing::Uniform => (w[1] - w[0]) as f64,
                DepthSpacing::Log => (w[1] / w[0]) as f64,
                DepthSpacing::Inverse => 1.0 / w[0] as f64 - 1.0 / w[1] as f64,
            })
            .collect();
        assert!(
            steps
                .iter()
                .all(|s| (s - steps[0]).abs() < 1e-4 * steps[0].abs())
        );
    }
    let one = EpipolarConfig {
        num_samples: 1,
        ..Default::default()
    };
    assert_eq!(one.depths_m(), vec![one.near_m]);
    for bad in [
        EpipolarConfig {
            num_samples: 0,
            ..Default::default()
        },
        EpipolarConfig {
            near_m: 0.0,
            ..Default::default()
        },
        EpipolarConfig {
            far_m: 1.0,
            ..Default::default()
        },
        EpipolarConfig {
            tau_m: f32::NAN,
            ..Default::default()
        },
    ] {
        assert!(
            matches!(bad.validate(), Err(GeomError::InvalidConfig { .. })),
            "{bad:?}"
        );
    }
}

#[test]
fn fourier_encoding_matches_closed_form() {
    let enc = FourierEncoding {
        num_freqs: 6,
        scale: 0.05,
        include_input: true,
    };
    enc.validate().unwrap();
    assert_eq!(enc.dim(), 39);
    for p in [
        Vec3::new(1.0, -2.0, 0.5),
        Vec3::new(80.0, -35.0, 3.0),
        Vec3::ZERO,
    ] {
        let mut out = Vec::new();
        enc.encode(p, &mut out);
        assert_eq!(out.len(), enc.dim());
        let sc = 0.05f32 as f64; // the f32 scale, exactly
        let q = [p.x as f64 * sc, p.y as f64 * sc, p.z as f64 * sc];
        for a in 0..3 {
            assert!((out[a] as f64 - q[a]).abs() < 1e-6);
        }
        for l in 0..6 {
            let freq = std::f64::consts::PI * 2f64.powi(l as i32);
            for a in 0..3 {
                let s = out[3 + 6 * l + a] as f64;
                let c = out[3 + 6 * l + 3 + a] as f64;
                assert!((s - (freq * q[a]).sin()).abs() < 1e-6, "sin l={l} a={a}");
                assert!((c - (freq * q[a]).cos()).abs() < 1e-6, "cos l={l} a={a}");
            }
        }
    }
    let no_input = FourierEncoding {
        include_input: false,
        ..enc
    };
    let mut out = vec![7.0];
    no_input.encode(Vec3::ONE, &mut out);
    assert_eq!(out.len(), 1 + 36);
    assert_eq!(out[0], 7.0, "encode appends");
    assert!(FourierEncoding { scale: 0.0, ..enc }.validate().is_err());
    assert!(
        FourierEncoding {
            num_freqs: 33,
            ..enc
        }
        .validate()
        .is_err()
    );
}

#[test]
fn region_split_is_x_positive_front() {
    assert!(Region::Front.contains(Vec3::new(1e-6, 0.0, 0.0)));
    assert!(!Region::Front.contains(Vec3::new(0.0, 5.0, 0.0)));
    assert!(Region::Rear.contains(Vec3::new(0.0, 5.0, 0.0)));
    assert!(Region::Rear.contains(Vec3::new(-0.0, 5.0, 0.0)));
    assert!(!Region::Front.contains(Vec3::NAN) && !Region::Rear.contains(Vec3::NAN));
    assert!(Region::All.contains(Vec3::NAN));
}

#[test]
fn sensors_round_trip_through_toml() {
    for s in [
        LidarSensor::hdl64e(),
        LidarSensor::hdl32e(),
        LidarSensor::hdl32e_per_beam(),
        per_beam_nearest_sensor(),
    ] {
        let text = toml::to_string(&s).unwrap();
        let back: LidarSensor = toml::from_str(&text).unwrap();
        assert_eq!(back, s, "{text}");
        back.validate().unwrap();
    }
    // a hand-written file: `beams` defaults to uniform; unknown keys are rejected
    let s: LidarSensor = toml::from_str(
        "rows = 64\ncols = 1024\nfov_up_deg = 3.0\nfov_down_deg = -25.0\nmin_range_m = 0.5\nmax_range_m = 120.0\n",
    )
    .unwrap();
    assert_eq!(s, LidarSensor::hdl64e());
    let per_beam: LidarSensor = toml::from_str(
        "rows = 2\ncols = 8\nfov_up_deg = 1.0\nfov_down_deg = -1.0\nmin_range_m = 0.0\nmax_range_m = 10.0\n\
         [beams]\nkind = \"per_beam\"\nelevations_deg = [0.5, -0.5]\nrow_source = \"nearest_elevation\"\n",
    )
    .unwrap();
    assert_eq!(
        per_beam.beams,
        BeamLayout::PerBeam {
            elevations_deg: vec![0.5, -0.5],
            row_source: RowSource::NearestElevation
        }
    );
    assert!(toml::from_str::<LidarSensor>("rows = 64\ncols = 1024\nfov_up_deg = 3.0\nfov_down_deg = -25.0\nmin_range_m = 0.5\nmax_range_m = 120.0\ncolumns = 3\n").is_err());
}

#[test]
fn invalid_sensors_are_rejected_with_a_reason() {
    let base = LidarSensor::hdl64e();
    let per_beam = |el: Vec<f32>| LidarSensor {
        rows: el.len() as u32,
        beams: BeamLayout::PerBeam {
            elevations_deg: el,
            row_source: RowSource::NearestElevation,
        },
        ..base.clone()
    };
    let cases = [
        (
            LidarSensor {
                rows: 0,
                ..base.clone()
            },
            "size",
        ),
        (
            LidarSensor {
                cols: 0,
                ..base.clone()
            },
            "size",
        ),
        (
            LidarSensor {
                fov_up_deg: f32::NAN,
                ..base.clone()
            },
            "finite",
        ),
        (
            LidarSensor {
                fov_up_deg: -30.0,
                ..base.clone()
            },
            "greater",
        ),
        (
            LidarSensor {
                fov_up_deg: 95.0,
                ..base.clone()
            },
            "within",
        ),
        (
            LidarSensor {
                min_range_m: 200.0,
                ..base.clone()
            },
            "range",
        ),
        (
            LidarSensor {
                min_range_m: -1.0,
                ..base.clone()
            },
            "range",
        ),
        (
            LidarSensor {
                max_range_m: f32::INFINITY,
                ..base.clone()
            },
            "range",
        ),
        (
            LidarSensor {
                rows: 3,
                ..per_beam(vec![1.0, 0.0])
            },
            "entries",
        ),
        (per_beam(vec![1.0, f32::NAN]), "not finite"),
        (per_beam(vec![1.0, -30.0]), "outside"),
        (per_beam(vec![1.0, 0.0, 0.5]), "monotone"),
        (per_beam(vec![1.0, 1.0]), "monotone"),
    ];
    for (s, needle) in cases {
        match s.validate() {
            Err(GeomError::InvalidSensor(msg)) => {
                assert!(msg.contains(needle), "{msg:?} should mention {needle:?}")
            }
            other => panic!("{s:?}: {other:?}"),
        }
        assert!(RayTable::new(&s).is_err());
    }
    per_beam(vec![2.0, 1.0, -3.0]).validate().unwrap();
    per_beam(vec![-3.0, 1.0, 2.0]).validate().unwrap();
}

#[test]
fn resized_camera_maps_pixel_centres_like_the_image_resize() {
    let p2 = [
        [721.5, 0.0, 609.6, 44.9],
        [0.0, 721.5, 172.9, 0.2],
        [0.0, 0.0, 1.0, 0.003],
    ];
    let cam = PinholeCamera::new(p2, glam::Mat4::IDENTITY, 1242, 375).unwrap();
    let small = cam.resized(320, 96).unwrap();
    let (sx, sy) = (320.0 / 1242.0f32, 96.0 / 375.0f32);
    for p in [
        glam::Vec3::new(1.0, -0.5, 10.0),
        glam::Vec3::new(-4.0, 1.5, 30.0),
        glam::Vec3::new(0.1, 0.2, 3.0),
    ] {
        let a = cam.try_project(p).unwrap();
        let b = small.try_project(p).unwrap();
        // the centre of pixel u maps to the centre of the resized pixel: (u + 0.5) s - 0.5
        assert!(
            (b.u_px - ((a.u_px + 0.5) * sx - 0.5)).abs() < 1e-3,
            "{a:?} {b:?}"
        );
        assert!(
            (b.v_px - ((a.v_px + 0.5) * sy - 0.5)).abs() < 1e-3,
            "{a:?} {b:?}"
        );
        assert!((b.depth_m - a.depth_m).abs() < 1e-5);
    }
    assert_eq!((small.width, small.height), (320, 96));
    assert!(cam.resized(0, 10).is_none());
    let same = cam.resized(1242, 375).unwrap();
    assert!(same.intrinsics.abs_diff_eq(cam.intrinsics, 1e-4));
}
