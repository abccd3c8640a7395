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
//! | `mean.safetensors` | the mean network of residual diffusion (when the config has `residual`) |
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

use std::collections::{BTreeMap, HashMap};
use std::fs;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};
use veila_data::contained::contained;
use veila_data::read_capped::{MAX_JSON_METADATA_BYTES, read_metadata};
use veila_geom::EpipolarConfig;
use veila_nn::encoders::kind::{AnyEncoder, EncoderKind};
use veila_nn::encoders::small_cnn::{SmallCnn, SmallCnnConfig};
use veila_nn::{Denoiser as Net, DenoiserConfig};

use crate::encoding::RangeEncoding;
use crate::error::{Error, Result};
use crate::objective::DiffusionConfig;
use crate::sampler::SamplerConfig;

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
/// File name of the residual-diffusion mean network's weights.
pub const MEAN_FILE: &str = "mean.safetensors";

/// The interval of each value of [`ResidualConfig::scale`]: training sets it to the residual's
/// standard deviation in encoded units, at least 1e-3 and at most 2 (the data lie in `[-1, 1]`).
pub const RESIDUAL_SCALE: (f32, f32) = (1e-4, 10.0);

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
        if self.residual.is_some() {
            v.push(MEAN_FILE);
        }
        v
    }

    /// Channels of the encoded range image (what the bundle generates).
    pub fn channels(&self) -> usize {
        self.encoding.num_channels()
    }

    fn check(&self, origin: &Path) -> Result<()> {
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
        if let Some(r) = &self.residual {
            if r.mean_net.in_channels != c || r.mean_net.out_channels != c {
                return Err(bad(format!(
                    "the mean network needs {c} input and output channels, it has {} and {}",
                    r.mean_net.in_channels, r.mean_net.out_channels
                )));
            }
            if r.mean_net.conditioning.is_some() != conditional {
                return Err(bad(
                    "the mean network and the denoiser must both be conditional or both not".into(),
                ));
            }
            if r.mean_net.height() != self.denoiser.height()
                || r.mean_net.width() != self.denoiser.width()
            {
                return Err(bad(
                    "the mean network's grid differs from the denoiser's".into()
                ));
            }
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
        crate::Diffusion::new(self.diffusion.clone()).map_err(at("diffusion"))?;
        self.epipolar
            .validate()
            .map_err(|e| format!("epipolar: {e}"))?;
        self.encoding.validate().map_err(at("encoding"))?;
        self.sampler.validate().map_err(at("sampler"))?;
        if self.sampler.steps == 0 && self.residual.is_none() {
            return Err(format!(
                "sampler.steps: 0 steps (the mean network alone) need a residual-diffusion bundle; \
                 must be between 1 and {}",
                crate::MAX_STEPS
            ));
        }
        Ok(())
    }
}

/// One image encoder of a bundle, named by kind (`bundle.json`'s `semantic_encoder` /
/// `depth_encoder`):
///
/// ```json
/// {"kind": "small-cnn", "config": {"channels": [16, 32, 64, 96], ...}}
/// {"kind": "depth-anything-v2-small", "weights": "depth_encoder.depth-anything-v2-small.safetensors", "sha256": "..."}
/// ```
///
/// A `small-cnn` has its architecture here and its weights in the bundle; a pretrained kind has
/// its weights file here. Bundles of format `veila-bundle/1` held a bare small-CNN config, which
/// is still read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "serde_json::Value")]
pub struct EncoderSpec {
    /// What encoder it is.
    pub kind: EncoderKind,
    /// The small CNN's architecture (`small-cnn` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub config: Option<SmallCnnConfig>,
    /// Pretrained kinds: the Hugging Face `model.safetensors`, relative to the bundle folder and
    /// inside it (an absolute path only until [`Bundle::save`] brings the file in).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub weights: Option<PathBuf>,
    /// Pretrained kinds: the weights' sha256 (lowercase hex), checked on every load when given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sha256: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct EncoderSpecFields {
    kind: EncoderKind,
    #[serde(default)]
    config: Option<SmallCnnConfig>,
    #[serde(default)]
    weights: Option<PathBuf>,
    #[serde(default)]
    sha256: Option<String>,
}

