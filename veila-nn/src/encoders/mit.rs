//! SegFormer's Mix Transformer (MiT) encoder, the paper's semantic encoder `E_s`.
//!
//! Architecture and weight names follow HuggingFace transformers' `SegformerEncoder`, so the
//! safetensors of `nvidia/mit-b0` (`SegformerForImageClassification`) and
//! `nvidia/segformer-b0-finetuned-*` (`SegformerForSemanticSegmentation`) load unchanged: both store
//! the encoder under `segformer.encoder.` (the default [`MitConfig::weight_prefix`]); a bare
//! `SegformerModel` stores it under `encoder.`. Other tensors of those files (`classifier.*`,
//! `decode_head.*`) are not read. The original NVlabs/mmseg `mit_b0.pth` naming (`patch_embed1`,
//! fused `attn.kv`) is *not* supported; convert it with transformers first.
//!
//! Per stage `i` (four stages):
//! 1. overlapping patch embedding `patch_embeddings.{i}`: `Conv2d(k = patch_sizes[i],
//!    stride = strides[i], padding = k / 2)` then `LayerNorm` over channels;
//! 2. `depths[i]` pre-norm transformer layers `block.{i}.{j}`: efficient self-attention whose keys
//!    and values come from the feature map reduced by a `sr_ratios[i]` strided conv + `LayerNorm`
//!    (PVT), then Mix-FFN `Linear -> depthwise 3x3 conv -> GELU (erf) -> Linear`, both residual;
//! 3. `LayerNorm` `layer_norm.{i}` and reshape to `[B, C_i, H_i, W_i]`.
//!
//! All LayerNorms use eps `1e-5` (PyTorch's default, as in transformers). Dropout and stochastic
//! depth are inference no-ops and are omitted.

use candle_core::{Module, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, LayerNorm, Linear, VarBuilder};

use super::{
    ImageEncoder, InputSpec, Normalization, conv_out, depthwise_conv2d_tokens, map_to_tokens,
    tokens_to_map,
};

/// HuggingFace prefix of the encoder in `nvidia/mit-b*` and `nvidia/segformer-b*-*` checkpoints.
pub const HF_SEGFORMER_PREFIX: &str = "segformer.encoder";

/// Upper bounds on a [`MitConfig`] (checked by [`MitConfig::validate`]), 16 to 50 times MiT-b5's
/// sizes, so that no config from a file can ask for an absurd network.
///
/// Input channels, `num_channels` (3).
pub const MAX_NUM_CHANNELS: usize = 256;
/// Channels of a stage, each of `hidden_sizes` (MiT-b5: at most 512).
pub const MAX_HIDDEN_SIZE: usize = 16_384;
/// Transformer layers of a stage, each of `depths` (MiT-b5: at most 40).
pub const MAX_DEPTH: usize = 2048;
/// Attention heads of a stage, each of `num_attention_heads` (at most 8).
pub const MAX_HEADS: usize = 512;
/// Spatial-reduction ratio of a stage, each of `sr_ratios` (at most 8).
pub const MAX_SR_RATIO: usize = 64;
/// Kernel of a patch embedding, each of `patch_sizes` (at most 7).
pub const MAX_PATCH_SIZE: usize = 64;
/// Stride of a patch embedding, each of `strides` (at most 4; kept small so that
/// [`MitConfig::min_input_size`]'s search stays short).
pub const MAX_STRIDE: usize = 8;
/// Mix-FFN expansion of a stage, each of `mlp_ratios` (4).
pub const MAX_MLP_RATIO: usize = 64;
/// Width of the SegFormer decode head, `decoder_hidden_size` (at most 768).
pub const MAX_DECODER_HIDDEN_SIZE: usize = 16_384;
/// Classes of the SegFormer decode head, `num_labels` (ADE20k: 150).
pub const MAX_LABELS: usize = 8192;

