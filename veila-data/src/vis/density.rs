//! Report building blocks: the bird's-eye-view point density of a set of scans, the image of the
//! signed difference of two densities (with its colour bar), a diverging colour map, and normalised
//! histograms.
//!
//! ```
//! use glam::Vec3;
//! use veila_data::PointCloud;
//! use veila_data::vis::density::{BevGrid, histogram};
//!
//! let cloud = PointCloud { xyz: vec![Vec3::new(1.0, 0.0, 0.0); 4], intensity: vec![0.5; 4], ring: None, label: None };
//! let grid = BevGrid { half_extent_m: 50.0, cell_m: 0.5 };
//! let d = grid.density(std::slice::from_ref(&cloud));
//! assert_eq!(d.iter().sum::<f64>(), 1.0);
//! let (img, max) = grid.difference_image(&d, &vec![0.0; d.len()]);
//! assert_eq!((img.width(), max), (2 * grid.side() as u32, 1.0));
//!
//! let h = histogram([0.5, 1.5, 1.5].into_iter(), 0.0, 2.0, 2);
//! assert_eq!(h, vec![(0.5, 1.0 / 3.0), (1.5, 2.0 / 3.0)]);
//! ```

use image::{Rgb, RgbImage};

use super::plot::{draw_text, text_width};
use crate::PointCloud;

/// Font size of the colour bar's labels, in pixels.
const LABEL_PX: f64 = 13.0;

/// A square bird's-eye-view grid centred on the sensor, in the image convention of the BEV previews:
/// forward (+x) up, left (+y) left.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BevGrid {
    /// Half the side of the square window, in metres.
    pub half_extent_m: f64,
    /// Cell size in metres.
    pub cell_m: f64,
}

impl BevGrid {
    /// Cells per side.
    pub fn side(&self) -> usize {
        (2.0 * self.half_extent_m / self.cell_m) as usize
    }

    /// Point density over the grid (row-major, `side() * side()` cells), normalised to sum 1 over
    /// the points inside the window (all zeros when none is). Non-finite points are skipped.
    pub fn density(&self, clouds: &[PointCloud]) -> Vec<f64> {
        let n = self.side();
        let mut grid = vec![0.0; n * n];
        let mut total = 0.0;
        for c in clouds {
            for p in &c.xyz {
                let (x, y) = (p.x as f64, p.y as f64);
                if !(x.is_finite() && y.is_finite()) {
                    continue;
                }
                let row = ((self.half_extent_m - x) / self.cell_m).floor();
                let col = ((self.half_extent_m - y) / self.cell_m).floor();
                if row >= 0.0 && col >= 0.0 && (row as usize) < n && (col as usize) < n {
                    grid[row as usize * n + col as usize] += 1.0;
                    total += 1.0;
                }
            }
        }
        if total > 0.0 {
            grid.iter_mut().for_each(|v| *v /= total);
        }
        grid
    }

    /// The image of `a - b` (two densities of this grid) on the [`diverging`] colour map at twice
    /// the grid's resolution, on a signed square-root scale so that small differences stay visible
    /// next to the largest, with the sensor marked and a colour bar labelled `-max .. 0 .. +max`
    /// underneath; and that largest |difference|.
    pub fn difference_image(&self, a: &[f64], b: &[f64]) -> (RgbImage, f64) {
        let n = self.side();
        let max = a
            .iter()
            .zip(b)
            .map(|(g, r)| (g - r).abs())
            .fold(0.0f64, f64::max);
        let zoom = 2;
        let side = (n * zoom) as u32;
        let bar_h = 44u32;
        let mut img = RgbImage::from_pixel(side, side + bar_h, Rgb([255, 255, 255]));
        for y in 0..side {
            for x in 0..side {
                let k = (y as usize / zoom) * n + x as usize / zoom;
                let d = a[k] - b[k];
                let t = if max > 0.0 {
                    d.signum() * (d.abs() / max).sqrt()
                } else {
                    0.0
                };
                img.put_pixel(x, y, Rgb(diverging(t)));
            }
        }
        // the sensor position
        let c = side / 2;
        for d in 0..5u32 {
            for (x, y) in [(c - 2 + d, c), (c, c - 2 + d)] {
                img.put_pixel(x, y, Rgb([0, 0, 0]));
            }
        }
        // colour bar: -max .. 0 .. +max (signed square-root scale)
        let (x0, x1) = (20u32, side - 20);
        for x in x0..x1 {
            let t = 2.0 * (x - x0) as f64 / (x1 - x0 - 1) as f64 - 1.0;
            for y in side + 6..side + 18 {
                img.put_pixel(x, y, Rgb(diverging(t)));
            }
        }
        let dark = Rgb([34, 34, 34]);
        let lo = format!("-{max:.1e}");
        let hi = format!("+{max:.1e}");
        let (px, y) = (LABEL_PX, side as i64 + 23);
        draw_text(&mut img, x0 as i64, y, &lo, px, dark);
        let mid = text_width("0", px) as i64;
        draw_text(&mut img, (side / 2) as i64 - mid / 2, y, "0", px, dark);
        let w = text_width(&hi, px) as i64;
        draw_text(&mut img, x1 as i64 - w, y, &hi, px, dark);
        (img, max)
    }
}

