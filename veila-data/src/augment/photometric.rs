//! The photometric operations: sRGB transfer functions, the linear-light image, the physical ops
//! (exposure, white balance, vignetting, blur, sensor noise) and the perceptual ones (contrast,
//! saturation, hue, JPEG).

use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, Poisson, StandardNormal};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{Error, Result};

pub(super) fn invalid(what: &str, message: impl Into<String>) -> Error {
    Error::Invalid {
        what: what.into(),
        message: message.into(),
    }
}

/// The sRGB decoding function of IEC 61966-2-1: encoded `v` in `[0, 1]` to linear light.
///
/// `v / 12.92` for `v <= 0.04045`, else `((v + 0.055) / 1.055)^2.4`. Inputs outside `[0, 1]` follow the
/// same formulas (the linear segment for negatives).
pub fn srgb_to_linear(v: f32) -> f32 {
    crate::srgb::srgb_to_linear(v)
}

/// The sRGB encoding function of IEC 61966-2-1: linear light `l` in `[0, 1]` to encoded.
///
/// `12.92 l` for `l <= 0.0031308`, else `1.055 l^(1/2.4) - 0.055`; the inverse of [`srgb_to_linear`].
pub fn linear_to_srgb(l: f32) -> f32 {
    crate::srgb::linear_to_srgb(l)
}

/// Linear light of an 8-bit sRGB value (`srgb_to_linear(v / 255)`, from a table).
pub fn srgb_u8_to_linear(v: u8) -> f32 {
    decode_table()[usize::from(v)]
}

/// The 8-bit sRGB value of linear light `l`: clamped to `[0, 1]`, encoded, scaled by 255 and rounded to
/// nearest. NaN maps to 0. `linear_to_srgb_u8(srgb_u8_to_linear(v)) == v` for every `v`.
pub fn linear_to_srgb_u8(l: f32) -> u8 {
    crate::srgb::linear_to_srgb_u8(l)
}

fn decode_table() -> &'static [f32; 256] {
    static TABLE: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let mut t = [0.0f32; 256];
        for (i, v) in t.iter_mut().enumerate() {
            // f64 for the table: the closest f32 to the exact value
            let e = i as f64 / 255.0;
            *v = if e <= 0.040_45 {
                (e / 12.92) as f32
            } else {
                ((e + 0.055) / 1.055).powf(2.4) as f32
            };
        }
        t
    })
}

/// An 8-bit sRGB image from a raw buffer (row-major, 3 bytes per pixel); an error unless the buffer
/// holds exactly `width * height * 3` bytes and the image is not empty.
pub fn rgb_image_from_raw(width: u32, height: u32, rgb: Vec<u8>) -> Result<RgbImage> {
    check_size(width, height, rgb.len(), "RGB image")?;
    let len = rgb.len();
    RgbImage::from_raw(width, height, rgb).ok_or_else(|| Error::Mismatch {
        context: "RGB image".into(),
        message: format!("{len} bytes for a {width}x{height} image"),
    })
}

fn check_size(width: u32, height: u32, len: usize, context: &str) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(invalid(
            &format!("{context} size"),
            format!("{width}x{height}: the image is empty"),
        ));
    }
    let want = (width as usize)
        .checked_mul(height as usize)
        .and_then(|n| n.checked_mul(3));
    if want != Some(len) {
        return Err(Error::Mismatch {
            context: context.into(),
            message: format!("{len} values for a {width}x{height} RGB image"),
        });
    }
    Ok(())
}

pub(super) fn check_rgb(img: &RgbImage) -> Result<()> {
    check_size(img.width(), img.height(), img.as_raw().len(), "RGB image")
}

fn check_finite(what: &str, v: f32) -> Result<()> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(invalid(what, format!("{v} is not finite")))
    }
}

fn check_non_negative(what: &str, v: f32) -> Result<()> {
    check_finite(what, v)?;
    if v < 0.0 {
        return Err(invalid(what, format!("{v} is negative")));
    }
    Ok(())
}

/// An RGB image in linear light (scene-referred: values may exceed 1 before encoding), `f32`, row-major,
/// 3 values per pixel. The physical operations work on this type without re-quantising in between.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearRgb {
    width: u32,
    height: u32,
    data: Vec<f32>,
}

