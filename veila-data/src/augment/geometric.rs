//! Random crop-and-zoom with the camera intrinsics updated.

use glam::Mat4;
use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use veila_geom::PinholeCamera;

use super::photometric::{invalid, uniform};
use crate::{Error, Result};

/// Slack, in pixels, allowed on the crop window's bounds (float rounding of drawn offsets).
const BOUND_SLACK_PX: f32 = 1e-3;

/// A crop-and-zoom of a `width x height` image: the window of `width / scale x height / scale` pixels
/// whose top-left corner lies `offset_px` pixels from the image's top-left corner, resampled back to
/// `width x height`.
///
/// In the pixel-centre convention of [`PinholeCamera`] (pixel `i` centred at `u = i`, covering
/// `[i - 0.5, i + 0.5]`), the new image coordinate of an old one is
///
/// `u' = s (u + 0.5 - x0) - 0.5`, `v' = s (v + 0.5 - y0) - 0.5`
///
/// with `s = scale` and `(x0, y0) = offset_px`; output pixel `(i', j')` samples the input at
/// `u = (i' + 0.5) / s + x0 - 0.5`. `scale = 1` with offset `(0, 0)` is the identity.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CropZoom {
    /// Width of the input and output images, pixels.
    pub width: u32,
    /// Height of the input and output images, pixels.
    pub height: u32,
    /// Zoom factor `s >= 1` (the window is `1 / s` of the image per axis).
    pub scale: f32,
    /// The window's top-left corner `(x0, y0)`, pixels from the image's top-left corner:
    /// `0 <= x0 <= W - W / s`, `0 <= y0 <= H - H / s`.
    pub offset_px: [f32; 2],
}

/// The output of [`crop_zoom`]: every input resampled, and the camera that sees the new image.
#[derive(Debug, Clone, PartialEq)]
pub struct CropZoomed {
    /// The RGB image, bilinear.
    pub image: RgbImage,
    /// The camera of the new image (same extrinsics, same size).
    pub camera: PinholeCamera,
    /// The label map, nearest neighbour (when one was given).
    pub labels: Option<Vec<u32>>,
    /// The depth map (camera-frame `z`, metres, 0 = no depth), nearest neighbour so that no depth mixes
    /// across edges; values unchanged (when one was given).
    pub depth_m: Option<Vec<f32>>,
}

impl CropZoom {
    /// The identity for a `width x height` image.
    pub fn identity(width: u32, height: u32) -> Self {
        CropZoom {
            width,
            height,
            scale: 1.0,
            offset_px: [0.0, 0.0],
        }
    }

    /// A validated crop-and-zoom.
    pub fn new(width: u32, height: u32, scale: f32, offset_px: [f32; 2]) -> Result<Self> {
        let c = CropZoom {
            width,
            height,
            scale,
            offset_px,
        };
        c.validate()?;
        Ok(c)
    }

    /// A random crop-and-zoom: `scale` uniform in `scale_range` (both `>= 1`), then each offset uniform in
    /// its allowed range `[0, W - W / s]`, from `ChaCha8Rng::seed_from_u64(seed)`.
    pub fn draw(width: u32, height: u32, scale_range: [f32; 2], seed: u64) -> Result<Self> {
        check_scale_range(scale_range)?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let scale = uniform(&mut rng, scale_range);
        let offset = |n: u32, rng: &mut ChaCha8Rng| {
            let max = (n as f32 - n as f32 / scale).max(0.0);
            (rng.random::<f32>() * max).min(max)
        };
        let x0 = offset(width, &mut rng);
        let y0 = offset(height, &mut rng);
        Self::new(width, height, scale, [x0, y0])
    }

