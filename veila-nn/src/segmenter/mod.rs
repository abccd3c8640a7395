//! A range-view semantic segmenter: a small encoder-decoder over range-image channels in the
//! SalsaNext / CENet lineage, and the RangeNet++ clean-up that carries its pixel classes back to
//! the scan's points ([`knn`]).
//!
//! # Input
//!
//! `[B, in_channels, rows, cols]` with [`IN_CHANNELS`] = 6 channels, in this order: range (m),
//! x, y, z (m, LiDAR frame), intensity, each normalised with the config's `input_mean` /
//! `input_std` and set to exactly 0 on empty pixels, then the validity mask (1 where the pixel
//! holds a return, 0 elsewhere). [`segmenter_input`] builds it from a projected scan.
//!
//! # Architecture
//!
//! Every convolution is 3x3 (1x1 in the shortcut projections and the classifier), has no bias
//! (the classifier has one), wraps around the azimuth axis and zero-pads the rows, as the range
//! image of a spinning LiDAR does; every one is followed by a BatchNorm (eps `bn_eps`) and a
//! LeakyReLU (`leaky_slope`), written `CBA` below.
//!
//! * stem: `CBA(in → stem)`, `CBA(stem → stem)` at full resolution;
//! * stages `stage1..stageS`, each `blocks` residual blocks (ResNet's basic block, as CENet's
//!   encoder): `act(BN(conv(act(BN(conv(x))))) + shortcut(x))`, the first conv of a stage's first
//!   block with the stage's `stride` (rows, cols; 1 or 2 each), the shortcut a 1x1 conv + BN
//!   where the stride or the width changes;
//! * head (CENet's decoder): the stem's map and every stage's output resized bilinearly
//!   (PyTorch's `align_corners=False`) to `rows x cols`, concatenated along channels, `CBA(sum →
//!   head)`, `CBA(head → head)`, a 1x1 classifier with bias to `num_classes` logits.
//!
//! # Weight names
//!
//! ```text
//! stem.{0,1}.conv.weight                 stem.{0,1}.bn.{weight,bias,running_mean,running_var}
//! stage{i}.block{j}.conv1.weight         stage{i}.block{j}.bn1.*
//! stage{i}.block{j}.conv2.weight         stage{i}.block{j}.bn2.*
//! stage{i}.block0.down.conv.weight       stage{i}.block0.down.bn.*     (where the shape changes)
//! head.fuse{1,2}.conv.weight             head.fuse{1,2}.bn.*
//! head.classifier.{weight,bias}
//! ```
//!
//! `i` counts from 1, `j` from 0. The PyTorch yardstick
//! (`veila-nn/tests/data/segmenter/segmenter_yardstick.py`) builds the same network from these
//! names.
//!
//! # Sizes
//!
//! [`SegmenterConfig::hdl64`] (64 x 1024, 20 SemanticKITTI classes) has 4.2 M parameters,
//! [`SegmenterConfig::bundled`] (the bundled model's 32 x 256 grid) 0.40 M
//! ([`SegmenterConfig::num_parameters`]; checked by the tests).

pub mod knn;

use candle_core::{DType, Device, Tensor};
use candle_nn::{BatchNorm, BatchNormConfig, Init, ModuleT, VarBuilder};
use glam::Vec3;
use serde::{Deserialize, Serialize};
use veila_geom::RangeImage;

use crate::error::{Error, Result, shape_err};
use crate::ops::{Im2ColSpec, bilinear_resize, conv2d_im2col};

/// Input channels: range, x, y, z, intensity (normalised, 0 where empty) and the validity mask.
pub const IN_CHANNELS: usize = 6;

/// Upper bounds of a [`SegmenterConfig`] (checked by [`SegmenterConfig::validate`]), far above
/// any range-view segmenter in use, so that no config from a file can ask for an absurd network.
///
/// Channels of the stem, `stem_channels`.
pub const MAX_STEM_CHANNELS: usize = 1024;
/// Encoder stages, the length of `stages`.
pub const MAX_STAGES: usize = 8;
/// Channels of a stage, `stages[i].channels`.
pub const MAX_STAGE_CHANNELS: usize = 4096;
/// Residual blocks of a stage, `stages[i].blocks`.
pub const MAX_STAGE_BLOCKS: usize = 64;
/// Channels of the head, `head_channels`.
pub const MAX_HEAD_CHANNELS: usize = 2048;
/// Classes, `num_classes` (SemanticKITTI: 20).
pub const MAX_CLASSES: usize = 1024;
/// Rows of the input grid, `rows` (the widest sensors have 128 beams).
pub const MAX_ROWS: usize = 1024;
/// Columns of the input grid, `cols`.
pub const MAX_COLS: usize = 16_384;

