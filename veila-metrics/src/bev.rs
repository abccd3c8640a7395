//! Bird's-eye-view (BEV) histograms of the R2DM / LiDARGen protocol.
//!
//! A scan is reduced to a `bins x bins` histogram of its `(x, y)` coordinates over
//! `[-half_extent_m, half_extent_m]^2`, keeping only points with `min_range_m < |p| < max_range_m` where `|p|`
//! is the **3-D Euclidean norm** (the range of the point, as in LiDARGen's `3 < r < 70` on range-image
//! depth and R2DM's `3 < ||xyz|| < 70`). Defaults ([`BevConfig::r2dm`]): 3 m, 70 m, 100 x 100 bins over
//! `[-80, 80]` m, i.e. 1.6 m cells.
//!
//! Bin edges follow `numpy.histogramdd(..., bins=100, range=[[-80, 80], [-80, 80]])` exactly: the edges are
//! `numpy.linspace(-80, 80, 101)` in `f64` (edge `k` is `k * 1.6 + (-80)`, the last edge exactly `80`), bins
//! are half-open `[e_k, e_{k+1})` except the last one, which is closed (`x == 80` lands in bin 99). Values
//! outside the range are dropped. Coordinates are promoted from `f32` to `f64` before binning and the norm
//! is computed in `f64`. (R2DM bins with `torch.histogramdd` in `f32`; the two can differ only for points
//! within one `f32` ulp of a bin edge or of the 3 m / 70 m radii.)
//!
//! Bin `(ix, iy)` is stored at `ix * bins + iy` (row-major `H[ix, iy]`, as numpy returns it).

use glam::Vec3;
use veila_geom::Region;

use crate::{Error, Result, check_finite};

/// Parameters of a BEV histogram.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BevConfig {
    /// Points with `|p| <= min_range_m` are dropped (strict `>`).
    pub min_range_m: f64,
    /// Points with `|p| >= max_range_m` are dropped (strict `<`).
    pub max_range_m: f64,
    /// Number of bins along x and along y.
    pub bins: usize,
    /// The histogram covers `[-half_extent_m, half_extent_m]` in x and in y.
    pub half_extent_m: f64,
}

impl Default for BevConfig {
    fn default() -> Self {
        Self::r2dm()
    }
}

impl BevConfig {
    /// The R2DM / LiDARGen protocol: `3 m < |p| < 70 m`, 100 x 100 bins over `[-80, 80]` m.
    pub const fn r2dm() -> Self {
        Self {
            min_range_m: 3.0,
            max_range_m: 70.0,
            bins: 100,
            half_extent_m: 80.0,
        }
    }

    /// Checks the configuration.
    pub fn validate(&self) -> Result<()> {
        if self.bins == 0 || self.bins > 65_535 {
            return Err(Error::InvalidParameter {
                name: "bins",
                reason: format!("{} not in 1..=65535", self.bins),
            });
        }
        if !(self.half_extent_m.is_finite() && self.half_extent_m > 0.0) {
            return Err(Error::InvalidParameter {
                name: "half_extent_m",
                reason: format!("{} must be finite and > 0", self.half_extent_m),
            });
        }
        if !(self.min_range_m >= 0.0 && self.min_range_m < self.max_range_m) {
            return Err(Error::InvalidParameter {
                name: "min_range_m",
                reason: format!(
                    "need 0 <= min_range_m < max_range_m, got {} and {}",
                    self.min_range_m, self.max_range_m
                ),
            });
        }
        Ok(())
    }

    /// The bin edges along one axis, exactly as `numpy.linspace(-h, h, bins + 1)`.
    pub fn edges(&self) -> Vec<f64> {
        linspace_edges(-self.half_extent_m, self.half_extent_m, self.bins)
    }

    /// Number of cells (`bins * bins`).
    pub fn num_cells(&self) -> usize {
        self.bins * self.bins
    }

    /// A human-readable description of the window, for error messages.
    pub fn window_description(&self) -> String {
        format!(
            "BEV ({} m < |p| < {} m, |x|,|y| <= {} m)",
            self.min_range_m, self.max_range_m, self.half_extent_m
        )
    }
}

/// `numpy.linspace(start, stop, bins + 1)` in `f64`, bit for bit.
pub(crate) fn linspace_edges(start: f64, stop: f64, bins: usize) -> Vec<f64> {
    let step = (stop - start) / bins as f64;
    let mut e: Vec<f64> = (0..=bins).map(|k| k as f64 * step + start).collect();
    e[bins] = stop;
    e
}

