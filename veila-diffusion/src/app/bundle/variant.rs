//! The model variants of the ablation study and the generative methods, as switches on a
//! bundle config ([`BundleConfig::cpu_default`], [`BundleConfig::with_method`]), and the size of
//! the networks and where their updates go ([`NetworkKnobs`], [`BundleConfig::set_network`]).

use serde::{Deserialize, Serialize};
use veila_geom::EpipolarConfig;
use veila_nn::DenoiserConfig;
use veila_nn::encoders::small_cnn::SmallCnnConfig;

use super::{BUNDLE_FORMAT, BundleConfig, EncoderSpec, ResidualConfig};
use crate::encoding::RangeEncoding;
use crate::error::{Result, invalid};
use crate::objective::DiffusionConfig;
use crate::sampler::SamplerConfig;

/// The model variants of the paper's ablation study (Table 4), as switches on a bundle config.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Variant {
    /// The full model: CACM + GCMA + PFC, semantic and depth cues.
    Full,
    /// No image conditioning (an R2DM-like baseline).
    Unconditional,
    /// Plain concatenation instead of CACM.
    NoCacm,
    /// No geometric alignment: the image enters only globally.
    NoGcma,
    /// No global self-attention at the bottleneck.
    NoPfc,
    /// Semantic cue (`E_s`) only.
    SemanticOnly,
    /// Depth cue (`E_d`) only.
    DepthOnly,
    /// The full model with three cameras (the paper's table 8): the front camera and two turned
    /// to its sides.
    ThreeCameras,
}

impl Variant {
    /// Every variant, the full model first.
    pub const ALL: [Variant; 8] = [
        Variant::Full,
        Variant::Unconditional,
        Variant::NoCacm,
        Variant::NoGcma,
        Variant::NoPfc,
        Variant::SemanticOnly,
        Variant::DepthOnly,
        Variant::ThreeCameras,
    ];

    /// Camera views the variant takes.
    pub fn views(self) -> usize {
        match self {
            Variant::ThreeCameras => 3,
            _ => 1,
        }
    }

    /// Kebab-case name (`no-gcma`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Variant::Full => "full",
            Variant::Unconditional => "unconditional",
            Variant::NoCacm => "no-cacm",
            Variant::NoGcma => "no-gcma",
            Variant::NoPfc => "no-pfc",
            Variant::SemanticOnly => "semantic-only",
            Variant::DepthOnly => "depth-only",
            Variant::ThreeCameras => "three-cameras",
        }
    }

    /// The label the paper's tables use.
    pub fn label(self) -> &'static str {
        match self {
            Variant::Full => "Veila",
            Variant::Unconditional => "unconditional (R2DM-like)",
            Variant::NoCacm => "w/o CACM",
            Variant::NoGcma => "w/o GCMA",
            Variant::NoPfc => "w/o PFC",
            Variant::SemanticOnly => "E_s only",
            Variant::DepthOnly => "E_d only",
            Variant::ThreeCameras => "3 cameras",
        }
    }
}

impl std::str::FromStr for Variant {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Variant::ALL
            .into_iter()
            .find(|v| v.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = Variant::ALL.iter().map(|v| v.name()).collect();
                format!("unknown variant `{s}` (one of: {})", names.join(", "))
            })
    }
}

/// How a bundle turns noise into a scan: the methods the benchmark compares at equal training
/// compute (`docs/lab/method-sweep/report.md`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// The paper's direct diffusion with ε-prediction.
    Eps,
    /// Direct diffusion with v-prediction.
    V,
    /// Residual ("corrective") diffusion: mean network + v-prediction diffusion of the residual.
    Residual,
    /// Rectified flow with Euler sampling (R2Flow-style).
    Flow,
    /// The one-pass regression network alone (the conditional median; no sampling).
    Regression,
}

impl Method {
    /// The method of the bundled model and of `veila train` / `cargo xtask train-default` unless
    /// told otherwise: the one that measured best at equal training compute
    /// (`docs/lab/method-sweep/report.md`; issue 55 reranks them by realism).
    pub const DEFAULT: Method = Method::Residual;

    /// Every method, in benchmark order.
    pub const ALL: [Method; 5] = [
        Method::Eps,
        Method::V,
        Method::Residual,
        Method::Flow,
        Method::Regression,
    ];

    /// The name used on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            Method::Eps => "eps",
            Method::V => "v",
            Method::Residual => "residual",
            Method::Flow => "flow",
            Method::Regression => "regression",
        }
    }

    /// A human-readable label.
    pub fn label(self) -> &'static str {
        match self {
            Method::Eps => "direct diffusion, ε-prediction",
            Method::V => "direct diffusion, v-prediction",
            Method::Residual => "residual diffusion (mean net + v-diffusion)",
            Method::Flow => "rectified flow (Euler)",
            Method::Regression => "one-pass regression (conditional median)",
        }
    }
}

