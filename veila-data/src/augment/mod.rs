//! Camera image augmentation and degradation: deterministic, seeded operations on 8-bit sRGB images,
//! used by training (augmentation) and by the simulator's camera (sensor randomisation).
//!
//! # Photometric operations
//!
//! The physical ones act on linear light ([`LinearRgb`], decoded with the exact IEC 61966-2-1 transfer
//! functions [`srgb_to_linear`] / [`linear_to_srgb`]); each also exists as a pure function on an
//! [`image::RgbImage`] that decodes, operates and encodes:
//!
//! | operation | formula (linear light `x`) |
//! |---|---|
//! | [`exposure`] | `x' = g x` |
//! | [`vignetting`] | `x' = (1 - k r^2) x`, `r` = distance from the image centre / half-diagonal |
//! | [`gaussian_blur`] | separable sampled Gaussian, radius `ceil(4 sigma)`, normalised, clamp-to-edge |
//! | [`white_balance`] | `x'_c = g_c x_c` |
//! | [`sensor_noise`] | `x' = a n + e`, `n ~ Poisson(x / a)`, `e ~ N(0, sigma_read^2)` ([`SensorNoise`]) |
//!
//! The perceptual ones act on sRGB-encoded values `v` in `[0, 1]` (colour jitter as in the usual
//! training pipelines) or on the bytes:
//!
//! | operation | formula (encoded `v`) |
//! |---|---|
//! | [`contrast`] | `v' = 0.5 + c (v - 0.5)` |
//! | [`saturation`] | `v' = Y' + s (v - Y')`, `Y' = 0.2126 R' + 0.7152 G' + 0.0722 B'` |
//! | [`hue_rotation`] | rotation by `t` about the grey axis `(1, 1, 1) / sqrt(3)` |
//! | [`jpeg_round_trip`] | encode / decode with the `image` crate's JPEG codec at quality 1 to 100 |
//!
//! # The pipeline
//!
//! [`Photometric`] holds ranges and probabilities (serde, for TOML configs); [`Photometric::draw`]
//! turns it and a seed into concrete [`PhotometricParams`], which [`PhotometricParams::apply`] runs in
//! the physical order of a camera:
//!
//! 1. scene radiance (the input decoded to linear light, or [`PhotometricParams::apply_linear`]'s input)
//! 2. exposure
//! 3. vignetting (the lens)
//! 4. blur (the optics)
//! 5. white balance
//! 6. sensor noise
//! 7. sRGB encoding to 8 bits
//! 8. colour jitter: contrast, then saturation, then hue
//! 9. JPEG compression
//!
//! Operations that are off are skipped, so [`Photometric::identity`] returns the input bytes exactly.
//!
//! # Geometry
//!
//! [`CropZoom`] crops a window of `1 / s` of the image and resamples it to the original size (bilinear
//! for RGB, nearest for label and depth maps), with the [`veila_geom::PinholeCamera`] updated
//! ([`CropZoom::camera`]); [`crop_zoom`] does all at once and [`CropZoomRange`] draws a random one.
//!
//! # Determinism
//!
//! Every draw uses `ChaCha8Rng::seed_from_u64(seed)`; sensor noise uses one ChaCha8 stream per image row,
//! so the bytes depend on the seed only, not on the number of threads.
//!
//! # Example
//!
//! ```
//! use veila_data::augment::{crop_zoom, CropZoom, Photometric};
//! use veila_data::image::{Rgb, RgbImage};
//! use veila_geom::PinholeCamera;
//!
//! let img = RgbImage::from_fn(64, 48, |x, y| Rgb([(4 * x) as u8, (5 * y) as u8, 128]));
//!
//! // "off" is an exact identity; the default draws a moderate random degradation, same seed same bytes
//! assert_eq!(Photometric::identity().augment(&img, 7)?, img);
//! let cfg = Photometric::default();
//! let a = cfg.augment(&img, 7)?;
//! assert_eq!(a, cfg.augment(&img, 7)?);
//! assert_eq!(a.dimensions(), img.dimensions());
//!
//! // zoom by 1.25 about a window 4 px from the left and 2 px from the top; the camera follows
//! let k = [[50.0, 0.0, 31.5, 0.0], [0.0, 50.0, 23.5, 0.0], [0.0, 0.0, 1.0, 0.0]];
//! let cam = PinholeCamera::new(k, glam::Mat4::IDENTITY, 64, 48)?;
//! let crop = CropZoom::new(64, 48, 1.25, [4.0, 2.0])?;
//! let out = crop_zoom(&img, &cam, None, None, &crop)?;
//! assert_eq!(out.camera.intrinsics.x_axis.x, 50.0 * 1.25);
//! # Ok::<(), veila_data::Error>(())
//! ```