/// numpy's `searchsorted(edges, x, 'right') - 1` with the closed last bin; `None` when outside.
#[inline]
fn bin_of(edges: &[f64], x: f64) -> Option<usize> {
    let bins = edges.len() - 1;
    let (lo, hi) = (edges[0], edges[bins]);
    if !(x >= lo && x <= hi) {
        return None;
    }
    if x == hi {
        return Some(bins - 1);
    }
    let step = (hi - lo) / bins as f64;
    let mut k = (((x - lo) / step).floor() as isize).clamp(0, bins as isize - 1) as usize;
    // fix the estimate so that edges[k] <= x < edges[k + 1]
    while k + 1 < bins && edges[k + 1] <= x {
        k += 1;
    }
    while k > 0 && edges[k] > x {
        k -= 1;
    }
    Some(k)
}

/// A dense BEV histogram of one scan (raw counts).
#[derive(Debug, Clone, PartialEq)]
pub struct BevHistogram {
    /// Bins per axis.
    pub bins: usize,
    /// Counts at `ix * bins + iy`.
    pub counts: Vec<u32>,
    /// Sum of `counts`.
    pub total: u64,
}

/// A sparse BEV histogram: the non-zero cells only, sorted by cell index.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SparseBevHistogram {
    /// Bins per axis.
    pub bins: usize,
    /// Cell indices `ix * bins + iy`, strictly increasing.
    pub cells: Vec<u32>,
    /// Count of each cell in `cells` (all `> 0`).
    pub counts: Vec<u32>,
    /// Sum of `counts`.
    pub total: u64,
}

/// Read access shared by dense and sparse histograms, used by the distribution metrics.
pub trait Histogram: Sync {
    /// Number of cells (`bins * bins`).
    fn num_cells(&self) -> usize;
    /// Sum of all counts.
    fn total(&self) -> u64;
    /// Calls `f(cell, count)` for every non-zero cell in increasing cell order.
    fn for_each_nonzero(&self, f: impl FnMut(usize, u32));
}

impl Histogram for BevHistogram {
    fn num_cells(&self) -> usize {
        self.counts.len()
    }
    fn total(&self) -> u64 {
        self.total
    }
    fn for_each_nonzero(&self, mut f: impl FnMut(usize, u32)) {
        for (i, &c) in self.counts.iter().enumerate() {
            if c != 0 {
                f(i, c);
            }
        }
    }
}

impl Histogram for SparseBevHistogram {
    fn num_cells(&self) -> usize {
        self.bins * self.bins
    }
    fn total(&self) -> u64 {
        self.total
    }
    fn for_each_nonzero(&self, mut f: impl FnMut(usize, u32)) {
        for (&i, &c) in self.cells.iter().zip(&self.counts) {
            f(i as usize, c);
        }
    }
}

impl BevHistogram {
    /// An all-zero histogram.
    pub fn zeros(bins: usize) -> Self {
        Self {
            bins,
            counts: vec![0; bins * bins],
            total: 0,
        }
    }

    /// The sparse form of this histogram.
    pub fn to_sparse(&self) -> SparseBevHistogram {
        let mut s = SparseBevHistogram {
            bins: self.bins,
            total: self.total,
            ..Default::default()
        };
        self.for_each_nonzero(|i, c| {
            s.cells.push(i as u32);
            s.counts.push(c);
        });
        s
    }

    /// Counts divided by their sum (`None` for an empty histogram).
    pub fn normalized(&self) -> Option<Vec<f64>> {
        if self.total == 0 {
            return None;
        }
        let t = self.total as f64;
        Some(self.counts.iter().map(|&c| c as f64 / t).collect())
    }
}

impl SparseBevHistogram {
    /// The dense form of this histogram.
    pub fn to_dense(&self) -> BevHistogram {
        let mut d = BevHistogram::zeros(self.bins);
        for (&i, &c) in self.cells.iter().zip(&self.counts) {
            d.counts[i as usize] = c;
        }
        d.total = self.total;
        d
    }
}

/// The protocol's binning, shared by the dense and sparse histograms: calls `add(cell)` with the flat
/// cell index (`ix * bins + iy`) of every point of `region` inside the range window and the grid.
fn for_each_cell<P: Copy + Into<Vec3>>(
    points: &[P],
    cfg: &BevConfig,
    region: Region,
    what: &str,
    mut add: impl FnMut(usize),
) -> Result<()> {
    cfg.validate()?;
    let edges = cfg.edges();
    for (i, &p) in points.iter().enumerate() {
        let p: Vec3 = p.into();
        check_finite(p, what, i)?;
        if let Some(cell) = cell_of([p.x as f64, p.y as f64, p.z as f64], cfg, &edges, region) {
            add(cell);
        }
    }
    Ok(())
}

