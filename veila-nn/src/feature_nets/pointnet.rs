//! A PointNet classifier over point sets (the FPD feature network).
//!
//! Architecture (Qi et al. 2017, as in the `pointnet.pytorch` classifier that SpareNet ships and R2DM's
//! FPD uses):
//!
//! * optional input transform (T-Net, `feat.stn.*`): shared MLP 3 → 64 → 128 → 1024, max-pool,
//!   FC 1024 → 512 → 256 → 9, plus the identity, giving a 3x3 matrix applied to every point;
//! * shared per-point MLP (`feat.conv{i}`, 1x1 convolutions) `3 → mlp[0] → ... → D`, each followed by
//!   BatchNorm (`feat.bn{i}`, when `batch_norm`) and ReLU, except the last layer (no ReLU, as the
//!   original);
//! * max-pool over the points: the global feature `[B, D]`;
//! * classification head (`fc{i}` + `bn{i}` + ReLU, then the last `fc` to the classes).
//!
//! Points are scaled by [`PointNetConfig::point_scale`] (1/80, the R2DM protocol) before the network.
//!
//! # Weight names
//!
//! The PyTorch state dict of `PointNetCls` minus `num_batches_tracked`: `feat.conv1.weight [64, 3, 1]`
//! (Conv1d layout), `feat.conv1.bias`, `feat.bn1.{weight,bias,running_mean,running_var}`, ...,
//! `feat.stn.conv1..3`, `feat.stn.fc1..3`, `feat.stn.bn1..5`, `fc1.weight [512, 1024]`, `fc1.bias`,
//! `bn1.*`, `fc2`, `bn2`, `fc3`.
//!
//! # Features for FPD
//!
//! [`PointNet::features`]: the max-pooled global feature `[B, D]` (1024 for
//! [`PointNetConfig::sparenet`], 256 for [`PointNetConfig::small`]). R2DM concatenates the global
//! feature with the classifier's hidden activations and logits (1808 values); Veila uses the global
//! feature alone, so FPD values are not comparable with published ones even with official weights.
//!
//! Max-pooling makes the feature invariant to the order of the points and to duplicated points, which
//! [`PointNet::prepare`] uses to pad small scans.

use std::collections::BTreeMap;
use std::path::Path;

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{BatchNorm, BatchNormConfig, Init, ModuleT, VarBuilder};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result, shape_err};

/// Upper bounds on a [`PointNetConfig`] (`pointnet.json`; checked by
/// [`PointNetConfig::validate`]), about 30 to 50 times the SpareNet classifier's sizes, so that no
/// config from a file can ask for an absurd network.
///
/// Width of a layer, each of `mlp` and `head` (SpareNet: at most 1024).
pub const MAX_WIDTH: usize = 32_768;
/// Layers of the shared MLP or of the head, the length of `mlp` and of `head` (at most 3).
pub const MAX_LAYERS: usize = 64;
/// Output classes, `num_classes` (SpareNet: 16, the project's: 23).
pub const MAX_CLASSES: usize = 1024;
/// Points per scan, `num_points` (the project's: 2048; a scan of up to this many points is
/// padded to it).
pub const MAX_POINTS: usize = 1 << 22;

/// Configuration of a [`PointNet`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointNetConfig {
    /// Short name, printed in metric protocols (e.g. `pointnet-small`).
    pub name: String,
    /// Widths of the shared per-point MLP after the 3 input coordinates; the last is the feature width.
    pub mlp: Vec<usize>,
    /// Hidden widths of the classification head.
    pub head: Vec<usize>,
    /// Output classes of the head.
    pub num_classes: usize,
    /// BatchNorm after every layer but the last of the MLP and the head (the original design).
    pub batch_norm: bool,
    /// The input transform (T-Net) of the original PointNet (requires `batch_norm`).
    pub input_transform: bool,
    /// Factor applied to the coordinates (metres) before the network: 1/80 in the R2DM protocol.
    pub point_scale: f32,
    /// Points per scan fed to the net: larger scans are subsampled (seeded, without replacement),
    /// smaller ones padded by repeating points (exact for a max-pool). `None`: every point.
    pub num_points: Option<usize>,
    /// Seed of the subsampling.
    pub sample_seed: u64,
    /// BatchNorm epsilon.
    pub bn_eps: f64,
    /// BatchNorm running-statistics momentum during training.
    pub bn_momentum: f64,
}