impl LinearRgb {
    /// An image from its values; an error unless `data` holds `width * height * 3` values, the image is
    /// not empty and every value is finite.
    pub fn new(width: u32, height: u32, data: Vec<f32>) -> Result<Self> {
        check_size(width, height, data.len(), "linear RGB image")?;
        if let Some(v) = data.iter().find(|v| !v.is_finite()) {
            return Err(invalid(
                "linear RGB image",
                format!("value {v} is not finite"),
            ));
        }
        Ok(LinearRgb {
            width,
            height,
            data,
        })
    }

    /// Decode an 8-bit sRGB image to linear light; an error for an empty image.
    pub fn from_srgb(img: &RgbImage) -> Result<Self> {
        check_rgb(img)?;
        let t = decode_table();
        Ok(LinearRgb {
            width: img.width(),
            height: img.height(),
            data: img.as_raw().iter().map(|&v| t[usize::from(v)]).collect(),
        })
    }

    /// Encode to 8-bit sRGB with [`linear_to_srgb_u8`] (clamps to `[0, 1]`).
    pub fn to_srgb(&self) -> RgbImage {
        let mut out = RgbImage::new(self.width, self.height);
        out.par_iter_mut()
            .zip(self.data.par_iter())
            .for_each(|(o, &l)| *o = linear_to_srgb_u8(l));
        out
    }

    /// Width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The values, row-major, 3 per pixel (R, G, B).
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// Exposure: every value times `gain` (`gain >= 0`, finite).
    pub fn exposure(&self, gain: f32) -> Result<Self> {
        check_non_negative("exposure gain", gain)?;
        self.white_balance([gain; 3])
    }

    /// White balance: channel `c` times `gains_rgb[c]` (each `>= 0`, finite).
    pub fn white_balance(&self, gains_rgb: [f32; 3]) -> Result<Self> {
        for g in gains_rgb {
            check_non_negative("white-balance gain", g)?;
        }
        let mut out = self.clone();
        for px in out.data.chunks_exact_mut(3) {
            for (v, g) in px.iter_mut().zip(gains_rgb) {
                *v *= g;
            }
        }
        Ok(out)
    }

    /// Vignetting: every pixel times `1 - strength * r^2`, where `r` is the distance of the pixel centre
    /// from the image centre `((W - 1) / 2, (H - 1) / 2)` divided by the half-diagonal
    /// `sqrt(W^2 + H^2) / 2` (so `r < 1` on every pixel). `strength` in `[0, 1]`.
    pub fn vignetting(&self, strength: f32) -> Result<Self> {
        check_non_negative("vignetting strength", strength)?;
        if strength > 1.0 {
            return Err(invalid(
                "vignetting strength",
                format!("{strength} is above 1"),
            ));
        }
        let mut out = self.clone();
        let w = self.width as usize;
        let (cx, cy) = (
            0.5 * (self.width as f32 - 1.0),
            0.5 * (self.height as f32 - 1.0),
        );
        let half_diag_sq = 0.25 * ((self.width as f32).powi(2) + (self.height as f32).powi(2));
        out.data
            .par_chunks_exact_mut(3 * w)
            .enumerate()
            .for_each(|(y, row)| {
                let dy = y as f32 - cy;
                for (x, px) in row.chunks_exact_mut(3).enumerate() {
                    let dx = x as f32 - cx;
                    let f = 1.0 - strength * (dx * dx + dy * dy) / half_diag_sq;
                    for v in px {
                        *v *= f;
                    }
                }
            });
        Ok(out)
    }

