//! The LiDAR points the effects share: where each point comes from, the beam table, the mutable
//! per-point working state, and the processed scan. The effects ([`super::rain`], [`super::snow`],
//! [`super::wet`]) and the pipeline runner ([`super::lidar`]) all build on this module.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::plan::EffectRecord;
use crate::{Error, PointCloud, Result};

/// Where a point of a weather-processed scan comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PointOrigin {
    /// The original hard target (its intensity may have changed).
    Target,
    /// A fog backscatter return (moved along the ray).
    Fog,
    /// A return from a rain drop near the sensor.
    Rain,
    /// A return from a snowflake.
    Snow,
}

/// Elevation angles of a LiDAR's beams: the documented fallback for a missing ring index (each point gets
/// the ring whose elevation is nearest to its own).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BeamTable {
    /// Elevation of each ring (index = ring id), radians.
    pub elevations_rad: Vec<f32>,
}

impl BeamTable {
    /// `n` beams spaced uniformly from `down_deg` (ring 0) to `up_deg` (ring n-1)... unless `n < 2`.
    pub fn uniform(n: usize, down_deg: f32, up_deg: f32) -> Result<Self> {
        if n < 2 || !(up_deg > down_deg) {
            return Err(Error::Invalid {
                what: "beam table".into(),
                message: format!("{n} beams from {down_deg} to {up_deg} deg"),
            });
        }
        let elevations_rad = (0..n)
            .map(|k| (down_deg + (up_deg - down_deg) * k as f32 / (n - 1) as f32).to_radians())
            .collect();
        Ok(BeamTable { elevations_rad })
    }

    /// The Velodyne HDL-64E as used by KITTI: 64 beams from -24.9 deg to +2.0 deg (uniform approximation,
    /// the same binning Robo3D uses for KITTI rings).
    pub fn hdl64e() -> Self {
        let elevations_rad = (0..64)
            .map(|k| (-24.9f32 + 26.9 * k as f32 / 63.0).to_radians())
            .collect();
        BeamTable { elevations_rad }
    }

    /// The beam elevations of a `veila_geom::LidarSensor` (row r -> ring r, top row first as in its
    /// range images; per-beam tables keep their own ring order).
    pub fn from_sensor(sensor: &veila_geom::LidarSensor) -> Self {
        let elevations_rad = match &sensor.beams {
            veila_geom::BeamLayout::PerBeam { elevations_deg, .. } => {
                elevations_deg.iter().map(|e| e.to_radians()).collect()
            }
            veila_geom::BeamLayout::Uniform => (0..sensor.rows)
                .map(|r| sensor.row_elevation_rad(r))
                .collect(),
        };
        BeamTable { elevations_rad }
    }

    /// Ring of a point: nearest elevation.
    pub fn ring_of(&self, p: Vec3) -> u16 {
        let el = p.z.atan2((p.x * p.x + p.y * p.y).sqrt());
        let mut best = (0usize, f32::INFINITY);
        for (k, e) in self.elevations_rad.iter().enumerate() {
            let d = (e - el).abs();
            if d < best.1 {
                best = (k, d);
            }
        }
        best.0 as u16
    }
}

/// A weather-processed scan.
#[derive(Debug, Clone, PartialEq)]
pub struct LidarOutput {
    /// The points (lost points removed; ring and label kept aligned; label 0 for weather returns).
    pub cloud: PointCloud,
    /// Origin of each output point.
    pub origin: Vec<PointOrigin>,
    /// What each effect did.
    pub records: Vec<EffectRecord>,
}

/// Mutable per-point state shared by the LiDAR effects (indices stay those of the input until the end).
#[derive(Debug)]
pub(crate) struct LidarState {
    pub xyz: Vec<Vec3>,
    pub intensity: Vec<f32>,
    pub origin: Vec<PointOrigin>,
    pub keep: Vec<bool>,
}

impl LidarState {
    pub fn new(cloud: &PointCloud) -> Self {
        let n = cloud.len();
        LidarState {
            xyz: cloud.xyz.clone(),
            intensity: cloud.intensity.clone(),
            origin: vec![PointOrigin::Target; n],
            keep: vec![true; n],
        }
    }

    /// Compact into the output cloud.
    pub fn finish(self, cloud: &PointCloud, records: Vec<EffectRecord>) -> LidarOutput {
        let n = self.xyz.len();
        let mut out = PointCloud {
            xyz: Vec::with_capacity(n),
            intensity: Vec::with_capacity(n),
            ring: cloud.ring.as_ref().map(|_| Vec::with_capacity(n)),
            label: cloud.label.as_ref().map(|_| Vec::with_capacity(n)),
        };
        let mut origin = Vec::with_capacity(n);
        for i in 0..n {
            if !self.keep[i] {
                continue;
            }
            out.xyz.push(self.xyz[i]);
            out.intensity.push(self.intensity[i]);
            if let (Some(dst), Some(src)) = (out.ring.as_mut(), cloud.ring.as_ref()) {
                dst.push(src[i]);
            }
            if let (Some(dst), Some(src)) = (out.label.as_mut(), cloud.label.as_ref()) {
                dst.push(if self.origin[i] == PointOrigin::Target {
                    src[i]
                } else {
                    0
                });
            }
            origin.push(self.origin[i]);
        }
        LidarOutput {
            cloud: out,
            origin,
            records,
        }
    }
}

/// Flush values too small for f32 (denormals) to zero and keep the result finite and non-negative.
pub(crate) fn to_f32_intensity(x: f64, max: f32) -> f32 {
    let v = x.min(max as f64);
    if !(v >= f32::MIN_POSITIVE as f64) {
        0.0
    } else {
        v as f32
    }
}
