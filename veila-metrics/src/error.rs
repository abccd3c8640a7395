//! The crate's single error type.

/// Everything that can go wrong when computing a metric.
///
/// Errors name the offending input (`what`: e.g. `"generated scan 3"`) so that a command-line front end can
/// report them without extra bookkeeping.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum Error {
    /// A set of scans, a point set, a feature matrix or a map was empty where at least one element is needed.
    #[error("{what} is empty")]
    Empty {
        /// Which input was empty.
        what: String,
    },
    /// An input held a NaN or an infinity.
    #[error("{what}: non-finite value at index {index}")]
    NonFinite {
        /// Which input.
        what: String,
        /// Index of the first offending element (point index, feature index, pixel index).
        index: usize,
    },
    /// A scan had no point inside the metric's window (e.g. the BEV window 3 m < |p| < 70 m), so its
    /// normalised histogram is undefined.
    #[error("{what} has no point inside the {window} window")]
    NoPointsInWindow {
        /// Which scan or set.
        what: String,
        /// Human-readable window description.
        window: String,
    },
    /// Two inputs that must agree in shape do not.
    #[error("{what}: expected {expected}, got {got}")]
    ShapeMismatch {
        /// Which input.
        what: String,
        /// Expected size / shape.
        expected: String,
        /// Actual size / shape.
        got: String,
    },
    /// Not enough samples for the requested statistic (e.g. a covariance needs at least two rows).
    #[error("{what}: need at least {needed} samples, got {got}")]
    TooFewSamples {
        /// Which input.
        what: String,
        /// Minimum sample count.
        needed: usize,
        /// Actual sample count.
        got: usize,
    },
    /// A configuration value is out of its domain.
    #[error("invalid parameter {name}: {reason}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// A label map whose ids are not in the label space the metric compares in.
    #[error("{what}: {label} at pixel {index} is not a {space} id; {hint}")]
    LabelSpace {
        /// Which map.
        what: String,
        /// The first offending label.
        label: u32,
        /// Its pixel (row-major index).
        index: usize,
        /// The expected label space, in words.
        space: &'static str,
        /// What the ids look like instead, in words.
        hint: String,
    },
    /// A dense linear-algebra routine failed (e.g. the eigensolver did not converge).
    #[error("linear algebra failure: {0}")]
    Linalg(String),
    /// One scan of a set (named by its file, or `file[i]` for a sample of a sample set) failed.
    #[error("{label}: {source}")]
    Scan {
        /// The scan.
        label: String,
        /// What went wrong with it.
        #[source]
        source: Box<Error>,
    },
}

/// The crate's result type.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub(crate) fn empty(what: impl Into<String>) -> Self {
        Error::Empty { what: what.into() }
    }
}
