//! The Veila denoiser on [candle](https://github.com/huggingface/candle): a U-Net over LiDAR range
//! images with the three components of the Veila paper (section 3) — the Confidence-Aware Conditioning
//! Mechanism ([`Cacm`], eqs. 4-6), Geometric Cross-Modal Alignment ([`Gcma`], eqs. 7-10, on
//! [`veila_geom::EpipolarTable`]s precomputed into a [`GcmaGeometry`]) and Panoramic Feature Coherence
//! ([`Pfc`], eq. 11) — plus image encoders ([`encoders`]), checkpoint IO ([`checkpoint`]) and the
//! RangeNet / PointNet feature networks of the FRD and FPD metrics ([`feature_nets`]), a range-view
//! semantic segmenter with RangeNet++'s point-label clean-up ([`segmenter`]), and the
//! export of a network with a reference input and output for implementations outside candle
//! ([`export`]).
//!
//! Every ablation of the paper is a switch in [`DenoiserConfig`]: `conditioning: None` (unconditional,
//! R2DM-like), [`Fusion::Concat`] (w/o CACM), `gcma: None` (w/o GCMA), `pfc: None` (w/o PFC),
//! [`Cues::SemanticOnly`] / [`Cues::DepthOnly`], and `num_views > 1` for multi-camera conditioning.
//!
//! Range images are `[B, C, H, W]` with `H x W = sensor.rows x sensor.cols`; every 3x3 convolution wraps
//! around the azimuth axis and zero-pads vertically.
//!
//! ```
//! use candle_core::{DType, Device, Tensor};
//! use candle_nn::VarMap;
//! use veila_nn::{Denoiser, DenoiserConfig, seeded_var_builder};
//!
//! let mut cfg = DenoiserConfig::tiny().unconditional();
//! cfg.sensor.rows = 8;
//! cfg.sensor.cols = 64;
//! let dev = Device::Cpu;
//! let varmap = VarMap::new();
//! let net = Denoiser::new(&cfg, seeded_var_builder(&varmap, 0, DType::F32, &dev))?;
//! let x = Tensor::zeros((2, 3, 8, 64), DType::F32, &dev)?;
//! let t = Tensor::new(&[0.1f32, 0.9], &dev)?;
//! let eps = net.forward(&x, &t, None)?;
//! assert_eq!(eps.dims(), &[2, 3, 8, 64]);
//! # Ok::<(), veila_nn::Error>(())
//! ```
//!
//! Conditioned use: build the geometry once per camera rig ([`Denoiser::geometry`]), fuse the encoder
//! pyramids once per image ([`Denoiser::prepare_condition`]), then call [`Denoiser::forward`] with the
//! prepared condition at every denoising step.
//!
//! **Speed on the CPU** (measured in BENCHMARKS.md by [`speed::measure`], `cargo xtask
//! bench-model`): the convolutions, GroupNorms and residual sums run as the multi-threaded kernels
//! of [`fused`]. A program of its own
//! gets the `veila` binary's speed with two process settings: a global allocator that keeps freed
//! memory (mimalloc, with a purge delay of seconds), and two environment variables set before the
//! first candle operation: `RAYON_NUM_THREADS` (candle 0.11 otherwise counts the cores from
//! `/proc/cpuinfo` on every matrix product) and `CANDLE_NUM_THREADS=1` (candle's own thread pool
//! spins after each of its ops on the cores the kernels here use next).

pub mod cacm;
pub mod checkpoint;
pub mod config;
pub mod encoders;
mod error;
pub mod export;
pub mod feature_nets;
pub mod fused;
pub mod gather;
pub mod gcma;
pub mod init;
pub mod ops;
pub mod pfc;
pub mod process;
pub mod recompute;
pub mod segmenter;
pub mod speed;
pub mod unet;
pub mod weights;

pub use cacm::{Cacm, ConditionFusion};
pub use config::{
    ConditioningConfig, Cues, DenoiserConfig, Fusion, GcmaConfig, PfcConfig, TimeEmbeddingConfig,
};
pub use error::{Error, Result, TensorReport};
pub use gcma::{Gcma, GcmaGeometry, LevelGeometry};
pub use init::seeded_var_builder;
pub use pfc::Pfc;
pub use recompute::RecomputeTape;
pub use unet::{ConditionInput, Denoiser, PreparedCondition, ResBlock};
