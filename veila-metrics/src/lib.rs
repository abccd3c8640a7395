//! # veila-metrics
//!
//! Metrics for generated LiDAR scans, each named by the **protocol** it reproduces, because "JSD", "MMD"
//! and "FRD" mean slightly different things in different projects:
//!
//! | metric | protocol | module |
//! |---|---|---|
//! | BEV histograms (3 m < ‖p‖ < 70 m, 100 x 100 bins over ±80 m, numpy bin edges) | R2DM / LiDARGen | [`bev`] |
//! | JSD — the Jensen–Shannon *distance* of the summed histograms (`scipy` semantics) | R2DM / LiDARGen | [`dist::jsd`] |
//! | MMD — biased Gaussian-kernel MMD, σ = 0.5, Frobenius distance (papers print × 10⁴) | R2DM | [`dist::mmd_r2dm_dense`], [`dist::mmd_r2dm_sparse`] |
//! | MMD — the same with the spectral-norm distance | LiDARGen | [`dist::mmd_lidargen`] |
//! | MMD — minimum matching distance, 2-D Chamfer over 0.5 m BEV occupancy | LiDM | [`lidm`] |
//! | Fréchet distance (FRD, FPD) from streaming, mergeable statistics | numpy/scipy | [`fd`] |
//! | Chamfer distance (squared, means summed) and MMD-CD | PyTorch3D | [`chamfer`], BVH in [`nn`] |
//! | CM-DC / CM-SC cross-modal consistency | Veila paper | [`crossmodal`] |
//! | Range MAE of two range images on one grid, over pixels valid in both | — | [`range`] |
//! | Semantic segmentation IoU / mIoU / accuracy from one confusion matrix, class 0 ignored | SemanticKITTI (`semantic-kitti-api`'s `iouEval`) | [`segmentation`] |
//! | Range MAE and coverage in a camera's view, camera depth at LiDAR points | — | [`view`] |
//! | Range-image realism: relative range-step histograms (log10, 0.25 decade) and smooth / edge shares, their W1 / JSD texture distance, ray drop per row, pairwise diversity, nearest-scan memorisation | — | [`texture`] |
//!
//! Every point-based metric can be restricted to the paper's front (`x > 0`) or rear (`x <= 0`) half with
//! [`Region`] (re-exported from `veila-geom`). Results are collected as [`MetricValue`]s whose JSON form is
//! what `veila eval` writes. The crate takes points (`&[glam::Vec3]` or `&[[f32; 3]]`), histograms and
//! feature rows; it does no file IO and does not depend on a neural-network framework.
//!
//! ```
//! use glam::Vec3;
//! use veila_metrics::{Region, bev::{BevConfig, bev_histogram}, dist, chamfer, fd};
//!
//! // two tiny "scans"
//! let a = vec![Vec3::new(10.0, 5.0, -1.0), Vec3::new(-20.0, 3.0, 0.5), Vec3::new(5.0, -30.0, 0.0)];
//! let b = vec![Vec3::new(10.5, 5.0, -1.0), Vec3::new(-20.0, 3.5, 0.5), Vec3::new(40.0, 1.0, 0.0)];
//!
//! let cfg = BevConfig::r2dm();
//! let ha = bev_histogram(&a, &cfg, Region::All, "a")?;
//! let hb = bev_histogram(&b, &cfg, Region::All, "b")?;
//! let jsd = dist::jsd(&[ha.clone()], &[hb.clone()])?;
//! assert!(jsd > 0.0 && jsd <= std::f64::consts::LN_2.sqrt());
//! assert_eq!(dist::jsd(&[ha.clone()], &[ha.clone()])?, 0.0);
//!
//! let cd = chamfer::chamfer_distance(&a, &b)?;
//! assert!(cd.value() > 0.0);
//!
//! // Fréchet distance of two feature matrices (rows = samples)
//! let fa = [0.0f32, 1.0, 2.0, 0.5, 1.0, 3.0, 0.2, 0.1];
//! let fb = [1.0f32, 1.0, 2.0, 1.5, 0.0, 3.0, 0.2, 0.4];
//! let d = fd::frechet_distance_rows(&fa, &fb, 2, fd::SqrtMethod::Eigen)?;
//! assert!(d > 0.0);
//! # Ok::<(), veila_metrics::Error>(())
//! ```

pub mod baseline;
pub mod bev;
pub mod chamfer;
pub mod crossmodal;
pub mod dist;
mod error;
pub mod fd;
pub mod lidm;
pub mod metric;
pub mod nn;
pub mod protocol;
pub mod range;
pub mod segmentation;
pub mod suite;
pub mod texture;
pub mod view;

// the main types at the root; the modules stay public for the rest
pub use bev::{BevConfig, BevHistogram};
pub use chamfer::Chamfer;
pub use error::{Error, Result};
pub use fd::{FeatureStats, SqrtMethod};
pub use metric::{MetricName, MetricReport, MetricValue, Protocol};
pub use nn::PointIndex;
pub use protocol::PeerProtocol;
pub use texture::TextureSummary;
pub use veila_geom::Region;

use glam::Vec3;

/// `Err(NonFinite)` naming `what` and `index` when `p` has a NaN or infinite coordinate.
#[inline]
pub(crate) fn check_finite(p: Vec3, what: &str, index: usize) -> Result<()> {
    if p.is_finite() {
        Ok(())
    } else {
        Err(Error::NonFinite {
            what: what.to_string(),
            index,
        })
    }
}

/// The points of `points` that lie in `region` (front: `x > 0`, rear: `x <= 0`).
pub fn filter_region<P: Copy + Into<Vec3>>(points: &[P], region: Region) -> Vec<Vec3> {
    points
        .iter()
        .map(|&p| p.into())
        .filter(|&p| region.contains(p))
        .collect()
}