    /// Separable Gaussian blur with standard deviation `sigma_px` (pixels), borders clamped to the edge.
    ///
    /// The kernel is the sampled Gaussian `g(t) = exp(-t^2 / (2 sigma^2))` for integer
    /// `|t| <= ceil(4 sigma)`, divided by its sum; it runs along rows, then along columns. `sigma_px = 0`
    /// returns the image unchanged.
    pub fn gaussian_blur(&self, sigma_px: f32) -> Result<Self> {
        check_non_negative("blur sigma_px", sigma_px)?;
        if sigma_px == 0.0 {
            return Ok(self.clone());
        }
        let kernel = gaussian_kernel(sigma_px)?;
        let r = (kernel.len() / 2) as isize;
        let (w, h) = (self.width as usize, self.height as usize);
        let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
        let mut tmp = vec![0.0f32; self.data.len()];
        tmp.par_chunks_exact_mut(3 * w)
            .zip(self.data.par_chunks_exact(3 * w))
            .for_each(|(out, src)| {
                for x in 0..w {
                    let mut acc = [0.0f32; 3];
                    for (k, &kv) in kernel.iter().enumerate() {
                        let sx = clamp(x as isize + k as isize - r, w);
                        for c in 0..3 {
                            acc[c] += kv * src[3 * sx + c];
                        }
                    }
                    out[3 * x..3 * x + 3].copy_from_slice(&acc);
                }
            });
        let mut out = vec![0.0f32; self.data.len()];
        out.par_chunks_exact_mut(3 * w)
            .enumerate()
            .for_each(|(y, row)| {
                for (k, &kv) in kernel.iter().enumerate() {
                    let sy = clamp(y as isize + k as isize - r, h);
                    let src = &tmp[3 * w * sy..3 * w * (sy + 1)];
                    for (o, s) in row.iter_mut().zip(src) {
                        *o += kv * s;
                    }
                }
            });
        Ok(LinearRgb {
            width: self.width,
            height: self.height,
            data: out,
        })
    }

    /// Poisson-Gaussian sensor noise (see [`SensorNoise`]) from the seeded stream `seed`.
    ///
    /// Row `y` draws from `ChaCha8Rng::seed_from_u64(seed)` on stream `y`, pixel by pixel, R, G, B: the
    /// result depends on the seed only, never on the thread count. Negative values are kept (they clamp
    /// to 0 on encoding).
    pub fn sensor_noise(&self, noise: &SensorNoise, seed: u64) -> Result<Self> {
        noise.validate()?;
        if noise.is_off() {
            return Ok(self.clone());
        }
        let w = self.width as usize;
        let mut out = self.clone();
        let read = Normal::new(0.0f32, noise.read_sigma)
            .map_err(|e| invalid("read-noise sigma", e.to_string()))?;
        out.data
            .par_chunks_exact_mut(3 * w)
            .enumerate()
            .for_each(|(y, row)| {
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                rng.set_stream(y as u64);
                for v in row {
                    let shot = if noise.shot_gain > 0.0 {
                        shot_sample(&mut rng, *v, noise.shot_gain)
                    } else {
                        *v
                    };
                    *v = if noise.read_sigma > 0.0 {
                        shot + read.sample(&mut rng)
                    } else {
                        shot
                    };
                }
            });
        Ok(out)
    }
}

/// Photo-electrons `n ~ Poisson(max(x, 0) / gain)`, returned as `gain * n` (variance `gain * x`). Large
/// counts (`> 1e7`) use the normal approximation, which is exact to far below 8-bit precision there.
fn shot_sample(rng: &mut ChaCha8Rng, x: f32, gain: f32) -> f32 {
    let lambda = f64::from(x.max(0.0)) / f64::from(gain);
    if lambda <= 0.0 {
        return 0.0;
    }
    let n = if lambda > 1e7 {
        let z: f64 = StandardNormal.sample(rng);
        (lambda + lambda.sqrt() * z).max(0.0)
    } else {
        match Poisson::new(lambda) {
            Ok(p) => p.sample(rng),
            // unreachable for 0 < lambda <= 1e7; keep the mean rather than panic
            Err(_) => lambda,
        }
    };
    (f64::from(gain) * n) as f32
}

/// The normalised sampled Gaussian kernel of [`LinearRgb::gaussian_blur`] (length `2 ceil(4 sigma) + 1`).
fn gaussian_kernel(sigma_px: f32) -> Result<Vec<f32>> {
    let radius = (4.0 * f64::from(sigma_px)).ceil().max(1.0);
    if radius > 4096.0 {
        return Err(invalid(
            "blur sigma_px",
            format!("{sigma_px} is too large (at most 1024 pixels)"),
        ));
    }
    let r = radius as i64;
    let s2 = 2.0 * f64::from(sigma_px).powi(2);
    // the centre weight is 1 even when sigma^2 underflows
    let g: Vec<f64> = (-r..=r)
        .map(|t| {
            if t == 0 {
                1.0
            } else {
                (-(t * t) as f64 / s2).exp()
            }
        })
        .collect();
    let sum: f64 = g.iter().sum();
    Ok(g.iter().map(|v| (v / sum) as f32).collect())
}