    /// Check the size (non-empty), the scale (finite, `1 <= s <= min(W, H)`, so the window keeps at least
    /// one pixel) and the offsets (the window inside the image).
    pub fn validate(&self) -> Result<()> {
        let (w, h) = (self.width as f32, self.height as f32);
        if self.width == 0 || self.height == 0 {
            return Err(invalid(
                "crop size",
                format!("{}x{}: the image is empty", self.width, self.height),
            ));
        }
        let s = self.scale;
        if !(s.is_finite() && s >= 1.0 && s <= w.min(h)) {
            return Err(invalid(
                "crop scale",
                format!("{s} must be finite and in [1, {}]", w.min(h)),
            ));
        }
        for (axis, (o, n)) in ["x", "y"]
            .iter()
            .zip(self.offset_px.into_iter().zip([w, h]))
        {
            let max = n - n / s;
            if !(o.is_finite() && o >= -BOUND_SLACK_PX && o <= max + BOUND_SLACK_PX) {
                return Err(invalid(
                    "crop offset",
                    format!("{axis} offset {o} px not in [0, {max}] for scale {s}"),
                ));
            }
        }
        Ok(())
    }

    fn check_size(&self, width: u32, height: u32, what: &str) -> Result<()> {
        self.validate()?;
        if (width, height) != (self.width, self.height) {
            return Err(Error::Mismatch {
                context: format!("crop-and-zoom {what}"),
                message: format!(
                    "{width}x{height} input for a crop planned on {}x{}",
                    self.width, self.height
                ),
            });
        }
        Ok(())
    }

    /// Input coordinate sampled by output pixel `i` along an axis with window offset `o`.
    fn source(&self, i: u32, o: f32) -> f32 {
        (i as f32 + 0.5) / self.scale + o - 0.5
    }

