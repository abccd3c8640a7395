//! Point labels from a segmented range image, with RangeNet++'s k-nearest-neighbour clean-up.
//!
//! A range image keeps one point per pixel (the nearest), so the points that share a pixel with a
//! nearer one, and the points on an object's boundary, would all take a class predicted for some
//! other surface. RangeNet++ (Milioto et al. 2019, `postproc/KNN.py` of PRBonn/lidar-bonnetal)
//! fixes this per point: among the pixels of a `search x search` window around the point's pixel,
//! it takes the `k` whose range is nearest to the point's own range, each range difference
//! weighted by one minus a normalised Gaussian of the pixel's offset (so the centre counts as
//! nearest), drops those farther than `cutoff`, and lets the rest vote.
//!
//! [`KnnConfig::default`] is the official configs' `post.KNN.params` (k 5, search 5, sigma 1,
//! cutoff 1 m). Details, where this implementation says what RangeNet++ leaves to chance:
//!
//! * the window centre takes the point's own range (distance 0), so the point's own pixel always
//!   votes;
//! * empty pixels and pixels outside the image never vote (RangeNet++ gives empty pixels an
//!   infinite range and the zero padding outside the image range 0; both fail its cutoff);
//! * equal distances are ordered by the window position (row-major), the votes' tie goes to the
//!   lower class, and class [`IGNORED_CLASS`] (SemanticKITTI's "unlabeled") never votes, as in
//!   RangeNet++;
//! * a point left without any vote takes its own pixel's class (RangeNet++ would answer class 1);
//! * the azimuth does not wrap (as RangeNet++).
//!
//! This lives beside the segmenter, not in `veila-geom`, because it is the network's
//! post-processing (class votes, the segmenter's ignore class), not geometry; it works on plain
//! slices, and the geometry it needs (each point's pixel and range) comes from
//! [`veila_geom::Projector::locate`] through [`locate_points`].

use glam::Vec3;
use serde::{Deserialize, Serialize};
use veila_geom::{PixelOutcome, Projector, RangeImage};

use crate::error::{Error, Result};

/// The class that never votes and that points without a pixel get (SemanticKITTI's train id 0).
pub const IGNORED_CLASS: u32 = 0;
/// Largest `search` window side.
pub const MAX_SEARCH: usize = 31;

/// Parameters of the clean-up (RangeNet++'s `post.KNN.params`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct KnnConfig {
    /// Neighbours that vote, `1..=search²`.
    pub k: usize,
    /// Side of the search window in pixels (odd, at most [`MAX_SEARCH`]).
    pub search: usize,
    /// Standard deviation of the Gaussian over the window, in pixels.
    pub sigma: f32,
    /// Largest weighted range difference of a voter, metres; 0 keeps every neighbour.
    pub cutoff: f32,
}

impl Default for KnnConfig {
    /// k 5, search 5, sigma 1, cutoff 1 (RangeNet++'s SemanticKITTI configs).
    fn default() -> Self {
        KnnConfig {
            k: 5,
            search: 5,
            sigma: 1.0,
            cutoff: 1.0,
        }
    }
}

impl KnnConfig {
    /// Checks every field (the message names the offending one).
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::Config(format!("knn: {m}")));
        if self.search == 0 || self.search.is_multiple_of(2) || self.search > MAX_SEARCH {
            return bad(format!(
                "search {} must be odd and in 1..={MAX_SEARCH}",
                self.search
            ));
        }
        if self.k == 0 || self.k > self.search * self.search {
            return bad(format!(
                "k {} must be in 1..=search² ({})",
                self.k,
                self.search * self.search
            ));
        }
        if !(self.sigma.is_finite() && self.sigma > 0.0) {
            return bad(format!("sigma {} must be finite and > 0", self.sigma));
        }
        if !(self.cutoff.is_finite() && self.cutoff >= 0.0) {
            return bad(format!("cutoff {} must be finite and >= 0", self.cutoff));
        }
        Ok(())
    }

    /// `1 - g` over the window (row-major), `g` the Gaussian of the offset from the centre with
    /// standard deviation `sigma`, normalised to sum 1.
    pub fn inverse_gaussian(&self) -> Vec<f32> {
        let s = self.search;
        let m = (s as f64 - 1.0) / 2.0;
        let var = f64::from(self.sigma) * f64::from(self.sigma);
        let g: Vec<f64> = (0..s * s)
            .map(|i| {
                let (dy, dx) = ((i / s) as f64 - m, (i % s) as f64 - m);
                (-(dx * dx + dy * dy) / (2.0 * var)).exp()
            })
            .collect();
        let sum: f64 = g.iter().sum();
        g.iter().map(|v| (1.0 - v / sum) as f32).collect()
    }
}

