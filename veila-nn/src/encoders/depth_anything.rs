//! Depth-Anything-V2 (DINOv2 + DPT neck + depth head), the paper's depth encoder `E_d`: the
//! feature extractor [`DepthAnythingV2Encoder`] and the whole depth model [`DepthAnythingV2`].
//!
//! Weight names follow HuggingFace transformers' `DepthAnythingForDepthEstimation`, i.e. the
//! safetensors of `depth-anything/Depth-Anything-V2-Small-hf` (and `-Base-hf`, `-Large-hf`):
//!
//! * backbone ([`DinoV2Backbone`], under `backbone.`): see [`super::dinov2`].
//! * neck reassemble stage: `neck.reassemble_stage.layers.{i}.projection` (1x1 conv to
//!   `neck_hidden_sizes[i]`) and `neck.reassemble_stage.layers.{i}.resize` (factor 4 and 2:
//!   transposed conv with kernel = stride = factor; factor 1: identity, no tensor; factor 0.5:
//!   3x3 conv, stride 2, padding 1).
//! * optional depth head ([`DepthAnythingV2`]): `neck.convs.{i}`, `neck.fusion_stage.layers.{j}`
//!   and `head.conv{1,2,3}`.
//!
//! Depth-Anything-V2 takes the hidden states after layers 2, 5, 8 and 11 (0-based; transformers'
//! `out_indices = [3, 6, 9, 12]`, where index 0 is the embedding output), applies the backbone's
//! final `layernorm` to each, drops the CLS token and reshapes the patch tokens to
//! `[B, C, H/14, W/14]` before the reassemble layers.

use candle_core::{DType, Module, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, ConvTranspose2d, ConvTranspose2dConfig, VarBuilder};

use super::dinov2::{DinoV2Backbone, DinoV2Config, bicubic_resize};
use super::{ImageEncoder, InputSpec, Normalization, conv_out};
use crate::config::check_max;

/// What a Depth-Anything head predicts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum DepthKind {
    /// Relative (affine-invariant inverse) depth, final ReLU (the V2 `-hf` checkpoints).
    Relative,
    /// Metric depth, `sigmoid * max_depth` (the `Metric-*` checkpoints).
    Metric,
}

/// Upper bounds on a [`DepthAnythingV2Config`] beyond its backbone's (checked by
/// [`DepthAnythingV2Config::validate`]), 16 to 50 times the Large model's sizes.
///
/// Channels of a reassemble projection, each of `neck_hidden_sizes` (Large: at most 1024).
pub const MAX_NECK_HIDDEN_SIZE: usize = 16_384;
/// Channels of the fusion stage, `fusion_hidden_size` (Large: 256).
pub const MAX_FUSION_HIDDEN_SIZE: usize = 16_384;
/// Channels of the head's second conv, `head_hidden_size` (32).
pub const MAX_HEAD_HIDDEN_SIZE: usize = 4096;
/// Up- or down-sampling factor of a reassemble layer, `k` or `1 / k` of `reassemble_factors`
/// (at most 4).
pub const MAX_RESIZE_FACTOR: usize = 64;

/// Configuration of the Depth-Anything-V2 feature extractor (transformers' `DepthAnythingConfig`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DepthAnythingV2Config {
    /// The DINOv2 backbone.
    pub backbone: DinoV2Config,
    /// Backbone hidden states fed to the neck (0 = embeddings, `l` = after layer `l`).
    pub out_indices: [usize; 4],
    /// Apply the backbone's final `layernorm` to those hidden states (true for Depth-Anything).
    pub apply_layernorm: bool,
    /// Channels after the reassemble projections (the encoder's output channels).
    pub neck_hidden_sizes: [usize; 4],
    /// Resize factor of each reassemble layer: an integer > 1 (transposed conv), 1 (identity) or
    /// `1 / n` (3x3 conv with stride n).
    pub reassemble_factors: [f32; 4],
    /// Channels of the fusion stage (depth head only).
    pub fusion_hidden_size: usize,
    /// Channels of the head's second conv (depth head only).
    pub head_hidden_size: usize,
    /// Relative or metric output (depth head only).
    pub depth_estimation_type: DepthKind,
    /// Output scale of the head (1 for relative, e.g. 80 for metric outdoor).
    pub max_depth: f32,
    /// Prefix of all tensors in the checkpoint (`""` for the `-hf` checkpoints, whose keys start at
    /// `backbone.` / `neck.` / `head.`).
    pub weight_prefix: String,
}

