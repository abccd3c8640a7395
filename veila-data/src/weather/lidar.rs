//! The LiDAR side: inputs, knobs, and the pipeline runner (the per-point state the effects share is in
//! [`super::points`]).
//!
//! Points are processed in fixed chunks of 2048 with one random stream per chunk (derived from the seed,
//! the effect and the chunk index), in parallel with rayon: results are bit-identical for any number of
//! threads.

use rand_distr::{Beta, Distribution};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::fog::{FogOutcome, FogTable, FogTableConfig, fog_point};
use super::plan::{EffectRecord, LidarEffect};
use super::points::{BeamTable, LidarState, PointOrigin, to_f32_intensity};
use super::rain::RainConfig;
use super::rng::{self, CHUNK};
use super::snow::SnowConfig;
use super::spec::{Weather, fog_backscatter_per_m};
use super::wet::WetGroundConfig;
use crate::{Error, PointCloud, Result};

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
