//! Round trips: points -> pixels -> points within a bound derived from the pixel's angular size,
//! every ray-table direction back to its own pixel, camera project / back-project.

use crate::common::per_beam_nearest_sensor;
use glam::{Mat3, Mat4, Vec3};
use proptest::prelude::*;
use std::f64::consts::PI;
use veila_geom::{BeamLayout, LidarSensor, PinholeCamera, ProjectionOptions, Projector, RayTable};

/// Largest angle between a point and the centre ray of its pixel: half a column in azimuth plus the
/// largest distance from a row's centre elevation to the edges of its band (uniform: half a row;
/// per-beam: up to the midpoint to the next beam or the field-of-view edge), plus f32 slack.
fn pixel_angular_radius(sensor: &LidarSensor) -> f64 {
    let half_col = std::f64::consts::PI / sensor.cols as f64;
    let up = (sensor.fov_up_deg as f64).to_radians();
    let down = (sensor.fov_down_deg as f64).to_radians();
    let half_row = match &sensor.beams {
        BeamLayout::Uniform => 0.5 * (up - down) / sensor.rows as f64,
        BeamLayout::PerBeam { elevations_deg, .. } => {
            let mut e: Vec<f64> = elevations_deg
                .iter()
                .map(|d| (*d as f64).to_radians())
                .collect();
            e.sort_by(f64::total_cmp);
            let mut worst: f64 = (e[0] - down).max(up - e[e.len() - 1]);
            for p in e.windows(2) {
                worst = worst.max(0.5 * (p[1] - p[0]));
            }
            worst
        }
    };
    // along a circle of latitude the azimuth step shrinks by cos(el) <= 1: the sum bounds the angle
    half_col + half_row + 1e-6
}

fn roundtrip_one(sensor: &LidarSensor, p: Vec3, ring: Option<u16>) -> Result<(), TestCaseError> {
    let pr = Projector::new(sensor, ProjectionOptions::default()).unwrap();
    let rays = RayTable::new(sensor).unwrap();
    let (img, stats) = pr
        .project(&[p], None, ring.map(|r| vec![r]).as_deref())
        .unwrap();
    prop_assert_eq!(stats.written, 1, "{:?} rejected: {:?}", p, stats.rejected);
    let back = rays.unproject(&img).unwrap();
    prop_assert_eq!(back.points.len(), 1);
    let q = back.points[0];
    let d = p.as_dvec3().length();
    // same range (f32 rounding), angle within the pixel's angular radius
    prop_assert!(
        (q.as_dvec3().length() - d).abs() <= 1e-6 * d + 1e-6,
        "range {} vs {}",
        q.length(),
        d
    );
    let angle = p.as_dvec3().angle_between(q.as_dvec3());
    let bound = pixel_angular_radius(sensor);
    prop_assert!(angle <= bound, "angle {angle} > bound {bound} for {p:?}");
    // and the chord: |p - q| <= 2 d sin(bound / 2)
    prop_assert!((p - q).as_dvec3().length() <= 2.0 * d * (bound / 2.0).sin() + 1e-5 * d);
    Ok(())
}

/// A point of the given direction angles and range.
fn point(az: f64, el: f64, d: f64) -> Vec3 {
    Vec3::new(
        (d * el.cos() * az.cos()) as f32,
        (d * el.cos() * az.sin()) as f32,
        (d * el.sin()) as f32,
    )
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 1500, rng_seed: proptest::test_runner::RngSeed::Fixed(11), ..ProptestConfig::default() })]

    #[test]
    fn uniform_roundtrip_hdl64e(az in -PI..PI, t in 0.0005f64..0.9995, d in 0.6f64..119.0) {
        let s = LidarSensor::hdl64e();
        let el = (s.fov_down_deg as f64 + t * (s.fov_up_deg - s.fov_down_deg) as f64).to_radians();
        roundtrip_one(&s, point(az, el, d), None)?;
    }

    #[test]
    fn uniform_roundtrip_hdl32e(az in -PI..PI, t in 0.0005f64..0.9995, d in 1.1f64..99.0) {
        let s = LidarSensor::hdl32e();
        let el = (s.fov_down_deg as f64 + t * (s.fov_up_deg - s.fov_down_deg) as f64).to_radians();
        roundtrip_one(&s, point(az, el, d), None)?;
    }

    #[test]
    fn per_beam_nearest_roundtrip(az in -PI..PI, t in 0.0005f64..0.9995, d in 0.6f64..119.0) {
        let s = per_beam_nearest_sensor();
        let el = (s.fov_down_deg as f64 + t * (s.fov_up_deg - s.fov_down_deg) as f64).to_radians();
        roundtrip_one(&s, point(az, el, d), None)?;
    }

    #[test]
    fn per_beam_ring_roundtrip(az in -PI..PI, ring in 0u16..32, jitter in -0.6f64..0.6, d in 1.1f64..99.0) {
        // a point near its ring's own elevation (within the ring's band)
        let s = LidarSensor::hdl32e_per_beam();
        let el = (s.beam_elevations_deg().unwrap()[ring as usize] as f64 + jitter).to_radians();
        roundtrip_one(&s, point(az, el, d), Some(ring))?;
    }
}

