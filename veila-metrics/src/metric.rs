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

/// A metric as `veila eval --metrics` names it. [`MetricName::ALL`] is the one list of metrics:
/// `--metrics`' choices are built from it (and a test of that door checks that they are), and
/// every [`MetricValue::name`] starts with its metric's name. A new set metric is a variant here
/// with its arms and its score in [`crate::suite::score_sets`] (`veila-metrics/src/suite.rs`);
/// the feature and cross-modal metrics are computed beside the set metrics, by the callers that
/// hold the networks and the cameras.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum MetricName {
    /// The protocol's JSD after its whole pipeline.
    Jsd,
    /// The protocol's MMD after its whole pipeline.
    Mmd,
    /// R2DM's BEV JSD on the raw points.
    JsdRaw,
    /// R2DM's BEV MMD on the raw points.
    MmdRaw,
    /// LiDARGen's spectral-norm BEV MMD on the raw points.
    MmdLidargenRaw,
    /// LiDM's minimum matching distance on the raw points, 64-beam grid.
    MmdLidmRaw,
    /// LiDM's minimum matching distance on the raw points, 32-beam nuScenes grid.
    MmdLidmNuscenesRaw,
    /// Minimum matching distance with the 3-D Chamfer distance.
    MmdCd,
    /// Chamfer distance of scans paired in order.
    Chamfer,
    /// Fréchet Range Distance ([`crate::fd`] of range-image network features).
    Frd,
    /// Fréchet Point Distance ([`crate::fd`] of point network features).
    Fpd,
    /// Cross-modal depth consistency, the paper's CM-DC ([`crate::crossmodal`]).
    CmDc,
    /// Cross-modal semantic consistency, the paper's CM-SC ([`crate::crossmodal`]).
    CmSc,
}

impl MetricName {
    /// Every metric, in the order help texts list them.
    pub const ALL: [MetricName; 13] = [
        MetricName::Jsd,
        MetricName::Mmd,
        MetricName::JsdRaw,
        MetricName::MmdRaw,
        MetricName::MmdLidargenRaw,
        MetricName::MmdLidmRaw,
        MetricName::MmdLidmNuscenesRaw,
        MetricName::MmdCd,
        MetricName::Chamfer,
        MetricName::Frd,
        MetricName::Fpd,
        MetricName::CmDc,
        MetricName::CmSc,
    ];

