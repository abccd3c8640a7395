//! Previews: range, intensity and label images, a bird's-eye view, and LiDAR points drawn on the camera
//! image coloured by depth (the paper's Figure 6 view).
//!
//! Colour maps are matplotlib's perceptually uniform `viridis` (range, depth, height) and `magma`
//! (intensity), from the `colorous` crate; empty pixels are black. Label
//! previews use the SemanticKITTI colours of the label map (stored BGR in the yaml, converted to RGB).

use glam::Vec3;
use image::{Rgb, RgbImage};
use veila_geom::{PinholeCamera, RangeImage};

use crate::semantic_kitti::LabelMap;
use crate::{Error, PointCloud, Result};

/// A perceptually uniform colour map.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Colormap {
    /// matplotlib's viridis (dark blue -> yellow).
    Viridis,
    /// matplotlib's magma (black -> light yellow).
    Magma,
}

impl Colormap {
    /// Colour of `t` in `[0, 1]` (clamped; NaN gives black), from colorous' copy of matplotlib's
    /// 256-entry table.
    pub fn rgb(self, t: f32) -> [u8; 3] {
        if t.is_nan() {
            return [0, 0, 0];
        }
        let gradient = match self {
            Colormap::Viridis => colorous::VIRIDIS,
            Colormap::Magma => colorous::MAGMA,
        };
        let c = gradient.eval_continuous(f64::from(t.clamp(0.0, 1.0)));
        [c.r, c.g, c.b]
    }
}

/// How range values become colours.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangePreview {
    /// Range mapped to the brightest colour, metres.
    pub near_m: f32,
    /// Range mapped to the darkest colour, metres.
    pub far_m: f32,
    /// Logarithmic scale (spreads the near field, where most structure is).
    pub log_scale: bool,
    /// Each range-image row is drawn this many pixels tall (64-beam images read better at 4).
    pub row_scale: u32,
}

impl Default for RangePreview {
    fn default() -> Self {
        RangePreview {
            near_m: 1.0,
            far_m: 80.0,
            log_scale: true,
            row_scale: 4,
        }
    }
}

impl RangePreview {
    fn t(&self, r: f32) -> f32 {
        let (a, b) = (
            self.near_m.max(1e-3),
            self.far_m.max(self.near_m.max(1e-3) * 1.0001),
        );
        let t = if self.log_scale {
            (r.max(a).ln() - a.ln()) / (b.ln() - a.ln())
        } else {
            (r - a) / (b - a)
        };
        1.0 - t.clamp(0.0, 1.0)
    }
}

fn scaled(rows: u32, cols: u32, row_scale: u32, px: impl Fn(usize) -> [u8; 3]) -> RgbImage {
    let s = row_scale.max(1);
    RgbImage::from_fn(cols, rows * s, |x, y| {
        Rgb(px((y / s) as usize * cols as usize + x as usize))
    })
}

/// Range preview: near bright, far dark (viridis), empty pixels black.
pub fn render_range(image: &RangeImage, opts: &RangePreview) -> RgbImage {
    scaled(image.rows, image.cols, opts.row_scale, |k| {
        let r = image.range_m[k];
        if image.mask[k] && r.is_finite() {
            Colormap::Viridis.rgb(opts.t(r))
        } else {
            [0, 0, 0]
        }
    })
}

/// Intensity preview (magma, `intensity / max_intensity`), empty pixels black.
pub fn render_intensity(image: &RangeImage, max_intensity: f32, row_scale: u32) -> RgbImage {
    let m = if max_intensity > 0.0 {
        max_intensity
    } else {
        1.0
    };
    scaled(image.rows, image.cols, row_scale, |k| {
        if image.mask[k] {
            Colormap::Magma.rgb(image.intensity[k] / m)
        } else {
            [0, 0, 0]
        }
    })
}

/// Label preview from raw SemanticKITTI labels (`image.label`) with the label map's colours; returns
/// `None` when the image has no labels.
pub fn render_labels(image: &RangeImage, map: &LabelMap, row_scale: u32) -> Option<RgbImage> {
    let labels = image.label.as_ref()?;
    Some(scaled(image.rows, image.cols, row_scale, |k| {
        if image.mask[k] {
            map.color_rgb(labels[k])
        } else {
            [0, 0, 0]
        }
    }))
}

