//! Named metric results, as reported by `veila eval`.

use serde::{Deserialize, Serialize};
use veila_geom::Region;

/// The protocol a metric value follows (its definition and constants).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Protocol {
    /// R2DM (also LiDARGen for JSD, Text2LiDAR, LiDARCrafter and most likely the Veila paper).
    R2dm,
    /// LiDARGen (spectral-norm MMD).
    Lidargen,
    /// LiDAR-Diffusion (minimum matching distance over 0.5 m BEV occupancy), 64-beam setting.
    Lidm,
    /// LiDAR-Diffusion's 32-beam (nuScenes) setting: ±30 m grids.
    #[serde(rename = "lidm-nuscenes")]
    LidmNuscenes,
    /// Text2LiDAR (R2DM's evaluation code at 32 x 1024).
    Text2lidar,
    /// PyTorch3D's Chamfer convention (squared distances, means summed).
    Pytorch3d,
    /// The Veila paper's cross-modal consistency metrics.
    Veila,
    /// Fréchet distance of feature statistics (numpy covariance, exact matrix square root).
    Frechet,
}

impl Protocol {
    /// Lower-case name.
    pub fn name(&self) -> &'static str {
        match self {
            Protocol::R2dm => "r2dm",
            Protocol::Lidargen => "lidargen",
            Protocol::Lidm => "lidm",
            Protocol::LidmNuscenes => "lidm-nuscenes",
            Protocol::Text2lidar => "text2lidar",
            Protocol::Pytorch3d => "pytorch3d",
            Protocol::Veila => "veila",
            Protocol::Frechet => "frechet",
        }
    }
}

impl std::fmt::Display for Protocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One metric value: `{"name": "jsd", "protocol": "r2dm", "region": "all", "value": 0.0123, "generated": 10,
/// "reference": 10}`. `paper_scale` (omitted when absent) is the factor papers multiply the value by before
/// printing (e.g. `1e4` for the R2DM MMD).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetricValue {
    /// Metric name (`jsd`, `mmd`, `mmd-cd`, `chamfer`, `fd`, `cm-dc`, `cm-sc`, ...).
    pub name: String,
    /// Protocol the value follows.
    pub protocol: Protocol,
    /// Region the points were restricted to.
    pub region: Region,
    /// The value (raw, unscaled).
    pub value: f64,
    /// Number of generated scans / samples.
    pub generated: usize,
    /// Number of reference scans / samples.
    pub reference: usize,
    /// Factor papers print the value multiplied by.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub paper_scale: Option<f64>,
}

/// A list of metric values: serialises as `{"metrics": [...]}`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MetricReport {
    /// The values, in computation order.
    pub metrics: Vec<MetricValue>,
}
