//! Image preprocessing exactly as the reference image processors do it: resize rule, resampling
//! filter, rescale to `[0, 1]` and mean/std normalisation.
//!
//! Hugging Face's `SegformerImageProcessor` and `DPTImageProcessor` (the one the Depth-Anything-V2
//! `-hf` checkpoints name) resize the `u8` image with Pillow before normalising it, so the
//! resampling here is Pillow's own algorithm ([`resize_rgb8`]): separable (the horizontal pass
//! first, unless the image shrinks vertically while it grows horizontally), the filter stretched by the scale factor when shrinking (antialiasing), weights normalised per
//! output pixel and applied in 22-bit fixed point with rounding, each pass rounded and clamped to
//! `u8`. It is hand-written rather than taken from an image crate because only Pillow's exact
//! arithmetic reproduces the processors' bytes (`image`'s filters differ in support and rounding).
//! `tests/it/preprocess.rs` checks every byte against Pillow, and the processors' pixel values
//! against `SegformerImageProcessorPil` / `DPTImageProcessorPil`, with the script that made the
//! references kept beside them.
//!
//! ```
//! use veila_nn::encoders::preprocess::ImageProcessor;
//!
//! # fn main() -> veila_nn::Result<()> {
//! // a KITTI-size camera image (375 x 1242)
//! let (h, w) = (375, 1242);
//! let rgb = vec![100u8; h * w * 3];
//! let da = ImageProcessor::depth_anything_v2();
//! // aspect kept, the side closer to the 518 target sets the scale, multiples of 14
//! assert_eq!(da.output_size(h, w)?, (518, 1722));
//! let seg = ImageProcessor::segformer(512, 512);
//! let x = seg.preprocess(&rgb, h, w, &candle_core::Device::Cpu)?;
//! assert_eq!(x.dims(), &[1, 3, 512, 512]);
//! # Ok(())
//! # }
//! ```

use candle_core::{Device, Tensor};

use super::{Normalization, depth_anything_resize_size, rgb8_to_tensor, size_for_multiple};

/// Largest image a resize may produce, in pixels (a bound on memory for any argument: 256 Mpx,
/// 768 MiB of RGB bytes).
pub const MAX_OUTPUT_PIXELS: usize = 1 << 28;

/// Pillow's resampling filters used by the reference processors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Resample {
    /// `PIL.Image.BILINEAR` (2): triangle filter, support 1 (SegFormer).
    Bilinear,
    /// `PIL.Image.BICUBIC` (3): cubic convolution with `a = -0.5`, support 2 (DPT, Depth-Anything,
    /// DINOv2).
    Bicubic,
}

impl Resample {
    fn support(self) -> f64 {
        match self {
            Resample::Bilinear => 1.0,
            Resample::Bicubic => 2.0,
        }
    }

    fn weight(self, x: f64) -> f64 {
        let x = x.abs();
        match self {
            Resample::Bilinear => {
                if x < 1.0 {
                    1.0 - x
                } else {
                    0.0
                }
            }
            Resample::Bicubic => {
                const A: f64 = -0.5;
                if x < 1.0 {
                    ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
                } else if x < 2.0 {
                    (((x - 5.0) * x + 8.0) * x - 4.0) * A
                } else {
                    0.0
                }
            }
        }
    }
}

/// Fixed-point precision of Pillow's 8-bit resampling.
const PRECISION_BITS: u32 = 32 - 8 - 2;

/// Per output pixel: first input index and fixed-point weights (Pillow's `precompute_coeffs`
/// followed by `normalize_coeffs_8bpc`).
fn coefficients(in_size: usize, out_size: usize, filter: Resample) -> Vec<(usize, Vec<i32>)> {
    let scale = in_size as f64 / out_size as f64;
    let filterscale = scale.max(1.0);
    let support = filter.support() * filterscale;
    let ss = 1.0 / filterscale;
    (0..out_size)
        .map(|xx| {
            let center = (xx as f64 + 0.5) * scale;
            // C's `(int)` truncates toward zero, as does `as`
            let xmin = ((center - support + 0.5) as i64).max(0) as usize;
            let xmax = ((center + support + 0.5) as i64).min(in_size as i64) as usize;
            let n = xmax.saturating_sub(xmin);
            let mut k: Vec<f64> = (0..n)
                .map(|x| filter.weight((x as f64 + xmin as f64 - center + 0.5) * ss))
                .collect();
            let ww: f64 = k.iter().sum();
            if ww != 0.0 {
                for v in &mut k {
                    *v /= ww;
                }
            }
            let one = (1u32 << PRECISION_BITS) as f64;
            let fixed = k
                .iter()
                .map(|&v| {
                    if v < 0.0 {
                        (-0.5 + v * one) as i32
                    } else {
                        (0.5 + v * one) as i32
                    }
                })
                .collect();
            (xmin, fixed)
        })
        .collect()
}

