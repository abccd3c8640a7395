//! Realism statistics of a set of range images on one grid: the texture of the range field (relative
//! range steps between neighbouring pixels), where rays drop, how different two scans are and how close a
//! generated scan is to its nearest training scan.
//!
//! Every function takes [`RangeImage`]s (row-major, row 0 = top beam, columns wrap around in azimuth) and,
//! where it says so, an optional per-pixel **region mask** of `rows * cols` booleans (e.g. "inside the
//! camera's view"). A pixel `p` is **valid** when `mask[p] && range_m[p].is_finite() && range_m[p] > 0`.
//! A pair of pixels counts only when both are valid and, with a region mask, both lie in the region.
//!
//! Images whose `range_m` or `mask` does not have `rows * cols` entries, images of different shapes within
//! one call, and a region mask of the wrong length are [`Error::ShapeMismatch`]; nothing here panics on
//! such input. Statistics over nothing (no pair, no pixel in the region) are `NaN` or an empty
//! [`StepHistogram`], not errors. All arithmetic is in `f64` on the `f32` ranges converted to `f64`.
//!
//! | statistic | definition |
//! |---|---|
//! | [`relative_step`] | `s = \|r1 - r2\| / min(r1, r2)` |
//! | [`StepHistogram`] | counts of `log10(s)`: underflow `s < 1e-6`, 32 bins of 0.25 decade over `[1e-6, 1e2)`, overflow `s >= 1e2` |
//! | [`StepHistogram::smooth_share`], [`StepHistogram::edge_share`] | share of pairs with `s < 3e-4`; with `s > 1` |
//! | [`texture_distance`] | 1-Wasserstein distance of two normalised histograms on the `log10` axis, in decades |
//! | [`texture_jsd`] | Jensen–Shannon distance of the two histograms (`scipy.spatial.distance.jensenshannon`) |
//! | [`raydrop_per_row`], [`raydrop_row_distance`] | share of invalid pixels in each row; mean absolute difference of two such profiles |
//! | [`pairwise_range_mae`], [`drop_disagreement`] | diversity of two scans: range MAE over pixels valid in both; share of pixels valid in exactly one |
//! | [`scan_distance`], [`nearest_scan`] | memorisation: mean `\|log2(1 + r_a) - log2(1 + r_b)\|` (0 for an invalid pixel) and the nearest scan of a pool |

use rayon::prelude::*;
use veila_geom::RangeImage;

use crate::{Error, Result};

/// Number of bins of a [`StepHistogram`]: underflow, 32 bins of 0.25 decade, overflow.
pub const STEP_BINS: usize = 34;
/// Steps `s` below this go to the underflow bin (bin 0), exact zeros included.
pub const UNDERFLOW_BELOW: f64 = 1e-6;
/// Steps `s` from this on go to the overflow bin (bin 33, the last).
pub const OVERFLOW_FROM: f64 = 1e2;
/// `log10` of the lower edge of the first regular bin.
pub const LOG10_LOW: f64 = -6.0;
/// Width of every bin on the `log10` axis, in decades (also the spacing of the bin centres).
pub const BIN_WIDTH_DECADES: f64 = 0.25;
/// Steps `s` strictly below this are "smooth" ([`StepHistogram::smooth_share`]).
pub const SMOOTH_BELOW: f64 = 3e-4;
/// Steps `s` strictly above this are "depth edges" ([`StepHistogram::edge_share`]): a jump of more than
/// 100 % of the nearer range.
pub const EDGE_ABOVE: f64 = 1.0;

/// Number of regular (0.25-decade) bins between underflow and overflow.
const REGULAR_BINS: usize = STEP_BINS - 2;

/// Which neighbouring pixels form a pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    /// `(r, c)` and `(r, (c + 1) % cols)`: neighbours in azimuth, wrapping from the last column to the
    /// first. An image with a single column has no such pair (a pixel is not its own neighbour); with two
    /// columns each pair occurs twice, as the definition says.
    AlongRow,
    /// `(r, c)` and `(r + 1, c)`: neighbouring beams, no wrap.
    AcrossRows,
}

impl Direction {
    /// Both directions.
    pub const ALL: [Direction; 2] = [Direction::AlongRow, Direction::AcrossRows];
}