/// Configuration of a MiT encoder (field names as in transformers' `SegformerConfig`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MitConfig {
    /// Input channels (3).
    pub num_channels: usize,
    /// Channels of the four stages.
    pub hidden_sizes: [usize; 4],
    /// Transformer layers per stage.
    pub depths: [usize; 4],
    /// Attention heads per stage (must divide the stage's hidden size).
    pub num_attention_heads: [usize; 4],
    /// Spatial-reduction ratio of the keys/values per stage (1 = none).
    pub sr_ratios: [usize; 4],
    /// Kernel of each overlapping patch embedding.
    pub patch_sizes: [usize; 4],
    /// Stride of each overlapping patch embedding.
    pub strides: [usize; 4],
    /// Mix-FFN expansion per stage.
    pub mlp_ratios: [usize; 4],
    /// LayerNorm epsilon.
    pub layer_norm_eps: f64,
    /// Prefix of the encoder's tensors in the checkpoint (`"segformer.encoder"`, `"encoder"`, or
    /// `""` when the `VarBuilder` is already positioned at the encoder).
    pub weight_prefix: String,
}

impl MitConfig {
    fn with(hidden_sizes: [usize; 4], depths: [usize; 4]) -> Self {
        Self {
            num_channels: 3,
            hidden_sizes,
            depths,
            num_attention_heads: [1, 2, 5, 8],
            sr_ratios: [8, 4, 2, 1],
            patch_sizes: [7, 3, 3, 3],
            strides: [4, 2, 2, 2],
            mlp_ratios: [4, 4, 4, 4],
            layer_norm_eps: 1e-5,
            weight_prefix: HF_SEGFORMER_PREFIX.to_string(),
        }
    }
    /// MiT-b0 (3.3 M parameters): hidden 32/64/160/256, depths 2/2/2/2.
    pub fn mit_b0() -> Self {
        Self::with([32, 64, 160, 256], [2, 2, 2, 2])
    }
    /// MiT-b1: hidden 64/128/320/512, depths 2/2/2/2.
    pub fn mit_b1() -> Self {
        Self::with([64, 128, 320, 512], [2, 2, 2, 2])
    }
    /// MiT-b2: hidden 64/128/320/512, depths 3/4/6/3.
    pub fn mit_b2() -> Self {
        Self::with([64, 128, 320, 512], [3, 4, 6, 3])
    }
    /// MiT-b3: hidden 64/128/320/512, depths 3/4/18/3.
    pub fn mit_b3() -> Self {
        Self::with([64, 128, 320, 512], [3, 4, 18, 3])
    }
    /// MiT-b4: hidden 64/128/320/512, depths 3/8/27/3.
    pub fn mit_b4() -> Self {
        Self::with([64, 128, 320, 512], [3, 8, 27, 3])
    }
    /// MiT-b5: hidden 64/128/320/512, depths 3/6/40/3.
    pub fn mit_b5() -> Self {
        Self::with([64, 128, 320, 512], [3, 6, 40, 3])
    }

    /// Checks the configuration for values the architecture cannot use.
    pub fn validate(&self) -> crate::Result<()> {
        if self.num_channels == 0 {
            config_bail!("MitConfig: num_channels must be positive");
        }
        for i in 0..4 {
            let (c, h) = (self.hidden_sizes[i], self.num_attention_heads[i]);
            if c == 0 || h == 0 || !c.is_multiple_of(h) {
                config_bail!(
                    "MitConfig: stage {i}: hidden size {c} must be a positive multiple of the {h} attention heads"
                );
            }
            if self.sr_ratios[i] == 0 || self.strides[i] == 0 || self.patch_sizes[i] == 0 {
                config_bail!(
                    "MitConfig: stage {i}: sr_ratio, stride and patch size must be positive"
                );
            }
            if self.mlp_ratios[i] == 0 {
                config_bail!("MitConfig: stage {i}: mlp_ratio must be positive");
            }
            self.validate_stage_bounds(i)?;
        }
        crate::config::check_max(
            "MitConfig.num_channels",
            self.num_channels,
            MAX_NUM_CHANNELS,
        )?;
        if self.layer_norm_eps.is_nan() || self.layer_norm_eps <= 0.0 {
            config_bail!("MitConfig: layer_norm_eps must be positive");
        }
        Ok(())
    }