impl TryFrom<serde_json::Value> for EncoderSpec {
    type Error = String;

    fn try_from(v: serde_json::Value) -> std::result::Result<Self, String> {
        if v.get("kind").is_some() {
            let f: EncoderSpecFields = serde_json::from_value(v).map_err(|e| e.to_string())?;
            return Ok(EncoderSpec {
                kind: f.kind,
                config: f.config,
                weights: f.weights,
                sha256: f.sha256,
            });
        }
        // veila-bundle/1: a bare small-CNN config
        let c: SmallCnnConfig = serde_json::from_value(v).map_err(|e| {
            format!("neither an encoder spec with a `kind` nor a small-CNN config: {e}")
        })?;
        Ok(EncoderSpec::small_cnn(c))
    }
}

impl EncoderSpec {
    /// A small CNN with this architecture.
    pub fn small_cnn(config: SmallCnnConfig) -> Self {
        Self {
            kind: EncoderKind::SmallCnn,
            config: Some(config),
            weights: None,
            sha256: None,
        }
    }

    /// A pretrained encoder whose weights are at `weights` (an absolute path, which
    /// [`Bundle::save`] brings into the bundle, or one relative to the bundle folder), with their
    /// sha256 when known.
    pub fn pretrained(kind: EncoderKind, weights: PathBuf, sha256: Option<String>) -> Self {
        Self {
            kind,
            config: None,
            weights: Some(weights),
            sha256,
        }
    }

    /// The small CNN's config, for `small-cnn` specs.
    pub fn small_cnn_config(&self) -> Option<&SmallCnnConfig> {
        self.config.as_ref().filter(|_| !self.kind.is_pretrained())
    }

    /// Output channels of the four feature maps.
    pub fn channels(&self) -> [usize; 4] {
        match (&self.config, self.kind.channels()) {
            (_, Some(c)) => c,
            (Some(c), None) => c.feature_channels(),
            (None, None) => [0; 4],
        }
    }

    /// Feature map sizes for a `height x width` camera image.
    pub fn feature_sizes(&self, height: usize, width: usize) -> Result<[(usize, usize); 4]> {
        if let Some(s) = self.kind.feature_sizes(height, width)? {
            return Ok(s);
        }
        match &self.config {
            Some(c) => Ok(c.feature_sizes(height, width)),
            None => Err(Error::Data(format!("{}: no config", self.kind))),
        }
    }

    fn check(&self, field: &str) -> std::result::Result<(), String> {
        match (self.kind.is_pretrained(), &self.config, &self.weights) {
            (false, Some(c), None) => c.validate().map_err(|e| format!("{field}: {e}")),
            (false, _, _) => Err(format!(
                "{field}: a small-cnn needs `config` and keeps its weights in the bundle (no `weights`)"
            )),
            (true, None, Some(_)) => match &self.sha256 {
                Some(h) if h.len() != 64 || !h.bytes().all(|b| b.is_ascii_hexdigit()) => {
                    Err(format!("{field}: sha256 `{h}` is not 64 hex digits"))
                }
                _ => Ok(()),
            },
            (true, _, _) => Err(format!(
                "{field}: a {} needs `weights` (the path of its model.safetensors) and no `config`",
                self.kind
            )),
        }
    }

    /// Where the pretrained weights are in the bundle folder `bundle_dir` (`field` names the spec
    /// in errors): the configured path when it is a file there, else the file of its name in the
    /// folder (weights copied in beside a moved bundle). The configured path must be relative and
    /// lie inside the folder, links included ([`veila_data::contained::contained`]): one that does
    /// not is an error naming `FIELD.weights` and `bundle.json` (unless a file of its name is in the
    /// folder), and nothing outside the folder is opened. `None` when no file is there.
    pub fn resolve_weights(&self, bundle_dir: &Path, field: &str) -> Result<Option<PathBuf>> {
        self.resolve_weights_from(&bundle_dir.join(CONFIG_FILE), field)
    }

