//! DINOv2 ViT backbone and the Depth-Anything-V2 feature extractor, the paper's depth encoder `E_d`.
//!
//! Weight names follow HuggingFace transformers' `DepthAnythingForDepthEstimation`, i.e. the
//! safetensors of `depth-anything/Depth-Anything-V2-Small-hf` (and `-Base-hf`, `-Large-hf`):
//!
//! * backbone (`Dinov2Backbone`, under `backbone.`): `embeddings.cls_token` `[1, 1, C]`,
//!   `embeddings.position_embeddings` `[1, 1 + G*G, C]` (G = 518 / 14 = 37),
//!   `embeddings.patch_embeddings.projection.{weight,bias}`,
//!   `encoder.layer.{l}.{norm1,norm2}`, `encoder.layer.{l}.attention.attention.{query,key,value}`,
//!   `encoder.layer.{l}.attention.output.dense`, `encoder.layer.{l}.layer_scale{1,2}.lambda1`,
//!   `encoder.layer.{l}.mlp.{fc1,fc2}` and `layernorm`. `embeddings.mask_token` (pre-training only)
//!   is not read. A plain `facebook/dinov2-small` checkpoint (`Dinov2Model`) has the same names
//!   without the `backbone.` prefix: build a [`DinoV2Backbone`] on the root `VarBuilder`.
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
//!
//! **Position embeddings.** When the patch grid differs from the stored `G x G` grid, the patch part
//! of the position embeddings is resampled with PyTorch's bicubic kernel (`A = -0.75`,
//! `align_corners = false`, border-clamped taps, no antialiasing) directly to the target grid
//! `(H/14, W/14)`, which is what current transformers does (`interpolate(size=...)`). The original
//! DINOv2 code instead passes a scale factor `(n + 0.1) / G`, which shifts the sampling positions by
//! a fraction of a percent of a cell; outputs therefore match transformers, not the original repo,
//! to within that tiny resampling difference. The resampling runs on the host once per grid size
//! and is cached.

use std::collections::HashMap;
use std::sync::Mutex;

use candle_core::{DType, Module, Tensor};
use candle_nn::{
    Conv2d, Conv2dConfig, ConvTranspose2d, ConvTranspose2dConfig, LayerNorm, Linear, VarBuilder,
};

use super::{ImageEncoder, InputSpec, Normalization, check_image, conv_out};

/// Configuration of a DINOv2 ViT (field names as in transformers' `Dinov2Config`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DinoV2Config {
    /// Token width.
    pub hidden_size: usize,
    /// Number of transformer layers.
    pub num_hidden_layers: usize,
    /// Attention heads (must divide `hidden_size`).
    pub num_attention_heads: usize,
    /// Patch size in pixels (14).
    pub patch_size: usize,
    /// Training image size the stored position embeddings belong to (518 = 37 patches).
    pub image_size: usize,
    /// MLP expansion.
    pub mlp_ratio: usize,
    /// LayerNorm epsilon (1e-6).
    pub layer_norm_eps: f64,
    /// Input channels (3).
    pub num_channels: usize,
}

impl DinoV2Config {
    /// ViT-S/14: hidden 384, 12 layers, 6 heads.
    pub fn vit_small_14() -> Self {
        Self {
            hidden_size: 384,
            num_hidden_layers: 12,
            num_attention_heads: 6,
            patch_size: 14,
            image_size: 518,
            mlp_ratio: 4,
            layer_norm_eps: 1e-6,
            num_channels: 3,
        }
    }
    /// ViT-B/14: hidden 768, 12 layers, 12 heads.
    pub fn vit_base_14() -> Self {
        Self {
            hidden_size: 768,
            num_attention_heads: 12,
            ..Self::vit_small_14()
        }
    }
    /// ViT-L/14: hidden 1024, 24 layers, 16 heads.
    pub fn vit_large_14() -> Self {
        Self {
            hidden_size: 1024,
            num_hidden_layers: 24,
            num_attention_heads: 16,
            ..Self::vit_small_14()
        }
    }
    /// Side of the stored position-embedding grid.
    pub fn grid_size(&self) -> usize {
        self.image_size / self.patch_size.max(1)
    }
    /// Checks the configuration.
    pub fn validate(&self) -> crate::Result<()> {
        let (c, h) = (self.hidden_size, self.num_attention_heads);
        if c == 0 || h == 0 || !c.is_multiple_of(h) {
            config_bail!(
                "DinoV2Config: hidden size {c} must be a positive multiple of the {h} heads"
            );
        }
        if self.patch_size == 0 || self.grid_size() == 0 {
            config_bail!(
                "DinoV2Config: patch size {} and image size {} give an empty position grid",
                self.patch_size,
                self.image_size
            );
        }
        if self.mlp_ratio == 0 || self.num_channels == 0 || self.num_hidden_layers == 0 {
            config_bail!("DinoV2Config: mlp_ratio, num_channels and layers must be positive");
        }
        if self.layer_norm_eps.is_nan() || self.layer_norm_eps <= 0.0 {
            config_bail!("DinoV2Config: layer_norm_eps must be positive");
        }
        Ok(())
    }
}

