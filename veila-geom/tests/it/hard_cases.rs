//! Hard inputs, one test each, with the documented outcome. Every test also checks that no output
//! holds a NaN and nothing panics.

use glam::{Mat4, Vec3};
use veila_geom::{
    AngleMethod, EpipolarConfig, EpipolarTable, GeomError, LidarSensor, OutOfFov, PinholeCamera,
    PixelOutcome, ProjectionOptions, ProjectionStats, Projector, RangeImage, RayTable,
};

fn project_all(pts: &[Vec3], opts: ProjectionOptions) -> (RangeImage, ProjectionStats) {
    let pr = Projector::new(&LidarSensor::hdl64e(), opts).unwrap();
    let (img, stats) = pr.project(pts, None, None).unwrap();
    assert_no_nan(&img);
    assert_eq!(
        stats.input,
        stats.written + stats.occluded + stats.rejected.total()
    );
    (img, stats)
}

fn assert_no_nan(img: &RangeImage) {
    assert!(
        img.range_m
            .iter()
            .chain(&img.intensity)
            .all(|v| v.is_finite())
    );
}

fn both_methods() -> [ProjectionOptions; 2] {
    [
        ProjectionOptions::default(),
        ProjectionOptions {
            angles: AngleMethod::Fast,
            ..Default::default()
        },
    ]
}

#[test]
fn point_at_origin_is_rejected_as_zero_range() {
    for opts in both_methods() {
        let (img, stats) = project_all(&[Vec3::ZERO, Vec3::new(-0.0, 0.0, -0.0)], opts);
        assert_eq!(stats.rejected.zero_range, 2);
        assert_eq!(img.num_valid(), 0);
    }
    // zero range is reported even when the minimum range is 0
    let mut s = LidarSensor::hdl64e();
    s.min_range_m = 0.0;
    let pr = Projector::new(&s, ProjectionOptions::default()).unwrap();
    assert_eq!(pr.locate(Vec3::ZERO, None), PixelOutcome::ZeroRange);
}

#[test]
fn huge_coordinates_are_too_far_and_never_overflow() {
    let pts = [
        Vec3::new(1e6, 0.0, 0.0),
        Vec3::new(-1e6, -1e6, 1e6),
        Vec3::new(1e30, -1e30, 0.0),
        Vec3::new(f32::MAX, f32::MAX, f32::MAX),
        Vec3::new(-f32::MAX, 0.0, f32::MIN),
    ];
    for opts in both_methods() {
        let (_, stats) = project_all(&pts, opts);
        assert_eq!(stats.rejected.too_far, pts.len(), "{stats:?}");
    }
    // with a sensor whose valid range reaches that far, they project to the reference pixel
    let mut s = LidarSensor::hdl64e();
    s.max_range_m = f32::MAX;
    let pr = Projector::new(
        &s,
        ProjectionOptions {
            out_of_fov: OutOfFov::ClampToEdgeRows,
            ..Default::default()
        },
    )
    .unwrap();
    for p in pts {
        let r = crate::common::reference_pixel(&s, p, None, 1e-6, true);
        match (pr.locate(p, None), r.outcome) {
            (
                PixelOutcome::Pixel {
                    row, col, range_m, ..
                },
                crate::common::RefOutcome::Pixel {
                    row: rr,
                    col: rc,
                    range,
                    ..
                },
            ) => {
                assert_eq!((row, col), (rr, rc), "{p:?}");
                assert_eq!(range_m, range as f32);
                assert!(range_m.is_finite() || range > f32::MAX as f64, "{p:?}");
            }
            // |(f32::MAX, f32::MAX, f32::MAX)| = 5.9e38 m exceeds even max_range_m = f32::MAX
            (PixelOutcome::TooFar, crate::common::RefOutcome::TooFar) => {
                assert!(p.as_dvec3().length() > f32::MAX as f64)
            }
            other => panic!("{p:?}: {other:?}"),
        }
    }
}

