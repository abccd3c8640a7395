//! A RangeNet++-style DarkNet encoder over 5-channel range images (the FRD feature network).
//!
//! Architecture (after RangeNet++'s `darknet` backbone, Milioto et al. 2019):
//!
//! * stem: 3x3 conv (no bias) → BatchNorm → LeakyReLU(0.1), full resolution;
//! * stages `enc1..encS`: a 3x3 conv with stride **(1, 2)** (RangeNet++ halves only the azimuth axis,
//!   never the beams) → BatchNorm → LeakyReLU, then `blocks` residual blocks, each
//!   `x + LeakyReLU(BN(conv3x3(LeakyReLU(BN(conv1x1(x))))))` with the 1x1 conv squeezing to the stage's
//!   input width;
//! * (project-trained nets only) a light per-pixel semantic head used for training: a 1x1 lateral conv
//!   per level (stem and every stage), nearest upsampling along the azimuth to full width, sum,
//!   LeakyReLU, 1x1 classifier.
//!
//! Convolutions zero-pad both axes (as RangeNet++; converted official weights then see what they were
//! trained on). Stride-1 convolutions run through [`crate::ops::conv2d_zero_pad`] and the stride-(1, 2)
//! ones through an explicit im2col with separate row / column strides ([`conv2d_strided`]), so the
//! backward pass stays fast on the CPU.
//!
//! # Input
//!
//! `[B, 5, H, W]`: range (m), x, y, z (m, LiDAR frame) and remission (`[0, 1]`), each normalised with
//! RangeNet++'s SemanticKITTI means / standard deviations ([`RANGENET_MEAN`], [`RANGENET_STD`]) and then
//! multiplied by the validity mask (empty pixels are exactly 0). [`RangeNetInput`] builds this from a
//! point cloud or a range image.
//!
//! # Weight names
//!
//! Names follow the PyTorch state dict of RangeNet++'s `Backbone` (`backbone` file of the official
//! `darknet21` / `darknet53*` archives), without `num_batches_tracked`:
//!
//! ```text
//! conv1.weight [32, 5, 3, 3]          bn1.{weight, bias, running_mean, running_var} [32]
//! enc1.conv.weight [64, 32, 3, 3]     enc1.bn.{weight, bias, running_mean, running_var} [64]
//! enc1.residual_0.conv1.weight [32, 64, 1, 1]   enc1.residual_0.bn1.* [32]
//! enc1.residual_0.conv2.weight [64, 32, 3, 3]   enc1.residual_0.bn2.* [64]
//! ...                                           enc5.residual_{i}.* for darknet53's 4 blocks
//! ```
//!
//! The semantic head (project-trained nets) lives under `head.lateral{i}.{weight,bias}` and
//! `head.classifier.{weight,bias}`; the official decoder (`decoder.*`) and head (`head.*` of the
//! official segmentation model) are not part of this encoder and must be dropped by the converter.
//!
//! BatchNorm runs in inference form with its running statistics (`candle_nn::BatchNorm`, eps `1e-5`).
//!
//! # Features for FRD
//!
//! [`RangeNet::features`]: the global average (over rows and columns) of the deepest encoder map,
//! `[B, C_last]` (1024 for DarkNet, 128 for [`RangeNetConfig::small`]). This is **not** R2DM's FRD
//! feature (4096 randomly chosen values of the last decoder stage's `32 x H x W` map); Veila's FRD
//! values are therefore not comparable with published ones even with official weights.

use std::collections::BTreeMap;
use std::path::Path;

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{BatchNorm, BatchNormConfig, Init, ModuleT, VarBuilder};
use glam::Vec3;
use serde::{Deserialize, Serialize};
use veila_geom::{LidarSensor, OutOfFov, ProjectionOptions, Projector, RangeImage, RayTable};

use crate::error::{Error, Result, shape_err};

/// Number of input channels: range, x, y, z, remission.
pub const IN_CHANNELS: usize = 5;
/// RangeNet++'s SemanticKITTI input means (range, x, y, z, remission), as used by R2DM's FRD.
pub const RANGENET_MEAN: [f32; 5] = [12.12, 10.88, 0.23, -1.04, 0.21];
/// RangeNet++'s SemanticKITTI input standard deviations (range, x, y, z, remission).
pub const RANGENET_STD: [f32; 5] = [12.32, 11.47, 6.91, 0.86, 0.16];

