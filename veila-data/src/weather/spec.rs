//! The weather description in physical units, its presets, and the shared extinction coefficient.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// Smallest fog visibility accepted (m). Below it the single-scattering models stop being meaningful
/// (and alpha would exceed 0.3 m^-1, beyond the Hahner et al. look-up tables' range of 0.2 m^-1).
pub const MIN_VISIBILITY_M: f64 = 10.0;

/// An extinction coefficient below this (m^-1) counts as "no fog": MOR > ~3000 km.
pub const ALPHA_EPSILON_PER_M: f64 = 1e-6;

/// Largest rain rate accepted (mm/h); the heaviest recorded hourly rates are ~300 mm/h.
pub const MAX_RAIN_RATE_MM_H: f64 = 300.0;

/// Largest snowfall rate accepted (mm/h).
pub const MAX_SNOWFALL_RATE_MM_H: f64 = 50.0;

/// Largest road water depth accepted (mm).
pub const MAX_WATER_DEPTH_MM: f64 = 20.0;

/// Density of falling snow used by Hahner et al. 2022 (g/cm^3).
pub const SNOW_DENSITY_G_CM3: f64 = 0.1;

/// Reference flake diameter `D_s` in the snowfall-rate to equivalent-rain-rate conversion (m).
pub const SNOW_REFERENCE_DIAMETER_M: f64 = 0.003;

/// Time of day. Only the camera sees it: a LiDAR brings its own light.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TimeOfDay {
    /// Full daylight: no illumination change.
    #[default]
    Day,
    /// Dusk: the scene is darkened in linear light (x0.25) and sensor noise is added.
    Dusk,
    /// Night: the scene is darkened in linear light (x0.05), sensor noise is added.
    Night,
}

impl TimeOfDay {
    /// Scale of the ambient illumination relative to daylight, in linear light (after auto exposure).
    pub fn ambient_scale(self) -> f64 {
        match self {
            TimeOfDay::Day => 1.0,
            TimeOfDay::Dusk => 0.25,
            TimeOfDay::Night => 0.05,
        }
    }
}

impl FromStr for TimeOfDay {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "day" => Ok(TimeOfDay::Day),
            "dusk" => Ok(TimeOfDay::Dusk),
            "night" => Ok(TimeOfDay::Night),
            other => Err(Error::Invalid {
                what: "time of day".into(),
                message: format!("'{other}' (expected day, dusk or night)"),
            }),
        }
    }
}

impl fmt::Display for TimeOfDay {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            TimeOfDay::Day => "day",
            TimeOfDay::Dusk => "dusk",
            TimeOfDay::Night => "night",
        })
    }
}

/// One weather description in physical units. `Weather::default()` is clear daylight: every effect is
/// inactive and applying it is a bit-exact identity that draws no random numbers.
///
/// Serialises to / from TOML and JSON, e.g.
/// `fog_visibility_m = 150.0`, `rain_rate_mm_h = 0.0`, `time_of_day = "night"`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Weather {
    /// Fog visibility as the meteorological optical range (MOR, contrast threshold 5 %), metres.
    /// `None` (or +inf) means no fog. Must be at least [`MIN_VISIBILITY_M`].
    pub fog_visibility_m: Option<f64>,
    /// Rain rate, mm/h (0 = no rain).
    pub rain_rate_mm_h: f64,
    /// Snowfall rate, mm/h (0 = no snow), as in Hahner et al. 2022.
    pub snowfall_rate_mm_h: f64,
    /// Terminal velocity of the snowflakes, m/s (used only when it snows; typically 0.5..2).
    pub snow_terminal_velocity_m_s: f64,
    /// Water film depth on the road, mm (0 = dry road).
    pub water_depth_mm: f64,
    /// Time of day (camera only).
    pub time_of_day: TimeOfDay,
    /// Seed of every random draw (fixed seed, ChaCha8 streams derived per effect, sensor and chunk).
    pub seed: u64,
}