impl DepthAnythingV2Config {
    /// `depth-anything/Depth-Anything-V2-Small-hf`: ViT-S/14, layers 2/5/8/11, neck 48/96/192/384.
    pub fn small() -> Self {
        Self {
            backbone: DinoV2Config::vit_small_14(),
            out_indices: [3, 6, 9, 12],
            apply_layernorm: true,
            neck_hidden_sizes: [48, 96, 192, 384],
            reassemble_factors: [4.0, 2.0, 1.0, 0.5],
            fusion_hidden_size: 64,
            head_hidden_size: 32,
            depth_estimation_type: DepthKind::Relative,
            max_depth: 1.0,
            weight_prefix: String::new(),
        }
    }
    /// `depth-anything/Depth-Anything-V2-Base-hf`: ViT-B/14, neck 96/192/384/768, fusion 128.
    pub fn base() -> Self {
        Self {
            backbone: DinoV2Config::vit_base_14(),
            neck_hidden_sizes: [96, 192, 384, 768],
            fusion_hidden_size: 128,
            ..Self::small()
        }
    }
    /// `depth-anything/Depth-Anything-V2-Large-hf`: ViT-L/14, layers 5/12/18/24 (1-based), neck
    /// 256/512/1024/1024, fusion 256.
    pub fn large() -> Self {
        Self {
            backbone: DinoV2Config::vit_large_14(),
            out_indices: [5, 12, 18, 24],
            neck_hidden_sizes: [256, 512, 1024, 1024],
            fusion_hidden_size: 256,
            ..Self::small()
        }
    }

    /// Checks the configuration.
    pub fn validate(&self) -> crate::Result<()> {
        self.backbone.validate()?;
        for (i, &ix) in self.out_indices.iter().enumerate() {
            if ix > self.backbone.num_hidden_layers {
                config_bail!(
                    "DepthAnythingV2Config: out_indices[{i}] = {ix} exceeds the {} backbone layers",
                    self.backbone.num_hidden_layers
                );
            }
        }
        for i in 0..4 {
            let factor = match resize_kind(self.reassemble_factors[i])? {
                Resize::Up(k) | Resize::Down(k) => k,
                Resize::Identity => 1,
            };
            check_max(
                &format!("DepthAnythingV2Config.reassemble_factors[{i}] (k or 1/k)"),
                factor,
                MAX_RESIZE_FACTOR,
            )?;
            if self.neck_hidden_sizes[i] == 0 {
                config_bail!("DepthAnythingV2Config: neck_hidden_sizes[{i}] must be positive");
            }
            check_max(
                &format!("DepthAnythingV2Config.neck_hidden_sizes[{i}]"),
                self.neck_hidden_sizes[i],
                MAX_NECK_HIDDEN_SIZE,
            )?;
        }
        self.validate_head()
    }

    /// The depth head's sizes within their bounds and a finite positive `max_depth`.
    fn validate_head(&self) -> crate::Result<()> {
        check_max(
            "DepthAnythingV2Config.fusion_hidden_size",
            self.fusion_hidden_size,
            MAX_FUSION_HIDDEN_SIZE,
        )?;
        check_max(
            "DepthAnythingV2Config.head_hidden_size",
            self.head_hidden_size,
            MAX_HEAD_HIDDEN_SIZE,
        )?;
        if !(self.max_depth.is_finite() && self.max_depth > 0.0) {
            config_bail!(
                "DepthAnythingV2Config: max_depth must be finite and positive, got {}",
                self.max_depth
            );
        }
        Ok(())
    }

