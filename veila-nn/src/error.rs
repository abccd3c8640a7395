//! The crate's single error type.

use std::fmt;
use std::path::PathBuf;

/// Result alias used throughout `veila-nn`.
pub type Result<T> = std::result::Result<T, Error>;

/// Everything that can go wrong in `veila-nn`.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// An error raised by candle (tensor op, device, dtype).
    #[error(transparent)]
    Candle(#[from] candle_core::Error),

    /// A model configuration is inconsistent (the message names the field).
    #[error("invalid config: {0}")]
    Config(String),

    /// An input value (image tensor, pixel buffer, label map, loss argument) is invalid; the message
    /// names the function and what is wrong.
    #[error("invalid input: {0}")]
    Input(String),

    /// A tensor handed to a forward pass has the wrong shape.
    #[error("bad shape for {what}: expected {expected}, got {got:?}")]
    Shape {
        /// Which input (e.g. `"x"`, `"semantic feature 2"`).
        what: String,
        /// Human-readable expected shape (may contain symbolic dims such as `B`).
        expected: String,
        /// The actual dims.
        got: Vec<usize>,
    },

    /// Geometry (sensor, camera, epipolar table) could not be built.
    #[error("geometry: {0}")]
    Geom(#[from] veila_geom::GeomError),

    /// Reading or writing a file failed.
    #[error("io error: {source}: {}", path.display())]
    Io {
        /// The file involved.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },

    /// A JSON config file could not be parsed or written.
    #[error("config json: {source}: {}", path.display())]
    Json {
        /// The file involved.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: serde_json::Error,
    },

    /// A weights file was refused before it was read: not a regular file (a link to `/dev/zero`,
    /// a FIFO, a directory), or larger than [`crate::weights::MAX_WEIGHTS_FILE_BYTES`].
    #[error("refused: {message}: {}", path.display())]
    Refused {
        /// The file involved.
        path: PathBuf,
        /// Why it was refused.
        message: String,
    },

    /// A safetensors file could not be parsed or written.
    #[error("safetensors: {message}: {}", path.display())]
    SafeTensors {
        /// The file involved.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },

    /// A file of a model bundle is missing from its manifest or its sha256 sum differs from the one
    /// the manifest records (a corrupted download or a hand-edited file).
    #[error("integrity check failed: {message}: {}", path.display())]
    Integrity {
        /// The file whose checksum is wrong (or the manifest itself).
        path: PathBuf,
        /// What is wrong (expected and found sums).
        message: String,
    },

    /// A tensor of a weights file has a dtype the model does not take, or values that are not
    /// finite or beyond [`crate::weights::MAX_ABS_WEIGHT`].
    #[error("bad weights: tensor `{tensor}`: {reason}: {}", path.display())]
    BadWeights {
        /// The weights file.
        path: PathBuf,
        /// The tensor's name.
        tensor: String,
        /// What is wrong with it.
        reason: String,
    },

    /// The tensors of a checkpoint do not match the model built from its config.
    #[error("checkpoint does not match the model: {report}: {}", path.display())]
    CheckpointMismatch {
        /// The weights file.
        path: PathBuf,
        /// Missing, unexpected and mis-shaped tensors, by name.
        report: TensorReport,
    },
}

/// Names of tensors that differ between a checkpoint and the model that should load it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TensorReport {
    /// Tensors the model needs that the file lacks (sorted).
    pub missing: Vec<String>,
    /// Tensors in the file that the model does not use (sorted).
    pub unexpected: Vec<String>,
    /// Tensors present in both with different shapes: `(name, expected, found)` (sorted by name).
    pub mis_shaped: Vec<(String, Vec<usize>, Vec<usize>)>,
}

impl TensorReport {
    /// True when nothing is missing, unexpected or mis-shaped.
    pub fn is_clean(&self) -> bool {
        self.missing.is_empty() && self.unexpected.is_empty() && self.mis_shaped.is_empty()
    }
}

impl fmt::Display for TensorReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        const SHOW: usize = 8;
        let mut parts = Vec::new();
        let list = |names: &[String]| {
            let mut s = names
                .iter()
                .take(SHOW)
                .cloned()
                .collect::<Vec<_>>()
                .join(", ");
            if names.len() > SHOW {
                s.push_str(&format!(", ... ({} more)", names.len() - SHOW));
            }
            s
        };
        if !self.missing.is_empty() {
            parts.push(format!(
                "{} missing [{}]",
                self.missing.len(),
                list(&self.missing)
            ));
        }
        if !self.unexpected.is_empty() {
            parts.push(format!(
                "{} unexpected [{}]",
                self.unexpected.len(),
                list(&self.unexpected)
            ));
        }
        if !self.mis_shaped.is_empty() {
            let shown: Vec<String> = self
                .mis_shaped
                .iter()
                .take(SHOW)
                .map(|(n, e, g)| format!("{n}: expected {e:?}, found {g:?}"))
                .collect();
            let mut s = shown.join(", ");
            if self.mis_shaped.len() > SHOW {
                s.push_str(&format!(", ... ({} more)", self.mis_shaped.len() - SHOW));
            }
            parts.push(format!("{} mis-shaped [{}]", self.mis_shaped.len(), s));
        }
        if parts.is_empty() {
            write!(f, "no differences")
        } else {
            write!(f, "{}", parts.join("; "))
        }
    }
}

pub(crate) fn shape_err(
    what: impl Into<String>,
    expected: impl Into<String>,
    got: &[usize],
) -> Error {
    Error::Shape {
        what: what.into(),
        expected: expected.into(),
        got: got.to_vec(),
    }
}
