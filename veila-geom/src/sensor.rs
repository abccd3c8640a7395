//! LiDAR sensor models: a uniform grid of beams or a per-beam elevation table.

use serde::{Deserialize, Serialize};

use crate::GeomError;

/// A built-in sensor by name. [`SensorPreset::ALL`] is the one list of presets: the data crate's
/// `--sensor` specs and sensor files, the simulator's `lidar.preset`, the CLI's `veila sensors` and
/// the Python wheel's `sensor=` all take their names from it (and a test of each door checks that
/// they do). A new preset is a constructor on [`LidarSensor`], a variant here and its arms in
/// [`SensorPreset::as_str`], [`SensorPreset::help`] and [`SensorPreset::sensor`].
///
/// Serialised as its name ([`SensorPreset::as_str`]); reading also takes `hdl32e_per_beam`, the
/// spelling scene files used before the presets had one list.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum SensorPreset {
    /// [`LidarSensor::hdl64e`].
    #[default]
    Hdl64e,
    /// [`LidarSensor::hdl32e`].
    Hdl32e,
    /// [`LidarSensor::hdl32e_per_beam`].
    Hdl32ePerBeam,
}

impl SensorPreset {
    /// Every preset, in the order help texts list them.
    pub const ALL: [SensorPreset; 3] = [
        SensorPreset::Hdl64e,
        SensorPreset::Hdl32e,
        SensorPreset::Hdl32ePerBeam,
    ];

    /// The one spelling of the preset's name: `hdl64e`, `hdl32e`, `hdl32e-per-beam`.
    pub fn as_str(self) -> &'static str {
        match self {
            SensorPreset::Hdl64e => "hdl64e",
            SensorPreset::Hdl32e => "hdl32e",
            SensorPreset::Hdl32ePerBeam => "hdl32e-per-beam",
        }
    }

    /// One line for a `--help` text.
    pub fn help(self) -> &'static str {
        match self {
            SensorPreset::Hdl64e => {
                "Velodyne HDL-64E (KITTI, SemanticKITTI): 64 x 1024, uniform rows"
            }
            SensorPreset::Hdl32e => "Velodyne HDL-32E (nuScenes): 32 x 1024, uniform rows",
            SensorPreset::Hdl32ePerBeam => {
                "HDL-32E with its per-beam elevation table, rows from the scan's ring index"
            }
        }
    }

    /// The sensor.
    pub fn sensor(self) -> LidarSensor {
        match self {
            SensorPreset::Hdl64e => LidarSensor::hdl64e(),
            SensorPreset::Hdl32e => LidarSensor::hdl32e(),
            SensorPreset::Hdl32ePerBeam => LidarSensor::hdl32e_per_beam(),
        }
    }

    /// Every preset's name, `, `-separated, in [`SensorPreset::ALL`]'s order (for help texts and
    /// error messages).
    pub fn names() -> String {
        SensorPreset::ALL.map(SensorPreset::as_str).join(", ")
    }

    /// The preset of a file written before the presets had one list: `hdl32e_per_beam`.
    fn from_old_spelling(name: &str) -> Option<SensorPreset> {
        (name == "hdl32e_per_beam").then_some(SensorPreset::Hdl32ePerBeam)
    }
}

impl std::fmt::Display for SensorPreset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for SensorPreset {
    type Err = GeomError;

    /// A preset by its one name; an unknown name is an error listing the presets.
    fn from_str(name: &str) -> Result<Self, GeomError> {
        SensorPreset::ALL
            .into_iter()
            .find(|p| p.as_str() == name)
            .ok_or_else(|| GeomError::InvalidConfig {
                what: "sensor preset",
                message: format!("`{name}` is not one of {}", SensorPreset::names()),
            })
    }
}

impl Serialize for SensorPreset {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> Deserialize<'de> for SensorPreset {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        SensorPreset::from_old_spelling(&name)
            .map_or_else(|| name.parse(), Ok)
            .map_err(serde::de::Error::custom)
    }
}