    /// The sizes of stage `i` within their `MAX_*` bounds of this module.
    fn validate_stage_bounds(&self, i: usize) -> crate::Result<()> {
        for (field, value, max) in [
            ("hidden_sizes", self.hidden_sizes[i], MAX_HIDDEN_SIZE),
            ("depths", self.depths[i], MAX_DEPTH),
            (
                "num_attention_heads",
                self.num_attention_heads[i],
                MAX_HEADS,
            ),
            ("sr_ratios", self.sr_ratios[i], MAX_SR_RATIO),
            ("patch_sizes", self.patch_sizes[i], MAX_PATCH_SIZE),
            ("strides", self.strides[i], MAX_STRIDE),
            ("mlp_ratios", self.mlp_ratios[i], MAX_MLP_RATIO),
        ] {
            crate::config::check_max(&format!("MitConfig.{field}[{i}]"), value, max)?;
        }
        Ok(())
    }

    /// `(H_i, W_i)` of the four stage outputs for an input of `height x width`.
    pub fn feature_sizes(&self, height: usize, width: usize) -> [(usize, usize); 4] {
        let mut out = [(0, 0); 4];
        let (mut h, mut w) = (height, width);
        for i in 0..4 {
            let (k, s) = (self.patch_sizes[i], self.strides[i]);
            h = conv_out(h, k, s, k / 2);
            w = conv_out(w, k, s, k / 2);
            out[i] = (h, w);
        }
        out
    }

    /// Smallest input side for which every stage map is at least as large as its reduction ratio.
    pub fn min_input_size(&self) -> usize {
        let mut s = 1;
        loop {
            let sizes = self.feature_sizes(s, s);
            if (0..4).all(|i| sizes[i].0 >= self.sr_ratios[i]) {
                return s;
            }
            s += 1;
        }
    }
}

impl Default for MitConfig {
    fn default() -> Self {
        Self::mit_b0()
    }
}

fn layer_norm(size: usize, eps: f64, vb: VarBuilder<'_>) -> crate::Result<LayerNorm> {
    Ok(candle_nn::layer_norm(size, eps, vb)?)
}

/// Overlapping patch embedding: strided conv with padding `k / 2`, then LayerNorm over channels.
#[derive(Debug, Clone)]
pub struct OverlapPatchEmbed {
    proj: Conv2d,
    layer_norm: LayerNorm,
}

impl OverlapPatchEmbed {
    /// Weights `proj.{weight,bias}` and `layer_norm.{weight,bias}` under `vb`.
    pub fn new(
        in_channels: usize,
        hidden: usize,
        patch_size: usize,
        stride: usize,
        eps: f64,
        vb: VarBuilder<'_>,
    ) -> crate::Result<Self> {
        let cfg = Conv2dConfig {
            padding: patch_size / 2,
            stride,
            ..Default::default()
        };
        let proj = candle_nn::conv2d(in_channels, hidden, patch_size, cfg, vb.pp("proj"))?;
        let layer_norm = layer_norm(hidden, eps, vb.pp("layer_norm"))?;
        Ok(Self { proj, layer_norm })
    }

    /// `[B, C_in, H, W]` -> (tokens `[B, h*w, hidden]`, h, w).
    pub fn forward(&self, x: &Tensor) -> crate::Result<(Tensor, usize, usize)> {
        let y = self.proj.forward(x)?;
        let (_, _, h, w) = y.dims4()?;
        let tokens = self.layer_norm.forward(&map_to_tokens(&y)?)?;
        Ok((tokens, h, w))
    }
}

/// SegFormer attention: efficient multi-head self-attention with spatial reduction of keys and
/// values (`attention.self.*`) followed by the output projection (`attention.output.dense`).
#[derive(Debug, Clone)]
pub struct MitAttention {
    query: Linear,
    key: Linear,
    value: Linear,
    sr: Option<(Conv2d, LayerNorm)>,
    dense: Linear,
    num_heads: usize,
    head_dim: usize,
}

