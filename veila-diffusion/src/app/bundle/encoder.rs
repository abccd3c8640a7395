//! A bundle's image encoders ([`EncoderSpec`]): a small CNN trained with the bundle or a
//! pretrained network whose weights file the bundle names, found and checked on load.

use std::path::{Path, PathBuf};

use candle_core::{DType, Device};
use serde::{Deserialize, Serialize};
use veila_data::contained::contained;
use veila_nn::encoders::kind::{AnyEncoder, EncoderKind};
use veila_nn::encoders::small_cnn::SmallCnnConfig;

use super::{CONFIG_FILE, sha256_hex};
use crate::error::{Error, Result};

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
    /// inside it (an absolute path only until [`Bundle::save`](super::Bundle::save) brings the file in).
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
    /// [`Bundle::save`](super::Bundle::save) brings into the bundle, or one relative to the bundle folder), with their
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

    pub(super) fn check(&self, field: &str) -> std::result::Result<(), String> {
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