/// How the rows (beams) of a range image are laid out in elevation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum BeamLayout {
    /// Rows split the vertical field of view evenly: row `r` covers
    /// `[fov_up - (r+1) f/h, fov_up - r f/h]` (equation 1 of the paper).
    #[default]
    Uniform,
    /// One elevation per beam, as the sensor's calibration gives it.
    PerBeam {
        /// Elevation of every beam in degrees, strictly monotone (either direction) and inside the field
        /// of view. Entry `i` is beam (ring) `i`.
        elevations_deg: Vec<f32>,
        /// How a point finds its row.
        row_source: RowSource,
    },
}

/// How a point is assigned to a beam in [`BeamLayout::PerBeam`] mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RowSource {
    /// The dataset stores the ring (beam) index of every point (nuScenes); use it.
    Ring,
    /// The beam whose elevation is nearest to the point's elevation (binary search).
    NearestElevation,
}

/// The most pixels (`rows * cols`) a sensor may have: 4 Mi, 8x a 128-beam sensor at 4096 columns.
/// Every range image, projection buffer and ray table of a sensor grows with its pixel count, so the
/// bound keeps a sensor file from asking for gigabytes (4096 x 262144 would be 1 Gi pixels).
pub const MAX_SENSOR_PIXELS: u64 = 1 << 22;

/// A spinning LiDAR: `rows` beams by `cols` azimuth steps, a vertical field of view and a valid range.
///
/// Row 0 is the top beam; column 0 starts at azimuth +pi (behind the sensor, on the left-hand side of
/// the seam) and columns advance clockwise seen from above, exactly as equation 1 of the paper:
/// `u = 1/2 (1 - atan2(y, x) / pi) w`. The LiDAR frame is x forward, y left, z up, metres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LidarSensor {
    /// Number of beams (range-image height).
    pub rows: u32,
    /// Number of azimuth steps (range-image width).
    pub cols: u32,
    /// Upper edge of the vertical field of view in degrees (positive up).
    pub fov_up_deg: f32,
    /// Lower edge of the vertical field of view in degrees (negative below the horizon).
    pub fov_down_deg: f32,
    /// Smallest valid range in metres; nearer returns are rejected.
    pub min_range_m: f32,
    /// Largest valid range in metres; farther returns are rejected.
    pub max_range_m: f32,
    /// Beam layout.
    #[serde(default)]
    pub beams: BeamLayout,
}

impl LidarSensor {
    /// Velodyne HDL-64E as used by KITTI and SemanticKITTI: 64 x 1024, +3 deg / -25 deg, uniform
    /// rows (the R2DM / LiDARGen convention), valid range 0.5 m to 120 m.
    pub fn hdl64e() -> Self {
        LidarSensor {
            rows: 64,
            cols: 1024,
            fov_up_deg: 3.0,
            fov_down_deg: -25.0,
            min_range_m: 0.5,
            max_range_m: 120.0,
            beams: BeamLayout::Uniform,
        }
    }

    /// Velodyne HDL-32E as used by nuScenes: 32 x 1024, +10 deg / -30 deg, uniform rows, valid range
    /// 1 m to 100 m (nuScenes' points within 1 m are returns from the ego vehicle).
    pub fn hdl32e() -> Self {
        LidarSensor {
            rows: 32,
            cols: 1024,
            fov_up_deg: 10.0,
            fov_down_deg: -30.0,
            min_range_m: 1.0,
            max_range_m: 100.0,
            beams: BeamLayout::Uniform,
        }
    }

    /// HDL-32E in per-beam mode with its nominal elevation table (-30.67 deg to +10.66 deg in
    /// steps of 4/3 deg), rows taken from the ring index nuScenes stores with every point.
    ///
    /// nuScenes' ring 0 is the lowest beam; the table is therefore increasing and row 0 (top) is ring 31.
    /// The field of view reaches half a beam spacing (2/3 deg) beyond the outer beams, so that the
    /// returns of the top and bottom rings, which scatter by about +-0.2 deg around their nominal
    /// elevation in real nuScenes sweeps, are not rejected as outside the field of view.
    pub fn hdl32e_per_beam() -> Self {
        let elevations_deg: Vec<f32> = (0..32).map(|i| -30.67 + i as f32 * (4.0 / 3.0)).collect();
        let half_step = 2.0 / 3.0;
        LidarSensor {
            fov_up_deg: elevations_deg[31] + half_step,
            fov_down_deg: elevations_deg[0] - half_step,
            beams: BeamLayout::PerBeam {
                elevations_deg,
                row_source: RowSource::Ring,
            },
            ..Self::hdl32e()
        }
    }