/// Which rows a pair may come from: a pair counts only when **both** its pixels lie in the band's rows.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum RowBand {
    /// Every row.
    #[default]
    All,
    /// Rows `0..rows / 2` (the upper beams).
    Upper,
    /// Rows `rows / 2..rows` (the lower beams).
    Lower,
}

impl RowBand {
    /// The three bands.
    pub const ALL: [RowBand; 3] = [RowBand::All, RowBand::Upper, RowBand::Lower];

    /// The band's rows of an image with `rows` rows, as a half-open range. With
    /// [`Direction::AcrossRows`] the pair of rows `rows / 2 - 1` and `rows / 2` straddles the two halves
    /// and is in neither `Upper` nor `Lower` (but is in `All`).
    pub fn rows(self, rows: usize) -> std::ops::Range<usize> {
        match self {
            RowBand::All => 0..rows,
            RowBand::Upper => 0..rows / 2,
            RowBand::Lower => rows / 2..rows,
        }
    }
}

/// The relative range step `s = |r1 - r2| / min(r1, r2)` of two ranges (both expected finite and > 0).
#[inline]
pub fn relative_step(r1: f64, r2: f64) -> f64 {
    (r1 - r2).abs() / r1.min(r2)
}

/// A histogram of relative range steps `s` ([`relative_step`]) on the `log10` axis, plus the two counts
/// that are not bin-aligned ([`SMOOTH_BELOW`], [`EDGE_ABOVE`]), counted from the raw `s`.
///
/// Bins ([`STEP_BINS`] = 34):
/// * bin 0, underflow: `s < 1e-6` (exact zeros included), centre `-6.125`;
/// * bin `k` in `1..=32`: `-6 + (k - 1) / 4 <= log10(s) < -6 + k / 4`, the test done on `log10(s)` in
///   `f64` against those exact edges (as `numpy.histogram` does), centre `-6 + (k - 1) / 4 + 0.125`; a
///   value `s < 1e2` whose `log10` rounds to `2.0` stays in bin 32;
/// * bin 33, overflow: `s >= 1e2`, centre `2.125`.
///
/// Histograms add up: [`merge`](Self::merge) pools the pairs of a whole set. Serialises as
/// `{"counts": [34 integers], "smooth": n, "edge": n}`; deserialising checks the length and that
/// `smooth` and `edge` do not exceed the total.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "StepHistogramRepr")]
pub struct StepHistogram {
    counts: Vec<u64>,
    smooth: u64,
    edge: u64,
}

#[derive(serde::Deserialize)]
struct StepHistogramRepr {
    counts: Vec<u64>,
    smooth: u64,
    edge: u64,
}

impl TryFrom<StepHistogramRepr> for StepHistogram {
    type Error = String;

    fn try_from(r: StepHistogramRepr) -> std::result::Result<Self, String> {
        if r.counts.len() != STEP_BINS {
            return Err(format!(
                "step histogram: expected {STEP_BINS} counts, got {}",
                r.counts.len()
            ));
        }
        let total = r
            .counts
            .iter()
            .try_fold(0u64, |a, &c| a.checked_add(c))
            .ok_or("step histogram: total overflows u64")?;
        if r.smooth > total || r.edge > total {
            return Err(format!(
                "step histogram: smooth {} / edge {} exceed the total {total}",
                r.smooth, r.edge
            ));
        }
        Ok(StepHistogram {
            counts: r.counts,
            smooth: r.smooth,
            edge: r.edge,
        })
    }
}

impl Default for StepHistogram {
    fn default() -> Self {
        Self::new()
    }
}

impl StepHistogram {
    /// An empty histogram.
    pub fn new() -> Self {
        StepHistogram {
            counts: vec![0; STEP_BINS],
            smooth: 0,
            edge: 0,
        }
    }

    /// The bin of a step `s` (see the type's doc); `None` for NaN. Negative `s` goes to the underflow bin.
    pub fn bin_of(s: f64) -> Option<usize> {
        if s.is_nan() {
            None
        } else if s < UNDERFLOW_BELOW {
            Some(0)
        } else if s >= OVERFLOW_FROM {
            Some(STEP_BINS - 1)
        } else {
            let x = s.log10();
            let edge = |k: usize| LOG10_LOW + BIN_WIDTH_DECADES * k as f64; // exact
            let guess = ((x - LOG10_LOW) / BIN_WIDTH_DECADES).floor();
            let mut k = if guess > 0.0 {
                (guess as usize).min(REGULAR_BINS - 1)
            } else {
                0
            };
            // the guess may be one off where the subtraction rounded: settle it on the exact edges
            while k > 0 && x < edge(k) {
                k -= 1;
            }
            while k + 1 < REGULAR_BINS && x >= edge(k + 1) {
                k += 1;
            }
            Some(k + 1)
        }
    }