    /// [`Self::resolve_weights`] for the spec of the bundle config file `config` (a `bundle.json`
    /// by another name too): its weights in the folder holding `config`.
    pub fn resolve_weights_from(&self, config: &Path, field: &str) -> Result<Option<PathBuf>> {
        let Some(w) = self.weights.as_ref() else {
            return Ok(None);
        };
        let bundle_dir = match config.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        let key = format!("{field}.weights");
        let primary = contained(bundle_dir, w, &key, config);
        if let Ok(p) = &primary
            && p.is_file()
        {
            return Ok(Some(p.clone()));
        }
        if let Some(name) = w.file_name() {
            let by_name = contained(bundle_dir, Path::new(name), &key, config)?;
            if by_name.is_file() {
                return Ok(Some(by_name));
            }
        }
        primary?;
        Ok(None)
    }

    /// Loads a pretrained encoder of a bundle (its weights found in `bundle_dir`, see
    /// [`Self::resolve_weights`]; `field` names the spec in errors), checking the sha256 when the
    /// spec has one.
    pub fn load(&self, bundle_dir: &Path, field: &str, device: &Device) -> Result<AnyEncoder> {
        let w = self.weights.as_ref().ok_or_else(|| Error::Checkpoint {
            reason: format!("{field}: a {} needs `weights`", self.kind),
            path: bundle_dir.join(CONFIG_FILE),
        })?;
        let repo = self.kind.hub_repo().unwrap_or("-");
        let Some(path) = self.resolve_weights(bundle_dir, field)? else {
            // relative and inside: `resolve_weights` refused anything else
            let primary = bundle_dir.join(w);
            let name = w.file_name().map(PathBuf::from).unwrap_or_default();
            return Err(Error::Checkpoint {
                reason: format!(
                    "{field} `{}`: weights not found (bundle.json names `{}`); download `model.safetensors` of {repo} from the Hugging Face Hub and put it at {} or at {}",
                    self.kind,
                    w.display(),
                    primary.display(),
                    bundle_dir.join(name).display()
                ),
                path: primary,
            });
        };
        self.load_at(&path, field, device)
    }

    /// Loads the pretrained encoder from `path`, a file the caller chose (a training config's
    /// `[model] semantic_weights`; a bundle's own go through [`Self::load`]), checking the sha256
    /// when the spec has one.
    pub fn load_at(&self, path: &Path, field: &str, device: &Device) -> Result<AnyEncoder> {
        let repo = self.kind.hub_repo().unwrap_or("-");
        // a regular file under the weights cap, checked before anything is read (a pretrained
        // encoder's file is the largest a bundle names: Depth-Anything-V2-Large is 1.3 GB)
        let bytes = veila_nn::checkpoint::read_weights_file(path)?;
        if let Some(want) = &self.sha256 {
            let got = sha256_hex(&bytes);
            if !want.eq_ignore_ascii_case(&got) {
                return Err(Error::Checkpoint {
                    reason: format!(
                        "{field} `{}`: sha256 {got}, the bundle was made with {want} (another file, or another revision of {repo})",
                        self.kind
                    ),
                    path: path.to_path_buf(),
                });
            }
        }
        Ok(self
            .kind
            .load_pretrained(&bytes, path, DType::F32, device)?)
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
        if let Some(r) = self.residual.as_mut() {
            fit(&mut r.mean_net);
        }
        self.semantic_encoder = semantic;
        self.depth_encoder = depth;
        self.denoiser.validate()?;
        Ok(())
    }
}

/// `manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// [`MANIFEST_FORMAT`].
    pub format: String,
    /// File name → lowercase hex sha256.
    pub files: BTreeMap<String, String>,
}

pub use veila_nn::checkpoint::{safetensors_bytes, sha256_hex};

