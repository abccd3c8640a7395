//! Spherical projection of point clouds into range images (equation 1 of the paper).
//!
//! ```text
//! u = 1/2 (1 - atan2(y, x) / pi) w          column = floor(u) mod w
//! v = (1 - (asin(z / d) + |f_down|) / f) h   row    = floor(v)
//! ```
//!
//! Rules, all deterministic:
//! - When several points land in one pixel the nearest wins (squared ranges compared in `f64`, exact
//!   products of the `f32` coordinates); equal ranges go to the lower point index.
//! - Points with a non-finite coordinate or intensity, zero range, a range outside the sensor's valid
//!   interval or (per-beam ring mode) a missing or out-of-range ring are rejected and counted by
//!   reason in [`Rejections`]; they are never written.
//! - The vertical field of view is the closed interval `[f_down, f_up]` widened by
//!   [`ProjectionOptions::edge_tolerance_rad`] on both sides, so that a point on an edge (up to `f32`
//!   rounding of its coordinates) lands in the edge row. `v = h` exactly (the bottom edge) maps to row
//!   `h - 1`. Points beyond the tolerance are rejected as `above_fov` / `below_fov`, or clamped into the
//!   edge rows with [`OutOfFov::ClampToEdgeRows`] (the R2DM / LiDARGen behaviour). In ring mode the
//!   ring gives the row; the field-of-view test still applies.
//! - A point exactly on a boundary between two pixels belongs to the pixel of `floor(u)` / `floor(v)`:
//!   the column to its right / the row below it.
//! - The azimuth seam: `atan2 = +pi` (`y = +0`, `x < 0`) gives `u = 0` and `atan2 = -pi` (`y = -0`)
//!   gives `u = w`, which wraps to column 0 too; both zeros land in column 0. A point with `y` just
//!   below zero lands in column `w - 1`.
//!
//! [`AngleMethod::Exact`] decides every pixel exactly (see [`Projector`] for how: `f64` sign tests
//! against the boundaries, behind an `f32` filter that settles ~99 % of the points); it agrees with a
//! plain `f64` evaluation of equation 1 except within about `1e-15` rad of a boundary, where `f64`
//! itself cannot decide. [`AngleMethod::Fast`] evaluates equation 1 with the `f32` polynomial
//! `atan2` / `asin` of [`crate::fastmath`] (errors about 2e-6 and 1e-6 rad) and puts points that lie
//! within about that of a pixel boundary into either neighbour: 33 of KITTI 000000's 115,384 points.
//! The field-of-view decision is exact in both. The benchmark prints both speeds and that count.
//!
//! [`Projector::with_threads`] spreads the per-point work over threads; the result is bit-identical.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::fastmath::{asin_approx, atan2_approx};
use crate::{BeamLayout, GeomError, LidarSensor, RowSource};

/// Marker for an empty pixel in [`RangeImage::point_index`].
pub const NO_POINT: u32 = u32::MAX;

/// What to do with points above or below the vertical field of view.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutOfFov {
    /// Reject and count them (default).
    #[default]
    Reject,
    /// Put them into the top or bottom row, as R2DM and LiDARGen do; they are counted as `clamped`.
    ClampToEdgeRows,
}

/// How the angles of equation 1 are evaluated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AngleMethod {
    /// Exact pixel decisions (`f64` boundary tests); the reference.
    #[default]
    Exact,
    /// Polynomial `f32` `atan2`/`asin`; faster, may misplace points within ~1e-5 rad of a boundary.
    Fast,
}

/// Options of [`Projector`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProjectionOptions {
    /// Points outside the vertical field of view.
    pub out_of_fov: OutOfFov,
    /// Angle evaluation.
    pub angles: AngleMethod,
    /// Slack around the field-of-view edges, radians (default 1e-6, far below a pixel's height).
    pub edge_tolerance_rad: f32,
}

impl Default for ProjectionOptions {
    fn default() -> Self {
        ProjectionOptions {
            out_of_fov: OutOfFov::Reject,
            angles: AngleMethod::Exact,
            edge_tolerance_rad: 1e-6,
        }
    }
}

/// A range image: `rows x cols` pixels, row-major, row 0 the top beam.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeImage {
    /// Height (beams).
    pub rows: u32,
    /// Width (azimuth steps).
    pub cols: u32,
    /// Range (Euclidean distance from the sensor origin) in metres; 0 where the pixel is empty.
    pub range_m: Vec<f32>,
    /// Intensity of the winning point; 0 where empty.
    pub intensity: Vec<f32>,
    /// Index of the winning source point, [`NO_POINT`] where empty.
    pub point_index: Vec<u32>,
    /// True where the pixel holds a return.
    pub mask: Vec<bool>,
    /// Optional per-pixel label (for example a SemanticKITTI raw label), 0 where empty.
    pub label: Option<Vec<u32>>,
}

impl RangeImage {
    /// An image with every pixel empty.
    pub fn new_empty(rows: u32, cols: u32) -> Self {
        let n = rows as usize * cols as usize;
        RangeImage {
            rows,
            cols,
            range_m: vec![0.0; n],
            intensity: vec![0.0; n],
            point_index: vec![NO_POINT; n],
            mask: vec![false; n],
            label: None,
        }
    }

    /// An image of `range_m` alone (row-major, `rows * cols` values): a pixel holds a return where
    /// its range is finite and > 0; intensity 0, no source points, no labels. For range images
    /// that come from elsewhere than a projection (a decoder, a file, a test).
    pub fn try_from_range_m(rows: u32, cols: u32, range_m: Vec<f32>) -> Result<Self, GeomError> {
        let n = rows as usize * cols as usize;
        if range_m.len() != n {
            return Err(GeomError::LengthMismatch {
                what: "range_m",
                expected: n,
                got: range_m.len(),
            });
        }
        let mask: Vec<bool> = range_m.iter().map(|r| r.is_finite() && *r > 0.0).collect();
        let range_m = range_m
            .iter()
            .zip(&mask)
            .map(|(r, m)| if *m { *r } else { 0.0 })
            .collect();
        Ok(RangeImage {
            rows,
            cols,
            range_m,
            intensity: vec![0.0; n],
            point_index: vec![NO_POINT; n],
            mask,
            label: None,
        })
    }