/// Upper bounds on a [`RangeNetConfig`] (`rangenet.json`; checked by
/// [`RangeNetConfig::validate`]), about 50 times DarkNet-53's sizes, so that no config from a
/// file can ask for an absurd network.
///
/// Channels of the stem conv, `stem_channels` (DarkNet: 32).
pub const MAX_STEM_CHANNELS: usize = 2048;
/// Encoder stages, the length of `stages` (5; each halves the width, so more than about 20 leave
/// no column of even the widest sensor).
pub const MAX_STAGES: usize = 32;
/// Channels of a stage, `stages[i].channels` (DarkNet: at most 1024).
pub const MAX_STAGE_CHANNELS: usize = 32_768;
/// Residual blocks of a stage, `stages[i].blocks` (DarkNet-53: at most 8).
pub const MAX_STAGE_BLOCKS: usize = 512;
/// Classes of the semantic head, `num_classes` (20).
pub const MAX_CLASSES: usize = 1024;
/// Channels of the semantic head, `head_channels` (32).
pub const MAX_HEAD_CHANNELS: usize = 2048;

/// One encoder stage: a stride-(1, 2) 3x3 conv to `channels`, then `blocks` residual blocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct RangeStage {
    /// Output channels of the stage.
    pub channels: usize,
    /// Residual blocks after the downsampling conv.
    pub blocks: usize,
}

/// Configuration of a [`RangeNet`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RangeNetConfig {
    /// Short name, printed in metric protocols (e.g. `rangenet-small`).
    pub name: String,
    /// Channels of the full-resolution stem conv.
    pub stem_channels: usize,
    /// Encoder stages (`enc1`, `enc2`, ...), each halving the width.
    pub stages: Vec<RangeStage>,
    /// Classes of the per-pixel semantic head (`None`: encoder only, e.g. converted official weights).
    pub num_classes: Option<usize>,
    /// Channels of the semantic head's lateral convs (ignored without a head).
    pub head_channels: usize,
    /// Per-channel input means (range, x, y, z, remission).
    pub input_mean: [f32; 5],
    /// Per-channel input standard deviations.
    pub input_std: [f32; 5],
    /// The sensor whose range images the net reads: point clouds are projected with it (rows clamped
    /// to the edge rows, nearest point wins), so `rows x cols` is the input size.
    pub sensor: LidarSensor,
    /// Negative slope of the LeakyReLUs (0.1 in RangeNet++).
    pub leaky_slope: f64,
    /// BatchNorm epsilon (1e-5, PyTorch's default).
    pub bn_eps: f64,
    /// BatchNorm running-statistics momentum during training (PyTorch convention).
    pub bn_momentum: f64,
}

impl RangeNetConfig {
    fn darknet(name: &str, blocks: [usize; 5]) -> Self {
        let widths = [64, 128, 256, 512, 1024];
        RangeNetConfig {
            name: name.to_string(),
            stem_channels: 32,
            stages: widths
                .iter()
                .zip(blocks)
                .map(|(&channels, blocks)| RangeStage { channels, blocks })
                .collect(),
            num_classes: None,
            head_channels: 32,
            input_mean: RANGENET_MEAN,
            input_std: RANGENET_STD,
            sensor: LidarSensor::hdl64e(),
            leaky_slope: 0.1,
            bn_eps: 1e-5,
            bn_momentum: 0.01,
        }
    }

    /// RangeNet++ DarkNet-21 backbone (residual blocks 1, 1, 2, 2, 1; widths 32 → 64 → ... → 1024),
    /// encoder only, 64 x 1024 HDL-64E input.
    pub fn darknet21() -> Self {
        Self::darknet("rangenet-darknet21", [1, 1, 2, 2, 1])
    }

    /// RangeNet++ DarkNet-53 backbone (residual blocks 1, 2, 8, 8, 4), encoder only, 64 x 1024 input
    /// (the `darknet53-1024` archive; set `sensor.cols = 2048` for `darknet53`).
    pub fn darknet53() -> Self {
        Self::darknet("rangenet-darknet53", [1, 2, 8, 8, 4])
    }