impl Default for Weather {
    fn default() -> Self {
        Weather {
            fog_visibility_m: None,
            rain_rate_mm_h: 0.0,
            snowfall_rate_mm_h: 0.0,
            snow_terminal_velocity_m_s: 1.6,
            water_depth_mm: 0.0,
            time_of_day: TimeOfDay::Day,
            seed: 0,
        }
    }
}

/// Named weather presets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// Clear daylight (identity).
    Clear,
    /// Fog, MOR 600 m (alpha = 0.005 m^-1, Foggy Cityscapes' lightest level).
    FogLight,
    /// Fog, MOR 150 m (alpha = 0.02 m^-1, Foggy Cityscapes' densest level).
    FogModerate,
    /// Fog, MOR 50 m (alpha = 0.06 m^-1, the Hahner et al. 2021 default).
    FogHeavy,
    /// Rain 2.5 mm/h on a road with a 0.2 mm water film.
    RainLight,
    /// Rain 10 mm/h on a road with a 1.0 mm water film.
    RainModerate,
    /// Rain 50 mm/h on a road with a 1.2 mm water film (fully flooded pavement texture).
    RainHeavy,
    /// Snowfall 0.5 mm/h at 2.0 m/s (Robo3D "light").
    SnowLight,
    /// Snowfall 1.0 mm/h at 1.6 m/s (Robo3D "moderate").
    SnowModerate,
    /// Snowfall 2.5 mm/h at 1.6 m/s (Robo3D "heavy").
    SnowHeavy,
    /// KITTI-Weather "clean": clear daylight.
    KittiClean,
    /// KITTI-Weather "night": camera at night, LiDAR untouched.
    KittiNight,
    /// KITTI-Weather "fog": MOR 50 m (alpha = 0.06 m^-1).
    KittiFog,
    /// KITTI-Weather "snow": snowfall 1.0 mm/h at 1.6 m/s (Robo3D moderate).
    KittiSnow,
}

impl Preset {
    /// Every preset, in declaration order.
    pub const ALL: [Preset; 14] = [
        Preset::Clear,
        Preset::FogLight,
        Preset::FogModerate,
        Preset::FogHeavy,
        Preset::RainLight,
        Preset::RainModerate,
        Preset::RainHeavy,
        Preset::SnowLight,
        Preset::SnowModerate,
        Preset::SnowHeavy,
        Preset::KittiClean,
        Preset::KittiNight,
        Preset::KittiFog,
        Preset::KittiSnow,
    ];

    /// The kebab-case name (`"fog-heavy"`, `"kitti-night"`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Preset::Clear => "clear",
            Preset::FogLight => "fog-light",
            Preset::FogModerate => "fog-moderate",
            Preset::FogHeavy => "fog-heavy",
            Preset::RainLight => "rain-light",
            Preset::RainModerate => "rain-moderate",
            Preset::RainHeavy => "rain-heavy",
            Preset::SnowLight => "snow-light",
            Preset::SnowModerate => "snow-moderate",
            Preset::SnowHeavy => "snow-heavy",
            Preset::KittiClean => "kitti-clean",
            Preset::KittiNight => "kitti-night",
            Preset::KittiFog => "kitti-fog",
            Preset::KittiSnow => "kitti-snow",
        }
    }

    /// The weather of this preset (seed 0).
    pub fn weather(self) -> Weather {
        let clear = Weather::default();
        let fog = |v: f64| Weather {
            fog_visibility_m: Some(v),
            ..Weather::default()
        };
        let rain = |r: f64, w: f64| Weather {
            rain_rate_mm_h: r,
            water_depth_mm: w,
            ..Weather::default()
        };
        let snow = |s: f64, vt: f64| Weather {
            snowfall_rate_mm_h: s,
            snow_terminal_velocity_m_s: vt,
            ..Weather::default()
        };
        match self {
            Preset::Clear | Preset::KittiClean => clear,
            Preset::FogLight => fog(600.0),
            Preset::FogModerate => fog(150.0),
            Preset::FogHeavy | Preset::KittiFog => fog(50.0),
            Preset::RainLight => rain(2.5, 0.2),
            Preset::RainModerate => rain(10.0, 1.0),
            Preset::RainHeavy => rain(50.0, 1.2),
            Preset::SnowLight => snow(0.5, 2.0),
            Preset::SnowModerate | Preset::KittiSnow => snow(1.0, 1.6),
            Preset::SnowHeavy => snow(2.5, 1.6),
            Preset::KittiNight => Weather {
                time_of_day: TimeOfDay::Night,
                ..clear
            },
        }
    }
}

