//! Ray tables: the unit direction of every range-image pixel centre (the paper's `Ray(u, v)`, the
//! inverse of equation 1), and unprojection of range images back to points.

use glam::Vec3;

use crate::{GeomError, LidarSensor, RangeImage};

/// Unit direction (LiDAR frame) of every pixel centre, row-major.
///
/// Uniform mode: the centre of row `r` is `v = r + 1/2` in equation 1; per-beam mode: the beam's own
/// elevation. Column `c`'s centre is `u = c + 1/2`. Every direction projects back to its own pixel
/// (tested).
#[derive(Debug, Clone, PartialEq)]
pub struct RayTable {
    rows: u32,
    cols: u32,
    dirs: Vec<Vec3>,
}

/// Points recovered from a range image.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Unprojected {
    /// Points in the LiDAR frame, metres.
    pub points: Vec<Vec3>,
    /// Intensity of each point.
    pub intensity: Vec<f32>,
    /// `(row, col)` each point came from.
    pub pixels: Vec<(u32, u32)>,
}

impl RayTable {
    /// Build the table for a sensor (validated first).
    pub fn new(sensor: &LidarSensor) -> Result<Self, GeomError> {
        sensor.validate()?;
        let mut dirs = Vec::with_capacity(sensor.num_pixels());
        let azimuths: Vec<(f64, f64)> = (0..sensor.cols)
            .map(|c| {
                let a = f64::from(sensor.col_azimuth_rad(c));
                (a.cos(), a.sin())
            })
            .collect();
        for r in 0..sensor.rows {
            let el = f64::from(sensor.row_elevation_rad(r));
            let (ce, se) = (el.cos(), el.sin());
            for &(ca, sa) in &azimuths {
                dirs.push(Vec3::new((ce * ca) as f32, (ce * sa) as f32, se as f32));
            }
        }
        Ok(RayTable {
            rows: sensor.rows,
            cols: sensor.cols,
            dirs,
        })
    }

    /// Height.
    pub fn rows(&self) -> u32 {
        self.rows
    }

    /// Width.
    pub fn cols(&self) -> u32 {
        self.cols
    }

    /// Unit direction of pixel `(row, col)`. Panics if out of bounds, like slice indexing.
    #[inline]
    pub fn dir(&self, row: u32, col: u32) -> Vec3 {
        self.dirs[row as usize * self.cols as usize + col as usize]
    }

    /// Unit direction of `(row, col)`, or `None` outside the image.
    pub fn try_dir(&self, row: u32, col: u32) -> Option<Vec3> {
        (row < self.rows && col < self.cols).then(|| self.dir(row, col))
    }

    /// All directions, row-major.
    pub fn dirs(&self) -> &[Vec3] {
        &self.dirs
    }

    /// Points of every valid pixel with a finite, positive range: `range_m * Ray(u, v)`.
    pub fn unproject(&self, image: &RangeImage) -> Result<Unprojected, GeomError> {
        image.validate()?;
        if image.rows != self.rows || image.cols != self.cols {
            return Err(GeomError::LengthMismatch {
                what: "range image pixels (rows x cols) against the ray table",
                expected: self.dirs.len(),
                got: image.num_pixels(),
            });
        }
        let mut out = Unprojected::default();
        for (k, dir) in self.dirs.iter().enumerate() {
            let r = image.range_m[k];
            if image.mask[k] && r.is_finite() && r > 0.0 {
                out.points.push(*dir * r);
                out.intensity.push(image.intensity[k]);
                out.pixels.push((
                    (k / self.cols as usize) as u32,
                    (k % self.cols as usize) as u32,
                ));
            }
        }
        Ok(out)
    }
}
