//! A segmenter model folder: what `veila segment predict` loads, and what `veila segment train`
//! writes.
//!
//! | file | content |
//! |---|---|
//! | `segmenter.json` | [`SegmenterModelConfig`]: the network, the sensor whose grid it segments, the kNN clean-up, the classes, provenance |
//! | `segmenter.safetensors` | the weights, BatchNorm running statistics included |
//! | `manifest.json` | `{"format": "veila-manifest/1", "files": {"NAME": "SHA256_HEX", ...}}` |
//!
//! The manifest is a bundle's ([`crate::app::bundle::Manifest`]), verified the same way before
//! anything is parsed, and the files are read as a bundle's are: inside the folder after links are
//! followed, regular files under their kind's cap, checked before they are read; the weights
//! must be exactly the tensors the config's network asks for, `f32`, finite and bounded.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use glam::Vec3;
use serde::{Deserialize, Serialize};
use veila_geom::{BeamLayout, LidarSensor, ProjectionOptions, Projector, RowSource};
use veila_nn::segmenter::knn::{KnnConfig, point_labels};
use veila_nn::segmenter::{Segmenter, SegmenterConfig, pixel_classes};

use super::frames::GridScan;
use super::labels::SegClass;
use crate::app::bundle::{
    MANIFEST_FILE, ManifestFolder, ModelFiles, read_folder_file, safetensors_bytes, sha256_hex,
};
use crate::app::dataset_gen::ScanLabeller;
use crate::app::pipeline::Scan;
use crate::error::{Error, Result};

/// Format tag of `segmenter.json`.
pub const SEGMENTER_FORMAT: &str = "veila-segmenter/1";
/// The config file of a segmenter folder.
pub const SEGMENTER_CONFIG_FILE: &str = "segmenter.json";
/// The weights file of a segmenter folder.
pub const SEGMENTER_WEIGHTS_FILE: &str = "segmenter.safetensors";

/// `segmenter.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegmenterModelConfig {
    /// [`SEGMENTER_FORMAT`].
    pub format: String,
    /// The network.
    pub network: SegmenterConfig,
    /// The sensor a scan is projected with (its grid is the network's).
    pub sensor: LidarSensor,
    /// RangeNet++'s clean-up that labels every point.
    #[serde(default)]
    pub knn: KnnConfig,
    /// Every train id, in order, with the raw id written for it.
    pub classes: Vec<SegClass>,
    /// How it was made (free JSON).
    #[serde(default)]
    pub provenance: serde_json::Value,
}

impl SegmenterModelConfig {
    /// The model of `network` with the field of view and range of `fov` (its grid: the
    /// network's) and the `classes`, RangeNet++'s clean-up, no provenance.
    pub fn new(network: SegmenterConfig, fov: &LidarSensor, classes: Vec<SegClass>) -> Self {
        SegmenterModelConfig {
            format: SEGMENTER_FORMAT.into(),
            sensor: LidarSensor {
                rows: network.rows as u32,
                cols: network.cols as u32,
                ..fov.clone()
            },
            network,
            knn: KnnConfig::default(),
            classes,
            provenance: serde_json::Value::Null,
        }
    }

    /// Checks every part (errors name `origin`): the format, the network's and the sensor's
    /// bounds, the sensor's grid against the network's, a sensor that needs no rings (a KITTI
    /// `.bin` has none), the clean-up, and one class per train id.
    pub fn check(&self, origin: &Path) -> Result<()> {
        let bad = |reason: String| Error::Input {
            path: origin.to_path_buf(),
            reason,
        };
        if self.format != SEGMENTER_FORMAT {
            return Err(bad(format!(
                "format `{}`, expected `{SEGMENTER_FORMAT}`",
                self.format
            )));
        }
        let net = &self.network;
        net.validate().map_err(|e| bad(e.to_string()))?;
        self.sensor.validate().map_err(|e| bad(e.to_string()))?;
        self.knn.validate().map_err(|e| bad(e.to_string()))?;
        if (self.sensor.rows as usize, self.sensor.cols as usize) != (net.rows, net.cols) {
            return Err(bad(format!(
                "the sensor's grid is {} x {}, the network's {} x {}",
                self.sensor.rows, self.sensor.cols, net.rows, net.cols
            )));
        }
        if matches!(
            self.sensor.beams,
            BeamLayout::PerBeam {
                row_source: RowSource::Ring,
                ..
            }
        ) {
            return Err(bad(
                "the sensor takes rows from ring indices, which KITTI scans do not have".into(),
            ));
        }
        if self.classes.len() != net.num_classes {
            return Err(bad(format!(
                "{} classes listed for a network of {}",
                self.classes.len(),
                net.num_classes
            )));
        }
        for (i, c) in self.classes.iter().enumerate() {
            if c.train_id as usize != i || c.raw_id > 0xFFFF {
                return Err(bad(format!(
                    "classes[{i}]: train id {} (must be {i}), raw id {} (at most 65535)",
                    c.train_id, c.raw_id
                )));
            }
        }
        Ok(())
    }
}

