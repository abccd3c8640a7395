//! Epipolar sample tables for GCMA (equations 7-8 of the paper).
//!
//! For every range pixel `(u, v)` and depths `d_1..d_K`, the sample `r_k = d_k Ray(u, v)` is projected
//! into the camera. The table stores the image coordinates normalised to `[-1, 1]` in the convention of
//! PyTorch's `grid_sample(align_corners=False)` (`x_n = (2 u_px + 1) / W - 1`, so `-1` is the left edge of
//! the first pixel and the same normalised coordinate addresses every feature-map resolution), the
//! validity `m_k` (in front of the near plane and inside the image) and the weight
//! `w_k = exp(-d_k / tau) m_k`. Tables depend only on sensor, camera and image size: build them once and
//! reuse them for every diffusion step.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::{GeomError, PinholeCamera, RayTable};

/// How the `K` sample depths are spaced between `near_m` and `far_m`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DepthSpacing {
    /// Evenly in depth.
    Uniform,
    /// Evenly in `ln d` (default: dense near the sensor where the image has most pixels per metre).
    #[default]
    Log,
    /// Evenly in `1 / d` (disparity).
    Inverse,
}

/// Configuration of an [`EpipolarTable`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EpipolarConfig {
    /// Samples per ray, `K`.
    pub num_samples: usize,
    /// Nearest sample depth along the ray, metres.
    pub near_m: f32,
    /// Farthest sample depth, metres.
    pub far_m: f32,
    /// Depth spacing.
    pub spacing: DepthSpacing,
    /// Decay length `tau` of the depth-aware weights, metres.
    pub tau_m: f32,
}

impl Default for EpipolarConfig {
    fn default() -> Self {
        EpipolarConfig {
            num_samples: 8,
            near_m: 2.0,
            far_m: 80.0,
            spacing: DepthSpacing::Log,
            tau_m: 40.0,
        }
    }
}

impl EpipolarConfig {
    /// Check the configuration.
    pub fn validate(&self) -> Result<(), GeomError> {
        let bad = |m: String| {
            Err(GeomError::InvalidConfig {
                what: "epipolar table",
                message: m,
            })
        };
        if self.num_samples == 0 || self.num_samples > 1024 {
            return bad(format!(
                "num_samples must be in 1..=1024, got {}",
                self.num_samples
            ));
        }
        if !(self.near_m.is_finite()
            && self.far_m.is_finite()
            && self.near_m > 0.0
            && self.far_m > self.near_m)
        {
            return bad(format!(
                "need 0 < near_m < far_m (finite), got {} and {}",
                self.near_m, self.far_m
            ));
        }
        if !(self.tau_m.is_finite() && self.tau_m > 0.0) {
            return bad(format!(
                "tau_m must be finite and positive, got {}",
                self.tau_m
            ));
        }
        Ok(())
    }

    /// The `K` sample depths, increasing. With `K = 1` the single depth is `near_m`.
    pub fn depths_m(&self) -> Vec<f32> {
        let k = self.num_samples;
        let (n, f) = (f64::from(self.near_m), f64::from(self.far_m));
        (0..k)
            .map(|i| {
                let t = if k == 1 {
                    0.0
                } else {
                    i as f64 / (k - 1) as f64
                };
                let d = match self.spacing {
                    DepthSpacing::Uniform => n + (f - n) * t,
                    DepthSpacing::Log => (n.ln() + (f.ln() - n.ln()) * t).exp(),
                    DepthSpacing::Inverse => 1.0 / (1.0 / n + (1.0 / f - 1.0 / n) * t),
                };
                d as f32
            })
            .collect()
    }
}

/// Precomputed epipolar samples for one (sensor, camera, image size).
#[derive(Debug, Clone, PartialEq)]
pub struct EpipolarTable {
    /// Range-image height.
    pub rows: u32,
    /// Range-image width.
    pub cols: u32,
    /// Sample depths `d_k`, metres.
    pub depths_m: Vec<f32>,
    /// Normalised image coordinates `[x_n, y_n]`, `rows * cols * K` entries (pixel-major, then `k`);
    /// invalid samples hold `[-2, -2]` (outside the image, finite).
    pub grid: Vec<[f32; 2]>,
    /// Validity `m_k` of each sample.
    pub valid: Vec<bool>,
    /// `w_k = exp(-d_k / tau) m_k` of each sample.
    pub weight: Vec<f32>,
    dirs: Vec<Vec3>,
}

/// Four-tap bilinear gather for one feature-map resolution (zero padding outside the map).
#[derive(Debug, Clone, PartialEq)]
pub struct BilinearGather {
    /// Feature-map height.
    pub feat_h: usize,
    /// Feature-map width.
    pub feat_w: usize,
    /// Flat indices `y * feat_w + x` of the four taps of each sample (0 where the weight is 0).
    pub indices: Vec<[u32; 4]>,
    /// Bilinear weights of the four taps; all zero for invalid samples and taps outside the map.
    pub weights: Vec<[f32; 4]>,
}