    /// Flat index of `(row, col)`.
    #[inline]
    pub fn idx(&self, row: u32, col: u32) -> usize {
        row as usize * self.cols as usize + col as usize
    }

    /// Number of pixels.
    pub fn num_pixels(&self) -> usize {
        self.rows as usize * self.cols as usize
    }

    /// Number of pixels holding a return.
    pub fn num_valid(&self) -> usize {
        self.mask.iter().filter(|m| **m).count()
    }

    /// Check that every buffer has `rows * cols` entries.
    pub fn validate(&self) -> Result<(), GeomError> {
        let n = self.num_pixels();
        let check = |what, got| {
            if got == n {
                Ok(())
            } else {
                Err(GeomError::LengthMismatch {
                    what,
                    expected: n,
                    got,
                })
            }
        };
        check("range_m", self.range_m.len())?;
        check("intensity", self.intensity.len())?;
        check("point_index", self.point_index.len())?;
        check("mask", self.mask.len())?;
        if let Some(l) = &self.label {
            check("label", l.len())?;
        }
        Ok(())
    }

    /// Fill [`RangeImage::label`] from per-point labels through [`RangeImage::point_index`].
    pub fn gather_labels(&mut self, labels: &[u32]) -> Result<(), GeomError> {
        let mut out = vec![0u32; self.num_pixels()];
        for (o, &pi) in out.iter_mut().zip(&self.point_index) {
            if pi != NO_POINT {
                *o = *labels.get(pi as usize).ok_or(GeomError::LengthMismatch {
                    what: "labels",
                    expected: pi as usize + 1,
                    got: labels.len(),
                })?;
            }
        }
        self.label = Some(out);
        Ok(())
    }
}

/// Why points were not written, by reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rejections {
    /// A coordinate or the intensity was NaN or infinite.
    pub non_finite: usize,
    /// The point was exactly at the sensor origin.
    pub zero_range: usize,
    /// Range below the sensor's `min_range_m`.
    pub too_near: usize,
    /// Range above the sensor's `max_range_m`.
    pub too_far: usize,
    /// Above the vertical field of view.
    pub above_fov: usize,
    /// Below the vertical field of view.
    pub below_fov: usize,
    /// Ring mode: no ring given, or a ring outside `0..rows`.
    pub bad_ring: usize,
}

impl Rejections {
    /// Total number of rejected points.
    pub fn total(&self) -> usize {
        self.non_finite
            + self.zero_range
            + self.too_near
            + self.too_far
            + self.above_fov
            + self.below_fov
            + self.bad_ring
    }
}

/// What happened to the points of one projection. `input = written + occluded + rejected.total()`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ProjectionStats {
    /// Points given.
    pub input: usize,
    /// Pixels written (each by exactly one point).
    pub written: usize,
    /// Points that landed in an occupied pixel and lost to a nearer (or equally near, lower-index) point.
    pub occluded: usize,
    /// Points outside the field of view that were clamped into an edge row (they are also counted in
    /// `written` or `occluded`).
    pub clamped: usize,
    /// Points rejected, by reason.
    pub rejected: Rejections,
}

/// Outcome of locating one point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PixelOutcome {
    /// The point's pixel; `clamped` when it came from outside the field of view.
    Pixel {
        /// Row.
        row: u32,
        /// Column.
        col: u32,
        /// Whether it was clamped into an edge row.
        clamped: bool,
        /// Range of the point (computed in `f64`, rounded to `f32`), metres.
        range_m: f32,
    },
    /// Rejected (the reason is counted in [`Rejections`]).
    NonFinite,
    /// At the origin.
    ZeroRange,
    /// Nearer than the valid range.
    TooNear,
    /// Farther than the valid range.
    TooFar,
    /// Above the field of view.
    AboveFov,
    /// Below the field of view.
    BelowFov,
    /// Missing or invalid ring.
    BadRing,
}

/// Per-point result of the locate kernel: a pixel index (with [`CLAMP_BIT`] when it was clamped into an
/// edge row) or one of the `CODE_*` rejection codes.
type Code = u64;
const CLAMP_BIT: Code = 1 << 62;
const CODE_NON_FINITE: Code = u64::MAX - 6;
const CODE_ZERO_RANGE: Code = u64::MAX - 5;
const CODE_TOO_NEAR: Code = u64::MAX - 4;
const CODE_TOO_FAR: Code = u64::MAX - 3;
const CODE_ABOVE_FOV: Code = u64::MAX - 2;
const CODE_BELOW_FOV: Code = u64::MAX - 1;
const CODE_BAD_RING: Code = u64::MAX;
/// Smallest rejection code; every code below it is a pixel.
const CODE_REJECT_MIN: Code = CODE_NON_FINITE;

/// Points per block of the two-pass kernel.
const BLOCK: usize = 128;

/// Bins of the row candidate table per row (the table maps `sin(elevation)` to a candidate row).
const ROW_TABLE_BINS_PER_ROW: usize = 64;

/// Points per thread below which [`Projector::project`] uses fewer threads.
const MIN_POINTS_PER_THREAD: usize = 16_384;

/// Bound on the error of [`atan2_approx`] used by the exact path's filter, radians. The measured
/// worst case is below 4e-6 (tests); the filter assumes five times that.
const ATAN2_ERR_BOUND: f64 = 2e-5;
/// Bound on the error of the `f32` elevation estimate `asin_approx(z / d)` for `|elevation| <= 64`
/// degrees, radians: `asin_approx` is within 2e-6 (tested), `z / d` in `f32` within 2e-7 relative
/// (times at most 2.3 for the slope of `asin`); the filter assumes about five times the sum.
const ELEV_ERR_BOUND: f64 = 2e-5;
/// The row filter is used when the whole field of view lies within this elevation (degrees).
const ROW_FILTER_MAX_ELEV_DEG: f32 = 64.0;

