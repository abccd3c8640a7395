//! The scene file: a TOML description of a procedural driving scene.
//!
//! Every section and field is optional; a missing value takes the default of the chosen layout.
//! Unknown fields are an error (a typo never silently falls back to a default).
//!
//! ```toml
//! name = "junction"
//! layout = "junction"          # straight | junction | t_junction | narrow_street | open
//!
//! [road]
//! length_m = 240.0
//! lanes_per_direction = 2
//!
//! [population]
//! moving_vehicles = 8
//! pedestrians = 12
//! tree_line_probability = 0.5  # open roadsides only; belts of dense woodland (default 0)
//!
//! [ego]
//! speed_mps = 8.0
//!
//! [lidar]
//! preset = "hdl64e"            # or a full [lidar.sensor] table (veila_geom::LidarSensor)
//!
//! [appearance]
//! randomize = true             # textures, palettes, sun and sky drawn per scene (AppearanceConfig)
//! # randomize_lighting = true   # or the sun and sky alone, over the stock materials
//! # randomize_materials = true  # or the palettes and textures alone, under the stock sun and sky
//!
//! [rig]
//! randomize = true             # LiDAR height, camera height and pitch drawn per scene (RigConfig)
//!
//! [frames]
//! count = 10
//! ```
//!
//! Curved streets (`[road]`, every key optional; see [`RoadConfig::curve_probability`]): the main
//! street of the straight, narrow-street and open layouts bends with a probability drawn per
//! scene, left or right at even odds, on a circular arc between two straight tangents. The scene is
//! laid out in road coordinates (distance `s` along the centreline, offset across it) mapped
//! through the bent centreline ([`super::curve::RoadCurve`]): ground, markings and long runs of
//! fence, hedge and guardrail bend with the road; buildings, trees, poles, signs and vehicles stand
//! upright at their place turned to the road's heading there; the ego and the traffic drive along
//! their lanes; the LiDAR and camera turn with the ego. The junction layout ignores these keys.
//!
//! ```toml
//! [road]
//! curve_probability = 1.0          # default 0: straight
//! curve_radius_m = [40.0, 600.0]   # drawn per scene, log-uniform (default)
//! curve_angle_deg = [30.0, 120.0]  # how far the street turns (default)
//! ```

use std::path::Path;

/// The most frames one simulation renders (a scene file's `frames.count`, or the frame count a
/// caller passes to [`crate::sim::simulate_to_dir`]).
pub const MAX_FRAMES: u32 = 100_000;

use serde::{Deserialize, Serialize};
use veila_geom::{LidarSensor, SensorPreset};

use crate::{Error, Result};

/// Street layout of a scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Layout {
    /// A straight street with lanes in both directions, parking strips, sidewalks and buildings.
    #[default]
    Straight,
    /// Two streets crossing at the origin, with crosswalks, stop lines and traffic lights.
    Junction,
    /// A T junction: the ego's street ends at a cross street, and a row of lots across it (its
    /// facades where [`RoadConfig::building_frontage`] builds, fences, hedges and trees in the
    /// gaps) faces the ego, so the view straight ahead ends at them rather than running on down
    /// the street. Cross traffic, crosswalk and traffic lights as in [`Layout::Junction`]; with
    /// [`EgoConfig::start_x_range_m`] the facades stand at a different distance in every scene.
    TJunction,
    /// A narrow street: one lane per direction without markings, narrow sidewalks, facades close to
    /// the road and cars parked on the carriageway.
    NarrowStreet,
    /// A road through open country: no parking strips, a narrow paved shoulder (a `sidewalk`) and
    /// open roadsides on both sides by default ([`RoadConfig::open_side_probability`] 1): grass,
    /// trees in rows, clusters and alone at every distance, field fences and hedges, guardrails,
    /// and only now and then a row of buildings far back.
    Open,
}

impl Layout {
    /// Whether the scene has a cross street (the junction layouts), whose arms keep their lots
    /// and whose main street never bends.
    pub fn has_cross_street(self) -> bool {
        matches!(self, Layout::Junction | Layout::TJunction)
    }
}

/// A complete scene description (the root of a scene TOML file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct SceneConfig {
    /// Free-form name, written to the output's `scene.json`.
    pub name: String,
    /// Street layout.
    pub layout: Layout,
    /// Road cross-section and building lots.
    pub road: RoadConfig,
    /// How many objects of each kind.
    pub population: PopulationConfig,
    /// The ego vehicle carrying the sensors.
    pub ego: EgoConfig,
    /// The LiDAR and its return model.
    pub lidar: LidarConfig,
    /// The camera (KITTI-like by default).
    pub camera: CameraConfig,
    /// Sun and sky.
    pub lighting: LightingConfig,
    /// Appearance randomisation of the camera image (off by default; left out of the serialised
    /// scene while it is at its default, so `scene.json` of earlier scene files is unchanged).
    #[serde(skip_serializing_if = "AppearanceConfig::is_default")]
    pub appearance: AppearanceConfig,
    /// Sensor rig variation: LiDAR height, camera height and pitch drawn per scene (off by default;
    /// left out of the serialised scene while it is at its default).
    #[serde(skip_serializing_if = "RigConfig::is_default")]
    pub rig: RigConfig,
    /// Number of frames and their spacing.
    pub frames: FramesConfig,
}

