//! Feature networks for the Fréchet Range Distance (FRD) and the Fréchet Point Distance (FPD).
//!
//! * [`RangeNet`]: a RangeNet++-style DarkNet encoder over 5-channel range images (range, x, y, z,
//!   remission). FRD feature: the **global average** over rows and columns of the deepest encoder map
//!   ([`RangeNet::features`]).
//! * [`PointNet`]: a PointNet classifier over point sets (coordinates scaled by 1/80). FPD feature: the
//!   **max-pooled global feature** ([`PointNet::features`]).
//! * [`FeatureNets`]: the two nets as one verified bundle, loaded from a folder ([`FeatureNets::from_dir`])
//!   or from in-memory files ([`FeatureNets::from_bytes`], e.g. `include_bytes!`), with batched feature
//!   extraction from point clouds. [`save_bundle`] writes one.
//! * [`train`]: their training on labelled scans (`cargo xtask train-feature-nets`).
//!
//! The Fréchet distance itself is `veila_metrics::fd` (this crate only produces feature vectors).
//!
//! # Bundle layout
//!
//! A folder with `rangenet.json` ([`RangeNetConfig`]), `rangenet.safetensors`, `pointnet.json`
//! ([`PointNetConfig`]), `pointnet.safetensors` and `manifest.json`:
//!
//! ```json
//! {"format": 1, "name": "veila-sim", "description": "...",
//!  "files": {"rangenet.json": "<sha256 hex>", "rangenet.safetensors": "...", ...}}
//! ```
//!
//! Loading checks every file's sha256 against the manifest and fails with [`crate::Error::Integrity`]
//! naming the file; the tensors must then match the config's net exactly
//! ([`crate::Error::CheckpointMismatch`] lists missing, unexpected and mis-shaped tensors).
//!
//! # Comparability
//!
//! The project ships nets trained on the simulator (`cargo xtask train-feature-nets`). Their FRD / FPD
//! values are useful to compare models *with each other* under this toolkit, but are **not comparable
//! with published numbers**: those use RangeNet++ DarkNet-53 trained on SemanticKITTI (features: 4096
//! fixed random values of the last decoder map) and SpareNet's ShapeNet PointNet (1808-value
//! concatenated features). Even converted official weights only reproduce the *networks*, not R2DM's
//! feature selection (see [`rangenet`] and [`pointnet`]).
//!
//! # Converting official weights (untested: the weights are not available to this project)
//!
//! RangeNet++ archives (`darknet53-1024.tar.gz`) hold a `backbone` file, a pickled PyTorch state dict
//! (or module) whose names match [`RangeNet`]'s exactly (`conv1.weight`, `bn1.*`, `enc1.conv.weight`,
//! `enc1.residual_0.conv1.weight`, ...). SpareNet's `cls_model_39.pth` is a `PointNetCls` state dict
//! whose names match [`PointNet`] with [`PointNetConfig::sparenet`]. A conversion sketch
//! (`pip install torch safetensors`):
//!
//! ```text
//! import json, hashlib, torch
//! from safetensors.torch import save_file
//! def clean(sd):
//!     sd = sd.state_dict() if hasattr(sd, "state_dict") else sd
//!     sd = sd.get("model_state_dict", sd) if isinstance(sd, dict) else sd
//!     return {k.removeprefix("module."): v.float().contiguous() for k, v in sd.items()
//!             if not k.endswith("num_batches_tracked")}
//! save_file(clean(torch.load("darknet53-1024/backbone", map_location="cpu", weights_only=False)),
//!           "out/rangenet.safetensors")
//! save_file(clean(torch.load("cls_model_39.pth", map_location="cpu")), "out/pointnet.safetensors")
//! # rangenet.json / pointnet.json: serde JSON of RangeNetConfig::darknet53() and
//! # PointNetConfig::sparenet() (e.g. copy models/feature-nets/*.json and edit the fields), then
//! # manifest.json with the sha256 of the four files:
//! files = {f: hashlib.sha256(open("out/" + f, "rb").read()).hexdigest() for f in
//!          ["rangenet.json", "rangenet.safetensors", "pointnet.json", "pointnet.safetensors"]}
//! json.dump({"format": 1, "name": "official", "description": "converted", "files": files},
//!           open("out/manifest.json", "w"))
//! ```
//!
//! `xtask/scripts/convert_feature_nets.py` is the same sketch as a script.
//!
//! # Example
//!
//! ```
//! use candle_core::{DType, Device};
//! use candle_nn::VarMap;
//! use veila_nn::feature_nets::{PointNet, PointNetConfig};
//! use veila_nn::seeded_var_builder;
//!
//! let cfg = PointNetConfig { num_points: Some(64), ..PointNetConfig::small() };
//! let dev = Device::Cpu;
//! let varmap = VarMap::new();
//! let net = PointNet::new(&cfg, seeded_var_builder(&varmap, 0, DType::F32, &dev))?;
//! let pts: Vec<glam::Vec3> = (0..100).map(|i| glam::Vec3::new(i as f32, 1.0, -1.0)).collect();
//! let x = candle_core::Tensor::from_vec(PointNet::prepare(&cfg, &pts)?, (1, 3, 64), &dev)?;
//! assert_eq!(net.features(&x)?.dims(), &[1, 256]);
//! # Ok::<(), veila_nn::Error>(())
//! ```