impl std::str::FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Method::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = Method::ALL.iter().map(|m| m.name()).collect();
                format!("unknown method `{s}` (one of: {})", names.join(", "))
            })
    }
}

impl BundleConfig {
    /// The bundled CPU model's config ([`DenoiserConfig::small`], two default small CNN encoders
    /// at 96 x 320, KITTI range encoding, cosine log-SNR schedule with v-prediction and min-SNR-5
    /// weighting, DPM-Solver++(2M) with 16 steps uniform in log-SNR and guidance 1.5 by default;
    /// [`with_method`](Self::with_method) gives the residual method 16 DDPM steps without
    /// guidance), turned into `variant`.
    pub fn cpu_default(variant: Variant) -> Self {
        let mut denoiser = DenoiserConfig::small();
        let sem = SmallCnnConfig {
            depth_head: false,
            ..SmallCnnConfig::default()
        };
        let dep = SmallCnnConfig {
            semantic_head: false,
            ..SmallCnnConfig::default()
        };
        let (mut semantic, mut depth) = (Some(sem), Some(dep));
        match variant {
            Variant::Full => {}
            Variant::Unconditional => {
                denoiser.conditioning = None;
                semantic = None;
                depth = None;
            }
            Variant::NoCacm => {
                if let Some(c) = denoiser.conditioning.as_mut() {
                    c.fusion = veila_nn::Fusion::Concat;
                }
            }
            Variant::NoGcma => {
                if let Some(c) = denoiser.conditioning.as_mut() {
                    c.gcma = None;
                }
            }
            Variant::NoPfc => denoiser.pfc = None,
            Variant::SemanticOnly => {
                if let Some(c) = denoiser.conditioning.as_mut() {
                    c.cues = veila_nn::Cues::SemanticOnly;
                }
                depth = None;
            }
            Variant::DepthOnly => {
                if let Some(c) = denoiser.conditioning.as_mut() {
                    c.cues = veila_nn::Cues::DepthOnly;
                }
                semantic = None;
            }
            Variant::ThreeCameras => {
                if let Some(c) = denoiser.conditioning.as_mut() {
                    c.num_views = 3;
                }
            }
        }
        // steps uniform in log-SNR down to t = 1e-3: trailing steps end at t = 1/16 and never
        // visit the clean levels, where a direct-diffusion model's texture forms (BENCHMARKS.md,
        // "The step spacing of direct diffusion, again": FPD 10.7 against 15.0, smooth pairs
        // 2.9 % against 0.8 %, at the same 16 network calls)
        let mut sampler = SamplerConfig::dpm_solver_pp_2m(16);
        sampler.spacing = crate::Spacing::LogSnr;
        if denoiser.conditioning.is_some() {
            sampler.guidance_scale = 1.5;
        }
        BundleConfig {
            format: BUNDLE_FORMAT.into(),
            name: if variant == Variant::Full {
                "default".into()
            } else {
                format!("default-{}", variant.name())
            },
            image_height: 96,
            image_width: 320,
            semantic_encoder: semantic.map(EncoderSpec::small_cnn),
            depth_encoder: depth.map(EncoderSpec::small_cnn),
            denoiser,
            // v-prediction: with ε-prediction a short training run leaves the noisiest levels
            // (where x̂₀ = (x_t − σ ε̂) / α amplifies every error of ε̂ by σ / α > 10) unusable, and
            // samples drawn from pure noise come out as noise
            diffusion: DiffusionConfig {
                prediction: crate::prediction::Prediction::V,
                ..DiffusionConfig::default()
            },
            encoding: RangeEncoding::kitti(),
            epipolar: EpipolarConfig::default(),
            sampler,
            residual: None,
            prior: None,
            range_weight: None,
            provenance: serde_json::Value::Null,
        }
    }
}

impl BundleConfig {
    /// This config switched to `method` (denoiser channels, objective, residual settings and
    /// sampler); the residual scale starts at 1 and is set by training, and a prior mean network
    /// and its start level are dropped.
    pub fn with_method(mut self, method: Method) -> Self {
        use crate::objective::Objective;
        use crate::prediction::Prediction;
        let c = self.encoding.num_channels();
        self.residual = None;
        self.prior = None;
        self.sampler.start_t = None;
        self.denoiser.in_channels = c;
        self.diffusion.objective = Objective::Diffusion;
        match method {
            Method::Eps => self.diffusion.prediction = Prediction::Epsilon,
            Method::V => self.diffusion.prediction = Prediction::V,
            Method::Residual => {
                self.diffusion.prediction = Prediction::V;
                self.residual = Some(ResidualConfig {
                    mean_net: self.denoiser.clone(),
                    scale: vec![1.0; c],
                });
                self.denoiser.in_channels = 2 * c;
                // the realism-faithfulness frontier's rule (BENCHMARKS.md, "The residual's clip
                // and the default sampler"): the lowest FPD whose range error and CM-DC stay
                // inside the faithfulness bounds, then the fastest; 16 DDPM steps, FPD 10.5
                // against 13.2 for 4 steps (80 held-out frames), and guidance 1 ties 1.5 on FPD
                // (8.97 against 8.99 on 399 frames) at 0.71 against 1.28 s per scan
                self.sampler = crate::SamplerConfig::ddpm(16);
                self.sampler.guidance_scale = 1.0;
            }
            Method::Flow => self.diffusion.objective = Objective::rectified_flow(),
            Method::Regression => {
                self.diffusion.objective = Objective::Regression;
                self.sampler.steps = 1;
                self.sampler.guidance_scale = 1.0;
            }
        }
        self
    }

