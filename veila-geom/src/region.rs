//! The paper's front / rear split of the panorama.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// A region of the panorama: everything, the front half (`x > 0`, where the front camera looks) or
/// the rear half (`x <= 0`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Region {
    /// The whole panorama.
    All,
    /// Points with `x > 0` (LiDAR frame).
    Front,
    /// Points with `x <= 0`.
    Rear,
}

impl Region {
    /// All three regions, in report order.
    pub const ALL: [Region; 3] = [Region::All, Region::Front, Region::Rear];

    /// Whether the point lies in this region. NaN coordinates are in neither half.
    #[inline]
    pub fn contains(&self, p_lidar: Vec3) -> bool {
        match self {
            Region::All => true,
            Region::Front => p_lidar.x > 0.0,
            Region::Rear => p_lidar.x <= 0.0,
        }
    }

    /// Lower-case name (`all`, `front`, `rear`).
    pub fn name(&self) -> &'static str {
        match self {
            Region::All => "all",
            Region::Front => "front",
            Region::Rear => "rear",
        }
    }
}

impl std::fmt::Display for Region {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}
