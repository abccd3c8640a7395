//! Spherical projection of point clouds into range images (equation 1 of the paper).
//!
//! ```text
//! u = 1/2 (1 - atan2(y, x) / pi) w          column = floor(u) mod w
//! v = (1 - (asin(z / d) + |f_down|) / f) h   row    = floor(v)
//! ```
//!
//! Rules, all deterministic:
//! - When several points land in one pixel the nearest wins; equal ranges go to the lower point index.
//! - Points with a non-finite coordinate or intensity, zero range, a range outside the sensor's valid
//!   interval or (per-beam ring mode) a missing or out-of-range ring are rejected and counted by
//!   reason in [`Rejections`]; they are never written.
//! - The vertical field of view is the closed interval `[f_down, f_up]` widened by
//!   [`ProjectionOptions::edge_tolerance_rad`] on both sides, so that a point on an edge (up to `f32`
//!   rounding of its coordinates) lands in the edge row. `v = h` exactly (the bottom edge) maps to row
//!   `h - 1`. Points beyond the tolerance are rejected as `above_fov` / `below_fov`, or clamped into the
//!   edge rows with [`OutOfFov::ClampToEdgeRows`] (the R2DM / LiDARGen behaviour).
//! - The azimuth seam: `atan2 = +pi` (`y = +0`, `x < 0`) gives `u = 0` and `atan2 = -pi` (`y = -0`)
//!   gives `u = w`, which wraps to column 0 too; both zeros land in column 0.
//!
//! [`AngleMethod::Exact`] decides every pixel with `f64` comparisons against precomputed boundary
//! directions (no rounding of angles at all), [`AngleMethod::Fast`] evaluates equation 1 with `f32`
//! polynomial `atan2` / `asin` and may put points that lie within about 1e-5 rad of a pixel boundary
//! into the neighbouring pixel. The benchmark prints both speeds and the number of such points.

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
            if got == n { Ok(()) } else { Err(GeomError::LengthMismatch { what, expected: n, got }) }
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

/// Projects point clouds for one sensor. Building it precomputes the boundary tables; reuse it.
#[derive(Debug, Clone)]
pub struct Projector {
    sensor: LidarSensor,
    opts: ProjectionOptions,
    /// sin of row boundaries, top to bottom, `rows + 1` entries (descending). Interior entries
    /// `1..rows` separate rows; entries 0 and `rows` are the field-of-view edges with tolerance.
    row_bound_sin: Vec<f64>,
    /// Directions (cos a_c, sin a_c) of the column boundaries a_c = pi (1 - 2c/w), c = 0..=w.
    col_bound_dir: Vec<(f64, f64)>,
    /// For the fast path: the uniform-row constants.
    fov_up_rad: f32,
    fov_rad: f32,
}