impl FromStr for Preset {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        let want = s.to_ascii_lowercase().replace('_', "-");
        Preset::ALL
            .into_iter()
            .find(|p| p.name() == want)
            .ok_or_else(|| Error::Invalid {
                what: "weather preset".into(),
                message: format!(
                    "'{s}' (expected one of: {})",
                    Preset::ALL.map(|p| p.name()).join(", ")
                ),
            })
    }
}

impl fmt::Display for Preset {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Extinction coefficients (m^-1) of each hydrometeor and their sum, shared by LiDAR and camera
/// (extinction is nearly wavelength independent from 905 nm to the visible for particles this large).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Extinction {
    /// Fog: alpha = ln(20) / MOR.
    pub fog_per_m: f64,
    /// Rain: Marshall-Palmer with Q_ext = 2, alpha = 1e-6 pi N0 / Lambda^3 (= 3.65e-4 R^0.63).
    pub rain_per_m: f64,
    /// Snow: Marshall-Gunn with Q_ext = 2 at the equivalent rain rate (= 1.44e-3 R_eq^0.57).
    pub snow_per_m: f64,
}

impl Extinction {
    /// The total extinction coefficient alpha (m^-1) that both sensors use.
    pub fn total_per_m(&self) -> f64 {
        self.fog_per_m + self.rain_per_m + self.snow_per_m
    }
}

/// Fog extinction from MOR visibility: alpha = ln(20) / V (5 % contrast threshold, WMO).
/// Returns 0 for infinite visibility.
pub fn fog_alpha_per_m(visibility_m: f64) -> f64 {
    if visibility_m.is_infinite() {
        0.0
    } else {
        20f64.ln() / visibility_m
    }
}

/// Fog backscatter coefficient tied to visibility as in Hahner et al. 2021: beta = 0.046 / MOR (m^-1 sr^-1).
pub fn fog_backscatter_per_m(visibility_m: f64) -> f64 {
    if visibility_m.is_infinite() {
        0.0
    } else {
        0.046 / visibility_m
    }
}

/// Marshall-Palmer rain drop-size distribution: `(N0 [m^-3 mm^-1], Lambda [mm^-1])` at rate `r` mm/h.
pub fn marshall_palmer(rate_mm_h: f64) -> (f64, f64) {
    (8000.0, 4.1 * rate_mm_h.powf(-0.21))
}

/// Marshall-Gunn snow size distribution: `(N0 [m^-3 mm^-1], Lambda [mm^-1])` at the equivalent rain rate.
pub fn marshall_gunn(rate_eq_mm_h: f64) -> (f64, f64) {
    (
        7.6e3 * rate_eq_mm_h.powf(-0.87),
        2.55 * rate_eq_mm_h.powf(-0.48),
    )
}

/// Extinction of an exponential size distribution `N0 exp(-Lambda D)` with extinction efficiency 2:
/// `alpha = (pi/4) 1e-6 * integral D^2 Q N(D) dD = 1e-6 pi N0 / Lambda^3` (D in mm, alpha in m^-1).
pub fn exponential_dsd_alpha_per_m(n0: f64, lambda: f64) -> f64 {
    1e-6 * std::f64::consts::PI * n0 / (lambda * lambda * lambda)
}

/// Equivalent rain rate of a snowfall (Hahner et al. 2022):
/// `R = (S / (487 rho_snow D_s v_t))^(3/2)` with rho_snow = 0.1 g/cm^3 and D_s = 3 mm.
pub fn snow_equivalent_rain_rate_mm_h(snowfall_mm_h: f64, terminal_velocity_m_s: f64) -> f64 {
    (snowfall_mm_h
        / (487.0 * SNOW_DENSITY_G_CM3 * SNOW_REFERENCE_DIAMETER_M * terminal_velocity_m_s))
        .powf(1.5)
}