impl EpipolarTable {
    /// Build the table. Cost is `O(rows * cols * K)`; done once per camera.
    pub fn build(
        rays: &RayTable,
        camera: &PinholeCamera,
        cfg: &EpipolarConfig,
    ) -> Result<Self, GeomError> {
        cfg.validate()?;
        camera.validate()?;
        let depths_m = cfg.depths_m();
        let k = depths_m.len();
        let n = rays.dirs().len() * k;
        let mut grid = Vec::with_capacity(n);
        let mut valid = Vec::with_capacity(n);
        let mut weight = Vec::with_capacity(n);
        let decay: Vec<f32> = depths_m
            .iter()
            .map(|d| (-f64::from(*d) / f64::from(cfg.tau_m)).exp() as f32)
            .collect();
        let (w, h) = (camera.width as f32, camera.height as f32);
        for dir in rays.dirs() {
            for (d, dec) in depths_m.iter().zip(&decay) {
                match camera.try_project_in_image(*dir * *d) {
                    Some(ip) => {
                        grid.push([
                            (2.0 * ip.u_px + 1.0) / w - 1.0,
                            (2.0 * ip.v_px + 1.0) / h - 1.0,
                        ]);
                        valid.push(true);
                        weight.push(*dec);
                    }
                    None => {
                        grid.push([-2.0, -2.0]);
                        valid.push(false);
                        weight.push(0.0);
                    }
                }
            }
        }
        Ok(EpipolarTable {
            rows: rays.rows(),
            cols: rays.cols(),
            depths_m,
            grid,
            valid,
            weight,
            dirs: rays.dirs().to_vec(),
        })
    }

    /// Samples per pixel, `K`.
    pub fn num_samples(&self) -> usize {
        self.depths_m.len()
    }

    /// Flat index of sample `k` of pixel `(row, col)` into `grid`, `valid` and `weight`.
    #[inline]
    pub fn sample_idx(&self, row: u32, col: u32, k: usize) -> usize {
        (row as usize * self.cols as usize + col as usize) * self.num_samples() + k
    }

    /// The 3D sample `r_k = d_k Ray(u, v)` in the LiDAR frame.
    pub fn sample_point_lidar(&self, row: u32, col: u32, k: usize) -> Vec3 {
        self.dirs[row as usize * self.cols as usize + col as usize] * self.depths_m[k]
    }

    /// Per pixel: whether any sample is valid (the pixel's ray crosses the image within the depth range).
    pub fn any_valid_mask(&self) -> Vec<bool> {
        self.valid
            .chunks(self.num_samples())
            .map(|c| c.iter().any(|v| *v))
            .collect()
    }

    /// Bilinear taps of every sample on a `feat_h x feat_w` feature map (align_corners = false, zero
    /// padding). Computed once per resolution; the denoising loop then only gathers.
    pub fn bilinear_gather(&self, feat_h: usize, feat_w: usize) -> BilinearGather {
        let n = self.grid.len();
        let mut indices = Vec::with_capacity(n);
        let mut weights = Vec::with_capacity(n);
        for (g, ok) in self.grid.iter().zip(&self.valid) {
            if !*ok || feat_h == 0 || feat_w == 0 {
                indices.push([0; 4]);
                weights.push([0.0; 4]);
                continue;
            }
            let x = ((g[0] + 1.0) * feat_w as f32 - 1.0) * 0.5;
            let y = ((g[1] + 1.0) * feat_h as f32 - 1.0) * 0.5;
            let (x0, y0) = (x.floor(), y.floor());
            let (fx, fy) = (x - x0, y - y0);
            let taps = [
                (x0, y0, (1.0 - fx) * (1.0 - fy)),
                (x0 + 1.0, y0, fx * (1.0 - fy)),
                (x0, y0 + 1.0, (1.0 - fx) * fy),
                (x0 + 1.0, y0 + 1.0, fx * fy),
            ];
            let mut idx = [0u32; 4];
            let mut wts = [0.0f32; 4];
            for (t, (tx, ty, tw)) in taps.into_iter().enumerate() {
                if tx >= 0.0 && ty >= 0.0 && (tx as usize) < feat_w && (ty as usize) < feat_h {
                    idx[t] = (ty as usize * feat_w + tx as usize) as u32;
                    wts[t] = tw;
                }
            }
            indices.push(idx);
            weights.push(wts);
        }
        BilinearGather {
            feat_h,
            feat_w,
            indices,
            weights,
        }
    }
}
