//! A small CNN image encoder with a semantic head and a metric-depth head, trained by this project
//! on the simulator's ground truth: the bundled default for `E_s` / `E_d` when no pretrained
//! SegFormer / Depth-Anything weights are available.
//!
//! **Backbone** ([`SmallCnnEncoder`], tensors under `encoder.`): a stem of two 3x3 stride-2 convs
//! (`stem.conv1`, `stem.conv2`, each followed by GroupNorm + SiLU) reaches stride 4; stage 0 runs
//! `blocks[0]` residual blocks there, and stages 1..3 each halve the resolution with a 3x3 stride-2
//! conv (`stages.{i}.down`) before their residual blocks (`stages.{i}.blocks.{j}`: conv-GN-SiLU-conv-GN
//! plus identity, then SiLU). The four stage outputs are the features, at strides **4, 8, 16 and 32**,
//! the same as SegFormer's MiT, so the small CNN is a drop-in replacement for `E_s` and needs no
//! other change in the denoiser. Feature sizes are `ceil(H / s)` (3x3 convs with padding 1).
//! GroupNorm uses the largest group count `<= norm_groups` that divides the channels.
//!
//! **Heads** (`semantic_head.*`, `depth_head.*`): a light FPN: a 1x1 lateral conv per scale to
//! `head_channels`, bilinear upsampling to the stride-4 grid, sum, 3x3 conv + GroupNorm + SiLU, and
//! a 1x1 output conv, bilinearly upsampled to the input size. The semantic head outputs
//! `num_classes` logits (20 = SemanticKITTI's learning map, 0 = unlabelled, ignored by the loss and
//! never predicted); the depth head outputs natural-log metric depth
//! `ln d = raw + ln(depth_prior_m)`, trained with [`super::losses`] and clamped to
//! `[min_depth_m, max_depth_m]` only when turned into depth by [`SmallCnn::predict_maps`].
//!
//! **Ground prior** (optional, [`SmallCnnConfig::ground_prior`]): a fourth input channel after the
//! colours, the scaled inverse flat-ground depth of the image's camera ([`super::ground`]); only
//! `stem.conv1` changes shape. Off by default, and configs without the field (every bundle made
//! before it) read as off.
//!
//! **Depth features** (optional, [`SmallCnnConfig::depth_features`]): [`ImageEncoder::forward`]
//! appends the depth head's reading, log-depth relative to the prior, as one more channel of each
//! feature map, so a network conditioned on the features sees the head's metric depth directly.
//! Off by default; it changes no weight.
//!
//! With the default config the backbone has 0.35 M parameters and each head about 16 k (0.38 M in
//! all).

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, GroupNorm, VarBuilder};

use veila_geom::PinholeCamera;

use super::ground::GroundPrior;
use super::{
    ImageEncoder, InputSpec, Normalization, check_image_channels, conv_out,
    resize_bilinear_differentiable, rgb8_to_tensor,
};
use crate::ops::groups_for;

/// Upper bounds on a [`SmallCnnConfig`] (checked by [`SmallCnnConfig::validate`]), about 50 times
/// the default's, so that no config a bundle carries can ask for an absurd network.
///
/// Image channels, `in_channels` (the default: 3).
pub const MAX_IN_CHANNELS: usize = 256;
/// Channels of a stage, each of `channels` (the default: at most 96).
pub const MAX_CHANNELS: usize = 8192;
/// Residual blocks of a stage, each of `blocks` (the default: 1).
pub const MAX_BLOCKS: usize = 64;
/// The GroupNorm group bound `norm_groups` (the default: 8).
pub const MAX_NORM_GROUPS: usize = 1024;
/// Width of the heads, `head_channels` (the default: 32).
pub const MAX_HEAD_CHANNELS: usize = 2048;
/// Semantic classes, `num_classes` (the default: 20).
pub const MAX_CLASSES: usize = 1024;