fn cubic_weights(t: f32) -> [f32; 4] {
    // PyTorch's upsample_bicubic2d kernel (Keys, A = -0.75).
    const A: f32 = -0.75;
    let near = |x: f32| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    let far = |x: f32| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;
    [far(t + 1.0), near(t), near(1.0 - t), far(2.0 - t)]
}

/// Resamples a channel-major `[C, in_h, in_w]` buffer to `[C, out_h, out_w]` with PyTorch's bicubic
/// interpolation (`mode="bicubic"`, `align_corners=False`, `antialias=False`): source coordinate
/// `(o + 0.5) * in / out - 0.5`, Keys kernel with `A = -0.75`, taps outside the image clamped to the
/// border.
///
/// # Panics
/// Never on consistent input; `src.len()` must be `channels * in_h * in_w` (checked, returns an
/// empty vector otherwise).
pub fn bicubic_resize(
    src: &[f32],
    channels: usize,
    in_h: usize,
    in_w: usize,
    out_h: usize,
    out_w: usize,
) -> Vec<f32> {
    if src.len() != channels * in_h * in_w || in_h == 0 || in_w == 0 {
        return Vec::new();
    }
    let taps = |in_size: usize, out_size: usize| -> Vec<([usize; 4], [f32; 4])> {
        let scale = in_size as f32 / out_size as f32;
        (0..out_size)
            .map(|o| {
                let s = (o as f32 + 0.5) * scale - 0.5;
                let f = s.floor();
                let t = s - f;
                let base = f as isize;
                let mut idx = [0usize; 4];
                for (k, slot) in idx.iter_mut().enumerate() {
                    *slot = (base - 1 + k as isize).clamp(0, in_size as isize - 1) as usize;
                }
                (idx, cubic_weights(t))
            })
            .collect()
    };
    let ty = taps(in_h, out_h);
    let tx = taps(in_w, out_w);
    let mut out = vec![0f32; channels * out_h * out_w];
    let mut row = vec![0f32; in_w];
    for c in 0..channels {
        let plane = &src[c * in_h * in_w..(c + 1) * in_h * in_w];
        for (oy, (iy, wy)) in ty.iter().enumerate() {
            // vertical pass into one row, then horizontal pass
            for x in 0..in_w {
                let mut acc = 0f32;
                for k in 0..4 {
                    acc += wy[k] * plane[iy[k] * in_w + x];
                }
                row[x] = acc;
            }
            let dst = &mut out[(c * out_h + oy) * out_w..(c * out_h + oy + 1) * out_w];
            for (ox, (ix, wx)) in tx.iter().enumerate() {
                let mut acc = 0f32;
                for k in 0..4 {
                    acc += wx[k] * row[ix[k]];
                }
                dst[ox] = acc;
            }
        }
    }
    out
}

/// One DINOv2 transformer layer (`encoder.layer.{l}`).
#[derive(Debug, Clone)]
pub struct DinoV2Layer {
    norm1: LayerNorm,
    query: Linear,
    key: Linear,
    value: Linear,
    dense: Linear,
    lambda1: Tensor,
    norm2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
    lambda2: Tensor,
    num_heads: usize,
    head_dim: usize,
}