    /// The project-trained net: stem 16, five one-block stages 24 → 32 → 48 → 64 → 128, a 20-class
    /// SemanticKITTI head, 32 x 512 input with the HDL-64E field of view (every other beam row: two
    /// beams share a row, the nearest return wins). About 0.28 M parameters and 0.37 GMAC per scan, so
    /// it trains in minutes on a laptop CPU.
    pub fn small() -> Self {
        RangeNetConfig {
            name: "rangenet-small".into(),
            stem_channels: 16,
            stages: [24, 32, 48, 64, 128]
                .iter()
                .map(|&channels| RangeStage {
                    channels,
                    blocks: 1,
                })
                .collect(),
            num_classes: Some(20),
            head_channels: 32,
            input_mean: RANGENET_MEAN,
            input_std: RANGENET_STD,
            sensor: LidarSensor {
                rows: 32,
                cols: 512,
                ..LidarSensor::hdl64e()
            },
            leaky_slope: 0.1,
            bn_eps: 1e-5,
            bn_momentum: 0.1,
        }
    }

    /// Width of the FRD feature vector (channels of the last stage).
    pub fn feature_dim(&self) -> usize {
        self.stages
            .last()
            .map(|s| s.channels)
            .unwrap_or(self.stem_channels)
    }

    /// Checks every field (names the offending one).
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::Config(format!("rangenet {}: {m}", self.name)));
        if self.stem_channels == 0 {
            return bad("stem_channels must be > 0".into());
        }
        if self.stages.is_empty() {
            return bad("stages must not be empty".into());
        }
        if let Some(i) = self.stages.iter().position(|s| s.channels == 0) {
            return bad(format!("stage {} has 0 channels", i + 1));
        }
        if let Some(k) = self.num_classes {
            if k < 2 {
                return bad(format!("num_classes must be >= 2, got {k}"));
            }
            if self.head_channels == 0 {
                return bad("head_channels must be > 0".into());
            }
        }
        self.validate_bounds()?;
        for c in 0..IN_CHANNELS {
            let (m, s) = (self.input_mean[c], self.input_std[c]);
            if !(m.is_finite() && s.is_finite() && s > 0.0) {
                return bad(format!(
                    "input channel {c}: mean {m} and std {s} must be finite, std > 0"
                ));
            }
        }
        if !(self.leaky_slope.is_finite() && (0.0..1.0).contains(&self.leaky_slope)) {
            return bad(format!(
                "leaky_slope {} must be in [0, 1)",
                self.leaky_slope
            ));
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
        self.sensor.validate()?;
        Ok(())
    }
}

impl RangeNetConfig {
    /// Every size within its `MAX_*` bound of this module (the message names the field).
    fn validate_bounds(&self) -> Result<()> {
        let check = |field: &str, value: usize, max: usize| {
            crate::config::check_max(&format!("rangenet {}: {field}", self.name), value, max)
        };
        check("stem_channels", self.stem_channels, MAX_STEM_CHANNELS)?;
        check("stages (count)", self.stages.len(), MAX_STAGES)?;
        for (i, st) in self.stages.iter().enumerate() {
            check(
                &format!("stages[{i}].channels"),
                st.channels,
                MAX_STAGE_CHANNELS,
            )?;
            check(&format!("stages[{i}].blocks"), st.blocks, MAX_STAGE_BLOCKS)?;
        }
        check("head_channels", self.head_channels, MAX_HEAD_CHANNELS)?;
        check("num_classes", self.num_classes.unwrap_or(0), MAX_CLASSES)
    }
}

/// A zero-padded `k x k` convolution without bias with separate row and column strides
/// (`x: [B, C, H, W]`, `weight: [out, C, k, k]`), output
/// `[B, out, (H + 2 pad - k) / stride_h + 1, (W + 2 pad - k) / stride_w + 1]`.
///
/// Runs as [`crate::ops::conv2d_padded_hw`]: an explicit im2col whose backward pass is slices and
/// matrix products (fast on the CPU).
pub fn conv2d_strided(
    x: &Tensor,
    weight: &Tensor,
    pad: usize,
    stride_h: usize,
    stride_w: usize,
) -> Result<Tensor> {
    let xp = if pad > 0 {
        x.pad_with_zeros(2, pad, pad)?.pad_with_zeros(3, pad, pad)?
    } else {
        x.clone()
    };
    crate::ops::conv2d_padded_hw(&xp, weight, None, stride_h, stride_w)
}

