//! The effect planner: per sensor, a pipeline of only the effects a [`Weather`] calls for, and the
//! serialisable record of what ran (`effects.json`).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::camera_config::CameraConfig;
use super::spec::{Extinction, TimeOfDay, Weather};
use crate::Result;

/// A sensor of the rig.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sensor {
    /// The LiDAR (active: it makes its own light).
    Lidar,
    /// The RGB camera (passive).
    Camera,
}

/// An input an effect may need beyond the points / pixels themselves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Input {
    /// Laser ring (beam) index per point. Fallback: nearest elevation in a [`super::BeamTable`].
    Ring,
    /// Which points lie on the road. Fallback: SemanticKITTI labels, else a RANSAC + least-squares plane fit.
    GroundMask,
    /// Per-pixel z depth of the camera image (no fallback in the library: an error when absent).
    DepthMap,
    /// Camera intrinsics, to turn z depth into the distance along the pixel ray.
    Intrinsics,
}

/// LiDAR effects, in the order they run (surface first, then the volume, then particles).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LidarEffect {
    /// Water film on the road: Fresnel transmission through the film, weaker or lost ground returns.
    WetGround,
    /// Hahner et al. 2021 fog: two-way attenuation `exp(-2 alpha R)` with the total alpha, and the fog
    /// backscatter return that replaces the hard return when stronger.
    Fog,
    /// Two-way attenuation `exp(-2 alpha R)` alone (rain and/or snow without fog). [`super::WeatherSim`]
    /// drops it when only snow is active and its extinction is left to the flakes
    /// ([`super::snow::SnowConfig::lidar_extinction`]).
    Extinction,
    /// LISA rain: near-drop returns, range noise, lost points.
    Rain,
    /// Hahner et al. 2022 snowfall: beams partly occluded by sampled flakes, flake returns.
    Snow,
}

impl LidarEffect {
    /// The name used in reports.
    pub fn name(self) -> &'static str {
        match self {
            LidarEffect::WetGround => "wet_ground",
            LidarEffect::Fog => "fog",
            LidarEffect::Extinction => "extinction",
            LidarEffect::Rain => "rain",
            LidarEffect::Snow => "snow",
        }
    }

    /// Inputs this effect needs (each has the fallback documented on [`Input`]).
    pub fn required_inputs(self) -> &'static [Input] {
        match self {
            LidarEffect::WetGround => &[Input::GroundMask],
            LidarEffect::Snow => &[Input::Ring],
            _ => &[],
        }
    }
}

/// Camera effects, in the order they run (all in linear light; quantisation last).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraEffect {
    /// Dusk / night: ambient illumination scaled down in linear light.
    Darken,
    /// Headlights (only when dark and configured): `E = I0 cos^m(off-axis) / d^2` times the albedo.
    Headlights,
    /// Koschmieder veil `I = J t + A (1 - t)`, `t = exp(-alpha l)`, l along the pixel ray.
    Veil,
    /// Motion-blurred rain drops near the camera.
    RainStreaks,
    /// Snowflakes near the camera.
    Snowflakes,
    /// Shot + read noise and ADC quantisation (dusk / night).
    SensorNoise,
}

impl CameraEffect {
    /// The name used in reports.
    pub fn name(self) -> &'static str {
        match self {
            CameraEffect::Darken => "darken",
            CameraEffect::Headlights => "headlights",
            CameraEffect::Veil => "veil",
            CameraEffect::RainStreaks => "rain_streaks",
            CameraEffect::Snowflakes => "snowflakes",
            CameraEffect::SensorNoise => "sensor_noise",
        }
    }

    /// Inputs this effect needs.
    pub fn required_inputs(self) -> &'static [Input] {
        match self {
            CameraEffect::Headlights | CameraEffect::Veil => &[Input::DepthMap, Input::Intrinsics],
            CameraEffect::RainStreaks | CameraEffect::Snowflakes => &[Input::Intrinsics],
            _ => &[],
        }
    }
}

/// Per-sensor pipelines of only the active effects.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    /// LiDAR effects in run order (empty: the LiDAR output is the input, bit for bit).
    pub lidar: Vec<LidarEffect>,
    /// Camera effects in run order (empty: the image output is the input, bit for bit).
    pub camera: Vec<CameraEffect>,
    /// Extinction coefficients shared by both sensors.
    pub extinction: Extinction,
}