/// Road cross-section and lots; `None` takes the layout's default (see [`RoadParams`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct RoadConfig {
    /// Length of the main street, metres.
    pub length_m: Option<f32>,
    /// Lanes in each direction (1..=4).
    pub lanes_per_direction: Option<u32>,
    /// Lane width, metres.
    pub lane_width_m: Option<f32>,
    /// A parking strip (SemanticKITTI `parking`) along both kerbs.
    pub parking_lane: Option<bool>,
    /// Width of the parking strip, metres.
    pub parking_width_m: Option<f32>,
    /// Sidewalk width, metres.
    pub sidewalk_width_m: Option<f32>,
    /// Kerb height, metres.
    pub kerb_height_m: Option<f32>,
    /// Front-garden depth between sidewalk and facades, metres.
    pub setback_m: Option<f32>,
    /// Fraction of the street frontage covered by buildings, `[0, 1]`.
    pub building_frontage: Option<f32>,
    /// Lowest and highest building height, metres.
    pub building_height_m: Option<[f32; 2]>,
    /// Lane markings (dashed lane lines, edge lines, crosswalks).
    pub lane_markings: Option<bool>,
    /// Probability, within `[0, 1]`, that a roadside is open: drawn per scene for each side of the
    /// street, an open side has no building row behind its sidewalk but open ground (grass), trees
    /// in rows, clusters and alone at 1-60 m, bushes, field fences or hedges, maybe a guardrail
    /// and maybe a row of buildings set back far ([`RoadConfig::open_setback_m`]). Default 0 (1
    /// for the `open` layout). The junction layout ignores it (its arms keep their lots).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub open_side_probability: Option<f32>,
    /// On an open side: the range `[low, high]` of the distance, metres, from the sidewalk's outer
    /// edge to the facades of its far building row, drawn per side within `[5, 200]`. Default
    /// `[15, 60]`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub open_setback_m: Option<[f32; 2]>,
    /// On an open side: the probability, within `[0, 1]`, that it has a far building row at all
    /// (covering `building_frontage` of the frontage). Default 0.5 (0.3 for the `open` layout).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub open_building_probability: Option<f32>,
    /// On an open side: the probability, within `[0, 1]`, of a guardrail (a low metal barrier,
    /// labelled `fence` as in SemanticKITTI) in long runs along the road edge; never beside a
    /// parking strip. Default 0.2 (0.6 for the `open` layout).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub guardrail_probability: Option<f32>,
    /// A grade change of the main street: the range `[low, high]`, percent within `[-12, 12]`, of
    /// the grade drawn per scene (positive: the road climbs in +x). The street is flat up to a
    /// point drawn 30 m behind to 50 m ahead of the ego's start, then bends over a 40 m parabolic
    /// vertical curve into that grade; everything on it (the ego, pitching with the road, too)
    /// follows the road's height. Default `[0, 0]`: flat.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub grade_percent: Option<[f32; 2]>,
    /// Probability, within `[0, 1]`, that the main street bends, drawn per scene. A bent street
    /// runs straight up to a point drawn 20 m behind to 40 m ahead of the ego's start, turns left
    /// or right (even odds) along a circular arc of a radius drawn from
    /// [`RoadConfig::curve_radius_m`] through an angle drawn from [`RoadConfig::curve_angle_deg`],
    /// then runs straight again. Everything is laid out along it: the road surface, markings,
    /// kerbs, sidewalks and terrain bend with it, objects stand at their place along the road
    /// turned with it, and the ego and the traffic drive along their lanes. Composes with
    /// [`RoadConfig::grade_percent`] (the grade's distances are measured along the road). Default 0:
    /// straight. The junction layout ignores it (its streets stay straight).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub curve_probability: Option<f32>,
    /// The range `[low, high]` of the bend's radius, metres, drawn per scene log-uniformly; `low`
    /// at least 20 and more than the half carriageway plus the sidewalk plus 2 m, `high` at most
    /// 10000. Default `[40, 600]` (tight urban corners to rural bends).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub curve_radius_m: Option<[f32; 2]>,
    /// The range `[low, high]` of the angle the bent street turns through, degrees within
    /// `(0, 180]`, drawn per scene (a wide radius may turn less within the street's length).
    /// Default `[30, 120]`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub curve_angle_deg: Option<[f32; 2]>,
}

/// Road parameters with every default resolved for a layout.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoadParams {
    /// Length of the main street, metres.
    pub length_m: f32,
    /// Lanes in each direction.
    pub lanes_per_direction: u32,
    /// Lane width, metres.
    pub lane_width_m: f32,
    /// Parking strips along the kerbs.
    pub parking_lane: bool,
    /// Parking strip width, metres.
    pub parking_width_m: f32,
    /// Sidewalk width, metres.
    pub sidewalk_width_m: f32,
    /// Kerb height, metres.
    pub kerb_height_m: f32,
    /// Front-garden depth, metres.
    pub setback_m: f32,
    /// Building frontage fraction.
    pub building_frontage: f32,
    /// Building height range, metres.
    pub building_height_m: [f32; 2],
    /// Lane markings.
    pub lane_markings: bool,
    /// Probability that a roadside is open.
    pub open_side_probability: f32,
    /// Distance range of the far building row of an open side behind the sidewalk, metres.
    pub open_setback_m: [f32; 2],
    /// Probability that an open side has a far building row.
    pub open_building_probability: f32,
    /// Probability that an open side has a guardrail along the road edge.
    pub guardrail_probability: f32,
    /// Range of the main street's grade after its vertical curve, percent.
    pub grade_percent: [f32; 2],
    /// Probability that the main street bends.
    pub curve_probability: f32,
    /// Range of the bend's radius, metres.
    pub curve_radius_m: [f32; 2],
    /// Range of the angle the bend turns through, degrees.
    pub curve_angle_deg: [f32; 2],
}

impl RoadParams {
    /// Half width of the carriageway (kerb to kerb / 2), metres.
    pub fn half_carriageway_m(&self) -> f32 {
        self.lanes_per_direction as f32 * self.lane_width_m
            + if self.parking_lane {
                self.parking_width_m
            } else {
                0.0
            }
    }
}

