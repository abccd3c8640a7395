//! The LiDAR side: inputs, the per-point working state, and the pipeline runner.
//!
//! Points are processed in fixed chunks of 2048 with one random stream per chunk (derived from the seed,
//! the effect and the chunk index), in parallel with rayon: results are bit-identical for any number of
//! threads.

use glam::Vec3;
use rand_distr::{Beta, Distribution};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::fog::{FogOutcome, FogTable, FogTableConfig, fog_point};
use super::plan::{EffectRecord, LidarEffect};
use super::rain::RainConfig;
use super::rng::{self, CHUNK};
use super::snow::SnowConfig;
use super::spec::{Weather, fog_backscatter_per_m};
use super::wet::WetGroundConfig;
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

/// What the LiDAR pipeline reads.
#[derive(Debug, Clone, Copy)]
pub struct LidarInput<'a> {
    /// The scan (LiDAR frame, metres).
    pub cloud: &'a PointCloud,
    /// Which points lie on the road (for wet ground). Fallback: labels, else a plane fit.
    pub ground_mask: Option<&'a [bool]>,
    /// Beam elevations (for snow when the cloud has no ring index).
    pub beams: Option<&'a BeamTable>,
}

impl<'a> LidarInput<'a> {
    /// Just the cloud, no extra inputs.
    pub fn new(cloud: &'a PointCloud) -> Self {
        LidarInput {
            cloud,
            ground_mask: None,
            beams: None,
        }
    }
}

/// LiDAR knobs (defaults: KITTI / HDL-64E).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LidarConfig {
    /// Largest intensity value of the dataset's scale (KITTI 1.0, nuScenes 255).
    pub intensity_max: f32,
    /// Full beam divergence, radians (3 mrad as in LISA and Hahner et al. 2022).
    pub beam_divergence_rad: f64,
    /// Fog table resolution.
    pub fog_table: FogTableConfig,
    /// Scale of the additive fog range noise `scale * Beta(2, 20)` m (Hahner's v4 noise, 10 m).
    pub fog_range_noise_m: f64,
    /// Rain (LISA) knobs.
    pub rain: RainConfig,
    /// Snow knobs.
    pub snow: SnowConfig,
    /// Wet-ground knobs.
    pub wet_ground: WetGroundConfig,
}

impl Default for LidarConfig {
    fn default() -> Self {
        LidarConfig {
            intensity_max: 1.0,
            beam_divergence_rad: 3e-3,
            fog_table: FogTableConfig::default(),
            fog_range_noise_m: 10.0,
            rain: RainConfig::default(),
            snow: SnowConfig::default(),
            wet_ground: WetGroundConfig::default(),
        }
    }
}

impl LidarConfig {
    pub(crate) fn validate(&self) -> Result<()> {
        if !(self.intensity_max.is_finite() && self.intensity_max > 0.0) {
            return Err(Error::Invalid {
                what: "lidar intensity_max".into(),
                message: format!("{}", self.intensity_max),
            });
        }
        if !(self.beam_divergence_rad > 0.0 && self.beam_divergence_rad < 0.1) {
            return Err(Error::Invalid {
                what: "lidar beam_divergence_rad".into(),
                message: format!("{} (must be in (0, 0.1))", self.beam_divergence_rad),
            });
        }
        if !(self.fog_range_noise_m.is_finite() && self.fog_range_noise_m >= 0.0) {
            return Err(Error::Invalid {
                what: "lidar fog_range_noise_m".into(),
                message: format!("{}", self.fog_range_noise_m),
            });
        }
        self.rain.validate()?;
        self.snow.validate()?;
        self.wet_ground.validate()
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

/// Two-way attenuation `i exp(-2 alpha R)` of every point (f64; no denormals).
pub(crate) fn apply_extinction(st: &mut LidarState, alpha: f64, imax: f32) -> EffectRecord {
    st.xyz
        .par_iter()
        .zip(st.intensity.par_iter_mut())
        .for_each(|(p, i)| {
            let r = p.as_dvec3().length();
            if r > 0.0 && r.is_finite() {
                *i = to_f32_intensity(*i as f64 * (-2.0 * alpha * r).exp(), imax);
            }
        });
    EffectRecord::new(LidarEffect::Extinction.name())
        .param("alpha_per_m", alpha)
        .count("points_attenuated", st.xyz.len() as u64)
}

/// Hahner et al. 2021 fog on every point.
pub(crate) fn apply_fog(
    st: &mut LidarState,
    table: &FogTable,
    weather: &Weather,
    cfg: &LidarConfig,
) -> Result<EffectRecord> {
    let vis = weather.fog_visibility_m.unwrap_or(f64::INFINITY);
    let beta = fog_backscatter_per_m(vis);
    let imax = cfg.intensity_max;
    let noise = cfg.fog_range_noise_m;
    let beta_dist = Beta::new(2.0, 20.0).map_err(|e| Error::Invalid {
        what: "fog noise distribution".into(),
        message: e.to_string(),
    })?;
    let seed = weather.seed;
    let replaced: usize = st
        .xyz
        .par_chunks_mut(CHUNK)
        .zip(st.intensity.par_chunks_mut(CHUNK))
        .zip(st.origin.par_chunks_mut(CHUNK))
        .enumerate()
        .map(|(c, ((xyz, inten), origin))| {
            let mut rng = None;
            let mut count = 0;
            for k in 0..xyz.len() {
                let p = xyz[k].as_dvec3();
                let r0 = p.length();
                match fog_point(table, beta, r0, inten[k] as f64) {
                    FogOutcome::Hard { intensity } => inten[k] = to_f32_intensity(intensity, imax),
                    FogOutcome::Fog { range_m, intensity } => {
                        let rng = rng.get_or_insert_with(|| {
                            rng::stream(seed, rng::tag::LIDAR_FOG, c as u64)
                        });
                        let d: f64 = beta_dist.sample(rng);
                        // never behind the hard target
                        let new_r = (range_m + noise * d).min(r0);
                        xyz[k] = (p * (new_r / r0)).as_vec3();
                        inten[k] = to_f32_intensity(intensity, imax);
                        origin[k] = PointOrigin::Fog;
                        count += 1;
                    }
                }
            }
            count
        })
        .sum();
    let (r_sat, i_sat) = table.saturated();
    Ok(EffectRecord::new(LidarEffect::Fog.name())
        .param("visibility_m", vis)
        .param("alpha_per_m", table.alpha_per_m())
        .param("beta_per_m_sr", beta)
        .param("fog_return_range_saturated_m", r_sat)
        .param("fog_integral_saturated_s_per_m2", i_sat)
        .param("table_r0_step_m", cfg.fog_table.r0_step_m)
        .count("points", st.xyz.len() as u64)
        .count("replaced_by_fog_return", replaced as u64))
}
