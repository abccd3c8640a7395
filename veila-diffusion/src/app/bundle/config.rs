//! The bundle configuration, `bundle.json`: what the networks, the process, the sampler and the
//! range encoding are, and the checks every config passes before anything is built from it.

use std::path::Path;

use serde::{Deserialize, Serialize};
use veila_geom::EpipolarConfig;
use veila_nn::DenoiserConfig;

use super::{
    BUNDLE_FORMAT, BUNDLE_FORMAT_V1, CONFIG_FILE, DENOISER_FILE, DEPTH_FILE, EncoderSpec,
    MEAN_FILE, SEMANTIC_FILE,
};
use crate::encoding::RangeEncoding;
use crate::error::{Error, Result};
use crate::objective::DiffusionConfig;
use crate::sampler::SamplerConfig;

/// The interval of each value of [`ResidualConfig::scale`]: training sets it to the residual's
/// standard deviation in encoded units, at least 1e-3 and at most 2 (the data lie in `[-1, 1]`).
pub const RESIDUAL_SCALE: (f32, f32) = (1e-4, 10.0);

/// The interval of [`BundleConfig::range_weight`]: 0 (every pixel alike) to 2 (errors as metres).
pub const RANGE_WEIGHT_POWER: (f64, f64) = (0.0, 2.0);

/// Checks a [`BundleConfig::range_weight`] power against [`RANGE_WEIGHT_POWER`] (the message
/// names the interval, not the field).
pub(super) fn check_range_weight(p: f64) -> std::result::Result<(), String> {
    let (lo, hi) = RANGE_WEIGHT_POWER;
    if p.is_finite() && (lo..=hi).contains(&p) {
        Ok(())
    } else {
        Err(format!("must be between {lo} and {hi}, got {p}"))
    }
}

/// Everything about a bundle except its weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BundleConfig {
    /// [`BUNDLE_FORMAT`].
    pub format: String,
    /// A short name (`default`, `ablation-no-gcma`, ...).
    pub name: String,
    /// Height the camera image is resized to before the encoders, pixels.
    pub image_height: usize,
    /// Width the camera image is resized to, pixels.
    pub image_width: usize,
    /// The semantic encoder `E_s` (`None` for unconditional and depth-only models).
    pub semantic_encoder: Option<EncoderSpec>,
    /// The depth encoder `E_d` (`None` for unconditional and semantic-only models).
    pub depth_encoder: Option<EncoderSpec>,
    /// The U-Net; its sensor is the range-image grid.
    pub denoiser: DenoiserConfig,
    /// Schedule, prediction target, time input.
    pub diffusion: DiffusionConfig,
    /// How range images map to network channels.
    pub encoding: RangeEncoding,
    /// Epipolar sampling of GCMA.
    pub epipolar: EpipolarConfig,
    /// The sampler (and guidance scale) generation uses unless told otherwise.
    pub sampler: SamplerConfig,
    /// Residual ("corrective") diffusion: a one-pass mean network predicts the conditional median
    /// scan and the denoiser models only what is left, `(x₀ − μ) / scale`; zero sampler steps give
    /// `μ`. `None`: the denoiser models `x₀` directly.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub residual: Option<ResidualConfig>,
    /// A prior for direct diffusion: a one-pass mean network whose scan starts the sampler at
    /// level [`SamplerConfig::start_t`] (`α·μ + σ·ε`) instead of pure noise, so the draw keeps the
    /// image's layout and the denoiser adds the texture. Never with `residual`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prior: Option<PriorConfig>,
    /// Training only: the power `p` of the range weight in the denoiser's loss. A return's range
    /// and intensity errors weigh `((r + 1) / 11)^p` (`r` its true range in metres; dropped rays
    /// and the ray-drop channel weigh 1), and each scan's loss is the weighted mean. The log-range
    /// encoding makes a metre of error at 50 m count about 20 times less in the squared loss than
    /// at 10 m; `p = 1` gives a far return's error that much more of the gradient, `p = 2` weighs
    /// errors as metres. `None`: every pixel alike. Within [`RANGE_WEIGHT_POWER`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range_weight: Option<f64>,
    /// How the bundle was made (seed, steps, data, timings); informational.
    #[serde(default)]
    pub provenance: serde_json::Value,
}

