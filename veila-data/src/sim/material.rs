//! Surface materials and SemanticKITTI classes of the simulator.
//!
//! Every triangle of a scene carries a [`Material`]: an RGB albedo for the camera, a LiDAR
//! reflectivity at 905 nm for the LiDAR, and the SemanticKITTI raw class id its surface belongs to
//! (ids as in `semantic-kitti.yaml`, moving objects with the `moving-*` ids 252..259).

use serde::{Deserialize, Serialize};

/// SemanticKITTI raw class ids (the `labels:` table of `semantic-kitti.yaml`).
pub mod class {
    /// Unlabelled (sky and no-return pixels in the semantic maps).
    pub const UNLABELED: u16 = 0;
    /// Car (also vans with a continuous body, following the SemanticKITTI definition).
    pub const CAR: u16 = 10;
    /// Bicycle without a rider.
    pub const BICYCLE: u16 = 11;
    /// Bus.
    pub const BUS: u16 = 13;
    /// Truck (cabin separate from the cargo body).
    pub const TRUCK: u16 = 18;
    /// Other vehicle (trailers, caravans).
    pub const OTHER_VEHICLE: u16 = 20;
    /// Person.
    pub const PERSON: u16 = 30;
    /// Bicyclist (the rider together with the bicycle).
    pub const BICYCLIST: u16 = 31;
    /// Road.
    pub const ROAD: u16 = 40;
    /// Parking area.
    pub const PARKING: u16 = 44;
    /// Sidewalk (kerb included).
    pub const SIDEWALK: u16 = 48;
    /// Building.
    pub const BUILDING: u16 = 50;
    /// Fence (also guardrails and other low barriers).
    pub const FENCE: u16 = 51;
    /// Lane marking.
    pub const LANE_MARKING: u16 = 60;
    /// Vegetation (tree crowns, bushes, hedges).
    pub const VEGETATION: u16 = 70;
    /// Tree trunk.
    pub const TRUNK: u16 = 71;
    /// Terrain (grass, soil).
    pub const TERRAIN: u16 = 72;
    /// Pole.
    pub const POLE: u16 = 80;
    /// Traffic sign (the plate; its post is a pole).
    pub const TRAFFIC_SIGN: u16 = 81;
    /// Moving car.
    pub const MOVING_CAR: u16 = 252;
    /// Moving bicyclist.
    pub const MOVING_BICYCLIST: u16 = 253;
    /// Moving person.
    pub const MOVING_PERSON: u16 = 254;
    /// Moving bus.
    pub const MOVING_BUS: u16 = 257;
    /// Moving truck.
    pub const MOVING_TRUCK: u16 = 258;
    /// Moving other vehicle.
    pub const MOVING_OTHER_VEHICLE: u16 = 259;

    /// The `moving-*` id of a movable class, or the class itself when SemanticKITTI has none.
    pub fn moving(class: u16) -> u16 {
        match class {
            CAR => MOVING_CAR,
            BICYCLIST => MOVING_BICYCLIST,
            PERSON => MOVING_PERSON,
            BUS => MOVING_BUS,
            TRUCK => MOVING_TRUCK,
            OTHER_VEHICLE => MOVING_OTHER_VEHICLE,
            c => c,
        }
    }

    /// Number of classes of SemanticKITTI's learning map (0 = unlabelled / ignored, 1..=19 the
    /// evaluated classes).
    pub const NUM_LEARNING_CLASSES: usize = 20;

    /// SemanticKITTI's `learning_map` (raw id -> train id in `0..20`, `semantic-kitti.yaml`): moving
    /// classes fold into their static class, lane marking into road, bus into other-vehicle, ids
    /// without a train class (outliers, other-structure, other-object, unknown ids) into 0.
    pub fn learning_id(raw: u16) -> u8 {
        match raw {
            10 | 252 => 1,
            11 => 2,
            15 => 3,
            18 | 258 => 4,
            13 | 16 | 20 | 256 | 257 | 259 => 5,
            30 | 254 => 6,
            31 | 253 => 7,
            32 | 255 => 8,
            40 | 60 => 9,
            44 => 10,
            48 => 11,
            49 => 12,
            50 => 13,
            51 => 14,
            70 => 15,
            71 => 16,
            72 => 17,
            80 => 18,
            81 => 19,
            _ => 0,
        }
    }