impl MitAttention {
    /// `vb` points at `...attention`; reads `self.{query,key,value}`, `self.sr` and
    /// `self.layer_norm` (only when `sr_ratio > 1`) and `output.dense`.
    pub fn new(
        hidden: usize,
        num_heads: usize,
        sr_ratio: usize,
        eps: f64,
        vb: VarBuilder<'_>,
    ) -> crate::Result<Self> {
        if num_heads == 0 || !hidden.is_multiple_of(num_heads) {
            input_bail!(
                "MitAttention: hidden size {hidden} is not a multiple of {num_heads} heads"
            );
        }
        let vs = vb.pp("self");
        let query = candle_nn::linear(hidden, hidden, vs.pp("query"))?;
        let key = candle_nn::linear(hidden, hidden, vs.pp("key"))?;
        let value = candle_nn::linear(hidden, hidden, vs.pp("value"))?;
        let sr = if sr_ratio > 1 {
            let cfg = Conv2dConfig {
                stride: sr_ratio,
                ..Default::default()
            };
            let conv = candle_nn::conv2d(hidden, hidden, sr_ratio, cfg, vs.pp("sr"))?;
            let ln = layer_norm(hidden, eps, vs.pp("layer_norm"))?;
            Some((conv, ln))
        } else {
            None
        };
        let dense = candle_nn::linear(hidden, hidden, vb.pp("output").pp("dense"))?;
        Ok(Self {
            query,
            key,
            value,
            sr,
            dense,
            num_heads,
            head_dim: hidden / num_heads,
        })
    }

    fn split_heads(&self, x: &Tensor) -> crate::Result<Tensor> {
        let (b, n, _) = x.dims3()?;
        Ok(x.reshape((b, n, self.num_heads, self.head_dim))?
            .transpose(1, 2)?
            .contiguous()?)
    }

    /// Tokens `[B, h*w, C]` of an `h x w` map -> `[B, h*w, C]`.
    pub fn forward(&self, x: &Tensor, h: usize, w: usize) -> crate::Result<Tensor> {
        let (b, n, c) = x.dims3()?;
        let q = self.split_heads(&self.query.forward(x)?)?;
        let kv_src = match &self.sr {
            Some((conv, ln)) => {
                let map = tokens_to_map(x, h, w)?;
                let reduced = conv.forward(&map)?;
                ln.forward(&map_to_tokens(&reduced)?)?
            }
            None => x.clone(),
        };
        let k = self.split_heads(&self.key.forward(&kv_src)?)?;
        let v = self.split_heads(&self.value.forward(&kv_src)?)?;
        let scale = 1.0 / (self.head_dim as f64).sqrt();
        let scores = (q.matmul(&k.t()?)? * scale)?;
        let probs = candle_nn::ops::softmax_last_dim(&scores)?;
        let ctx = probs.matmul(&v)?.transpose(1, 2)?.reshape((b, n, c))?;
        Ok(self.dense.forward(&ctx)?)
    }
}

/// Mix-FFN: `dense1 -> depthwise 3x3 conv (dwconv.dwconv) -> GELU -> dense2`.
#[derive(Debug, Clone)]
pub struct MixFfn {
    dense1: Linear,
    dw_weight: Tensor,
    dw_bias: Tensor,
    dense2: Linear,
}