impl Projector {
    /// Validate the sensor and options and precompute the boundary tables.
    pub fn new(sensor: &LidarSensor, opts: ProjectionOptions) -> Result<Self, GeomError> {
        sensor.validate()?;
        if !(opts.edge_tolerance_rad.is_finite() && opts.edge_tolerance_rad >= 0.0) {
            return Err(GeomError::InvalidConfig {
                what: "projection options",
                message: format!("edge_tolerance_rad must be finite and >= 0, got {}", opts.edge_tolerance_rad),
            });
        }
        let h = sensor.rows as usize;
        let up = f64::from(sensor.fov_up_deg).to_radians();
        let down = f64::from(sensor.fov_down_deg).to_radians();
        let tol = f64::from(opts.edge_tolerance_rad);
        let mut row_bound = vec![0.0f64; h + 1];
        row_bound[0] = (up + tol).min(std::f64::consts::FRAC_PI_2);
        row_bound[h] = (down - tol).max(-std::f64::consts::FRAC_PI_2);
        match &sensor.beams {
            BeamLayout::Uniform => {
                for (r, b) in row_bound.iter_mut().enumerate().take(h).skip(1) {
                    *b = up - (r as f64) / (h as f64) * (up - down);
                }
            }
            BeamLayout::PerBeam { .. } => {
                // midpoints between consecutive beams, in row order (top to bottom)
                for r in 1..h {
                    let a = f64::from(sensor.row_elevation_rad(r as u32 - 1));
                    let b = f64::from(sensor.row_elevation_rad(r as u32));
                    row_bound[r] = 0.5 * (a + b);
                }
            }
        }
        let row_bound_sin = row_bound.iter().map(|b| b.sin()).collect();
        let w = sensor.cols as usize;
        let col_bound_dir = (0..=w)
            .map(|c| {
                let a = std::f64::consts::PI * (1.0 - 2.0 * c as f64 / w as f64);
                (a.cos(), a.sin())
            })
            .collect();
        Ok(Projector {
            sensor: sensor.clone(),
            opts,
            row_bound_sin,
            col_bound_dir,
            fov_up_rad: sensor.fov_up_rad(),
            fov_rad: sensor.fov_rad(),
        })
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
        if !p.is_finite() {
            return PixelOutcome::NonFinite;
        }
        let (x, y, z) = (f64::from(p.x), f64::from(p.y), f64::from(p.z));
        let d = (x * x + y * y + z * z).sqrt();
        if d == 0.0 {
            return PixelOutcome::ZeroRange;
        }
        if d < f64::from(self.sensor.min_range_m) {
            return PixelOutcome::TooNear;
        }
        if d > f64::from(self.sensor.max_range_m) {
            return PixelOutcome::TooFar;
        }
        let h = self.sensor.rows;
        let s = z / d;
        // field of view (with tolerance); clamping keeps the point in an edge row
        let mut clamped = false;
        let fov_row = if s > self.row_bound_sin[0] {
            match self.opts.out_of_fov {
                OutOfFov::Reject => return PixelOutcome::AboveFov,
                OutOfFov::ClampToEdgeRows => {
                    clamped = true;
                    Some(0)
                }
            }
        } else if s < self.row_bound_sin[h as usize] {
            match self.opts.out_of_fov {
                OutOfFov::Reject => return PixelOutcome::BelowFov,
                OutOfFov::ClampToEdgeRows => {
                    clamped = true;
                    Some(h - 1)
                }
            }
        } else {
            None
        };
        let row = match (&self.sensor.beams, fov_row) {
            (BeamLayout::PerBeam { row_source: RowSource::Ring, .. }, _) => {
                match ring.and_then(|r| self.sensor.row_of_ring(u32::from(r))) {
                    Some(row) => row,
                    None => return PixelOutcome::BadRing,
                }
            }
            (_, Some(row)) => row,
            (BeamLayout::PerBeam { .. }, None) => self.row_by_search(s),
            (BeamLayout::Uniform, None) => match self.opts.angles {
                AngleMethod::Exact => self.row_exact_uniform(z as f32, d as f32, s),
                AngleMethod::Fast => self.row_fast_uniform(p.z / d as f32),
            },
        };
        let col = match self.opts.angles {
            AngleMethod::Exact => self.col_exact(p.x, p.y, x, y),
            AngleMethod::Fast => self.col_fast(p.x, p.y),
        };
        PixelOutcome::Pixel { row, col, clamped, range_m: d as f32 }
    }

    /// The pixel of `p`, or `None` when the point would be rejected.
    pub fn try_pixel(&self, p: Vec3, ring: Option<u16>) -> Option<(u32, u32)> {
        match self.locate(p, ring) {
            PixelOutcome::Pixel { row, col, .. } => Some((row, col)),
            _ => None,
        }
    }

    /// Row = number of interior boundaries at or above the point's elevation (binary search).
    #[inline]
    fn row_by_search(&self, s: f64) -> u32 {
        let h = self.sensor.rows as usize;
        let interior = &self.row_bound_sin[1..h];
        // descending: count entries >= s
        interior.partition_point(|&b| b >= s) as u32
    }

    /// Uniform rows: candidate from an approximate asin, corrected with exact boundary tests.
    #[inline]
    fn row_exact_uniform(&self, z: f32, d: f32, s: f64) -> u32 {
        let h = self.sensor.rows as usize;
        let el = asin_approx((z / d).clamp(-1.0, 1.0));
        let v = (self.fov_up_rad - el) / self.fov_rad * h as f32;
        let mut r = (v.max(0.0) as usize).min(h - 1);
        // row r holds s with bound[r+1] < s <= bound[r] (interior bounds only; edges already checked)
        while r > 0 && s > self.row_bound_sin[r] {
            r -= 1;
        }
        while r + 1 < h && s <= self.row_bound_sin[r + 1] {
            r += 1;
        }
        r as u32
    }