impl DinoV2Layer {
    /// `vb` points at `encoder.layer.{l}`.
    pub fn new(cfg: &DinoV2Config, vb: VarBuilder<'_>) -> crate::Result<Self> {
        let c = cfg.hidden_size;
        let va = vb.pp("attention");
        let vs = va.pp("attention");
        let ones = candle_nn::Init::Const(1.0);
        Ok(Self {
            norm1: candle_nn::layer_norm(c, cfg.layer_norm_eps, vb.pp("norm1"))?,
            query: candle_nn::linear(c, c, vs.pp("query"))?,
            key: candle_nn::linear(c, c, vs.pp("key"))?,
            value: candle_nn::linear(c, c, vs.pp("value"))?,
            dense: candle_nn::linear(c, c, va.pp("output").pp("dense"))?,
            lambda1: vb.pp("layer_scale1").get_with_hints(c, "lambda1", ones)?,
            norm2: candle_nn::layer_norm(c, cfg.layer_norm_eps, vb.pp("norm2"))?,
            fc1: candle_nn::linear(c, c * cfg.mlp_ratio, vb.pp("mlp").pp("fc1"))?,
            fc2: candle_nn::linear(c * cfg.mlp_ratio, c, vb.pp("mlp").pp("fc2"))?,
            lambda2: vb.pp("layer_scale2").get_with_hints(c, "lambda1", ones)?,
            num_heads: cfg.num_attention_heads,
            head_dim: c / cfg.num_attention_heads,
        })
    }

    fn heads(&self, x: &Tensor) -> crate::Result<Tensor> {
        let (b, n, _) = x.dims3()?;
        Ok(x.reshape((b, n, self.num_heads, self.head_dim))?
            .transpose(1, 2)?
            .contiguous()?)
    }

    /// Tokens `[B, N, C]` -> `[B, N, C]`.
    pub fn forward(&self, x: &Tensor) -> crate::Result<Tensor> {
        let (b, n, c) = x.dims3()?;
        let y = self.norm1.forward(x)?;
        let q = self.heads(&self.query.forward(&y)?)?;
        let k = self.heads(&self.key.forward(&y)?)?;
        let v = self.heads(&self.value.forward(&y)?)?;
        let scores = (q.matmul(&k.t()?)? * (1.0 / (self.head_dim as f64).sqrt()))?;
        let probs = candle_nn::ops::softmax_last_dim(&scores)?;
        let ctx = probs.matmul(&v)?.transpose(1, 2)?.reshape((b, n, c))?;
        let a = self.dense.forward(&ctx)?.broadcast_mul(&self.lambda1)?;
        let x = (x + a)?;
        let m = self
            .fc2
            .forward(&self.fc1.forward(&self.norm2.forward(&x)?)?.gelu_erf()?)?
            .broadcast_mul(&self.lambda2)?;
        Ok((x + m)?)
    }
}

/// The DINOv2 ViT backbone (`Dinov2Backbone` / `Dinov2Model` weights, final `layernorm` included).
#[derive(Debug)]
pub struct DinoV2Backbone {
    cfg: DinoV2Config,
    patch: Conv2d,
    cls_token: Tensor,
    position_embeddings: Tensor,
    layers: Vec<DinoV2Layer>,
    layernorm: LayerNorm,
    pos_cache: Mutex<HashMap<(usize, usize), Tensor>>,
}