fn clip8(v: i64) -> u8 {
    (v >> PRECISION_BITS).clamp(0, 255) as u8
}

/// Resizes an interleaved RGB `u8` image (`height x width x 3`, row-major) to
/// `out_height x out_width` with Pillow's algorithm and arithmetic, byte for byte what
/// `PIL.Image.resize((out_width, out_height), filter, reducing_gap=None)` returns.
///
/// # Errors
/// When the buffer does not hold `height * width * 3` bytes, a size is zero, or the output would
/// exceed [`MAX_OUTPUT_PIXELS`].
pub fn resize_rgb8(
    rgb: &[u8],
    (height, width): (usize, usize),
    (out_height, out_width): (usize, usize),
    filter: Resample,
) -> crate::Result<Vec<u8>> {
    if height == 0 || width == 0 || out_height == 0 || out_width == 0 {
        input_bail!("resize_rgb8: cannot resize {height}x{width} to {out_height}x{out_width}");
    }
    if rgb.len() != height * width * 3 {
        input_bail!(
            "resize_rgb8: buffer holds {} bytes but a {height}x{width} RGB image needs {}",
            rgb.len(),
            height * width * 3
        );
    }
    if out_height.saturating_mul(out_width) > MAX_OUTPUT_PIXELS {
        input_bail!(
            "resize_rgb8: {out_height}x{out_width} exceeds the limit of {MAX_OUTPUT_PIXELS} pixels"
        );
    }
    let mut cur = rgb.to_vec();
    let (mut h, mut w) = (height, width);
    // Pillow runs the vertical pass first exactly when it shrinks while the horizontal one grows
    // (found by testing all four cases against Pillow 13; each pass rounds to u8, so it matters)
    let vertical_first = out_height < height && out_width > width;
    if vertical_first && out_height != height {
        cur = resample_vertical(&cur, w, h, out_height, filter);
        h = out_height;
    }
    if out_width != w {
        cur = resample_horizontal(&cur, h, w, out_width, filter);
        w = out_width;
    }
    if out_height != h {
        cur = resample_vertical(&cur, w, h, out_height, filter);
    }
    Ok(cur)
}

/// One horizontal pass over `height` rows of `width` RGB pixels.
fn resample_horizontal(
    rgb: &[u8],
    height: usize,
    width: usize,
    out_width: usize,
    filter: Resample,
) -> Vec<u8> {
    let round = 1i64 << (PRECISION_BITS - 1);
    let coeffs = coefficients(width, out_width, filter);
    let mut out = vec![0u8; height * out_width * 3];
    for y in 0..height {
        let row = &rgb[y * width * 3..(y + 1) * width * 3];
        for (xx, (xmin, k)) in coeffs.iter().enumerate() {
            for c in 0..3 {
                let mut ss = round;
                for (i, &kv) in k.iter().enumerate() {
                    ss += row[(xmin + i) * 3 + c] as i64 * kv as i64;
                }
                out[(y * out_width + xx) * 3 + c] = clip8(ss);
            }
        }
    }
    out
}

/// One vertical pass over `height` rows of `width` RGB pixels.
fn resample_vertical(
    rgb: &[u8],
    width: usize,
    height: usize,
    out_height: usize,
    filter: Resample,
) -> Vec<u8> {
    let round = 1i64 << (PRECISION_BITS - 1);
    let coeffs = coefficients(height, out_height, filter);
    let stride = width * 3;
    let mut out = vec![0u8; out_height * stride];
    let mut acc = vec![0i64; stride];
    for (yy, (ymin, k)) in coeffs.iter().enumerate() {
        acc.fill(round);
        for (i, &kv) in k.iter().enumerate() {
            let row = &rgb[(ymin + i) * stride..(ymin + i + 1) * stride];
            for (a, &p) in acc.iter_mut().zip(row) {
                *a += p as i64 * kv as i64;
            }
        }
        for (o, &a) in out[yy * stride..(yy + 1) * stride].iter_mut().zip(&acc) {
            *o = clip8(a);
        }
    }
    out
}