fn assert_every_ray_reprojects(sensor: &LidarSensor, use_rings: bool) {
    let pr = Projector::new(sensor, ProjectionOptions::default()).unwrap();
    let rays = RayTable::new(sensor).unwrap();
    for row in 0..sensor.rows {
        let ring = use_rings.then(|| sensor.ring_of_row(row) as u16);
        for col in 0..sensor.cols {
            let d = rays.dir(row, col);
            assert!((d.length() - 1.0).abs() < 1e-6);
            for range in [1.5f32, 37.0] {
                assert_eq!(
                    pr.try_pixel(d * range, ring),
                    Some((row, col)),
                    "pixel ({row}, {col}) at {range} m"
                );
            }
        }
    }
}

#[test]
fn every_ray_reprojects_to_its_pixel_hdl64e() {
    assert_every_ray_reprojects(&LidarSensor::hdl64e(), false);
}

#[test]
fn every_ray_reprojects_to_its_pixel_hdl32e() {
    assert_every_ray_reprojects(&LidarSensor::hdl32e(), false);
}

#[test]
fn every_ray_reprojects_to_its_pixel_hdl32e_per_beam_rings() {
    assert_every_ray_reprojects(&LidarSensor::hdl32e_per_beam(), true);
}

#[test]
fn every_ray_reprojects_to_its_pixel_per_beam_nearest() {
    assert_every_ray_reprojects(&per_beam_nearest_sensor(), false);
}

/// KITTI 000000's calibration (P2, R0_rect, Tr_velo_to_cam as published), 1224 x 370.
pub fn kitti_like_camera() -> PinholeCamera {
    let p2 = [
        [707.0493, 0.0, 604.0814, 45.75831],
        [0.0, 707.0493, 180.5066, -0.3454157],
        [0.0, 0.0, 1.0, 0.004981016],
    ];
    let r0 = Mat3::from_cols_array_2d(&[
        [0.9999128, 0.01009263, -0.01085618],
        [-0.01012729, 0.9999406, -0.003159306],
        [0.01082487, 0.003269028, 0.9999361],
    ])
    .transpose();
    let tr = [
        [0.006927964, -0.9999722, -0.002757829, -0.02457729],
        [-0.001162982, 0.002749836, -0.9999955, -0.06127237],
        [0.9999753, 0.006931141, -0.001143899, -0.3321029],
    ];
    PinholeCamera::from_kitti(p2, r0, tr, 1224, 370).unwrap()
}

/// A nuScenes-like front camera: 1600 x 900, fx = fy = 1266.4, camera looking along LiDAR +x with a
/// small yaw and an offset.
pub fn nuscenes_like_camera() -> PinholeCamera {
    let k =
        Mat3::from_cols_array_2d(&[[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]])
            .transpose();
    // camera axes in the LiDAR frame: x_cam = -y_lidar, y_cam = -z_lidar, z_cam = +x_lidar, then yaw 0.02
    let base = Mat3::from_cols(
        Vec3::new(0.0, 0.0, 1.0),
        Vec3::new(-1.0, 0.0, 0.0),
        Vec3::new(0.0, -1.0, 0.0),
    );
    let rot = base * Mat3::from_rotation_z(0.02);
    let t = Mat4::from_mat3(rot) * Mat4::from_translation(Vec3::new(-1.5, 0.01, 0.3));
    PinholeCamera::from_nuscenes(k, t, 1600, 900).unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 1000, rng_seed: proptest::test_runner::RngSeed::Fixed(12), ..ProptestConfig::default() })]

    /// project then back-project returns the point (relative error ~1e-5: f32 matrices).
    #[test]
    fn camera_project_back_project_agree(x in 1.0f32..80.0, y in -30.0f32..30.0, z in -3.0f32..5.0) {
        for cam in [kitti_like_camera(), nuscenes_like_camera()] {
            let p = Vec3::new(x, y, z);
            let Some(ip) = cam.try_project(p) else {
                // only points at or behind the near plane give None
                let pc = cam.cam_from_lidar.transform_point3(p);
                prop_assert!(pc.z <= cam.near_m + 0.01, "{p:?} -> {pc:?}");
                continue;
            };
            prop_assert!(ip.depth_m > 0.0);
            let q = cam.try_back_project(ip.u_px, ip.v_px, ip.depth_m).unwrap();
            prop_assert!((q - p).length() <= 2e-5 * p.length() + 1e-4, "{p:?} -> {ip:?} -> {q:?}");
            // and the pixel from plain math: K (T p) / w
            let c = cam.intrinsics * cam.cam_from_lidar * p.extend(1.0);
            prop_assert!((c.x / c.z - ip.u_px).abs() < 1e-2 && (c.y / c.z - ip.v_px).abs() < 1e-2);
        }
    }

    /// back-project then project returns the pixel.
    #[test]
    fn camera_back_project_project_agree(u in 0.0f32..1200.0, v in 0.0f32..360.0, depth in 0.5f32..80.0) {
        for cam in [kitti_like_camera(), nuscenes_like_camera()] {
            let p = cam.try_back_project(u, v, depth).unwrap();
            let ip = cam.try_project(p).unwrap();
            prop_assert!((ip.u_px - u).abs() < 0.02 && (ip.v_px - v).abs() < 0.02, "({u}, {v}) -> {ip:?}");
            prop_assert!((ip.depth_m - depth).abs() < 1e-4 * depth + 1e-4);
        }
    }
}