mod geometric;
mod photometric;

use std::borrow::Cow;

use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

pub use geometric::{CropZoom, CropZoomRange, CropZoomed, crop_zoom};
pub use photometric::{
    LinearRgb, SensorNoise, contrast, exposure, gaussian_blur, hue_rotation, jpeg_round_trip,
    linear_to_srgb, linear_to_srgb_u8, rgb_image_from_raw, saturation, sensor_noise,
    srgb_to_linear, srgb_u8_to_linear, vignetting, white_balance,
};
use photometric::{invalid, uniform};

use crate::Result;

/// Ranges and probabilities of the photometric augmentation (serde; unknown keys are an error, missing
/// keys take the [`Default`]).
///
/// Each operation is applied with its probability `*_p`; its parameter is then drawn uniformly from its
/// range (exposure and white balance in stops, i.e. `log2` of the gain).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Photometric {
    /// Probability of an exposure change.
    pub exposure_p: f32,
    /// Exposure change in stops: gain `2^e`, `e` uniform in this range.
    pub exposure_stops: [f32; 2],
    /// Probability of vignetting.
    pub vignetting_p: f32,
    /// Vignetting strength `k` (corner falloff `1 - k`), within `[0, 1]`.
    pub vignetting_strength: [f32; 2],
    /// Probability of a blur.
    pub blur_p: f32,
    /// Blur standard deviation, pixels, `>= 0`.
    pub blur_sigma_px: [f32; 2],
    /// Probability of a white-balance change.
    pub white_balance_p: f32,
    /// Largest white-balance change in stops: red and blue gains `2^e`, each `e` uniform in
    /// `[-w, w]`, green gain 1.
    pub white_balance_stops: f32,
    /// Probability of sensor noise.
    pub noise_p: f32,
    /// Shot-noise gain range, linear units per photo-electron (see [`SensorNoise`]).
    pub noise_shot_gain: [f32; 2],
    /// Read-noise standard deviation range, linear units.
    pub noise_read_sigma: [f32; 2],
    /// Probability of a contrast change.
    pub contrast_p: f32,
    /// Contrast factor range (`>= 0`; 1 = unchanged).
    pub contrast: [f32; 2],
    /// Probability of a saturation change.
    pub saturation_p: f32,
    /// Saturation factor range (`>= 0`; 1 = unchanged).
    pub saturation: [f32; 2],
    /// Probability of a hue rotation.
    pub hue_p: f32,
    /// Hue rotation range, degrees.
    pub hue_deg: [f32; 2],
    /// Probability of JPEG compression.
    pub jpeg_p: f32,
    /// JPEG quality range, within `1..=100`.
    pub jpeg_quality: [u8; 2],
}

impl Default for Photometric {
    /// A moderate augmentation: each operation on a share of the images, with mild parameters.
    fn default() -> Self {
        Photometric {
            exposure_p: 0.5,
            exposure_stops: [-0.5, 0.5],
            vignetting_p: 0.3,
            vignetting_strength: [0.0, 0.4],
            blur_p: 0.3,
            blur_sigma_px: [0.3, 1.2],
            white_balance_p: 0.5,
            white_balance_stops: 0.2,
            noise_p: 0.5,
            noise_shot_gain: [1e-4, 1e-3],
            noise_read_sigma: [0.002, 0.01],
            contrast_p: 0.5,
            contrast: [0.8, 1.2],
            saturation_p: 0.5,
            saturation: [0.7, 1.3],
            hue_p: 0.3,
            hue_deg: [-10.0, 10.0],
            jpeg_p: 0.3,
            jpeg_quality: [40, 95],
        }
    }
}

fn check_p(what: &str, p: f32) -> Result<()> {
    if (0.0..=1.0).contains(&p) {
        Ok(())
    } else {
        Err(invalid(what, format!("probability {p} not in [0, 1]")))
    }
}

fn check_range(what: &str, [lo, hi]: [f32; 2], min: f32, max: f32) -> Result<()> {
    if lo.is_finite() && hi.is_finite() && min <= lo && lo <= hi && hi <= max {
        Ok(())
    } else {
        Err(invalid(
            what,
            format!("range [{lo}, {hi}] must be finite, ordered and within [{min}, {max}]"),
        ))
    }
}