/// How rows are found (decided once in [`Projector::new`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum RowMode {
    /// Uniform rows, exact: filtered `f32` estimate of `v`, boundary tests near boundaries.
    UniformExact,
    /// Uniform rows, equation 1 with the polynomial `asin` (fast path).
    UniformFast,
    /// Per-beam, nearest beam elevation: boundary tests from a table candidate.
    Nearest,
    /// Per-beam, the point's ring.
    Ring,
}

/// Projects point clouds for one sensor. Building it precomputes the boundary tables; reuse it.
///
/// # How [`AngleMethod::Exact`] decides a pixel
///
/// Every decision is, in the end, a sign test in `f64`:
/// - rows: `z |z| <= sin(b) |sin(b)| (x^2 + y^2 + z^2)` against the row boundaries `b` (no `asin`, no
///   square root, no division; `x^2` etc. are exact for `f32` inputs);
/// - columns: the sign of the cross product of the column-boundary direction with `(x, y)`.
///
/// Boundary directions that an `f32` point can lie on exactly are represented exactly: the azimuths
/// that are multiples of 45 degrees (`(1, 0)`, `(1, 1)`, `(0, 1)`, ...) and the elevation 0. Every
/// other boundary is irrational, so no `f32` point lies on it; the `f64` rounding of the boundaries and
/// of the tests (a few `1e-16` relative) can only matter for points closer than about `1e-15` rad to a
/// boundary.
///
/// For speed, `u` and `v` of equation 1 are first estimated in `f32` with the polynomial `atan2` /
/// `asin` (vectorised over blocks of points). Where the estimate is farther from an integer than its
/// error bound (a few `1e-3` pixels at 64 x 1024, with a five-fold margin over the measured error),
/// its floor *is* the exact pixel; only the remaining ~1 % of points run the sign tests. The result is
/// the same as with the sign tests alone (tested against an independent `f64` implementation).
#[derive(Debug, Clone)]
pub struct Projector {
    sensor: LidarSensor,
    opts: ProjectionOptions,
    row_mode: RowMode,
    /// `sin(b) |sin(b)|` of the row boundaries `b`, top to bottom, `rows + 1` entries (descending).
    /// Interior entries `1..rows` separate rows; entries 0 and `rows` are the field-of-view edges
    /// widened by the edge tolerance.
    row_bound_sq: Vec<f64>,
    /// Candidate row for `sin(elevation)` in bins of `1 / row_table_inv_step` from `row_table_lo`.
    row_table: Vec<u32>,
    row_table_lo: f32,
    row_table_inv_step: f32,
    /// Directions of the column boundaries `a_c = pi (1 - 2c/w)`, `c = 0..=w` (not normalised: exact
    /// integer vectors at multiples of 45 degrees; entries 0 and `w` are both `(-1, 0)`).
    col_bound_dir: Vec<(f64, f64)>,
    /// Squared valid range interval, `f64`.
    min_range_sq: f64,
    max_range_sq: f64,
    /// Squared range interval of the filtered lane: the valid interval, narrowed so that the `f32`
    /// estimates are accurate (no `f32` overflow or subnormal).
    lane_min_sq: f64,
    lane_max_sq: f64,
    /// Error bounds of the `u` and `v` estimates, pixels (a filter is off when its bound is >= 0.25).
    col_delta: f32,
    row_delta: f32,
    /// Whether the filtered lane applies (uniform rows, field of view inside +-64 degrees).
    row_filter: bool,
    /// Uniform-row constants of the `v` estimate: `v = (fov_up - el) * v_scale`.
    fov_up_rad: f32,
    v_scale: f32,
    /// Threads used by [`Projector::project`] (1 = the calling thread only).
    threads: usize,
}

/// `x |x|`: a monotone function that compares like `x` and is exact on `f32` inputs in `f64`.
#[inline(always)]
fn signed_sq(x: f64) -> f64 {
    x * x.abs()
}

/// Direction `(cos a, sin a)` of `a = pi k / n` for `k` in `-n..=n`; exact (unnormalised integer
/// vectors) where `a` is a multiple of 45 degrees.
fn boundary_dir(k: i64, n: i64) -> (f64, f64) {
    if (4 * k) % n == 0 {
        match (4 * k) / n {
            4 | -4 => (-1.0, 0.0),
            3 => (-1.0, 1.0),
            2 => (0.0, 1.0),
            1 => (1.0, 1.0),
            0 => (1.0, 0.0),
            -1 => (1.0, -1.0),
            -2 => (0.0, -1.0),
            _ => (-1.0, -1.0), // -3
        }
    } else {
        let a = std::f64::consts::PI * (k as f64 / n as f64);
        (a.cos(), a.sin())
    }
}

/// Whether `0 <= x < 2^22` lies at least `delta` (< 0.5) away from every integer; false for NaN.
/// Branch-free (`x + 1.5 * 2^23 - 1.5 * 2^23` rounds to the nearest integer), so it vectorises.
#[inline(always)]
fn clear_of_integers(x: f32, delta: f32) -> bool {
    const MAGIC: f32 = 12_582_912.0;
    let nearest = (x + MAGIC) - MAGIC;
    (x - nearest).abs() >= delta
}

/// Nearest-wins buffers and counters of a range of points.
#[derive(Debug)]
struct Accumulator {
    best_d2: Vec<f64>,
    best_i: Vec<u32>,
    counts: [usize; 7],
    clamped: usize,
    candidates: usize,
}