pub mod pointnet;
pub mod rangenet;
pub mod train;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use glam::Vec3;
use serde::{Deserialize, Serialize};

pub use pointnet::{PointNet, PointNetConfig, PointNetOutput};
pub use rangenet::{RangeNet, RangeNetConfig, RangeNetInput, RangeStage};

use crate::error::{Error, Result};

/// Config of the range net inside a bundle.
pub const RANGENET_CONFIG: &str = "rangenet.json";
/// Weights of the range net inside a bundle.
pub const RANGENET_WEIGHTS: &str = "rangenet.safetensors";
/// Config of the point net inside a bundle.
pub const POINTNET_CONFIG: &str = "pointnet.json";
/// Weights of the point net inside a bundle.
pub const POINTNET_WEIGHTS: &str = "pointnet.safetensors";
/// The manifest (sha256 of the four other files).
pub const MANIFEST: &str = "manifest.json";
/// The four files a manifest must list.
pub const BUNDLE_FILES: [&str; 4] = [
    RANGENET_CONFIG,
    RANGENET_WEIGHTS,
    POINTNET_CONFIG,
    POINTNET_WEIGHTS,
];
/// Current manifest format.
pub const MANIFEST_FORMAT: u32 = 1;

/// `manifest.json` of a bundle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Format version ([`MANIFEST_FORMAT`]).
    pub format: u32,
    /// Short name of the weights' origin, printed in metric protocols (e.g. `veila-sim`).
    pub name: String,
    /// Free text: how the nets were trained or converted.
    #[serde(default)]
    pub description: String,
    /// File name → lower-case hex sha256.
    pub files: BTreeMap<String, String>,
}

pub use crate::weights::sha256_hex;

fn parse_json<T: serde::de::DeserializeOwned>(bytes: &[u8], path: &Path) -> Result<T> {
    serde_json::from_slice(bytes).map_err(|source| Error::Json {
        path: path.to_path_buf(),
        source,
    })
}

/// The FRD and FPD networks of one bundle (see the module docs).
#[derive(Debug, Clone)]
pub struct FeatureNets {
    manifest: Manifest,
    rangenet: RangeNet,
    pointnet: PointNet,
    device: Device,
}

