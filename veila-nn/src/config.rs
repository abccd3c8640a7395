//! Serde configuration of the denoiser, with the `tiny` (CPU) and `paper` presets and a switch for
//! every ablation of the paper.

use serde::{Deserialize, Serialize};
use veila_geom::{BeamLayout, FourierEncoding, LidarSensor};

use crate::error::{Error, Result};

/// Upper bounds on the sizes of a [`DenoiserConfig`] (checked by [`DenoiserConfig::validate`]):
/// about 50 times what the [`DenoiserConfig::paper`] preset uses, so that no config a bundle or
/// checkpoint carries can ask for an absurd network (the weights of a valid config are bounded
/// again, in total, by [`crate::weights::MAX_PARAMETERS`]).
///
/// Input and output channels of the range image (the presets use 3, residual models 6).
pub const MAX_IO_CHANNELS: usize = 256;
/// Channels of the first level (`paper`: 64).
pub const MAX_BASE_CHANNELS: usize = 4096;
/// Channels of any level, `base_channels * channel_mults[l]` (`paper`: 512).
pub const MAX_LEVEL_CHANNELS: usize = 16_384;
/// U-Net levels, the length of `channel_mults` (the presets use 4; the range image must be
/// divisible by `2^(levels - 1)`).
pub const MAX_LEVELS: usize = 8;
/// Residual blocks per level (`paper`: 3).
pub const MAX_RES_BLOCKS: usize = 128;
/// The GroupNorm group bound `norm_groups` (the presets use 8).
pub const MAX_NORM_GROUPS: usize = 1024;
/// Width of the sinusoidal time features, `time.dim` (`paper`: 128).
pub const MAX_TIME_DIM: usize = 8192;
/// Attention heads of PFC and GCMA (`paper`: 8 and 4).
pub const MAX_HEADS: usize = 512;
/// Width of GCMA's queries, keys and values, `gcma.attn_dim` (`paper`: 64).
pub const MAX_ATTN_DIM: usize = 4096;
/// Channels of an encoder feature map or a fused map (`semantic_channels`, `depth_channels`,
/// `cond_channels`; `paper`: at most 384).
pub const MAX_FEATURE_CHANNELS: usize = 16_384;
/// Feature scales, the length of `feature_sizes` (the presets use 4).
pub const MAX_FEATURE_SCALES: usize = 16;
/// Pixels `H_i * W_i` of one feature map (`paper`: 96 x 312 = 29 952).
pub const MAX_FEATURE_PIXELS: usize = 1 << 21;
/// Camera views per sample, `conditioning.num_views` (the presets use 1 or 3).
pub const MAX_VIEWS: usize = 64;
/// The multiplier of the time input, `time.input_scale` (the presets use 1000 for a time in
/// `[0, 1]`; 1 suits a step index or a log-SNR): at most 100 times the presets'. Beyond, the
/// sinusoids of the time embedding are noise in `f32` (1e300 gave an empty scan).
pub const MAX_TIME_INPUT_SCALE: f64 = 1e5;

/// Sinusoidal embedding of the per-sample noise level.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TimeEmbeddingConfig {
    /// Width of the sinusoidal features (even).
    pub dim: usize,
    /// Longest period of the sinusoids.
    pub max_period: f64,
    /// The scalar the caller passes (diffusion time in `[0, 1]`, a step index or a log-SNR) is multiplied
    /// by this before the sinusoids (e.g. 1000 for continuous `t`, 1 for integer steps or log-SNR).
    pub input_scale: f64,
}

/// Which image cues condition the model (the "E_s only" / "E_d only" ablations).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Cues {
    /// Semantic (E_s) and depth (E_d) features, the full model.
    Both,
    /// Semantic features only.
    SemanticOnly,
    /// Depth features only.
    DepthOnly,
}

/// How semantic and depth features are fused when both are used (the "w/o CACM" ablation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Fusion {
    /// Confidence-aware conditioning, equations 4-6.
    Cacm,
    /// Plain concatenation followed by a 1x1 convolution.
    Concat,
}

