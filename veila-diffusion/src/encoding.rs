//! Range-image encoding for diffusion, after R2DM (Nakashima & Kurazume, ICRA 2024).
//!
//! Each pixel becomes up to three channels in `[-1, 1]`:
//!
//! | channel | encoding |
//! |---|---|
//! | range | `2 · log2(r + 1) / log2(r_max + 1) − 1`, `r` clamped to `[0, r_max]` |
//! | intensity (optional) | `2 · i / i_max − 1`, `i` clamped to `[0, i_max]` |
//! | ray drop (optional) | `+1` for a return, `−1` for a dropped ray |
//!
//! A dropped ray has range `−1` and intensity `−1` as well, so a model trained without the explicit
//! ray-drop channel still sees R2DM's convention (a drop is range zero). Decoding turns a pixel back
//! into a missing point when its ray-drop channel is at or below
//! [`RangeEncoding::raydrop_threshold`] (or, without that channel, when its decoded range is below
//! [`RangeEncoding::min_range_m`]); NaN outputs are always decoded as missing points.

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};
use veila_geom::RangeImage;

use crate::error::{Error, Result, invalid};

/// The range interval [`RangeEncoding::max_range_m`] may take, metres: from 1 m (the encoding
/// divides by `log2(max_range_m + 1)`: 1e-30 made every return saturate) to 1000 m (no LiDAR
/// reaches further; the presets use 80 m).
pub const ENCODED_RANGE_M: (f32, f32) = (1.0, 1000.0);

/// The interval [`RangeEncoding::intensity_max`] may take: KITTI's intensities are in `[0, 1]`,
/// nuScenes' in `[0, 255]`; 1e-3 to 1e6 holds any sensor's unit.
pub const INTENSITY_MAX: (f32, f32) = (1e-3, 1e6);

/// How range images are mapped to and from the network's `[-1, 1]` channels.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RangeEncoding {
    /// Ranges above this are clamped to it before encoding (metres).
    pub max_range_m: f32,
    /// Decoded returns closer than this are treated as dropped rays (metres).
    pub min_range_m: f32,
    /// Intensity value that maps to `+1` (1.0 for KITTI, 255.0 for nuScenes).
    pub intensity_max: f32,
    /// Whether an intensity channel is present.
    pub intensity: bool,
    /// Whether an explicit ray-drop channel is present (last channel).
    pub raydrop: bool,
    /// Decoded ray-drop values at or below this mean "no return".
    pub raydrop_threshold: f32,
}

impl Default for RangeEncoding {
    fn default() -> Self {
        Self::kitti()
    }
}

impl RangeEncoding {
    /// R2DM's KITTI setting: 1.45–80 m, intensity in `[0, 1]`, with intensity and ray-drop channels.
    pub fn kitti() -> Self {
        Self {
            max_range_m: 80.0,
            min_range_m: 1.45,
            intensity_max: 1.0,
            intensity: true,
            raydrop: true,
            raydrop_threshold: 0.0,
        }
    }

    /// Checks that every field is in its domain: `max_range_m` within [`ENCODED_RANGE_M`],
    /// `min_range_m` in `[0, max_range_m)`, `intensity_max` within [`INTENSITY_MAX`],
    /// `raydrop_threshold` in `(-1, 1)`.
    pub fn validate(&self) -> Result<()> {
        let (lo, hi) = ENCODED_RANGE_M;
        if !(self.max_range_m.is_finite() && (lo..=hi).contains(&self.max_range_m)) {
            return Err(invalid(
                "max_range_m",
                format!("must be between {lo} and {hi} m, got {}", self.max_range_m),
            ));
        }
        if !(self.min_range_m.is_finite()
            && self.min_range_m >= 0.0
            && self.min_range_m < self.max_range_m)
        {
            return Err(invalid(
                "min_range_m",
                format!("must be in [0, max_range_m), got {}", self.min_range_m),
            ));
        }
        let (lo, hi) = INTENSITY_MAX;
        if !(self.intensity_max.is_finite() && (lo..=hi).contains(&self.intensity_max)) {
            return Err(invalid(
                "intensity_max",
                format!("must be between {lo} and {hi}, got {}", self.intensity_max),
            ));
        }
        if !(self.raydrop_threshold.is_finite() && self.raydrop_threshold.abs() < 1.0) {
            return Err(invalid(
                "raydrop_threshold",
                format!("must be in (-1, 1), got {}", self.raydrop_threshold),
            ));
        }
        Ok(())
    }

    /// Number of encoded channels (1 to 3).
    pub fn num_channels(&self) -> usize {
        1 + usize::from(self.intensity) + usize::from(self.raydrop)
    }

    /// Index of the intensity channel, if any.
    pub fn intensity_channel(&self) -> Option<usize> {
        self.intensity.then_some(1)
    }

    /// Index of the ray-drop channel, if any.
    pub fn raydrop_channel(&self) -> Option<usize> {
        self.raydrop.then_some(self.num_channels() - 1)
    }

    /// Encodes one range in metres to `[-1, 1]` (log scale). Non-finite or negative ranges map to `-1`.
    pub fn encode_range(&self, range_m: f32) -> f32 {
        if !range_m.is_finite() || range_m <= 0.0 {
            return -1.0;
        }
        let r = range_m.min(self.max_range_m) as f64;
        let v = (r + 1.0).log2() / (self.max_range_m as f64 + 1.0).log2();
        (2.0 * v - 1.0) as f32
    }

