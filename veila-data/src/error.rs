//! The one error type of `veila-data`. Every variant that concerns a file names it.

use std::path::PathBuf;

/// Result alias of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Everything that can go wrong while reading, writing or simulating data.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// An operating-system error on a file or directory.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A file whose content is not what its format requires.
    #[error("{}: {message}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong, in words.
        message: String,
    },
    /// A file refused before its content was read: not a regular file (a FIFO, a device, a
    /// directory), or larger than the cap for its kind (see [`crate::read_capped`]).
    #[error("{}: {message}", path.display())]
    Refused {
        /// The file.
        path: PathBuf,
        /// Why it was refused, in words.
        message: String,
    },
    /// A path read from an artifact (a calibration's image, a manifest's shard, a bundle's
    /// weights) that is absolute, climbs out with `..`, or leads out of its folder through a link:
    /// refused before anything at it is opened (see [`crate::contained`]).
    #[error("{}: {field} `{value}`: {reason}", file.display())]
    PathOutside {
        /// The file that names the path (or the folder, for a folder's fixed files).
        file: PathBuf,
        /// The field that holds it (`cameras.CAM_FRONT.file`, `shards[0].file`, ...).
        field: String,
        /// The path as written, control characters escaped.
        value: String,
        /// Why it was refused, in words.
        reason: String,
    },
    /// Inputs that do not fit together (point and label counts, image sizes, ...).
    #[error("{context}: {message}")]
    Mismatch {
        /// Which inputs (file names where there are files).
        context: String,
        /// What does not fit.
        message: String,
    },
    /// An invalid configuration or argument.
    #[error("invalid {what}: {message}")]
    Invalid {
        /// What was invalid.
        what: String,
        /// Why.
        message: String,
    },
    /// An active weather effect lacks an input it needs and has no fallback for it.
    #[error("weather effect '{effect}' needs {input}, which was not given")]
    MissingInput {
        /// The effect (or effects) that need it.
        effect: String,
        /// The missing input, in words.
        input: String,
    },
    /// A geometry error from `veila-geom`.
    #[error(transparent)]
    Geom(#[from] veila_geom::GeomError),
}

impl Error {
    /// Build an [`Error::Io`] for `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
    /// Build an [`Error::Format`] for `path`.
    pub fn format(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Format {
            path: path.into(),
            message: message.into(),
        }
    }
}