/// `max(x, slope x)`.
fn leaky(x: &Tensor, slope: f64) -> Result<Tensor> {
    Ok(x.maximum(&x.affine(slope, 0.0)?)?)
}

fn batch_norm(c: usize, cfg: &RangeNetConfig, vb: VarBuilder<'_>) -> Result<BatchNorm> {
    let bn_cfg = BatchNormConfig {
        eps: cfg.bn_eps,
        remove_mean: true,
        affine: true,
        momentum: cfg.bn_momentum,
    };
    Ok(candle_nn::batch_norm(c, bn_cfg, vb)?)
}

/// Conv (no bias) + BatchNorm + LeakyReLU.
#[derive(Debug, Clone)]
struct ConvBn {
    weight: Tensor,
    bn: BatchNorm,
    bn_name: String,
    pad: usize,
    stride_w: usize,
    slope: f64,
}

impl ConvBn {
    #[allow(clippy::too_many_arguments)]
    fn new(
        in_c: usize,
        out_c: usize,
        k: usize,
        stride_w: usize,
        cfg: &RangeNetConfig,
        vb: &VarBuilder<'_>,
        conv_name: &str,
        bn_name: &str,
    ) -> Result<Self> {
        let weight = vb.pp(conv_name).get_with_hints(
            (out_c, in_c, k, k),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let bn = batch_norm(out_c, cfg, vb.pp(bn_name))?;
        let full = if vb.prefix().is_empty() {
            bn_name.to_string()
        } else {
            format!("{}.{bn_name}", vb.prefix())
        };
        Ok(Self {
            weight,
            bn,
            bn_name: full,
            pad: k / 2,
            stride_w,
            slope: cfg.leaky_slope,
        })
    }

    fn forward(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let y = if self.weight.dim(2)? == 1 && self.stride_w == 1 {
            let (b, c, h, w) = x.dims4()?;
            let out_c = self.weight.dim(0)?;
            self.weight
                .reshape((1, out_c, c))?
                .broadcast_matmul(&x.reshape((b, c, h * w))?)?
                .reshape((b, out_c, h, w))?
        } else {
            conv2d_strided(x, &self.weight, self.pad, 1, self.stride_w)?
        };
        leaky(&self.bn.forward_t(&y, train)?, self.slope)
    }
}

#[derive(Debug, Clone)]
struct Residual {
    a: ConvBn,
    b: ConvBn,
}

#[derive(Debug, Clone)]
struct Stage {
    down: ConvBn,
    blocks: Vec<Residual>,
}

#[derive(Debug, Clone)]
struct SegHead {
    laterals: Vec<(Tensor, Tensor)>,
    classifier: (Tensor, Tensor),
}

fn linear_1x1(x: &Tensor, w: &Tensor, b: &Tensor) -> Result<Tensor> {
    let (bs, c, h, wd) = x.dims4()?;
    let out_c = w.dim(0)?;
    Ok(w.reshape((1, out_c, c))?
        .broadcast_matmul(&x.reshape((bs, c, h * wd))?)?
        .broadcast_add(&b.reshape((1, out_c, 1))?)?
        .reshape((bs, out_c, h, wd))?)
}

fn conv1x1_params(
    in_c: usize,
    out_c: usize,
    vb: VarBuilder<'_>,
) -> candle_core::Result<(Tensor, Tensor)> {
    let w = vb.get_with_hints(
        (out_c, in_c, 1, 1),
        "weight",
        candle_nn::init::DEFAULT_KAIMING_NORMAL,
    )?;
    let bound = 1.0 / (in_c as f64).sqrt();
    let b = vb.get_with_hints(
        out_c,
        "bias",
        Init::Uniform {
            lo: -bound,
            up: bound,
        },
    )?;
    Ok((w, b))
}

/// Nearest upsampling along the width by `factor`, cropped to `width` columns.
fn upsample_w(x: &Tensor, factor: usize, width: usize) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    let y = if factor == 1 {
        x.clone()
    } else {
        x.reshape((b, c, h, w, 1))?
            .broadcast_as((b, c, h, w, factor))?
            .reshape((b, c, h, w * factor))?
    };
    let have = y.dim(3)?;
    Ok(if have > width {
        y.narrow(3, 0, width)?
    } else {
        y
    })
}