/// Label preview from train ids (0..19) with the label map's colours.
pub fn render_train_labels(
    train_ids: &[u8],
    mask: &[bool],
    rows: u32,
    cols: u32,
    map: &LabelMap,
    row_scale: u32,
) -> Result<RgbImage> {
    let n = rows as usize * cols as usize;
    if train_ids.len() != n || mask.len() != n {
        return Err(Error::Mismatch {
            context: "label preview".into(),
            message: format!(
                "{rows}x{cols} image but {} labels and {} mask values",
                train_ids.len(),
                mask.len()
            ),
        });
    }
    Ok(scaled(rows, cols, row_scale, |k| {
        if mask[k] {
            map.train_color_rgb(train_ids[k])
        } else {
            [0, 0, 0]
        }
    }))
}

/// Bird's-eye-view parameters. The image looks down on the LiDAR: forward (+x) is up, left (+y) is
/// left.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BevOptions {
    /// Half the side of the square shown, metres.
    pub half_extent_m: f32,
    /// Metres per pixel.
    pub resolution_m: f32,
    /// Height mapped to the darkest colour, metres.
    pub z_min_m: f32,
    /// Height mapped to the brightest colour, metres.
    pub z_max_m: f32,
}

impl Default for BevOptions {
    fn default() -> Self {
        BevOptions {
            half_extent_m: 50.0,
            resolution_m: 0.1,
            z_min_m: -2.5,
            z_max_m: 1.5,
        }
    }
}

/// Bird's-eye view coloured by height (viridis), the highest point of each cell wins; background
/// black. Non-finite points are skipped.
pub fn render_bev(cloud: &PointCloud, opts: &BevOptions) -> Result<RgbImage> {
    let valid = opts.half_extent_m > 0.0 && opts.resolution_m > 0.0 && opts.z_max_m > opts.z_min_m;
    if !valid {
        return Err(Error::Invalid {
            what: "BEV options".into(),
            message: format!("{opts:?}: extent and resolution must be positive and z_max > z_min"),
        });
    }
    let side = (2.0 * opts.half_extent_m / opts.resolution_m).ceil() as u64;
    if side == 0 || side > 16384 {
        return Err(Error::Invalid {
            what: "BEV options".into(),
            message: format!("image side {side} px is outside 1..=16384"),
        });
    }
    let side = side as u32;
    let mut top = vec![f32::NEG_INFINITY; side as usize * side as usize];
    for p in &cloud.xyz {
        if !p.is_finite() {
            continue;
        }
        let col = ((opts.half_extent_m - p.y) / opts.resolution_m).floor();
        let row = ((opts.half_extent_m - p.x) / opts.resolution_m).floor();
        if col < 0.0 || row < 0.0 || col >= side as f32 || row >= side as f32 {
            continue;
        }
        let k = row as usize * side as usize + col as usize;
        top[k] = top[k].max(p.z);
    }
    let span = opts.z_max_m - opts.z_min_m;
    Ok(RgbImage::from_fn(side, side, |x, y| {
        let z = top[y as usize * side as usize + x as usize];
        if z == f32::NEG_INFINITY {
            Rgb([0, 0, 0])
        } else {
            Rgb(Colormap::Viridis.rgb((z - opts.z_min_m) / span))
        }
    }))
}

/// Camera-overlay parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OverlayOptions {
    /// Depth mapped to the brightest colour (metres); nearer is clamped.
    pub near_m: f32,
    /// Depth mapped to the darkest colour (metres); farther is clamped.
    pub far_m: f32,
    /// Dot radius in pixels (0 = single pixel).
    pub radius_px: u32,
    /// Points at or nearer than this camera depth are not drawn (nuScenes' devkit uses 1 m).
    pub min_depth_m: f32,
}