impl Accumulator {
    /// Add point `i` (points arrive in increasing index order: only a strictly nearer point replaces).
    #[inline(always)]
    fn push(&mut self, i: usize, code: Code, d2: f64) {
        if code >= CODE_REJECT_MIN {
            self.counts[(code - CODE_REJECT_MIN) as usize] += 1;
        } else {
            self.clamped += usize::from(code & CLAMP_BIT != 0);
            self.push_pixel((code & !CLAMP_BIT) as usize, i, d2);
        }
    }

    /// Add point `i`, known to land in pixel `k` without clamping.
    #[inline(always)]
    fn push_pixel(&mut self, k: usize, i: usize, d2: f64) {
        self.candidates += 1;
        // written as selects: the outcome is unpredictable, a branch would stall
        let better = d2 < self.best_d2[k];
        self.best_d2[k] = if better { d2 } else { self.best_d2[k] };
        self.best_i[k] = if better { i as u32 } else { self.best_i[k] };
    }

    /// Merge the buffers of a later range of points: per pixel the lower squared range wins, and on
    /// a tie the lower index (ours, since all of `later`'s indices are higher).
    fn absorb(&mut self, later: Accumulator) {
        for ((d, i), (ld, li)) in self
            .best_d2
            .iter_mut()
            .zip(&mut self.best_i)
            .zip(later.best_d2.iter().zip(&later.best_i))
        {
            if *ld < *d {
                *d = *ld;
                *i = *li;
            }
        }
        for (c, lc) in self.counts.iter_mut().zip(later.counts) {
            *c += lc;
        }
        self.clamped += later.clamped;
        self.candidates += later.candidates;
    }
}

/// `2^23`: adding it to an integer-valued `0 <= x < 2^23` puts `x` into the low mantissa bits.
const MANTISSA_ONE: f32 = 8_388_608.0;

/// `floor(x)` for `0 <= x < 2^22` without a float-to-int conversion (vectorises); any value for
/// other inputs (they are never used).
#[inline(always)]
fn floor_small(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0;
    let nearest = (x + MAGIC) - MAGIC;
    if nearest > x { nearest - 1.0 } else { nearest }
}

/// The `f32` estimates of one point: squared range (`f64`, exact products), `sin(elevation)`, `u` and
/// (when the row mode uses it) `v` of equation 1.
#[derive(Debug, Clone, Copy, Default)]
struct Estimate {
    d2: f64,
    s: f32,
    u: f32,
    v: f32,
    /// The filter's verdict on `u` and `v` (see [`Projector::finish`]).
    clear: bool,
    /// The pixel `floor(v) w + col(u)` the filtered lane uses when `clear`.
    pixel: u32,
}

/// [`Estimate`]s of a block of points, structure of arrays (so the loop filling it vectorises).
#[derive(Debug)]
struct EstimateBlock {
    d2: [f64; BLOCK],
    s: [f32; BLOCK],
    u: [f32; BLOCK],
    v: [f32; BLOCK],
    clear: [bool; BLOCK],
    pixel: [u32; BLOCK],
}

impl EstimateBlock {
    fn new() -> Self {
        EstimateBlock {
            d2: [0.0; BLOCK],
            s: [0.0; BLOCK],
            u: [0.0; BLOCK],
            v: [0.0; BLOCK],
            clear: [false; BLOCK],
            pixel: [0; BLOCK],
        }
    }

    #[inline(always)]
    fn get(&self, j: usize) -> Estimate {
        Estimate {
            d2: self.d2[j],
            s: self.s[j],
            u: self.u[j],
            v: self.v[j],
            clear: self.clear[j],
            pixel: self.pixel[j],
        }
    }
}

