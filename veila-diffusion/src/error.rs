//! The crate's error type.

use std::path::PathBuf;

/// Everything that can go wrong in `veila-diffusion`.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A tensor operation failed inside candle.
    #[error(transparent)]
    Candle(#[from] candle_core::Error),

    /// A configuration value is out of its domain.
    #[error("invalid config `{field}`: {reason}")]
    InvalidConfig {
        /// Name of the offending field.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },

    /// A tensor or slice has the wrong shape.
    #[error("shape mismatch for {what}: expected {expected}, got {got}")]
    Shape {
        /// Which input.
        what: &'static str,
        /// Expected shape, human readable.
        expected: String,
        /// Actual shape, human readable.
        got: String,
    },

    /// A value that must be finite is NaN or infinite.
    #[error("non-finite {what} at training step {step}")]
    NonFinite {
        /// What was not finite (loss, gradient norm, ...).
        what: &'static str,
        /// Training step at which it happened.
        step: u64,
    },

    /// File system error, with the path it happened on (path last).
    #[error("{action} failed: {source}: {}", path.display())]
    Io {
        /// What was being done (`writing checkpoint`, ...).
        action: &'static str,
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },

    /// A checkpoint is incomplete or inconsistent with the model being trained.
    #[error("bad checkpoint: {reason}: {}", path.display())]
    Checkpoint {
        /// What is wrong.
        reason: String,
        /// The checkpoint directory or file.
        path: PathBuf,
    },

    /// JSON (de)serialisation of training state failed.
    #[error("json error: {source}: {}", path.display())]
    Json {
        /// The JSON file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: serde_json::Error,
    },

    /// The `veila-nn` network failed.
    #[cfg(feature = "app")]
    #[error(transparent)]
    Model(#[from] veila_nn::Error),

    /// A metric could not be computed (the error names the metric and the input).
    #[cfg(feature = "app")]
    #[error(transparent)]
    Metrics(#[from] veila_metrics::Error),

    /// A sensor or camera is invalid.
    #[error(transparent)]
    Geom(#[from] veila_geom::GeomError),

    /// An input file (an image, a calibration) is unusable; the reason names what is wrong.
    #[error("{}: {reason}", path.display())]
    Input {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },

    /// An output folder that cannot take this job (another job's, holding files it did not
    /// write, or inside its own input); nothing in it was changed.
    #[error("{}: {reason}", path.display())]
    Output {
        /// The output folder or the file in it that is in the way.
        path: PathBuf,
        /// What is wrong and what to do, in words.
        reason: String,
    },

    /// Reading or writing a file of `veila-data`'s formats failed (the error names the file).
    #[cfg(feature = "app")]
    #[error(transparent)]
    Files(#[from] veila_data::Error),

    /// The training data source ran out or failed.
    #[error("data source: {0}")]
    Data(String),

    /// Loading the encoders of another bundle for a training run failed (what failed follows).
    #[error("loading the encoders of {}: {source}", dir.display())]
    EncodersFrom {
        /// The bundle folder the encoders come from.
        dir: PathBuf,
        /// What failed.
        #[source]
        source: Box<Error>,
    },

    /// Data-parallel training: a rank could not reach, or lost, the others (the message names
    /// the rank and the address).
    #[error("data-parallel group: {0}")]
    Distributed(String),
}

/// `Result` with this crate's [`Error`].
pub type Result<T> = std::result::Result<T, Error>;

pub(crate) fn invalid(field: &'static str, reason: impl Into<String>) -> Error {
    Error::InvalidConfig {
        field,
        reason: reason.into(),
    }
}