    /// `(H_i, W_i)` of the four reassembled maps for an input of `height x width`.
    pub fn feature_sizes(&self, height: usize, width: usize) -> [(usize, usize); 4] {
        let p = self.backbone.patch_size.max(1);
        let (ph, pw) = (height / p, width / p);
        let mut out = [(0, 0); 4];
        for i in 0..4 {
            out[i] = match resize_kind(self.reassemble_factors[i]) {
                Ok(Resize::Up(k)) => (ph * k, pw * k),
                Ok(Resize::Identity) | Err(_) => (ph, pw),
                Ok(Resize::Down(s)) => (conv_out(ph, 3, s, 1), conv_out(pw, 3, s, 1)),
            };
        }
        out
    }
}

impl Default for DepthAnythingV2Config {
    fn default() -> Self {
        Self::small()
    }
}

fn scope_prefix(prefix: &str) -> String {
    if prefix.is_empty() {
        String::new()
    } else {
        format!("{prefix}.")
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Resize {
    Up(usize),
    Identity,
    Down(usize),
}

fn resize_kind(f: f32) -> crate::Result<Resize> {
    let bad = || {
        crate::Error::Config(format!(
            "DepthAnythingV2Config: reassemble factor {f} must be an integer >= 1 or the reciprocal of an integer"
        ))
    };
    if !(f.is_finite() && f > 0.0) {
        return Err(bad());
    }
    if f >= 1.0 {
        let k = f.round();
        if (f - k).abs() > 1e-6 {
            return Err(bad());
        }
        return Ok(if k as usize == 1 {
            Resize::Identity
        } else {
            Resize::Up(k as usize)
        });
    }
    let s = (1.0 / f).round();
    if (1.0 / f - s).abs() > 1e-4 {
        return Err(bad());
    }
    Ok(Resize::Down(s as usize))
}

#[derive(Debug, Clone)]
enum ResizeLayer {
    Up(ConvTranspose2d),
    Identity,
    Down(Conv2d),
}

#[derive(Debug, Clone)]
struct ReassembleLayer {
    projection: Conv2d,
    resize: ResizeLayer,
}

/// Depth-Anything-V2 feature extractor: DINOv2 backbone plus the DPT reassemble stage, giving four
/// maps `[B, neck_hidden_sizes[i], H_i, W_i]` at strides 3.5, 7, 14 and 28 (for patch 14 and
/// factors 4, 2, 1, 0.5).
#[derive(Debug)]
pub struct DepthAnythingV2Encoder {
    cfg: DepthAnythingV2Config,
    backbone: DinoV2Backbone,
    reassemble: Vec<ReassembleLayer>,
}

impl DepthAnythingV2Encoder {
    /// Reads `{prefix}backbone.*` and `{prefix}neck.reassemble_stage.layers.*`.
    pub fn new(cfg: &DepthAnythingV2Config, vb: VarBuilder<'_>) -> crate::Result<Self> {
        cfg.validate()?;
        let vb = if cfg.weight_prefix.is_empty() {
            vb
        } else {
            vb.pp(&cfg.weight_prefix)
        };
        let backbone = DinoV2Backbone::new(&cfg.backbone, vb.pp("backbone"))?;
        let vr = vb.pp("neck").pp("reassemble_stage").pp("layers");
        let mut reassemble = Vec::with_capacity(4);
        for i in 0..4 {
            let ch = cfg.neck_hidden_sizes[i];
            let vl = vr.pp(i);
            let projection = candle_nn::conv2d(
                cfg.backbone.hidden_size,
                ch,
                1,
                Conv2dConfig::default(),
                vl.pp("projection"),
            )?;
            let resize = match resize_kind(cfg.reassemble_factors[i])? {
                Resize::Up(k) => ResizeLayer::Up(candle_nn::conv_transpose2d(
                    ch,
                    ch,
                    k,
                    ConvTranspose2dConfig {
                        stride: k,
                        ..Default::default()
                    },
                    vl.pp("resize"),
                )?),
                Resize::Identity => ResizeLayer::Identity,
                Resize::Down(s) => ResizeLayer::Down(candle_nn::conv2d(
                    ch,
                    ch,
                    3,
                    Conv2dConfig {
                        stride: s,
                        padding: 1,
                        ..Default::default()
                    },
                    vl.pp("resize"),
                )?),
            };
            reassemble.push(ReassembleLayer { projection, resize });
        }
        Ok(Self {
            cfg: cfg.clone(),
            backbone,
            reassemble,
        })
    }

    /// Loads a HuggingFace Depth-Anything(-V2) safetensors file (e.g.
    /// `Depth-Anything-V2-Small-hf/model.safetensors`), checking the backbone and reassemble tensors
    /// first (see [`super::load_checked`]); the fusion neck, the head and `mask_token` are ignored.
    pub fn load(
        cfg: &DepthAnythingV2Config,
        path: &std::path::Path,
        dtype: DType,
        device: &candle_core::Device,
    ) -> crate::Result<Self> {
        let p = scope_prefix(&cfg.weight_prefix);
        let backbone = format!("{p}backbone.");
        let reassemble = format!("{p}neck.reassemble_stage.");
        super::load_checked(
            path,
            dtype,
            device,
            |n| {
                (n.starts_with(&backbone) || n.starts_with(&reassemble))
                    && !n.ends_with("mask_token")
            },
            |vb| Self::new(cfg, vb),
        )
    }

    /// The configuration.
    pub fn config(&self) -> &DepthAnythingV2Config {
        &self.cfg
    }

    /// The DINOv2 backbone.
    pub fn backbone(&self) -> &DinoV2Backbone {
        &self.backbone
    }

    /// Four maps and the patch grid `(ph, pw)`.
    pub fn forward_with_grid(&self, image: &Tensor) -> crate::Result<(Vec<Tensor>, usize, usize)> {
        let (hs, ph, pw) =
            self.backbone
                .hidden_states(image, &self.cfg.out_indices, self.cfg.apply_layernorm)?;
        let mut out = Vec::with_capacity(4);
        for (h, layer) in hs.iter().zip(&self.reassemble) {
            let (b, n, c) = h.dims3()?;
            let map = h
                .narrow(1, 1, n - 1)?
                .transpose(1, 2)?
                .reshape((b, c, ph, pw))?;
            let y = layer.projection.forward(&map)?;
            let y = match &layer.resize {
                ResizeLayer::Up(conv) => conv.forward(&y)?,
                ResizeLayer::Identity => y,
                ResizeLayer::Down(conv) => conv.forward(&y)?,
            };
            out.push(y);
        }
        Ok((out, ph, pw))
    }
}

impl ImageEncoder for DepthAnythingV2Encoder {
    fn forward(&self, image: &Tensor) -> crate::Result<Vec<Tensor>> {
        let _span = tracing::trace_span!("depth_anything_v2_encoder").entered();
        Ok(self.forward_with_grid(image)?.0)
    }

    fn channels(&self) -> [usize; 4] {
        self.cfg.neck_hidden_sizes
    }

    fn strides(&self) -> [f32; 4] {
        let p = self.cfg.backbone.patch_size as f32;
        self.cfg.reassemble_factors.map(|f| p / f)
    }

    fn feature_sizes(&self, height: usize, width: usize) -> [(usize, usize); 4] {
        self.cfg.feature_sizes(height, width)
    }

    fn input_spec(&self) -> InputSpec {
        InputSpec {
            normalization: Normalization::IMAGENET,
            size_multiple: self.cfg.backbone.patch_size,
            min_size: self.cfg.backbone.patch_size,
        }
    }
}

#[derive(Debug, Clone)]
struct PreActResidual {
    conv1: Conv2d,
    conv2: Conv2d,
}

impl PreActResidual {
    fn new(ch: usize, vb: VarBuilder<'_>) -> crate::Result<Self> {
        let cfg = Conv2dConfig {
            padding: 1,
            ..Default::default()
        };
        Ok(Self {
            conv1: candle_nn::conv2d(ch, ch, 3, cfg, vb.pp("convolution1"))?,
            conv2: candle_nn::conv2d(ch, ch, 3, cfg, vb.pp("convolution2"))?,
        })
    }
    fn forward(&self, x: &Tensor) -> crate::Result<Tensor> {
        let y = self.conv1.forward(&x.relu()?)?;
        let y = self.conv2.forward(&y.relu()?)?;
        Ok((y + x)?)
    }
}

#[derive(Debug, Clone)]
struct FusionLayer {
    projection: Conv2d,
    residual_layer1: PreActResidual,
    residual_layer2: PreActResidual,
}

impl FusionLayer {
    fn forward(
        &self,
        x: &Tensor,
        residual: Option<&Tensor>,
        size: Option<(usize, usize)>,
    ) -> crate::Result<Tensor> {
        let mut x = x.clone();
        if let Some(r) = residual {
            let (_, _, h, w) = x.dims4()?;
            let (_, _, rh, rw) = r.dims4()?;
            let r = if (rh, rw) != (h, w) {
                r.upsample_bilinear2d(h, w, false)?
            } else {
                r.clone()
            };
            x = (x + self.residual_layer1.forward(&r)?)?;
        }
        let x = self.residual_layer2.forward(&x)?;
        let (_, _, h, w) = x.dims4()?;
        let (th, tw) = size.unwrap_or((2 * h, 2 * w));
        let x = x.upsample_bilinear2d(th, tw, true)?;
        Ok(self.projection.forward(&x)?)
    }
}

/// The full Depth-Anything-V2 model: [`DepthAnythingV2Encoder`] plus the DPT fusion neck and the
/// depth head (`neck.convs`, `neck.fusion_stage`, `head.conv{1,2,3}`). Its [`ImageEncoder`] features
/// are the encoder's; [`DepthAnythingV2::predict_depth`] gives the per-pixel prediction (relative
/// inverse depth for the V2 `-hf` checkpoints) that the cross-modal depth metric can use.
#[derive(Debug)]
pub struct DepthAnythingV2 {
    encoder: DepthAnythingV2Encoder,
    convs: Vec<Conv2d>,
    fusion: Vec<FusionLayer>,
    head_conv1: Conv2d,
    head_conv2: Conv2d,
    head_conv3: Conv2d,
}

impl DepthAnythingV2 {
    /// Reads the encoder's tensors plus `neck.convs.*`, `neck.fusion_stage.*` and `head.*`.
    pub fn new(cfg: &DepthAnythingV2Config, vb: VarBuilder<'_>) -> crate::Result<Self> {
        let encoder = DepthAnythingV2Encoder::new(cfg, vb.clone())?;
        let vb = if cfg.weight_prefix.is_empty() {
            vb
        } else {
            vb.pp(&cfg.weight_prefix)
        };
        let f = cfg.fusion_hidden_size;
        if f < 2 || cfg.head_hidden_size == 0 {
            config_bail!(
                "DepthAnythingV2Config: fusion_hidden_size must be >= 2 and head_hidden_size positive"
            );
        }
        let pad1 = Conv2dConfig {
            padding: 1,
            ..Default::default()
        };
        let vn = vb.pp("neck");
        let mut convs = Vec::with_capacity(4);
        for i in 0..4 {
            convs.push(candle_nn::conv2d_no_bias(
                cfg.neck_hidden_sizes[i],
                f,
                3,
                pad1,
                vn.pp("convs").pp(i),
            )?);
        }
        let mut fusion = Vec::with_capacity(4);
        for j in 0..4 {
            let vl = vn.pp("fusion_stage").pp("layers").pp(j);
            fusion.push(FusionLayer {
                projection: candle_nn::conv2d(
                    f,
                    f,
                    1,
                    Conv2dConfig::default(),
                    vl.pp("projection"),
                )?,
                residual_layer1: PreActResidual::new(f, vl.pp("residual_layer1"))?,
                residual_layer2: PreActResidual::new(f, vl.pp("residual_layer2"))?,
            });
        }
        let vh = vb.pp("head");
        let head_conv1 = candle_nn::conv2d(f, f / 2, 3, pad1, vh.pp("conv1"))?;
        let head_conv2 = candle_nn::conv2d(f / 2, cfg.head_hidden_size, 3, pad1, vh.pp("conv2"))?;
        let head_conv3 = candle_nn::conv2d(
            cfg.head_hidden_size,
            1,
            1,
            Conv2dConfig::default(),
            vh.pp("conv3"),
        )?;
        Ok(Self {
            encoder,
            convs,
            fusion,
            head_conv1,
            head_conv2,
            head_conv3,
        })
    }

    /// Loads a complete HuggingFace Depth-Anything(-V2) safetensors file, checking every tensor
    /// (only `mask_token`, used in pre-training, may be left unread).
    pub fn load(
        cfg: &DepthAnythingV2Config,
        path: &std::path::Path,
        dtype: DType,
        device: &candle_core::Device,
    ) -> crate::Result<Self> {
        let p = scope_prefix(&cfg.weight_prefix);
        super::load_checked(
            path,
            dtype,
            device,
            |n| n.starts_with(&p) && !n.ends_with("mask_token"),
            |vb| Self::new(cfg, vb),
        )
    }

    /// The feature encoder.
    pub fn encoder(&self) -> &DepthAnythingV2Encoder {
        &self.encoder
    }

    /// Depth prediction `[B, 14*ph, 14*pw]` (ReLU output for [`DepthKind::Relative`],
    /// `sigmoid * max_depth` for [`DepthKind::Metric`]).
    pub fn predict_depth(&self, image: &Tensor) -> crate::Result<Tensor> {
        let (feats, ph, pw) = self.encoder.forward_with_grid(image)?;
        self.depth_from_features(&feats, ph, pw)
    }

    /// The depth map of one RGB image (`height x width x 3` bytes) at its own size, as
    /// transformers' processor and `post_process_depth_estimation(target_sizes=...)` compute it:
    /// `processor` (normally [`ImageProcessor::depth_anything_v2`]), the head's prediction, bicubic
    /// resampling to `height x width` (PyTorch's kernel, [`bicubic_resize`]). Row-major; relative
    /// checkpoints give affine-invariant inverse depth, metric ones metres.
    ///
    /// [`ImageProcessor::depth_anything_v2`]: super::preprocess::ImageProcessor::depth_anything_v2
    pub fn predict_depth_map_rgb8(
        &self,
        processor: &super::preprocess::ImageProcessor,
        rgb: &[u8],
        height: usize,
        width: usize,
        device: &candle_core::Device,
    ) -> crate::Result<Vec<f32>> {
        let x = processor.preprocess(rgb, height, width, device)?;
        let d = self.predict_depth(&x)?.to_dtype(DType::F32)?;
        let (_, h, w) = d.dims3()?;
        let v = d.flatten_all()?.to_vec1::<f32>()?;
        Ok(bicubic_resize(&v, 1, h, w, height, width))
    }

    /// The fusion neck and head on precomputed encoder features.
    pub fn depth_from_features(
        &self,
        feats: &[Tensor],
        ph: usize,
        pw: usize,
    ) -> crate::Result<Tensor> {
        if feats.len() != 4 {
            input_bail!(
                "DepthAnythingV2: expected 4 feature maps, got {}",
                feats.len()
            );
        }
        let projected = feats
            .iter()
            .zip(&self.convs)
            .map(|(f, c)| c.forward(f))
            .collect::<candle_core::Result<Vec<_>>>()?;
        // deepest first
        let mut fused: Option<Tensor> = None;
        for (j, layer) in self.fusion.iter().enumerate() {
            let idx = 3 - j;
            let size = if idx > 0 {
                let (_, _, h, w) = projected[idx - 1].dims4()?;
                Some((h, w))
            } else {
                None
            };
            fused = Some(match fused {
                None => layer.forward(&projected[idx], None, size)?,
                Some(prev) => layer.forward(&prev, Some(&projected[idx]), size)?,
            });
        }
        let x = match fused {
            Some(x) => x,
            None => input_bail!("DepthAnythingV2: empty fusion stage"),
        };
        let cfg = &self.encoder.cfg;
        let p = cfg.backbone.patch_size;
        let x = self.head_conv1.forward(&x)?;
        let x = x.upsample_bilinear2d(ph * p, pw * p, true)?;
        let x = self.head_conv2.forward(&x)?.relu()?;
        let x = self.head_conv3.forward(&x)?;
        let x = match cfg.depth_estimation_type {
            DepthKind::Relative => (x.relu()? * cfg.max_depth as f64)?,
            DepthKind::Metric => (candle_nn::ops::sigmoid(&x)? * cfg.max_depth as f64)?,
        };
        Ok(x.squeeze(1)?)
    }
}

forward_image_encoder!([] DepthAnythingV2, |s| s.encoder);