/// Sensor noise in linear light: shot noise (Poisson photo-electron counts) plus Gaussian read noise.
///
/// A linear value `x` becomes `gain * n + e` with `n ~ Poisson(x / gain)` and `e ~ N(0, read_sigma^2)`:
/// mean `x`, variance `shot_gain * x + read_sigma^2`. `shot_gain = 0` turns shot noise off,
/// `read_sigma = 0` read noise.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorNoise {
    /// Linear units per photo-electron: the shot-noise variance per unit of signal (`>= 0`).
    pub shot_gain: f32,
    /// Standard deviation of the read noise, linear units (`>= 0`).
    pub read_sigma: f32,
}

impl SensorNoise {
    /// No noise.
    pub const OFF: SensorNoise = SensorNoise {
        shot_gain: 0.0,
        read_sigma: 0.0,
    };

    /// Both parameters finite, non-negative, and at most 1.
    pub fn validate(&self) -> Result<()> {
        check_non_negative("shot-noise gain", self.shot_gain)?;
        check_non_negative("read-noise sigma", self.read_sigma)?;
        if self.shot_gain > 1.0 || self.read_sigma > 1.0 {
            return Err(invalid(
                "sensor noise",
                format!(
                    "shot_gain {} and read_sigma {} must be at most 1",
                    self.shot_gain, self.read_sigma
                ),
            ));
        }
        Ok(())
    }

    /// Whether both parts are off.
    pub fn is_off(&self) -> bool {
        self.shot_gain == 0.0 && self.read_sigma == 0.0
    }
}

fn linear_op(img: &RgbImage, op: impl FnOnce(&LinearRgb) -> Result<LinearRgb>) -> Result<RgbImage> {
    Ok(op(&LinearRgb::from_srgb(img)?)?.to_srgb())
}

/// [`LinearRgb::exposure`] on an 8-bit sRGB image (decoded, multiplied, encoded).
pub fn exposure(img: &RgbImage, gain: f32) -> Result<RgbImage> {
    linear_op(img, |l| l.exposure(gain))
}

/// [`LinearRgb::white_balance`] on an 8-bit sRGB image.
pub fn white_balance(img: &RgbImage, gains_rgb: [f32; 3]) -> Result<RgbImage> {
    linear_op(img, |l| l.white_balance(gains_rgb))
}

/// [`LinearRgb::vignetting`] on an 8-bit sRGB image.
pub fn vignetting(img: &RgbImage, strength: f32) -> Result<RgbImage> {
    linear_op(img, |l| l.vignetting(strength))
}

/// [`LinearRgb::gaussian_blur`] on an 8-bit sRGB image (blurred in linear light).
pub fn gaussian_blur(img: &RgbImage, sigma_px: f32) -> Result<RgbImage> {
    linear_op(img, |l| l.gaussian_blur(sigma_px))
}

/// [`LinearRgb::sensor_noise`] on an 8-bit sRGB image.
pub fn sensor_noise(img: &RgbImage, noise: &SensorNoise, seed: u64) -> Result<RgbImage> {
    linear_op(img, |l| l.sensor_noise(noise, seed))
}

/// Apply `f` to every pixel as `[0, 1]` sRGB-encoded values and quantise back (round to nearest).
fn encoded_op(img: &RgbImage, f: impl Fn([f32; 3]) -> [f32; 3] + Sync) -> Result<RgbImage> {
    check_rgb(img)?;
    let mut out = img.clone();
    let w = img.width() as usize;
    let q = |v: f32| (v * 255.0).round().clamp(0.0, 255.0) as u8;
    out.par_chunks_exact_mut(3 * w).for_each(|row| {
        for px in row.chunks_exact_mut(3) {
            let v = f([
                f32::from(px[0]) / 255.0,
                f32::from(px[1]) / 255.0,
                f32::from(px[2]) / 255.0,
            ]);
            px.copy_from_slice(&v.map(q));
        }
    });
    Ok(out)
}