/// Geometric cross-modal alignment (equations 7-10).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GcmaConfig {
    /// U-Net levels (0 = full resolution) that get a GCMA block after their residual blocks. Level `l`
    /// attends to feature scale `min(l, num_scales - 1)`.
    pub levels: Vec<usize>,
    /// Also place a GCMA block (own weights) at the same levels of the decoder.
    pub decoder: bool,
    /// Width of queries, keys and values.
    pub attn_dim: usize,
    /// Number of attention heads (`attn_dim % num_heads == 0`); `d_h = attn_dim / num_heads`.
    pub num_heads: usize,
    /// Fourier encoding `gamma` of the sampled 3-D points (LiDAR frame, metres) fed to the query MLP.
    pub point_encoding: FourierEncoding,
}

/// Image conditioning: encoder feature widths, fusion, alignment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConditioningConfig {
    /// Which cues are used.
    pub cues: Cues,
    /// How the cues are fused when both are used.
    pub fusion: Fusion,
    /// Channels `D_i^s` of the semantic encoder's feature maps, one per scale (ignored for depth-only).
    pub semantic_channels: Vec<usize>,
    /// Channels `D_i^d` of the depth encoder's feature maps, one per scale (ignored for semantic-only).
    pub depth_channels: Vec<usize>,
    /// Resolution `[H_i, W_i]` of the fused maps `F^(i)`, one per scale: the semantic features must have
    /// this size; depth features are resized to it bilinearly.
    pub feature_sizes: Vec<[usize; 2]>,
    /// Channels of the fused maps `F^(i)`, one per scale.
    pub cond_channels: Vec<usize>,
    /// `delta` of equation 6.
    pub cacm_delta: f32,
    /// Number of camera views per sample (multi-camera conditioning concatenates their samples).
    pub num_views: usize,
    /// Geometric alignment. `None` is the "w/o GCMA" ablation: the image condition then enters only
    /// globally (the deepest fused map, mean-pooled over pixels and views, added to the time embedding
    /// through a linear layer), with no pixel-level alignment.
    pub gcma: Option<GcmaConfig>,
}

impl ConditioningConfig {
    /// Feature sizes of a 4-scale pyramid with strides 4, 8, 16, 32 (SegFormer MiT convention, with
    /// `ceil` like a stride-2 conv with padding) for an input image of `image_h x image_w`.
    pub fn pyramid_sizes(image_h: usize, image_w: usize) -> Vec<[usize; 2]> {
        [4usize, 8, 16, 32]
            .iter()
            .map(|s| [image_h.div_ceil(*s), image_w.div_ceil(*s)])
            .collect()
    }

    /// Takes channel counts and feature sizes from the encoders that will feed the model, for input
    /// images of `image_h x image_w` (the fused maps get the semantic encoder's resolution, or the depth
    /// encoder's when there is no semantic encoder). `cues` is set to match which encoders are given.
    pub fn set_encoders(
        &mut self,
        semantic: Option<&dyn crate::encoders::ImageEncoder>,
        depth: Option<&dyn crate::encoders::ImageEncoder>,
        image_h: usize,
        image_w: usize,
    ) -> Result<()> {
        let sizes = |e: &dyn crate::encoders::ImageEncoder| -> Vec<[usize; 2]> {
            e.feature_sizes(image_h, image_w)
                .iter()
                .map(|(h, w)| [*h, *w])
                .collect()
        };
        match (semantic, depth) {
            (None, None) => {
                return Err(Error::Config(
                    "set_encoders needs at least one encoder".into(),
                ));
            }
            (Some(s), d) => {
                self.semantic_channels = s.channels().to_vec();
                self.feature_sizes = sizes(s);
                if let Some(d) = d {
                    self.depth_channels = d.channels().to_vec();
                }
                self.cues = if d.is_some() {
                    Cues::Both
                } else {
                    Cues::SemanticOnly
                };
            }
            (None, Some(d)) => {
                self.depth_channels = d.channels().to_vec();
                self.feature_sizes = sizes(d);
                self.cues = Cues::DepthOnly;
            }
        }
        if self.cond_channels.len() != self.feature_sizes.len() {
            let last = self.cond_channels.last().copied().unwrap_or(64);
            self.cond_channels.resize(self.feature_sizes.len(), last);
        }
        Ok(())
    }

    /// Number of feature scales.
    pub fn num_scales(&self) -> usize {
        self.feature_sizes.len()
    }