impl FeatureNets {
    /// Loads and verifies the bundle in folder `dir`.
    pub fn from_dir(dir: &Path, device: &Device) -> Result<Self> {
        let mut files = Vec::new();
        for name in [MANIFEST].iter().chain(BUNDLE_FILES.iter()) {
            let path = dir.join(name);
            // regular files under a cap, checked before reading (a link to /dev/zero, a FIFO)
            let bytes = if name.ends_with(".safetensors") {
                crate::weights::read_weights_file(&path)?
            } else {
                crate::weights::read_capped(
                    &path,
                    crate::weights::MAX_MODEL_JSON_BYTES,
                    "a feature-network bundle file",
                )?
            };
            files.push((path, bytes));
        }
        Self::from_paths(files, device)
    }

    /// Loads and verifies a bundle from in-memory files `(file name, bytes)` (all five files of the
    /// layout; extra entries are ignored). Errors name the files as given.
    pub fn from_bytes(files: &[(&str, &[u8])], device: &Device) -> Result<Self> {
        let mut out = Vec::new();
        for name in [MANIFEST].iter().chain(BUNDLE_FILES.iter()) {
            let Some((_, bytes)) = files.iter().find(|(n, _)| n == name) else {
                return Err(Error::Integrity {
                    path: PathBuf::from(name),
                    message: "the bundle lacks this file".into(),
                });
            };
            out.push((PathBuf::from(name), bytes.to_vec()));
        }
        Self::from_paths(out, device)
    }

    /// `files`: the manifest first, then [`BUNDLE_FILES`] in order.
    fn from_paths(files: Vec<(PathBuf, Vec<u8>)>, device: &Device) -> Result<Self> {
        let (manifest_path, manifest_bytes) = &files[0];
        let manifest: Manifest = parse_json(manifest_bytes, manifest_path)?;
        if manifest.format != MANIFEST_FORMAT {
            return Err(Error::Integrity {
                path: manifest_path.clone(),
                message: format!(
                    "manifest format {} is not supported (expected {MANIFEST_FORMAT})",
                    manifest.format
                ),
            });
        }
        for ((path, bytes), name) in files[1..].iter().zip(BUNDLE_FILES) {
            let Some(want) = manifest.files.get(name) else {
                return Err(Error::Integrity {
                    path: manifest_path.clone(),
                    message: format!("the manifest does not list {name}"),
                });
            };
            let got = sha256_hex(bytes);
            if !got.eq_ignore_ascii_case(want) {
                return Err(Error::Integrity {
                    path: path.clone(),
                    message: format!(
                        "sha256 {got} differs from {want} recorded in {}",
                        manifest_path.display()
                    ),
                });
            }
        }
        let (rc_path, rc) = &files[1];
        let (rw_path, rw) = &files[2];
        let (pc_path, pc) = &files[3];
        let (pw_path, pw) = &files[4];
        let rcfg: RangeNetConfig = parse_json(rc, rc_path)?;
        rcfg.validate()
            .map_err(|e| Error::Config(format!("{e} (in {})", rc_path.display())))?;
        let pcfg: PointNetConfig = parse_json(pc, pc_path)?;
        pcfg.validate()
            .map_err(|e| Error::Config(format!("{e} (in {})", pc_path.display())))?;
        Ok(Self {
            manifest,
            rangenet: RangeNet::from_safetensors(rw, rw_path, &rcfg, device)?,
            pointnet: PointNet::from_safetensors(pw, pw_path, &pcfg, device)?,
            device: device.clone(),
        })
    }

    /// The bundle's manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The range net.
    pub fn rangenet(&self) -> &RangeNet {
        &self.rangenet
    }

    /// The point net.
    pub fn pointnet(&self) -> &PointNet {
        &self.pointnet
    }

    /// Protocol label of FRD values from this bundle, e.g. `veila-sim rangenet-small, gap features`.
    pub fn frd_protocol(&self) -> String {
        format!(
            "{} {}, gap features",
            self.manifest.name,
            self.rangenet.config().name
        )
    }

    /// Protocol label of FPD values from this bundle, e.g. `veila-sim pointnet-small, max-pool features`.
    pub fn fpd_protocol(&self) -> String {
        format!(
            "{} {}, max-pool features",
            self.manifest.name,
            self.pointnet.config().name
        )
    }