impl Projector {
    /// Validate the sensor and options and precompute the boundary tables.
    pub fn new(sensor: &LidarSensor, opts: ProjectionOptions) -> Result<Self, GeomError> {
        sensor.validate()?;
        if !(opts.edge_tolerance_rad.is_finite() && opts.edge_tolerance_rad >= 0.0) {
            return Err(GeomError::InvalidConfig {
                what: "projection options",
                message: format!(
                    "edge_tolerance_rad must be finite and >= 0, got {}",
                    opts.edge_tolerance_rad
                ),
            });
        }
        let h = sensor.rows as usize;
        let up_deg = f64::from(sensor.fov_up_deg);
        let down_deg = f64::from(sensor.fov_down_deg);
        let tol = f64::from(opts.edge_tolerance_rad);
        let half_pi = std::f64::consts::FRAC_PI_2;
        // boundaries in degrees first, so that a boundary at exactly 0 deg stays exactly 0
        let mut row_bound = vec![0.0f64; h + 1];
        match &sensor.beams {
            BeamLayout::Uniform => {
                for (r, b) in row_bound.iter_mut().enumerate().take(h).skip(1) {
                    let deg = (up_deg * (h - r) as f64 + down_deg * r as f64) / h as f64;
                    *b = deg.to_radians();
                }
            }
            BeamLayout::PerBeam { elevations_deg, .. } => {
                // midpoints between consecutive beams, in row order (top to bottom)
                for r in 1..h {
                    let a = f64::from(elevations_deg[sensor.ring_of_row(r as u32 - 1) as usize]);
                    let b = f64::from(elevations_deg[sensor.ring_of_row(r as u32) as usize]);
                    row_bound[r] = (0.5 * (a + b)).to_radians();
                }
            }
        }
        row_bound[0] = (up_deg.to_radians() + tol).min(half_pi);
        row_bound[h] = (down_deg.to_radians() - tol).max(-half_pi);
        let row_bound_sin: Vec<f64> = row_bound
            .iter()
            .map(|b| {
                if b.abs() == half_pi {
                    b.signum()
                } else {
                    b.sin()
                }
            })
            .collect();
        let row_bound_sq = row_bound_sin.iter().map(|s| signed_sq(*s)).collect();

        // candidate table over sin(elevation): the row of each bin's lower end
        let bins = (ROW_TABLE_BINS_PER_ROW * h).max(256);
        let (s_lo, s_hi) = (row_bound_sin[h], row_bound_sin[0]);
        let step = (s_hi - s_lo) / bins as f64;
        let interior = &row_bound_sin[1..h];
        let row_table = (0..bins)
            .map(|i| {
                let s = s_lo + step * i as f64;
                interior.partition_point(|&b| b >= s) as u32
            })
            .collect();

        let w = i64::from(sensor.cols);
        let col_bound_dir = (0..=w).map(|c| boundary_dir(w - 2 * c, w)).collect();

        let row_mode = match (&sensor.beams, opts.angles) {
            (
                BeamLayout::PerBeam {
                    row_source: RowSource::Ring,
                    ..
                },
                _,
            ) => RowMode::Ring,
            (
                BeamLayout::PerBeam {
                    row_source: RowSource::NearestElevation,
                    ..
                },
                _,
            ) => RowMode::Nearest,
            (BeamLayout::Uniform, AngleMethod::Exact) => RowMode::UniformExact,
            (BeamLayout::Uniform, AngleMethod::Fast) => RowMode::UniformFast,
        };
        // error bounds of the f32 estimates, in pixels (see ATAN2_ERR_BOUND / ELEV_ERR_BOUND); the
        // second terms bound the f32 rounding of the formula itself
        let (wf, hf) = (f64::from(sensor.cols), h as f64);
        let fov = f64::from(sensor.fov_up_deg - sensor.fov_down_deg).to_radians();
        let col_delta = wf * (ATAN2_ERR_BOUND / std::f64::consts::TAU + 4e-7);
        let row_delta = hf * (ELEV_ERR_BOUND / fov + 4e-7);
        let row_filter = matches!(row_mode, RowMode::UniformExact | RowMode::UniformFast)
            && sensor.num_pixels() < (1 << 23)
            && sensor.fov_up_deg.abs().max(sensor.fov_down_deg.abs()) <= ROW_FILTER_MAX_ELEV_DEG;
        let min_range_sq = f64::from(sensor.min_range_m) * f64::from(sensor.min_range_m);
        let max_range_sq = f64::from(sensor.max_range_m) * f64::from(sensor.max_range_m);
        Ok(Projector {
            sensor: sensor.clone(),
            opts,
            row_mode,
            row_bound_sq,
            row_table,
            row_table_lo: s_lo as f32,
            row_table_inv_step: (1.0 / step) as f32,
            col_bound_dir,
            min_range_sq,
            max_range_sq,
            lane_min_sq: min_range_sq.max(1e-20),
            lane_max_sq: max_range_sq.min(1e30),
            col_delta: col_delta as f32,
            row_delta: row_delta as f32,
            row_filter,
            fov_up_rad: sensor.fov_up_rad(),
            v_scale: (hf / fov) as f32,
            threads: 1,
        })
    }

    /// Use up to `threads` threads in [`Projector::project`] (clamped to at least 1; the default is 1).
    /// The result is bit-identical for every thread count: threads only locate points, and the
    /// nearest-wins merge runs once, in point order. Clouds smaller than about 16k points per thread
    /// are projected on fewer threads.
    #[must_use]
    pub fn with_threads(mut self, threads: usize) -> Self {
        self.threads = threads.max(1);
        self
    }

    /// The largest number of threads [`Projector::project`] uses.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// The sensor.
    pub fn sensor(&self) -> &LidarSensor {
        &self.sensor
    }

    /// The options.
    pub fn options(&self) -> &ProjectionOptions {
        &self.opts
    }

    /// Locate one point (with its ring, needed in ring mode). Never panics.
    pub fn locate(&self, p: Vec3, ring: Option<u16>) -> PixelOutcome {
        let (code, d2) = self.finish(p, 0.0, ring, self.estimate(p));
        match code {
            CODE_NON_FINITE => PixelOutcome::NonFinite,
            CODE_ZERO_RANGE => PixelOutcome::ZeroRange,
            CODE_TOO_NEAR => PixelOutcome::TooNear,
            CODE_TOO_FAR => PixelOutcome::TooFar,
            CODE_ABOVE_FOV => PixelOutcome::AboveFov,
            CODE_BELOW_FOV => PixelOutcome::BelowFov,
            CODE_BAD_RING => PixelOutcome::BadRing,
            _ => {
                let k = (code & !CLAMP_BIT) as usize;
                let w = self.sensor.cols as usize;
                PixelOutcome::Pixel {
                    row: (k / w) as u32,
                    col: (k % w) as u32,
                    clamped: code & CLAMP_BIT != 0,
                    range_m: d2.sqrt() as f32,
                }
            }
        }
    }

    /// The pixel of `p`, or `None` when the point would be rejected.
    pub fn try_pixel(&self, p: Vec3, ring: Option<u16>) -> Option<(u32, u32)> {
        match self.locate(p, ring) {
            PixelOutcome::Pixel { row, col, .. } => Some((row, col)),
            _ => None,
        }
    }

    /// The first pass of the kernel for one point (see [`Estimate`]): the block pass on a block of one,
    /// so that [`Projector::locate`] and [`Projector::project`] agree bit for bit.
    #[inline(always)]
    fn estimate(&self, p: Vec3) -> Estimate {
        let mut est = EstimateBlock::new();
        self.estimate_any(std::slice::from_ref(&p), &mut est);
        est.get(0)
    }

