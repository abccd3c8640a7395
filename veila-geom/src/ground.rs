//! The flat-ground prior: where a camera pixel's ray, or a LiDAR ray, meets a level ground plane.
//!
//! The plane is `z = ground_z_lidar_m` in the LiDAR frame (z up): `-1.73` for KITTI's HDL-64E,
//! mounted 1.73 m above the road. Everything else comes from the calibration: the camera's height
//! and pitch relative to the LiDAR are in `cam_from_lidar`, its field of view in `K`. On real data
//! the calibration is exact, so the prior says where flat ground would be without looking at a
//! pixel (issue 18: geometry that transfers from simulated to real images).
//!
//! - [`try_flat_ground_depth_m`]: one pixel's camera depth (`z` in the camera frame, metres) at
//!   the plane, `None` when the ray misses it (at or above the horizon, or a camera at or below
//!   the plane) or the input is not finite;
//! - [`flat_ground_depth_map_m`]: the whole image, row-major, `0` where the ray misses;
//! - [`flat_ground_range_image`]: the same plane seen by a LiDAR sensor, as a range image.
//!
//! ```
//! use glam::{Mat4, Vec3, Vec4};
//! use veila_geom::{PinholeCamera, flat_ground_depth_map_m, try_flat_ground_depth_m};
//!
//! // a level camera at the LiDAR's origin (x right = LiDAR -y, y down = -z, z forward = +x)
//! let axes = Mat4::from_cols(
//!     Vec4::new(0., 0., 1., 0.),
//!     Vec4::new(-1., 0., 0., 0.),
//!     Vec4::new(0., -1., 0., 0.),
//!     Vec4::W,
//! );
//! let k = [[100.0, 0.0, 32.0, 0.0], [0.0, 100.0, 24.0, 0.0], [0.0, 0.0, 1.0, 0.0]];
//! let cam = PinholeCamera::new(k, axes, 64, 48)?;
//! // 1.5 m above the ground, the row 10 pixels below the centre sees it at f h / (v - cy) = 15 m
//! let d = try_flat_ground_depth_m(&cam, 32.0, 34.0, -1.5).unwrap();
//! assert!((d - 15.0).abs() < 1e-4);
//! // the upper half looks at or above the horizon
//! assert_eq!(try_flat_ground_depth_m(&cam, 32.0, 20.0, -1.5), None);
//! let map = flat_ground_depth_map_m(&cam, -1.5);
//! assert_eq!(map.len(), 64 * 48);
//! assert_eq!(map[0], 0.0);
//! # Ok::<(), veila_geom::GeomError>(())
//! ```

use glam::{DMat3, DVec3};

use crate::{GeomError, LidarSensor, PinholeCamera, RangeImage, RayTable};

/// What every pixel of one camera shares: the pixel ray and the projection centre in the LiDAR
/// frame, computed once (f64, so rays near the horizon keep their digits).
struct CameraRays {
    /// `K3⁻¹`.
    k_inv: DMat3,
    /// `K3⁻¹ t` (KITTI's `P2` carries a translation `t` in its fourth column).
    off: DVec3,
    /// The rotation part of `lidar_from_cam`.
    rot_inv: DMat3,
    /// The projection centre in the LiDAR frame.
    centre_lidar: DVec3,
    near_m: f64,
}

impl CameraRays {
    fn new(camera: &PinholeCamera) -> Option<Self> {
        let intrinsics = camera.intrinsics.as_dmat4();
        let k3 = DMat3::from_mat4(intrinsics);
        if k3.determinant() == 0.0 {
            return None;
        }
        let k_inv = k3.inverse();
        let off = k_inv * intrinsics.w_axis.truncate();
        let lidar_from_cam = camera.cam_from_lidar.as_dmat4().inverse();
        if !lidar_from_cam.is_finite() {
            return None;
        }
        // p_cam(w) = w ray - off; its LiDAR position at w = 0 is the projection centre
        let centre_lidar = lidar_from_cam.transform_point3(-off);
        Some(CameraRays {
            k_inv,
            off,
            rot_inv: DMat3::from_mat4(lidar_from_cam),
            centre_lidar,
            near_m: f64::from(camera.near_m),
        })
    }