    /// Decodes one encoded range back to metres (input clamped to `[-1, 1]`; NaN gives NaN).
    pub fn decode_range(&self, v: f32) -> f32 {
        if v.is_nan() {
            return f32::NAN;
        }
        let u = ((v.clamp(-1.0, 1.0) as f64) + 1.0) * 0.5;
        let r = (u * (self.max_range_m as f64 + 1.0).log2()).exp2() - 1.0;
        r.max(0.0) as f32
    }

    /// Encodes one intensity to `[-1, 1]` (clamped; non-finite gives `-1`).
    pub fn encode_intensity(&self, intensity: f32) -> f32 {
        if !intensity.is_finite() {
            return -1.0;
        }
        2.0 * (intensity / self.intensity_max).clamp(0.0, 1.0) - 1.0
    }

    /// Decodes one encoded intensity (clamped to `[0, intensity_max]`).
    pub fn decode_intensity(&self, v: f32) -> f32 {
        if v.is_nan() {
            return 0.0;
        }
        (v.clamp(-1.0, 1.0) + 1.0) * 0.5 * self.intensity_max
    }

    /// Encodes one scan into a `C * rows * cols` channel-major buffer (pixels without a return,
    /// or with a range that is not finite and > 0, encode as "dropped").
    pub fn encode_to_vec(&self, scan: &RangeImage) -> Result<Vec<f32>> {
        self.validate()?;
        let n = scan.num_pixels();
        check_len("range_m", n, scan.range_m.len())?;
        check_len("intensity", n, scan.intensity.len())?;
        check_len("mask", n, scan.mask.len())?;
        let c = self.num_channels();
        let mut out = vec![-1.0f32; c * n];
        for p in 0..n {
            let r = scan.range_m[p];
            let valid = scan.mask[p] && r.is_finite() && r > 0.0;
            if !valid {
                continue;
            }
            out[p] = self.encode_range(r);
            if let Some(ci) = self.intensity_channel() {
                out[ci * n + p] = self.encode_intensity(scan.intensity[p]);
            }
            if let Some(cd) = self.raydrop_channel() {
                out[cd * n + p] = 1.0;
            }
        }
        Ok(out)
    }

    /// Encodes a batch of equally sized scans into a `[B, C, rows, cols]` f32 tensor.
    pub fn encode_batch(&self, scans: &[&RangeImage], device: &Device) -> Result<Tensor> {
        let Some(first) = scans.first() else {
            return Err(invalid("scans", "empty batch"));
        };
        let (rows, cols) = (first.rows as usize, first.cols as usize);
        let mut data = Vec::with_capacity(scans.len() * self.num_channels() * rows * cols);
        for s in scans {
            if (s.rows as usize, s.cols as usize) != (rows, cols) {
                return Err(Error::Shape {
                    what: "scan in batch",
                    expected: format!("{rows}x{cols}"),
                    got: format!("{}x{}", s.rows, s.cols),
                });
            }
            data.extend(self.encode_to_vec(s)?);
        }
        Ok(Tensor::from_vec(
            data,
            (scans.len(), self.num_channels(), rows, cols),
            device,
        )?)
    }

    /// Decodes a `[B, C, rows, cols]` tensor (any float dtype, any device) into scans (no source
    /// points: `point_index` is [`veila_geom::NO_POINT`] everywhere; no labels).
    pub fn decode_batch(&self, x: &Tensor) -> Result<Vec<RangeImage>> {
        self.validate()?;
        let (b, c, rows, cols) = x.dims4()?;
        if c != self.num_channels() {
            return Err(Error::Shape {
                what: "encoded range image channels",
                expected: self.num_channels().to_string(),
                got: c.to_string(),
            });
        }
        let data = x
            .to_dtype(candle_core::DType::F32)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let n = rows * cols;
        data.chunks_exact(c * n)
            .take(b)
            .map(|img| self.decode_slice(img, rows, cols))
            .collect()
    }

    /// Decodes one channel-major `C * rows * cols` buffer.
    pub fn decode_slice(&self, img: &[f32], rows: usize, cols: usize) -> Result<RangeImage> {
        let (r32, c32) = match (u32::try_from(rows), u32::try_from(cols)) {
            (Ok(r), Ok(c)) => (r, c),
            _ => {
                return Err(invalid(
                    "rows / cols",
                    format!("{rows} x {cols} is too large"),
                ));
            }
        };
        let n = rows * cols;
        let mut out = RangeImage::new_empty(r32, c32);
        for p in 0..n.min(img.len()) {
            let v = img[p];
            if v.is_nan() {
                continue;
            }
            if let Some(cd) = self.raydrop_channel() {
                match img.get(cd * n + p) {
                    Some(d) if *d > self.raydrop_threshold => {}
                    _ => continue,
                }
            }
            let r = self.decode_range(v);
            if r.is_nan() || r < self.min_range_m {
                continue;
            }
            out.range_m[p] = r;
            out.mask[p] = true;
            if let Some(ci) = self.intensity_channel() {
                out.intensity[p] = img
                    .get(ci * n + p)
                    .map_or(0.0, |&i| self.decode_intensity(i));
            }
        }
        Ok(out)
    }
}

fn check_len(what: &'static str, expected: usize, got: usize) -> Result<()> {
    if expected == got {
        Ok(())
    } else {
        Err(Error::Shape {
            what,
            expected: format!("{expected} pixels"),
            got: format!("{got} pixels"),
        })
    }
}

#[cfg(test)]
mod tests;