    /// [`Projector::estimate_any`] compiled for the widest vector unit the CPU has (AVX-512: 16 lanes,
    /// AVX2: 8, baseline SSE2: 4). Bit-identical on every path: the same IEEE operations in the same
    /// order (Rust never contracts `a * b + c` into an FMA), checked by a test against the baseline.
    #[inline(always)]
    fn estimate_dispatch(&self, block: &[Vec3], est: &mut EstimateBlock) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512vl")
            {
                // SAFETY: the CPU supports AVX-512F and AVX-512VL, checked just above.
                #[allow(unsafe_code)]
                unsafe {
                    self.estimate_any_avx512(block, est)
                };
                return;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU supports AVX2, checked just above.
                #[allow(unsafe_code)]
                unsafe {
                    self.estimate_any_avx2(block, est)
                };
                return;
            }
        }
        self.estimate_any(block, est);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,avx512f,avx512vl")]
    fn estimate_any_avx512(&self, block: &[Vec3], est: &mut EstimateBlock) {
        self.estimate_any(block, est);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn estimate_any_avx2(&self, block: &[Vec3], est: &mut EstimateBlock) {
        self.estimate_any(block, est);
    }

    /// [`Projector::estimate_block`] for the row mode.
    #[inline(always)]
    fn estimate_any(&self, block: &[Vec3], est: &mut EstimateBlock) {
        match self.row_mode {
            RowMode::UniformExact => self.estimate_block::<true, true>(block, est),
            RowMode::UniformFast => self.estimate_block::<true, false>(block, est),
            RowMode::Nearest | RowMode::Ring => self.estimate_block::<false, false>(block, est),
        }
    }

    /// [`Projector::estimate`] over a block, into structure-of-arrays form. The body is spelled out
    /// with every constant hoisted, so that the compiler vectorises it.
    #[inline(always)]
    fn estimate_block<const WITH_V: bool, const CLEAR_UV: bool>(
        &self,
        block: &[Vec3],
        out: &mut EstimateBlock,
    ) {
        let n = block.len().min(BLOCK);
        let (d2o, so, uo, vo, co, po) = (
            &mut out.d2[..n],
            &mut out.s[..n],
            &mut out.u[..n],
            &mut out.v[..n],
            &mut out.clear[..n],
            &mut out.pixel[..n],
        );
        let block = &block[..n];
        let w = self.sensor.cols as f32;
        let h = self.sensor.rows as f32;
        let (up, v_scale, dv, du) = (
            self.fov_up_rad,
            self.v_scale,
            self.row_delta,
            self.col_delta,
        );
        let row_filter = self.row_filter;
        let (lane_min, lane_max) = (self.lane_min_sq, self.lane_max_sq);
        for j in 0..n {
            let p = block[j];
            let (x, y, z) = (f64::from(p.x), f64::from(p.y), f64::from(p.z));
            // exact products (f32 * f32 fits in f64); one rounding per addition
            let d2 = x * x + y * y + z * z;
            let s = p.z / (d2 as f32).sqrt();
            let az = atan2_approx(p.y, p.x);
            let u = 0.5 * (1.0 - az * std::f32::consts::FRAC_1_PI) * w;
            d2o[j] = d2;
            so[j] = s;
            uo[j] = u;
            if WITH_V {
                let v = (up - asin_approx(s.clamp(-1.0, 1.0))) * v_scale;
                let mut clear = (v >= dv) & (v <= h - dv);
                if CLEAR_UV {
                    clear = clear
                        & clear_of_integers(v, dv)
                        & (u >= du)
                        & (u <= w - du)
                        & clear_of_integers(u, du);
                }
                // the pixel in f32 arithmetic (exact: the filter is off for images of 2^23 pixels
                // or more), read out of the mantissa: no float-to-int conversion, so it vectorises
                let c = floor_small(u);
                let c = if c >= w { c - w } else { c }; // fast path: u = w wraps to column 0
                let pixel = floor_small(v) * w + c;
                vo[j] = v;
                // in the valid range (so finite), and where the f32 estimates are accurate
                co[j] = clear & row_filter & (d2 >= lane_min) & (d2 <= lane_max);
                po[j] = (pixel + MANTISSA_ONE).to_bits() & 0x007F_FFFF;
            } else {
                vo[j] = 0.0;
                co[j] = false;
                po[j] = 0;
            }
        }
    }

    /// The second pass of the kernel: rejections and the pixel.
    #[inline(always)]
    fn finish(&self, p: Vec3, intensity: f32, ring: Option<u16>, e: Estimate) -> (Code, f64) {
        let d2 = e.d2;
        // the filtered lane: in range (so finite), estimates clear of every boundary by more than
        // their error bound, so their floors are the exact pixel (fast path: the row is inside the
        // field of view and equation 1's estimate is the answer)
        if e.clear && intensity.is_finite() {
            return (Code::from(e.pixel), d2);
        }
        self.finish_slow(p, intensity, ring, e)
    }

    /// The kernel without the filter: every test spelled out.
    #[inline(never)]
    fn finish_slow(&self, p: Vec3, intensity: f32, ring: Option<u16>, e: Estimate) -> (Code, f64) {
        let d2 = e.d2;
        if !(p.is_finite() && intensity.is_finite()) {
            return (CODE_NON_FINITE, 0.0);
        }
        if d2 == 0.0 {
            return (CODE_ZERO_RANGE, d2);
        }
        if d2 < self.min_range_sq {
            return (CODE_TOO_NEAR, d2);
        }
        if d2 > self.max_range_sq {
            return (CODE_TOO_FAR, d2);
        }
        let h = self.sensor.rows as usize;
        let zz = signed_sq(f64::from(p.z));
        let mut clamp_bit = 0;
        let mut edge_row = None;
        if zz > self.row_bound_sq[0] * d2 {
            if self.opts.out_of_fov == OutOfFov::Reject {
                return (CODE_ABOVE_FOV, d2);
            }
            clamp_bit = CLAMP_BIT;
            edge_row = Some(0);
        } else if zz < self.row_bound_sq[h] * d2 {
            if self.opts.out_of_fov == OutOfFov::Reject {
                return (CODE_BELOW_FOV, d2);
            }
            clamp_bit = CLAMP_BIT;
            edge_row = Some(h - 1);
        }
        let row = match (self.row_mode, edge_row) {
            (RowMode::Ring, _) => match ring.and_then(|r| self.sensor.row_of_ring(u32::from(r))) {
                Some(row) => row as usize,
                None => return (CODE_BAD_RING, d2),
            },
            (_, Some(row)) => row,
            (RowMode::UniformFast, None) => (e.v.max(0.0) as usize).min(h - 1),
            (RowMode::UniformExact | RowMode::Nearest, None) => self.row_exact(e.s, zz, d2),
        };
        let col = match self.opts.angles {
            AngleMethod::Exact => self.col_exact(e.u, p.x, p.y),
            AngleMethod::Fast => self.col_fast(e.u),
        };
        (
            (row * self.sensor.cols as usize + col) as Code | clamp_bit,
            d2,
        )
    }

    /// Exact row inside the field of view: a candidate from the table, then boundary tests.
    /// Row `r` holds `b[r+1] < s <= b[r]` (`s = sin(elevation)`), the bottom row `b[h] <= s <= b[h-1]`.
    #[inline(always)]
    fn row_exact(&self, s_estimate: f32, zz: f64, d2: f64) -> usize {
        let h = self.sensor.rows as usize;
        // saturating cast: NaN and negatives give bin 0; a poor candidate only costs steps
        let bin = ((s_estimate - self.row_table_lo) * self.row_table_inv_step) as usize;
        let mut r = self.row_table[bin.min(self.row_table.len() - 1)] as usize;
        while r > 0 && zz > self.row_bound_sq[r] * d2 {
            r -= 1;
        }
        while r + 1 < h && zz <= self.row_bound_sq[r + 1] * d2 {
            r += 1;
        }
        r
    }

    /// Exact column: the filtered estimate, else cross-product sign tests from it.
    ///
    /// Column `c` holds the azimuths `(a_{c+1}, a_c]`, i.e. the points clockwise of (or on) the
    /// boundary direction `b_c` and strictly counter-clockwise of `b_{c+1}`. For `w >= 3` every column
    /// spans less than `pi`, so the two half-plane tests identify the column exactly; the walk wraps
    /// around the seam. The seam `a_0 = pi = a_w + 2 pi` is the exact direction `(-1, 0)`: points on the
    /// negative x axis (`y = +0` or `y = -0`) land in column 0, as equation 1 with the wrap `u mod w`
    /// says.
    #[inline(always)]
    fn col_exact(&self, u: f32, xf: f32, yf: f32) -> usize {
        let w = self.sensor.cols as usize;
        let du = self.col_delta;
        if u >= du && u <= w as f32 - du && clear_of_integers(u, du) {
            return u as usize;
        }
        let (x, y) = (f64::from(xf), f64::from(yf));
        if w <= 2 {
            // column 0 holds (pi (1 - 2/w), pi], column 1 (if any) holds (-pi, 0]
            let in_upper = y > 0.0 || (y == 0.0 && x < 0.0);
            return if w == 1 || in_upper { 0 } else { 1 };
        }
        let mut c = self.col_fast(u);
        let cross = |b: (f64, f64)| b.0 * y - b.1 * x;
        // a step or none in practice; bounded by w for any input
        for _ in 0..w {
            if cross(self.col_bound_dir[c]) > 0.0 {
                c = if c == 0 { w - 1 } else { c - 1 }; // counter-clockwise of a_c
            } else if cross(self.col_bound_dir[c + 1]) <= 0.0 {
                c = if c + 1 == w { 0 } else { c + 1 }; // clockwise of (or on) a_{c+1}
            } else {
                break;
            }
        }
        c
    }

    /// Equation 1's column from the `u` estimate: `floor(u) mod w` (saturating: NaN gives 0).
    #[inline(always)]
    fn col_fast(&self, u: f32) -> usize {
        let w = self.sensor.cols as usize;
        let c = u.max(0.0) as usize; // u lies in [0, w] up to rounding; u = w wraps to column 0
        if c >= w { (c - w).min(w - 1) } else { c }
    }

    /// Locate `points` (global indices from `start`) and keep the nearest point of every pixel.
    fn accumulate(
        &self,
        points: &[Vec3],
        start: usize,
        intensity: Option<&[f32]>,
        rings: Option<&[u16]>,
    ) -> Accumulator {
        let np = self.sensor.num_pixels();
        let mut acc = Accumulator {
            best_d2: vec![f64::INFINITY; np],
            best_i: vec![NO_POINT; np],
            counts: [0; 7],
            clamped: 0,
            candidates: 0,
        };
        let mut est = EstimateBlock::new();
        for (b, block) in points.chunks(BLOCK).enumerate() {
            let start = start + b * BLOCK;
            self.estimate_dispatch(block, &mut est);
            for (j, &p) in block.iter().enumerate() {
                let i = start + j;
                let inten = intensity.map_or(0.0, |v| v[i]);
                // the filtered lane of `finish`, inlined: the pixel is known
                if est.clear[j] && inten.is_finite() {
                    acc.push_pixel(est.pixel[j] as usize, i, est.d2[j]);
                } else {
                    let (code, d2) = self.finish_slow(p, inten, rings.map(|r| r[i]), est.get(j));
                    acc.push(i, code, d2);
                }
            }
        }
        acc
    }

    /// Project a point cloud. `intensity` and `rings` must have one entry per point when given; rings
    /// are required by per-beam ring mode (points without one are rejected as `bad_ring`).
    ///
    /// Nearest wins: ranges are compared as squared `f64` ranges (exact products of the `f32`
    /// coordinates), and equal ranges go to the lower point index. The stored range is the `f64`
    /// range rounded to `f32`.
    pub fn project(
        &self,
        points: &[Vec3],
        intensity: Option<&[f32]>,
        rings: Option<&[u16]>,
    ) -> Result<(RangeImage, ProjectionStats), GeomError> {
        let n = points.len();
        if let Some(i) = intensity
            && i.len() != n
        {
            return Err(GeomError::LengthMismatch {
                what: "intensity",
                expected: n,
                got: i.len(),
            });
        }
        if let Some(r) = rings
            && r.len() != n
        {
            return Err(GeomError::LengthMismatch {
                what: "rings",
                expected: n,
                got: r.len(),
            });
        }
        if n >= NO_POINT as usize {
            return Err(GeomError::InvalidConfig {
                what: "point cloud",
                message: format!(
                    "{n} points exceed the supported maximum of {}",
                    NO_POINT - 1
                ),
            });
        }
        let np = self.sensor.num_pixels();
        let threads = self.threads.min(n / MIN_POINTS_PER_THREAD).max(1);
        let acc = if threads == 1 {
            self.accumulate(points, 0, intensity, rings)
        } else {
            // every thread projects a contiguous range of points into its own nearest-wins buffers;
            // the merge keeps, per pixel, the lowest squared range, then the lowest index: the
            // serial result, bit for bit
            let chunk = n.div_ceil(threads).next_multiple_of(BLOCK);
            let parts: Vec<Accumulator> = std::thread::scope(|s| {
                let handles: Vec<_> = (0..n.div_ceil(chunk))
                    .map(|t| {
                        let start = t * chunk;
                        let block = &points[start..(start + chunk).min(n)];
                        s.spawn(move || self.accumulate(block, start, intensity, rings))
                    })
                    .collect();
                handles
                    .into_iter()
                    .map(|h| h.join().expect("projection thread panicked"))
                    .collect()
            });
            let mut parts = parts.into_iter();
            let mut acc = parts.next().expect("at least one part");
            for part in parts {
                acc.absorb(part);
            }
            acc
        };
        let Accumulator {
            best_d2,
            best_i,
            counts,
            clamped,
            candidates,
        } = acc;
        let mut img = RangeImage::new_empty(self.sensor.rows, self.sensor.cols);
        for k in 0..np {
            let i = best_i[k];
            if i != NO_POINT {
                img.mask[k] = true;
                img.range_m[k] = best_d2[k].sqrt() as f32;
                img.intensity[k] = intensity.map_or(0.0, |v| v[i as usize]);
                img.point_index[k] = i;
            }
        }
        let [
            non_finite,
            zero_range,
            too_near,
            too_far,
            above_fov,
            below_fov,
            bad_ring,
        ] = counts;
        let written = img.num_valid();
        let stats = ProjectionStats {
            input: n,
            written,
            occluded: candidates - written,
            clamped,
            rejected: Rejections {
                non_finite,
                zero_range,
                too_near,
                too_far,
                above_fov,
                below_fov,
                bad_ring,
            },
        };
        Ok((img, stats))
    }
}