    /// The class name used in `semantic-kitti.yaml`, or `None` for ids the simulator never emits.
    pub fn name(class: u16) -> Option<&'static str> {
        Some(match class {
            UNLABELED => "unlabeled",
            CAR => "car",
            BICYCLE => "bicycle",
            BUS => "bus",
            TRUCK => "truck",
            OTHER_VEHICLE => "other-vehicle",
            PERSON => "person",
            BICYCLIST => "bicyclist",
            ROAD => "road",
            PARKING => "parking",
            SIDEWALK => "sidewalk",
            BUILDING => "building",
            FENCE => "fence",
            LANE_MARKING => "lane-marking",
            VEGETATION => "vegetation",
            TRUNK => "trunk",
            TERRAIN => "terrain",
            POLE => "pole",
            TRAFFIC_SIGN => "traffic-sign",
            MOVING_CAR => "moving-car",
            MOVING_BICYCLIST => "moving-bicyclist",
            MOVING_PERSON => "moving-person",
            MOVING_BUS => "moving-bus",
            MOVING_TRUCK => "moving-truck",
            MOVING_OTHER_VEHICLE => "moving-other-vehicle",
            _ => return None,
        })
    }
}

/// How a surface looks to the camera and to the LiDAR, and what it is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Material {
    /// Diffuse albedo in linear RGB, each in `[0, 1]`.
    pub albedo: [f32; 3],
    /// Reflectivity at the LiDAR wavelength, in `[0, 1]`, on the scale of KITTI's calibrated
    /// reflectance: the stock values are set so that near-range returns match the per-class mean
    /// intensities of real SemanticKITTI scans (road ~0.22, sidewalk ~0.30, building ~0.45).
    pub reflectivity: f32,
    /// SemanticKITTI raw class id (see [`class`]).
    pub class: u16,
    /// Procedural albedo grain in `[0, 1]` (asphalt, grass); 0 for a flat colour.
    pub grain: f32,
}

impl Material {
    /// A material with no grain.
    pub const fn new(albedo: [f32; 3], reflectivity: f32, class: u16) -> Self {
        Material {
            albedo,
            reflectivity,
            class,
            grain: 0.0,
        }
    }

    /// The same material with procedural grain.
    pub const fn with_grain(mut self, grain: f32) -> Self {
        self.grain = grain;
        self
    }

    /// The same material relabelled (e.g. as a `moving-*` class).
    pub const fn with_class(mut self, class: u16) -> Self {
        self.class = class;
        self
    }
}

/// The simulator's stock materials (linear albedo; reflectivities are typical 905 nm values).
pub mod stock {
    use super::{Material, class};

    /// Asphalt.
    pub const ROAD: Material = Material::new([0.09, 0.09, 0.1], 0.31, class::ROAD).with_grain(0.35);
    /// Parking strip (slightly different asphalt).
    pub const PARKING: Material =
        Material::new([0.12, 0.12, 0.12], 0.42, class::PARKING).with_grain(0.35);
    /// White lane paint (with glass beads: high LiDAR return).
    pub const LANE_MARKING: Material = Material::new([0.75, 0.75, 0.72], 0.65, class::LANE_MARKING);
    /// Concrete paving of sidewalks and kerbs.
    pub const SIDEWALK: Material =
        Material::new([0.32, 0.31, 0.3], 0.42, class::SIDEWALK).with_grain(0.2);
    /// Grass / soil.
    pub const TERRAIN: Material =
        Material::new([0.16, 0.22, 0.08], 0.6, class::TERRAIN).with_grain(0.5);
    /// Leaves (high near-infrared reflectance).
    pub const VEGETATION: Material =
        Material::new([0.06, 0.16, 0.04], 0.6, class::VEGETATION).with_grain(0.4);
    /// Bark.
    pub const TRUNK: Material = Material::new([0.14, 0.1, 0.07], 0.45, class::TRUNK);
    /// Metal pole (galvanised).
    pub const POLE: Material = Material::new([0.35, 0.36, 0.37], 0.22, class::POLE);
    /// Retro-reflective sign face.
    pub const SIGN: Material = Material::new([0.8, 0.8, 0.82], 0.95, class::TRAFFIC_SIGN);
    /// Wooden / metal fence.
    pub const FENCE: Material = Material::new([0.3, 0.24, 0.17], 0.3, class::FENCE);
    /// Galvanised steel of guardrails (SemanticKITTI labels guardrails `fence`).
    pub const GUARDRAIL: Material = Material::new([0.42, 0.43, 0.44], 0.55, class::FENCE);
    /// Tyres.
    pub const TYRE: Material = Material::new([0.03, 0.03, 0.03], 0.05, class::CAR);
    /// Vehicle glass (dark; LiDAR sees little of it).
    pub const GLASS: Material = Material::new([0.05, 0.06, 0.07], 0.06, class::CAR);
    /// Clothing.
    pub const CLOTH: Material = Material::new([0.2, 0.2, 0.25], 0.3, class::PERSON);
    /// Skin.
    pub const SKIN: Material = Material::new([0.55, 0.4, 0.3], 0.4, class::PERSON);
}