    /// The name: `jsd`, `mmd`, `jsd-raw`, ..., `cm-sc`.
    pub fn as_str(self) -> &'static str {
        match self {
            MetricName::Jsd => "jsd",
            MetricName::Mmd => "mmd",
            MetricName::JsdRaw => "jsd-raw",
            MetricName::MmdRaw => "mmd-raw",
            MetricName::MmdLidargenRaw => "mmd-lidargen-raw",
            MetricName::MmdLidmRaw => "mmd-lidm-raw",
            MetricName::MmdLidmNuscenesRaw => "mmd-lidm-nuscenes-raw",
            MetricName::MmdCd => "mmd-cd",
            MetricName::Chamfer => "chamfer",
            MetricName::Frd => "frd",
            MetricName::Fpd => "fpd",
            MetricName::CmDc => "cm-dc",
            MetricName::CmSc => "cm-sc",
        }
    }

    /// One paragraph for a `--help` text.
    pub fn help(self) -> &'static str {
        match self {
            MetricName::Jsd => {
                "The --protocol's JSD after its whole pipeline (R2DM / Text2LiDAR / LiDARGen: \
                 summed 100 x 100 BEV histograms; LiDM: summed 0.05 m occupancy)."
            }
            MetricName::Mmd => {
                "The --protocol's MMD after its whole pipeline (R2DM / Text2LiDAR: Gaussian \
                 kernel, Frobenius, printed x 1e4; LiDARGen: spectral norm; LiDM: minimum matching \
                 2-D Chamfer, printed x 1e4)."
            }
            MetricName::JsdRaw => {
                "R2DM's BEV JSD on the raw points (no projection, no range caps)."
            }
            MetricName::MmdRaw => {
                "R2DM's BEV MMD on the raw points (no projection, no range caps)."
            }
            MetricName::MmdLidargenRaw => {
                "LiDARGen's spectral-norm BEV MMD on the raw points (O(N^2) SVDs)."
            }
            MetricName::MmdLidmRaw => {
                "LiDM's minimum matching distance on the raw points, 64-beam grid (+-50 m)."
            }
            MetricName::MmdLidmNuscenesRaw => {
                "LiDM's minimum matching distance on the raw points, 32-beam nuScenes grid \
                 (+-30 m)."
            }
            MetricName::MmdCd => {
                "Minimum matching distance with the 3-D Chamfer distance (PyTorch3D convention)."
            }
            MetricName::Chamfer => {
                "Chamfer distance of scans paired by file name, averaged over pairs (PyTorch3D \
                 convention)."
            }
            MetricName::Frd => {
                "Fréchet Range Distance: Fréchet distance of RangeNet features (global average of \
                 the deepest encoder map) of each scan's range image, whole panorama only. With \
                 the built-in simulator-trained net, NOT comparable with published FRD values \
                 (different weights and feature layer)."
            }
            MetricName::Fpd => {
                "Fréchet Point Distance: Fréchet distance of PointNet max-pooled features of each \
                 scan (points / 80 m), whole panorama only. With the built-in simulator-trained \
                 net, NOT comparable with published FPD values (different weights and feature \
                 layer)."
            }
            MetricName::CmDc => {
                "Cross-modal depth consistency (the paper's CM-DC): each generated scan's points \
                 projected into its camera (--calib) against a depth map (--depth-maps), AbsRel \
                 after --depth-alignment, averaged over the scans; the camera's field of view only."
            }
            MetricName::CmSc => {
                "Cross-modal semantic consistency (the paper's CM-SC): the percentage of generated \
                 points whose class from the built-in range segmentation net (SemanticKITTI train \
                 ids) equals the class map's (--semantic-maps) where they project; averaged over \
                 the scans."
            }
        }
    }

    /// Whether [`crate::suite::score_sets`] computes it (from the scans alone); the feature and
    /// cross-modal metrics need networks or cameras and are computed beside it.
    pub fn is_set_metric(self) -> bool {
        !matches!(
            self,
            MetricName::Frd | MetricName::Fpd | MetricName::CmDc | MetricName::CmSc
        )
    }
}

impl std::fmt::Display for MetricName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for MetricName {
    type Err = crate::Error;

    fn from_str(name: &str) -> crate::Result<Self> {
        MetricName::ALL
            .into_iter()
            .find(|m| m.as_str() == name)
            .ok_or_else(|| {
                let names: Vec<&str> = MetricName::ALL.map(MetricName::as_str).into();
                crate::Error::InvalidParameter {
                    name: "metric",
                    reason: format!("`{name}` is not one of {}", names.join(", ")),
                }
            })
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_metric_has_one_name_that_parses_back() {
        for m in MetricName::ALL {
            assert_eq!(m.as_str().parse::<MetricName>().unwrap(), m);
            assert_eq!(m.to_string(), m.as_str());
            assert!(!m.help().is_empty());
            let same = MetricName::ALL.iter().filter(|n| n.as_str() == m.as_str());
            assert_eq!(same.count(), 1, "{m}");
        }
        let e = "fid".parse::<MetricName>().unwrap_err().to_string();
        assert!(
            e.contains("fid") && e.contains("mmd-lidm-nuscenes-raw"),
            "{e}"
        );
        // the set metrics come first, as score_sets reports them
        let set = MetricName::ALL.iter().filter(|m| m.is_set_metric()).count();
        assert!(MetricName::ALL[..set].iter().all(|m| m.is_set_metric()));
    }
}
