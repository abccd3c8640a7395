//! Surface materials of the simulator, each labelled with a SemanticKITTI class.
//!
//! Every triangle of a scene carries a [`Material`]: an RGB albedo for the camera, a LiDAR
//! reflectivity at 905 nm for the LiDAR, and the SemanticKITTI raw class id its surface belongs to
//! (ids as in `semantic-kitti.yaml`, moving objects with the `moving-*` ids 252..259).

use serde::{Deserialize, Serialize};

/// How a surface looks to the camera and to the LiDAR, and what it is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Material {
    /// Diffuse albedo in linear RGB, each in `[0, 1]`.
    pub albedo: [f32; 3],
    /// Reflectivity at the LiDAR wavelength, in `[0, 1]`, on the scale of KITTI's calibrated
    /// reflectance: the stock values are set so that near-range returns match the per-class mean
    /// intensities of real SemanticKITTI scans (road ~0.22, sidewalk ~0.30, building ~0.45).
    pub reflectivity: f32,
    /// SemanticKITTI raw class id (see [`crate::semantic_kitti::class`]).
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
    use super::Material;
    use crate::semantic_kitti::class;

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