impl Plan {
    /// Plan the pipelines for `weather` (validated first). Clear daylight gives two empty pipelines.
    ///
    /// * night / dusk: camera only ([`CameraEffect::Darken`], optional headlights, [`CameraEffect::SensorNoise`]);
    /// * fog, rain, snow: both sensors through the one total extinction coefficient;
    /// * wet ground: LiDAR only.
    pub fn new(weather: &Weather, camera: &CameraConfig) -> Result<Plan> {
        weather.validate()?;
        let extinction = weather.extinction();
        let alpha = extinction.total_per_m();
        let mut lidar = Vec::new();
        if weather.wet_ground_active() {
            lidar.push(LidarEffect::WetGround);
        }
        if weather.fog_active() {
            lidar.push(LidarEffect::Fog);
        } else if alpha > 0.0 {
            lidar.push(LidarEffect::Extinction);
        }
        if weather.rain_active() {
            lidar.push(LidarEffect::Rain);
        }
        if weather.snow_active() {
            lidar.push(LidarEffect::Snow);
        }

        let mut cam = Vec::new();
        let dark = weather.time_of_day != TimeOfDay::Day;
        if dark {
            cam.push(CameraEffect::Darken);
            if camera.headlights.is_some() {
                cam.push(CameraEffect::Headlights);
            }
        }
        if alpha > 0.0 {
            cam.push(CameraEffect::Veil);
        }
        if weather.rain_active() {
            cam.push(CameraEffect::RainStreaks);
        }
        if weather.snow_active() {
            cam.push(CameraEffect::Snowflakes);
        }
        if dark {
            cam.push(CameraEffect::SensorNoise);
        }
        Ok(Plan {
            lidar,
            camera: cam,
            extinction,
        })
    }

    /// True when neither sensor changes.
    pub fn is_identity(&self) -> bool {
        self.lidar.is_empty() && self.camera.is_empty()
    }
}

/// What one effect did on one sensor.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct EffectRecord {
    /// Effect name ([`LidarEffect::name`] / [`CameraEffect::name`]).
    pub effect: String,
    /// Physical parameters used (alpha, beta, rates, ...).
    pub params: BTreeMap<String, f64>,
    /// Counts (points changed / replaced / lost, particles drawn, ...).
    pub counts: BTreeMap<String, u64>,
    /// Fallbacks taken and other remarks, in words.
    pub notes: Vec<String>,
}

impl EffectRecord {
    pub(crate) fn new(effect: &str) -> Self {
        EffectRecord {
            effect: effect.to_string(),
            ..Default::default()
        }
    }
    pub(crate) fn param(mut self, k: &str, v: f64) -> Self {
        self.params.insert(k.to_string(), v);
        self
    }
    pub(crate) fn count(mut self, k: &str, v: u64) -> Self {
        self.counts.insert(k.to_string(), v);
        self
    }
    pub(crate) fn note(mut self, n: impl Into<String>) -> Self {
        self.notes.push(n.into());
        self
    }
}

/// The record of one weather run over a LiDAR scan and / or a camera image (written as `effects.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EffectsReport {
    /// The weather applied.
    pub weather: Weather,
    /// Extinction coefficients (m^-1).
    pub extinction: Extinction,
    /// Total extinction coefficient alpha (m^-1).
    pub alpha_total_per_m: f64,
    /// LiDAR effects that ran, in order (empty = identity).
    pub lidar: Vec<EffectRecord>,
    /// Camera effects that ran, in order (empty = identity).
    pub camera: Vec<EffectRecord>,
}

impl EffectsReport {
    /// An empty report for `weather` (no effect ran yet).
    pub fn new(weather: &Weather) -> Self {
        let extinction = weather.extinction();
        EffectsReport {
            weather: weather.clone(),
            extinction,
            alpha_total_per_m: extinction.total_per_m(),
            lidar: Vec::new(),
            camera: Vec::new(),
        }
    }

    /// Names of the effects that ran on `sensor`.
    pub fn names(&self, sensor: Sensor) -> Vec<&str> {
        let v = match sensor {
            Sensor::Lidar => &self.lidar,
            Sensor::Camera => &self.camera,
        };
        v.iter().map(|r| r.effect.as_str()).collect()
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> Result<String> {
        serde_json::to_string_pretty(self).map_err(|e| crate::Error::Invalid {
            what: "effects report".into(),
            message: e.to_string(),
        })
    }
}