/// A loaded segmenter.
#[derive(Debug, Clone)]
pub struct SegmenterModel {
    /// The config.
    pub config: SegmenterModelConfig,
    /// The network.
    pub net: Segmenter,
    projector: Projector,
    origin: PathBuf,
    /// What identifies it ([`SegmenterModel::identity`]).
    identity: String,
    device: Device,
}

fn parse_config(bytes: &[u8], path: &Path) -> Result<SegmenterModelConfig> {
    serde_json::from_slice(bytes).map_err(|source| Error::Json {
        path: path.to_path_buf(),
        source,
    })
}

impl SegmenterModel {
    /// Reads and verifies a segmenter folder (module docs).
    pub fn from_dir(dir: &Path, device: &Device) -> Result<Self> {
        let files: Vec<(&str, Vec<u8>)> =
            [MANIFEST_FILE, SEGMENTER_CONFIG_FILE, SEGMENTER_WEIGHTS_FILE]
                .into_iter()
                .map(|name| Ok((name, read_folder_file(dir, name, "segmenter")?)))
                .collect::<Result<_>>()?;
        let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (*n, b.as_slice())).collect();
        Self::from_files(&refs, dir, device)
    }

    /// Builds a segmenter from its files in memory (`(file name, bytes)`; a binary embeds its
    /// default one); `origin` names the source in errors. Every file is checked against the
    /// manifest first.
    pub fn from_files(files: &[(&str, &[u8])], origin: &Path, device: &Device) -> Result<Self> {
        let model_files = ModelFiles::new(files, origin)?;
        let verified = |name: &str| model_files.verified(name);
        let cfg_path = origin.join(SEGMENTER_CONFIG_FILE);
        let config = parse_config(verified(SEGMENTER_CONFIG_FILE)?, &cfg_path)?;
        config.check(&cfg_path)?;
        let expected = expected_tensors(&config.network)?;
        let weights = veila_nn::checkpoint::read_checked_bytes(
            verified(SEGMENTER_WEIGHTS_FILE)?,
            &origin.join(SEGMENTER_WEIGHTS_FILE),
            &expected,
            device,
        )?;
        let identity = format!(
            "segmenter manifest sha256 {}",
            sha256_hex(model_files.manifest_bytes()?)
        );
        Self::build(config, weights, origin, device, Some(identity))
    }

    /// The segmenter of `config` with `weights` (exactly the tensors its network asks for);
    /// `origin` names it in errors.
    pub fn new(
        config: SegmenterModelConfig,
        weights: HashMap<String, Tensor>,
        origin: &Path,
        device: &Device,
    ) -> Result<Self> {
        Self::build(config, weights, origin, device, None)
    }

    /// [`SegmenterModel::new`] with its identity given, or (`None`) computed from the config and
    /// the weights.
    fn build(
        config: SegmenterModelConfig,
        weights: HashMap<String, Tensor>,
        origin: &Path,
        device: &Device,
        identity: Option<String>,
    ) -> Result<Self> {
        config.check(origin)?;
        let identity = match identity {
            Some(id) => id,
            None => {
                let json = serde_json::to_vec(&config).map_err(|source| Error::Json {
                    path: origin.join(SEGMENTER_CONFIG_FILE),
                    source,
                })?;
                let bytes = safetensors_bytes(&weights, &origin.join(SEGMENTER_WEIGHTS_FILE))?;
                format!(
                    "segmenter in memory sha256 {}",
                    sha256_hex(&[json, bytes].concat())
                )
            }
        };
        let net = Segmenter::new(
            &config.network,
            VarBuilder::from_tensors(weights, DType::F32, device),
        )?;
        let projector = Projector::new(&config.sensor, ProjectionOptions::default())?;
        Ok(SegmenterModel {
            config,
            net,
            projector,
            origin: origin.to_path_buf(),
            identity,
            device: device.clone(),
        })
    }

    /// Writes a segmenter folder (module docs) atomically: the files into a hidden temporary
    /// folder beside `dir`, the manifest last, one rename.
    pub fn save(
        dir: &Path,
        config: &SegmenterModelConfig,
        weights: &HashMap<String, Tensor>,
    ) -> Result<()> {
        config.check(dir)?;
        let mut folder = ManifestFolder::new(dir)?;
        let json = serde_json::to_vec_pretty(config).map_err(|source| Error::Json {
            path: dir.join(SEGMENTER_CONFIG_FILE),
            source,
        })?;
        folder.put(SEGMENTER_CONFIG_FILE, &json)?;
        let bytes = safetensors_bytes(weights, &dir.join(SEGMENTER_WEIGHTS_FILE))?;
        folder.put(SEGMENTER_WEIGHTS_FILE, &bytes)?;
        folder.finish()
    }

    /// Where it was loaded from (a folder, or a label for an embedded one).
    pub fn origin(&self) -> &Path {
        &self.origin
    }

    /// A scan (its points with their intensity) projected on the segmenter's grid.
    pub fn grid_scan(&self, points: &[Vec3], intensity: &[f32]) -> Result<GridScan> {
        GridScan::new(points, intensity, &self.projector, &self.config.network)
    }

    /// The train id of every point of every scan: the network's pixel classes, carried to the
    /// points by the kNN clean-up (points the projection rejects get train id 0).
    pub fn predict(&self, scans: &[GridScan]) -> Result<Vec<Vec<u32>>> {
        if scans.is_empty() {
            return Ok(Vec::new());
        }
        let cfg = &self.config.network;
        let device = &self.device;
        let data: Vec<f32> = scans.iter().flat_map(|s| s.input.iter().copied()).collect();
        let x = Tensor::from_vec(
            data,
            (
                scans.len(),
                veila_nn::segmenter::IN_CHANNELS,
                cfg.rows,
                cfg.cols,
            ),
            device,
        )?;
        let classes = pixel_classes(&self.net.forward(&x)?)?;
        scans
            .iter()
            .zip(&classes)
            .map(|(s, c)| Ok(point_labels(&s.image, c, &s.pixels, &self.config.knn)?))
            .collect()
    }

    /// What identifies it: the SHA-256 of its `manifest.json` (every file it loaded was checked
    /// against it), or for one built from weights in memory, of its config and weights.
    pub fn identity(&self) -> &str {
        &self.identity
    }

    /// The raw ids written for `train_ids` (the classes' `raw_id`).
    pub fn raw_ids(&self, train_ids: &[u32]) -> Vec<u32> {
        train_ids
            .iter()
            .map(|&t| self.config.classes.get(t as usize).map_or(0, |c| c.raw_id))
            .collect()
    }
}

/// Pseudo-labels for dataset generation (`veila generate --frames --segmenter`): every point of a
/// generated scan, labelled as `veila segment predict` labels the points of its `.bin`.
impl ScanLabeller for SegmenterModel {
    fn identity(&self) -> String {
        SegmenterModel::identity(self).to_string()
    }

    fn label(&self, scan: &Scan) -> Result<Vec<u32>> {
        let grid = self.grid_scan(&scan.points.xyz, &scan.points.intensity)?;
        let train_ids = self
            .predict(std::slice::from_ref(&grid))?
            .pop()
            .unwrap_or_default();
        Ok(self.raw_ids(&train_ids))
    }
}

/// Every tensor (name and shape) the network of `cfg` reads, BatchNorm statistics included.
pub fn expected_tensors(
    cfg: &SegmenterConfig,
) -> Result<std::collections::BTreeMap<String, Vec<usize>>> {
    Ok(veila_nn::weights::record_tensors(|vb| {
        Segmenter::new(cfg, vb).map(|_| ())
    })?)
}