/// The RangeNet++-style encoder (see the module docs).
#[derive(Debug, Clone)]
pub struct RangeNet {
    cfg: RangeNetConfig,
    stem: ConvBn,
    stages: Vec<Stage>,
    head: Option<SegHead>,
}

impl RangeNet {
    /// Builds the net of `cfg` with its weights under `vb` (names in the module docs).
    pub fn new(cfg: &RangeNetConfig, vb: VarBuilder<'_>) -> Result<Self> {
        cfg.validate()?;
        let stem = ConvBn::new(
            IN_CHANNELS,
            cfg.stem_channels,
            3,
            1,
            cfg,
            &vb,
            "conv1",
            "bn1",
        )?;
        let mut in_c = cfg.stem_channels;
        let mut stages = Vec::with_capacity(cfg.stages.len());
        for (i, s) in cfg.stages.iter().enumerate() {
            let svb = vb.pp(format!("enc{}", i + 1));
            let down = ConvBn::new(in_c, s.channels, 3, 2, cfg, &svb, "conv", "bn")?;
            let mut blocks = Vec::with_capacity(s.blocks);
            for j in 0..s.blocks {
                let rvb = svb.pp(format!("residual_{j}"));
                blocks.push(Residual {
                    a: ConvBn::new(s.channels, in_c, 1, 1, cfg, &rvb, "conv1", "bn1")?,
                    b: ConvBn::new(in_c, s.channels, 3, 1, cfg, &rvb, "conv2", "bn2")?,
                });
            }
            stages.push(Stage { down, blocks });
            in_c = s.channels;
        }
        let head = match cfg.num_classes {
            None => None,
            Some(k) => {
                let hvb = vb.pp("head");
                let mut widths = vec![cfg.stem_channels];
                widths.extend(cfg.stages.iter().map(|s| s.channels));
                let laterals = widths
                    .iter()
                    .enumerate()
                    .map(|(i, &c)| {
                        conv1x1_params(c, cfg.head_channels, hvb.pp(format!("lateral{i}")))
                    })
                    .collect::<candle_core::Result<Vec<_>>>()?;
                let classifier = conv1x1_params(cfg.head_channels, k, hvb.pp("classifier"))?;
                Some(SegHead {
                    laterals,
                    classifier,
                })
            }
        };
        Ok(Self {
            cfg: cfg.clone(),
            stem,
            stages,
            head,
        })
    }

    /// The config the net was built from.
    pub fn config(&self) -> &RangeNetConfig {
        &self.cfg
    }

    fn check_input(&self, x: &Tensor) -> Result<()> {
        match x.dims() {
            [b, c, h, w] if *b > 0 && *c == IN_CHANNELS && *h > 0 && *w > 0 => Ok(()),
            d => Err(shape_err("rangenet input", "[B, 5, H, W]", d)),
        }
    }

    /// The feature maps of every level: the stem's `[B, C0, H, W]`, then each stage's
    /// `[B, C_i, H, ceil(W / 2^i)]`. `train` selects batch statistics (and updates the BatchNorm running
    /// statistics) instead of the running statistics.
    pub fn encode(&self, x: &Tensor, train: bool) -> Result<Vec<Tensor>> {
        self.check_input(x)?;
        let mut h = self.stem.forward(x, train)?;
        let mut levels = Vec::with_capacity(self.stages.len() + 1);
        levels.push(h.clone());
        for stage in &self.stages {
            h = stage.down.forward(&h, train)?;
            for blk in &stage.blocks {
                let r = blk.b.forward(&blk.a.forward(&h, train)?, train)?;
                h = (r + &h)?;
            }
            levels.push(h.clone());
        }
        Ok(levels)
    }

