//! The one error type of `veila-geom`.

/// Everything that can be wrong with geometric input: invalid sensors, cameras, tables or mismatched
/// buffers. Projection of individual points never fails; bad points are rejected and counted instead.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum GeomError {
    /// A sensor description that cannot be used (zero size, non-finite or inverted field of view, a bad
    /// per-beam table, an empty range interval).
    #[error("invalid LiDAR sensor: {0}")]
    InvalidSensor(String),
    /// A camera whose matrices are non-finite or degenerate (for example `fx = 0`).
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
    /// An invalid configuration value (epipolar table, Fourier encoding, projection options).
    #[error("invalid {what}: {message}")]
    InvalidConfig {
        /// The configuration.
        what: &'static str,
        /// Why it is invalid.
        message: String,
    },
    /// Two buffers that must have the same length do not.
    #[error("{what}: expected {expected} values, got {got}")]
    LengthMismatch {
        /// Which buffer.
        what: &'static str,
        /// The length it must have.
        expected: usize,
        /// The length it has.
        got: usize,
    },
}
