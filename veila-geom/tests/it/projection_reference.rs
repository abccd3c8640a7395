//! The projection against the independent brute-force `f64` implementation of equation 1 in
//! `common`: real scans (skipped when absent) and many random points, exact and fast paths, every
//! sensor mode, and bit-identical results for every thread count.

use crate::common::*;
use glam::Vec3;
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_geom::{
    AngleMethod, BeamLayout, LidarSensor, NO_POINT, OutOfFov, PixelOutcome, ProjectionOptions,
    Projector, RowSource,
};

/// A disagreement between the exact path and the `f64` reference is acceptable only where `f64`
/// itself cannot decide: the point lies within this many pixels of a row or column boundary in the
/// reference's own `u` / `v` (f64 atan2 / asin and the formula round at ~1e-16 relative, so a few
/// 1e-13 pixels at 64 x 1024 is already generous).
const AMBIGUOUS_PX: f64 = 1e-9;

/// Compare one point; returns Ok(true) on agreement, Ok(false) on an f64-ambiguous disagreement.
fn compare_point(
    pr: &Projector,
    sensor: &LidarSensor,
    p: Vec3,
    ring: Option<u16>,
    tol: f64,
    clamp: bool,
) -> Result<bool, String> {
    let got = pr.locate(p, ring);
    let r = reference_pixel(sensor, p, ring, tol, clamp);
    let same = match (got, r.outcome) {
        (
            PixelOutcome::Pixel {
                row,
                col,
                clamped,
                range_m,
            },
            RefOutcome::Pixel {
                row: rr,
                col: rc,
                range,
                clamped: rcl,
            },
        ) => {
            assert_eq!(range_m, range as f32, "range of {p:?}");
            (row, col, clamped) == (rr, rc, rcl)
        }
        (PixelOutcome::NonFinite, RefOutcome::NonFinite)
        | (PixelOutcome::ZeroRange, RefOutcome::ZeroRange)
        | (PixelOutcome::TooNear, RefOutcome::TooNear)
        | (PixelOutcome::TooFar, RefOutcome::TooFar)
        | (PixelOutcome::AboveFov, RefOutcome::AboveFov)
        | (PixelOutcome::BelowFov, RefOutcome::BelowFov)
        | (PixelOutcome::BadRing, RefOutcome::BadRing) => true,
        _ => false,
    };
    if same {
        return Ok(true);
    }
    // judge: on a column boundary (u), a row boundary (uniform v) or a field-of-view edge
    let near_u = dist_to_integer(r.u) < AMBIGUOUS_PX;
    let near_v = matches!(sensor.beams, BeamLayout::Uniform) && dist_to_integer(r.v) < AMBIGUOUS_PX;
    if near_u || near_v {
        Ok(false)
    } else {
        Err(format!(
            "{p:?} (ring {ring:?}): projector {got:?}, reference {:?} (u {}, v {})",
            r.outcome, r.u, r.v
        ))
    }
}

/// Random points over the whole sphere and a wide range of ranges, some outside the field of view
/// and the valid range.
fn random_points(n: usize, seed: u64) -> Vec<Vec3> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let az = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
            let el = rng.random_range(-0.7f64..0.25);
            let r = 10f64.powf(rng.random_range(-0.5..2.2));
            Vec3::new(
                (r * el.cos() * az.cos()) as f32,
                (r * el.cos() * az.sin()) as f32,
                (r * el.sin()) as f32,
            )
        })
        .collect()
}

/// Points placed close to row and column boundaries: the hardest inputs for the filter.
fn boundary_points(sensor: &LidarSensor, n: usize, seed: u64) -> Vec<Vec3> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let up = (sensor.fov_up_deg as f64).to_radians();
    let down = (sensor.fov_down_deg as f64).to_radians();
    (0..n)
        .map(|i| {
            let (h, w) = (sensor.rows as f64, sensor.cols as f64);
            let c = rng.random_range(0..=sensor.cols) as f64;
            let r = rng.random_range(0..=sensor.rows) as f64;
            // offsets from 1e-7 to 3e-2 pixels, log-uniform, either side: below, around and above the
            // error bound of the projector's f32 filter (a few 1e-3 px)
            let jitter = |rng: &mut ChaCha8Rng| {
                let m = 10f64.powf(rng.random_range(-7.0..-1.5));
                if rng.random_bool(0.5) { m } else { -m }
            };
            let az = std::f64::consts::PI * (1.0 - 2.0 * (c + jitter(&mut rng)) / w);
            let el = if i % 2 == 0 {
                up - (r + jitter(&mut rng)) / h * (up - down)
            } else {
                rng.random_range(down..up)
            };
            let d = rng.random_range(1.0..100.0);
            Vec3::new(
                (d * el.cos() * az.cos()) as f32,
                (d * el.cos() * az.sin()) as f32,
                (d * el.sin()) as f32,
            )
        })
        .collect()
}