impl MixFfn {
    /// `vb` points at `...mlp`.
    pub fn new(hidden: usize, mlp_hidden: usize, vb: VarBuilder<'_>) -> crate::Result<Self> {
        let dense1 = candle_nn::linear(hidden, mlp_hidden, vb.pp("dense1"))?;
        let vd = vb.pp("dwconv").pp("dwconv");
        let dw_weight = vd.get_with_hints(
            (mlp_hidden, 1, 3, 3),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let dw_bias = vd.get_with_hints(mlp_hidden, "bias", candle_nn::Init::Const(0.0))?;
        let dense2 = candle_nn::linear(mlp_hidden, hidden, vb.pp("dense2"))?;
        Ok(Self {
            dense1,
            dw_weight,
            dw_bias,
            dense2,
        })
    }

    /// Tokens `[B, h*w, C]` -> `[B, h*w, C]`.
    pub fn forward(&self, x: &Tensor, h: usize, w: usize) -> crate::Result<Tensor> {
        let y = self.dense1.forward(x)?;
        let y =
            depthwise_conv2d_tokens(&y, (h, w), &self.dw_weight, &self.dw_bias, 1)?.gelu_erf()?;
        Ok(self.dense2.forward(&y)?)
    }
}

/// One pre-norm MiT layer (`block.{i}.{j}`).
#[derive(Debug, Clone)]
pub struct MitLayer {
    layer_norm_1: LayerNorm,
    attention: MitAttention,
    layer_norm_2: LayerNorm,
    mlp: MixFfn,
}

impl MitLayer {
    /// `vb` points at `block.{i}.{j}`.
    pub fn new(
        hidden: usize,
        num_heads: usize,
        sr_ratio: usize,
        mlp_ratio: usize,
        eps: f64,
        vb: VarBuilder<'_>,
    ) -> crate::Result<Self> {
        Ok(Self {
            layer_norm_1: layer_norm(hidden, eps, vb.pp("layer_norm_1"))?,
            attention: MitAttention::new(hidden, num_heads, sr_ratio, eps, vb.pp("attention"))?,
            layer_norm_2: layer_norm(hidden, eps, vb.pp("layer_norm_2"))?,
            mlp: MixFfn::new(hidden, hidden * mlp_ratio, vb.pp("mlp"))?,
        })
    }

    /// Tokens `[B, h*w, C]` -> `[B, h*w, C]`.
    pub fn forward(&self, x: &Tensor, h: usize, w: usize) -> crate::Result<Tensor> {
        let a = self
            .attention
            .forward(&self.layer_norm_1.forward(x)?, h, w)?;
        let x = (x + a)?;
        let m = self.mlp.forward(&self.layer_norm_2.forward(&x)?, h, w)?;
        Ok((x + m)?)
    }
}

/// The SegFormer MiT hierarchical encoder: four maps at strides 4, 8, 16, 32.
#[derive(Debug, Clone)]
pub struct MitEncoder {
    cfg: MitConfig,
    patch_embeddings: Vec<OverlapPatchEmbed>,
    blocks: Vec<Vec<MitLayer>>,
    layer_norms: Vec<LayerNorm>,
    min_size: usize,
}

impl MitEncoder {
    /// Builds the encoder, reading `{weight_prefix}.patch_embeddings.*`, `{weight_prefix}.block.*`
    /// and `{weight_prefix}.layer_norm.*` from `vb` (missing or mis-shaped tensors are errors that
    /// name the tensor).
    pub fn new(cfg: &MitConfig, vb: VarBuilder<'_>) -> crate::Result<Self> {
        cfg.validate()?;
        let vb = if cfg.weight_prefix.is_empty() {
            vb
        } else {
            vb.pp(&cfg.weight_prefix)
        };
        let mut patch_embeddings = Vec::with_capacity(4);
        let mut blocks = Vec::with_capacity(4);
        let mut layer_norms = Vec::with_capacity(4);
        for i in 0..4 {
            let in_ch = if i == 0 {
                cfg.num_channels
            } else {
                cfg.hidden_sizes[i - 1]
            };
            let hidden = cfg.hidden_sizes[i];
            patch_embeddings.push(OverlapPatchEmbed::new(
                in_ch,
                hidden,
                cfg.patch_sizes[i],
                cfg.strides[i],
                cfg.layer_norm_eps,
                vb.pp("patch_embeddings").pp(i),
            )?);
            let mut layers = Vec::with_capacity(cfg.depths[i]);
            for j in 0..cfg.depths[i] {
                layers.push(MitLayer::new(
                    hidden,
                    cfg.num_attention_heads[i],
                    cfg.sr_ratios[i],
                    cfg.mlp_ratios[i],
                    cfg.layer_norm_eps,
                    vb.pp("block").pp(i).pp(j),
                )?);
            }
            blocks.push(layers);
            layer_norms.push(layer_norm(
                hidden,
                cfg.layer_norm_eps,
                vb.pp("layer_norm").pp(i),
            )?);
        }
        Ok(Self {
            min_size: cfg.min_input_size(),
            cfg: cfg.clone(),
            patch_embeddings,
            blocks,
            layer_norms,
        })
    }