impl RoadConfig {
    /// Resolve every default for `layout`.
    pub fn resolve(&self, layout: Layout) -> RoadParams {
        let narrow = layout == Layout::NarrowStreet;
        let open = layout == Layout::Open;
        RoadParams {
            length_m: self.length_m.unwrap_or(if narrow {
                160.0
            } else if open {
                300.0
            } else {
                240.0
            }),
            lanes_per_direction: self
                .lanes_per_direction
                .unwrap_or(if narrow { 1 } else { 2 }),
            lane_width_m: self.lane_width_m.unwrap_or(if narrow { 2.9 } else { 3.5 }),
            parking_lane: self.parking_lane.unwrap_or(!narrow && !open),
            parking_width_m: self.parking_width_m.unwrap_or(2.3),
            sidewalk_width_m: self.sidewalk_width_m.unwrap_or(if narrow {
                1.6
            } else if open {
                1.5
            } else {
                3.5
            }),
            kerb_height_m: self.kerb_height_m.unwrap_or(if open { 0.1 } else { 0.15 }),
            setback_m: self.setback_m.unwrap_or(if narrow { 0.0 } else { 3.0 }),
            building_frontage: self.building_frontage.unwrap_or(if narrow {
                0.95
            } else if open {
                0.5
            } else {
                0.7
            }),
            building_height_m: self.building_height_m.unwrap_or(if narrow {
                [9.0, 18.0]
            } else if open {
                [4.0, 12.0]
            } else {
                [6.0, 22.0]
            }),
            lane_markings: self.lane_markings.unwrap_or(!narrow),
            open_side_probability: self.open_side_probability.unwrap_or(if open {
                1.0
            } else {
                0.0
            }),
            open_setback_m: self.open_setback_m.unwrap_or([15.0, 60.0]),
            open_building_probability: self.open_building_probability.unwrap_or(if open {
                0.3
            } else {
                0.5
            }),
            guardrail_probability: self.guardrail_probability.unwrap_or(if open {
                0.6
            } else {
                0.2
            }),
            grade_percent: self.grade_percent.unwrap_or([0.0, 0.0]),
            curve_probability: self.curve_probability.unwrap_or(0.0),
            curve_radius_m: self.curve_radius_m.unwrap_or([40.0, 600.0]),
            curve_angle_deg: self.curve_angle_deg.unwrap_or([30.0, 120.0]),
        }
    }
}

/// Object counts and densities (per 100 m of street, both sides together, unless a count).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PopulationConfig {
    /// Parked vehicles per 100 m of street.
    pub parked_vehicles_per_100m: f32,
    /// Moving vehicles in the whole scene.
    pub moving_vehicles: u32,
    /// Fraction of vehicles that are vans (labelled car, as SemanticKITTI does).
    pub van_fraction: f32,
    /// Fraction of vehicles that are trucks.
    pub truck_fraction: f32,
    /// Fraction of vehicles that are buses.
    pub bus_fraction: f32,
    /// Fraction of parked vehicles that are trailers / caravans (other-vehicle).
    pub trailer_fraction: f32,
    /// Pedestrians in the whole scene.
    pub pedestrians: u32,
    /// Fraction of pedestrians standing still.
    pub standing_fraction: f32,
    /// Cyclists in the whole scene.
    pub cyclists: u32,
    /// Street trees per 100 m.
    pub trees_per_100m: f32,
    /// Street lights per 100 m.
    pub poles_per_100m: f32,
    /// Traffic signs per 100 m.
    pub signs_per_100m: f32,
    /// Bushes per 100 m (in front gardens and lot gaps).
    pub bushes_per_100m: f32,
    /// Probability that a gap between buildings is closed by a fence (else a hedge or open).
    pub fence_probability: f32,
    /// Probability, within `[0, 1]`, that an open roadside ([`RoadConfig::open_side_probability`])
    /// has tree lines: belts of dense woodland 4-14 m deep with crowns down to the undergrowth, in
    /// runs of 30-150 m, 2-50 m behind the sidewalk (and in front of a far building row). Heights
    /// in [`PopulationConfig::tree_line_height_m`]. Default 0 (drawn from its own random stream,
    /// so a scene without tree lines is the same as before they existed; left out of the written
    /// `scene.json` while 0, so that file is too).
    #[serde(skip_serializing_if = "is_zero")]
    pub tree_line_probability: f32,
    /// Height range `[low, high]` of a tree line's crowns, metres within `(1, 40]`. Default
    /// `[6, 20]` (left out of `scene.json` while the default).
    #[serde(skip_serializing_if = "is_default_tree_line_height")]
    pub tree_line_height_m: [f32; 2],
}

/// The default of [`PopulationConfig::tree_line_height_m`].
const DEFAULT_TREE_LINE_HEIGHT_M: [f32; 2] = [6.0, 20.0];

fn is_zero(x: &f32) -> bool {
    *x == 0.0
}

fn is_default_tree_line_height(h: &[f32; 2]) -> bool {
    *h == DEFAULT_TREE_LINE_HEIGHT_M
}

impl Default for PopulationConfig {
    fn default() -> Self {
        PopulationConfig {
            parked_vehicles_per_100m: 8.0,
            moving_vehicles: 6,
            van_fraction: 0.15,
            truck_fraction: 0.08,
            bus_fraction: 0.03,
            trailer_fraction: 0.04,
            pedestrians: 10,
            standing_fraction: 0.3,
            cyclists: 3,
            trees_per_100m: 8.0,
            poles_per_100m: 5.0,
            signs_per_100m: 3.0,
            bushes_per_100m: 10.0,
            fence_probability: 0.4,
            tree_line_probability: 0.0,
            tree_line_height_m: DEFAULT_TREE_LINE_HEIGHT_M,
        }
    }
}

/// The ego vehicle: it drives along the rightmost lane of the main street in +x.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EgoConfig {
    /// Speed, m/s.
    pub speed_mps: f32,
    /// Position along the main street at frame 0, metres (0 = street centre / junction centre; on
    /// a curved street, the distance along its centreline).
    pub start_x_m: f32,
    /// LiDAR height above the road, metres (KITTI: 1.73).
    pub lidar_height_m: f32,
    /// Draw the position at frame 0 per scene, uniformly within `[low, high]` metres, instead of
    /// `start_x_m` (default: none, `start_x_m`). On a [`Layout::TJunction`] this sets how far
    /// ahead the facades across the cross street stand.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_x_range_m: Option<[f32; 2]>,
}

impl Default for EgoConfig {
    fn default() -> Self {
        EgoConfig {
            speed_mps: 8.0,
            start_x_m: -25.0,
            lidar_height_m: 1.73,
            start_x_range_m: None,
        }
    }
}

/// The random stream of [`EgoConfig::start_x`] (its own, so drawing the start changes no other
/// draw of a scene).
const EGO_START_STREAM: u64 = 0x6567_0000;