    fn range_batch(&self) -> usize {
        let cfg = self.rangenet.config();
        let pixels = cfg.sensor.rows as usize * cfg.sensor.cols as usize * cfg.stem_channels;
        (8 * 1024 * 1024 / pixels.max(1)).clamp(1, 16)
    }

    /// FRD features of prepared range images (all of the range net's input size), one `Vec` of
    /// [`RangeNetConfig::feature_dim`] values per input.
    pub fn range_features(&self, inputs: &[RangeNetInput]) -> Result<Vec<Vec<f32>>> {
        let cfg = self.rangenet.config();
        let (h, w) = (cfg.sensor.rows as usize, cfg.sensor.cols as usize);
        let mut out = Vec::with_capacity(inputs.len());
        for (ci, chunk) in inputs.chunks(self.range_batch()).enumerate() {
            for (j, x) in chunk.iter().enumerate() {
                if (x.rows, x.cols) != (h, w) {
                    return Err(Error::Input(format!(
                        "range_features: input {} is {}x{}, the net {} reads {h}x{w}",
                        ci * self.range_batch() + j,
                        x.rows,
                        x.cols,
                        cfg.name
                    )));
                }
            }
            let refs: Vec<&RangeNetInput> = chunk.iter().collect();
            let x = RangeNetInput::batch(&refs, cfg, &self.device)?;
            let f = self.rangenet.features(&x)?.to_dtype(DType::F32)?;
            out.extend(f.to_vec2::<f32>()?);
        }
        Ok(out)
    }

    /// FRD features of point clouds: each is projected with the range net's sensor
    /// ([`RangeNetInput::from_points`]); `intensity` per scan is optional (remission 0 without).
    pub fn scan_range_features(
        &self,
        scans: &[(&[Vec3], Option<&[f32]>)],
    ) -> Result<Vec<Vec<f32>>> {
        let sensor = &self.rangenet.config().sensor;
        let inputs = scans
            .iter()
            .map(|(p, i)| RangeNetInput::from_points(p, *i, sensor))
            .collect::<Result<Vec<_>>>()?;
        self.range_features(&inputs)
    }

    /// A SemanticKITTI train id (1..=19, never 0 = unlabelled) for every point the range net sees,
    /// from its segmentation head: the points are projected with the net's sensor and each kept
    /// pixel's point is returned with the pixel's class (points that lose their pixel to a nearer one
    /// are left out). `intensity` is optional (remission 0 without). What CM-SC compares with an
    /// image's class map.
    pub fn segment_points(
        &self,
        points: &[Vec3],
        intensity: Option<&[f32]>,
    ) -> Result<(Vec<Vec3>, Vec<u32>)> {
        let cfg = self.rangenet.config();
        let input = RangeNetInput::from_points(points, intensity, &cfg.sensor)?;
        let x = RangeNetInput::batch(&[&input], cfg, &self.device)?;
        let logits = self.rangenet.forward(&x)?;
        // never class 0 (unlabelled): the argmax runs over classes 1..
        let labels = logits
            .narrow(1, 1, logits.dim(1)? - 1)?
            .argmax(1)?
            .flatten_all()?
            .to_vec1::<u32>()?;
        let mut kept = Vec::new();
        let mut out = Vec::new();
        for (k, &pi) in input.point_index.iter().enumerate() {
            if input.mask[k] && (pi as usize) < points.len() {
                kept.push(points[pi as usize]);
                out.push(labels[k] + 1);
            }
        }
        Ok((kept, out))
    }

