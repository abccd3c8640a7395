//! Serde configuration of the denoiser, with the `tiny` (CPU) and `paper` presets and a switch for
//! every ablation of the paper.

use serde::{Deserialize, Serialize};
use veila_geom::{BeamLayout, FourierEncoding, LidarSensor};

use crate::error::{Error, Result};

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

    /// Checks every invariant; [`crate::Denoiser::new`] calls it.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::Config(m));
        self.sensor.validate()?;
        if self.in_channels == 0 || self.out_channels == 0 || self.base_channels == 0 {
            return bad("in_channels, out_channels and base_channels must be positive".into());
        }
        if self.channel_mults.is_empty() || self.channel_mults.contains(&0) {
            return bad(format!(
                "channel_mults must be non-empty and positive, got {:?}",
                self.channel_mults
            ));
        }
        let f = 1usize << (self.num_levels() - 1);
        if !self.height().is_multiple_of(f) || !self.width().is_multiple_of(f) {
            return bad(format!(
                "range image {}x{} must be divisible by 2^(levels-1) = {f} for {} levels",
                self.height(),
                self.width(),
                self.num_levels()
            ));
        }
        if self.norm_groups == 0 {
            return bad("norm_groups must be positive".into());
        }
        if !(self.residual_scale.is_finite() && self.residual_scale > 0.0) {
            return bad(format!(
                "residual_scale must be finite and positive, got {}",
                self.residual_scale
            ));
        }
        if self.time.dim == 0
            || !self.time.dim.is_multiple_of(2)
            || self.time.max_period.partial_cmp(&1.0) != Some(std::cmp::Ordering::Greater)
        {
            return bad(format!(
                "time embedding needs an even dim and max_period > 1, got {:?}",
                self.time
            ));
        }
        if let Some(rf) = &self.ray_features {
            rf.validate()?;
        }
        if let Some(pfc) = &self.pfc {
            let c = self.level_channels(self.num_levels() - 1);
            if pfc.num_heads == 0 || !c.is_multiple_of(pfc.num_heads) {
                return bad(format!(
                    "pfc.num_heads {} must divide the deepest channels {c}",
                    pfc.num_heads
                ));
            }
        }
        if let Some(cc) = &self.conditioning {
            let n = cc.feature_sizes.len();
            if n == 0 {
                return bad("conditioning.feature_sizes must list at least one scale".into());
            }
            if cc.cond_channels.len() != n {
                return bad(format!(
                    "conditioning.cond_channels needs {n} entries (one per scale)"
                ));
            }
            if cc.cues != Cues::DepthOnly && cc.semantic_channels.len() != n {
                return bad(format!(
                    "conditioning.semantic_channels needs {n} entries (one per scale)"
                ));
            }
            if cc.cues != Cues::SemanticOnly && cc.depth_channels.len() != n {
                return bad(format!(
                    "conditioning.depth_channels needs {n} entries (one per scale)"
                ));
            }
            if cc.feature_sizes.iter().any(|s| s[0] == 0 || s[1] == 0)
                || cc.cond_channels.contains(&0)
            {
                return bad("conditioning feature sizes and channels must be positive".into());
            }
            if cc.num_views == 0 {
                return bad("conditioning.num_views must be at least 1".into());
            }
            if !(cc.cacm_delta.is_finite() && cc.cacm_delta > 0.0) {
                return bad(format!(
                    "cacm_delta must be finite and positive, got {}",
                    cc.cacm_delta
                ));
            }
            if let Some(g) = &cc.gcma {
                if g.levels.iter().any(|l| *l >= self.num_levels()) {
                    return bad(format!(
                        "gcma.levels {:?} out of range for {} levels",
                        g.levels,
                        self.num_levels()
                    ));
                }
                if g.num_heads == 0 || g.attn_dim == 0 || !g.attn_dim.is_multiple_of(g.num_heads) {
                    return bad(format!(
                        "gcma.num_heads {} must divide attn_dim {}",
                        g.num_heads, g.attn_dim
                    ));
                }
                g.point_encoding.validate()?;
            }
        }
        Ok(())
    }
}