    /// Loads a HuggingFace SegFormer / MiT safetensors file (e.g. `nvidia/mit-b0`'s
    /// `model.safetensors`), checking every encoder tensor first (see [`super::load_checked`]):
    /// tensors outside `weight_prefix` (classifier, decode head) are ignored.
    pub fn load(
        cfg: &MitConfig,
        path: &std::path::Path,
        dtype: candle_core::DType,
        device: &candle_core::Device,
    ) -> crate::Result<Self> {
        let scope = if cfg.weight_prefix.is_empty() {
            String::new()
        } else {
            format!("{}.", cfg.weight_prefix)
        };
        super::load_checked(
            path,
            dtype,
            device,
            |n| n.starts_with(&scope),
            |vb| Self::new(cfg, vb),
        )
    }

    /// The configuration.
    pub fn config(&self) -> &MitConfig {
        &self.cfg
    }
}

impl ImageEncoder for MitEncoder {
    fn forward(&self, image: &Tensor) -> crate::Result<Vec<Tensor>> {
        let _span = tracing::trace_span!("mit_encoder").entered();
        let dims = image.dims();
        if dims.len() != 4 || dims[1] != self.cfg.num_channels {
            input_bail!(
                "MitEncoder: expected an image tensor [B, {}, H, W], got shape {dims:?}",
                self.cfg.num_channels
            );
        }
        if dims[2] < self.min_size || dims[3] < self.min_size || dims[0] == 0 {
            input_bail!(
                "MitEncoder: image {}x{} is too small; with sr_ratios {:?} both sides must be at least {} pixels",
                dims[2],
                dims[3],
                self.cfg.sr_ratios,
                self.min_size
            );
        }
        let mut x = image.clone();
        let mut out = Vec::with_capacity(4);
        for i in 0..4 {
            let (mut t, h, w) = self.patch_embeddings[i].forward(&x)?;
            for layer in &self.blocks[i] {
                t = layer.forward(&t, h, w)?;
            }
            let t = self.layer_norms[i].forward(&t)?;
            x = tokens_to_map(&t, h, w)?.contiguous()?;
            out.push(x.clone());
        }
        Ok(out)
    }

    fn channels(&self) -> [usize; 4] {
        self.cfg.hidden_sizes
    }

    fn strides(&self) -> [f32; 4] {
        let mut s = [0f32; 4];
        let mut acc = 1usize;
        for i in 0..4 {
            acc *= self.cfg.strides[i];
            s[i] = acc as f32;
        }
        s
    }

    fn feature_sizes(&self, height: usize, width: usize) -> [(usize, usize); 4] {
        self.cfg.feature_sizes(height, width)
    }

    fn input_spec(&self) -> InputSpec {
        InputSpec {
            normalization: Normalization::IMAGENET,
            size_multiple: self.cfg.strides.iter().product(),
            min_size: self.min_size,
        }
    }
}

/// Configuration of [`SegFormer`]: a MiT encoder plus the all-MLP decode head of transformers'
/// `SegformerForSemanticSegmentation`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SegFormerConfig {
    /// The encoder.
    pub encoder: MitConfig,
    /// Width of the decode head (256 for b0/b1, 768 for b2..b5).
    pub decoder_hidden_size: usize,
    /// Number of output classes (19 for the Cityscapes checkpoints, 150 for ADE20k).
    pub num_labels: usize,
    /// Prefix of the head's tensors (`"decode_head"`).
    pub head_prefix: String,
    /// BatchNorm epsilon of the head (1e-5).
    pub batch_norm_eps: f64,
}

impl SegFormerConfig {
    /// `nvidia/segformer-b0-finetuned-cityscapes-*`: MiT-b0, head width 256, 19 classes.
    pub fn b0_cityscapes() -> Self {
        Self {
            encoder: MitConfig::mit_b0(),
            decoder_hidden_size: 256,
            num_labels: 19,
            head_prefix: "decode_head".to_string(),
            batch_norm_eps: 1e-5,
        }
    }