    /// Camera depth where pixel `(u, v)`'s ray meets `z_lidar = ground_z`.
    fn depth_m(&self, u_px: f64, v_px: f64, ground_z: f64) -> Option<f32> {
        if self.centre_lidar.z.is_nan() || self.centre_lidar.z <= ground_z {
            return None; // a camera at or below the plane sees no ground from above
        }
        let ray = self.k_inv * DVec3::new(u_px, v_px, 1.0);
        let dir_z = (self.rot_inv * ray).z;
        // centre.z + w dir_z = ground_z, with w > 0 in front of the projection centre
        if dir_z.is_nan() || dir_z >= 0.0 {
            return None; // at or above the horizon
        }
        let w = (ground_z - self.centre_lidar.z) / dir_z;
        let depth = w * ray.z - self.off.z;
        (w > self.near_m && depth > 0.0 && depth.is_finite()).then_some(depth as f32)
    }
}

/// The camera depth (`z` in the camera frame, metres) at which pixel `(u_px, v_px)`'s ray meets
/// the ground plane `z = ground_z_lidar_m` of the LiDAR frame; the point seen there projects back
/// onto the pixel ([`PinholeCamera::try_back_project`] at this depth lies on the plane).
///
/// `None` when the ray misses the plane (at or above the horizon), when the meeting point is not
/// in front of the camera's near plane, when the camera sits at or below the plane, or for
/// non-finite input.
pub fn try_flat_ground_depth_m(
    camera: &PinholeCamera,
    u_px: f32,
    v_px: f32,
    ground_z_lidar_m: f32,
) -> Option<f32> {
    if !(u_px.is_finite() && v_px.is_finite() && ground_z_lidar_m.is_finite()) {
        return None;
    }
    CameraRays::new(camera)?.depth_m(
        f64::from(u_px),
        f64::from(v_px),
        f64::from(ground_z_lidar_m),
    )
}

/// [`try_flat_ground_depth_m`] at every pixel centre of the camera's `width x height` image,
/// row-major (`v * width + u`), `0.0` where the ray misses the plane (and everywhere for a
/// non-finite `ground_z_lidar_m` or a camera whose matrices cannot be inverted).
pub fn flat_ground_depth_map_m(camera: &PinholeCamera, ground_z_lidar_m: f32) -> Vec<f32> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut out = vec![0.0f32; w * h];
    let Some(rays) = CameraRays::new(camera).filter(|_| ground_z_lidar_m.is_finite()) else {
        return out;
    };
    let g = f64::from(ground_z_lidar_m);
    for v in 0..h {
        for u in 0..w {
            if let Some(d) = rays.depth_m(u as f64, v as f64, g) {
                out[v * w + u] = d;
            }
        }
    }
    out
}

/// The ground plane `z = ground_z_lidar_m` on `sensor`'s range grid: each ray below the horizon
/// meets it at range `ground_z_lidar_m / dir.z`, kept when within the sensor's range limits; the
/// other pixels have no return. Intensity is 0.
///
/// # Errors
/// An invalid sensor, or a `ground_z_lidar_m` that is not finite and negative (the plane must lie
/// below the LiDAR).
pub fn flat_ground_range_image(
    sensor: &LidarSensor,
    ground_z_lidar_m: f32,
) -> Result<RangeImage, GeomError> {
    if !(ground_z_lidar_m.is_finite() && ground_z_lidar_m < 0.0) {
        return Err(GeomError::InvalidConfig {
            what: "flat ground",
            message: format!(
                "ground_z_lidar_m must be finite and below the LiDAR (< 0), got {ground_z_lidar_m}"
            ),
        });
    }
    let rays = RayTable::new(sensor)?;
    let mut img = RangeImage::new_empty(sensor.rows, sensor.cols);
    for (i, d) in rays.dirs().iter().enumerate() {
        if d.z < 0.0 {
            let r = ground_z_lidar_m / d.z;
            if r >= sensor.min_range_m && r <= sensor.max_range_m {
                img.range_m[i] = r;
                img.mask[i] = true;
            }
        }
    }
    Ok(img)
}

#[cfg(test)]
mod tests {
    use glam::{Mat4, Vec3, Vec4};

    use super::*;