/// Contrast about mid-grey on sRGB-encoded values: `v' = 0.5 + factor (v - 0.5)`, clamped to `[0, 1]`.
/// `factor = 1` is the identity, `0` a flat grey; `factor >= 0`, finite.
pub fn contrast(img: &RgbImage, factor: f32) -> Result<RgbImage> {
    check_non_negative("contrast factor", factor)?;
    encoded_op(img, |p| p.map(|v| 0.5 + factor * (v - 0.5)))
}

/// Rec. 709 luma weights, applied to sRGB-encoded values (`Y'`).
const LUMA: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// Saturation on sRGB-encoded values: `v' = Y' + factor (v - Y')` with the luma
/// `Y' = 0.2126 R' + 0.7152 G' + 0.0722 B'`. `factor = 1` is the identity, `0` gives grey pixels
/// (`R' = G' = B' = Y'`); `factor >= 0`, finite.
pub fn saturation(img: &RgbImage, factor: f32) -> Result<RgbImage> {
    check_non_negative("saturation factor", factor)?;
    encoded_op(img, |p| {
        let y = LUMA[0] * p[0] + LUMA[1] * p[1] + LUMA[2] * p[2];
        p.map(|v| y + factor * (v - y))
    })
}

/// Hue rotation on sRGB-encoded values: the colour vector turns by `degrees` about the grey axis
/// `(1, 1, 1) / sqrt(3)` (Rodrigues' formula, `M = cos t I + (1 - cos t) a a^T + sin t [a]_x`), which
/// keeps `R' + G' + B'` and the distance from grey. `0` is the identity; `120` maps `(R', G', B')` to
/// `(B', R', G')`. Finite.
pub fn hue_rotation(img: &RgbImage, degrees: f32) -> Result<RgbImage> {
    check_finite("hue rotation", degrees)?;
    let m = hue_matrix(degrees);
    encoded_op(img, |p| {
        [0, 1, 2].map(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2])
    })
}

fn hue_matrix(degrees: f32) -> [[f32; 3]; 3] {
    let t = f64::from(degrees).to_radians();
    let (s, c) = t.sin_cos();
    let a = (1.0 - c) / 3.0;
    let b = s / 3f64.sqrt();
    let m = [
        [c + a, a - b, a + b],
        [a + b, c + a, a - b],
        [a - b, a + b, c + a],
    ];
    m.map(|r| r.map(|v| v as f32))
}

/// JPEG artefacts: encode with the `image` crate's baseline JPEG encoder at `quality` (1 to 100) and decode
/// again. Same size; an error for a quality outside `1..=100` or an image wider or taller than 65535.
pub fn jpeg_round_trip(img: &RgbImage, quality: u8) -> Result<RgbImage> {
    check_rgb(img)?;
    if !(1..=100).contains(&quality) {
        return Err(invalid("JPEG quality", format!("{quality} not in 1..=100")));
    }
    if img.width() > 65535 || img.height() > 65535 {
        return Err(invalid(
            "JPEG image size",
            format!("{}x{} exceeds 65535", img.width(), img.height()),
        ));
    }
    let mut buf = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut buf, quality)
        .encode(
            img.as_raw(),
            img.width(),
            img.height(),
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| invalid("JPEG encoding", e.to_string()))?;
    let back = image::load_from_memory_with_format(&buf, image::ImageFormat::Jpeg)
        .map_err(|e| invalid("JPEG decoding", e.to_string()))?
        .into_rgb8();
    if back.dimensions() != img.dimensions() {
        return Err(Error::Mismatch {
            context: "JPEG round trip".into(),
            message: format!(
                "{:?} came back as {:?}",
                img.dimensions(),
                back.dimensions()
            ),
        });
    }
    Ok(back)
}

/// A uniform draw in `[lo, hi]` (exactly `lo` when the range is a point).
pub(super) fn uniform(rng: &mut ChaCha8Rng, [lo, hi]: [f32; 2]) -> f32 {
    let u: f32 = rng.random();
    if hi > lo {
        (lo + (hi - lo) * u).min(hi)
    } else {
        lo
    }
}