impl EgoConfig {
    /// The ego's position along the main street at frame 0 for scene `seed`: `start_x_m`, or a
    /// draw within `start_x_range_m` (the same seed always gives the same start).
    pub fn start_x(&self, seed: u64) -> f32 {
        use rand::{Rng, SeedableRng};
        match self.start_x_range_m {
            Some([lo, hi]) if hi > lo => {
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
                rng.set_stream(EGO_START_STREAM);
                lo + (hi - lo) * rng.random::<f32>()
            }
            Some([lo, _]) => lo,
            None => self.start_x_m,
        }
    }
}

/// The LiDAR sensor and its return model.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LidarConfig {
    /// A sensor preset (one of [`SensorPreset::ALL`]; `hdl64e` by default). Ignored when `sensor`
    /// is given.
    pub preset: SensorPreset,
    /// A full sensor description (overrides `preset`).
    pub sensor: Option<LidarSensor>,
    /// Return model (intensity, ray drop).
    pub returns: LidarReturnModel,
}

impl LidarConfig {
    /// The sensor this configuration names, validated.
    pub fn sensor(&self) -> Result<LidarSensor> {
        let s = match &self.sensor {
            Some(s) => s.clone(),
            None => self.preset.sensor(),
        };
        s.validate()?;
        Ok(s)
    }
}

/// The LiDAR return model (see [`crate::sim::lidar`] for the equations).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LidarReturnModel {
    /// Detection threshold: the reflectivity a surface at normal incidence needs to be detected at
    /// 100 m. A return is weak (dropped) when `rho cos(theta) (100 m / R)^2` falls below it.
    pub min_reflectivity_at_100m: f32,
    /// Width of the soft drop zone around the threshold, in decades of received power (0 = hard cut).
    pub drop_softness_decades: f32,
    /// Returns with `cos(incidence)` below this are dropped (grazing).
    pub grazing_cos_min: f32,
    /// Probability of dropping any return at random (dust, multipath, sensor dead time).
    pub random_drop: f32,
    /// Range at which the reported intensity falls to half (see [`crate::sim::lidar`]).
    pub intensity_half_range_m: f32,
    /// Incidence knee `c0` of the intensity: `g(c) = (1 + c0^2) c^2 / (c^2 + c0^2)`, `c = cos(theta)`;
    /// near 1 down to `c ~ 2 c0`, falling like `c^2` at grazing incidence (0 = no incidence effect).
    pub incidence_knee: f32,
    /// Standard deviation of the range noise, metres (0 = exact ranges). The default, 1 cm, lies
    /// within the HDL-64E datasheet's "< 2 cm" accuracy. It gives the ground rings the texture of
    /// real KITTI scans (median relative step between neighbours along a beam: 0.12-0.16 % in four
    /// real scans, 0.21 % here at 64 x 1024), where exact ranges put 77 % of those pairs within
    /// 0.03 % of each other against 11-14 % in the real scans (BENCHMARKS.md, "The simulator's
    /// range noise").
    pub range_noise_m: f32,
}

impl Default for LidarReturnModel {
    fn default() -> Self {
        LidarReturnModel {
            min_reflectivity_at_100m: 0.02,
            drop_softness_decades: 0.3,
            grazing_cos_min: 0.02,
            random_drop: 0.005,
            intensity_half_range_m: 45.0,
            incidence_knee: 0.15,
            range_noise_m: 0.01,
        }
    }
}

impl LidarReturnModel {
    /// An ideal sensor: every hit within range returns, exact ranges (for tests and references).
    pub fn ideal() -> Self {
        LidarReturnModel {
            min_reflectivity_at_100m: 0.0,
            drop_softness_decades: 0.0,
            grazing_cos_min: 0.0,
            random_drop: 0.0,
            intensity_half_range_m: 45.0,
            incidence_knee: 0.15,
            range_noise_m: 0.0,
        }
    }

    /// Check ranges of every parameter.
    pub fn validate(&self) -> Result<()> {
        let bad = |field: &str, msg: &str| {
            Err(Error::Invalid {
                what: format!("lidar.returns.{field}"),
                message: msg.into(),
            })
        };
        let finite_nonneg = |x: f32| x.is_finite() && x >= 0.0;
        if !finite_nonneg(self.min_reflectivity_at_100m) {
            return bad("min_reflectivity_at_100m", "must be finite and >= 0");
        }
        if !finite_nonneg(self.drop_softness_decades) || self.drop_softness_decades > 5.0 {
            return bad("drop_softness_decades", "must be in [0, 5]");
        }
        if !(0.0..1.0).contains(&self.grazing_cos_min) {
            return bad("grazing_cos_min", "must be in [0, 1)");
        }
        if !(0.0..=1.0).contains(&self.random_drop) {
            return bad("random_drop", "must be in [0, 1]");
        }
        if !(self.intensity_half_range_m.is_finite() && self.intensity_half_range_m > 0.0) {
            return bad("intensity_half_range_m", "must be finite and > 0");
        }
        if !finite_nonneg(self.incidence_knee) || self.incidence_knee > 10.0 {
            return bad("incidence_knee", "must be in [0, 10]");
        }
        if !finite_nonneg(self.range_noise_m) || self.range_noise_m > 1.0 {
            return bad("range_noise_m", "must be in [0, 1] m");
        }
        Ok(())
    }
}

/// A pinhole camera, mounted KITTI-like: `image_2` sits `ahead_m` in front of the LiDAR, `up_m`
/// above it (negative: below) and `left_m` to its left, looking along the LiDAR's x axis.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length along x, pixels.
    pub fx: f32,
    /// Focal length along y, pixels.
    pub fy: f32,
    /// Principal point x, pixels.
    pub cx: f32,
    /// Principal point y, pixels.
    pub cy: f32,
    /// Camera 0 (the rectified reference camera) ahead of the LiDAR, metres.
    pub ahead_m: f32,
    /// Camera 0 above the LiDAR, metres.
    pub up_m: f32,
    /// Camera 2 (`image_2`, the rendered one) to the left of camera 0, metres (KITTI: 0.06).
    pub cam2_left_m: f32,
    /// Stereo baseline between camera 0 and camera 1 (and 2 and 3), metres (KITTI: 0.54).
    pub baseline_m: f32,
    /// Downward pitch of the camera, degrees.
    pub pitch_down_deg: f32,
    /// Samples per pixel along each axis (1 = one ray through the pixel centre; n = n x n grid).
    pub samples_per_axis: u32,
    /// Shadow rays toward the sun.
    pub shadows: bool,
}