    /// Check every invariant; all other methods assume a validated sensor.
    pub fn validate(&self) -> Result<(), GeomError> {
        let bad = |m: String| Err(GeomError::InvalidSensor(m));
        if self.rows == 0 || self.cols == 0 {
            return bad(format!(
                "size must be positive, got {}x{}",
                self.rows, self.cols
            ));
        }
        if self.rows > 1 << 16 || self.cols > 1 << 20 {
            return bad(format!(
                "size {}x{} is unreasonably large",
                self.rows, self.cols
            ));
        }
        let pixels = u64::from(self.rows) * u64::from(self.cols);
        if pixels > MAX_SENSOR_PIXELS {
            return bad(format!(
                "size {}x{} is {pixels} pixels, more than the limit of {MAX_SENSOR_PIXELS} \
                 (every range image of the sensor is held in memory, ~24 bytes per pixel)",
                self.rows, self.cols
            ));
        }
        if !self.fov_up_deg.is_finite() || !self.fov_down_deg.is_finite() {
            return bad("field of view must be finite".into());
        }
        if self.fov_up_deg <= self.fov_down_deg {
            return bad(format!(
                "fov_up_deg ({}) must be greater than fov_down_deg ({})",
                self.fov_up_deg, self.fov_down_deg
            ));
        }
        if self.fov_up_deg > 90.0 || self.fov_down_deg < -90.0 {
            return bad("field of view must lie within [-90, 90] degrees".into());
        }
        if !(self.min_range_m.is_finite() && self.max_range_m.is_finite())
            || self.min_range_m < 0.0
            || self.min_range_m >= self.max_range_m
        {
            return bad(format!(
                "valid range must satisfy 0 <= min < max (finite), got [{}, {}]",
                self.min_range_m, self.max_range_m
            ));
        }
        if let BeamLayout::PerBeam { elevations_deg, .. } = &self.beams {
            if elevations_deg.len() != self.rows as usize {
                return bad(format!(
                    "per-beam table has {} entries for {} rows",
                    elevations_deg.len(),
                    self.rows
                ));
            }
            if let Some((i, e)) = elevations_deg
                .iter()
                .enumerate()
                .find(|(_, e)| !e.is_finite())
            {
                return bad(format!("beam {i} elevation {e} is not finite"));
            }
            if let Some((i, e)) = elevations_deg
                .iter()
                .enumerate()
                .find(|(_, e)| **e > self.fov_up_deg || **e < self.fov_down_deg)
            {
                return bad(format!(
                    "beam {i} elevation {e} deg lies outside the field of view [{}, {}]",
                    self.fov_down_deg, self.fov_up_deg
                ));
            }
            if self.rows > 1 {
                let inc = elevations_deg.windows(2).all(|w| w[1] > w[0]);
                let dec = elevations_deg.windows(2).all(|w| w[1] < w[0]);
                if !inc && !dec {
                    return bad("per-beam elevations must be strictly monotone".into());
                }
            }
        }
        Ok(())
    }

    /// Number of pixels of the range image (`rows * cols`).
    pub fn num_pixels(&self) -> usize {
        self.rows as usize * self.cols as usize
    }

    /// Upper edge of the vertical field of view, radians.
    pub fn fov_up_rad(&self) -> f32 {
        self.fov_up_deg.to_radians()
    }

    /// Lower edge of the vertical field of view, radians (negative below the horizon).
    pub fn fov_down_rad(&self) -> f32 {
        self.fov_down_deg.to_radians()
    }