/// A loaded bundle: config, networks (on one device, `f32`).
#[derive(Debug, Clone)]
pub struct Bundle {
    /// The config.
    pub config: BundleConfig,
    /// `E_s`.
    pub semantic: Option<AnyEncoder>,
    /// `E_d`.
    pub depth: Option<AnyEncoder>,
    /// The denoiser.
    pub denoiser: Net,
    /// The denoiser's weights by name (to rebuild it for another number of views).
    pub weights: HashMap<String, Tensor>,
    /// The mean network of residual diffusion and its weights by name.
    pub mean: Option<(Net, HashMap<String, Tensor>)>,
    /// Where it was loaded from (a folder, or a label for embedded bundles).
    pub origin: PathBuf,
}

impl Bundle {
    /// Reads and verifies a bundle folder. Its `manifest.json` and `bundle.json` must be regular
    /// files of at most [`MAX_JSON_METADATA_BYTES`] (checked before they are read). Every file it
    /// reads, pretrained weights included, lies inside `dir` after links are followed
    /// ([`veila_data::contained::contained`]): one that leads out is refused unread.
    pub fn from_dir(dir: &Path, device: &Device) -> Result<Self> {
        // every file of the folder lies in it: a link out of it is refused unread
        let inside = |name: &str| -> Result<PathBuf> {
            Ok(contained(dir, Path::new(name), "bundle file", dir)?)
        };
        // weights: regular files under veila-nn's cap, checked before reading
        let read = |name: &str| -> Result<Vec<u8>> {
            Ok(veila_nn::checkpoint::read_weights_file(&inside(name)?)?)
        };
        let read_json = |name: &str| -> Result<Vec<u8>> {
            let what = format!("a bundle's {name}");
            Ok(read_metadata(
                &inside(name)?,
                MAX_JSON_METADATA_BYTES,
                &what,
            )?)
        };
        let manifest = read_json(MANIFEST_FILE)?;
        let config = read_json(CONFIG_FILE)?;
        let cfg: BundleConfig = serde_json::from_slice(&config).map_err(|source| Error::Json {
            path: dir.join(CONFIG_FILE),
            source,
        })?;
        let mut files: Vec<(String, Vec<u8>)> = vec![
            (MANIFEST_FILE.into(), manifest),
            (CONFIG_FILE.into(), config),
        ];
        for name in cfg.weight_files() {
            files.push((name.into(), read(name)?));
        }
        let refs: Vec<(&str, &[u8])> = files
            .iter()
            .map(|(n, b)| (n.as_str(), b.as_slice()))
            .collect();
        Self::from_files(&refs, dir, device)
    }