    /// The camera of the cropped and zoomed image: `K' = A K` with
    /// `A = [[s, 0, s (0.5 - x0) - 0.5], [0, s, s (0.5 - y0) - 0.5], [0, 0, 1]]` (padded to 4x4, applied
    /// to all four columns of `K`, so KITTI's `P2` translation follows); extrinsics, size and near plane
    /// unchanged.
    pub fn camera(&self, camera: &PinholeCamera) -> Result<PinholeCamera> {
        self.check_size(camera.width, camera.height, "camera")?;
        let s = self.scale;
        let cx = s * (0.5 - self.offset_px[0]) - 0.5;
        let cy = s * (0.5 - self.offset_px[1]) - 0.5;
        let a = Mat4::from_cols_array_2d(&[
            [s, 0.0, 0.0, 0.0],
            [0.0, s, 0.0, 0.0],
            [cx, cy, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]);
        let out = PinholeCamera {
            intrinsics: a * camera.intrinsics,
            ..*camera
        };
        out.validate()?;
        Ok(out)
    }

    /// Resample an RGB image bilinearly (clamped to the edge), rounding to nearest.
    pub fn resample_rgb(&self, img: &RgbImage) -> Result<RgbImage> {
        self.check_size(img.width(), img.height(), "image")?;
        let (w, h) = (self.width as usize, self.height as usize);
        let src = img.as_raw();
        let mut out = RgbImage::new(self.width, self.height);
        let axis = |n: usize, o: f32| -> Vec<(usize, usize, f32)> {
            (0..n as u32)
                .map(|i| {
                    let u = self.source(i, o).clamp(0.0, n as f32 - 1.0);
                    let i0 = u.floor() as usize;
                    let i1 = (i0 + 1).min(n - 1);
                    (i0, i1, u - i0 as f32)
                })
                .collect()
        };
        let xs = axis(w, self.offset_px[0]);
        let ys = axis(h, self.offset_px[1]);
        let px = |x: usize, y: usize, c: usize| f32::from(src[3 * (y * w + x) + c]);
        for (j, &(y0, y1, fy)) in ys.iter().enumerate() {
            for (i, &(x0, x1, fx)) in xs.iter().enumerate() {
                let mut rgb = [0u8; 3];
                for (c, o) in rgb.iter_mut().enumerate() {
                    let top = px(x0, y0, c) * (1.0 - fx) + px(x1, y0, c) * fx;
                    let bottom = px(x0, y1, c) * (1.0 - fx) + px(x1, y1, c) * fx;
                    *o = (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8;
                }
                out.put_pixel(i as u32, j as u32, image::Rgb(rgb));
            }
        }
        Ok(out)
    }

    /// Resample a per-pixel map (labels, depth, ...; row-major, one value per pixel) by nearest
    /// neighbour: output pixel `(i', j')` takes input pixel `(round(u), round(v))`, clamped to the image.
    pub fn resample_nearest<T: Copy>(&self, map: &[T], width: u32, height: u32) -> Result<Vec<T>> {
        self.check_size(width, height, "map")?;
        let (w, h) = (width as usize, height as usize);
        if map.len() != w * h {
            return Err(Error::Mismatch {
                context: "crop-and-zoom map".into(),
                message: format!("{} values for a {width}x{height} map", map.len()),
            });
        }
        let nearest = |i: u32, o: f32, n: usize| {
            ((self.source(i, o) + 0.5).floor().max(0.0) as usize).min(n - 1)
        };
        let xs: Vec<usize> = (0..width)
            .map(|i| nearest(i, self.offset_px[0], w))
            .collect();
        let mut out = Vec::with_capacity(w * h);
        for j in 0..height {
            let row = nearest(j, self.offset_px[1], h) * w;
            out.extend(xs.iter().map(|&x| map[row + x]));
        }
        Ok(out)
    }
}

fn check_scale_range([lo, hi]: [f32; 2]) -> Result<()> {
    if !(lo.is_finite() && hi.is_finite() && lo >= 1.0 && hi >= lo) {
        return Err(invalid(
            "crop scale range",
            format!("[{lo}, {hi}] must be finite with 1 <= lo <= hi"),
        ));
    }
    Ok(())
}

/// Crop and zoom an image with its camera and, optionally, its label and depth maps (see
/// [`CropZoom`]). Depth values are copied, never changed: the camera does not move.
pub fn crop_zoom(
    image: &RgbImage,
    camera: &PinholeCamera,
    labels: Option<&[u32]>,
    depth_m: Option<&[f32]>,
    crop: &CropZoom,
) -> Result<CropZoomed> {
    let (w, h) = image.dimensions();
    Ok(CropZoomed {
        image: crop.resample_rgb(image)?,
        camera: crop.camera(camera)?,
        labels: labels.map(|l| crop.resample_nearest(l, w, h)).transpose()?,
        depth_m: depth_m
            .map(|d| crop.resample_nearest(d, w, h))
            .transpose()?,
    })
}

/// Configuration of the random crop-and-zoom (TOML / JSON via serde).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CropZoomRange {
    /// Probability of cropping at all, `[0, 1]`.
    pub p: f32,
    /// Zoom factor range `[lo, hi]`, `1 <= lo <= hi`.
    pub scale: [f32; 2],
}

impl Default for CropZoomRange {
    /// Half of the images zoomed by 1 to 1.3.
    fn default() -> Self {
        CropZoomRange {
            p: 0.5,
            scale: [1.0, 1.3],
        }
    }
}

impl CropZoomRange {
    /// Never crop.
    pub fn identity() -> Self {
        CropZoomRange {
            p: 0.0,
            scale: [1.0, 1.0],
        }
    }

    /// Check the probability and the scale range.
    pub fn validate(&self) -> Result<()> {
        if !(0.0..=1.0).contains(&self.p) {
            return Err(invalid(
                "crop probability",
                format!("{} not in [0, 1]", self.p),
            ));
        }
        check_scale_range(self.scale)
    }

    /// Draw a crop for a `width x height` image from `seed`: with probability `p` a
    /// [`CropZoom::draw`] (its seed taken from this stream), else the identity.
    pub fn draw(&self, width: u32, height: u32, seed: u64) -> Result<CropZoom> {
        self.validate()?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let on = rng.random::<f32>() < self.p;
        let sub_seed: u64 = rng.random();
        if on {
            CropZoom::draw(width, height, self.scale, sub_seed)
        } else {
            let c = CropZoom::identity(width, height);
            c.validate()?;
            Ok(c)
        }
    }
}