    /// Total vertical field of view `f = |f_up| + |f_down|` for a field of view spanning the horizon,
    /// in general `f_up - f_down`, radians.
    pub fn fov_rad(&self) -> f32 {
        (self.fov_up_deg - self.fov_down_deg).to_radians()
    }

    /// The beam (ring) that feeds `row`, in per-beam mode; `row` itself in uniform mode.
    pub fn ring_of_row(&self, row: u32) -> u32 {
        match &self.beams {
            BeamLayout::PerBeam { elevations_deg, .. }
                if self.rows > 1 && elevations_deg[1] > elevations_deg[0] =>
            {
                self.rows - 1 - row
            }
            _ => row,
        }
    }

    /// The row that beam (ring) `ring` feeds; `None` for a ring outside `0..rows`.
    pub fn row_of_ring(&self, ring: u32) -> Option<u32> {
        (ring < self.rows).then(|| self.ring_of_row(ring))
    }

    /// Elevation of the centre of `row` in radians. Uniform mode: the centre of the row's band
    /// (`v = row + 1/2` in equation 1); per-beam mode: the beam's own elevation.
    pub fn row_elevation_rad(&self, row: u32) -> f32 {
        match &self.beams {
            BeamLayout::Uniform => {
                let up = f64::from(self.fov_up_deg).to_radians();
                let f = f64::from(self.fov_up_deg - self.fov_down_deg).to_radians();
                (up - (f64::from(row) + 0.5) / f64::from(self.rows) * f) as f32
            }
            BeamLayout::PerBeam { elevations_deg, .. } => {
                elevations_deg[self.ring_of_row(row) as usize].to_radians()
            }
        }
    }

    /// Azimuth of the centre of `col` in radians, in `(-pi, pi]`; the inverse of equation 1
    /// (`atan2(y, x) = pi (1 - 2u/w)` at `u = col + 1/2`).
    pub fn col_azimuth_rad(&self, col: u32) -> f32 {
        let u = f64::from(col) + 0.5;
        (std::f64::consts::PI * (1.0 - 2.0 * u / f64::from(self.cols))) as f32
    }

    /// Read-only access to the per-beam elevations (degrees, by ring), if any.
    pub fn beam_elevations_deg(&self) -> Option<&[f32]> {
        match &self.beams {
            BeamLayout::PerBeam { elevations_deg, .. } => Some(elevations_deg),
            BeamLayout::Uniform => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_preset_has_one_name_that_parses_back_and_a_valid_sensor() {
        for p in SensorPreset::ALL {
            assert_eq!(p.as_str().parse::<SensorPreset>(), Ok(p));
            assert_eq!(p.to_string(), p.as_str());
            assert!(!p.help().is_empty());
            p.sensor().validate().unwrap();
            assert_eq!(
                SensorPreset::ALL
                    .iter()
                    .filter(|q| q.as_str() == p.as_str())
                    .count(),
                1
            );
        }
        let e = "vlp16".parse::<SensorPreset>().unwrap_err().to_string();
        assert!(
            e.contains("vlp16") && e.contains(&SensorPreset::names()),
            "{e}"
        );
        // the old spelling is a file's alias only, not a second name
        assert!("hdl32e_per_beam".parse::<SensorPreset>().is_err());
    }

    #[test]
    fn presets_serialise_as_their_name_and_old_files_still_read() {
        #[derive(Debug, PartialEq, Serialize, Deserialize)]
        struct File {
            preset: SensorPreset,
        }
        for preset in SensorPreset::ALL {
            let text = toml::to_string(&File { preset }).unwrap();
            assert_eq!(text.trim(), format!("preset = \"{preset}\""));
            assert_eq!(toml::from_str::<File>(&text).unwrap(), File { preset });
        }
        let old: File = toml::from_str("preset = \"hdl32e_per_beam\"").unwrap();
        assert_eq!(old.preset, SensorPreset::Hdl32ePerBeam);
        let e = toml::from_str::<File>("preset = \"vlp16\"")
            .unwrap_err()
            .to_string();
        assert!(e.contains("vlp16") && e.contains("hdl32e-per-beam"), "{e}");
    }
}