    /// FPD features of point clouds (metres, LiDAR frame), one `Vec` of
    /// [`PointNetConfig::feature_dim`] values per scan. Fails on a scan without finite points.
    pub fn point_features(&self, scans: &[&[Vec3]]) -> Result<Vec<Vec<f32>>> {
        let cfg = self.pointnet.config();
        let batch = if cfg.num_points.is_some() { 16 } else { 1 };
        let mut out = Vec::with_capacity(scans.len());
        for chunk in scans.chunks(batch) {
            let mut data = Vec::new();
            let mut n = 0;
            for p in chunk {
                let v = PointNet::prepare(cfg, p)?;
                n = v.len() / 3;
                data.extend(v);
            }
            let x = Tensor::from_vec(data, (chunk.len(), 3, n), &self.device)?;
            out.extend(self.pointnet.features(&x)?.to_vec2::<f32>()?);
        }
        Ok(out)
    }
}

fn json_bytes<T: Serialize>(v: &T, path: &Path) -> Result<Vec<u8>> {
    let mut s = serde_json::to_string_pretty(v).map_err(|source| Error::Json {
        path: path.to_path_buf(),
        source,
    })?;
    s.push('\n');
    Ok(s.into_bytes())
}

/// Writes a bundle into `dir` (created if needed): the two configs, the two weight files and the
/// manifest with their sha256 sums. The tensors must match the configs' nets exactly (checked before
/// anything is written); every file is written to a temporary name and renamed, the manifest last.
pub fn save_bundle(
    dir: &Path,
    name: &str,
    description: &str,
    rangenet: (&RangeNetConfig, &HashMap<String, Tensor>),
    pointnet: (&PointNetConfig, &HashMap<String, Tensor>),
) -> Result<Manifest> {
    let check = |expected: BTreeMap<String, Vec<usize>>,
                 tensors: &HashMap<String, Tensor>,
                 file: &str|
     -> Result<()> {
        let found = tensors
            .iter()
            .map(|(k, v)| (k.clone(), v.dims().to_vec()))
            .collect();
        let report = crate::weights::compare_tensors(&expected, &found);
        if report.is_clean() {
            Ok(())
        } else {
            Err(Error::CheckpointMismatch {
                path: dir.join(file),
                report,
            })
        }
    };
    check(
        RangeNet::expected_tensors(rangenet.0)?,
        rangenet.1,
        RANGENET_WEIGHTS,
    )?;
    check(
        PointNet::expected_tensors(pointnet.0)?,
        pointnet.1,
        POINTNET_WEIGHTS,
    )?;
    std::fs::create_dir_all(dir).map_err(|source| Error::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let contents: Vec<(&str, Vec<u8>)> = vec![
        (
            RANGENET_CONFIG,
            json_bytes(rangenet.0, &dir.join(RANGENET_CONFIG))?,
        ),
        (
            RANGENET_WEIGHTS,
            crate::weights::safetensors_bytes(rangenet.1, &dir.join(RANGENET_WEIGHTS))?,
        ),
        (
            POINTNET_CONFIG,
            json_bytes(pointnet.0, &dir.join(POINTNET_CONFIG))?,
        ),
        (
            POINTNET_WEIGHTS,
            crate::weights::safetensors_bytes(pointnet.1, &dir.join(POINTNET_WEIGHTS))?,
        ),
    ];
    let manifest = Manifest {
        format: MANIFEST_FORMAT,
        name: name.to_string(),
        description: description.to_string(),
        files: contents
            .iter()
            .map(|(n, b)| (n.to_string(), sha256_hex(b)))
            .collect(),
    };
    let manifest_bytes = json_bytes(&manifest, &dir.join(MANIFEST))?;
    for (file, bytes) in contents
        .iter()
        .map(|(n, b)| (*n, b.as_slice()))
        .chain([(MANIFEST, manifest_bytes.as_slice())])
    {
        let path = dir.join(file);
        let tmp = crate::weights::tmp_path(&path);
        std::fs::write(&tmp, bytes).map_err(|source| Error::Io {
            path: path.clone(),
            source,
        })?;
        std::fs::rename(&tmp, &path).map_err(|source| Error::Io {
            path: path.clone(),
            source,
        })?;
    }
    Ok(manifest)
}