/// One encoder stage: `blocks` residual blocks of `channels`, the first with `stride`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SegStage {
    /// Output channels.
    pub channels: usize,
    /// Residual blocks (at least 1).
    pub blocks: usize,
    /// Stride of the stage's first convolution, (rows, cols), each 1 or 2.
    pub stride: [usize; 2],
}

/// Configuration of a [`Segmenter`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SegmenterConfig {
    /// Short name (e.g. `seg-hdl64`).
    pub name: String,
    /// Rows of the input range image.
    pub rows: usize,
    /// Columns of the input range image.
    pub cols: usize,
    /// Classes of the logits (SemanticKITTI: 20 train ids, 0 the ignored class).
    pub num_classes: usize,
    /// Channels of the two stem convolutions.
    pub stem_channels: usize,
    /// Encoder stages.
    pub stages: Vec<SegStage>,
    /// Channels of the head's two fusion convolutions.
    pub head_channels: usize,
    /// Means of range, x, y, z and intensity ([`segmenter_input`]).
    pub input_mean: [f32; 5],
    /// Standard deviations of range, x, y, z and intensity.
    pub input_std: [f32; 5],
    /// Negative slope of the LeakyReLUs.
    pub leaky_slope: f64,
    /// BatchNorm epsilon (keeps a constant input finite in training mode).
    pub bn_eps: f64,
    /// BatchNorm running-statistics momentum (PyTorch convention).
    pub bn_momentum: f64,
}

fn stage(channels: usize, blocks: usize, stride: usize) -> SegStage {
    SegStage {
        channels,
        blocks,
        stride: [stride, stride],
    }
}

impl SegmenterConfig {
    /// The 64 x 1024 HDL-64E grid of SemanticKITTI, 20 classes: stem 32, stages 64 → 128 → 128 →
    /// 256 (two blocks each; the last three halve both axes), head 128. 4.2 M parameters.
    pub fn hdl64() -> Self {
        SegmenterConfig {
            name: "seg-hdl64".into(),
            rows: 64,
            cols: 1024,
            num_classes: 20,
            stem_channels: 32,
            stages: vec![
                stage(64, 2, 1),
                stage(128, 2, 2),
                stage(128, 2, 2),
                stage(256, 2, 2),
            ],
            head_channels: 128,
            // RangeNet++'s SemanticKITTI statistics, as the FRD network normalises
            input_mean: crate::feature_nets::rangenet::RANGENET_MEAN,
            input_std: crate::feature_nets::rangenet::RANGENET_STD,
            leaky_slope: 0.1,
            bn_eps: 1e-5,
            bn_momentum: 0.01,
        }
    }

    /// The bundled model's 32 x 256 grid, 20 classes: stem 16, stages 32 → 48 → 64 → 96 (one
    /// block each; the last three halve both axes), head 48. 0.40 M parameters.
    pub fn bundled() -> Self {
        SegmenterConfig {
            name: "seg-bundled".into(),
            rows: 32,
            cols: 256,
            stem_channels: 16,
            stages: vec![
                stage(32, 1, 1),
                stage(48, 1, 2),
                stage(64, 1, 2),
                stage(96, 1, 2),
            ],
            head_channels: 48,
            ..Self::hdl64()
        }
    }

    /// A toy network for tests (16 x 64, 5 classes, a few thousand parameters).
    pub fn tiny() -> Self {
        SegmenterConfig {
            name: "seg-tiny".into(),
            rows: 16,
            cols: 64,
            num_classes: 5,
            stem_channels: 4,
            stages: vec![
                stage(6, 1, 1),
                stage(8, 2, 2),
                SegStage {
                    channels: 8,
                    blocks: 1,
                    stride: [1, 2],
                },
            ],
            head_channels: 6,
            ..Self::hdl64()
        }
    }