/// Where a point fell in the range image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointPixel {
    /// Row.
    pub row: u32,
    /// Column.
    pub col: u32,
    /// The point's range, metres.
    pub range_m: f32,
}

/// Each point's pixel and range under `projector` (the projection that made the image), `None`
/// for a point the projection rejects. `rings`, when given, has one entry per point.
pub fn locate_points(
    projector: &Projector,
    points: &[Vec3],
    rings: Option<&[u16]>,
) -> Result<Vec<Option<PointPixel>>> {
    if let Some(r) = rings
        && r.len() != points.len()
    {
        return Err(Error::Input(format!(
            "locate_points: {} rings for {} points",
            r.len(),
            points.len()
        )));
    }
    Ok(points
        .iter()
        .enumerate()
        .map(|(i, &p)| match projector.locate(p, rings.map(|r| r[i])) {
            PixelOutcome::Pixel {
                row, col, range_m, ..
            } => Some(PointPixel { row, col, range_m }),
            _ => None,
        })
        .collect())
}

/// The class of every point: `pixel_class` (row-major, one per pixel of `image`, e.g. from
/// [`super::pixel_classes`]) carried to `points` (from [`locate_points`]) by the k-nearest-neighbour
/// vote of the module docs. Points without a pixel get [`IGNORED_CLASS`].
///
/// Fails when the config is invalid, `pixel_class` does not have one entry per pixel, or a point
/// names a pixel outside the image.
pub fn point_labels(
    image: &RangeImage,
    pixel_class: &[u32],
    points: &[Option<PointPixel>],
    cfg: &KnnConfig,
) -> Result<Vec<u32>> {
    cfg.validate()?;
    image.validate()?;
    let (h, w) = (image.rows as usize, image.cols as usize);
    if pixel_class.len() != h * w {
        return Err(Error::Input(format!(
            "point_labels: {} pixel classes for a {h} x {w} image",
            pixel_class.len()
        )));
    }
    let inv_g = cfg.inverse_gaussian();
    let s = cfg.search;
    let half = (s / 2) as i64;
    let mut cand: Vec<(f32, usize, u32)> = Vec::with_capacity(s * s);
    let mut votes: Vec<(u32, usize)> = Vec::with_capacity(cfg.k);
    let mut out = Vec::with_capacity(points.len());
    for (i, p) in points.iter().enumerate() {
        let Some(p) = p else {
            out.push(IGNORED_CLASS);
            continue;
        };
        let (r0, c0) = (p.row as usize, p.col as usize);
        if r0 >= h || c0 >= w {
            return Err(Error::Input(format!(
                "point_labels: point {i} at pixel ({r0}, {c0}) of a {h} x {w} image"
            )));
        }
        let own = pixel_class[r0 * w + c0];
        cand.clear();
        for (j, g) in inv_g.iter().enumerate() {
            let (rr, cc) = (
                r0 as i64 + (j / s) as i64 - half,
                c0 as i64 + (j % s) as i64 - half,
            );
            if rr < 0 || cc < 0 || rr >= h as i64 || cc >= w as i64 {
                continue;
            }
            let q = rr as usize * w + cc as usize;
            let d = if rr as usize == r0 && cc as usize == c0 {
                0.0
            } else if image.mask[q] {
                (image.range_m[q] - p.range_m).abs() * g
            } else {
                continue;
            };
            if d.is_finite() {
                cand.push((d, j, pixel_class[q]));
            }
        }
        cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        votes.clear();
        for &(d, _, class) in cand.iter().take(cfg.k) {
            if (cfg.cutoff > 0.0 && d > cfg.cutoff) || class == IGNORED_CLASS {
                continue;
            }
            match votes.iter_mut().find(|v| v.0 == class) {
                Some(v) => v.1 += 1,
                None => votes.push((class, 1)),
            }
        }
        let best = votes
            .iter()
            .copied()
            .max_by(|a, b| a.1.cmp(&b.1).then(b.0.cmp(&a.0)))
            .map_or(own, |v| v.0);
        out.push(best);
    }
    Ok(out)
}