    /// The feature scale a U-Net level attends to.
    pub fn scale_for_level(&self, level: usize) -> usize {
        level.min(self.num_scales().saturating_sub(1))
    }
}

/// Global self-attention at the deepest level (Panoramic Feature Coherence).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PfcConfig {
    /// Number of attention heads (must divide the deepest level's channels).
    pub num_heads: usize,
}

/// The full denoiser configuration. Serialises to JSON next to checkpoints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DenoiserConfig {
    /// The LiDAR: its `rows x cols` is the range-image size `H x W`; its ray directions feed the ray
    /// features and (through [`crate::GcmaGeometry`]) the epipolar sampling.
    pub sensor: LidarSensor,
    /// Input channels of the range image (e.g. 3: depth, intensity, ray-drop).
    pub in_channels: usize,
    /// Output channels (usually `in_channels`).
    pub out_channels: usize,
    /// Channels of the first level.
    pub base_channels: usize,
    /// Channel multiplier of every level; the number of levels is its length (`H` and `W` must be
    /// divisible by `2^(levels-1)`).
    pub channel_mults: Vec<usize>,
    /// Residual blocks per level in the encoder (the decoder has one more, as in ADM).
    pub num_res_blocks: usize,
    /// Maximum GroupNorm groups (the largest divisor of the channel count not above it is used).
    pub norm_groups: usize,
    /// Residual connections are scaled by this (`1/sqrt(2)` as in R2DM / Imagen).
    pub residual_scale: f32,
    /// Noise-level embedding.
    pub time: TimeEmbeddingConfig,
    /// Fourier features of each pixel's unit ray direction, concatenated to the input (`None`: off).
    pub ray_features: Option<FourierEncoding>,
    /// Panoramic Feature Coherence (`None`: the "w/o PFC" ablation).
    pub pfc: Option<PfcConfig>,
    /// Image conditioning (`None`: unconditional, an R2DM-like baseline).
    pub conditioning: Option<ConditioningConfig>,
}

impl DenoiserConfig {
    /// A CPU-sized model at 32 x 512 (HDL-64E field of view, uniform rows): 32 base channels, 4 levels,
    /// 1 residual block per level, CACM + GCMA (encoder levels) + PFC, 96 x 320 conditioning images
    /// encoded by two default [`crate::encoders::small_cnn::SmallCnn`]s (16/32/64/96 channels, strides
    /// 4-32).
    pub fn tiny() -> Self {
        let sensor = LidarSensor {
            rows: 32,
            cols: 512,
            beams: BeamLayout::Uniform,
            ..LidarSensor::hdl64e()
        };
        DenoiserConfig {
            sensor,
            in_channels: 3,
            out_channels: 3,
            base_channels: 32,
            channel_mults: vec![1, 2, 2, 4],
            num_res_blocks: 1,
            norm_groups: 8,
            residual_scale: std::f32::consts::FRAC_1_SQRT_2,
            time: TimeEmbeddingConfig {
                dim: 64,
                max_period: 10_000.0,
                input_scale: 1000.0,
            },
            ray_features: Some(FourierEncoding {
                num_freqs: 4,
                scale: 1.0,
                include_input: true,
            }),
            pfc: Some(PfcConfig { num_heads: 4 }),
            conditioning: Some(ConditioningConfig {
                cues: Cues::Both,
                fusion: Fusion::Cacm,
                semantic_channels: vec![16, 32, 64, 96],
                depth_channels: vec![16, 32, 64, 96],
                feature_sizes: ConditioningConfig::pyramid_sizes(96, 320),
                cond_channels: vec![32, 32, 64, 64],
                cacm_delta: 1e-6,
                num_views: 1,
                gcma: Some(GcmaConfig {
                    levels: vec![0, 1, 2, 3],
                    decoder: false,
                    attn_dim: 32,
                    num_heads: 4,
                    point_encoding: FourierEncoding {
                        num_freqs: 4,
                        scale: 1.0 / 80.0,
                        include_input: true,
                    },
                }),
            }),
        }
    }