/// Configuration of [`SmallCnn`].
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SmallCnnConfig {
    /// Image channels (3; the network takes [`Self::input_channels`]).
    pub in_channels: usize,
    /// Channels of the four stages (feature channels).
    pub channels: [usize; 4],
    /// Residual blocks per stage.
    pub blocks: [usize; 4],
    /// Upper bound on the GroupNorm group count.
    pub norm_groups: usize,
    /// Width of the heads.
    pub head_channels: usize,
    /// Build the semantic head.
    pub semantic_head: bool,
    /// Semantic classes including the ignored class (20 for SemanticKITTI).
    pub num_classes: usize,
    /// Class excluded from the loss and from predictions (`Some(0)` = unlabelled).
    pub ignore_index: Option<u32>,
    /// Build the depth head.
    pub depth_head: bool,
    /// Depth the untrained head predicts (offset of the log-depth output), metres.
    pub depth_prior_m: f32,
    /// Lower clamp of predicted depth, metres.
    pub min_depth_m: f32,
    /// Upper clamp of predicted depth, metres.
    pub max_depth_m: f32,
    /// The flat-ground prior as one more input channel after the colours (`None`, the default:
    /// colours only). Such a network needs every image's camera ([`Self::input_tensor`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ground_prior: Option<GroundPrior>,
    /// Append the depth head's reading to every feature map as one more channel (`false`, the
    /// default: the backbone's features only). The channel is the head's log-depth relative to
    /// `depth_prior_m`, clamped to `[min_depth_m, max_depth_m]`, at each map's resolution, so a
    /// network conditioned on the features gets the metric depth the head reads directly. The
    /// weights are the same either way: only what [`ImageEncoder::forward`] returns changes.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub depth_features: bool,
}

impl Default for SmallCnnConfig {
    fn default() -> Self {
        Self {
            in_channels: 3,
            channels: [16, 32, 64, 96],
            blocks: [1, 1, 1, 1],
            norm_groups: 8,
            head_channels: 32,
            semantic_head: true,
            num_classes: 20,
            ignore_index: Some(0),
            depth_head: true,
            depth_prior_m: 10.0,
            min_depth_m: 0.5,
            max_depth_m: 80.0,
            ground_prior: None,
            depth_features: false,
        }
    }
}

impl SmallCnnConfig {
    /// Checks the configuration.
    pub fn validate(&self) -> crate::Result<()> {
        if self.in_channels == 0 || self.channels.contains(&0) || self.head_channels == 0 {
            config_bail!("SmallCnnConfig: channel counts must be positive");
        }
        if self.norm_groups == 0 {
            config_bail!("SmallCnnConfig: norm_groups must be positive");
        }
        self.validate_bounds()?;
        if let Some(g) = &self.ground_prior {
            g.validate()?;
        }
        if self.depth_features && !self.depth_head {
            config_bail!("SmallCnnConfig: depth_features needs the depth head");
        }
        if self.semantic_head && self.num_classes < 2 {
            config_bail!(
                "SmallCnnConfig: the semantic head needs at least 2 classes, got {}",
                self.num_classes
            );
        }
        let (lo, hi, prior) = (self.min_depth_m, self.max_depth_m, self.depth_prior_m);
        if self.depth_head
            && !(lo > 0.0 && hi > lo && prior > 0.0 && hi.is_finite() && prior.is_finite())
        {
            config_bail!(
                "SmallCnnConfig: need 0 < min_depth_m < max_depth_m < inf and 0 < depth_prior_m < inf, got {lo}, {hi}, {prior}"
            );
        }
        Ok(())
    }

    /// Every size within its `MAX_*` bound of this module.
    fn validate_bounds(&self) -> crate::Result<()> {
        use crate::config::check_max;
        check_max(
            "SmallCnnConfig.in_channels",
            self.in_channels,
            MAX_IN_CHANNELS,
        )?;
        for i in 0..4 {
            check_max(
                &format!("SmallCnnConfig.channels[{i}]"),
                self.channels[i],
                MAX_CHANNELS,
            )?;
            check_max(
                &format!("SmallCnnConfig.blocks[{i}]"),
                self.blocks[i],
                MAX_BLOCKS,
            )?;
        }
        check_max(
            "SmallCnnConfig.norm_groups",
            self.norm_groups,
            MAX_NORM_GROUPS,
        )?;
        check_max(
            "SmallCnnConfig.head_channels",
            self.head_channels,
            MAX_HEAD_CHANNELS,
        )?;
        check_max("SmallCnnConfig.num_classes", self.num_classes, MAX_CLASSES)
    }

    /// Channels of the four maps [`ImageEncoder::forward`] returns: the backbone's, plus one for
    /// the depth head's reading when [`Self::depth_features`] is on.
    pub fn feature_channels(&self) -> [usize; 4] {
        self.channels.map(|c| c + usize::from(self.depth_features))
    }