fn check_all(
    sensor: &LidarSensor,
    opts: ProjectionOptions,
    pts: &[Vec3],
    rings: Option<&[u16]>,
) -> (usize, usize) {
    let pr = Projector::new(sensor, opts).unwrap();
    let clamp = opts.out_of_fov == OutOfFov::ClampToEdgeRows;
    let mut ambiguous = 0;
    for (i, p) in pts.iter().enumerate() {
        match compare_point(
            &pr,
            sensor,
            *p,
            rings.map(|r| r[i]),
            opts.edge_tolerance_rad as f64,
            clamp,
        ) {
            Ok(true) => {}
            Ok(false) => ambiguous += 1,
            Err(e) => panic!("{e}"),
        }
    }
    (pts.len(), ambiguous)
}

#[test]
fn exact_matches_reference_on_random_points_every_mode() {
    let pts = random_points(60_000, 1);
    let nearest = per_beam_nearest_sensor();
    for sensor in [
        LidarSensor::hdl64e(),
        LidarSensor::hdl32e(),
        nearest.clone(),
    ] {
        for out_of_fov in [OutOfFov::Reject, OutOfFov::ClampToEdgeRows] {
            for tol in [0.0f32, 1e-6] {
                let opts = ProjectionOptions {
                    out_of_fov,
                    angles: AngleMethod::Exact,
                    edge_tolerance_rad: tol,
                };
                let (n, amb) = check_all(&sensor, opts, &pts, None);
                // random points essentially never sit within 1e-9 px of a boundary
                assert_eq!(amb, 0, "{n} points, {amb} ambiguous ({sensor:?})");
            }
        }
    }
}

#[test]
fn exact_matches_reference_near_boundaries() {
    for sensor in [LidarSensor::hdl64e(), LidarSensor::hdl32e()] {
        let pts = boundary_points(&sensor, 60_000, 2);
        let (n, amb) = check_all(&sensor, ProjectionOptions::default(), &pts, None);
        println!(
            "{}x{}: {n} boundary points, {amb} within {AMBIGUOUS_PX} px of a boundary in f64",
            sensor.rows, sensor.cols
        );
        assert!(amb * 1000 < n, "too many ambiguous points: {amb}");
    }
}

#[test]
fn ring_mode_matches_reference() {
    let sensor = LidarSensor::hdl32e_per_beam();
    let pts = random_points(20_000, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    // rings 0..=40: some invalid
    let rings: Vec<u16> = (0..pts.len()).map(|_| rng.random_range(0..41)).collect();
    let (_, amb) = check_all(&sensor, ProjectionOptions::default(), &pts, Some(&rings));
    assert_eq!(amb, 0);
    // and without rings every in-range, in-view point is a bad ring
    let pr = Projector::new(&sensor, ProjectionOptions::default()).unwrap();
    let (img, stats) = pr.project(&pts, None, None).unwrap();
    assert_eq!(img.num_valid(), 0);
    let refs: Vec<RefPoint> = pts
        .iter()
        .map(|p| reference_pixel(&sensor, *p, None, 1e-6, false))
        .collect();
    assert_eq!(
        rejections_array(&stats.rejected),
        reference_rejections(&refs)
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, rng_seed: proptest::test_runner::RngSeed::Fixed(7), ..ProptestConfig::default() })]

    /// Any finite f32 point (including huge, tiny and axis-aligned ones) agrees with the reference.
    #[test]
    fn exact_matches_reference_on_arbitrary_points(
        x in prop_oneof![-200.0f32..200.0, Just(0.0f32), Just(-0.0f32), -1e-30f32..1e-30],
        y in prop_oneof![-200.0f32..200.0, Just(0.0f32), Just(-0.0f32), -1e-30f32..1e-30],
        z in prop_oneof![-60.0f32..20.0, Just(0.0f32), Just(-0.0f32)],
    ) {
        let p = Vec3::new(x, y, z);
        for sensor in [LidarSensor::hdl64e(), per_beam_nearest_sensor()] {
            let pr = Projector::new(&sensor, ProjectionOptions::default()).unwrap();
            let r = compare_point(&pr, &sensor, p, None, 1e-6, false);
            prop_assert!(r.is_ok(), "{}", r.unwrap_err());
        }
    }
}