/// Diverging colour: blue (-1) through near-white (0) to red (+1), ColorBrewer's RdBu (from
/// colorous); out-of-range values are clamped, NaN is the middle.
pub fn diverging(t: f64) -> [u8; 3] {
    let t = if t.is_nan() { 0.0 } else { t.clamp(-1.0, 1.0) };
    let c = colorous::RED_BLUE.eval_continuous((1.0 - t) / 2.0);
    [c.r, c.g, c.b]
}

/// Normalised histogram (density per unit) of `values` over `[lo, hi)` in `bins` bins, as points at
/// the bin centres. Values outside the range and non-finite values are left out; no value in range
/// gives all zeros.
pub fn histogram(
    values: impl Iterator<Item = f64>,
    lo: f64,
    hi: f64,
    bins: usize,
) -> Vec<(f64, f64)> {
    let mut counts = vec![0.0; bins];
    let width = (hi - lo) / bins as f64;
    let mut total = 0.0;
    for v in values {
        if v.is_finite() && v >= lo && v < hi {
            let b = (((v - lo) / width) as usize).min(bins - 1);
            counts[b] += 1.0;
            total += 1.0;
        }
    }
    counts
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let density = if total > 0.0 {
                c / (total * width)
            } else {
                0.0
            };
            (lo + (i as f64 + 0.5) * width, density)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn cloud(xyz: Vec<Vec3>) -> PointCloud {
        let n = xyz.len();
        PointCloud {
            xyz,
            intensity: vec![0.0; n],
            ring: None,
            label: None,
        }
    }

    #[test]
    fn density_bins_by_brute_force_and_sums_to_one() {
        let grid = BevGrid {
            half_extent_m: 2.0,
            cell_m: 1.0,
        };
        // forward-left point -> top-left quadrant; behind-right -> bottom-right; outside -> dropped
        let pts = vec![
            Vec3::new(1.5, 1.5, 0.0),
            Vec3::new(-0.5, -1.2, 0.0),
            Vec3::new(-0.5, -1.2, 3.0),
            Vec3::new(9.0, 0.0, 0.0),
            Vec3::new(f32::NAN, 0.0, 0.0),
        ];
        let d = grid.density(&[cloud(pts)]);
        let mut want = vec![0.0; 16];
        want[0] = 1.0 / 3.0; // row floor((2-1.5)/1)=0, col 0
        want[2 * 4 + 3] = 2.0 / 3.0; // row floor(2.5)=2, col floor(3.2)=3
        assert_eq!(d, want);
        assert_eq!(grid.density(&[cloud(vec![])]), vec![0.0; 16]);
    }

    #[test]
    fn diverging_ends_and_middle() {
        // ColorBrewer RdBu: #053061 (blue end), #f7f7f7 (middle), #67001f (red end); colorous
        // interpolates the 11 classes with a B-spline, so the knots are met only approximately
        let near = |a: [u8; 3], b: [u8; 3]| (0..3).all(|k| (a[k] as i32 - b[k] as i32).abs() <= 10);
        assert!(
            near(diverging(0.0), [247, 247, 247]),
            "{:?}",
            diverging(0.0)
        );
        assert!(near(diverging(-1.0), [5, 48, 97]), "{:?}", diverging(-1.0));
        assert!(near(diverging(1.0), [103, 0, 31]), "{:?}", diverging(1.0));
        assert_eq!(diverging(7.0), diverging(1.0));
        assert_eq!(diverging(f64::NAN), diverging(0.0));
        // red half is red-dominant, blue half blue-dominant
        let (r, b) = (diverging(0.5), diverging(-0.5));
        assert!(r[0] > r[2] && b[2] > b[0], "{r:?} {b:?}");
    }

    #[test]
    fn difference_image_signs_and_size() {
        let grid = BevGrid {
            half_extent_m: 10.0,
            cell_m: 1.0,
        };
        let n = grid.side();
        let mut a = vec![0.0; n * n];
        let mut b = vec![0.0; n * n];
        a[0] = 0.5; // top-left cell: more generated -> red
        b[n * n - 1] = 0.25; // bottom-right cell: more reference -> blue
        let (img, max) = grid.difference_image(&a, &b);
        assert_eq!(max, 0.5);
        assert_eq!(img.dimensions(), (2 * n as u32, 2 * n as u32 + 44));
        assert_eq!(img.get_pixel(1, 1).0, diverging(1.0));
        let far = 2 * n as u32 - 1;
        assert_eq!(img.get_pixel(far, far).0, diverging(-(0.5f64).sqrt()));
        assert_eq!(img.get_pixel(5, 9).0, diverging(0.0));
    }

    #[test]
    fn histogram_integrates_to_one_and_drops_outliers() {
        let values = [0.1, 0.2, 0.7, 1.0, -0.1, f64::NAN, 0.99];
        let h = histogram(values.into_iter(), 0.0, 1.0, 4);
        let xs: Vec<f64> = h.iter().map(|p| p.0).collect();
        assert_eq!(xs, vec![0.125, 0.375, 0.625, 0.875]);
        let integral: f64 = h.iter().map(|p| p.1 * 0.25).sum();
        assert!((integral - 1.0).abs() < 1e-12);
        // counts 2, 0, 1, 1 of 4 in-range values, bin width 0.25
        assert_eq!(
            h.iter().map(|p| p.1).collect::<Vec<_>>(),
            vec![2.0, 0.0, 1.0, 1.0]
        );
        assert!(
            histogram(std::iter::empty(), 0.0, 1.0, 3)
                .iter()
                .all(|p| p.1 == 0.0)
        );
    }
}
