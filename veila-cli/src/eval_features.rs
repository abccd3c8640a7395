//! FRD and FPD for `veila eval`: features of every scan from the feature networks
//! ([`veila_nn::feature_nets`]), then the Fréchet distance of their statistics
//! ([`veila_metrics::fd`]).
//!
//! The networks are the bundle shipped in `models/feature-nets` (embedded in the binary and verified
//! against its manifest at load time) or a folder with the same layout (`--feature-nets DIR`, e.g.
//! converted official weights). Scans are read in chunks, so memory stays bounded by one chunk of
//! scans plus one feature vector per scan.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use glam::Vec3;
use rayon::prelude::*;
use veila_data::scan::PointFormat;
use veila_metrics::fd::{FeatureStats, frechet_distance};
use veila_nn::feature_nets::{self, FeatureNets};

/// The bundle trained by `cargo xtask train-feature-nets`, embedded in the binary.
const SHIPPED: [(&str, &[u8]); 5] = [
    (
        feature_nets::MANIFEST,
        include_bytes!("../../models/feature-nets/manifest.json"),
    ),
    (
        feature_nets::RANGENET_CONFIG,
        include_bytes!("../../models/feature-nets/rangenet.json"),
    ),
    (
        feature_nets::RANGENET_WEIGHTS,
        include_bytes!("../../models/feature-nets/rangenet.safetensors"),
    ),
    (
        feature_nets::POINTNET_CONFIG,
        include_bytes!("../../models/feature-nets/pointnet.json"),
    ),
    (
        feature_nets::POINTNET_WEIGHTS,
        include_bytes!("../../models/feature-nets/pointnet.safetensors"),
    ),
];

/// Scans read and pushed through the nets at a time.
const CHUNK: usize = 32;

/// The shipped bundle, or the one in `dir`.
pub(crate) fn load_nets(dir: Option<&Path>) -> Result<FeatureNets> {
    let dev = crate::model::device()?;
    match dir {
        Some(d) => FeatureNets::from_dir(d, &dev)
            .with_context(|| format!("loading the feature networks from {}", d.display())),
        None => FeatureNets::from_bytes(&SHIPPED, &dev)
            .context("loading the built-in feature networks (models/feature-nets)"),
    }
}

/// Which features to extract.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Want {
    pub(crate) frd: bool,
    pub(crate) fpd: bool,
}

/// Feature statistics of one folder.
pub(crate) struct SetFeatures {
    pub(crate) range: Option<FeatureStats>,
    pub(crate) point: Option<FeatureStats>,
}

/// Intensity on KITTI's `[0, 1]` scale (nuScenes stores 0..255), `None` when the file has none.
fn remission(cloud: &veila_data::points::PointCloud, format: PointFormat) -> Option<Vec<f32>> {
    if cloud.intensity.len() != cloud.xyz.len() {
        return None;
    }
    let scale = match format {
        PointFormat::NuScenesPcdBin => 1.0 / 255.0,
        _ => 1.0,
    };
    Some(cloud.intensity.iter().map(|v| v * scale).collect())
}

/// FRD / FPD feature statistics of the scans in `files`.
pub(crate) fn set_features(
    nets: &FeatureNets,
    files: &[PathBuf],
    what: &str,
    want: Want,
) -> Result<SetFeatures> {
    let mut range = want
        .frd
        .then(|| FeatureStats::new(nets.rangenet().config().feature_dim()));
    let mut point = want
        .fpd
        .then(|| FeatureStats::new(nets.pointnet().config().feature_dim()));
    let pb = crate::progress::bar(files.len() as u64, &format!("{what} features"));
    for chunk in files.chunks(CHUNK) {
        let scans: Vec<(Vec<Vec3>, Option<Vec<f32>>)> = chunk
            .par_iter()
            .map(|f| {
                let loaded = veila_data::scan::read_points(f)
                    .with_context(|| format!("reading {}", f.display()))?;
                if loaded.cloud.xyz.is_empty() {
                    bail!("{}: the scan has no (finite) points", f.display());
                }
                let inten = remission(&loaded.cloud, loaded.format);
                Ok((loaded.cloud.xyz, inten))
            })
            .collect::<Result<_>>()?;
        if let Some(stats) = range.as_mut() {
            let pairs: Vec<(&[Vec3], Option<&[f32]>)> = scans
                .iter()
                .map(|(p, i)| (p.as_slice(), i.as_deref()))
                .collect();
            let feats = nets
                .scan_range_features(&pairs)
                .with_context(|| format!("range features of {what} scans"))?;
            for (f, file) in feats.iter().zip(chunk) {
                stats
                    .push_rows(f, "range feature")
                    .with_context(|| file.display().to_string())?;
            }
        }
        if let Some(stats) = point.as_mut() {
            let pts: Vec<&[Vec3]> = scans.iter().map(|(p, _)| p.as_slice()).collect();
            let feats = nets
                .point_features(&pts)
                .with_context(|| format!("point features of {what} scans"))?;
            for (f, file) in feats.iter().zip(chunk) {
                stats
                    .push_rows(f, "point feature")
                    .with_context(|| file.display().to_string())?;
            }
        }
        pb.inc(chunk.len() as u64);
    }
    pb.finish_and_clear();
    Ok(SetFeatures { range, point })
}

/// The Fréchet distance of two sets' statistics; both need at least 2 scans.
pub(crate) fn frechet(
    generated: &FeatureStats,
    reference: &FeatureStats,
    metric: &str,
    dirs: (&Path, &Path),
) -> Result<f64> {
    for (stats, dir) in [(generated, dirs.0), (reference, dirs.1)] {
        if stats.count() < 2 {
            bail!(
                "{metric} needs at least 2 scans per folder (a covariance), {} has {}",
                dir.display(),
                stats.count()
            );
        }
    }
    Ok(frechet_distance(generated, reference)?)
}