/// Project with default options (exact angles, rejecting out-of-view points).
pub fn project(
    sensor: &LidarSensor,
    points: &[Vec3],
    intensity: Option<&[f32]>,
) -> Result<(RangeImage, ProjectionStats), GeomError> {
    Projector::new(sensor, ProjectionOptions::default())?.project(points, intensity, None)
}

#[cfg(test)]
mod dispatch_tests {
    use super::*;

    /// Every vector path computes exactly what the baseline computes (the dispatch may only change
    /// the speed). Points: a spiral through every azimuth, elevations across and beyond the field of
    /// view, ranges from 0 to beyond the valid interval, and the special values.
    #[test]
    fn vector_paths_are_bit_identical_to_the_baseline() {
        let mut pts = Vec::new();
        for i in 0..BLOCK * 7 + 5 {
            let t = i as f32 * 0.0137;
            let r = (i % 97) as f32 * 1.31;
            pts.push(Vec3::new(
                r * t.cos(),
                r * t.sin(),
                (i % 23) as f32 * 0.4 - 5.0,
            ));
        }
        pts.extend([
            Vec3::ZERO,
            Vec3::new(-1.0, 0.0, 0.0),
            Vec3::new(-1.0, -0.0, 0.0),
            Vec3::new(f32::NAN, 1.0, 1.0),
            Vec3::new(f32::INFINITY, 1.0, 1.0),
            Vec3::new(1e-40, 1e-40, 1e-40),
            Vec3::new(1e6, -1e6, 1e6),
        ]);
        for sensor in [
            LidarSensor::hdl64e(),
            LidarSensor::hdl32e(),
            LidarSensor::hdl32e_per_beam(),
        ] {
            for angles in [AngleMethod::Exact, AngleMethod::Fast] {
                let opts = ProjectionOptions {
                    angles,
                    ..Default::default()
                };
                let p = Projector::new(&sensor, opts).unwrap();
                for block in pts.chunks(BLOCK) {
                    let mut base = EstimateBlock::new();
                    let mut fast = EstimateBlock::new();
                    p.estimate_any(block, &mut base);
                    p.estimate_dispatch(block, &mut fast);
                    for j in 0..block.len() {
                        let (a, b) = (base.get(j), fast.get(j));
                        assert_eq!(a.d2.to_bits(), b.d2.to_bits());
                        assert_eq!(a.s.to_bits(), b.s.to_bits());
                        assert_eq!(a.u.to_bits(), b.u.to_bits());
                        assert_eq!(a.v.to_bits(), b.v.to_bits());
                        assert_eq!((a.clear, a.pixel), (b.clear, b.pixel));
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod range_image_tests {
    use super::*;

    #[test]
    fn a_range_image_from_ranges_alone_marks_returns_where_the_range_is_finite_and_positive() {
        let r =
            RangeImage::try_from_range_m(1, 6, vec![5.0, 0.0, -1.0, f32::NAN, f32::INFINITY, 0.5])
                .unwrap();
        assert_eq!(r.mask, vec![true, false, false, false, false, true]);
        assert_eq!(r.range_m, vec![5.0, 0.0, 0.0, 0.0, 0.0, 0.5]);
        assert_eq!(r.intensity, vec![0.0; 6]);
        assert!(r.point_index.iter().all(|&p| p == NO_POINT));
        r.validate().unwrap();
        let err = RangeImage::try_from_range_m(2, 3, vec![1.0; 5]).unwrap_err();
        assert!(
            matches!(
                err,
                GeomError::LengthMismatch {
                    expected: 6,
                    got: 5,
                    ..
                }
            ),
            "{err}"
        );
    }
}