impl PointNetConfig {
    /// The PointNet classifier of `pointnet.pytorch` as trained by SpareNet on ShapeNet (16 classes),
    /// used by R2DM's FPD: input T-Net, MLP 3 → 64 → 128 → 1024 with BatchNorm, head 512 → 256 → 16.
    /// Every point of a scan is used (`num_points: None`).
    pub fn sparenet() -> Self {
        PointNetConfig {
            name: "pointnet-sparenet".into(),
            mlp: vec![64, 128, 1024],
            head: vec![512, 256],
            num_classes: 16,
            batch_norm: true,
            input_transform: true,
            point_scale: 1.0 / 80.0,
            num_points: None,
            sample_seed: 0,
            bn_eps: 1e-5,
            bn_momentum: 0.1,
        }
    }

    /// The project-trained net: no T-Net, no normalisation layers, MLP 3 → 64 → 128 → 256, head
    /// 256 → 128 → 23 (see `cargo xtask train-feature-nets`), 2048 points per scan.
    pub fn small() -> Self {
        PointNetConfig {
            name: "pointnet-small".into(),
            mlp: vec![64, 128, 256],
            head: vec![128],
            num_classes: 23,
            batch_norm: false,
            input_transform: false,
            point_scale: 1.0 / 80.0,
            num_points: Some(2048),
            sample_seed: 0,
            bn_eps: 1e-5,
            bn_momentum: 0.1,
        }
    }

    /// Width of the FPD feature (the last MLP width).
    pub fn feature_dim(&self) -> usize {
        self.mlp.last().copied().unwrap_or(3)
    }

    /// Checks every field (names the offending one).
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::Config(format!("pointnet {}: {m}", self.name)));
        if self.mlp.is_empty() || self.mlp.contains(&0) {
            return bad(format!(
                "mlp widths must be non-empty and > 0, got {:?}",
                self.mlp
            ));
        }
        if self.head.contains(&0) {
            return bad(format!("head widths must be > 0, got {:?}", self.head));
        }
        if self.num_classes < 2 {
            return bad(format!(
                "num_classes must be >= 2, got {}",
                self.num_classes
            ));
        }
        if self.input_transform && !self.batch_norm {
            return bad("input_transform (T-Net) requires batch_norm".into());
        }
        if !(self.point_scale.is_finite() && self.point_scale > 0.0) {
            return bad(format!("point_scale {} must be > 0", self.point_scale));
        }
        if self.num_points == Some(0) {
            return bad("num_points must be > 0 (or null for every point)".into());
        }
        if !(self.bn_eps.is_finite() && self.bn_eps > 0.0) {
            return bad(format!("bn_eps {} must be > 0", self.bn_eps));
        }
        if !(self.bn_momentum.is_finite() && self.bn_momentum > 0.0 && self.bn_momentum <= 1.0) {
            return bad(format!(
                "bn_momentum {} must be in (0, 1]",
                self.bn_momentum
            ));
        }
        self.validate_bounds()
    }

    /// Every size within its `MAX_*` bound of this module (the message names the field).
    fn validate_bounds(&self) -> Result<()> {
        let check = |field: &str, value: usize, max: usize| {
            crate::config::check_max(&format!("pointnet {}: {field}", self.name), value, max)
        };
        for (field, widths) in [("mlp", &self.mlp), ("head", &self.head)] {
            check(&format!("{field} (layers)"), widths.len(), MAX_LAYERS)?;
            for (i, w) in widths.iter().enumerate() {
                check(&format!("{field}[{i}]"), *w, MAX_WIDTH)?;
            }
        }
        check("num_classes", self.num_classes, MAX_CLASSES)?;
        check("num_points", self.num_points.unwrap_or(0), MAX_POINTS)
    }
}

