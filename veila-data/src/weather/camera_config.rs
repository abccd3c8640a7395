//! The camera's knobs, read by the planner (whether headlights run) and by the camera effects
//! ([`super::camera`]).

use serde::{Deserialize, Serialize};

/// Headlights of the ego vehicle (camera frame: x right, y down, z forward).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Headlights {
    /// On-axis irradiance at 1 m, in units of the daylight white level.
    pub intensity: f64,
    /// Cone exponent m of `cos^m` (8: half power at ~24 deg).
    pub exponent: f64,
    /// Light position in the camera frame (m).
    pub position_m: [f64; 3],
    /// Downward tilt of the beam axis (deg).
    pub tilt_down_deg: f64,
    /// Low-beam cut-off: no light more than this far above the lamp's horizontal plane (deg).
    pub cutoff_above_horizontal_deg: f64,
}

impl Default for Headlights {
    fn default() -> Self {
        Headlights {
            intensity: 40.0,
            exponent: 8.0,
            position_m: [0.0, 0.95, 0.0],
            tilt_down_deg: 2.0,
            cutoff_above_horizontal_deg: 0.5,
        }
    }
}

/// Camera knobs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CameraConfig {
    /// Exposure time (s), for the particle streak length.
    pub exposure_s: f64,
    /// Airlight in linear RGB 0..1 (daylight); `None`: estimated from the image's dark channel.
    pub airlight: Option<[f32; 3]>,
    /// Headlights at dusk / night; `None`: none.
    pub headlights: Option<Headlights>,
    /// Bits of the ADC that quantises the noisy linear signal.
    pub adc_bits: u32,
    /// Upper bound on drawn particles per image (the count is reported when it binds).
    pub max_particles: usize,
}

impl Default for CameraConfig {
    fn default() -> Self {
        CameraConfig {
            exposure_s: 0.008,
            airlight: None,
            headlights: None,
            adc_bits: 10,
            max_particles: 200_000,
        }
    }
}