    /// Camera x right = LiDAR -y, y down = LiDAR -z, z forward = LiDAR +x.
    fn axes() -> Mat4 {
        Mat4::from_cols(
            Vec4::new(0., 0., 1., 0.),
            Vec4::new(-1., 0., 0., 0.),
            Vec4::new(0., -1., 0., 0.),
            Vec4::W,
        )
    }

    fn k(f: f32, cx: f32, cy: f32, tx: f32) -> [[f32; 4]; 3] {
        [[f, 0.0, cx, tx], [0.0, f, cy, 0.0], [0.0, 0.0, 1.0, 0.0]]
    }

    #[test]
    fn level_camera_matches_the_closed_form() {
        // a level camera at the LiDAR origin, the ground h below: depth f h / (v - cy)
        let (f, cx, cy, h) = (180.0f32, 80.5, 30.25, 1.73f32);
        let cam = PinholeCamera::new(k(f, cx, cy, 0.0), axes(), 160, 64).unwrap();
        let map = flat_ground_depth_map_m(&cam, -h);
        for v in 0..64u32 {
            for u in 0..160u32 {
                let got = map[(v * 160 + u) as usize];
                let single = try_flat_ground_depth_m(&cam, u as f32, v as f32, -h);
                assert_eq!(single.unwrap_or(0.0), got);
                let dv = v as f32 - cy;
                if dv > 0.0 {
                    let want = f * h / dv;
                    assert!((got - want).abs() <= 1e-5 * want, "v {v}: {got} vs {want}");
                } else {
                    assert_eq!(got, 0.0, "v {v} is at or above the horizon");
                }
            }
        }
    }

    #[test]
    fn pitched_raised_camera_matches_the_closed_form() {
        // pitched down by theta, 0.08 m above the LiDAR, LiDAR 1.73 m above the ground: camera
        // height H = 1.81; a row's ray (0, t, 1), t = (v - cy) / f, falls H / (t cos + sin) along
        // its camera z: depth = f H / (f sin + (v - cy) cos), none at or above v = cy - f tan.
        let (f, cx, cy) = (200.0f32, 100.0, 40.0);
        let theta = 4f32.to_radians();
        let cam_from_lidar = Mat4::from_rotation_x(theta)
            * axes()
            * Mat4::from_translation(Vec3::new(0.3, 0.1, -0.08));
        let cam = PinholeCamera::new(k(f, cx, cy, 0.0), cam_from_lidar, 200, 80).unwrap();
        let height = 1.81f64;
        let (s, c) = (f64::from(theta).sin(), f64::from(theta).cos());
        let horizon = f64::from(cy) - f64::from(f) * s / c;
        let mut seen = 0;
        for v in 0..80u32 {
            let den = f64::from(f) * s + (f64::from(v) - f64::from(cy)) * c;
            for u in [0u32, 57, 199] {
                let got = try_flat_ground_depth_m(&cam, u as f32, v as f32, -1.73);
                if den > 0.0 {
                    let want = f64::from(f) * height / den;
                    let got = got.unwrap() as f64;
                    assert!((got - want).abs() <= 2e-5 * want, "v {v}: {got} vs {want}");
                    seen += 1;
                } else {
                    assert!(f64::from(v) <= horizon + 1e-3);
                    assert_eq!(got, None, "v {v}");
                }
            }
        }
        assert!(seen > 3 * 40);
    }