    /// Checks the encoder ([`MitConfig::validate`]) and the head: a positive width and class
    /// count within [`MAX_DECODER_HIDDEN_SIZE`] and [`MAX_LABELS`], a positive finite epsilon.
    pub fn validate(&self) -> crate::Result<()> {
        self.encoder.validate()?;
        check_head(self.decoder_hidden_size, self.num_labels)?;
        if !(self.batch_norm_eps.is_finite() && self.batch_norm_eps > 0.0) {
            config_bail!("SegFormerConfig: batch_norm_eps must be finite and positive");
        }
        Ok(())
    }
}

/// The decode head's width and class count: positive and within their bounds.
fn check_head(hidden: usize, num_labels: usize) -> crate::Result<()> {
    if hidden == 0 || num_labels == 0 {
        config_bail!("SegFormerConfig: decoder_hidden_size and num_labels must be positive");
    }
    crate::config::check_max(
        "SegFormerConfig.decoder_hidden_size",
        hidden,
        MAX_DECODER_HIDDEN_SIZE,
    )?;
    crate::config::check_max("SegFormerConfig.num_labels", num_labels, MAX_LABELS)
}

/// SegFormer's decode head (`decode_head.*`): per-scale `Linear` to the head width
/// (`linear_c.{i}.proj`), bilinear upsampling to the stride-4 grid, concatenation deepest first,
/// 1x1 conv without bias (`linear_fuse`), BatchNorm in inference mode (`batch_norm`, running
/// statistics), ReLU and a 1x1 classifier (`classifier`).
#[derive(Debug, Clone)]
pub struct SegFormerDecodeHead {
    linear_c: Vec<Linear>,
    fuse: Conv2d,
    bn_scale: Tensor,
    bn_shift: Tensor,
    classifier: Conv2d,
}

impl SegFormerDecodeHead {
    /// `vb` points at the head (`decode_head`).
    pub fn new(
        in_channels: [usize; 4],
        hidden: usize,
        num_labels: usize,
        bn_eps: f64,
        vb: VarBuilder<'_>,
    ) -> crate::Result<Self> {
        check_head(hidden, num_labels)?;
        let linear_c = (0..4)
            .map(|i| candle_nn::linear(in_channels[i], hidden, vb.pp("linear_c").pp(i).pp("proj")))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let fuse = candle_nn::conv2d_no_bias(
            4 * hidden,
            hidden,
            1,
            Conv2dConfig::default(),
            vb.pp("linear_fuse"),
        )?;
        let vbn = vb.pp("batch_norm");
        let one = candle_nn::Init::Const(1.0);
        let zero = candle_nn::Init::Const(0.0);
        let w = vbn.get_with_hints(hidden, "weight", one)?;
        let b = vbn.get_with_hints(hidden, "bias", zero)?;
        let mean = vbn.get_with_hints(hidden, "running_mean", zero)?;
        let var = vbn.get_with_hints(hidden, "running_var", one)?;
        let bn_scale = (w / (var + bn_eps)?.sqrt()?)?;
        let bn_shift = (b - (mean * &bn_scale)?)?;
        let classifier = candle_nn::conv2d(
            hidden,
            num_labels,
            1,
            Conv2dConfig::default(),
            vb.pp("classifier"),
        )?;
        Ok(Self {
            linear_c,
            fuse,
            bn_scale: bn_scale.reshape((1, hidden, 1, 1))?,
            bn_shift: bn_shift.reshape((1, hidden, 1, 1))?,
            classifier,
        })
    }

    /// Four encoder maps (finest first) -> logits `[B, num_labels, H_0, W_0]` on the finest grid.
    pub fn forward(&self, features: &[Tensor]) -> crate::Result<Tensor> {
        if features.len() != 4 {
            input_bail!(
                "SegFormerDecodeHead: expected 4 feature maps, got {}",
                features.len()
            );
        }
        let (_, _, h0, w0) = features[0].dims4()?;
        let mut ups = Vec::with_capacity(4);
        for (f, lin) in features.iter().zip(&self.linear_c) {
            let (_, _, h, w) = f.dims4()?;
            let y = tokens_to_map(&lin.forward(&map_to_tokens(f)?)?, h, w)?;
            let y = if (h, w) != (h0, w0) {
                y.upsample_bilinear2d(h0, w0, false)?
            } else {
                y.contiguous()?
            };
            ups.push(y);
        }
        ups.reverse();
        let x = Tensor::cat(&ups, 1)?;
        let x = self
            .fuse
            .forward(&x)?
            .broadcast_mul(&self.bn_scale)?
            .broadcast_add(&self.bn_shift)?
            .relu()?;
        Ok(self.classifier.forward(&x)?)
    }
}