    /// Builds a bundle from its files in memory (`(file name, bytes)`); `origin` names the source in
    /// errors. Every file is checked against `manifest.json` first.
    pub fn from_files(files: &[(&str, &[u8])], origin: &Path, device: &Device) -> Result<Self> {
        let get = |name: &str| -> Result<&[u8]> {
            files
                .iter()
                .find(|(n, _)| *n == name)
                .map(|(_, b)| *b)
                .ok_or_else(|| Error::Checkpoint {
                    reason: format!("missing file `{name}`"),
                    path: origin.to_path_buf(),
                })
        };
        let manifest: Manifest =
            serde_json::from_slice(get(MANIFEST_FILE)?).map_err(|source| Error::Json {
                path: origin.join(MANIFEST_FILE),
                source,
            })?;
        if manifest.format != MANIFEST_FORMAT {
            return Err(Error::Checkpoint {
                reason: format!(
                    "manifest format `{}`, expected `{MANIFEST_FORMAT}`",
                    manifest.format
                ),
                path: origin.join(MANIFEST_FILE),
            });
        }
        let verified = |name: &str| -> Result<&[u8]> {
            let bytes = get(name)?;
            let want = manifest.files.get(name).ok_or_else(|| Error::Checkpoint {
                reason: format!("`{name}` is not listed in the manifest"),
                path: origin.join(MANIFEST_FILE),
            })?;
            let got = sha256_hex(bytes);
            if !want.eq_ignore_ascii_case(&got) {
                return Err(Error::Checkpoint {
                    reason: format!(
                        "sha256 mismatch: the manifest says {want}, the file hashes to {got} (corrupted or replaced)"
                    ),
                    path: origin.join(name),
                });
            }
            Ok(bytes)
        };
        let cfg: BundleConfig =
            serde_json::from_slice(verified(CONFIG_FILE)?).map_err(|source| Error::Json {
                path: origin.join(CONFIG_FILE),
                source,
            })?;
        cfg.check(origin)?;
        let load_encoder = |spec: &EncoderSpec, field: &str, name: &str| -> Result<AnyEncoder> {
            match &spec.config {
                Some(c) if !spec.kind.is_pretrained() => {
                    let bytes = verified(name)?;
                    Ok(AnyEncoder::from(veila_nn::encoders::load_checked_bytes(
                        bytes,
                        &origin.join(name),
                        DType::F32,
                        device,
                        |_| true,
                        |vb| SmallCnn::new(c, vb),
                    )?))
                }
                _ => spec.load(origin, field, device),
            }
        };
        let semantic = cfg
            .semantic_encoder
            .as_ref()
            .map(|c| load_encoder(c, "semantic_encoder", SEMANTIC_FILE))
            .transpose()?;
        let depth = cfg
            .depth_encoder
            .as_ref()
            .map(|c| load_encoder(c, "depth_encoder", DEPTH_FILE))
            .transpose()?;
        let path = origin.join(DENOISER_FILE);
        let expected = veila_nn::checkpoint::expected_tensors(&cfg.denoiser)?;
        let weights = veila_nn::checkpoint::read_checked_bytes(
            verified(DENOISER_FILE)?,
            &path,
            &expected,
            device,
        )?;
        let denoiser = Net::new(
            &cfg.denoiser,
            candle_nn::VarBuilder::from_tensors(weights.clone(), DType::F32, device),
        )?;
        let mean = match &cfg.residual {
            Some(r) => {
                let path = origin.join(MEAN_FILE);
                let expected = veila_nn::checkpoint::expected_tensors(&r.mean_net)?;
                let w = veila_nn::checkpoint::read_checked_bytes(
                    verified(MEAN_FILE)?,
                    &path,
                    &expected,
                    device,
                )?;
                let net = Net::new(
                    &r.mean_net,
                    candle_nn::VarBuilder::from_tensors(w.clone(), DType::F32, device),
                )?;
                Some((net, w))
            }
            None => None,
        };
        Ok(Self {
            config: cfg,
            semantic,
            depth,
            denoiser,
            weights,
            mean,
            origin: origin.to_path_buf(),
        })
    }