    #[inline]
    fn row_fast_uniform(&self, s: f32) -> u32 {
        let h = self.sensor.rows;
        let el = asin_approx(s.clamp(-1.0, 1.0));
        let v = (self.fov_up_rad - el) / self.fov_rad * h as f32;
        (v.max(0.0) as u32).min(h - 1)
    }

    /// Exact column: approximate candidate, then boundary tests with f64 cross products.
    /// Column c holds azimuths in (a_{c+1}, a_c]; "az <= a_c" is `cross(b_c, p) <= 0` locally.
    #[inline]
    fn col_exact(&self, xf: f32, yf: f32, x: f64, y: f64) -> u32 {
        let w = self.sensor.cols as usize;
        let az = atan2_approx(yf, xf);
        let u = 0.5 * (1.0 - az * std::f32::consts::FRAC_1_PI) * w as f32;
        let mut c = (u.max(0.0) as usize).min(w - 1);
        let cross = |b: (f64, f64)| b.0 * y - b.1 * x;
        // at most a couple of steps: the approximation is within ~1e-5 rad
        for _ in 0..4 {
            if cross(self.col_bound_dir[c]) > 0.0 && c > 0 {
                c -= 1; // p is counter-clockwise of a_c: az > a_c
            } else if cross(self.col_bound_dir[c + 1]) <= 0.0 && c + 1 < w {
                c += 1; // az <= a_{c+1}
            } else {
                break;
            }
        }
        c as u32
    }

    #[inline]
    fn col_fast(&self, x: f32, y: f32) -> u32 {
        let w = self.sensor.cols;
        let az = atan2_approx(y, x);
        let u = 0.5 * (1.0 - az * std::f32::consts::FRAC_1_PI) * w as f32;
        let c = u.max(0.0) as u32;
        if c >= w { c - w } else { c }
    }

    /// Project a point cloud. `intensity` and `rings` must have one entry per point when given; rings
    /// are required by per-beam ring mode (points without one are rejected as `bad_ring`).
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
            return Err(GeomError::LengthMismatch { what: "intensity", expected: n, got: i.len() });
        }
        if let Some(r) = rings
            && r.len() != n
        {
            return Err(GeomError::LengthMismatch { what: "rings", expected: n, got: r.len() });
        }
        if n >= NO_POINT as usize {
            return Err(GeomError::InvalidConfig {
                what: "point cloud",
                message: format!("{n} points exceed the supported maximum of {}", NO_POINT - 1),
            });
        }
        let mut img = RangeImage::new_empty(self.sensor.rows, self.sensor.cols);
        let mut stats = ProjectionStats { input: n, ..Default::default() };
        let mut candidates = 0usize;
        for (i, &p) in points.iter().enumerate() {
            let inten = intensity.map_or(0.0, |v| v[i]);
            if !inten.is_finite() {
                stats.rejected.non_finite += 1;
                continue;
            }
            let outcome = self.locate(p, rings.map(|r| r[i]));
            let (row, col, range) = match outcome {
                PixelOutcome::Pixel { row, col, clamped, range_m } => {
                    stats.clamped += usize::from(clamped);
                    (row, col, range_m)
                }
                PixelOutcome::NonFinite => {
                    stats.rejected.non_finite += 1;
                    continue;
                }
                PixelOutcome::ZeroRange => {
                    stats.rejected.zero_range += 1;
                    continue;
                }
                PixelOutcome::TooNear => {
                    stats.rejected.too_near += 1;
                    continue;
                }
                PixelOutcome::TooFar => {
                    stats.rejected.too_far += 1;
                    continue;
                }
                PixelOutcome::AboveFov => {
                    stats.rejected.above_fov += 1;
                    continue;
                }
                PixelOutcome::BelowFov => {
                    stats.rejected.below_fov += 1;
                    continue;
                }
                PixelOutcome::BadRing => {
                    stats.rejected.bad_ring += 1;
                    continue;
                }
            };
            candidates += 1;
            let k = img.idx(row, col);
            // points arrive in increasing index order: only a strictly nearer point replaces
            if !img.mask[k] || range < img.range_m[k] {
                img.mask[k] = true;
                img.range_m[k] = range;
                img.intensity[k] = inten;
                img.point_index[k] = i as u32;
            }
        }
        stats.written = img.num_valid();
        stats.occluded = candidates - stats.written;
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