    /// Channels the network takes: the image's, plus one for the ground prior.
    pub fn input_channels(&self) -> usize {
        self.in_channels + usize::from(self.ground_prior.is_some())
    }

    /// The network's input for one `height x width` RGB image: the colours normalised with the
    /// ImageNet statistics ([`rgb8_to_tensor`]), then the ground-prior channel of `camera` when
    /// the config has one; `[1, input_channels, height, width]`.
    ///
    /// # Errors
    /// A buffer of the wrong size, an image that is not RGB (`in_channels != 3`), or a config
    /// with a ground prior and no camera.
    pub fn input_tensor(
        &self,
        rgb: &[u8],
        height: usize,
        width: usize,
        camera: Option<&PinholeCamera>,
        device: &Device,
    ) -> crate::Result<Tensor> {
        if self.in_channels != 3 {
            input_bail!(
                "SmallCnnConfig::input_tensor: RGB bytes for a network of {} image channels",
                self.in_channels
            );
        }
        let image = rgb8_to_tensor(rgb, height, width, &Normalization::IMAGENET, device)?;
        match (&self.ground_prior, camera) {
            (None, _) => Ok(image),
            (Some(g), Some(cam)) => Ok(Tensor::cat(
                &[image, g.tensor(cam, height, width, device)?],
                1,
            )?),
            (Some(_), None) => input_bail!(
                "this small CNN takes the flat-ground prior as an input channel: it needs the image's camera, none was given"
            ),
        }
    }

    /// `(H_i, W_i)` of the four features for an input of `height x width` (`ceil(H / s)` chains).
    pub fn feature_sizes(&self, height: usize, width: usize) -> [(usize, usize); 4] {
        let half = |v: usize| conv_out(v, 3, 2, 1);
        let mut sizes = [(0, 0); 4];
        let (mut h, mut w) = (half(half(height)), half(half(width)));
        sizes[0] = (h, w);
        for s in sizes.iter_mut().skip(1) {
            h = half(h);
            w = half(w);
            *s = (h, w);
        }
        sizes
    }
}

/// Conv + GroupNorm (+ SiLU in `forward_act`).
#[derive(Debug, Clone)]
struct ConvNorm {
    conv: Conv2d,
    norm: GroupNorm,
}

impl ConvNorm {
    fn new(
        cin: usize,
        cout: usize,
        k: usize,
        stride: usize,
        groups: usize,
        conv_vb: VarBuilder<'_>,
        norm_vb: VarBuilder<'_>,
    ) -> crate::Result<Self> {
        let cfg = Conv2dConfig {
            padding: k / 2,
            stride,
            ..Default::default()
        };
        Ok(Self {
            conv: candle_nn::conv2d(cin, cout, k, cfg, conv_vb)?,
            norm: candle_nn::group_norm(groups_for(cout, groups), cout, 1e-5, norm_vb)?,
        })
    }
    fn forward(&self, x: &Tensor) -> crate::Result<Tensor> {
        Ok(self
            .norm
            .forward(&crate::ops::conv2d_module(&self.conv, x)?)?)
    }
    fn forward_act(&self, x: &Tensor) -> crate::Result<Tensor> {
        Ok(self.forward(x)?.silu()?)
    }
}

#[derive(Debug, Clone)]
struct ResBlock {
    a: ConvNorm,
    b: ConvNorm,
}

impl ResBlock {
    fn new(ch: usize, groups: usize, vb: VarBuilder<'_>) -> crate::Result<Self> {
        Ok(Self {
            a: ConvNorm::new(ch, ch, 3, 1, groups, vb.pp("conv1"), vb.pp("norm1"))?,
            b: ConvNorm::new(ch, ch, 3, 1, groups, vb.pp("conv2"), vb.pp("norm2"))?,
        })
    }
    fn forward(&self, x: &Tensor) -> crate::Result<Tensor> {
        let y = self.b.forward(&self.a.forward_act(x)?)?;
        Ok((x + y)?.silu()?)
    }
}

#[derive(Debug, Clone)]
struct Stage {
    down: Option<ConvNorm>,
    blocks: Vec<ResBlock>,
}