    /// The bundled CPU model (`models/default`, trained by `cargo xtask train-default` in well under
    /// two hours on two CPU cores): 32 x 256 range images (HDL-64E field of view, uniform rows), 16
    /// base channels, 4 levels, 1 residual block per level, CACM, GCMA at the three coarser encoder
    /// levels (the full-resolution level is left out for speed), PFC with 2 heads, 96 x 320
    /// conditioning images encoded by two default small CNNs. About 0.8 M parameters.
    pub fn small() -> Self {
        let mut cfg = Self::tiny();
        cfg.sensor.cols = 256;
        cfg.base_channels = 16;
        cfg.time.dim = 32;
        cfg.pfc = Some(PfcConfig { num_heads: 2 });
        if let Some(c) = cfg.conditioning.as_mut() {
            c.cond_channels = vec![16, 16, 32, 32];
            if let Some(g) = c.gcma.as_mut() {
                g.levels = vec![1, 2, 3];
                g.attn_dim = 16;
                g.num_heads = 2;
            }
        }
        cfg
    }

    /// The paper-sized model at 64 x 1024 (HDL-64E): R2DM's Efficient-U-Net widths (base 64, multipliers
    /// 1-2-4-8, 3 residual blocks per level, 8-head attention at the 8 x 128 level), SegFormer-B0 semantic
    /// features (32/64/160/256 channels) and Depth-Anything-V2-Small DPT features (48/96/192/384) from a
    /// 384 x 1248 KITTI image, GCMA at every encoder and decoder level. 75.5 M parameters (our residual
    /// blocks are ADM-style with two 3x3 convolutions and the decoder has one block more per level, so
    /// the count is above the 31.1 M of R2DM's Efficient U-Net at the same widths).
    pub fn paper() -> Self {
        DenoiserConfig {
            sensor: LidarSensor::hdl64e(),
            in_channels: 3,
            out_channels: 3,
            base_channels: 64,
            channel_mults: vec![1, 2, 4, 8],
            num_res_blocks: 3,
            norm_groups: 8,
            residual_scale: std::f32::consts::FRAC_1_SQRT_2,
            time: TimeEmbeddingConfig {
                dim: 128,
                max_period: 10_000.0,
                input_scale: 1000.0,
            },
            ray_features: Some(FourierEncoding {
                num_freqs: 6,
                scale: 1.0,
                include_input: true,
            }),
            pfc: Some(PfcConfig { num_heads: 8 }),
            conditioning: Some(ConditioningConfig {
                cues: Cues::Both,
                fusion: Fusion::Cacm,
                semantic_channels: vec![32, 64, 160, 256],
                depth_channels: vec![48, 96, 192, 384],
                feature_sizes: ConditioningConfig::pyramid_sizes(384, 1248),
                cond_channels: vec![64, 128, 256, 256],
                cacm_delta: 1e-6,
                num_views: 1,
                gcma: Some(GcmaConfig {
                    levels: vec![0, 1, 2, 3],
                    decoder: true,
                    attn_dim: 64,
                    num_heads: 4,
                    point_encoding: FourierEncoding {
                        num_freqs: 6,
                        scale: 1.0 / 80.0,
                        include_input: true,
                    },
                }),
            }),
        }
    }

    /// The same network without image conditioning (an R2DM-like baseline).
    pub fn unconditional(mut self) -> Self {
        self.conditioning = None;
        self
    }

    /// Replaces the sensor (and so the range-image size).
    pub fn with_sensor(mut self, sensor: LidarSensor) -> Self {
        self.sensor = sensor;
        self
    }

    /// Range-image height `H`.
    pub fn height(&self) -> usize {
        self.sensor.rows as usize
    }

    /// Range-image width `W`.
    pub fn width(&self) -> usize {
        self.sensor.cols as usize
    }

    /// Number of U-Net levels.
    pub fn num_levels(&self) -> usize {
        self.channel_mults.len()
    }

    /// Channels at `level`.
    pub fn level_channels(&self, level: usize) -> usize {
        self.base_channels * self.channel_mults[level]
    }

    /// Width of the time embedding after the MLP (`4 * base_channels`).
    pub fn time_embed_dim(&self) -> usize {
        4 * self.base_channels
    }

    /// Number of ray-feature input channels.
    pub fn ray_feature_channels(&self) -> usize {
        self.ray_features.map_or(0, |f| f.dim())
    }

    /// Parses a JSON config and validates it.
    pub fn from_json(text: &str) -> std::result::Result<Self, serde_json::Error> {
        serde_json::from_str(text)
    }

