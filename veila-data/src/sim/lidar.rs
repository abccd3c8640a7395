//! Simulated LiDAR scans: one ray per range-image pixel, cast through the scene's BVH.
//!
//! The beam pattern is exactly the sensor's: ray `(row, col)` has the direction
//! [`RayTable::dir`](veila_geom::RayTable::dir) of that pixel's centre (uniform rows or the per-beam
//! elevation table), so projecting a simulated scan with [`veila_geom::Projector`] puts every point
//! back in its own pixel.
//!
//! # Return model
//!
//! For the closest surface at range `R` with LiDAR reflectivity `rho` and incidence angle `theta`
//! (between the ray and the surface normal):
//!
//! - **Range window.** Surfaces nearer than `min_range_m` or farther than `max_range_m` give no return.
//! - **Grazing drop.** `cos(theta) < grazing_cos_min` gives no return.
//! - **Weak-return drop.** The received power of a Lambertian target filling the beam is proportional to
//!   `P = rho cos(theta) / R^2`. It is compared with the detection threshold
//!   `P_min = min_reflectivity_at_100m / (100 m)^2` in decades: with `x = log10(P / P_min) / s`
//!   (`s = drop_softness_decades`) the return is kept with probability `smoothstep(-1, 1, x)`
//!   (`s = 0`: kept iff `P >= P_min`).
//! - **Random drop** with probability `random_drop`.
//! - **Intensity** (KITTI scale, `[0, 1]`): `I = rho g(cos theta) / (1 + (R / R_half)^2)` with
//!   `g(c) = (1 + c0^2) c^2 / (c^2 + c0^2)` (`c0 = incidence_knee`, `R_half = intensity_half_range_m`).
//!   Real Velodyne intensities are range- and angle-compensated: in SemanticKITTI a road seen at
//!   `cos(theta) ~ 0.2` still reports ~0.22 near the car but fades to ~0.015 beyond 30 m, which a
//!   Lambertian `cos(theta)` cannot give; `g` is flat down to `c ~ 2 c0` and falls like `c^2` at
//!   grazing incidence. Detection (above) keeps the physical `cos(theta) / R^2` power.
//! - **Range noise**: Gaussian with standard deviation `range_noise_m` along the ray (0 = exact).
//!
//! Every random decision uses a hash of (frame seed, pixel index), never a shared generator, so the
//! scan is bit-identical for any number of threads.

use glam::{Affine3A, Vec3};
use rayon::prelude::*;
use veila_geom::{LidarSensor, NO_POINT, RangeImage, RayTable};

use super::config::LidarReturnModel;
use super::frame::SceneSnapshot;
use super::hash::hash_unit;
use crate::{PointCloud, Result};

/// What happened to one LiDAR ray.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum RayOutcome {
    /// A point was returned.
    Return = 0,
    /// No surface within the maximum range (sky, open space).
    NoHit = 1,
    /// The closest surface is nearer than the minimum range.
    TooNear = 2,
    /// Dropped: grazing incidence.
    Grazing = 3,
    /// Dropped: the return was too weak.
    Weak = 4,
    /// Dropped at random.
    RandomDrop = 5,
}

/// A simulated scan.
#[derive(Debug, Clone)]
pub struct SimScan {
    /// Returned points in the LiDAR frame, row-major pixel order, with intensity (`[0, 1]`), ring
    /// (the sensor's beam index) and SemanticKITTI label (`class | instance << 16`).
    pub points: PointCloud,
    /// The same returns as a range image (with [`RangeImage::label`] set); `point_index` points into
    /// [`SimScan::points`].
    pub range_image: RangeImage,
    /// Per pixel: what happened to its ray.
    pub outcome: Vec<RayOutcome>,
    /// Per pixel: range of the closest surface whether or not it returned (0 = no surface within the
    /// maximum range). Ground truth for ray-drop studies.
    pub surface_range_m: Vec<f32>,
    /// Per pixel: label of the closest surface whether or not it returned (0 = none).
    pub surface_label: Vec<u32>,
}

impl SimScan {
    /// Number of rays with each outcome, indexed by `RayOutcome as usize`.
    pub fn outcome_counts(&self) -> [usize; 6] {
        let mut c = [0usize; 6];
        for o in &self.outcome {
            c[*o as usize] += 1;
        }
        c
    }
}

/// The incidence term `g(c) = (1 + c0^2) c^2 / (c^2 + c0^2)` of the intensity (`g(1) = 1`, `g(0) = 0`;
/// `c0 = 0` gives 1 everywhere).
pub fn incidence_gain(cos: f32, knee: f32) -> f32 {
    let (c2, k2) = (cos * cos, knee * knee);
    if c2 + k2 <= 0.0 {
        1.0
    } else {
        (1.0 + k2) * c2 / (c2 + k2)
    }
}