    /// Checks every field (the message names the offending one).
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::Config(format!("segmenter {}: {m}", self.name)));
        let check = |field: &str, value: usize, max: usize| {
            crate::config::check_max(&format!("segmenter {}: {field}", self.name), value, max)
        };
        for (field, value) in [
            ("rows", self.rows),
            ("cols", self.cols),
            ("stem_channels", self.stem_channels),
            ("head_channels", self.head_channels),
        ] {
            if value == 0 {
                return bad(format!("{field} must be > 0"));
            }
        }
        if self.num_classes < 2 {
            return bad(format!(
                "num_classes must be >= 2, got {}",
                self.num_classes
            ));
        }
        if self.stages.is_empty() {
            return bad("stages must not be empty".into());
        }
        check("rows", self.rows, MAX_ROWS)?;
        check("cols", self.cols, MAX_COLS)?;
        check("num_classes", self.num_classes, MAX_CLASSES)?;
        check("stem_channels", self.stem_channels, MAX_STEM_CHANNELS)?;
        check("head_channels", self.head_channels, MAX_HEAD_CHANNELS)?;
        check("stages (count)", self.stages.len(), MAX_STAGES)?;
        for (i, s) in self.stages.iter().enumerate() {
            if s.channels == 0 || s.blocks == 0 {
                return bad(format!("stages[{i}]: channels and blocks must be > 0"));
            }
            check(
                &format!("stages[{i}].channels"),
                s.channels,
                MAX_STAGE_CHANNELS,
            )?;
            check(&format!("stages[{i}].blocks"), s.blocks, MAX_STAGE_BLOCKS)?;
            if s.stride.iter().any(|&st| st != 1 && st != 2) {
                return bad(format!(
                    "stages[{i}].stride {:?}: each must be 1 or 2",
                    s.stride
                ));
            }
        }
        // the smallest level keeps at least one row and column, and the ring padding of a 3x3
        // convolution needs a level at least one column wide
        let (mut h, mut w) = (self.rows, self.cols);
        for (i, s) in self.stages.iter().enumerate() {
            h = h.div_ceil(s.stride[0]);
            w = w.div_ceil(s.stride[1]);
            if h < 1 || w < 2 {
                return bad(format!("stages[{i}] leaves a {h} x {w} map (rows x cols)"));
            }
        }
        for c in 0..5 {
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
        if !((1e-8..=1.0).contains(&self.bn_eps)) {
            return bad(format!("bn_eps {} must be in [1e-8, 1]", self.bn_eps));
        }
        if !(self.bn_momentum.is_finite() && self.bn_momentum > 0.0 && self.bn_momentum <= 1.0) {
            return bad(format!(
                "bn_momentum {} must be in (0, 1]",
                self.bn_momentum
            ));
        }
        Ok(())
    }

    /// Trainable parameters (convolution weights, BatchNorm scales and shifts, the classifier's
    /// weight and bias; not the BatchNorm running statistics).
    pub fn num_parameters(&self) -> usize {
        let cba = |i: usize, o: usize, k: usize| i * o * k * k + 2 * o;
        let mut n = cba(IN_CHANNELS, self.stem_channels, 3)
            + cba(self.stem_channels, self.stem_channels, 3);
        let mut c = self.stem_channels;
        let mut concat = c;
        for s in &self.stages {
            for j in 0..s.blocks {
                let cin = if j == 0 { c } else { s.channels };
                n += cba(cin, s.channels, 3) + cba(s.channels, s.channels, 3);
                if j == 0 && (cin != s.channels || s.stride != [1, 1]) {
                    n += cba(cin, s.channels, 1);
                }
            }
            c = s.channels;
            concat += c;
        }
        n + cba(concat, self.head_channels, 3)
            + cba(self.head_channels, self.head_channels, 3)
            + self.head_channels * self.num_classes
            + self.num_classes
    }
}

/// Conv (3x3 ring-padded or 1x1, no bias) + BatchNorm (+ LeakyReLU where `act`).
#[derive(Debug, Clone)]
struct Cba {
    weight: Tensor,
    bn: BatchNorm,
    stride: [usize; 2],
    slope: Option<f64>,
}

