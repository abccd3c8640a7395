//! The DINOv2 ViT backbone ([`DinoV2Backbone`]) and a plain DINOv2 as an image encoder
//! ([`DinoV2Encoder`]); the Depth-Anything-V2 model built on it is [`super::depth_anything`].
//!
//! Weight names follow HuggingFace transformers: a `facebook/dinov2-small` checkpoint
//! (`Dinov2Model`) at the root, or Depth-Anything-V2's backbone (`Dinov2Backbone`, under
//! `backbone.`): `embeddings.cls_token` `[1, 1, C]`,
//! `embeddings.position_embeddings` `[1, 1 + G*G, C]` (G = 518 / 14 = 37),
//! `embeddings.patch_embeddings.projection.{weight,bias}`,
//! `encoder.layer.{l}.{norm1,norm2}`, `encoder.layer.{l}.attention.attention.{query,key,value}`,
//! `encoder.layer.{l}.attention.output.dense`, `encoder.layer.{l}.layer_scale{1,2}.lambda1`,
//! `encoder.layer.{l}.mlp.{fc1,fc2}` and `layernorm`. `embeddings.mask_token` (pre-training only)
//! is not read.
//!
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
use candle_nn::{Conv2d, Conv2dConfig, LayerNorm, Linear, VarBuilder};

use super::{ImageEncoder, InputSpec, Normalization, check_image};

/// Upper bounds on a [`DinoV2Config`] (checked by [`DinoV2Config::validate`]), 16 to 50 times
/// ViT-L/14's sizes, so that no config from a file can ask for an absurd network.
///
/// Token width, `hidden_size` (ViT-L: 1024).
pub const MAX_HIDDEN_SIZE: usize = 16_384;
/// Transformer layers, `num_hidden_layers` (ViT-L: 24).
pub const MAX_LAYERS: usize = 1024;
/// Attention heads, `num_attention_heads` (ViT-L: 16).
pub const MAX_HEADS: usize = 512;
/// Patch size in pixels, `patch_size` (14).
pub const MAX_PATCH_SIZE: usize = 256;
/// Side of the stored position grid, `image_size / patch_size` (37).
pub const MAX_GRID_SIZE: usize = 1024;
/// MLP expansion, `mlp_ratio` (4).
pub const MAX_MLP_RATIO: usize = 64;
/// Input channels, `num_channels` (3).
pub const MAX_NUM_CHANNELS: usize = 256;

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
        self.validate_bounds()
    }

    /// Every size within its `MAX_*` bound of this module.
    fn validate_bounds(&self) -> crate::Result<()> {
        for (field, value, max) in [
            ("hidden_size", self.hidden_size, MAX_HIDDEN_SIZE),
            ("num_hidden_layers", self.num_hidden_layers, MAX_LAYERS),
            ("num_attention_heads", self.num_attention_heads, MAX_HEADS),
            ("patch_size", self.patch_size, MAX_PATCH_SIZE),
            ("image_size / patch_size", self.grid_size(), MAX_GRID_SIZE),
            ("mlp_ratio", self.mlp_ratio, MAX_MLP_RATIO),
            ("num_channels", self.num_channels, MAX_NUM_CHANNELS),
        ] {
            crate::config::check_max(&format!("DinoV2Config.{field}"), value, max)?;
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