impl Default for CameraConfig {
    fn default() -> Self {
        CameraConfig {
            width: 1242,
            height: 375,
            fx: 721.5377,
            fy: 721.5377,
            cx: 609.5593,
            cy: 172.854,
            ahead_m: 0.27,
            up_m: -0.08,
            cam2_left_m: 0.06,
            baseline_m: 0.54,
            pitch_down_deg: 0.0,
            samples_per_axis: 1,
            shadows: true,
        }
    }
}

/// Sun and sky (linear RGB radiometry, arbitrary units; 1.0 is white paper in full sun).
///
/// With [`AppearanceConfig::randomize`] the sun and sky are drawn per scene instead, and these
/// values are the clear-sky reference of the draw: the sun's and the ambient's luminance, the sky
/// colours and the exposure (which is always this one).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LightingConfig {
    /// Sun azimuth, degrees counter-clockwise from the world +x axis (the main street).
    pub sun_azimuth_deg: f32,
    /// Sun elevation above the horizon, degrees.
    pub sun_elevation_deg: f32,
    /// Direct sun irradiance on a surface facing the sun (linear RGB).
    pub sun_rgb: [f32; 3],
    /// Ambient sky irradiance on an upward-facing surface (linear RGB).
    pub sky_ambient_rgb: [f32; 3],
    /// Sky radiance at the zenith (linear RGB), for rays that miss.
    pub sky_zenith_rgb: [f32; 3],
    /// Sky radiance at the horizon (linear RGB).
    pub sky_horizon_rgb: [f32; 3],
    /// Exposure multiplier before the sRGB transfer curve.
    pub exposure: f32,
}

impl Default for LightingConfig {
    fn default() -> Self {
        LightingConfig {
            sun_azimuth_deg: 130.0,
            sun_elevation_deg: 40.0,
            sun_rgb: [1.0, 0.95, 0.85],
            sky_ambient_rgb: [0.3, 0.34, 0.42],
            sky_zenith_rgb: [0.22, 0.38, 0.75],
            sky_horizon_rgb: [0.72, 0.8, 0.9],
            exposure: 1.6,
        }
    }
}

/// Appearance randomisation of the camera image (TOML section `[appearance]`).
///
/// With `randomize = true` every scene draws, from its seed, a sun (elevation, azimuth, colour
/// temperature), a sky between clear blue and overcast grey, class palettes (asphalt grey, paving,
/// facades, grass, foliage, fences, car paints by their share of real fleets), texture styles
/// (paving slabs or pavers, brick, panels or plaster walls) and per-surface colour jitter, and the
/// camera shades every hit with a procedural texture of its class evaluated at the world point (see
/// [`crate::sim::camera`]). The draws are per scene, not per frame: nothing moves the sun or
/// repaints a wall within a sequence. LiDAR scans, depth, semantics and instances never change.
///
/// The two halves can be drawn alone (the same draws as `randomize` makes for that seed):
/// `randomize_lighting = true` draws the sun and sky and shades the flat stock materials under
/// them; `randomize_materials = true` draws the palettes and textures and shades them under the
/// configured [`LightingConfig`].
///
/// With both `false` (the default) the ranges are ignored (but still validated) and images are
/// exactly those of the flat stock materials under [`LightingConfig`].
///
/// `wide_facade_share` widens the facade palettes where they are drawn: that share of a scene's
/// facade looks takes any hue and up to strong saturation (painted, clad or glazed-tile walls, a
/// blue mosaic among them), which the plaster, brick and cladding palettes never do.
///
/// ```toml
/// [appearance]
/// randomize = true
/// sun_elevation_deg = [8.0, 70.0]
/// overcast = [0.0, 0.6]
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AppearanceConfig {
    /// Draw textures, colours, sun and sky per scene.
    pub randomize: bool,
    /// Draw only the sun and sky per scene (the sun and overcast ranges below) and keep the stock
    /// materials flat: the lighting half of `randomize`, which draws both.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub randomize_lighting: bool,
    /// Draw only the palettes and textures per scene and keep the configured sun and sky: the
    /// material half of `randomize`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub randomize_materials: bool,
    /// Sun elevation range `[low, high]`, degrees above the horizon, within `[0, 90]`.
    pub sun_elevation_deg: [f32; 2],
    /// Sun azimuth range `[low, high]`, degrees counter-clockwise from the world +x axis (the main
    /// street), within `[-360, 720]` and at most 360 wide.
    pub sun_azimuth_deg: [f32; 2],
    /// Correlated colour temperature of direct sunlight, `[low, high]` kelvin within
    /// `[2000, 12000]` (6500 K renders white); a low sun is capped at 2000 K + 300 K per degree of
    /// elevation.
    pub sun_temperature_k: [f32; 2],
    /// Cloud cover range `[low, high]` within `[0, 1]`: 0 a clear blue sky, 1 an overcast grey one
    /// (the sun's irradiance falls to 15 % and the sky ambient rises).
    pub overcast: [f32; 2],
    /// Asphalt albedo range `[low, high]` (linear grey level, one per scene) within `[0, 1]`.
    pub road_albedo: [f32; 2],
    /// Relative brightness jitter per surface and instance: the HSV value scales by a factor in
    /// `[1 - j, 1 + j]`; `j` within `[0, 1]`.
    pub brightness_jitter: f32,
    /// Hue jitter per surface and instance, degrees (half width), within `[0, 180]`.
    pub hue_jitter_deg: f32,
    /// Relative saturation jitter per surface and instance (half width), within `[0, 1]`.
    pub saturation_jitter: f32,
    /// Contrast of the procedural textures within `[0, 2]`: 0 flat (palettes and jitter only), 1
    /// as designed.
    pub texture_contrast: f32,
    /// Share of a scene's facade looks, within `[0, 1]`, drawn from the whole colour wheel (any
    /// hue, up to strongly saturated: glazed tile, painted or clad walls, half of them as mosaic
    /// tiles) instead of the plaster, brick and cladding palettes. It applies where the palettes
    /// are drawn (`randomize` or `randomize_materials`); 0 (the default) draws the stock palettes
    /// exactly as before.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub wide_facade_share: f32,
}