impl BundleConfig {
    /// The weight files this config needs, in a fixed order.
    pub fn weight_files(&self) -> Vec<&'static str> {
        let mut v = Vec::new();
        let inside = |e: &Option<EncoderSpec>| e.as_ref().is_some_and(|e| !e.kind.is_pretrained());
        if inside(&self.semantic_encoder) {
            v.push(SEMANTIC_FILE);
        }
        if inside(&self.depth_encoder) {
            v.push(DEPTH_FILE);
        }
        v.push(DENOISER_FILE);
        if self.mean_net().is_some() {
            v.push(MEAN_FILE);
        }
        v
    }

    /// [`Self::mean_net`], to change.
    pub fn mean_net_mut(&mut self) -> Option<&mut DenoiserConfig> {
        match (&mut self.residual, &mut self.prior) {
            (Some(r), _) => Some(&mut r.mean_net),
            (None, Some(p)) => Some(&mut p.mean_net),
            (None, None) => None,
        }
    }

    /// The mean network, a residual bundle's or a prior's (its weights are [`MEAN_FILE`]).
    pub fn mean_net(&self) -> Option<&DenoiserConfig> {
        match (&self.residual, &self.prior) {
            (Some(r), _) => Some(&r.mean_net),
            (None, Some(p)) => Some(&p.mean_net),
            (None, None) => None,
        }
    }

    /// Channels of the encoded range image (what the bundle generates).
    pub fn channels(&self) -> usize {
        self.encoding.num_channels()
    }

    pub(super) fn check(&self, origin: &Path) -> Result<()> {
        let bad = |reason: String| Error::Checkpoint {
            reason,
            path: origin.join(CONFIG_FILE),
        };
        if self.format != BUNDLE_FORMAT && self.format != BUNDLE_FORMAT_V1 {
            return Err(bad(format!(
                "format `{}`, this build reads `{BUNDLE_FORMAT}`",
                self.format
            )));
        }
        if self.image_height == 0 || self.image_width == 0 {
            return Err(bad("image size has a zero dimension".into()));
        }
        for (field, e) in [
            ("semantic_encoder", &self.semantic_encoder),
            ("depth_encoder", &self.depth_encoder),
        ] {
            if let Some(e) = e {
                e.check(field).map_err(bad)?;
                e.kind
                    .input_size(self.image_height, self.image_width)
                    .map_err(|err| bad(format!("{field}: {err}")))?;
            }
        }
        let conditional = self.denoiser.conditioning.is_some();
        let has_encoder = self.semantic_encoder.is_some() || self.depth_encoder.is_some();
        if conditional != has_encoder {
            return Err(bad(format!(
                "the denoiser is {}conditional but the bundle has {} image encoder",
                if conditional { "" } else { "un" },
                if has_encoder { "an" } else { "no" }
            )));
        }
        let c = self.encoding.num_channels();
        let want_in = if self.residual.is_some() { 2 * c } else { c };
        if self.denoiser.in_channels != want_in || self.denoiser.out_channels != c {
            return Err(bad(format!(
                "the range encoding has {c} channels: the {}denoiser needs {want_in} in and {c} out, it has {} and {}",
                if self.residual.is_some() {
                    "residual "
                } else {
                    ""
                },
                self.denoiser.in_channels,
                self.denoiser.out_channels
            )));
        }
        if self.residual.is_some() && self.prior.is_some() {
            return Err(bad(
                "a bundle has a residual or a prior mean network, not both".into(),
            ));
        }
        if self.prior.is_some() && !conditional {
            return Err(bad(
                "a prior mean network needs an image-conditioned bundle (without the image its \
                 scan is the mean scan)"
                    .into(),
            ));
        }
        if let Some(m) = self.mean_net() {
            if m.in_channels != c || m.out_channels != c {
                return Err(bad(format!(
                    "the mean network needs {c} input and output channels, it has {} and {}",
                    m.in_channels, m.out_channels
                )));
            }
            if m.conditioning.is_some() != conditional {
                return Err(bad(
                    "the mean network and the denoiser must both be conditional or both not".into(),
                ));
            }
            if m.height() != self.denoiser.height() || m.width() != self.denoiser.width() {
                return Err(bad(
                    "the mean network's grid differs from the denoiser's".into()
                ));
            }
        }
        if let Some(r) = &self.residual {
            let (lo, hi) = RESIDUAL_SCALE;
            if r.scale.len() != c || r.scale.iter().any(|s| !(lo..=hi).contains(s)) {
                return Err(bad(format!(
                    "residual.scale needs {c} values between {lo} and {hi}, got {:?}",
                    r.scale
                )));
            }
        }
        self.check_values().map_err(bad)
    }

    /// The values of the networks, the process and the sampler against the library's bounds (the
    /// same the command-line flags are held to): every error names the field.
    fn check_values(&self) -> std::result::Result<(), String> {
        let at = |section: &str| {
            let section = section.to_string();
            move |e: Error| match e {
                Error::InvalidConfig { field, reason } => format!("{section}.{field}: {reason}"),
                other => format!("{section}: {other}"),
            }
        };
        self.denoiser
            .validate()
            .map_err(|e| format!("denoiser: {e}"))?;
        if let Some(r) = &self.residual {
            r.mean_net
                .validate()
                .map_err(|e| format!("residual.mean_net: {e}"))?;
        }
        if let Some(p) = &self.prior {
            p.mean_net
                .validate()
                .map_err(|e| format!("prior.mean_net: {e}"))?;
        }
        crate::Diffusion::new(self.diffusion.clone()).map_err(at("diffusion"))?;
        self.epipolar
            .validate()
            .map_err(|e| format!("epipolar: {e}"))?;
        self.encoding.validate().map_err(at("encoding"))?;
        self.sampler.validate().map_err(at("sampler"))?;
        if self.sampler.steps == 0 && self.mean_net().is_none() {
            return Err(format!(
                "sampler.steps: 0 steps (the mean network alone) need a bundle with a mean network \
                 (a residual-diffusion bundle or a prior); must be between 1 and {}",
                crate::MAX_STEPS
            ));
        }
        if let Some(p) = self.range_weight {
            check_range_weight(p).map_err(|e| format!("range_weight: {e}"))?;
        }
        if self.sampler.start_t.is_some() && self.prior.is_none() {
            return Err(
                "sampler.start_t: a start level needs a prior mean network (`prior`); leave it \
                 out to start from pure noise"
                    .into(),
            );
        }
        Ok(())
    }
}