impl Default for OverlayOptions {
    fn default() -> Self {
        OverlayOptions {
            near_m: 2.0,
            far_m: 60.0,
            radius_px: 1,
            min_depth_m: 1.0,
        }
    }
}

/// Result of [`render_overlay`].
#[derive(Debug, Clone)]
pub struct Overlay {
    /// The camera image with the points drawn.
    pub image: RgbImage,
    /// Points that landed inside the image (and passed the depth limit), each drawn once.
    pub drawn: usize,
}

/// Draw LiDAR points on the camera image, coloured by camera depth on a log scale between `near_m`
/// and `far_m` (near bright, far dark; viridis), far points first so near ones stay on top. The image must have the camera's size.
pub fn render_overlay(
    image: &RgbImage,
    camera: &PinholeCamera,
    points: &[Vec3],
    opts: &OverlayOptions,
) -> Result<Overlay> {
    if image.dimensions() != (camera.width, camera.height) {
        return Err(Error::Mismatch {
            context: "camera overlay".into(),
            message: format!(
                "image is {}x{} but the calibration is for {}x{}",
                image.width(),
                image.height(),
                camera.width,
                camera.height
            ),
        });
    }
    let mut hits: Vec<(f32, f32, f32)> = points
        .iter()
        .filter_map(|p| camera.try_project_in_image(*p))
        .filter(|ip| ip.depth_m > opts.min_depth_m)
        .map(|ip| (ip.u_px, ip.v_px, ip.depth_m))
        .collect();
    hits.sort_by(|a, b| b.2.total_cmp(&a.2));
    let mut out = image.clone();
    let (w, h) = (image.width() as i64, image.height() as i64);
    let r = opts.radius_px as i64;
    let near = opts.near_m.max(1e-3);
    let log_span = (opts.far_m.max(near * 1.0001) / near).ln();
    for &(u, v, d) in &hits {
        let c = Colormap::Viridis.rgb(1.0 - (d.max(near) / near).ln() / log_span);
        let (cu, cv) = ((u + 0.5).floor() as i64, (v + 0.5).floor() as i64);
        for dy in -r..=r {
            for dx in -r..=r {
                if dx * dx + dy * dy > r * r {
                    continue;
                }
                let (x, y) = (cu + dx, cv + dy);
                if x >= 0 && y >= 0 && x < w && y < h {
                    out.put_pixel(x as u32, y as u32, Rgb(c));
                }
            }
        }
    }
    Ok(Overlay {
        image: out,
        drawn: hits.len(),
    })
}

/// Images stacked top to bottom (left-aligned; the canvas is as wide as the widest, gaps black).
pub fn stack_vertical(images: &[RgbImage]) -> RgbImage {
    let w = images.iter().map(|i| i.width()).max().unwrap_or(0);
    let h = images.iter().map(|i| i.height()).sum();
    let mut out = RgbImage::new(w, h);
    let mut y = 0;
    for img in images {
        image::imageops::replace(&mut out, img, 0, i64::from(y));
        y += img.height();
    }
    out
}