impl Cba {
    fn new(
        cin: usize,
        cout: usize,
        k: usize,
        stride: [usize; 2],
        act: bool,
        cfg: &SegmenterConfig,
        (vb, conv, bn): (&VarBuilder<'_>, &str, &str),
    ) -> Result<Self> {
        let weight = vb.pp(conv).get_with_hints(
            (cout, cin, k, k),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let bn_cfg = BatchNormConfig {
            eps: cfg.bn_eps,
            remove_mean: true,
            affine: true,
            momentum: cfg.bn_momentum,
        };
        let bn = candle_nn::batch_norm(cout, bn_cfg, vb.pp(bn))?;
        Ok(Self {
            weight,
            bn,
            stride,
            slope: act.then_some(cfg.leaky_slope),
        })
    }

    fn forward(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let k = self.weight.dim(2)?;
        let y = conv2d_im2col(
            x,
            &self.weight,
            None,
            Im2ColSpec {
                kernel: (k, k),
                stride: (self.stride[0], self.stride[1]),
                pad_h: k / 2,
                pad_w: k / 2,
                ring: true,
                ones_row: false,
            },
        )?;
        let y = self.bn.forward_t(&y, train)?;
        match self.slope {
            Some(s) => leaky(&y, s),
            None => Ok(y),
        }
    }
}

/// `max(x, slope x)` (`slope` in `[0, 1)`).
fn leaky(x: &Tensor, slope: f64) -> Result<Tensor> {
    Ok(x.maximum(&x.affine(slope, 0.0)?)?)
}

#[derive(Debug, Clone)]
struct Block {
    a: Cba,
    b: Cba,
    down: Option<Cba>,
    slope: f64,
}

impl Block {
    fn forward(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let y = self.b.forward(&self.a.forward(x, train)?, train)?;
        let skip = match &self.down {
            Some(d) => d.forward(x, train)?,
            None => x.clone(),
        };
        leaky(&(y + skip)?, self.slope)
    }
}

/// The range-view segmenter (see the module docs).
#[derive(Debug, Clone)]
pub struct Segmenter {
    cfg: SegmenterConfig,
    stem: [Cba; 2],
    stages: Vec<Vec<Block>>,
    fuse: [Cba; 2],
    classifier: (Tensor, Tensor),
}

impl Segmenter {
    /// Builds the network of `cfg` with its weights under `vb` (names in the module docs).
    pub fn new(cfg: &SegmenterConfig, vb: VarBuilder<'_>) -> Result<Self> {
        cfg.validate()?;
        let sc = cfg.stem_channels;
        let svb = vb.pp("stem");
        let stem = [
            Cba::new(
                IN_CHANNELS,
                sc,
                3,
                [1, 1],
                true,
                cfg,
                (&svb.pp("0"), "conv", "bn"),
            )?,
            Cba::new(sc, sc, 3, [1, 1], true, cfg, (&svb.pp("1"), "conv", "bn"))?,
        ];
        let mut c = sc;
        let mut concat = sc;
        let mut stages = Vec::with_capacity(cfg.stages.len());
        for (i, s) in cfg.stages.iter().enumerate() {
            let stvb = vb.pp(format!("stage{}", i + 1));
            let mut blocks = Vec::with_capacity(s.blocks);
            for j in 0..s.blocks {
                let bvb = stvb.pp(format!("block{j}"));
                let (cin, stride) = if j == 0 {
                    (c, s.stride)
                } else {
                    (s.channels, [1, 1])
                };
                let down = if cin != s.channels || stride != [1, 1] {
                    Some(Cba::new(
                        cin,
                        s.channels,
                        1,
                        stride,
                        false,
                        cfg,
                        (&bvb.pp("down"), "conv", "bn"),
                    )?)
                } else {
                    None
                };
                blocks.push(Block {
                    a: Cba::new(
                        cin,
                        s.channels,
                        3,
                        stride,
                        true,
                        cfg,
                        (&bvb, "conv1", "bn1"),
                    )?,
                    b: Cba::new(
                        s.channels,
                        s.channels,
                        3,
                        [1, 1],
                        false,
                        cfg,
                        (&bvb, "conv2", "bn2"),
                    )?,
                    down,
                    slope: cfg.leaky_slope,
                });
            }
            stages.push(blocks);
            c = s.channels;
            concat += c;
        }
        let hvb = vb.pp("head");
        let hc = cfg.head_channels;
        let fuse = [
            Cba::new(
                concat,
                hc,
                3,
                [1, 1],
                true,
                cfg,
                (&hvb.pp("fuse1"), "conv", "bn"),
            )?,
            Cba::new(
                hc,
                hc,
                3,
                [1, 1],
                true,
                cfg,
                (&hvb.pp("fuse2"), "conv", "bn"),
            )?,
        ];
        let cvb = hvb.pp("classifier");
        let weight = cvb.get_with_hints(
            (cfg.num_classes, hc, 1, 1),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let bound = 1.0 / (hc as f64).sqrt();
        let bias = cvb.get_with_hints(
            cfg.num_classes,
            "bias",
            Init::Uniform {
                lo: -bound,
                up: bound,
            },
        )?;
        Ok(Self {
            cfg: cfg.clone(),
            stem,
            stages,
            fuse,
            classifier: (weight, bias),
        })
    }

    /// The config the network was built from.
    pub fn config(&self) -> &SegmenterConfig {
        &self.cfg
    }

    /// Logits `[B, num_classes, rows, cols]` of `x: [B, 6, rows, cols]` ([`segmenter_input`]),
    /// BatchNorm on its running statistics (inference).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_t(x, false)
    }

    /// [`Segmenter::forward`] with `train` choosing the BatchNorm's batch statistics (and updating
    /// the running ones) instead of the running statistics.
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let (rows, cols) = (self.cfg.rows, self.cfg.cols);
        match x.dims() {
            [b, c, h, w] if *b > 0 && *c == IN_CHANNELS && *h == rows && *w == cols => {}
            d => {
                return Err(shape_err(
                    "segmenter input",
                    format!("[B, {IN_CHANNELS}, {rows}, {cols}]"),
                    d,
                ));
            }
        }
        let mut h = self.stem[1].forward(&self.stem[0].forward(x, train)?, train)?;
        let mut levels = vec![h.clone()];
        for blocks in &self.stages {
            for blk in blocks {
                h = blk.forward(&h, train)?;
            }
            levels.push(bilinear_resize(&h, rows, cols)?);
        }
        let cat = Tensor::cat(&levels, 1)?;
        let f = self.fuse[1].forward(&self.fuse[0].forward(&cat, train)?, train)?;
        let (w, b) = &self.classifier;
        conv2d_im2col(&f, w, Some(b), Im2ColSpec::POINTWISE)
    }
}

/// The class of every pixel, the argmax over `logits: [B, K, H, W]` (ties go to the lower class),
/// one row-major `H x W` vector per batch item.
pub fn pixel_classes(logits: &Tensor) -> Result<Vec<Vec<u32>>> {
    let (b, _, h, w) = logits.dims4()?;
    let am = logits.argmax_keepdim(1)?.to_dtype(DType::U32)?;
    let flat = am.reshape((b, h * w))?.to_vec2::<u32>()?;
    Ok(flat)
}

/// The segmenter's input `[1, 6, rows, cols]` for one projected scan: `image` from
/// [`veila_geom::Projector::project`] of `points` (its `point_index` names the winning point of
/// each pixel), normalised with `cfg.input_mean` / `cfg.input_std` (module docs).
///
/// Fails when the image is not `cfg.rows x cols`, is inconsistent, or names a point that
/// `points` does not have.
pub fn segmenter_input(
    image: &RangeImage,
    points: &[Vec3],
    cfg: &SegmenterConfig,
    device: &Device,
) -> Result<Tensor> {
    image.validate()?;
    let (h, w) = (image.rows as usize, image.cols as usize);
    if (h, w) != (cfg.rows, cfg.cols) {
        return Err(shape_err(
            "segmenter_input image",
            format!("{} x {}", cfg.rows, cfg.cols),
            &[h, w],
        ));
    }
    let n = h * w;
    let mut data = vec![0f32; IN_CHANNELS * n];
    for k in 0..n {
        if !image.mask[k] {
            continue;
        }
        let Some(p) = points.get(image.point_index[k] as usize) else {
            return Err(Error::Input(format!(
                "segmenter_input: pixel {k} names point {} of {}",
                image.point_index[k],
                points.len()
            )));
        };
        let raw = [image.range_m[k], p.x, p.y, p.z, image.intensity[k]];
        for (c, v) in raw.iter().enumerate() {
            let z = (v - cfg.input_mean[c]) / cfg.input_std[c];
            data[c * n + k] = if z.is_finite() { z } else { 0.0 };
        }
        data[5 * n + k] = 1.0;
    }
    Ok(Tensor::from_vec(data, (1, IN_CHANNELS, h, w), device)?)
}