/// A shared per-point layer (1x1 Conv1d, weight `[out, in, 1]`) or a fully connected one
/// (weight `[out, in]`), with optional BatchNorm.
#[derive(Debug, Clone)]
struct Layer {
    weight: Tensor,
    bias: Tensor,
    bn: Option<(String, BatchNorm)>,
}

fn bn_cfg(eps: f64, momentum: f64) -> BatchNormConfig {
    BatchNormConfig {
        eps,
        remove_mean: true,
        affine: true,
        momentum,
    }
}

impl Layer {
    /// `conv`: Conv1d layout; otherwise Linear layout.
    #[allow(clippy::too_many_arguments)]
    fn new(
        in_c: usize,
        out_c: usize,
        conv: bool,
        bn: bool,
        cfg: &PointNetConfig,
        vb: &VarBuilder<'_>,
        name: &str,
        bn_name: &str,
    ) -> Result<Self> {
        let lvb = vb.pp(name);
        let init = candle_nn::init::DEFAULT_KAIMING_NORMAL;
        let weight = if conv {
            lvb.get_with_hints((out_c, in_c, 1), "weight", init)?
        } else {
            lvb.get_with_hints((out_c, in_c), "weight", init)?
        };
        let bound = 1.0 / (in_c as f64).sqrt();
        let bias = lvb.get_with_hints(
            out_c,
            "bias",
            Init::Uniform {
                lo: -bound,
                up: bound,
            },
        )?;
        let bn = if bn {
            let full = if vb.prefix().is_empty() {
                bn_name.to_string()
            } else {
                format!("{}.{bn_name}", vb.prefix())
            };
            Some((
                full,
                candle_nn::batch_norm(out_c, bn_cfg(cfg.bn_eps, cfg.bn_momentum), vb.pp(bn_name))?,
            ))
        } else {
            None
        };
        Ok(Self { weight, bias, bn })
    }

    /// `[B, in, N] -> [B, out, N]` (per point) or `[B, in] -> [B, out]`.
    fn forward(&self, x: &Tensor, relu: bool, train: bool) -> Result<Tensor> {
        let out_c = self.weight.dim(0)?;
        let y = if x.rank() == 3 {
            let in_c = x.dim(1)?;
            self.weight
                .reshape((1, out_c, in_c))?
                .broadcast_matmul(x)?
                .broadcast_add(&self.bias.reshape((1, out_c, 1))?)?
        } else {
            let w = self.weight.reshape((out_c, ()))?;
            x.matmul(&w.t()?)?
                .broadcast_add(&self.bias.reshape((1, out_c))?)?
        };
        let y = match &self.bn {
            Some((_, bn)) => bn.forward_t(&y, train)?,
            None => y,
        };
        Ok(if relu { y.relu()? } else { y })
    }
}

#[derive(Debug, Clone)]
struct TNet {
    convs: Vec<Layer>,
    fcs: Vec<Layer>,
}

impl TNet {
    fn forward(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let mut h = x.clone();
        for c in &self.convs {
            h = c.forward(&h, true, train)?;
        }
        let mut h = h.max(D::Minus1)?;
        let last = self.fcs.len() - 1;
        for (i, f) in self.fcs.iter().enumerate() {
            h = f.forward(&h, i < last, train)?;
        }
        let b = h.dim(0)?;
        let eye = Tensor::eye(3, h.dtype(), h.device())?.reshape((1, 9))?;
        Ok(h.broadcast_add(&eye)?.reshape((b, 3, 3))?)
    }
}

/// Output of [`PointNet::forward_t`].
#[derive(Debug, Clone)]
pub struct PointNetOutput {
    /// Max-pooled global feature `[B, D]` (the FPD feature).
    pub global: Tensor,
    /// Class logits `[B, K]`.
    pub logits: Tensor,
}