/// Images side by side, left to right (top-aligned; the canvas is as tall as the tallest).
pub fn stack_horizontal(images: &[RgbImage]) -> RgbImage {
    let w = images.iter().map(|i| i.width()).sum();
    let h = images.iter().map(|i| i.height()).max().unwrap_or(0);
    let mut out = RgbImage::new(w, h);
    let mut x = 0;
    for img in images {
        image::imageops::replace(&mut out, img, i64::from(x), 0);
        x += img.width();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Relative luminance (Rec. 709 on sRGB-decoded values).
    fn luminance(c: [u8; 3]) -> f32 {
        let lin = |v: u8| {
            let s = v as f32 / 255.0;
            if s <= 0.04045 {
                s / 12.92
            } else {
                ((s + 0.055) / 1.055).powf(2.4)
            }
        };
        0.2126 * lin(c[0]) + 0.7152 * lin(c[1]) + 0.0722 * lin(c[2])
    }

    #[test]
    fn stacking_places_each_image_at_its_offset() {
        let a = RgbImage::from_pixel(3, 2, Rgb([1, 0, 0]));
        let b = RgbImage::from_pixel(2, 4, Rgb([0, 2, 0]));
        let v = stack_vertical(&[a.clone(), b.clone()]);
        assert_eq!(v.dimensions(), (3, 6));
        assert_eq!(v.get_pixel(2, 1), &Rgb([1, 0, 0]));
        assert_eq!(v.get_pixel(1, 5), &Rgb([0, 2, 0]));
        assert_eq!(
            v.get_pixel(2, 5),
            &Rgb([0, 0, 0]),
            "gap right of the narrower image"
        );
        let h = stack_horizontal(&[a, b]);
        assert_eq!(h.dimensions(), (5, 4));
        assert_eq!(h.get_pixel(0, 1), &Rgb([1, 0, 0]));
        assert_eq!(h.get_pixel(4, 3), &Rgb([0, 2, 0]));
        assert_eq!(
            h.get_pixel(0, 3),
            &Rgb([0, 0, 0]),
            "gap below the shorter image"
        );
        assert_eq!(stack_vertical(&[]).dimensions(), (0, 0));
    }

    #[test]
    fn colormaps_are_monotone_in_luminance() {
        for cm in [Colormap::Viridis, Colormap::Magma] {
            let mut prev = -1.0;
            for i in 0..=64 {
                let l = luminance(cm.rgb(i as f32 / 64.0));
                assert!(l > prev, "{cm:?} not monotone at {i}");
                prev = l;
            }
            assert_eq!(cm.rgb(f32::NAN), [0, 0, 0]);
            // the ends of matplotlib's tables (viridis #440154 .. #fde725, magma #000004 .. #fcfdbf)
            let ends = match cm {
                Colormap::Viridis => [[68u8, 1, 84], [253, 231, 37]],
                Colormap::Magma => [[0, 0, 4], [252, 253, 191]],
            };
            for (t, want) in [(0.0, ends[0]), (1.0, ends[1])] {
                let got = cm.rgb(t);
                assert!(
                    (0..3).all(|k| (got[k] as i32 - want[k] as i32).abs() <= 3),
                    "{cm:?}({t}) = {got:?}, matplotlib {want:?}"
                );
            }
            assert_eq!(cm.rgb(-3.0), cm.rgb(0.0));
            assert_eq!(cm.rgb(7.0), cm.rgb(1.0));
        }
    }

    #[test]
    fn range_preview_blacks_out_empty_and_orders_near_bright() {
        let mut img = RangeImage::new_empty(2, 3);
        img.mask[0] = true;
        img.range_m[0] = 2.0;
        img.mask[1] = true;
        img.range_m[1] = 60.0;
        let png = render_range(
            &img,
            &RangePreview {
                row_scale: 2,
                ..Default::default()
            },
        );
        assert_eq!(png.dimensions(), (3, 4));
        assert_eq!(png.get_pixel(2, 0).0, [0, 0, 0]);
        assert_eq!(png.get_pixel(0, 1).0, png.get_pixel(0, 0).0);
        assert!(luminance(png.get_pixel(0, 0).0) > luminance(png.get_pixel(1, 0).0));
    }

    #[test]
    fn bev_puts_forward_up_and_left_left() {
        let cloud = PointCloud {
            xyz: vec![
                Vec3::new(40.0, 0.0, 0.0),
                Vec3::new(0.0, 40.0, 0.0),
                Vec3::new(f32::NAN, 0.0, 0.0),
            ],
            intensity: vec![0.0; 3],
            ring: None,
            label: None,
        };
        let opts = BevOptions {
            half_extent_m: 50.0,
            resolution_m: 1.0,
            ..Default::default()
        };
        let img = render_bev(&cloud, &opts).unwrap();
        assert_eq!(img.dimensions(), (100, 100));
        assert_ne!(img.get_pixel(50, 10).0, [0, 0, 0]); // forward: row 10, centre column
        assert_ne!(img.get_pixel(10, 50).0, [0, 0, 0]); // left: column 10, centre row
        let lit = img.pixels().filter(|p| p.0 != [0, 0, 0]).count();
        assert_eq!(lit, 2);
    }
}