    /// Brute force, independent of the closed-form solve: march along each pixel's ray with
    /// `try_back_project` and bisect the first depth whose point lies below the plane.
    fn marched(cam: &PinholeCamera, u: f32, v: f32, g: f32, max_m: f32) -> Option<f32> {
        let z = |d: f32| cam.try_back_project(u, v, d).map(|p| p.z);
        let (mut lo, step) = (0.2f32, 0.05f32);
        let mut hi = lo;
        loop {
            hi += step;
            if hi > max_m {
                return None;
            }
            if z(hi)? <= g {
                break;
            }
            lo = hi;
        }
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if z(mid)? <= g {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        Some(0.5 * (lo + hi))
    }

    #[test]
    fn agrees_with_brute_force_marching_for_a_kitti_like_rolled_camera() {
        // KITTI-like P2 with its translation, a little roll and pitch, camera 0.1 m above the LiDAR
        let cam_from_lidar = Mat4::from_rotation_z(2f32.to_radians())
            * Mat4::from_rotation_x(3f32.to_radians())
            * axes()
            * Mat4::from_translation(Vec3::new(-0.27, 0.0, -0.1));
        let cam = PinholeCamera::new(k(230.0, 160.0, 52.0, 12.0), cam_from_lidar, 320, 96).unwrap();
        let g = -1.73;
        let map = flat_ground_depth_map_m(&cam, g);
        let (mut hits, mut misses) = (0, 0);
        for v in (0..96u32).step_by(5) {
            for u in (0..320u32).step_by(17) {
                let got = map[(v * 320 + u) as usize];
                match marched(&cam, u as f32, v as f32, g, 60.0) {
                    Some(want) => {
                        hits += 1;
                        assert!((got - want).abs() < 1e-3 * want.max(1.0), "({u}, {v})");
                        // the point lies on the plane and projects back onto the pixel
                        let p = cam.try_back_project(u as f32, v as f32, got).unwrap();
                        assert!((p.z - g).abs() < 1e-3);
                        let ip = cam.try_project(p).unwrap();
                        assert!((ip.u_px - u as f32).abs() < 1e-2);
                        assert!((ip.v_px - v as f32).abs() < 1e-2);
                    }
                    // beyond the march: the horizon, or ground farther than 60 m
                    None => {
                        misses += 1;
                        assert!(got == 0.0 || got > 59.0, "({u}, {v}): {got}");
                    }
                }
            }
        }
        assert!(hits > 100 && misses > 10, "{hits} {misses}");
    }

    #[test]
    fn out_of_domain_input_gives_none_or_zero() {
        let cam = PinholeCamera::new(k(100.0, 32.0, 24.0, 0.0), axes(), 64, 48).unwrap();
        assert_eq!(try_flat_ground_depth_m(&cam, f32::NAN, 30.0, -1.5), None);
        assert_eq!(
            try_flat_ground_depth_m(&cam, 3.0, f32::INFINITY, -1.5),
            None
        );
        assert_eq!(try_flat_ground_depth_m(&cam, 3.0, 30.0, f32::NAN), None);
        // the plane above the camera: looking down never meets it from above
        assert_eq!(try_flat_ground_depth_m(&cam, 3.0, 30.0, 0.5), None);
        assert_eq!(try_flat_ground_depth_m(&cam, 3.0, 10.0, 0.5), None);
        assert!(
            flat_ground_depth_map_m(&cam, f32::NAN)
                .iter()
                .all(|&d| d == 0.0)
        );
        assert!(flat_ground_depth_map_m(&cam, 0.0).iter().all(|&d| d == 0.0));
        // a camera looking straight down sees ground at every pixel, the centre at h
        let down = Mat4::from_rotation_x(90f32.to_radians()) * axes();
        let cam = PinholeCamera::new(k(100.0, 32.0, 24.0, 0.0), down, 64, 48).unwrap();
        let map = flat_ground_depth_map_m(&cam, -2.0);
        assert!(map.iter().all(|&d| d > 0.0));
        assert!((try_flat_ground_depth_m(&cam, 32.0, 24.0, -2.0).unwrap() - 2.0).abs() < 1e-5);
    }

    #[test]
    fn range_image_rays_meet_the_plane() {
        let sensor = LidarSensor {
            rows: 16,
            cols: 32,
            ..LidarSensor::hdl64e()
        };
        let img = flat_ground_range_image(&sensor, -1.73).unwrap();
        let rays = RayTable::new(&sensor).unwrap();
        let mut below = 0;
        for (i, d) in rays.dirs().iter().enumerate() {
            if img.mask[i] {
                below += 1;
                // the point lies on z = -1.73
                assert!((d.z * img.range_m[i] + 1.73).abs() < 1e-4);
            } else {
                // no return: at or above the horizon, or beyond the range limit
                assert!(d.z >= 0.0 || 1.73 / -d.z > sensor.max_range_m);
            }
        }
        assert!(below > 0);
        assert!(flat_ground_range_image(&sensor, 0.5).is_err());
        assert!(flat_ground_range_image(&sensor, f32::NAN).is_err());
    }
}