/// The PointNet classifier (see the module docs).
#[derive(Debug, Clone)]
pub struct PointNet {
    cfg: PointNetConfig,
    tnet: Option<TNet>,
    mlp: Vec<Layer>,
    head: Vec<Layer>,
}

impl PointNet {
    /// Builds the net of `cfg` with its weights under `vb` (names in the module docs).
    pub fn new(cfg: &PointNetConfig, vb: VarBuilder<'_>) -> Result<Self> {
        cfg.validate()?;
        let fvb = vb.pp("feat");
        let tnet = if cfg.input_transform {
            let svb = fvb.pp("stn");
            let widths = [3, 64, 128, 1024];
            let convs = (0..3)
                .map(|i| {
                    Layer::new(
                        widths[i],
                        widths[i + 1],
                        true,
                        true,
                        cfg,
                        &svb,
                        &format!("conv{}", i + 1),
                        &format!("bn{}", i + 1),
                    )
                })
                .collect::<Result<Vec<_>>>()?;
            let fw = [1024, 512, 256, 9];
            let fcs = (0..3)
                .map(|i| {
                    Layer::new(
                        fw[i],
                        fw[i + 1],
                        false,
                        i < 2,
                        cfg,
                        &svb,
                        &format!("fc{}", i + 1),
                        &format!("bn{}", i + 4),
                    )
                })
                .collect::<Result<Vec<_>>>()?;
            Some(TNet { convs, fcs })
        } else {
            None
        };
        let mut mlp = Vec::with_capacity(cfg.mlp.len());
        let mut in_c = 3;
        for (i, &w) in cfg.mlp.iter().enumerate() {
            mlp.push(Layer::new(
                in_c,
                w,
                true,
                cfg.batch_norm,
                cfg,
                &fvb,
                &format!("conv{}", i + 1),
                &format!("bn{}", i + 1),
            )?);
            in_c = w;
        }
        let mut head = Vec::with_capacity(cfg.head.len() + 1);
        for (i, &w) in cfg.head.iter().chain([&cfg.num_classes]).enumerate() {
            let hidden = i < cfg.head.len();
            head.push(Layer::new(
                in_c,
                w,
                false,
                cfg.batch_norm && hidden,
                cfg,
                &vb,
                &format!("fc{}", i + 1),
                &format!("bn{}", i + 1),
            )?);
            in_c = w;
        }
        Ok(Self {
            cfg: cfg.clone(),
            tnet,
            mlp,
            head,
        })
    }

    /// The config the net was built from.
    pub fn config(&self) -> &PointNetConfig {
        &self.cfg
    }

    /// Global feature and logits of scaled points `x: [B, 3, N]` (see [`PointNet::prepare`]). `train`
    /// selects batch statistics for the BatchNorm layers (and updates their running statistics).
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<PointNetOutput> {
        match x.dims() {
            [b, 3, n] if *b > 0 && *n > 0 => {}
            d => return Err(shape_err("pointnet input", "[B, 3, N]", d)),
        }
        let mut h = match &self.tnet {
            Some(t) => {
                let trans = t.forward(x, train)?;
                x.transpose(1, 2)?
                    .contiguous()?
                    .matmul(&trans)?
                    .transpose(1, 2)?
                    .contiguous()?
            }
            None => x.clone(),
        };
        let last = self.mlp.len() - 1;
        for (i, l) in self.mlp.iter().enumerate() {
            h = l.forward(&h, i < last, train)?;
        }
        let global = h.max(D::Minus1)?;
        let mut z = global.clone();
        let last = self.head.len() - 1;
        for (i, l) in self.head.iter().enumerate() {
            z = l.forward(&z, i < last, train)?;
        }
        Ok(PointNetOutput { global, logits: z })
    }

    /// Inference-mode [`PointNet::forward_t`].
    pub fn forward(&self, x: &Tensor) -> Result<PointNetOutput> {
        self.forward_t(x, false)
    }

