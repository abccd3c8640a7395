//! Physically based weather for paired LiDAR scans and camera images, applied only where a scene's
//! weather calls for it.
//!
//! * [`Weather`]: one description in physical units (fog MOR visibility, rain rate, snowfall rate and
//!   terminal velocity, road water depth, time of day, seed), with [`Preset`]s (light / moderate / heavy
//!   fog, rain, snow; KITTI-Weather clean, night, fog, snow).
//! * [`Plan`]: per sensor, a pipeline of only the active effects. Night changes only the camera (a LiDAR
//!   makes its own light); fog, rain and snow change both sensors through one extinction coefficient
//!   `alpha = alpha_fog + alpha_rain + alpha_snow` (LiDAR two-way `exp(-2 alpha R)`, camera one-way
//!   `exp(-alpha l)` with `l` along the pixel ray); wet ground changes the LiDAR. Clear daylight plans two
//!   empty pipelines: outputs are the inputs bit for bit and no random stream is ever constructed.
//!   Exception: the LiDAR leaves `alpha_snow` out by default, because its sampled snowflakes already
//!   occlude the beams ([`WeatherSim::lidar_alpha_per_m`], [`snow::SnowConfig::lidar_extinction`]).
//! * [`WeatherSim`]: the plan plus start-up work (the fog look-up table for the alpha in use), then
//!   [`WeatherSim::apply_lidar`] and [`WeatherSim::apply_camera`]; [`EffectsReport`] records what ran
//!   (`effects.json`).
//!
//! [`files`] applies a simulator to files (scan, image, calibration) for `veila weather` and
//! `cargo xtask kitti-weather`.
//!
//! Models: LiDAR fog after Hahner et al. 2021 ([`fog`]), snowfall after Hahner et al. 2022 ([`snow`]),
//! rain after LISA ([`rain`]), wet ground after the water-film / Fresnel model ([`wet`]); camera
//! Koschmieder veil, particles, night ([`camera`]). Each module documents its formulas and the bugs of
//! the reference implementations it avoids. Determinism: every random draw comes from a ChaCha8 stream
//! derived from (seed, effect, sensor, fixed chunk index), so results do not depend on the thread count.
//!
//! ```
//! use veila_data::PointCloud;
//! use veila_data::weather::{LidarInput, Preset, Weather, WeatherConfig, WeatherSim};
//! use glam::Vec3;
//!
//! let cloud = PointCloud {
//!     xyz: vec![Vec3::new(60.0, 0.0, 0.0), Vec3::new(5.0, 1.0, 0.0)],
//!     intensity: vec![0.5, 0.5],
//!     ring: None,
//!     label: None,
//! };
//! // clear weather: an exact identity
//! let sim = WeatherSim::new(&Weather::clear(), &WeatherConfig::default())?;
//! assert!(sim.plan().is_identity());
//! assert_eq!(sim.apply_lidar(LidarInput::new(&cloud))?.cloud, cloud);
//!
//! // dense fog: the far point becomes a fog return a few metres from the sensor
//! let sim = WeatherSim::new(&Weather::preset(Preset::FogHeavy).with_seed(7), &WeatherConfig::default())?;
//! let out = sim.apply_lidar(LidarInput::new(&cloud))?;
//! assert!(out.cloud.xyz[0].length() < 10.0);
//! assert_eq!(out.records[0].effect, "fog");
//! # Ok::<(), veila_data::Error>(())
//! ```

// `!(x > 0.0)` is used on purpose throughout: it rejects NaN together with the out-of-range values.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod camera;
pub mod camera_config;
pub mod files;
pub mod fog;
pub mod lidar;
pub mod plan;
pub mod points;
pub mod rain;
mod rng;
pub mod snow;
pub mod spec;
pub mod wet;

use serde::{Deserialize, Serialize};

pub use camera::{CameraInput, CameraOutput, DepthMap, Intrinsics};
pub use camera_config::{CameraConfig, Headlights};
pub use fog::{FogTable, FogTableConfig};
pub use lidar::{LidarConfig, LidarInput};
pub use plan::{CameraEffect, EffectRecord, EffectsReport, Input, LidarEffect, Plan, Sensor};
pub use points::{BeamTable, LidarOutput, PointOrigin};
pub use rng::rng_streams_created;
pub use spec::{Extinction, Preset, TimeOfDay, Weather};

use crate::{Error, Result};

/// All knobs of the simulator (defaults: KITTI, HDL-64E).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct WeatherConfig {
    /// LiDAR knobs.
    pub lidar: LidarConfig,
    /// Camera knobs.
    pub camera: CameraConfig,
}

/// A planned weather, ready to apply to any number of scans and images.
#[derive(Debug, Clone)]
pub struct WeatherSim {
    weather: Weather,
    cfg: WeatherConfig,
    plan: Plan,
    lidar_alpha: f64,
    fog_table: Option<FogTable>,
}