impl BundleConfig {
    /// Gives every small-CNN encoder the flat-ground prior as an input channel (`None`: takes it
    /// away), the config switch of issue 18's "geometry that transfers" (stored in `bundle.json`
    /// inside each encoder's `config`; bundles without it have none). Pretrained encoders take
    /// colours only and are left alone. Returns how many encoders it set.
    pub fn set_ground_prior(
        &mut self,
        prior: Option<veila_nn::encoders::ground::GroundPrior>,
    ) -> usize {
        let mut n = 0;
        for spec in [&mut self.semantic_encoder, &mut self.depth_encoder]
            .into_iter()
            .flatten()
        {
            if spec.kind.is_pretrained() {
                continue;
            }
            if let Some(c) = spec.config.as_mut() {
                c.ground_prior = prior;
                n += 1;
            }
        }
        n
    }

    /// Appends the small-CNN depth encoder's own reading to its feature maps (`true`) or not
    /// ([`veila_nn::encoders::small_cnn::SmallCnnConfig::depth_features`], issue 18), and fits the
    /// denoiser's and the mean network's conditioning to the new channel counts. The encoder's
    /// weights are the same either way; the networks conditioned on it are not, so set it before
    /// they are trained.
    ///
    /// Turning it off where it cannot be on (no depth encoder, a pretrained one) changes nothing.
    ///
    /// # Errors
    /// Turning it on without a depth encoder, with a pretrained one, or with a small CNN without
    /// a depth head.
    pub fn set_depth_features(&mut self, on: bool) -> Result<()> {
        if !on && !self.depth_features() {
            return Ok(());
        }
        let Some(spec) = self.depth_encoder.as_mut() else {
            return Err(Error::Data(
                "depth features: the model has no depth encoder".into(),
            ));
        };
        let kind = spec.kind;
        let Some(c) = spec.config.as_mut().filter(|_| !kind.is_pretrained()) else {
            return Err(Error::Data(format!(
                "depth features: the depth encoder is {kind}, not a small CNN with a depth head"
            )));
        };
        if !c.depth_head {
            return Err(Error::Data(
                "depth features: the small-CNN depth encoder has no depth head".into(),
            ));
        }
        c.depth_features = on;
        let (semantic, depth) = (self.semantic_encoder.clone(), self.depth_encoder.clone());
        self.set_encoders(semantic, depth)
    }