#[test]
fn azimuth_seam_lands_in_column_zero_for_both_zeros() {
    // atan2(+0, x<0) = +pi gives u = 0; atan2(-0, x<0) = -pi gives u = w, which wraps to 0 as well
    for opts in both_methods() {
        let pr = Projector::new(&LidarSensor::hdl64e(), opts).unwrap();
        for y in [0.0f32, -0.0] {
            for x in [-1.0f32, -10.0, -100.0] {
                let (_, col) = pr.try_pixel(Vec3::new(x, y, 0.05 * x), None).unwrap();
                assert_eq!(col, 0, "y = {y:?}, x = {x}, {:?}", opts.angles);
            }
        }
        // just either side of the seam: column 0 (above) and column w - 1 (below); the fast path's
        // f32 u = 1024 - 1.6e-5 rounds to 1024 and wraps to column 0 (documented imprecision)
        assert_eq!(
            pr.try_pixel(Vec3::new(-10.0, 1e-6, -0.5), None).unwrap().1,
            0
        );
        let below = pr.try_pixel(Vec3::new(-10.0, -1e-6, -0.5), None).unwrap().1;
        match opts.angles {
            AngleMethod::Exact => assert_eq!(below, 1023),
            AngleMethod::Fast => assert!(below == 1023 || below == 0),
        }
        // x = -0.0 on the y axis: atan2(+-1, -0) = +-pi/2: columns 256 and 768 exactly (u = 256, 768)
        assert_eq!(
            pr.try_pixel(Vec3::new(-0.0, 10.0, -0.5), None).unwrap().1,
            256
        );
        assert_eq!(
            pr.try_pixel(Vec3::new(-0.0, -10.0, -0.5), None).unwrap().1,
            768
        );
        assert_eq!(
            pr.try_pixel(Vec3::new(0.0, 10.0, -0.5), None).unwrap().1,
            256
        );
        // +x axis: u = w/2 exactly, column 512; the diagonal x = y: u = 384 exactly
        assert_eq!(
            pr.try_pixel(Vec3::new(10.0, 0.0, -0.5), None).unwrap().1,
            512
        );
        assert_eq!(
            pr.try_pixel(Vec3::new(10.0, -0.0, -0.5), None).unwrap().1,
            512
        );
        assert_eq!(
            pr.try_pixel(Vec3::new(7.0, 7.0, -0.5), None).unwrap().1,
            384
        );
        assert_eq!(
            pr.try_pixel(Vec3::new(-7.0, -7.0, -0.5), None).unwrap().1,
            896
        );
    }
}

