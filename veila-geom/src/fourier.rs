//! NeRF-style Fourier positional encoding of 3D points.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::GeomError;

/// `gamma(p) = [p*scale?, sin(2^0 pi s p), cos(2^0 pi s p), ..., sin(2^(L-1) pi s p), cos(2^(L-1) pi s p)]`
/// with `s = scale`; each sin/cos group holds the three coordinates `x, y, z`.
///
/// Points in metres should be scaled to roughly `[-1, 1]` (for example `scale = 1 / max_range_m`),
/// otherwise the high frequencies alias.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FourierEncoding {
    /// Number of frequencies `L`.
    pub num_freqs: usize,
    /// Multiplies the point before encoding.
    pub scale: f32,
    /// Whether the scaled point itself leads the encoding.
    pub include_input: bool,
}

impl FourierEncoding {
    /// Check the configuration (`scale` finite and positive, `num_freqs <= 32`).
    pub fn validate(&self) -> Result<(), GeomError> {
        if !(self.scale.is_finite() && self.scale > 0.0) || self.num_freqs > 32 {
            return Err(GeomError::InvalidConfig {
                what: "Fourier encoding",
                message: format!(
                    "need a finite positive scale and at most 32 frequencies, got scale {} and {} frequencies",
                    self.scale, self.num_freqs
                ),
            });
        }
        Ok(())
    }

    /// Length of one encoding.
    pub fn dim(&self) -> usize {
        6 * self.num_freqs + if self.include_input { 3 } else { 0 }
    }

    /// Append the encoding of `p` to `out`. Angles are reduced in `f64`, so large frequencies stay
    /// accurate.
    pub fn encode(&self, p: Vec3, out: &mut Vec<f32>) {
        let s = f64::from(self.scale);
        let q = [f64::from(p.x) * s, f64::from(p.y) * s, f64::from(p.z) * s];
        if self.include_input {
            out.extend(q.iter().map(|v| *v as f32));
        }
        for l in 0..self.num_freqs {
            let f = std::f64::consts::PI * (1u64 << l) as f64;
            out.extend(q.iter().map(|v| (f * v).sin() as f32));
            out.extend(q.iter().map(|v| (f * v).cos() as f32));
        }
    }
}