    /// The centre of bin `bin` on the `log10` axis: `-6.125`, `-5.875`, ..., `1.875`, `2.125`.
    pub fn bin_center(bin: usize) -> f64 {
        LOG10_LOW - BIN_WIDTH_DECADES / 2.0 + BIN_WIDTH_DECADES * bin as f64
    }

    /// Records one step `s`; a NaN is not recorded.
    pub fn add(&mut self, s: f64) {
        let Some(bin) = Self::bin_of(s) else { return };
        self.counts[bin] += 1;
        if s < SMOOTH_BELOW {
            self.smooth += 1;
        }
        if s > EDGE_ABOVE {
            self.edge += 1;
        }
    }

    /// Adds the counts of `other` to these (pools two sets of pairs).
    pub fn merge(&mut self, other: &StepHistogram) {
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
        self.smooth += other.smooth;
        self.edge += other.edge;
    }

    /// Records the pairs of one image in `direction` within `band` (both pixels valid and in `region`).
    ///
    /// Errors: `range_m` or `mask` not of `rows * cols` entries, or `region` not of `rows * cols`.
    pub fn add_image(
        &mut self,
        image: &RangeImage,
        region: Option<&[bool]>,
        direction: Direction,
        band: RowBand,
    ) -> Result<()> {
        check_image(image, "range image")?;
        check_region(region, image)?;
        let (rows, cols) = (image.rows as usize, image.cols as usize);
        let usable = |p: usize| is_valid(image, p) && region.is_none_or(|m| m[p]);
        let band_rows = band.rows(rows);
        match direction {
            Direction::AlongRow => {
                if cols < 2 {
                    return Ok(());
                }
                for r in band_rows {
                    for c in 0..cols {
                        let (p, q) = (r * cols + c, r * cols + (c + 1) % cols);
                        if usable(p) && usable(q) {
                            self.add(relative_step(range(image, p), range(image, q)));
                        }
                    }
                }
            }
            Direction::AcrossRows => {
                for r in band_rows.start..band_rows.end.saturating_sub(1) {
                    for c in 0..cols {
                        let (p, q) = (r * cols + c, (r + 1) * cols + c);
                        if usable(p) && usable(q) {
                            self.add(relative_step(range(image, p), range(image, q)));
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// The counts of the [`STEP_BINS`] bins.
    pub fn counts(&self) -> &[u64] {
        &self.counts
    }

    /// Number of pairs recorded.
    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// True when no pair was recorded.
    pub fn is_empty(&self) -> bool {
        self.total() == 0
    }

    /// Number of pairs with `s < 3e-4`.
    pub fn smooth_count(&self) -> u64 {
        self.smooth
    }

    /// Number of pairs with `s > 1`.
    pub fn edge_count(&self) -> u64 {
        self.edge
    }

    /// The counts divided by their total; every entry `NaN` when the histogram is empty.
    pub fn probabilities(&self) -> Vec<f64> {
        let n = self.total() as f64;
        self.counts.iter().map(|&c| c as f64 / n).collect()
    }

    /// Share of pairs with `s < 3e-4` ([`SMOOTH_BELOW`]), counted from the raw steps; `NaN` when empty.
    pub fn smooth_share(&self) -> f64 {
        self.smooth as f64 / self.total() as f64
    }

    /// Share of pairs with `s > 1` ([`EDGE_ABOVE`], "depth edges"), counted from the raw steps; `NaN` when
    /// empty.
    pub fn edge_share(&self) -> f64 {
        self.edge as f64 / self.total() as f64
    }
}

/// The step histogram of a set of images, pooled over the set: every pair of every image in `direction`
/// within `band`, both pixels valid and in `region` (one mask for all images).
///
/// Errors: an empty set ([`Error::Empty`]); an image whose `range_m` / `mask` is not `rows * cols` long or
/// whose shape differs from the first image's, or a `region` not of `rows * cols` ([`Error::ShapeMismatch`]).
/// A region that excludes every pair gives an empty histogram.
pub fn step_histogram(
    images: &[RangeImage],
    region: Option<&[bool]>,
    direction: Direction,
    band: RowBand,
) -> Result<StepHistogram> {
    check_set(images, region, "range image set")?;
    images
        .par_iter()
        .map(|img| {
            let mut h = StepHistogram::new();
            h.add_image(img, region, direction, band)?;
            Ok(h)
        })
        .try_reduce(StepHistogram::new, |mut a, b| {
            a.merge(&b);
            Ok(a)
        })
}

/// Texture distance: the 1-Wasserstein distance, in decades, between the normalised distributions of two
/// step histograms on the `log10(s)` axis, each bin a point mass at its centre
/// ([`StepHistogram::bin_center`]):
/// `W1 = sum_{k=0}^{32} |CDF_a(k) - CDF_b(k)| * (centre(k + 1) - centre(k))`, every spacing 0.25, with
/// `CDF(k)` = (sum of the counts of bins `0..=k`) / total (= `scipy.stats.wasserstein_distance` of the bin
/// centres weighted by the probabilities). `NaN` when either histogram is empty; `0` for equal
/// distributions; two single-bin histograms `k` bins apart are `0.25 k` apart.
pub fn texture_distance(a: &StepHistogram, b: &StepHistogram) -> f64 {
    let (na, nb) = (a.total(), b.total());
    if na == 0 || nb == 0 {
        return f64::NAN;
    }
    let (na, nb) = (na as f64, nb as f64);
    let (mut ca, mut cb) = (0u64, 0u64);
    let mut w = 0.0f64;
    for k in 0..STEP_BINS - 1 {
        ca += a.counts[k];
        cb += b.counts[k];
        let width = StepHistogram::bin_center(k + 1) - StepHistogram::bin_center(k);
        w += (ca as f64 / na - cb as f64 / nb).abs() * width;
    }
    w
}

/// The Jensen–Shannon **distance** (natural log, the square root of the divergence) between two step
/// histograms, exactly as `scipy.spatial.distance.jensenshannon(a.counts, b.counts)`
/// ([`crate::dist::jensen_shannon_distance`]): in `[0, sqrt(ln 2)]`. `NaN` when either is empty.
pub fn texture_jsd(a: &StepHistogram, b: &StepHistogram) -> f64 {
    if a.is_empty() || b.is_empty() {
        return f64::NAN;
    }
    let p: Vec<f64> = a.counts.iter().map(|&c| c as f64).collect();
    let q: Vec<f64> = b.counts.iter().map(|&c| c as f64).collect();
    crate::dist::jensen_shannon_distance(&p, &q).unwrap_or(f64::NAN)
}

/// Ray drop per row of a set of images: for each row `r`, (number of invalid pixels of row `r` in the
/// region, over all images) / (number of pixels of row `r` in the region, over all images), i.e. the mean
/// over images of each image's share. All pixels count without a region mask; a row with no pixel in the
/// region is `NaN`. One value per row.
///
/// Errors: as [`step_histogram`] (empty set, mismatched shapes or region).
pub fn raydrop_per_row(images: &[RangeImage], region: Option<&[bool]>) -> Result<Vec<f64>> {
    let (rows, cols) = check_set(images, region, "range image set")?;
    let mut invalid = vec![0u64; rows];
    let mut total = vec![0u64; rows];
    for img in images {
        for r in 0..rows {
            for c in 0..cols {
                let p = r * cols + c;
                if region.is_none_or(|m| m[p]) {
                    total[r] += 1;
                    if !is_valid(img, p) {
                        invalid[r] += 1;
                    }
                }
            }
        }
    }
    Ok(invalid
        .iter()
        .zip(&total)
        .map(|(&i, &t)| {
            if t == 0 {
                f64::NAN
            } else {
                i as f64 / t as f64
            }
        })
        .collect())
}

/// Mean over the rows whose shares are finite in both profiles of `|a[r] - b[r]|` (profiles from
/// [`raydrop_per_row`]); `NaN` when no row is finite in both.
///
/// Errors: profiles of different lengths ([`Error::ShapeMismatch`]).
pub fn raydrop_row_distance(a: &[f64], b: &[f64]) -> Result<f64> {
    if a.len() != b.len() {
        return Err(Error::ShapeMismatch {
            what: "ray-drop profile b".into(),
            expected: format!("{} rows", a.len()),
            got: format!("{} rows", b.len()),
        });
    }
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (&x, &y) in a.iter().zip(b) {
        if x.is_finite() && y.is_finite() {
            sum += (x - y).abs();
            n += 1;
        }
    }
    Ok(sum / n as f64)
}

/// Diversity of two scans: mean `|r_a - r_b|` in metres (ranges converted to `f64` first) over the pixels
/// valid in both and in `region`; `NaN` when there is none.
///
/// Errors: either image malformed, the two of different shapes, or `region` not of `rows * cols`.
pub fn pairwise_range_mae(a: &RangeImage, b: &RangeImage, region: Option<&[bool]>) -> Result<f64> {
    check_pair(a, b, region)?;
    let (mut sum, mut n) = (0.0f64, 0usize);
    for p in 0..num_pixels(a) {
        if region.is_none_or(|m| m[p]) && is_valid(a, p) && is_valid(b, p) {
            sum += (range(a, p) - range(b, p)).abs();
            n += 1;
        }
    }
    Ok(sum / n as f64)
}

/// Share of the pixels in `region` (all pixels without one) where exactly one of the two scans is valid;
/// `NaN` when the region holds no pixel.
///
/// Errors: as [`pairwise_range_mae`].
pub fn drop_disagreement(a: &RangeImage, b: &RangeImage, region: Option<&[bool]>) -> Result<f64> {
    check_pair(a, b, region)?;
    let (mut differ, mut n) = (0usize, 0usize);
    for p in 0..num_pixels(a) {
        if region.is_none_or(|m| m[p]) {
            n += 1;
            if is_valid(a, p) != is_valid(b, p) {
                differ += 1;
            }
        }
    }
    Ok(differ as f64 / n as f64)
}

/// Memorisation distance of two scans: the mean over **all** `rows * cols` pixels of `|e_a(p) - e_b(p)|`,
/// `e(p) = log2(1 + r(p))` for a valid pixel and `0` for an invalid one (so a drop against a return costs
/// `log2(1 + r)`). Errors: malformed or differently shaped images, or images of 0 pixels
/// ([`Error::Empty`]).
pub fn scan_distance(a: &RangeImage, b: &RangeImage) -> Result<f64> {
    check_pair(a, b, None)?;
    let n = num_pixels(a);
    if n == 0 {
        return Err(Error::empty("range image (0 pixels)"));
    }
    Ok(scan_distance_unchecked(a, b, n))
}

fn scan_distance_unchecked(a: &RangeImage, b: &RangeImage, n: usize) -> f64 {
    let e = |img: &RangeImage, p: usize| {
        if is_valid(img, p) {
            (1.0 + range(img, p)).log2()
        } else {
            0.0
        }
    };
    let sum: f64 = (0..n).map(|p| (e(a, p) - e(b, p)).abs()).sum();
    sum / n as f64
}

/// The scan of `pool` nearest to `query` by [`scan_distance`]: its index and the distance. Brute force,
/// parallel over the pool; exact ties go to the lowest index.
///
/// Errors: an empty pool or a query of 0 pixels ([`Error::Empty`]); a malformed image or a pool scan whose
/// shape differs from the query's ([`Error::ShapeMismatch`] naming the pool index).
pub fn nearest_scan(query: &RangeImage, pool: &[RangeImage]) -> Result<(usize, f64)> {
    if pool.is_empty() {
        return Err(Error::empty("nearest_scan pool"));
    }
    check_image(query, "query range image")?;
    let n = num_pixels(query);
    if n == 0 {
        return Err(Error::empty("query range image (0 pixels)"));
    }
    for (i, img) in pool.iter().enumerate() {
        check_same(query, img, &format!("pool range image {i}"))?;
    }
    let d: Vec<f64> = pool
        .par_iter()
        .map(|img| scan_distance_unchecked(query, img, n))
        .collect();
    let mut best = (0usize, d[0]);
    for (i, &x) in d.iter().enumerate().skip(1) {
        if x < best.1 {
            best = (i, x);
        }
    }
    Ok(best)
}

#[inline]
fn num_pixels(img: &RangeImage) -> usize {
    img.rows as usize * img.cols as usize
}

#[inline]
fn range(img: &RangeImage, p: usize) -> f64 {
    f64::from(img.range_m[p])
}

/// `mask[p] && range_m[p].is_finite() && range_m[p] > 0`.
#[inline]
fn is_valid(img: &RangeImage, p: usize) -> bool {
    let r = img.range_m[p];
    img.mask[p] && r.is_finite() && r > 0.0
}

/// `range_m` and `mask` both hold `rows * cols` entries.
fn check_image(img: &RangeImage, what: &str) -> Result<()> {
    let n = num_pixels(img);
    for (field, len) in [("range_m", img.range_m.len()), ("mask", img.mask.len())] {
        if len != n {
            return Err(Error::ShapeMismatch {
                what: format!("{what} {field}"),
                expected: format!("{n} entries ({} x {})", img.rows, img.cols),
                got: format!("{len} entries"),
            });
        }
    }
    Ok(())
}

/// `img` is well formed and of the shape of `reference` (assumed well formed).
fn check_same(reference: &RangeImage, img: &RangeImage, what: &str) -> Result<()> {
    if (img.rows, img.cols) != (reference.rows, reference.cols) {
        return Err(Error::ShapeMismatch {
            what: what.to_string(),
            expected: format!("{} x {}", reference.rows, reference.cols),
            got: format!("{} x {}", img.rows, img.cols),
        });
    }
    check_image(img, what)
}

fn check_region(region: Option<&[bool]>, img: &RangeImage) -> Result<()> {
    match region {
        Some(m) if m.len() != num_pixels(img) => Err(Error::ShapeMismatch {
            what: "region mask".into(),
            expected: format!("{} entries ({} x {})", num_pixels(img), img.rows, img.cols),
            got: format!("{} entries", m.len()),
        }),
        _ => Ok(()),
    }
}

fn check_pair(a: &RangeImage, b: &RangeImage, region: Option<&[bool]>) -> Result<()> {
    check_image(a, "range image a")?;
    check_same(a, b, "range image b")?;
    check_region(region, a)
}

/// A non-empty set of well-formed images of one shape, and a region of that shape; returns `(rows, cols)`.
fn check_set(images: &[RangeImage], region: Option<&[bool]>, what: &str) -> Result<(usize, usize)> {
    let Some(first) = images.first() else {
        return Err(Error::empty(what));
    };
    check_image(first, &format!("{what}: image 0"))?;
    for (i, img) in images.iter().enumerate().skip(1) {
        check_same(first, img, &format!("{what}: image {i}"))?;
    }
    check_region(region, first)?;
    Ok((first.rows as usize, first.cols as usize))
}

/// The texture figures of one scan against a reference scan on the same grid (what `veila demo`
/// prints): the depth-edge share of the upper half of the rows along rows (where facades and
/// vehicles stand against what lies behind them), the smooth share of the lower half (the ground
/// rings), and the [`texture_distance`] of all along-row steps to the reference's.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TextureSummary {
    /// [`StepHistogram::edge_share`] of the upper half, along rows, in percent.
    pub depth_edges_upper_pct: f64,
    /// [`StepHistogram::smooth_share`] of the lower half, along rows, in percent.
    pub smooth_lower_pct: f64,
    /// [`texture_distance`] of all along-row steps to the reference's (decades; 0 for the
    /// reference itself).
    pub w1_along_decades: f64,
}

impl TextureSummary {
    /// The figures of `scan` against `reference` (the same grid; an error otherwise).
    pub fn of(scan: &RangeImage, reference: &RangeImage) -> Result<Self> {
        let one = |img: &RangeImage, band: RowBand| {
            step_histogram(std::slice::from_ref(img), None, Direction::AlongRow, band)
        };
        let (all, reference_all) = (one(scan, RowBand::All)?, one(reference, RowBand::All)?);
        Ok(Self {
            depth_edges_upper_pct: 100.0 * one(scan, RowBand::Upper)?.edge_share(),
            smooth_lower_pct: 100.0 * one(scan, RowBand::Lower)?.smooth_share(),
            w1_along_decades: texture_distance(&all, &reference_all),
        })
    }
}