/// The cell of one finite point, `None` when it is outside `region`, the range window or the grid.
#[inline]
fn cell_of(p: [f64; 3], cfg: &BevConfig, edges: &[f64], region: Region) -> Option<usize> {
    let [x, y, z] = p;
    let inside = match region {
        Region::All => true,
        Region::Front => x > 0.0,
        Region::Rear => x <= 0.0,
    };
    if !inside {
        return None;
    }
    let r = (x * x + y * y + z * z).sqrt();
    if !(r > cfg.min_range_m && r < cfg.max_range_m) {
        return None;
    }
    match (bin_of(edges, x), bin_of(edges, y)) {
        (Some(ix), Some(iy)) => Some(ix * cfg.bins + iy),
        _ => None,
    }
}

fn sparse_from_cells(mut cells: Vec<u32>, bins: usize) -> SparseBevHistogram {
    cells.sort_unstable();
    let mut s = SparseBevHistogram {
        bins,
        total: cells.len() as u64,
        ..Default::default()
    };
    for c in cells {
        if s.cells.last() == Some(&c) {
            *s.counts.last_mut().expect("non-empty") += 1;
        } else {
            s.cells.push(c);
            s.counts.push(1);
        }
    }
    s
}

/// [`bev_histogram_sparse`] for `f64` points (e.g. the LiDARGen protocol's unprojected points, which the
/// peer bins in `float64`).
pub fn bev_histogram_sparse_f64(
    points: &[[f64; 3]],
    cfg: &BevConfig,
    region: Region,
    what: &str,
) -> Result<SparseBevHistogram> {
    cfg.validate()?;
    let edges = cfg.edges();
    let mut cells = Vec::new();
    for (i, &p) in points.iter().enumerate() {
        if !p.iter().all(|v| v.is_finite()) {
            return Err(Error::NonFinite {
                what: what.to_string(),
                index: i,
            });
        }
        if let Some(c) = cell_of(p, cfg, &edges, region) {
            cells.push(c as u32);
        }
    }
    Ok(sparse_from_cells(cells, cfg.bins))
}

/// Bins the points of one scan that lie in `region` (see the [module docs](self) for the exact rules).
///
/// Errors: invalid configuration, or a NaN / infinite coordinate ([`Error::NonFinite`], naming `what`).
/// A scan with no point inside the window gives an all-zero histogram (`total == 0`); the metrics decide
/// what that means.
pub fn bev_histogram<P: Copy + Into<Vec3>>(
    points: &[P],
    cfg: &BevConfig,
    region: Region,
    what: &str,
) -> Result<BevHistogram> {
    let mut h = BevHistogram::zeros(cfg.bins);
    for_each_cell(points, cfg, region, what, |cell| {
        h.counts[cell] += 1;
        h.total += 1;
    })?;
    Ok(h)
}

/// Like [`bev_histogram`] but returns the sparse form directly.
pub fn bev_histogram_sparse<P: Copy + Into<Vec3>>(
    points: &[P],
    cfg: &BevConfig,
    region: Region,
    what: &str,
) -> Result<SparseBevHistogram> {
    let mut cells: Vec<u32> = Vec::new();
    for_each_cell(points, cfg, region, what, |cell| cells.push(cell as u32))?;
    Ok(sparse_from_cells(cells, cfg.bins))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edges_match_linspace_ends() {
        let e = BevConfig::r2dm().edges();
        assert_eq!(e.len(), 101);
        assert_eq!(e[0], -80.0);
        assert_eq!(e[100], 80.0);
        assert_eq!(e[50], 50.0 * 1.6 - 80.0);
    }

    #[test]
    fn bin_rules() {
        let e = BevConfig::r2dm().edges();
        assert_eq!(bin_of(&e, -80.0), Some(0));
        assert_eq!(bin_of(&e, 80.0), Some(99));
        assert_eq!(bin_of(&e, 80.000001), None);
        assert_eq!(bin_of(&e, -80.000001), None);
        for k in 0..100 {
            assert_eq!(bin_of(&e, e[k]), Some(k), "edge {k}");
        }
        assert_eq!(bin_of(&e, f64::NAN), None);
    }
}