    /// Checks every invariant, sizes included (the `MAX_*` bounds of this module);
    /// [`crate::Denoiser::new`] calls it.
    pub fn validate(&self) -> Result<()> {
        self.sensor.validate()?;
        self.validate_sizes()?;
        self.validate_levels()?;
        if !(self.residual_scale.is_finite() && self.residual_scale > 0.0) {
            return bad(format!(
                "residual_scale must be finite and positive, got {}",
                self.residual_scale
            ));
        }
        self.validate_time()?;
        if let Some(rf) = &self.ray_features {
            rf.validate()?;
        }
        if let Some(pfc) = &self.pfc {
            let c = self.level_channels(self.num_levels() - 1);
            check_max("pfc.num_heads", pfc.num_heads, MAX_HEADS)?;
            if pfc.num_heads == 0 || !c.is_multiple_of(pfc.num_heads) {
                return bad(format!(
                    "pfc.num_heads {} must divide the deepest channels {c}",
                    pfc.num_heads
                ));
            }
        }
        if let Some(cc) = &self.conditioning {
            cc.validate(self.num_levels())?;
        }
        Ok(())
    }

    /// Channel counts, blocks and groups: positive and within their bounds.
    fn validate_sizes(&self) -> Result<()> {
        if self.in_channels == 0 || self.out_channels == 0 || self.base_channels == 0 {
            return bad("in_channels, out_channels and base_channels must be positive".into());
        }
        check_max("in_channels", self.in_channels, MAX_IO_CHANNELS)?;
        check_max("out_channels", self.out_channels, MAX_IO_CHANNELS)?;
        check_max("base_channels", self.base_channels, MAX_BASE_CHANNELS)?;
        check_max("num_res_blocks", self.num_res_blocks, MAX_RES_BLOCKS)?;
        if self.norm_groups == 0 {
            return bad("norm_groups must be positive".into());
        }
        check_max("norm_groups", self.norm_groups, MAX_NORM_GROUPS)
    }

    /// `channel_mults`: 1 to [`MAX_LEVELS`] positive multipliers whose level widths stay within
    /// [`MAX_LEVEL_CHANNELS`], and a range image divisible by `2^(levels - 1)`.
    fn validate_levels(&self) -> Result<()> {
        let n = self.num_levels();
        if n > MAX_LEVELS {
            return bad(format!(
                "channel_mults lists {n} U-Net levels, more than the limit of {MAX_LEVELS}"
            ));
        }
        if n == 0 || self.channel_mults.contains(&0) {
            return bad(format!(
                "channel_mults must be non-empty and positive, got {:?}",
                self.channel_mults
            ));
        }
        for (l, m) in self.channel_mults.iter().enumerate() {
            let c = self.base_channels.checked_mul(*m);
            if c.is_none_or(|c| c > MAX_LEVEL_CHANNELS) {
                return bad(format!(
                    "channel_mults[{l}] = {m}: level {l} would have base_channels {} x {m} channels, more than the limit of {MAX_LEVEL_CHANNELS}",
                    self.base_channels
                ));
            }
        }
        let f = 1usize << (n - 1);
        if !self.height().is_multiple_of(f) || !self.width().is_multiple_of(f) {
            return bad(format!(
                "range image {}x{} must be divisible by 2^(levels-1) = {f} for {n} levels",
                self.height(),
                self.width(),
            ));
        }
        Ok(())
    }

    /// The time embedding: an even `dim` within [`MAX_TIME_DIM`], finite `max_period > 1` and an
    /// `input_scale` above 0 and at most [`MAX_TIME_INPUT_SCALE`].
    fn validate_time(&self) -> Result<()> {
        let t = &self.time;
        if t.dim == 0
            || !t.dim.is_multiple_of(2)
            || !t.max_period.is_finite()
            || t.max_period.partial_cmp(&1.0) != Some(std::cmp::Ordering::Greater)
        {
            return bad(format!(
                "time embedding needs an even dim and a finite max_period > 1, got {t:?}"
            ));
        }
        let s = t.input_scale;
        if !(s.is_finite() && s > 0.0 && s <= MAX_TIME_INPUT_SCALE) {
            return bad(format!(
                "time.input_scale = {s} must be above 0 and at most {MAX_TIME_INPUT_SCALE}"
            ));
        }
        check_max("time.dim", t.dim, MAX_TIME_DIM)
    }
}

