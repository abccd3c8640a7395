//! Model bundles: everything generation needs (image encoders, denoiser, diffusion and sampler
//! settings, range encoding, image size) in one folder, with a manifest of sha256 sums that is
//! verified on every load.
//!
//! Layout of a bundle folder:
//!
//! | file | content |
//! |---|---|
//! | `bundle.json` | [`BundleConfig`] |
//! | `semantic_encoder.safetensors` | `E_s` weights (when the semantic encoder is a `small-cnn`) |
//! | `depth_encoder.safetensors` | `E_d` weights (when the depth encoder is a `small-cnn`) |
//! | `denoiser.safetensors` | the U-Net (EMA weights for trained bundles) |
//! | `mean.safetensors` | the mean network (when the config has `residual` or `prior`) |
//! | `manifest.json` | `{"format": "veila-manifest/1", "files": {"NAME": "SHA256_HEX", ...}}` |
//!
//! [`Bundle::from_dir`] reads a folder, [`Bundle::from_files`] takes the same files from memory (a
//! binary can embed its default model with `include_bytes!`); both check that every file the config
//! needs is listed in the manifest with a matching sum before anything is parsed, and that every
//! tensor of every network is present with the right shape.
//!
//! Each encoder is named by kind ([`EncoderSpec`]): `small-cnn` (trained with the bundle, weights
//! inside it) or a pretrained `segformer-b{0..5}`, `depth-anything-v2-{small,base,large}` or
//! `dinov2-{s,b,l}`, whose Hugging Face `model.safetensors` stays outside the manifest: the config
//! names its path, relative to the bundle folder and inside it ([`Bundle::save`] brings a file
//! given by an absolute path in), and its sha256. A file missing there is also looked for under its
//! file name inside the bundle folder; a path that is absolute, climbs out with `..` or leads out
//! through a link is refused without opening it (unless a file of its name is in the folder); a
//! missing, replaced or mis-shaped file is an error naming the file, the tensors and where to get
//! it.

mod config;
mod encoder;
mod io;
mod prior;
mod variant;

pub use config::{BundleConfig, PriorConfig, RANGE_WEIGHT_POWER, RESIDUAL_SCALE, ResidualConfig};
pub use encoder::EncoderSpec;
pub use io::{Bundle, Manifest};
pub(crate) use io::{ManifestFolder, ModelFiles, read_folder_file};
pub use prior::attach_prior;
pub use variant::{Method, NetworkKnobs, Variant};
pub use veila_nn::checkpoint::{safetensors_bytes, sha256_hex};

/// Format tag of `bundle.json` this build writes.
pub const BUNDLE_FORMAT: &str = "veila-bundle/2";
/// The earlier format, still read: its encoders are bare small-CNN configs.
pub const BUNDLE_FORMAT_V1: &str = "veila-bundle/1";
/// Format tag of `manifest.json`.
pub const MANIFEST_FORMAT: &str = "veila-manifest/1";
/// Name of the config file.
pub const CONFIG_FILE: &str = "bundle.json";
/// Name of the manifest.
pub const MANIFEST_FILE: &str = "manifest.json";
/// Semantic encoder weights.
pub const SEMANTIC_FILE: &str = "semantic_encoder.safetensors";
/// Depth encoder weights.
pub const DEPTH_FILE: &str = "depth_encoder.safetensors";
/// Denoiser weights.
pub const DENOISER_FILE: &str = "denoiser.safetensors";
/// File name of the mean network's weights (residual diffusion's, or a prior's).
pub const MEAN_FILE: &str = "mean.safetensors";