impl Default for AppearanceConfig {
    fn default() -> Self {
        AppearanceConfig {
            randomize: false,
            randomize_lighting: false,
            randomize_materials: false,
            sun_elevation_deg: [8.0, 70.0],
            sun_azimuth_deg: [0.0, 360.0],
            sun_temperature_k: [4000.0, 6500.0],
            overcast: [0.0, 0.8],
            road_albedo: [0.04, 0.2],
            brightness_jitter: 0.15,
            hue_jitter_deg: 8.0,
            saturation_jitter: 0.2,
            texture_contrast: 1.0,
            wide_facade_share: 0.0,
        }
    }
}

impl AppearanceConfig {
    fn is_default(&self) -> bool {
        *self == Self::default()
    }

    /// Whether scenes draw their sun and sky (`randomize` or its lighting half).
    pub(crate) fn draws_lighting(&self) -> bool {
        self.randomize || self.randomize_lighting
    }

    /// Whether scenes draw their palettes and textures (`randomize` or its material half).
    pub(crate) fn draws_materials(&self) -> bool {
        self.randomize || self.randomize_materials
    }

    /// Check every range (finite, `low <= high`, within its bounds); the error names the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, message: String| {
            Err(Error::Invalid {
                what: format!("appearance.{key}"),
                message,
            })
        };
        for (key, [lo, hi], min, max) in [
            ("sun_elevation_deg", self.sun_elevation_deg, 0.0, 90.0),
            ("sun_azimuth_deg", self.sun_azimuth_deg, -360.0, 720.0),
            ("sun_temperature_k", self.sun_temperature_k, 2000.0, 12000.0),
            ("overcast", self.overcast, 0.0, 1.0),
            ("road_albedo", self.road_albedo, 0.0, 1.0),
        ] {
            if !(lo.is_finite() && hi.is_finite() && min <= lo && lo <= hi && hi <= max) {
                return bad(
                    key,
                    format!("[{lo}, {hi}] must satisfy {min} <= low <= high <= {max}"),
                );
            }
        }
        let [lo, hi] = self.sun_azimuth_deg;
        if hi - lo > 360.0 {
            return bad(
                "sun_azimuth_deg",
                format!("[{lo}, {hi}] is wider than 360 degrees"),
            );
        }
        for (key, v, max) in [
            ("brightness_jitter", self.brightness_jitter, 1.0),
            ("hue_jitter_deg", self.hue_jitter_deg, 180.0),
            ("saturation_jitter", self.saturation_jitter, 1.0),
            ("texture_contrast", self.texture_contrast, 2.0),
            ("wide_facade_share", self.wide_facade_share, 1.0),
        ] {
            if !(v.is_finite() && (0.0..=max).contains(&v)) {
                return bad(key, format!("{v} not in [0, {max}]"));
            }
        }
        Ok(())
    }
}

/// Sensor rig variation (TOML section `[rig]`).
///
/// With `randomize = true` every scene draws, from its seed, the LiDAR's height above the road
/// (replacing [`EgoConfig::lidar_height_m`]), camera 0's height relative to the LiDAR (replacing
/// [`CameraConfig::up_m`]) and a change of the camera's pitch (added to
/// [`CameraConfig::pitch_down_deg`]), each uniform in its range; [`Scene::camera_config`] and
/// [`Scene::lidar_height_m`] give the drawn values, and the frames' camera and KITTI calibration
/// follow them. With `randomize = false` (the default) the ranges are ignored (but validated).
///
/// [`Scene::camera_config`]: super::Scene::camera_config
/// [`Scene::lidar_height_m`]: super::Scene::lidar_height_m
///
/// ```toml
/// [rig]
/// randomize = true
/// lidar_height_m = [1.6, 2.0]   # KITTI 1.73, nuScenes 1.84
/// camera_up_m = [-0.35, 0.0]    # KITTI -0.08, nuScenes about -0.33
/// pitch_offset_deg = [-2.0, 2.0]
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RigConfig {
    /// Draw the rig per scene.
    pub randomize: bool,
    /// LiDAR height above the road, `[low, high]` metres within `(0, 10]`.
    pub lidar_height_m: [f32; 2],
    /// Camera 0 above the LiDAR (negative: below), `[low, high]` metres within `[-2, 2]`.
    pub camera_up_m: [f32; 2],
    /// Change of the camera's downward pitch, `[low, high]` degrees within `[-10, 10]`.
    pub pitch_offset_deg: [f32; 2],
}

impl Default for RigConfig {
    fn default() -> Self {
        RigConfig {
            randomize: false,
            lidar_height_m: [1.6, 2.0],
            camera_up_m: [-0.35, 0.0],
            pitch_offset_deg: [-2.0, 2.0],
        }
    }
}

impl RigConfig {
    fn is_default(&self) -> bool {
        *self == Self::default()
    }

    /// Check every range (finite, `low <= high`, within its bounds); the error names the key.
    pub fn validate(&self) -> Result<()> {
        for (key, [lo, hi], min, max) in [
            ("lidar_height_m", self.lidar_height_m, 0.0, 10.0),
            ("camera_up_m", self.camera_up_m, -2.0, 2.0),
            ("pitch_offset_deg", self.pitch_offset_deg, -10.0, 10.0),
        ] {
            let in_bounds = if key == "lidar_height_m" {
                min < lo
            } else {
                min <= lo
            };
            if !(lo.is_finite() && hi.is_finite() && in_bounds && lo <= hi && hi <= max) {
                return Err(Error::Invalid {
                    what: format!("rig.{key}"),
                    message: format!("[{lo}, {hi}] must satisfy {min} <= low <= high <= {max}"),
                });
            }
        }
        Ok(())
    }