    /// The FPD feature `[B, D]`: the max-pooled global feature, inference mode.
    pub fn features(&self, x: &Tensor) -> Result<Tensor> {
        Ok(self.forward_t(x, false)?.global)
    }

    /// Scaled coordinates `[3, N]` (channel-major) of a scan, ready for [`PointNet::forward_t`]:
    /// non-finite points dropped, then subsampled or padded to `num_points` when set (see
    /// [`PointNetConfig::num_points`]). Fails on a scan without finite points.
    pub fn prepare(cfg: &PointNetConfig, points: &[Vec3]) -> Result<Vec<f32>> {
        let finite: Vec<Vec3> = points.iter().copied().filter(|p| p.is_finite()).collect();
        if finite.is_empty() {
            return Err(Error::Input(format!(
                "pointnet input: no finite point among {}",
                points.len()
            )));
        }
        let chosen: Vec<Vec3> = match cfg.num_points {
            None => finite,
            Some(m) if finite.len() > m => {
                // partial Fisher-Yates: the first m entries become a uniform sample without replacement
                let mut idx: Vec<usize> = (0..finite.len()).collect();
                let mut rng = ChaCha8Rng::seed_from_u64(cfg.sample_seed);
                for i in 0..m {
                    let j = rng.random_range(i..idx.len());
                    idx.swap(i, j);
                }
                idx[..m].iter().map(|&i| finite[i]).collect()
            }
            Some(m) => (0..m).map(|i| finite[i % finite.len()]).collect(),
        };
        let n = chosen.len();
        let s = cfg.point_scale;
        let mut out = vec![0f32; 3 * n];
        for (k, p) in chosen.iter().enumerate() {
            out[k] = p.x * s;
            out[n + k] = p.y * s;
            out[2 * n + k] = p.z * s;
        }
        Ok(out)
    }

    /// The BatchNorm running statistics by tensor name (see [`super::RangeNet::batch_norm_stats`]).
    pub fn batch_norm_stats(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::new();
        let layers = self
            .tnet
            .iter()
            .flat_map(|t| t.convs.iter().chain(&t.fcs))
            .chain(&self.mlp)
            .chain(&self.head);
        for l in layers {
            if let Some((name, bn)) = &l.bn {
                out.push((format!("{name}.running_mean"), bn.running_mean().clone()));
                out.push((format!("{name}.running_var"), bn.running_var().clone()));
            }
        }
        out
    }

    /// Every tensor the net of `cfg` has, by name, with its shape.
    pub fn expected_tensors(cfg: &PointNetConfig) -> Result<BTreeMap<String, Vec<usize>>> {
        crate::weights::record_tensors(|vb| PointNet::new(cfg, vb).map(|_| ()))
    }

    /// Number of scalar parameters (BatchNorm running statistics included).
    pub fn parameter_count(cfg: &PointNetConfig) -> Result<usize> {
        Ok(Self::expected_tensors(cfg)?
            .values()
            .map(|s| s.iter().product::<usize>())
            .sum())
    }

    /// Loads a safetensors file holding exactly the tensors of `cfg`'s net; a mismatch fails with
    /// [`Error::CheckpointMismatch`].
    pub fn load(path: &Path, cfg: &PointNetConfig, device: &Device) -> Result<Self> {
        cfg.validate()?;
        crate::weights::load_checked(path, DType::F32, device, |_| true, |vb| Self::new(cfg, vb))
    }

    /// [`PointNet::load`] from the bytes of a safetensors file (`path` names it in errors).
    pub fn from_safetensors(
        bytes: &[u8],
        path: &Path,
        cfg: &PointNetConfig,
        device: &Device,
    ) -> Result<Self> {
        cfg.validate()?;
        crate::weights::load_checked_bytes(
            bytes,
            path,
            DType::F32,
            device,
            |_| true,
            |vb| Self::new(cfg, vb),
        )
    }
}