/// How a processor chooses the network's input size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case", tag = "rule")]
pub enum ResizeRule {
    /// Keep the image's size.
    Keep,
    /// Exactly this size, aspect ratio not kept (`SegformerImageProcessor`'s `size`).
    Exact {
        /// Output height.
        height: usize,
        /// Output width.
        width: usize,
    },
    /// `DPTImageProcessor` with `keep_aspect_ratio` and `ensure_multiple_of`: one scale for both
    /// sides, the one closer to 1 of the two scales to the target, then each side rounded to the
    /// nearest multiple (ties to even) ([`depth_anything_resize_size`]).
    KeepAspectMultiple {
        /// Target height.
        height: usize,
        /// Target width.
        width: usize,
        /// The sides become multiples of this.
        multiple: usize,
    },
    /// The nearest size whose sides are multiples of `multiple` (unchanged when they already are;
    /// [`size_for_multiple`]): what a bundle does to fit its image to a patch encoder.
    NearestMultiple {
        /// The sides become multiples of this.
        multiple: usize,
    },
}

/// A reference image processor: resize rule, Pillow resampling filter, normalisation.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImageProcessor {
    /// The input size rule.
    pub resize: ResizeRule,
    /// The resampling filter.
    pub resample: Resample,
    /// Mean / std normalisation after rescaling to `[0, 1]`.
    pub normalization: Normalization,
}

impl ImageProcessor {
    /// `SegformerImageProcessor` of the `nvidia/segformer-*` checkpoints: bilinear resize to
    /// exactly `height x width` (512 x 512 for the ADE20k ones, 1024 x 1024 for Cityscapes),
    /// ImageNet mean/std.
    pub fn segformer(height: usize, width: usize) -> Self {
        Self {
            resize: ResizeRule::Exact { height, width },
            resample: Resample::Bilinear,
            normalization: Normalization::IMAGENET,
        }
    }

    /// `DPTImageProcessor` as the `depth-anything/Depth-Anything-V2-*-hf` checkpoints configure
    /// it: target 518 x 518, aspect kept, multiples of 14, bicubic, ImageNet mean/std.
    pub fn depth_anything_v2() -> Self {
        Self {
            resize: ResizeRule::KeepAspectMultiple {
                height: 518,
                width: 518,
                multiple: 14,
            },
            resample: Resample::Bicubic,
            normalization: Normalization::IMAGENET,
        }
    }

    /// The input size for a `height x width` image.
    ///
    /// # Errors
    /// When the rule gives a zero side (an image far smaller than the target) or more than
    /// [`MAX_OUTPUT_PIXELS`].
    pub fn output_size(&self, height: usize, width: usize) -> crate::Result<(usize, usize)> {
        if height == 0 || width == 0 {
            input_bail!("ImageProcessor: image size {height}x{width} has a zero dimension");
        }
        let (h, w) = match self.resize {
            ResizeRule::Keep => (height, width),
            ResizeRule::Exact { height, width } => (height, width),
            ResizeRule::KeepAspectMultiple {
                height: th,
                width: tw,
                multiple,
            } => depth_anything_resize_size(height, width, (th, tw), multiple, true),
            ResizeRule::NearestMultiple { multiple } => {
                let m = multiple.max(1);
                if height.is_multiple_of(m) && width.is_multiple_of(m) {
                    (height, width)
                } else {
                    size_for_multiple(height, width, m)
                }
            }
        };
        if h == 0 || w == 0 {
            input_bail!(
                "ImageProcessor: a {height}x{width} image is too small for {:?} (gives {h}x{w})",
                self.resize
            );
        }
        if h.saturating_mul(w) > MAX_OUTPUT_PIXELS {
            input_bail!("ImageProcessor: {h}x{w} exceeds the limit of {MAX_OUTPUT_PIXELS} pixels");
        }
        Ok((h, w))
    }

    /// The resized `u8` image and its size.
    pub fn resize_rgb8(
        &self,
        rgb: &[u8],
        height: usize,
        width: usize,
    ) -> crate::Result<(Vec<u8>, usize, usize)> {
        let (h, w) = self.output_size(height, width)?;
        if (h, w) == (height, width) {
            if rgb.len() != height * width * 3 {
                input_bail!(
                    "ImageProcessor: buffer holds {} bytes but a {height}x{width} RGB image needs {}",
                    rgb.len(),
                    height * width * 3
                );
            }
            return Ok((rgb.to_vec(), h, w));
        }
        Ok((
            resize_rgb8(rgb, (height, width), (h, w), self.resample)?,
            h,
            w,
        ))
    }

    /// The network input `[1, 3, H', W']`: resized, rescaled to `[0, 1]` and normalised, as the
    /// reference processor's `pixel_values`.
    pub fn preprocess(
        &self,
        rgb: &[u8],
        height: usize,
        width: usize,
        device: &Device,
    ) -> crate::Result<Tensor> {
        let (bytes, h, w) = self.resize_rgb8(rgb, height, width)?;
        rgb8_to_tensor(&bytes, h, w, &self.normalization, device)
    }
}