    /// Writes a bundle folder: every file into a hidden temporary folder beside `dir`, the manifest
    /// last, then one rename (an existing `dir` is replaced only after the new one is complete).
    /// `weights` maps each of [`BundleConfig::weight_files`] to its tensors. A pretrained encoder
    /// whose `weights` is an absolute path (a file the caller chose) is put into the bundle as
    /// `FIELD.KIND.safetensors` (a hard link where the file system allows, else a copy), and
    /// `bundle.json` names it there: a bundle names no file outside itself.
    pub fn save(
        dir: &Path,
        config: &BundleConfig,
        weights: &HashMap<&str, HashMap<String, Tensor>>,
    ) -> Result<()> {
        config.check(dir)?;
        let parent = dir
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        fs::create_dir_all(parent).map_err(|source| Error::Io {
            action: "creating bundle parent folder",
            path: parent.to_path_buf(),
            source,
        })?;
        let name = dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "bundle".into());
        let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
        let _ = fs::remove_dir_all(&tmp);
        let io = |action: &'static str, path: &Path| {
            let path = path.to_path_buf();
            move |source| Error::Io {
                action,
                path,
                source,
            }
        };
        fs::create_dir_all(&tmp).map_err(io("creating bundle folder", &tmp))?;
        let mut manifest = Manifest {
            format: MANIFEST_FORMAT.into(),
            files: BTreeMap::new(),
        };
        let mut put = |file: &str, bytes: &[u8]| -> Result<()> {
            let p = tmp.join(file);
            fs::write(&p, bytes).map_err(io("writing bundle file", &p))?;
            manifest.files.insert(file.into(), sha256_hex(bytes));
            Ok(())
        };
        let mut config = BundleConfig {
            format: BUNDLE_FORMAT.into(),
            ..config.clone()
        };
        // pretrained weights the caller gave by an absolute path (a training config's) come into
        // the bundle, which then names no file outside itself
        for (field, spec) in [
            ("semantic_encoder", &mut config.semantic_encoder),
            ("depth_encoder", &mut config.depth_encoder),
        ] {
            let Some(spec) = spec.as_mut().filter(|s| s.kind.is_pretrained()) else {
                continue;
            };
            let Some(src) = spec.weights.clone().filter(|w| w.is_absolute()) else {
                continue;
            };
            let file = format!("{field}.{}.safetensors", spec.kind);
            let dst = tmp.join(&file);
            fs::hard_link(&src, &dst)
                .or_else(|_| fs::copy(&src, &dst).map(|_| ()))
                .map_err(io(
                    "copying pretrained encoder weights into the bundle",
                    &src,
                ))?;
            spec.weights = Some(file.into());
        }
        let config = &config;
        let json = serde_json::to_vec_pretty(config).map_err(|source| Error::Json {
            path: dir.join(CONFIG_FILE),
            source,
        })?;
        put(CONFIG_FILE, &json)?;
        for file in config.weight_files() {
            let tensors = weights.get(file).ok_or_else(|| Error::Checkpoint {
                reason: format!("no weights given for `{file}`"),
                path: dir.to_path_buf(),
            })?;
            let bytes = safetensors_bytes(tensors, &dir.join(file))?;
            put(file, &bytes)?;
        }
        let json = serde_json::to_vec_pretty(&manifest).map_err(|source| Error::Json {
            path: dir.join(MANIFEST_FILE),
            source,
        })?;
        let p = tmp.join(MANIFEST_FILE);
        fs::write(&p, json).map_err(io("writing bundle file", &p))?;
        if dir.exists() {
            let old = parent.join(format!(".{name}.old-{}", std::process::id()));
            let _ = fs::remove_dir_all(&old);
            fs::rename(dir, &old).map_err(io("replacing bundle", dir))?;
            fs::rename(&tmp, dir).map_err(io("replacing bundle", dir))?;
            let _ = fs::remove_dir_all(&old);
        } else {
            fs::rename(&tmp, dir).map_err(io("writing bundle", dir))?;
        }
        Ok(())
    }
}

/// What generation needs of a bundle (the generation methods themselves, [`Bundle::generate`],
/// [`Bundle::inpaint`], [`Bundle::encode_views`], are in [`super::generate`], which uses this file
/// and not the other way round).
impl Bundle {
    /// The range-image grid `(rows, cols)`.
    pub fn grid(&self) -> (usize, usize) {
        (self.config.denoiser.height(), self.config.denoiser.width())
    }

    /// Whether the denoiser uses the image.
    pub fn is_conditional(&self) -> bool {
        self.config.denoiser.conditioning.is_some()
    }

    pub(crate) fn denoiser_device(&self) -> &Device {
        self.denoiser
            .ray_features()
            .map(|t| t.device())
            .unwrap_or(&Device::Cpu)
    }

    /// The denoiser for `views` camera views (a model trained with one view runs on several: no
    /// weight depends on the number of views).
    pub(crate) fn net_for_views(&self, views: usize) -> Result<Net> {
        rebuild_for_views(
            &self.denoiser,
            &self.config.denoiser,
            &self.weights,
            views,
            self.denoiser_device(),
        )
    }

