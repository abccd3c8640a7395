//! Diffusion for Veila: range-image encoding, noise schedules, the training objective, samplers
//! and the trainer, on [candle](https://github.com/huggingface/candle).
//!
//! The crate never needs a concrete network: everything is written against the [`Denoiser`] trait
//! (`x_t`, per-sample time value, optional conditioning → prediction), so the Veila U-Net from
//! `veila-nn`, a test network or an analytic [`oracle`] plug in alike.
//!
//! * [`encoding`]: R2DM's log-range encoding, intensity and an explicit ray-drop channel, and back.
//! * [`schedule`]: linear and cosine discrete schedules, the continuous cosine log-SNR schedule;
//!   every quantity evaluated in `f64` through the log-SNR, so nothing divides by `ᾱ = 0` or `1 − ᾱ = 0`.
//! * [`prediction`]: ε-, v- and x₀-prediction with conversions, the network's time input, min-SNR-γ.
//! * [`Diffusion`]: forward noising and the training loss (one random level per sample).
//! * [`sampler`]: DDPM, DDIM (η), DPM-Solver++(2M), classifier-free guidance, RePaint inpainting.
//! * [`trainer`]: AdamW, warm-up + cosine LR, EMA, gradient clipping, atomic checkpoints with exact
//!   resume, progress and preview callbacks.
//!
//! Everything above is the generic diffusion core, on candle and `veila-geom` alone. The `app`
//! module beside it (the default feature `app`, which brings `veila-nn`, `veila-data` and
//! `veila-metrics`) is the application: model bundles, the generate and inpaint pipeline, rig and
//! calibration loading, and the one training recipe the binaries share. A project that wants the
//! schedules, samplers and trainer alone depends on the crate with `default-features = false`.
//!
//! All randomness comes from caller-provided RNGs (use `rand_chacha::ChaCha8Rng` with a fixed seed);
//! noise is drawn on the CPU, so a seed gives the same samples on every device.
//!
//! # Example
//!
//! Sample range images with DDIM from the exact denoiser of Gaussian data and decode them into
//! range, intensity and ray-drop:
//!
//! ```
//! use candle_core::Device;
//! use rand::SeedableRng;
//! use rand_chacha::ChaCha8Rng;
//! use veila_diffusion::{
//!     Diffusion, DiffusionConfig, RangeEncoding, Sampler, SamplerConfig, oracle::GaussianOracle,
//! };
//!
//! # fn main() -> veila_diffusion::Result<()> {
//! let diffusion = Diffusion::new(DiffusionConfig::default())?;
//! // data: every channel ~ N(0.3, 0.2²) in the encoded [-1, 1] space
//! let model = GaussianOracle::new(0.3, 0.2, diffusion.clone())?;
//! let sampler = Sampler::new(&diffusion, SamplerConfig::ddim(20, 0.0))?;
//! let mut rng = ChaCha8Rng::seed_from_u64(7);
//! let encoding = RangeEncoding::kitti(); // range, intensity, ray-drop
//! let x = sampler.sample(&model, &[2, encoding.num_channels(), 8, 64], &Device::Cpu, None, &mut rng)?;
//!
//! let mean = x.mean_all()?.to_scalar::<f32>()?;
//! assert!((mean - 0.3).abs() < 0.02, "sample mean {mean}");
//!
//! let scans = encoding.decode_batch(&x)?;
//! assert_eq!(scans.len(), 2);
//! // ray-drop channel ~ N(0.3, 0.2²) is > 0 for ~93% of the 512 pixels: those are returns
//! assert!((400..512).contains(&scans[0].num_valid()));
//! assert!(scans[0].range_m.iter().all(|r| (0.0..=80.0).contains(r)));
//! # Ok(())
//! # }
//! ```

#[cfg(feature = "app")]
pub mod app;
pub mod denoiser;
pub mod encoding;
pub mod error;
pub mod noise;
pub mod objective;
pub mod oracle;
pub mod prediction;
pub mod sampler;
pub mod schedule;
pub mod trainer;

#[cfg(feature = "app")]
pub use app::nn::{NetCond, VeilaDenoiser};
pub use denoiser::{Autocast, CondDropout, Conditioning, Denoiser, guide};
pub use encoding::RangeEncoding;
pub use error::{Error, Result};
pub use objective::{Denoised, Diffusion, DiffusionConfig, LossOutput, Objective};
pub use prediction::{LossWeighting, Prediction, TimeInput};
pub use sampler::{
    DdpmVariance, DpmSolverPp2M, MAX_GUIDANCE, MAX_STEPS, RepaintConfig, Sampler, SamplerConfig,
    SamplerKind, SamplerName, StepInfo, inpaint,
};
pub use schedule::{
    CosineLogSnr, DiscreteSchedule, NoiseLevel, NoiseSchedule, ScheduleConfig, Spacing, TrainLevels,
};
pub use trainer::{
    ActivationCheckpointing, Batch, BatchSource, Clock, FitSummary, LossAverage, LrSchedule,
    Precision, StepStats, TrainConfig, TrainObserver, Trainer, claim_checkpoint_dir,
};