impl ConditioningConfig {
    /// Checks the conditioning of a U-Net of `num_levels` levels (what
    /// [`DenoiserConfig::validate`] calls).
    fn validate(&self, num_levels: usize) -> Result<()> {
        let n = self.feature_sizes.len();
        if n == 0 {
            return bad("conditioning.feature_sizes must list at least one scale".into());
        }
        check_max("conditioning.feature_sizes (scales)", n, MAX_FEATURE_SCALES)?;
        if self.cond_channels.len() != n {
            return bad(format!(
                "conditioning.cond_channels needs {n} entries (one per scale)"
            ));
        }
        if self.cues != Cues::DepthOnly && self.semantic_channels.len() != n {
            return bad(format!(
                "conditioning.semantic_channels needs {n} entries (one per scale)"
            ));
        }
        if self.cues != Cues::SemanticOnly && self.depth_channels.len() != n {
            return bad(format!(
                "conditioning.depth_channels needs {n} entries (one per scale)"
            ));
        }
        if self.feature_sizes.iter().any(|s| s[0] == 0 || s[1] == 0)
            || self.cond_channels.contains(&0)
        {
            return bad("conditioning feature sizes and channels must be positive".into());
        }
        self.validate_feature_bounds()?;
        if self.num_views == 0 {
            return bad("conditioning.num_views must be at least 1".into());
        }
        check_max("conditioning.num_views", self.num_views, MAX_VIEWS)?;
        if !(self.cacm_delta.is_finite() && self.cacm_delta > 0.0) {
            return bad(format!(
                "cacm_delta must be finite and positive, got {}",
                self.cacm_delta
            ));
        }
        if let Some(g) = &self.gcma {
            g.validate(num_levels)?;
        }
        Ok(())
    }

    /// Channel counts within [`MAX_FEATURE_CHANNELS`] and feature maps within
    /// [`MAX_FEATURE_PIXELS`].
    fn validate_feature_bounds(&self) -> Result<()> {
        for (field, list) in [
            ("conditioning.semantic_channels", &self.semantic_channels),
            ("conditioning.depth_channels", &self.depth_channels),
            ("conditioning.cond_channels", &self.cond_channels),
        ] {
            if let Some((i, c)) = list
                .iter()
                .enumerate()
                .find(|(_, c)| **c > MAX_FEATURE_CHANNELS)
            {
                return bad(format!(
                    "{field}[{i}] = {c} is more than the limit of {MAX_FEATURE_CHANNELS}"
                ));
            }
        }
        for (i, [h, w]) in self.feature_sizes.iter().enumerate() {
            if h.checked_mul(*w).is_none_or(|p| p > MAX_FEATURE_PIXELS) {
                return bad(format!(
                    "conditioning.feature_sizes[{i}] = {h}x{w} is more than the limit of {MAX_FEATURE_PIXELS} pixels"
                ));
            }
        }
        Ok(())
    }
}

impl GcmaConfig {
    /// Checks the alignment of a U-Net of `num_levels` levels.
    fn validate(&self, num_levels: usize) -> Result<()> {
        if self.levels.iter().any(|l| *l >= num_levels) {
            return bad(format!(
                "gcma.levels {:?} out of range for {num_levels} levels",
                self.levels
            ));
        }
        check_max("gcma.attn_dim", self.attn_dim, MAX_ATTN_DIM)?;
        check_max("gcma.num_heads", self.num_heads, MAX_HEADS)?;
        if self.num_heads == 0
            || self.attn_dim == 0
            || !self.attn_dim.is_multiple_of(self.num_heads)
        {
            return bad(format!(
                "gcma.num_heads {} must divide attn_dim {}",
                self.num_heads, self.attn_dim
            ));
        }
        Ok(self.point_encoding.validate()?)
    }
}

/// A config error.
fn bad(message: String) -> Result<()> {
    Err(Error::Config(message))
}

/// [`Error::Config`] naming `field` when `value` exceeds its bound `max` (the configs of every
/// network of the crate check their sizes with it).
pub(crate) fn check_max(field: &str, value: usize, max: usize) -> Result<()> {
    if value > max {
        return bad(format!("{field} = {value} is more than the limit of {max}"));
    }
    Ok(())
}