impl WeatherSim {
    /// Validate, plan, and do the start-up work of the active effects (the fog table).
    pub fn new(weather: &Weather, cfg: &WeatherConfig) -> Result<Self> {
        cfg.lidar.validate()?;
        let mut plan = Plan::new(weather, &cfg.camera)?;
        let lidar_alpha = lidar_alpha_per_m(&plan.extinction, weather, &cfg.lidar);
        if !(lidar_alpha > 0.0) {
            // snow alone, with its extinction carried by the flakes themselves
            plan.lidar.retain(|e| *e != LidarEffect::Extinction);
        }
        let fog_table = if plan.lidar.contains(&LidarEffect::Fog) {
            Some(FogTable::new(lidar_alpha, &cfg.lidar.fog_table)?)
        } else {
            None
        };
        Ok(WeatherSim {
            weather: weather.clone(),
            cfg: cfg.clone(),
            plan,
            lidar_alpha,
            fog_table,
        })
    }

    /// The extinction coefficient the LiDAR effects apply (m^-1): fog + rain, plus snow only when
    /// [`snow::SnowConfig::lidar_extinction`] is set (the sampled flakes carry the snow's extinction).
    /// The camera uses the plan's full total.
    pub fn lidar_alpha_per_m(&self) -> f64 {
        self.lidar_alpha
    }

    /// The weather.
    pub fn weather(&self) -> &Weather {
        &self.weather
    }

    /// The plan (per-sensor pipelines).
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The configuration.
    pub fn config(&self) -> &WeatherConfig {
        &self.cfg
    }

    /// The fog table, when fog is active.
    pub fn fog_table(&self) -> Option<&FogTable> {
        self.fog_table.as_ref()
    }

    /// The same simulator with another seed (e.g. one per frame); the fog table is reused.
    pub fn with_seed(&self, seed: u64) -> Self {
        let mut s = self.clone();
        s.weather.seed = seed;
        s
    }

    /// Run the LiDAR pipeline. An empty pipeline returns the input cloud unchanged (no random draw).
    /// Errors: the cloud's attributes do not align; a needed input is missing without a fallback.
    pub fn apply_lidar(&self, input: LidarInput<'_>) -> Result<LidarOutput> {
        let cloud = input.cloud;
        cloud.validate()?;
        if self.plan.lidar.is_empty() {
            return Ok(LidarOutput {
                cloud: cloud.clone(),
                origin: vec![PointOrigin::Target; cloud.len()],
                records: Vec::new(),
            });
        }
        // fail before any work when an input is missing
        if self.plan.lidar.contains(&LidarEffect::Snow)
            && cloud.ring.is_none()
            && input.beams.is_none()
        {
            return Err(Error::MissingInput {
                effect: "snow".into(),
                input: "a ring index per point or a beam elevation table (LidarInput::beams)"
                    .into(),
            });
        }
        let lc = &self.cfg.lidar;
        let alpha = self.lidar_alpha;
        let mut st = points::LidarState::new(cloud);
        let mut records = Vec::new();
        for &e in &self.plan.lidar {
            let rec = match e {
                LidarEffect::WetGround => wet::apply_wet_ground(
                    &mut st,
                    cloud,
                    input.ground_mask,
                    &self.weather,
                    lc.intensity_max,
                    &lc.wet_ground,
                )?,
                LidarEffect::Fog => {
                    let table = self.fog_table.as_ref().ok_or_else(|| Error::Invalid {
                        what: "weather simulator".into(),
                        message: "fog planned without a fog table".into(),
                    })?;
                    lidar::apply_fog(&mut st, table, &self.weather, lc)?
                }
                LidarEffect::Extinction => {
                    lidar::apply_extinction(&mut st, alpha, lc.intensity_max)
                }
                LidarEffect::Rain => rain::apply_rain(
                    &mut st,
                    &self.weather,
                    alpha,
                    lc.beam_divergence_rad,
                    lc.intensity_max,
                    &lc.rain,
                ),
                LidarEffect::Snow => snow::apply_snow(
                    &mut st,
                    cloud.ring.as_deref(),
                    input.beams,
                    &self.weather,
                    alpha,
                    lc.beam_divergence_rad,
                    lc.intensity_max,
                    &lc.snow,
                )?,
            };
            records.push(rec);
        }
        Ok(st.finish(cloud, records))
    }

    /// Run the camera pipeline. An empty pipeline returns a copy of the image (no random draw).
    pub fn apply_camera(&self, input: CameraInput<'_>) -> Result<CameraOutput> {
        camera::apply_camera(&self.plan, &self.weather, &self.cfg.camera, input)
    }

    /// An [`EffectsReport`] holding the given per-sensor records.
    pub fn report(&self, lidar: Vec<EffectRecord>, camera: Vec<EffectRecord>) -> EffectsReport {
        let mut r = EffectsReport::new(&self.weather);
        r.lidar = lidar;
        r.camera = camera;
        r
    }
}

/// See [`WeatherSim::lidar_alpha_per_m`]; the sum is formed from the parts, so it equals the plan's
/// total exactly whenever the snow share is included (or zero).
fn lidar_alpha_per_m(e: &Extinction, weather: &Weather, cfg: &LidarConfig) -> f64 {
    if weather.snow_active() && !cfg.snow.lidar_extinction {
        e.fog_per_m + e.rain_per_m
    } else {
        e.total_per_m()
    }
}