    /// The mean network of a residual bundle for `views` camera views.
    pub(crate) fn mean_for_views(&self, views: usize) -> Result<Option<Net>> {
        match (&self.mean, &self.config.residual) {
            (Some((net, weights)), Some(r)) => Ok(Some(rebuild_for_views(
                net,
                &r.mean_net,
                weights,
                views,
                self.denoiser_device(),
            )?)),
            _ => Ok(None),
        }
    }
}

fn rebuild_for_views(
    net: &Net,
    cfg: &veila_nn::DenoiserConfig,
    weights: &HashMap<String, Tensor>,
    views: usize,
    device: &Device,
) -> Result<Net> {
    let Some(cc) = &cfg.conditioning else {
        return Ok(net.clone());
    };
    if cc.num_views == views {
        return Ok(net.clone());
    }
    let mut cfg = cfg.clone();
    if let Some(c) = cfg.conditioning.as_mut() {
        c.num_views = views;
    }
    Ok(Net::new(
        &cfg,
        VarBuilder::from_tensors(weights.clone(), DType::F32, device),
    )?)
}

/// The model variants of the paper's ablation study (Table 4), as switches on a bundle config.
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

impl ResidualConfig {
    /// The process the mean network runs: one regression pass.
    pub fn mean_diffusion() -> DiffusionConfig {
        DiffusionConfig {
            objective: crate::objective::Objective::Regression,
            ..DiffusionConfig::default()
        }
    }
}

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
    /// This config switched to `method` (denoiser channels, objective, residual settings and
    /// sampler); the residual scale starts at 1 and is set by training.
    pub fn with_method(mut self, method: Method) -> Self {
        use crate::objective::Objective;
        use crate::prediction::Prediction;
        let c = self.encoding.num_channels();
        self.residual = None;
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

    /// Camera views the denoiser takes (1 when it is unconditional).
    pub fn num_views(&self) -> usize {
        self.denoiser
            .conditioning
            .as_ref()
            .map_or(1, |c| c.num_views.max(1))
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

impl BundleConfig {
    /// The bundled CPU model's config ([`DenoiserConfig::small`], two default small CNN encoders
    /// at 96 x 320, KITTI range encoding, cosine log-SNR schedule with v-prediction and min-SNR-5
    /// weighting, DPM-Solver++(2M)
    /// with 16 steps and guidance 1.5 by default; [`with_method`](Self::with_method) gives the
    /// residual method 16 DDPM steps without guidance), turned into `variant`.
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
        let mut sampler = SamplerConfig::dpm_solver_pp_2m(16);
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
            provenance: serde_json::Value::Null,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bundle folder whose `bundle.json` is `make(path)` (its manifest a small placeholder:
    /// the files are refused before anything is parsed).
    fn bundle_dir_with_config(make: impl FnOnce(&Path)) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join(MANIFEST_FILE), b"{}").unwrap();
        make(&dir.path().join(CONFIG_FILE));
        dir
    }

    #[cfg(unix)]
    #[test]
    fn a_bundle_json_linked_to_dev_zero_is_refused_naming_it() {
        let dir = bundle_dir_with_config(|p| std::os::unix::fs::symlink("/dev/zero", p).unwrap());
        let e = Bundle::from_dir(dir.path(), &Device::Cpu)
            .unwrap_err()
            .to_string();
        // a link out of the bundle folder is refused before the size and type checks look at it
        assert!(
            e.contains(CONFIG_FILE) && e.contains("leads through the link `bundle.json`"),
            "{e}"
        );
    }

    #[test]
    fn a_sparse_3_gb_bundle_json_is_refused_unread() {
        let dir = bundle_dir_with_config(|p| {
            fs::File::create(p).unwrap().set_len(3 << 30).unwrap();
        });
        let e = Bundle::from_dir(dir.path(), &Device::Cpu)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(CONFIG_FILE)
                && e.contains(&format!(
                    "3221225472 bytes, more than the cap of {MAX_JSON_METADATA_BYTES} bytes"
                )),
            "{e}"
        );
    }
}