/// SegFormer for semantic segmentation (HuggingFace `SegformerForSemanticSegmentation`, e.g.
/// `nvidia/segformer-b0-finetuned-cityscapes-1024-1024`): the pretrained `E_s` together with the
/// head that yields its label map. Its [`ImageEncoder`] features are the MiT encoder's.
#[derive(Debug, Clone)]
pub struct SegFormer {
    encoder: MitEncoder,
    head: SegFormerDecodeHead,
}

impl SegFormer {
    /// Reads `{encoder.weight_prefix}.*` and `{head_prefix}.*`.
    pub fn new(cfg: &SegFormerConfig, vb: VarBuilder<'_>) -> crate::Result<Self> {
        cfg.validate()?;
        let encoder = MitEncoder::new(&cfg.encoder, vb.clone())?;
        let vh = if cfg.head_prefix.is_empty() {
            vb
        } else {
            vb.pp(&cfg.head_prefix)
        };
        let head = SegFormerDecodeHead::new(
            cfg.encoder.hidden_sizes,
            cfg.decoder_hidden_size,
            cfg.num_labels,
            cfg.batch_norm_eps,
            vh,
        )?;
        Ok(Self { encoder, head })
    }

    /// Loads a HuggingFace `SegformerForSemanticSegmentation` safetensors file, checking every
    /// tensor (BatchNorm's `num_batches_tracked` may be left unread).
    pub fn load(
        cfg: &SegFormerConfig,
        path: &std::path::Path,
        dtype: candle_core::DType,
        device: &candle_core::Device,
    ) -> crate::Result<Self> {
        super::load_checked(
            path,
            dtype,
            device,
            |n| !n.ends_with("num_batches_tracked"),
            |vb| Self::new(cfg, vb),
        )
    }

    /// The encoder.
    pub fn encoder(&self) -> &MitEncoder {
        &self.encoder
    }

    /// Logits `[B, num_labels, ceil(H/4), ceil(W/4)]` (the head's native stride-4 grid).
    pub fn logits(&self, image: &Tensor) -> crate::Result<Tensor> {
        let feats = self.encoder.forward(image)?;
        self.head.forward(&feats)
    }

    /// Per-image label maps at the input resolution (logits upsampled bilinearly, then argmax, as
    /// transformers' `post_process_semantic_segmentation`), row-major.
    pub fn predict_labels(&self, image: &Tensor) -> crate::Result<Vec<Vec<u32>>> {
        let (_, _, h, w) = image.dims4()?;
        let logits = self
            .logits(&image.detach())?
            .to_dtype(candle_core::DType::F32)?
            .upsample_bilinear2d(h, w, false)?;
        Ok(logits.argmax(1)?.flatten_from(1)?.to_vec2::<u32>()?)
    }

    /// The class map of one RGB image (`height x width x 3` bytes) at its own size, as
    /// transformers' processor and `post_process_semantic_segmentation(target_sizes=...)` compute
    /// it: `processor` (e.g. [`ImageProcessor::segformer`](super::preprocess::ImageProcessor::segformer)`(1024, 1024)` for the Cityscapes
    /// checkpoints), logits, bilinear upsampling to `height x width`, argmax. Row-major.
    pub fn predict_label_map_rgb8(
        &self,
        processor: &super::preprocess::ImageProcessor,
        rgb: &[u8],
        height: usize,
        width: usize,
        device: &candle_core::Device,
    ) -> crate::Result<Vec<u32>> {
        let x = processor.preprocess(rgb, height, width, device)?;
        let logits = self
            .logits(&x)?
            .to_dtype(candle_core::DType::F32)?
            .upsample_bilinear2d(height, width, false)?;
        Ok(logits.argmax(1)?.flatten_all()?.to_vec1::<u32>()?)
    }
}

forward_image_encoder!([] SegFormer, |s| s.encoder);