    /// Per-pixel class logits `[B, K, H, W]` (nets with a semantic head only).
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let Some(head) = &self.head else {
            return Err(Error::Config(format!(
                "rangenet {}: no semantic head (num_classes is None)",
                self.cfg.name
            )));
        };
        let width = x.dim(3)?;
        let levels = self.encode(x, train)?;
        let mut sum: Option<Tensor> = None;
        for (i, (f, (w, b))) in levels.iter().zip(&head.laterals).enumerate() {
            let factor = if i == 0 { 1 } else { 1usize << i };
            let y = upsample_w(&linear_1x1(f, w, b)?, factor, width)?;
            sum = Some(match sum {
                None => y,
                Some(s) => (s + y)?,
            });
        }
        let sum = sum.ok_or_else(|| Error::Config("rangenet: no levels".into()))?;
        let h = leaky(&sum, self.cfg.leaky_slope)?;
        linear_1x1(&h, &head.classifier.0, &head.classifier.1)
    }

    /// Per-pixel class logits in inference mode.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_t(x, false)
    }

    /// The FRD feature `[B, D]`: the global average over rows and columns of the deepest encoder map
    /// (inference mode).
    pub fn features(&self, x: &Tensor) -> Result<Tensor> {
        let levels = self.encode(x, false)?;
        let last = levels
            .last()
            .ok_or_else(|| Error::Config("rangenet: no levels".into()))?;
        Ok(last.mean(D::Minus1)?.mean(D::Minus1)?)
    }

    /// The BatchNorm running statistics by tensor name (`<bn>.running_mean`, `<bn>.running_var`).
    ///
    /// `candle_nn::BatchNorm` updates its own copies during training; save these (over the values in
    /// the training `VarMap`) to keep the trained statistics.
    pub fn batch_norm_stats(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::new();
        let mut push = |c: &ConvBn| {
            out.push((
                format!("{}.running_mean", c.bn_name),
                c.bn.running_mean().clone(),
            ));
            out.push((
                format!("{}.running_var", c.bn_name),
                c.bn.running_var().clone(),
            ));
        };
        push(&self.stem);
        for s in &self.stages {
            push(&s.down);
            for b in &s.blocks {
                push(&b.a);
                push(&b.b);
            }
        }
        out
    }

    /// Every tensor the net of `cfg` has, by name, with its shape.
    pub fn expected_tensors(cfg: &RangeNetConfig) -> Result<BTreeMap<String, Vec<usize>>> {
        crate::weights::record_tensors(|vb| RangeNet::new(cfg, vb).map(|_| ()))
    }

    /// Number of scalar parameters (BatchNorm running statistics included).
    pub fn parameter_count(cfg: &RangeNetConfig) -> Result<usize> {
        Ok(Self::expected_tensors(cfg)?
            .values()
            .map(|s| s.iter().product::<usize>())
            .sum())
    }

    /// Loads a safetensors file holding exactly the tensors of `cfg`'s net (see the module docs for
    /// the names); a mismatch fails with [`Error::CheckpointMismatch`] listing missing, unexpected and
    /// mis-shaped tensors.
    pub fn load(path: &Path, cfg: &RangeNetConfig, device: &Device) -> Result<Self> {
        cfg.validate()?;
        crate::weights::load_checked(path, DType::F32, device, |_| true, |vb| Self::new(cfg, vb))
    }

    /// [`RangeNet::load`] from the bytes of a safetensors file (`path` names it in errors).
    pub fn from_safetensors(
        bytes: &[u8],
        path: &Path,
        cfg: &RangeNetConfig,
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

/// A range image ready for [`RangeNet`]: the raw channels (range, x, y, z, remission), channel-major
/// `[5, rows, cols]`, and the validity mask.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeNetInput {
    /// Rows (beams).
    pub rows: usize,
    /// Columns (azimuth steps).
    pub cols: usize,
    /// `5 * rows * cols` raw values (metres and remission), 0 on empty pixels.
    pub channels: Vec<f32>,
    /// `rows * cols`, true where a return was projected.
    pub mask: Vec<bool>,
    /// `rows * cols`: index of each pixel's source point (`u32::MAX` where empty), e.g. to look up
    /// per-point labels.
    pub point_index: Vec<u32>,
}