    /// The rig of scene `seed`: the LiDAR height above the road and the camera configuration (with
    /// `up_m` and `pitch_down_deg` drawn). Without `randomize`, `lidar_height_m` and `camera`
    /// unchanged.
    pub(crate) fn draw(
        &self,
        seed: u64,
        lidar_height_m: f32,
        camera: &CameraConfig,
    ) -> (f32, CameraConfig) {
        if !self.randomize {
            return (lidar_height_m, *camera);
        }
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(RIG_STREAM);
        let mut draw = |[lo, hi]: [f32; 2]| lo + (hi - lo) * rng.random::<f32>();
        let height = draw(self.lidar_height_m);
        let up = draw(self.camera_up_m);
        let pitch = draw(self.pitch_offset_deg);
        let camera = CameraConfig {
            up_m: up,
            pitch_down_deg: camera.pitch_down_deg + pitch,
            ..*camera
        };
        (height, camera)
    }
}

/// The random stream of the rig draw (apart from the scene generator's streams).
const RIG_STREAM: u64 = 0x7269_6700;

/// Number of frames and their spacing.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FramesConfig {
    /// Frames to render (the CLI's `--frames` overrides it).
    pub count: u32,
    /// Time between frames, seconds (KITTI: 0.1).
    pub interval_s: f32,
}

impl Default for FramesConfig {
    fn default() -> Self {
        FramesConfig {
            count: 1,
            interval_s: 0.1,
        }
    }
}

impl SceneConfig {
    /// Parse a scene from TOML text (`origin` names the source in errors).
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self> {
        let cfg: SceneConfig = toml::from_str(text)
            .map_err(|e| Error::format(origin, format!("not a valid scene file: {e}")))?;
        cfg.validate()
            .map_err(|e| Error::format(origin, e.to_string()))?;
        Ok(cfg)
    }