/// Project a real scan and check the whole image and every count against the reference.
fn check_real_scan(rel: &str) {
    let Some(path) = real_file(rel) else { return };
    let (pts, refl) = read_kitti_bin(&path);
    let sensor = LidarSensor::hdl64e();
    let pr = Projector::new(&sensor, ProjectionOptions::default()).unwrap();
    let (img, stats) = pr.project(&pts, Some(&refl), None).unwrap();

    let refs: Vec<RefPoint> = pts
        .iter()
        .map(|p| reference_pixel(&sensor, *p, None, 1e-6, false))
        .collect();
    let ref_img = reference_image(&refs, sensor.cols);
    assert_eq!(
        rejections_array(&stats.rejected),
        reference_rejections(&refs),
        "{rel}: rejections"
    );
    assert_eq!(img.num_valid(), ref_img.len(), "{rel}: occupied pixels");
    assert_eq!(stats.written, ref_img.len());
    let candidates = refs
        .iter()
        .filter(|r| matches!(r.outcome, RefOutcome::Pixel { .. }))
        .count();
    assert_eq!(stats.occluded, candidates - ref_img.len());
    assert_eq!(
        stats.input,
        stats.written + stats.occluded + stats.rejected.total()
    );
    for (k, (range, idx)) in &ref_img {
        assert!(img.mask[*k]);
        assert_eq!(
            img.point_index[*k], *idx as u32,
            "{rel}: winner of pixel {k}"
        );
        assert_eq!(img.range_m[*k], *range as f32);
        assert_eq!(img.intensity[*k], refl[*idx]);
    }
    for k in 0..img.num_pixels() {
        assert_eq!(img.mask[k], img.point_index[k] != NO_POINT);
        assert!(img.range_m[k].is_finite() && img.intensity[k].is_finite());
    }
    println!(
        "{rel}: {} points, {} occupied pixels, {} occluded, rejected {:?}",
        pts.len(),
        stats.written,
        stats.occluded,
        stats.rejected
    );

    // the fast path: count the points in a different pixel (the benchmark prints the same figure)
    let fast = Projector::new(
        &sensor,
        ProjectionOptions {
            angles: AngleMethod::Fast,
            ..Default::default()
        },
    )
    .unwrap();
    let moved = pts
        .iter()
        .filter(|p| fast.try_pixel(**p, None) != pr.try_pixel(**p, None))
        .count();
    println!(
        "{rel}: fast path puts {moved} of {} points into another pixel",
        pts.len()
    );
    assert!(
        moved * 200 < pts.len(),
        "fast path misplaces {moved} points"
    );
}

#[test]
fn real_kitti_000000_matches_reference() {
    check_real_scan("kitti/training/velodyne/000000.bin");
}

#[test]
fn real_kitti_000001_matches_reference() {
    check_real_scan("kitti/training/velodyne/000001.bin");
}

#[test]
fn real_semantickitti_000000_matches_reference() {
    check_real_scan("semantickitti/sequences/00/velodyne/000000.bin");
}

#[test]
fn real_scan_has_the_documented_point_counts() {
    for (rel, n) in [
        ("kitti/training/velodyne/000000.bin", 115_384),
        ("kitti/training/velodyne/000001.bin", 120_268),
        ("semantickitti/sequences/00/velodyne/000000.bin", 124_668),
    ] {
        let Some(path) = real_file(rel) else { continue };
        assert_eq!(read_kitti_bin(&path).0.len(), n, "{rel}");
    }
}

#[test]
fn threads_give_bit_identical_results() {
    // a real scan when present, else random points; with duplicates and bad points mixed in
    let mut pts = match real_file("kitti/training/velodyne/000000.bin") {
        Some(p) => read_kitti_bin(&p).0,
        None => random_points(100_000, 5),
    };
    let dup: Vec<Vec3> = pts.iter().step_by(7).copied().collect();
    pts.extend(dup);
    pts.extend([Vec3::NAN, Vec3::ZERO, Vec3::new(1e6, 0.0, 0.0)]);
    let inten: Vec<f32> = (0..pts.len()).map(|i| (i % 97) as f32).collect();
    for angles in [AngleMethod::Exact, AngleMethod::Fast] {
        for sensor in [LidarSensor::hdl64e(), per_beam_nearest_sensor()] {
            let pr = Projector::new(
                &sensor,
                ProjectionOptions {
                    angles,
                    ..Default::default()
                },
            )
            .unwrap();
            let serial = pr.project(&pts, Some(&inten), None).unwrap();
            for t in [2, 3, 8] {
                let par = pr
                    .clone()
                    .with_threads(t)
                    .project(&pts, Some(&inten), None)
                    .unwrap();
                assert_eq!(serial, par, "{t} threads, {angles:?}");
            }
            // and locate() agrees with project() point by point
            let (img, _) = &serial;
            for (k, &i) in img.point_index.iter().enumerate() {
                if i != NO_POINT {
                    let (r, c) = pr.try_pixel(pts[i as usize], None).unwrap();
                    assert_eq!(img.idx(r, c), k);
                }
            }
        }
    }
}

#[test]
fn ring_sensor_keeps_edge_rings_of_real_nuscenes_like_elevations() {
    // nuScenes' top ring scatters about +-0.2 deg around its nominal 10.66 deg: the per-beam preset's
    // field of view reaches half a beam spacing beyond the outer beams, so none of it is rejected
    let sensor = LidarSensor::hdl32e_per_beam();
    let pr = Projector::new(&sensor, ProjectionOptions::default()).unwrap();
    for (el_deg, ring) in [(10.87f64, 31u16), (10.45, 31), (-30.89, 0), (-30.4, 0)] {
        let el = el_deg.to_radians();
        let p = Vec3::new((10.0 * el.cos()) as f32, 0.3, (10.0 * el.sin()) as f32);
        let expected_row = if ring == 31 { 0 } else { 31 };
        assert_eq!(
            pr.try_pixel(p, Some(ring)).map(|x| x.0),
            Some(expected_row),
            "{el_deg} deg"
        );
    }
    match &sensor.beams {
        BeamLayout::PerBeam { row_source, .. } => assert_eq!(*row_source, RowSource::Ring),
        BeamLayout::Uniform => panic!("per-beam expected"),
    }
}