impl DinoV2Backbone {
    /// `vb` points at the backbone root (`backbone` in Depth-Anything checkpoints, the file root for
    /// `facebook/dinov2-*`).
    pub fn new(cfg: &DinoV2Config, vb: VarBuilder<'_>) -> crate::Result<Self> {
        cfg.validate()?;
        let c = cfg.hidden_size;
        let ve = vb.pp("embeddings");
        let g = cfg.grid_size();
        let init = candle_nn::Init::Randn {
            mean: 0.0,
            stdev: 0.02,
        };
        let cls_token = ve.get_with_hints((1, 1, c), "cls_token", init)?;
        let position_embeddings =
            ve.get_with_hints((1, 1 + g * g, c), "position_embeddings", init)?;
        let pcfg = Conv2dConfig {
            stride: cfg.patch_size,
            ..Default::default()
        };
        let patch = candle_nn::conv2d(
            cfg.num_channels,
            c,
            cfg.patch_size,
            pcfg,
            ve.pp("patch_embeddings").pp("projection"),
        )?;
        let mut layers = Vec::with_capacity(cfg.num_hidden_layers);
        for l in 0..cfg.num_hidden_layers {
            layers.push(DinoV2Layer::new(cfg, vb.pp("encoder").pp("layer").pp(l))?);
        }
        let layernorm = candle_nn::layer_norm(c, cfg.layer_norm_eps, vb.pp("layernorm"))?;
        Ok(Self {
            cfg: cfg.clone(),
            patch,
            cls_token,
            position_embeddings,
            layers,
            layernorm,
            pos_cache: Mutex::new(HashMap::new()),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &DinoV2Config {
        &self.cfg
    }

    /// Position embeddings `[1, 1 + ph*pw, C]` for a `ph x pw` patch grid (bicubic, cached).
    pub fn position_embeddings_for(&self, ph: usize, pw: usize) -> crate::Result<Tensor> {
        let g = self.cfg.grid_size();
        if (ph, pw) == (g, g) {
            return Ok(self.position_embeddings.clone());
        }
        if let Ok(cache) = self.pos_cache.lock()
            && let Some(t) = cache.get(&(ph, pw))
        {
            return Ok(t.clone());
        }
        let c = self.cfg.hidden_size;
        let dtype = self.position_embeddings.dtype();
        let device = self.position_embeddings.device().clone();
        let cls = self.position_embeddings.narrow(1, 0, 1)?;
        // [1, G*G, C] -> [C, G, G] on the host, f32
        let patch = self
            .position_embeddings
            .narrow(1, 1, g * g)?
            .squeeze(0)?
            .t()?
            .to_dtype(DType::F32)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let resized = bicubic_resize(&patch, c, g, g, ph, pw);
        let patch = Tensor::from_vec(resized, (c, ph * pw), &device)?
            .t()?
            .unsqueeze(0)?
            .to_dtype(dtype)?;
        let pos = Tensor::cat(&[&cls, &patch], 1)?.contiguous()?;
        if let Ok(mut cache) = self.pos_cache.lock() {
            cache.insert((ph, pw), pos.clone());
        }
        Ok(pos)
    }

    /// Embedding output `[B, 1 + ph*pw, C]` (CLS first) and the patch grid `(ph, pw)`. Trailing
    /// pixels beyond a multiple of the patch size are ignored, as in PyTorch's strided conv.
    pub fn embed(&self, image: &Tensor) -> crate::Result<(Tensor, usize, usize)> {
        let (b, _, _) = check_image(image, self.cfg.patch_size, "DinoV2Backbone")?;
        let x = self.patch.forward(image)?;
        let (_, c, ph, pw) = x.dims4()?;
        let tokens = x.flatten_from(2)?.transpose(1, 2)?;
        let cls = self.cls_token.expand((b, 1, c))?;
        let tokens = Tensor::cat(&[&cls, &tokens], 1)?;
        let tokens = tokens.broadcast_add(&self.position_embeddings_for(ph, pw)?)?;
        Ok((tokens, ph, pw))
    }

    /// Hidden states at the requested indices (0 = embedding output, `l` = after layer `l`,
    /// 1-based as transformers' `out_indices`), in the order requested, each `[B, 1 + ph*pw, C]`,
    /// optionally passed through the final `layernorm`; plus the patch grid. Layers after the
    /// deepest requested index are not run.
    pub fn hidden_states(
        &self,
        image: &Tensor,
        indices: &[usize],
        apply_layernorm: bool,
    ) -> crate::Result<(Vec<Tensor>, usize, usize)> {
        let _span = tracing::trace_span!("dinov2_backbone").entered();
        let max = indices.iter().copied().max().unwrap_or(0);
        if max > self.layers.len() {
            input_bail!(
                "DinoV2Backbone: hidden-state index {max} requested but the model has {} layers",
                self.layers.len()
            );
        }
        let (mut x, ph, pw) = self.embed(image)?;
        let mut found: Vec<Option<Tensor>> = vec![None; indices.len()];
        for l in 0..=max {
            if l > 0 {
                x = self.layers[l - 1].forward(&x)?;
            }
            for (slot, &want) in found.iter_mut().zip(indices) {
                if want == l {
                    *slot = Some(if apply_layernorm {
                        self.layernorm.forward(&x)?
                    } else {
                        x.clone()
                    });
                }
            }
        }
        let out = found
            .into_iter()
            .map(|t| t.ok_or_else(|| candle_core::Error::Msg("missing hidden state".into())))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok((out, ph, pw))
    }
}

/// What a Depth-Anything head predicts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum DepthKind {
    /// Relative (affine-invariant inverse) depth, final ReLU (the V2 `-hf` checkpoints).
    Relative,
    /// Metric depth, `sigmoid * max_depth` (the `Metric-*` checkpoints).
    Metric,
}

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
            resize_kind(self.reassemble_factors[i])?;
            if self.neck_hidden_sizes[i] == 0 {
                config_bail!("DepthAnythingV2Config: neck_hidden_sizes[{i}] must be positive");
            }
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

/// A plain DINOv2 backbone as an image encoder: the hidden states after four layers (final
/// `layernorm` applied, CLS token dropped), each reshaped to the `H/14 x W/14` patch grid. All four
/// maps share stride 14 and `hidden_size` channels; unlike Depth-Anything's reassemble stage nothing
/// is learned on top, so a pyramid is not made up.
#[derive(Debug)]
pub struct DinoV2Encoder {
    backbone: DinoV2Backbone,
    out_indices: [usize; 4],
}

impl DinoV2Encoder {
    /// Layers 3, 6, 9, 12 for 12-layer models, 6, 12, 18, 24 for ViT-L (1-based, as
    /// transformers' `out_indices`).
    pub fn default_out_indices(cfg: &DinoV2Config) -> [usize; 4] {
        let n = cfg.num_hidden_layers;
        [n / 4, n / 2, 3 * n / 4, n]
    }

    /// `vb` points at the backbone root (the file root of `facebook/dinov2-*`, `backbone` in a
    /// Depth-Anything checkpoint).
    pub fn new(
        cfg: &DinoV2Config,
        out_indices: [usize; 4],
        vb: VarBuilder<'_>,
    ) -> crate::Result<Self> {
        for (i, &ix) in out_indices.iter().enumerate() {
            if ix == 0 || ix > cfg.num_hidden_layers {
                config_bail!(
                    "DinoV2Encoder: out_indices[{i}] = {ix} must be in 1..={}",
                    cfg.num_hidden_layers
                );
            }
        }
        Ok(Self {
            backbone: DinoV2Backbone::new(cfg, vb)?,
            out_indices,
        })
    }

    /// The backbone.
    pub fn backbone(&self) -> &DinoV2Backbone {
        &self.backbone
    }
}

impl ImageEncoder for DinoV2Encoder {
    fn forward(&self, image: &Tensor) -> crate::Result<Vec<Tensor>> {
        let _span = tracing::trace_span!("dinov2_encoder").entered();
        let (hs, ph, pw) = self
            .backbone
            .hidden_states(image, &self.out_indices, true)?;
        hs.iter()
            .map(|h| {
                let (b, n, c) = h.dims3()?;
                Ok(h.narrow(1, 1, n - 1)?
                    .transpose(1, 2)?
                    .reshape((b, c, ph, pw))?)
            })
            .collect()
    }

    fn channels(&self) -> [usize; 4] {
        [self.backbone.config().hidden_size; 4]
    }

    fn strides(&self) -> [f32; 4] {
        [self.backbone.config().patch_size as f32; 4]
    }

    fn feature_sizes(&self, height: usize, width: usize) -> [(usize, usize); 4] {
        let p = self.backbone.config().patch_size.max(1);
        [(height / p, width / p); 4]
    }

    fn input_spec(&self) -> InputSpec {
        let p = self.backbone.config().patch_size;
        InputSpec {
            normalization: Normalization::IMAGENET,
            size_multiple: p,
            min_size: p,
        }
    }
}