fn smoothstep(x: f32) -> f32 {
    let t = ((x + 1.0) * 0.5).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

struct RayResult {
    outcome: RayOutcome,
    range_m: f32,
    surface_range_m: f32,
    intensity: f32,
    label: u32,
}

impl SceneSnapshot {
    /// Render a scan of `sensor` from this snapshot's LiDAR pose.
    pub fn render_lidar(&self, sensor: &LidarSensor, model: &LidarReturnModel) -> Result<SimScan> {
        self.render_lidar_at(sensor, model, self.world_from_lidar)
    }

    /// Render a scan of `sensor` mounted at `world_from_lidar` (rotation and translation only).
    pub fn render_lidar_at(
        &self,
        sensor: &LidarSensor,
        model: &LidarReturnModel,
        world_from_lidar: Affine3A,
    ) -> Result<SimScan> {
        model.validate()?;
        let rays = RayTable::new(sensor)?;
        let origin = Vec3::from(world_from_lidar.translation);
        let (rows, cols) = (sensor.rows, sensor.cols);
        let seed = self.noise_seed;
        let per_pixel: Vec<RayResult> = (0..sensor.num_pixels())
            .into_par_iter()
            .with_min_len(256)
            .map(|k| {
                let (row, col) = ((k / cols as usize) as u32, (k % cols as usize) as u32);
                let dir_l = rays.dir(row, col);
                let dir_w = world_from_lidar.transform_vector3(dir_l).normalize();
                self.cast_lidar_ray(origin, dir_w, sensor, model, seed, k as u64)
            })
            .collect();

        let n = per_pixel.len();
        let mut image = RangeImage::new_empty(rows, cols);
        let mut labels_img = vec![0u32; n];
        let mut outcome = Vec::with_capacity(n);
        let mut surface_range_m = Vec::with_capacity(n);
        let mut surface_label = Vec::with_capacity(n);
        let mut cloud = PointCloud {
            ring: Some(Vec::new()),
            label: Some(Vec::new()),
            ..Default::default()
        };
        for (k, r) in per_pixel.into_iter().enumerate() {
            outcome.push(r.outcome);
            surface_range_m.push(r.surface_range_m);
            surface_label.push(r.label);
            if r.outcome == RayOutcome::Return {
                let (row, col) = ((k / cols as usize) as u32, (k % cols as usize) as u32);
                let idx = cloud.xyz.len();
                cloud.xyz.push(rays.dir(row, col) * r.range_m);
                cloud.intensity.push(r.intensity);
                if let Some(v) = cloud.ring.as_mut() {
                    v.push(sensor.ring_of_row(row) as u16);
                }
                if let Some(v) = cloud.label.as_mut() {
                    v.push(r.label);
                }
                image.range_m[k] = r.range_m;
                image.intensity[k] = r.intensity;
                image.point_index[k] = idx as u32;
                image.mask[k] = true;
                labels_img[k] = r.label;
            } else {
                debug_assert_eq!(image.point_index[k], NO_POINT);
            }
        }
        image.label = Some(labels_img);
        Ok(SimScan {
            points: cloud,
            range_image: image,
            outcome,
            surface_range_m,
            surface_label,
        })
    }

    fn cast_lidar_ray(
        &self,
        origin: Vec3,
        dir: Vec3,
        sensor: &LidarSensor,
        m: &LidarReturnModel,
        seed: u64,
        pixel: u64,
    ) -> RayResult {
        let none = |outcome| RayResult {
            outcome,
            range_m: 0.0,
            surface_range_m: 0.0,
            intensity: 0.0,
            label: 0,
        };
        let Some(hit) = self.accel.closest_hit(origin, dir, 0.0, sensor.max_range_m) else {
            return none(RayOutcome::NoHit);
        };
        let t = hit.t;
        let label = u32::from(hit.surface.material.class) | (u32::from(hit.surface.instance) << 16);
        let mut res = RayResult {
            outcome: RayOutcome::Return,
            range_m: t,
            surface_range_m: t,
            intensity: 0.0,
            label,
        };
        if t < sensor.min_range_m {
            res.outcome = RayOutcome::TooNear;
            return res;
        }
        let cos = (-hit.normal.dot(dir)).clamp(0.0, 1.0);
        if cos < m.grazing_cos_min {
            res.outcome = RayOutcome::Grazing;
            return res;
        }
        let rho = hit.surface.material.reflectivity;
        if m.min_reflectivity_at_100m > 0.0 {
            // P / P_min = rho cos (100 / R)^2 / min_reflectivity_at_100m
            let ratio = rho * cos * (100.0 / t).powi(2) / m.min_reflectivity_at_100m;
            let keep = if m.drop_softness_decades > 0.0 {
                let x = if ratio > 0.0 {
                    ratio.log10() / m.drop_softness_decades
                } else {
                    f32::NEG_INFINITY
                };
                hash_unit(seed, pixel, 1) < smoothstep(x)
            } else {
                ratio >= 1.0
            };
            if !keep {
                res.outcome = RayOutcome::Weak;
                return res;
            }
        }
        if m.random_drop > 0.0 && hash_unit(seed, pixel, 2) < m.random_drop {
            res.outcome = RayOutcome::RandomDrop;
            return res;
        }
        if m.range_noise_m > 0.0 {
            // Box-Muller from two hashed uniforms
            let u1 = hash_unit(seed, pixel, 3).max(1e-7);
            let u2 = hash_unit(seed, pixel, 4);
            let z = (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos();
            res.range_m = (t + m.range_noise_m * z).max(sensor.min_range_m);
        }
        let falloff = 1.0 / (1.0 + (t / m.intensity_half_range_m).powi(2));
        res.intensity = (rho * incidence_gain(cos, m.incidence_knee) * falloff).clamp(0.0, 1.0);
        res
    }
}