impl Photometric {
    /// Every operation off: [`Photometric::augment`] returns its input unchanged.
    pub fn identity() -> Self {
        Photometric {
            exposure_p: 0.0,
            exposure_stops: [0.0, 0.0],
            vignetting_p: 0.0,
            vignetting_strength: [0.0, 0.0],
            blur_p: 0.0,
            blur_sigma_px: [0.0, 0.0],
            white_balance_p: 0.0,
            white_balance_stops: 0.0,
            noise_p: 0.0,
            noise_shot_gain: [0.0, 0.0],
            noise_read_sigma: [0.0, 0.0],
            contrast_p: 0.0,
            contrast: [1.0, 1.0],
            saturation_p: 0.0,
            saturation: [1.0, 1.0],
            hue_p: 0.0,
            hue_deg: [0.0, 0.0],
            jpeg_p: 0.0,
            jpeg_quality: [100, 100],
        }
    }

    /// Check every probability and range.
    pub fn validate(&self) -> Result<()> {
        for (what, p) in [
            ("exposure_p", self.exposure_p),
            ("vignetting_p", self.vignetting_p),
            ("blur_p", self.blur_p),
            ("white_balance_p", self.white_balance_p),
            ("noise_p", self.noise_p),
            ("contrast_p", self.contrast_p),
            ("saturation_p", self.saturation_p),
            ("hue_p", self.hue_p),
            ("jpeg_p", self.jpeg_p),
        ] {
            check_p(what, p)?;
        }
        check_range("exposure_stops", self.exposure_stops, -16.0, 16.0)?;
        check_range("vignetting_strength", self.vignetting_strength, 0.0, 1.0)?;
        check_range("blur_sigma_px", self.blur_sigma_px, 0.0, 1024.0)?;
        let w = self.white_balance_stops;
        check_range("white_balance_stops", [0.0, w], 0.0, 16.0)?;
        check_range("noise_shot_gain", self.noise_shot_gain, 0.0, 1.0)?;
        check_range("noise_read_sigma", self.noise_read_sigma, 0.0, 1.0)?;
        check_range("contrast", self.contrast, 0.0, f32::MAX)?;
        check_range("saturation", self.saturation, 0.0, f32::MAX)?;
        check_range("hue_deg", self.hue_deg, -360.0, 360.0)?;
        let [qlo, qhi] = self.jpeg_quality;
        if !(1 <= qlo && qlo <= qhi && qhi <= 100) {
            return Err(invalid(
                "jpeg_quality",
                format!("range [{qlo}, {qhi}] must be ordered and within [1, 100]"),
            ));
        }
        Ok(())
    }

    /// Draw concrete parameters from `ChaCha8Rng::seed_from_u64(seed)`.
    ///
    /// The stream is consumed the same way whatever the probabilities (per operation in pipeline order:
    /// one coin, then its parameters; then the noise seed), so changing one range does not reshuffle the
    /// others.
    pub fn draw(&self, seed: u64) -> Result<PhotometricParams> {
        self.validate()?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let coin = |p: f32, rng: &mut ChaCha8Rng| rng.random::<f32>() < p;
        let mut out = PhotometricParams::identity();

        let on = coin(self.exposure_p, &mut rng);
        let e = uniform(&mut rng, self.exposure_stops);
        if on {
            out.exposure_gain = e.exp2();
        }
        let on = coin(self.vignetting_p, &mut rng);
        let k = uniform(&mut rng, self.vignetting_strength);
        if on {
            out.vignetting_strength = k;
        }
        let on = coin(self.blur_p, &mut rng);
        let s = uniform(&mut rng, self.blur_sigma_px);
        if on {
            out.blur_sigma_px = s;
        }
        let on = coin(self.white_balance_p, &mut rng);
        let w = self.white_balance_stops;
        let r = uniform(&mut rng, [-w, w]);
        let b = uniform(&mut rng, [-w, w]);
        if on {
            out.white_balance_gains = [r.exp2(), 1.0, b.exp2()];
        }
        let on = coin(self.noise_p, &mut rng);
        let shot = uniform(&mut rng, self.noise_shot_gain);
        let read = uniform(&mut rng, self.noise_read_sigma);
        if on {
            out.noise = SensorNoise {
                shot_gain: shot,
                read_sigma: read,
            };
        }
        let on = coin(self.contrast_p, &mut rng);
        let c = uniform(&mut rng, self.contrast);
        if on {
            out.contrast = c;
        }
        let on = coin(self.saturation_p, &mut rng);
        let s = uniform(&mut rng, self.saturation);
        if on {
            out.saturation = s;
        }
        let on = coin(self.hue_p, &mut rng);
        let h = uniform(&mut rng, self.hue_deg);
        if on {
            out.hue_deg = h;
        }
        let on = coin(self.jpeg_p, &mut rng);
        let [qlo, qhi] = self.jpeg_quality;
        let q = rng.random_range(qlo..=qhi);
        if on {
            out.jpeg_quality = Some(q);
        }
        out.noise_seed = rng.random();
        Ok(out)
    }