    /// Read and validate a scene file.
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = crate::read_capped::read_metadata_string(
            path,
            crate::read_capped::MAX_CONFIG_BYTES,
            "a scene file",
        )?;
        Self::from_toml_str(&text, path)
    }

    /// Resolved road parameters.
    pub fn road_params(&self) -> RoadParams {
        self.road.resolve(self.layout)
    }

    /// Check every value (ranges, finiteness, the LiDAR sensor).
    pub fn validate(&self) -> Result<()> {
        fn check(ok: bool, what: &str, message: String) -> Result<()> {
            if ok {
                Ok(())
            } else {
                Err(Error::Invalid {
                    what: what.into(),
                    message,
                })
            }
        }
        let r = self.road_params();
        let pos = |x: f32| x.is_finite() && x > 0.0;
        let nonneg = |x: f32| x.is_finite() && x >= 0.0;
        check(
            pos(r.length_m) && r.length_m <= 5000.0,
            "road.length_m",
            format!("{} not in (0, 5000]", r.length_m),
        )?;
        check(
            (1..=4).contains(&r.lanes_per_direction),
            "road.lanes_per_direction",
            format!("{} not in 1..=4", r.lanes_per_direction),
        )?;
        check(
            pos(r.lane_width_m) && r.lane_width_m <= 6.0,
            "road.lane_width_m",
            format!("{} not in (0, 6]", r.lane_width_m),
        )?;
        check(
            pos(r.parking_width_m) && r.parking_width_m <= 6.0,
            "road.parking_width_m",
            format!("{} not in (0, 6]", r.parking_width_m),
        )?;
        check(
            pos(r.sidewalk_width_m) && r.sidewalk_width_m <= 15.0,
            "road.sidewalk_width_m",
            format!("{} not in (0, 15]", r.sidewalk_width_m),
        )?;
        check(
            nonneg(r.kerb_height_m) && r.kerb_height_m <= 0.5,
            "road.kerb_height_m",
            format!("{} not in [0, 0.5]", r.kerb_height_m),
        )?;
        check(
            nonneg(r.setback_m) && r.setback_m <= 50.0,
            "road.setback_m",
            format!("{} not in [0, 50]", r.setback_m),
        )?;
        check(
            (0.0..=1.0).contains(&r.building_frontage),
            "road.building_frontage",
            format!("{} not in [0, 1]", r.building_frontage),
        )?;
        check(
            (0.0..=1.0).contains(&r.open_side_probability),
            "road.open_side_probability",
            format!("{} not in [0, 1]", r.open_side_probability),
        )?;
        let [o0, o1] = r.open_setback_m;
        check(
            o0.is_finite() && o1.is_finite() && (5.0..=o1).contains(&o0) && o1 <= 200.0,
            "road.open_setback_m",
            format!("[{o0}, {o1}] must satisfy 5 <= low <= high <= 200"),
        )?;
        for (name, v) in [
            ("open_building_probability", r.open_building_probability),
            ("guardrail_probability", r.guardrail_probability),
        ] {
            check(
                (0.0..=1.0).contains(&v),
                &format!("road.{name}"),
                format!("{v} not in [0, 1]"),
            )?;
        }
        let [g0, g1] = r.grade_percent;
        check(
            g0.is_finite() && g1.is_finite() && (-12.0..=g1).contains(&g0) && g1 <= 12.0,
            "road.grade_percent",
            format!("[{g0}, {g1}] must satisfy -12 <= low <= high <= 12"),
        )?;
        check(
            (0.0..=1.0).contains(&r.curve_probability),
            "road.curve_probability",
            format!("{} not in [0, 1]", r.curve_probability),
        )?;
        let [c0, c1] = r.curve_radius_m;
        let c_min = (r.half_carriageway_m() + r.sidewalk_width_m + 2.0).max(20.0);
        check(
            c0.is_finite() && c1.is_finite() && c0 >= c_min && c0 <= c1 && c1 <= 10_000.0,
            "road.curve_radius_m",
            format!(
                "[{c0}, {c1}] must satisfy {c_min} <= low <= high <= 10000 (the carriageway and \
                 sidewalk must fit inside the bend)"
            ),
        )?;
        let [a0, a1] = r.curve_angle_deg;
        check(
            a0.is_finite() && a1.is_finite() && a0 > 0.0 && a0 <= a1 && a1 <= 180.0,
            "road.curve_angle_deg",
            format!("[{a0}, {a1}] must satisfy 0 < low <= high <= 180"),
        )?;
        let min_len = match self.layout {
            // the junction's arms need room beyond the crossing street's sidewalks
            Layout::Junction | Layout::TJunction => {
                2.0 * (r.half_carriageway_m() + r.sidewalk_width_m + r.setback_m + 10.0)
            }
            _ => 20.0,
        };
        check(
            r.length_m >= min_len,
            "road.length_m",
            format!(
                "{} is too short for this layout and cross-section (at least {min_len} m)",
                r.length_m
            ),
        )?;
        let [h0, h1] = r.building_height_m;
        check(
            pos(h0) && h1 >= h0 && h1 <= 300.0,
            "road.building_height_m",
            format!("[{h0}, {h1}] must satisfy 0 < low <= high <= 300"),
        )?;
        let p = &self.population;
        check(
            nonneg(p.parked_vehicles_per_100m) && p.parked_vehicles_per_100m <= 50.0,
            "population.parked_vehicles_per_100m",
            "must be in [0, 50]".into(),
        )?;
        for (name, v) in [
            ("trees_per_100m", p.trees_per_100m),
            ("poles_per_100m", p.poles_per_100m),
            ("signs_per_100m", p.signs_per_100m),
            ("bushes_per_100m", p.bushes_per_100m),
        ] {
            check(
                nonneg(v) && v <= 100.0,
                &format!("population.{name}"),
                format!("{v} not in [0, 100]"),
            )?;
        }
        for (name, v) in [
            ("van_fraction", p.van_fraction),
            ("truck_fraction", p.truck_fraction),
            ("bus_fraction", p.bus_fraction),
            ("trailer_fraction", p.trailer_fraction),
            ("standing_fraction", p.standing_fraction),
            ("fence_probability", p.fence_probability),
            ("tree_line_probability", p.tree_line_probability),
        ] {
            check(
                (0.0..=1.0).contains(&v),
                &format!("population.{name}"),
                format!("{v} not in [0, 1]"),
            )?;
        }
        let [t0, t1] = p.tree_line_height_m;
        check(
            t0 > 1.0 && t0 <= t1 && t1 <= 40.0,
            "population.tree_line_height_m",
            format!("[{t0}, {t1}] is not an interval within (1, 40]"),
        )?;
        check(
            p.van_fraction + p.truck_fraction + p.bus_fraction <= 1.0,
            "population",
            "van_fraction + truck_fraction + bus_fraction must not exceed 1".into(),
        )?;
        for (name, v) in [
            ("moving_vehicles", p.moving_vehicles),
            ("pedestrians", p.pedestrians),
            ("cyclists", p.cyclists),
        ] {
            check(
                v <= 500,
                &format!("population.{name}"),
                format!("{v} is more than 500"),
            )?;
        }
        let e = &self.ego;
        check(
            nonneg(e.speed_mps) && e.speed_mps <= 60.0,
            "ego.speed_mps",
            format!("{} not in [0, 60]", e.speed_mps),
        )?;
        check(
            e.start_x_m.is_finite() && e.start_x_m.abs() <= r.length_m / 2.0,
            "ego.start_x_m",
            format!(
                "{} is off the street (|x| <= {})",
                e.start_x_m,
                r.length_m / 2.0
            ),
        )?;
        if let Some([lo, hi]) = e.start_x_range_m {
            check(
                lo.is_finite()
                    && hi.is_finite()
                    && lo <= hi
                    && lo.abs() <= r.length_m / 2.0
                    && hi.abs() <= r.length_m / 2.0,
                "ego.start_x_range_m",
                format!(
                    "[{lo}, {hi}] must be low <= high, both on the street (|x| <= {})",
                    r.length_m / 2.0
                ),
            )?;
        }
        check(
            pos(e.lidar_height_m) && e.lidar_height_m <= 10.0,
            "ego.lidar_height_m",
            format!("{} not in (0, 10]", e.lidar_height_m),
        )?;
        self.lidar.sensor()?;
        self.lidar.returns.validate()?;
        let c = &self.camera;
        check(
            (1..=8192).contains(&c.width) && (1..=8192).contains(&c.height),
            "camera",
            format!("size {}x{} not in 1..=8192", c.width, c.height),
        )?;
        check(
            pos(c.fx) && pos(c.fy) && c.cx.is_finite() && c.cy.is_finite(),
            "camera",
            "focal lengths must be positive and the principal point finite".into(),
        )?;
        check(
            [c.ahead_m, c.up_m, c.cam2_left_m, c.baseline_m]
                .iter()
                .all(|x| x.is_finite() && x.abs() <= 5.0),
            "camera",
            "mounting offsets must be finite and within 5 m".into(),
        )?;
        check(
            c.pitch_down_deg.is_finite() && c.pitch_down_deg.abs() <= 45.0,
            "camera.pitch_down_deg",
            "must be within [-45, 45]".into(),
        )?;
        self.rig.validate()?;
        if self.rig.randomize {
            let [p0, p1] = self.rig.pitch_offset_deg;
            check(
                (c.pitch_down_deg + p0).abs() <= 45.0 && (c.pitch_down_deg + p1).abs() <= 45.0,
                "rig.pitch_offset_deg",
                "camera.pitch_down_deg plus the offsets must stay within [-45, 45]".into(),
            )?;
        }
        check(
            (1..=8).contains(&c.samples_per_axis),
            "camera.samples_per_axis",
            format!("{} not in 1..=8", c.samples_per_axis),
        )?;
        let l = &self.lighting;
        check(
            l.sun_azimuth_deg.is_finite() && (-90.0..=90.0).contains(&l.sun_elevation_deg),
            "lighting",
            "sun elevation must be within [-90, 90] degrees".into(),
        )?;
        check(
            [
                l.sun_rgb,
                l.sky_ambient_rgb,
                l.sky_zenith_rgb,
                l.sky_horizon_rgb,
            ]
            .iter()
            .flatten()
            .all(|x| nonneg(*x) && *x <= 100.0)
                && pos(l.exposure),
            "lighting",
            "colours must be in [0, 100] and exposure positive".into(),
        )?;
        self.appearance.validate()?;
        check(
            self.frames.count <= MAX_FRAMES,
            "frames.count",
            format!("{} is more than {MAX_FRAMES}", self.frames.count),
        )?;
        check(
            pos(self.frames.interval_s) && self.frames.interval_s <= 10.0,
            "frames.interval_s",
            format!("{} not in (0, 10]", self.frames.interval_s),
        )?;
        Ok(())
    }
}