    /// Whether the small-CNN depth encoder appends its depth reading to its feature maps
    /// ([`Self::set_depth_features`]).
    pub fn depth_features(&self) -> bool {
        self.depth_encoder
            .as_ref()
            .and_then(|s| s.small_cnn_config())
            .is_some_and(|c| c.depth_features)
    }

    /// Sets the encoders (either may be `None`, not both for a conditional denoiser) and fits the
    /// denoiser's and the mean network's conditioning to them: channels per scale, fused feature
    /// sizes (the semantic encoder's, else the depth encoder's, at the image size) and cues.
    pub fn set_encoders(
        &mut self,
        semantic: Option<EncoderSpec>,
        depth: Option<EncoderSpec>,
    ) -> Result<()> {
        let (ih, iw) = (self.image_height, self.image_width);
        let fused = match (&semantic, &depth) {
            (Some(s), _) => s.feature_sizes(ih, iw)?,
            (None, Some(d)) => d.feature_sizes(ih, iw)?,
            (None, None) => {
                return Err(Error::Data(
                    "set_encoders: a conditional bundle needs at least one encoder".into(),
                ));
            }
        };
        let cues = match (&semantic, &depth) {
            (Some(_), Some(_)) => veila_nn::Cues::Both,
            (Some(_), None) => veila_nn::Cues::SemanticOnly,
            _ => veila_nn::Cues::DepthOnly,
        };
        let fit = |d: &mut DenoiserConfig| {
            if let Some(c) = d.conditioning.as_mut() {
                if let Some(s) = &semantic {
                    c.semantic_channels = s.channels().to_vec();
                }
                if let Some(e) = &depth {
                    c.depth_channels = e.channels().to_vec();
                }
                c.feature_sizes = fused.iter().map(|&(h, w)| [h, w]).collect();
                c.cues = cues;
            }
        };
        fit(&mut self.denoiser);
        if let Some(m) = self.mean_net_mut() {
            fit(m);
        }
        self.semantic_encoder = semantic;
        self.depth_encoder = depth;
        self.denoiser.validate()?;
        Ok(())
    }
}

/// Residual diffusion settings of a bundle (see [`BundleConfig::residual`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResidualConfig {
    /// The mean network: a U-Net of the denoiser's family trained with
    /// [`Objective::Regression`](crate::Objective::Regression) (same encoders, own weights).
    pub mean_net: DenoiserConfig,
    /// Per-channel divisor of the residual (its standard deviation on the training set), so
    /// that the diffusion sees unit-scale data.
    pub scale: Vec<f32>,
}

/// A prior mean network of a direct-diffusion bundle (see [`BundleConfig::prior`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PriorConfig {
    /// A U-Net of the denoiser's family trained with
    /// [`Objective::Regression`](crate::Objective::Regression) on the same encoders' features
    /// (a residual bundle's mean network is one).
    pub mean_net: DenoiserConfig,
}

impl ResidualConfig {
    /// The process the mean network runs: one regression pass.
    pub fn mean_diffusion() -> DiffusionConfig {
        DiffusionConfig {
            objective: crate::objective::Objective::Regression,
            ..DiffusionConfig::default()
        }
    }
}

impl BundleConfig {
    /// Camera views the denoiser takes (1 when it is unconditional).
    pub fn num_views(&self) -> usize {
        self.denoiser
            .conditioning
            .as_ref()
            .map_or(1, |c| c.num_views.max(1))
    }

    /// Whether training this bundle looks at the camera: its denoiser is conditional, or it has
    /// encoders to train (`encoders_reused`: they come trained, from another bundle). Without
    /// it, the examples need no image ([`crate::app::dataset::blind_camera`]).
    pub fn needs_camera(&self, encoders_reused: bool) -> bool {
        self.denoiser.conditioning.is_some()
            || (!encoders_reused
                && (self.semantic_encoder.is_some() || self.depth_encoder.is_some()))
    }
}