/// The backbone of [`SmallCnn`]: four GroupNorm + SiLU stages at strides 4, 8, 16, 32.
#[derive(Debug, Clone)]
pub struct SmallCnnEncoder {
    cfg: SmallCnnConfig,
    stem1: ConvNorm,
    stem2: ConvNorm,
    stages: Vec<Stage>,
}

impl SmallCnnEncoder {
    /// `vb` points at the encoder (`encoder` inside a [`SmallCnn`] checkpoint).
    pub fn new(cfg: &SmallCnnConfig, vb: VarBuilder<'_>) -> crate::Result<Self> {
        cfg.validate()?;
        let g = cfg.norm_groups;
        let c = cfg.channels;
        let vs = vb.pp("stem");
        let stem1 = ConvNorm::new(
            cfg.input_channels(),
            c[0],
            3,
            2,
            g,
            vs.pp("conv1"),
            vs.pp("norm1"),
        )?;
        let stem2 = ConvNorm::new(c[0], c[0], 3, 2, g, vs.pp("conv2"), vs.pp("norm2"))?;
        let mut stages = Vec::with_capacity(4);
        for i in 0..4 {
            let vi = vb.pp("stages").pp(i);
            let down = if i > 0 {
                let vd = vi.pp("down");
                Some(ConvNorm::new(
                    c[i - 1],
                    c[i],
                    3,
                    2,
                    g,
                    vd.pp("conv"),
                    vd.pp("norm"),
                )?)
            } else {
                None
            };
            let blocks = (0..cfg.blocks[i])
                .map(|j| ResBlock::new(c[i], g, vi.pp("blocks").pp(j)))
                .collect::<crate::Result<Vec<_>>>()?;
            stages.push(Stage { down, blocks });
        }
        Ok(Self {
            cfg: cfg.clone(),
            stem1,
            stem2,
            stages,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &SmallCnnConfig {
        &self.cfg
    }
}

impl ImageEncoder for SmallCnnEncoder {
    fn forward(&self, image: &Tensor) -> crate::Result<Vec<Tensor>> {
        let _span = tracing::trace_span!("small_cnn_encoder").entered();
        let dims = image.dims();
        if dims.len() != 4 || dims[1] != self.cfg.input_channels() || dims[0] == 0 {
            input_bail!(
                "SmallCnnEncoder: expected an image tensor [B, {}, H, W]{}, got shape {dims:?}",
                self.cfg.input_channels(),
                if self.cfg.ground_prior.is_some() {
                    " (colours and the ground prior)"
                } else {
                    ""
                }
            );
        }
        let mut x = self.stem2.forward_act(&self.stem1.forward_act(image)?)?;
        let mut out = Vec::with_capacity(4);
        for stage in &self.stages {
            if let Some(down) = &stage.down {
                x = down.forward_act(&x)?;
            }
            for b in &stage.blocks {
                x = b.forward(&x)?;
            }
            out.push(x.clone());
        }
        Ok(out)
    }
    fn channels(&self) -> [usize; 4] {
        self.cfg.channels
    }
    fn strides(&self) -> [f32; 4] {
        [4.0, 8.0, 16.0, 32.0]
    }
    fn feature_sizes(&self, height: usize, width: usize) -> [(usize, usize); 4] {
        self.cfg.feature_sizes(height, width)
    }
    fn input_spec(&self) -> InputSpec {
        InputSpec {
            normalization: Normalization::IMAGENET,
            size_multiple: 32,
            min_size: 1,
        }
    }
}

/// A light FPN head predicting `out_channels` maps at the input resolution.
#[derive(Debug, Clone)]
pub struct DenseHead {
    lateral: Vec<Conv2d>,
    fuse: ConvNorm,
    out: Conv2d,
}

impl DenseHead {
    /// `vb` points at the head (`semantic_head` or `depth_head`).
    pub fn new(
        in_channels: [usize; 4],
        head_channels: usize,
        out_channels: usize,
        norm_groups: usize,
        vb: VarBuilder<'_>,
    ) -> crate::Result<Self> {
        let lateral = (0..4)
            .map(|i| {
                candle_nn::conv2d(
                    in_channels[i],
                    head_channels,
                    1,
                    Conv2dConfig::default(),
                    vb.pp("lateral").pp(i),
                )
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        let vf = vb.pp("fuse");
        let fuse = ConvNorm::new(
            head_channels,
            head_channels,
            3,
            1,
            norm_groups,
            vf.pp("conv"),
            vf.pp("norm"),
        )?;
        let out = candle_nn::conv2d(
            head_channels,
            out_channels,
            1,
            Conv2dConfig::default(),
            vb.pp("out"),
        )?;
        Ok(Self { lateral, fuse, out })
    }

    /// Features (finest first) -> `[B, out_channels, height, width]`.
    pub fn forward(
        &self,
        features: &[Tensor],
        height: usize,
        width: usize,
    ) -> crate::Result<Tensor> {
        if features.len() != 4 {
            input_bail!("DenseHead: expected 4 feature maps, got {}", features.len());
        }
        let (_, _, h0, w0) = features[0].dims4()?;
        let mut acc: Option<Tensor> = None;
        for (f, lat) in features.iter().zip(&self.lateral) {
            let y = crate::ops::conv2d_module(lat, f)?;
            let (_, _, h, w) = y.dims4()?;
            let y = if (h, w) != (h0, w0) {
                resize_bilinear_differentiable(&y, h0, w0)?
            } else {
                y
            };
            acc = Some(match acc {
                None => y,
                Some(a) => (a + y)?,
            });
        }
        let x = match acc {
            Some(a) => a,
            None => input_bail!("DenseHead: no features"),
        };
        let x = crate::ops::conv2d_module(&self.out, &self.fuse.forward_act(&x)?)?;
        if (h0, w0) == (height, width) {
            Ok(x)
        } else {
            Ok(resize_bilinear_differentiable(&x, height, width)?)
        }
    }
}

/// Everything [`SmallCnn::forward_all`] computes.
#[derive(Debug, Clone)]
pub struct SmallCnnOutput {
    /// The backbone's four feature maps (what [`ImageEncoder::forward`] returns, without the
    /// depth channel of [`SmallCnnConfig::depth_features`]).
    pub features: Vec<Tensor>,
    /// `[B, num_classes, H, W]` logits, when the semantic head exists.
    pub semantic_logits: Option<Tensor>,
    /// `[B, 1, H, W]` natural-log depth in metres (unclamped), when the depth head exists.
    pub log_depth: Option<Tensor>,
}

/// Per-image dense predictions for the cross-modal metrics, row-major `height x width`.
#[derive(Debug, Clone, PartialEq)]
pub struct DenseMaps {
    /// Image height in pixels.
    pub height: usize,
    /// Image width in pixels.
    pub width: usize,
    /// Semantic label per pixel (argmax over the classes other than the ignore index).
    pub labels: Option<Vec<u32>>,
    /// Metric depth per pixel, metres, clamped to `[min_depth_m, max_depth_m]`.
    pub depth_m: Option<Vec<f32>>,
}

/// Which depth loss [`SmallCnn::loss`] uses.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum DepthLoss {
    /// Mean absolute log-depth error ([`super::losses::log_depth_l1`]).
    LogL1,
    /// Scale-invariant log loss with this `lambda` ([`super::losses::silog`]).
    SiLog {
        /// Weight of the scale-invariance term, in `[0, 1]`.
        lambda: f64,
    },
}

/// Weights of the training loss of [`SmallCnn`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SmallCnnLossConfig {
    /// Weight of the semantic cross-entropy.
    pub semantic_weight: f64,
    /// Weight of the depth loss.
    pub depth_weight: f64,
    /// The depth loss.
    pub depth_loss: DepthLoss,
}

impl Default for SmallCnnLossConfig {
    fn default() -> Self {
        Self {
            semantic_weight: 1.0,
            depth_weight: 1.0,
            depth_loss: DepthLoss::LogL1,
        }
    }
}

/// The training loss of one batch and its parts (for logging).
#[derive(Debug, Clone)]
pub struct SmallCnnLoss {
    /// Weighted sum, a scalar to call `backward` on.
    pub total: Tensor,
    /// Semantic cross-entropy, when labels were given and the head exists.
    pub semantic: Option<f32>,
    /// Depth loss, when depth was given and the head exists.
    pub depth: Option<f32>,
}

/// The small CNN encoder with its optional semantic and depth heads.
#[derive(Debug, Clone)]
pub struct SmallCnn {
    cfg: SmallCnnConfig,
    encoder: SmallCnnEncoder,
    semantic: Option<DenseHead>,
    depth: Option<DenseHead>,
}

impl SmallCnn {
    /// Reads `encoder.*`, `semantic_head.*` and `depth_head.*` (heads only when enabled).
    pub fn new(cfg: &SmallCnnConfig, vb: VarBuilder<'_>) -> crate::Result<Self> {
        let encoder = SmallCnnEncoder::new(cfg, vb.pp("encoder"))?;
        let semantic = if cfg.semantic_head {
            Some(DenseHead::new(
                cfg.channels,
                cfg.head_channels,
                cfg.num_classes,
                cfg.norm_groups,
                vb.pp("semantic_head"),
            )?)
        } else {
            None
        };
        let depth = if cfg.depth_head {
            Some(DenseHead::new(
                cfg.channels,
                cfg.head_channels,
                1,
                cfg.norm_groups,
                vb.pp("depth_head"),
            )?)
        } else {
            None
        };
        Ok(Self {
            cfg: cfg.clone(),
            encoder,
            semantic,
            depth,
        })
    }

    /// Loads weights saved from the `VarMap` the model was trained in (`VarMap::save`), checking
    /// every tensor first (see [`super::load_checked`]; any tensor the model does not read is
    /// reported as unexpected, e.g. a head the config disables).
    pub fn load(
        cfg: &SmallCnnConfig,
        path: &std::path::Path,
        dtype: DType,
        device: &candle_core::Device,
    ) -> crate::Result<Self> {
        super::load_checked(path, dtype, device, |_| true, |vb| Self::new(cfg, vb))
    }

    /// The configuration.
    pub fn config(&self) -> &SmallCnnConfig {
        &self.cfg
    }

    /// The backbone.
    pub fn encoder(&self) -> &SmallCnnEncoder {
        &self.encoder
    }

    /// Features plus head outputs at the input resolution.
    pub fn forward_all(&self, image: &Tensor) -> crate::Result<SmallCnnOutput> {
        let (_, h, w) = check_image_channels(image, self.cfg.input_channels(), 1, "SmallCnn")?;
        let features = self.encoder.forward(image)?;
        let semantic_logits = match &self.semantic {
            Some(head) => Some(head.forward(&features, h, w)?),
            None => None,
        };
        let log_depth = match &self.depth {
            Some(head) => {
                let raw = head.forward(&features, h, w)?;
                Some((raw + f64::from(self.cfg.depth_prior_m).ln())?)
            }
            None => None,
        };
        Ok(SmallCnnOutput {
            features,
            semantic_logits,
            log_depth,
        })
    }

    /// Training loss on ground truth: `labels` `[B, H, W]` (integer class ids of the learning map,
    /// the config's `ignore_index` skipped) and/or `depth_m` `[B, H, W]` or `[B, 1, H, W]` (metric
    /// depth; `0`, NaN and inf mark pixels without ground truth).
    ///
    /// # Errors
    /// When neither target is given for an existing head, or shapes disagree.
    pub fn loss(
        &self,
        image: &Tensor,
        labels: Option<&Tensor>,
        depth_m: Option<&Tensor>,
        cfg: &SmallCnnLossConfig,
    ) -> crate::Result<SmallCnnLoss> {
        let out = self.forward_all(image)?;
        let mut total: Option<Tensor> = None;
        let mut add = |t: Tensor, w: f64| -> crate::Result<()> {
            let t = (t * w)?;
            total = Some(match total.take() {
                None => t,
                Some(a) => (a + t)?,
            });
            Ok(())
        };
        let mut semantic = None;
        if let (Some(logits), Some(labels)) = (&out.semantic_logits, labels) {
            let ce = super::losses::semantic_cross_entropy(logits, labels, self.cfg.ignore_index)?;
            semantic = Some(ce.to_dtype(DType::F32)?.to_scalar::<f32>()?);
            add(ce, cfg.semantic_weight)?;
        }
        let mut depth = None;
        if let (Some(ld), Some(target)) = (&out.log_depth, depth_m) {
            let dl = match cfg.depth_loss {
                DepthLoss::LogL1 => super::losses::log_depth_l1(ld, target)?,
                DepthLoss::SiLog { lambda } => super::losses::silog(ld, target, lambda)?,
            };
            depth = Some(dl.to_dtype(DType::F32)?.to_scalar::<f32>()?);
            add(dl, cfg.depth_weight)?;
        }
        match total {
            Some(total) => Ok(SmallCnnLoss {
                total,
                semantic,
                depth,
            }),
            None => input_bail!(
                "SmallCnn::loss: no target for any head (semantic head: {}, depth head: {}, labels given: {}, depth given: {})",
                self.semantic.is_some(),
                self.depth.is_some(),
                labels.is_some(),
                depth_m.is_some()
            ),
        }
    }

    /// Per-image label and depth maps (the inputs of the cross-modal semantic and depth metrics).
    pub fn predict_maps(&self, image: &Tensor) -> crate::Result<Vec<DenseMaps>> {
        let out = self.forward_all(&image.detach())?;
        let (b, _, h, w) = image.dims4()?;
        let labels = match &out.semantic_logits {
            Some(logits) => {
                let logits = logits.detach().to_dtype(DType::F32)?;
                let k = self.cfg.num_classes;
                let logits = match self.cfg.ignore_index {
                    Some(ix) if (ix as usize) < k => {
                        let mut mask = vec![0f32; k];
                        mask[ix as usize] = f32::NEG_INFINITY;
                        let mask = Tensor::from_vec(mask, (1, k, 1, 1), logits.device())?;
                        logits.broadcast_add(&mask)?
                    }
                    _ => logits,
                };
                Some(logits.argmax(1)?.flatten_from(1)?.to_vec2::<u32>()?)
            }
            None => None,
        };
        let depth = match &out.log_depth {
            Some(ld) => {
                let lo = f64::from(self.cfg.min_depth_m).ln();
                let hi = f64::from(self.cfg.max_depth_m).ln();
                let d = ld
                    .detach()
                    .to_dtype(DType::F32)?
                    .clamp(lo, hi)?
                    .exp()?
                    .flatten_from(1)?
                    .to_vec2::<f32>()?;
                Some(d)
            }
            None => None,
        };
        let mut maps = Vec::with_capacity(b);
        for i in 0..b {
            maps.push(DenseMaps {
                height: h,
                width: w,
                labels: labels.as_ref().map(|l| l[i].clone()),
                depth_m: depth.as_ref().map(|d| {
                    // guard against non-finite values from a diverged model
                    d[i].iter()
                        .map(|&v| {
                            if v.is_finite() {
                                v
                            } else {
                                self.cfg.depth_prior_m
                            }
                        })
                        .collect()
                }),
            });
        }
        Ok(maps)
    }
}

impl SmallCnn {
    /// The depth head's reading as one channel per feature map (see
    /// [`SmallCnnConfig::depth_features`]): `ln(depth / depth_prior_m)`, clamped to the config's
    /// depth range, computed at the finest map's resolution and resized bilinearly to the others.
    fn depth_channels(&self, features: &[Tensor]) -> crate::Result<Vec<Tensor>> {
        let Some(head) = &self.depth else {
            config_bail!("SmallCnn: depth_features needs the depth head");
        };
        let (_, _, h0, w0) = features[0].dims4()?;
        let prior = f64::from(self.cfg.depth_prior_m);
        let lo = (f64::from(self.cfg.min_depth_m) / prior).ln();
        let hi = (f64::from(self.cfg.max_depth_m) / prior).ln();
        let fine = head.forward(features, h0, w0)?.clamp(lo, hi)?;
        features
            .iter()
            .map(|f| {
                let (_, _, h, w) = f.dims4()?;
                if (h, w) == (h0, w0) {
                    Ok(fine.clone())
                } else {
                    Ok(resize_bilinear_differentiable(&fine, h, w)?)
                }
            })
            .collect()
    }
}

impl ImageEncoder for SmallCnn {
    fn forward(&self, image: &Tensor) -> crate::Result<Vec<Tensor>> {
        let features = self.encoder.forward(image)?;
        if !self.cfg.depth_features {
            return Ok(features);
        }
        let depth = self.depth_channels(&features)?;
        features
            .iter()
            .zip(&depth)
            .map(|(f, d)| Ok(Tensor::cat(&[f, d], 1)?))
            .collect()
    }
    fn channels(&self) -> [usize; 4] {
        self.cfg.feature_channels()
    }
    fn strides(&self) -> [f32; 4] {
        self.encoder.strides()
    }
    fn feature_sizes(&self, height: usize, width: usize) -> [(usize, usize); 4] {
        self.encoder.feature_sizes(height, width)
    }
    fn input_spec(&self) -> InputSpec {
        self.encoder.input_spec()
    }
}