#[test]
fn points_exactly_on_the_field_of_view_edges_land_in_the_edge_rows() {
    // the edges are closed (v = 0 -> row 0, v = h -> row h - 1), widened by edge_tolerance_rad (1e-6)
    // so that an f32 point whose exact elevation is the edge, rounded, still lands there
    let s = LidarSensor::hdl64e();
    for opts in both_methods() {
        let pr = Projector::new(&s, opts).unwrap();
        for (deg, row) in [(3.0f64, 0u32), (-25.0, 63)] {
            let el = deg.to_radians();
            for az in [0.3f64, 2.0, -2.9] {
                let p = Vec3::new(
                    (20.0 * el.cos() * az.cos()) as f32,
                    (20.0 * el.cos() * az.sin()) as f32,
                    (20.0 * el.sin()) as f32,
                );
                assert_eq!(pr.try_pixel(p, None).map(|x| x.0), Some(row), "{deg} deg");
            }
            // 1e-4 rad beyond the edge: rejected (or clamped)
            let beyond = if row == 0 { el + 1e-4 } else { el - 1e-4 };
            let p = Vec3::new(
                (20.0 * beyond.cos()) as f32,
                0.0,
                (20.0 * beyond.sin()) as f32,
            );
            let expected = if row == 0 {
                PixelOutcome::AboveFov
            } else {
                PixelOutcome::BelowFov
            };
            assert_eq!(pr.locate(p, None), expected);
            let clamp = Projector::new(
                &s,
                ProjectionOptions {
                    out_of_fov: OutOfFov::ClampToEdgeRows,
                    ..opts
                },
            )
            .unwrap();
            assert!(
                matches!(clamp.locate(p, None), PixelOutcome::Pixel { row: r, clamped: true, .. } if r == row)
            );
        }
    }
    // with zero tolerance an elevation of exactly 0 (z = 0), a boundary of hdl32e's rows
    // (10 - 8 * 40/32 = 0 deg), lands in the row below it, as floor(v) with v = 8 says
    let s = LidarSensor::hdl32e();
    let pr = Projector::new(
        &s,
        ProjectionOptions {
            edge_tolerance_rad: 0.0,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(pr.try_pixel(Vec3::new(10.0, 3.0, 0.0), None).unwrap().0, 8);
    assert_eq!(pr.try_pixel(Vec3::new(10.0, 3.0, -0.0), None).unwrap().0, 8);
    assert_eq!(pr.try_pixel(Vec3::new(10.0, 3.0, 1e-6), None).unwrap().0, 7);
}

#[test]
fn nan_and_infinite_coordinates_are_rejected_as_non_finite() {
    let pts = [
        Vec3::new(f32::NAN, 1.0, 1.0),
        Vec3::new(1.0, f32::NAN, 1.0),
        Vec3::new(1.0, 1.0, f32::NAN),
        Vec3::new(f32::INFINITY, 0.0, 0.0),
        Vec3::new(0.0, f32::NEG_INFINITY, 0.0),
        Vec3::new(5.0, 0.0, f32::INFINITY),
        Vec3::NAN,
        Vec3::new(10.0, 0.0, -1.0), // a good one
    ];
    for opts in both_methods() {
        let (img, stats) = project_all(&pts, opts);
        assert_eq!(stats.rejected.non_finite, 7);
        assert_eq!(stats.written, 1);
        assert_eq!(
            img.point_index[img.mask.iter().position(|m| *m).unwrap()],
            7
        );
    }
    // a non-finite intensity rejects its point too
    let pr = Projector::new(&LidarSensor::hdl64e(), ProjectionOptions::default()).unwrap();
    let p = [Vec3::new(10.0, 0.0, -1.0), Vec3::new(10.0, 5.0, -1.0)];
    let (img, stats) = pr.project(&p, Some(&[f32::NAN, 0.5]), None).unwrap();
    assert_eq!((stats.rejected.non_finite, stats.written), (1, 1));
    assert_no_nan(&img);
}

#[test]
fn subnormal_coordinates_are_handled_exactly() {
    // subnormal f32 squares are exact in f64: the range is tiny but not zero
    let tiny = f32::from_bits(1); // 1.4e-45
    let pts = [
        Vec3::new(tiny, 0.0, 0.0),
        Vec3::new(-tiny, tiny, -tiny),
        Vec3::new(1e-40, -3e-41, 2e-42),
    ];
    for opts in both_methods() {
        let (_, stats) = project_all(&pts, opts);
        assert_eq!(stats.rejected.too_near, 3);
    }
    // with min_range 0 they are valid points and project to the reference pixel (direction only)
    let mut s = LidarSensor::hdl64e();
    s.min_range_m = 0.0;
    let pr = Projector::new(
        &s,
        ProjectionOptions {
            out_of_fov: OutOfFov::ClampToEdgeRows,
            ..Default::default()
        },
    )
    .unwrap();
    for p in pts {
        let r = crate::common::reference_pixel(&s, p, None, 1e-6, true);
        match (pr.locate(p, None), r.outcome) {
            (
                PixelOutcome::Pixel {
                    row, col, range_m, ..
                },
                crate::common::RefOutcome::Pixel {
                    row: rr, col: rc, ..
                },
            ) => {
                assert_eq!((row, col), (rr, rc), "{p:?}");
                assert!(range_m.is_finite() && range_m >= 0.0);
            }
            other => panic!("{p:?}: {other:?}"),
        }
    }
    // a normal point with a subnormal y sits just beside the seam or the x axis
    assert_eq!(
        pr.try_pixel(Vec3::new(-10.0, tiny, -1.0), None).unwrap().1,
        0
    );
    assert_eq!(
        pr.try_pixel(Vec3::new(-10.0, -tiny, -1.0), None).unwrap().1,
        1023
    );
    assert_eq!(
        pr.try_pixel(Vec3::new(10.0, tiny, -1.0), None).unwrap().1,
        511
    );
    assert_eq!(
        pr.try_pixel(Vec3::new(10.0, -tiny, -1.0), None).unwrap().1,
        512
    );
}

#[test]
fn duplicate_points_go_to_the_lowest_index() {
    let p = Vec3::new(12.0, -3.0, -1.0);
    let near = Vec3::new(6.0, -1.5, -0.5); // same pixel, nearer
    let pts = [Vec3::new(1.0, 50.0, 0.0), p, p, p, near, near];
    let inten = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5];
    for opts in both_methods() {
        let pr = Projector::new(&LidarSensor::hdl64e(), opts).unwrap();
        let (img, stats) = pr.project(&pts[..4], Some(&inten[..4]), None).unwrap();
        let (r, c) = pr.try_pixel(p, None).unwrap();
        let k = img.idx(r, c);
        assert_eq!(
            (img.point_index[k], img.intensity[k], stats.occluded),
            (1, 0.1, 2)
        );
        // a nearer point wins; among equal nearer points again the lowest index
        let (img, _) = pr.project(&pts, Some(&inten), None).unwrap();
        assert_eq!(img.point_index[k], 4);
        // and reversing the order changes the winner only among equals
        let rev: Vec<Vec3> = pts.iter().rev().copied().collect();
        let (img, _) = pr.project(&rev, None, None).unwrap();
        assert_eq!(img.point_index[k], 0); // index 0 of the reversed cloud is `near`
    }
}

#[test]
fn every_point_behind_the_camera_projects_to_none() {
    let cam = PinholeCamera::new(
        [
            [700.0, 0.0, 600.0, 0.0],
            [0.0, 700.0, 180.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
        // camera looking along LiDAR +x
        Mat4::from_cols_array_2d(&[
            [0.0, 0.0, 1.0, 0.0],
            [-1.0, 0.0, 0.0, 0.0],
            [0.0, -1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]),
        1200,
        360,
    )
    .unwrap();
    let mut n = 0;
    for i in 0..2000 {
        let t = i as f32 * 0.37;
        // x <= near: behind or on the near plane, including points whose mirror image would land
        // inside the image
        let p = Vec3::new(-(t % 50.0), (t * 1.3).sin() * 20.0, (t * 0.7).cos() * 3.0);
        assert!(cam.try_project(p).is_none(), "{p:?}");
        assert!(cam.try_project_in_image(p).is_none());
        n += 1;
    }
    assert_eq!(n, 2000);
    // the mirror of a visible point is not visible
    let visible = Vec3::new(20.0, 1.0, 0.5);
    assert!(cam.try_project_in_image(visible).is_some());
    assert!(cam.try_project(-visible).is_none());
}

#[test]
fn degenerate_intrinsics_are_errors() {
    let t = Mat4::IDENTITY;
    for k in [
        [
            [0.0, 0.0, 600.0, 0.0],
            [0.0, 700.0, 180.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ], // fx = 0
        [
            [700.0, 0.0, 600.0, 0.0],
            [0.0, 0.0, 180.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ], // fy = 0
        [
            [700.0, 0.0, 600.0, 0.0],
            [700.0, 0.0, 600.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ], // rank 2
        [[0.0; 4]; 3],
        [
            [f32::NAN, 0.0, 600.0, 0.0],
            [0.0, 700.0, 180.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
    ] {
        assert!(
            matches!(
                PinholeCamera::new(k, t, 100, 100),
                Err(GeomError::InvalidCamera(_))
            ),
            "{k:?}"
        );
    }
    let good = [
        [700.0, 0.0, 600.0, 0.0],
        [0.0, 700.0, 180.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    assert!(PinholeCamera::new(good, t, 0, 100).is_err());
    assert!(PinholeCamera::new(good, Mat4::ZERO, 100, 100).is_err());
    let cam = PinholeCamera::new(good, t, 100, 100).unwrap();
    assert!(cam.with_near_m(0.0).validate().is_err());
    assert!(cam.with_near_m(f32::NAN).validate().is_err());
}

#[test]
fn near_plane_boundary_is_exclusive() {
    // identity extrinsic: camera z = LiDAR z; near plane 0.5 m
    let k = [
        [500.0, 0.0, 50.0, 0.0],
        [0.0, 500.0, 50.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    let cam = PinholeCamera::new(k, Mat4::IDENTITY, 100, 100)
        .unwrap()
        .with_near_m(0.5);
    assert!(
        cam.try_project(Vec3::new(0.0, 0.0, 0.5)).is_none(),
        "at the near plane"
    );
    assert!(cam.try_project(Vec3::new(0.0, 0.0, 0.4999)).is_none());
    let ip = cam.try_project(Vec3::new(0.01, 0.0, 0.5001)).unwrap();
    assert!(ip.u_px.is_finite() && (ip.u_px - (50.0 + 500.0 * 0.01 / 0.5001)).abs() < 1e-3);
    assert!(cam.try_project(Vec3::new(0.0, 0.0, 0.0)).is_none());
    assert!(cam.try_project(Vec3::new(1.0, 1.0, -0.0)).is_none());
    assert!(cam.try_project(Vec3::new(f32::NAN, 0.0, 1.0)).is_none());
    assert!(cam.try_back_project(f32::NAN, 0.0, 1.0).is_none());
}

#[test]
fn epipolar_table_of_a_camera_looking_away_is_all_invalid() {
    // camera looking along LiDAR -z (at the sky... from below: straight down through the ground),
    // no sample of the hdl64e's rays (elevation <= 3 deg, depths >= 2 m) is in front of it within
    // the image: every weight is zero and the grid stays finite
    let s = LidarSensor::hdl64e();
    let rays = RayTable::new(&s).unwrap();
    // camera z axis = LiDAR +z (up): samples at elevation <= 3 deg have camera depth <= 0.05 d,
    // and those in front project far outside a narrow image
    let t = Mat4::from_cols_array_2d(&[
        [1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]);
    let k = [
        [100.0, 0.0, 32.0, 0.0],
        [0.0, 100.0, 32.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    let cam = PinholeCamera::new(k, t, 64, 64).unwrap();
    let cfg = EpipolarConfig {
        num_samples: 8,
        ..Default::default()
    };
    let table = EpipolarTable::build(&rays, &cam, &cfg).unwrap();
    assert!(table.valid.iter().all(|v| !v));
    assert!(table.weight.iter().all(|w| *w == 0.0));
    assert!(
        table
            .grid
            .iter()
            .all(|g| g[0].is_finite() && g[1].is_finite())
    );
    assert!(table.any_valid_mask().iter().all(|v| !v));
    assert!(cam.frustum_mask(&rays).iter().all(|v| !v));
    let g = table.bilinear_gather(16, 16);
    assert!(g.weights.iter().all(|w| *w == [0.0; 4]));
}

#[test]
fn mismatched_buffers_are_errors_not_panics() {
    let pr = Projector::new(&LidarSensor::hdl64e(), ProjectionOptions::default()).unwrap();
    let pts = [Vec3::X * 10.0; 3];
    assert!(matches!(
        pr.project(&pts, Some(&[1.0]), None),
        Err(GeomError::LengthMismatch {
            what: "intensity",
            ..
        })
    ));
    assert!(matches!(
        pr.project(&pts, None, Some(&[1, 2])),
        Err(GeomError::LengthMismatch { what: "rings", .. })
    ));
    let rays = RayTable::new(&LidarSensor::hdl32e()).unwrap();
    let img = RangeImage::new_empty(64, 1024);
    assert!(rays.unproject(&img).is_err());
    let mut bad = RangeImage::new_empty(32, 1024);
    bad.mask.pop();
    assert!(rays.unproject(&bad).is_err());
    let (img, _) = pr.project(&pts, None, None).unwrap();
    let mut img2 = img.clone();
    assert!(img2.gather_labels(&[]).is_err());
    assert!(
        Projector::new(
            &LidarSensor::hdl64e(),
            ProjectionOptions {
                edge_tolerance_rad: f32::NAN,
                ..Default::default()
            }
        )
        .is_err()
    );
    assert!(
        Projector::new(
            &LidarSensor::hdl64e(),
            ProjectionOptions {
                edge_tolerance_rad: -1.0,
                ..Default::default()
            }
        )
        .is_err()
    );
}

#[test]
fn tiny_widths_use_the_exact_seam_rules() {
    // w = 1: one column; w = 2: column 0 holds (0, pi], column 1 holds (-pi, 0]
    for (w, cases) in [
        (
            1u32,
            vec![
                (Vec3::new(1.0, 0.0, 0.0), 0u32),
                (Vec3::new(-1.0, -0.0, 0.0), 0),
            ],
        ),
        (
            2,
            vec![
                (Vec3::new(1.0, 1.0, 0.0), 0),
                (Vec3::new(-1.0, 0.0, 0.0), 0),
                (Vec3::new(-1.0, -0.0, 0.0), 0),
                (Vec3::new(1.0, 0.0, 0.0), 1),
                (Vec3::new(1.0, -1.0, 0.0), 1),
            ],
        ),
        (
            3,
            vec![
                (Vec3::new(1.0, 0.0, 0.0), 1),
                (Vec3::new(-1.0, -0.0, 0.0), 0),
                (Vec3::new(-1.0, -1e-3, 0.0), 2),
            ],
        ),
    ] {
        let s = LidarSensor {
            cols: w,
            ..LidarSensor::hdl64e()
        };
        let pr = Projector::new(
            &s,
            ProjectionOptions {
                out_of_fov: OutOfFov::ClampToEdgeRows,
                ..Default::default()
            },
        )
        .unwrap();
        for (p, col) in cases {
            let p = p * 10.0;
            assert_eq!(pr.try_pixel(p, None).unwrap().1, col, "w = {w}, {p:?}");
            let r = crate::common::reference_pixel(&s, p, None, 1e-6, true);
            assert!(
                matches!(r.outcome, crate::common::RefOutcome::Pixel { col: c, .. } if c == col),
                "reference, w = {w}, {p:?}"
            );
        }
    }
}