impl RangeNetInput {
    /// Projects a point cloud with `sensor` (rows outside the field of view clamped to the edge rows,
    /// the nearest point wins a pixel, as RangeNet++'s and R2DM's projections) and keeps each pixel's
    /// winning point's exact x, y, z. Without intensities the remission channel is 0.
    pub fn from_points(
        points: &[Vec3],
        intensity: Option<&[f32]>,
        sensor: &LidarSensor,
    ) -> Result<Self> {
        if let Some(i) = intensity
            && i.len() != points.len()
        {
            return Err(Error::Input(format!(
                "RangeNetInput::from_points: {} intensities for {} points",
                i.len(),
                points.len()
            )));
        }
        let opts = ProjectionOptions {
            out_of_fov: OutOfFov::ClampToEdgeRows,
            ..ProjectionOptions::default()
        };
        let projector = Projector::new(sensor, opts)?;
        let (image, _) = projector.project(points, intensity, None)?;
        let (rows, cols) = (image.rows as usize, image.cols as usize);
        let n = rows * cols;
        let mut channels = vec![0f32; IN_CHANNELS * n];
        for k in 0..n {
            if !image.mask[k] {
                continue;
            }
            let p = points[image.point_index[k] as usize];
            channels[k] = image.range_m[k];
            channels[n + k] = p.x;
            channels[2 * n + k] = p.y;
            channels[3 * n + k] = p.z;
            channels[4 * n + k] = image.intensity[k];
        }
        Ok(Self {
            rows,
            cols,
            channels,
            mask: image.mask,
            point_index: image.point_index,
        })
    }

    /// From a range image: x, y, z are the range along each pixel's ray direction of `rays` (which must
    /// have the image's size); the remission channel is the image's intensity.
    pub fn from_range_image(image: &RangeImage, rays: &RayTable) -> Result<Self> {
        image.validate()?;
        if (rays.rows(), rays.cols()) != (image.rows, image.cols) {
            return Err(Error::Input(format!(
                "RangeNetInput::from_range_image: a {}x{} image with a {}x{} ray table",
                image.rows,
                image.cols,
                rays.rows(),
                rays.cols()
            )));
        }
        let (rows, cols) = (image.rows as usize, image.cols as usize);
        let n = rows * cols;
        let mut channels = vec![0f32; IN_CHANNELS * n];
        let mut mask = image.mask.clone();
        let mut point_index = image.point_index.clone();
        for k in 0..n {
            let r = image.range_m[k];
            if !mask[k] || !r.is_finite() {
                mask[k] = false;
                point_index[k] = u32::MAX;
                continue;
            }
            let d = rays.dirs()[k] * r;
            channels[k] = r;
            channels[n + k] = d.x;
            channels[2 * n + k] = d.y;
            channels[3 * n + k] = d.z;
            channels[4 * n + k] = if image.intensity[k].is_finite() {
                image.intensity[k]
            } else {
                0.0
            };
        }
        Ok(Self {
            rows,
            cols,
            channels,
            mask,
            point_index,
        })
    }

    /// The normalised input of `cfg`'s net, `[5, rows, cols]` channel-major:
    /// `(value - mean) / std` on valid pixels, exactly 0 on empty ones.
    pub fn normalized(&self, cfg: &RangeNetConfig) -> Vec<f32> {
        let n = self.rows * self.cols;
        let mut out = vec![0f32; IN_CHANNELS * n];
        for c in 0..IN_CHANNELS {
            let (m, s) = (cfg.input_mean[c], cfg.input_std[c]);
            for k in 0..n {
                if self.mask[k] {
                    out[c * n + k] = (self.channels[c * n + k] - m) / s;
                }
            }
        }
        out
    }

    /// Stacks normalised inputs (all of the same size) into a `[B, 5, H, W]` tensor.
    pub fn batch(
        inputs: &[&RangeNetInput],
        cfg: &RangeNetConfig,
        device: &Device,
    ) -> Result<Tensor> {
        let Some(first) = inputs.first() else {
            return Err(Error::Input("RangeNetInput::batch: no inputs".into()));
        };
        let (h, w) = (first.rows, first.cols);
        let mut data = Vec::with_capacity(inputs.len() * IN_CHANNELS * h * w);
        for (i, x) in inputs.iter().enumerate() {
            if (x.rows, x.cols) != (h, w) || x.channels.len() != IN_CHANNELS * h * w {
                return Err(Error::Input(format!(
                    "RangeNetInput::batch: input {i} is {}x{}, input 0 is {h}x{w}",
                    x.rows, x.cols
                )));
            }
            data.extend(x.normalized(cfg));
        }
        Ok(Tensor::from_vec(
            data,
            (inputs.len(), IN_CHANNELS, h, w),
            device,
        )?)
    }
}