    /// The method this config describes.
    pub fn method(&self) -> Method {
        use crate::objective::Objective;
        match (self.diffusion.objective, &self.residual) {
            (Objective::Regression, _) => Method::Regression,
            (Objective::RectifiedFlow { .. }, _) => Method::Flow,
            (Objective::Diffusion, Some(_)) => Method::Residual,
            (Objective::Diffusion, None) => match self.diffusion.prediction {
                crate::prediction::Prediction::Epsilon => Method::Eps,
                _ => Method::V,
            },
        }
    }
}

/// The size of the networks and where their updates go, as both training doors take them
/// (`cargo xtask train-default`'s flags, `veila train`'s `[model]`); `None` keeps the config's.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct NetworkKnobs {
    /// Width of the U-Nets' first level.
    pub base_channels: Option<usize>,
    /// Width multipliers of the U-Net levels (their count is the number of levels).
    pub channel_mults: Option<Vec<usize>>,
    /// Residual blocks per U-Net level.
    pub res_blocks: Option<usize>,
    /// Octaves of the Fourier features of every pixel's ray direction fed to the U-Nets (the
    /// CPU default's 4 resolve about 10 pixels of azimuth at 256 columns; 6 about 2.6, R2DM's
    /// pixel-scale code).
    pub ray_freqs: Option<usize>,
    /// How the noise levels weigh in the loss.
    pub loss_weighting: Option<crate::prediction::LossWeighting>,
    /// The share of training draws at the clean levels
    /// ([`TrainLevels::clean_share`](crate::TrainLevels::clean_share)).
    pub clean_share: Option<f64>,
    /// The power of the range weight in the denoiser's loss ([`BundleConfig::range_weight`]).
    pub range_weight: Option<f64>,
}

impl BundleConfig {
    /// Sizes the denoiser, and a mean network (residual or prior) alike, and sets the loss
    /// weighting and training levels as `knobs` say; the networks are checked against their
    /// limits (widths, levels, the grid's divisibility, at most
    /// [`veila_nn::weights::MAX_PARAMETERS`] weights) and the training levels against theirs.
    pub fn set_network(&mut self, knobs: &NetworkKnobs) -> Result<()> {
        let nets = std::iter::once(&mut self.denoiser)
            .chain(self.residual.as_mut().map(|r| &mut r.mean_net))
            .chain(self.prior.as_mut().map(|p| &mut p.mean_net));
        for net in nets {
            if let Some(c) = knobs.base_channels {
                net.base_channels = c;
            }
            if let Some(m) = &knobs.channel_mults {
                net.channel_mults = m.clone();
            }
            if let Some(n) = knobs.res_blocks {
                net.num_res_blocks = n;
            }
            if let Some(n) = knobs.ray_freqs {
                // a config without ray features gets the CPU default's kind of them
                net.ray_features
                    .get_or_insert(veila_geom::FourierEncoding {
                        num_freqs: n,
                        scale: 1.0,
                        include_input: true,
                    })
                    .num_freqs = n;
            }
            // the shapes alone are recorded (nothing of the network's size is allocated): a
            // network past veila-nn's MAX_PARAMETERS is refused before training allocates it
            net.validate()
                .and_then(|()| veila_nn::checkpoint::parameter_count(net).map(drop))
                .map_err(|e| {
                    invalid(
                        "base_channels / res_blocks / channel_mults / ray_freqs",
                        e.to_string(),
                    )
                })?;
        }
        if let Some(w) = knobs.loss_weighting {
            self.diffusion.loss_weighting = w;
        }
        if let Some(share) = knobs.clean_share {
            let levels = crate::TrainLevels::clean_share(share);
            levels.validate()?;
            self.diffusion.train_levels = levels;
        }
        if let Some(p) = knobs.range_weight {
            super::config::check_range_weight(p).map_err(|e| invalid("range_weight", e))?;
            self.range_weight = (p > 0.0).then_some(p);
        }
        Ok(())
    }
}