    /// [`Photometric::draw`] then [`PhotometricParams::apply`].
    pub fn augment(&self, img: &RgbImage, seed: u64) -> Result<RgbImage> {
        self.draw(seed)?.apply(img)
    }
}

/// Concrete photometric parameters (one draw of [`Photometric`]); [`PhotometricParams::identity`] is
/// all off.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhotometricParams {
    /// Exposure gain (1 = off).
    pub exposure_gain: f32,
    /// Vignetting strength (0 = off).
    pub vignetting_strength: f32,
    /// Blur sigma, pixels (0 = off).
    pub blur_sigma_px: f32,
    /// White-balance gains, R, G, B (all 1 = off).
    pub white_balance_gains: [f32; 3],
    /// Sensor noise ([`SensorNoise::OFF`] = off).
    pub noise: SensorNoise,
    /// Seed of the per-pixel noise streams.
    pub noise_seed: u64,
    /// Contrast factor (1 = off).
    pub contrast: f32,
    /// Saturation factor (1 = off).
    pub saturation: f32,
    /// Hue rotation, degrees (0 = off).
    pub hue_deg: f32,
    /// JPEG quality (`None` = off).
    pub jpeg_quality: Option<u8>,
}

impl Default for PhotometricParams {
    fn default() -> Self {
        Self::identity()
    }
}

impl PhotometricParams {
    /// Every operation off.
    pub fn identity() -> Self {
        PhotometricParams {
            exposure_gain: 1.0,
            vignetting_strength: 0.0,
            blur_sigma_px: 0.0,
            white_balance_gains: [1.0; 3],
            noise: SensorNoise::OFF,
            noise_seed: 0,
            contrast: 1.0,
            saturation: 1.0,
            hue_deg: 0.0,
            jpeg_quality: None,
        }
    }

    fn linear_is_off(&self) -> bool {
        self.exposure_gain == 1.0
            && self.vignetting_strength == 0.0
            && self.blur_sigma_px == 0.0
            && self.white_balance_gains == [1.0; 3]
            && self.noise.is_off()
    }

    /// Run the pipeline (module docs) on an 8-bit sRGB image. Operations that are off are skipped; with
    /// every one off the output equals the input.
    pub fn apply(&self, img: &RgbImage) -> Result<RgbImage> {
        let encoded = if self.linear_is_off() {
            // still refuse what the linear stage would refuse
            photometric::check_rgb(img)?;
            img.clone()
        } else {
            self.linear_stage(&LinearRgb::from_srgb(img)?)?.to_srgb()
        };
        self.encoded_stage(encoded)
    }

    /// Run the pipeline on scene radiance already in linear light (for a renderer's output).
    pub fn apply_linear(&self, radiance: &LinearRgb) -> Result<RgbImage> {
        self.encoded_stage(self.linear_stage(radiance)?.to_srgb())
    }

    fn linear_stage(&self, img: &LinearRgb) -> Result<LinearRgb> {
        let mut x = Cow::Borrowed(img);
        if self.exposure_gain != 1.0 {
            x = Cow::Owned(x.exposure(self.exposure_gain)?);
        }
        if self.vignetting_strength != 0.0 {
            x = Cow::Owned(x.vignetting(self.vignetting_strength)?);
        }
        if self.blur_sigma_px != 0.0 {
            x = Cow::Owned(x.gaussian_blur(self.blur_sigma_px)?);
        }
        if self.white_balance_gains != [1.0; 3] {
            x = Cow::Owned(x.white_balance(self.white_balance_gains)?);
        }
        if !self.noise.is_off() {
            x = Cow::Owned(x.sensor_noise(&self.noise, self.noise_seed)?);
        }
        Ok(x.into_owned())
    }

    fn encoded_stage(&self, mut img: RgbImage) -> Result<RgbImage> {
        if self.contrast != 1.0 {
            img = contrast(&img, self.contrast)?;
        }
        if self.saturation != 1.0 {
            img = saturation(&img, self.saturation)?;
        }
        if self.hue_deg != 0.0 {
            img = hue_rotation(&img, self.hue_deg)?;
        }
        if let Some(q) = self.jpeg_quality {
            img = jpeg_round_trip(&img, q)?;
        }
        Ok(img)
    }
}