/// Fraction of the plane occupied by snowflakes (Hahner et al. 2022):
/// `rho_occ = rho_water S / (3.6e6 rho_snow v_t)`.
pub fn snow_occupancy(snowfall_mm_h: f64, terminal_velocity_m_s: f64) -> f64 {
    snowfall_mm_h / (3.6e6 * SNOW_DENSITY_G_CM3 * terminal_velocity_m_s)
}

impl Weather {
    /// Clear daylight with the given seed.
    pub fn clear() -> Self {
        Weather::default()
    }

    /// The weather of a named preset.
    pub fn preset(p: Preset) -> Self {
        p.weather()
    }

    /// The same weather with another seed.
    pub fn with_seed(mut self, seed: u64) -> Self {
        self.seed = seed;
        self
    }

    /// Check every field's domain (finite, non-negative, within physical limits).
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str, message: String| {
            Err(Error::Invalid {
                what: format!("weather {what}"),
                message,
            })
        };
        if let Some(v) = self.fog_visibility_m
            && (v.is_nan() || v < MIN_VISIBILITY_M)
        {
            return bad(
                "fog_visibility_m",
                format!(
                    "{v} m (must be at least {MIN_VISIBILITY_M} m, or absent / inf for no fog)"
                ),
            );
        }
        let check = |what: &str, x: f64, max: f64| -> Result<()> {
            if !(x.is_finite() && (0.0..=max).contains(&x)) {
                return bad(what, format!("{x} (must be finite, in [0, {max}])"));
            }
            Ok(())
        };
        check("rain_rate_mm_h", self.rain_rate_mm_h, MAX_RAIN_RATE_MM_H)?;
        check(
            "snowfall_rate_mm_h",
            self.snowfall_rate_mm_h,
            MAX_SNOWFALL_RATE_MM_H,
        )?;
        check("water_depth_mm", self.water_depth_mm, MAX_WATER_DEPTH_MM)?;
        let vt = self.snow_terminal_velocity_m_s;
        if self.snowfall_rate_mm_h > 0.0 && !(vt.is_finite() && (0.05..=20.0).contains(&vt)) {
            return bad(
                "snow_terminal_velocity_m_s",
                format!("{vt} m/s (must be in [0.05, 20])"),
            );
        }
        Ok(())
    }

    /// True when fog is active (visibility finite and alpha above [`ALPHA_EPSILON_PER_M`]).
    pub fn fog_active(&self) -> bool {
        matches!(self.fog_visibility_m, Some(v) if v.is_finite() && fog_alpha_per_m(v) >= ALPHA_EPSILON_PER_M)
    }

    /// True when it rains.
    pub fn rain_active(&self) -> bool {
        self.rain_rate_mm_h > 0.0
    }

    /// True when it snows.
    pub fn snow_active(&self) -> bool {
        self.snowfall_rate_mm_h > 0.0
    }

    /// True when the road carries a water film.
    pub fn wet_ground_active(&self) -> bool {
        self.water_depth_mm > 0.0
    }

    /// The extinction coefficients. Inactive hydrometeors contribute exactly 0.
    pub fn extinction(&self) -> Extinction {
        let fog_per_m = match self.fog_visibility_m {
            Some(v) if self.fog_active() => fog_alpha_per_m(v),
            _ => 0.0,
        };
        let rain_per_m = if self.rain_active() {
            let (n0, l) = marshall_palmer(self.rain_rate_mm_h);
            exponential_dsd_alpha_per_m(n0, l)
        } else {
            0.0
        };
        let snow_per_m = if self.snow_active() {
            let r = snow_equivalent_rain_rate_mm_h(
                self.snowfall_rate_mm_h,
                self.snow_terminal_velocity_m_s,
            );
            let (n0, l) = marshall_gunn(r);
            exponential_dsd_alpha_per_m(n0, l)
        } else {
            0.0
        };
        Extinction {
            fog_per_m,
            rain_per_m,
            snow_per_m,
        }
    }
}
