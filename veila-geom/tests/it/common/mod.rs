//! Helpers shared by the integration tests: real-data paths and loaders, and an independent
//! brute-force `f64` implementation of equation 1 (atan2 / asin in `f64`, floor, wrap).
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::Vec3;
use veila_geom::{BeamLayout, LidarSensor, RowSource};

/// `../shared/data/real` beside the workspace root.
pub fn real_data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real")
}

/// The path of a real-data file, or `None` (with the "skipping" message) when it is absent.
pub fn real_file(rel: &str) -> Option<PathBuf> {
    let p = real_data_dir().join(rel);
    if p.is_file() {
        Some(p)
    } else {
        println!("skipping: {} not found", p.display());
        None
    }
}

/// A KITTI velodyne scan: little-endian f32 x, y, z, reflectance.
pub fn read_kitti_bin(path: &Path) -> (Vec<Vec3>, Vec<f32>) {
    let bytes = std::fs::read(path).expect("readable scan");
    assert_eq!(
        bytes.len() % 16,
        0,
        "{}: not a multiple of 16 bytes",
        path.display()
    );
    let f = |c: &[u8], i: usize| {
        f32::from_le_bytes([c[4 * i], c[4 * i + 1], c[4 * i + 2], c[4 * i + 3]])
    };
    let pts = bytes
        .chunks_exact(16)
        .map(|c| Vec3::new(f(c, 0), f(c, 1), f(c, 2)))
        .collect();
    let refl = bytes.chunks_exact(16).map(|c| f(c, 3)).collect();
    (pts, refl)
}

/// Outcome of the reference for one point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RefOutcome {
    Pixel {
        row: u32,
        col: u32,
        range: f64,
        clamped: bool,
    },
    NonFinite,
    ZeroRange,
    TooNear,
    TooFar,
    AboveFov,
    BelowFov,
    BadRing,
}

/// Where the reference put a point, with the raw `u` and `v` (for judging boundary cases).
#[derive(Debug, Clone, Copy)]
pub struct RefPoint {
    pub outcome: RefOutcome,
    /// `u` of equation 1 before flooring (NaN when not computed).
    pub u: f64,
    /// `v` of equation 1 (uniform) before flooring; for per-beam the elevation in radians.
    pub v: f64,
}

/// Equation 1 in `f64`, written plainly: `u = 1/2 (1 - atan2(y, x) / pi) w`,
/// `v = (1 - (asin(z/d) - f_down) / f) h`, floor, `u` wrapped modulo `w`. The field of view is closed and
/// widened by `tol_rad`; `v = h` (bottom edge) belongs to the last row. Per-beam nearest mode picks
/// the beam with the nearest elevation; ring mode takes the ring.
pub fn reference_pixel(
    sensor: &LidarSensor,
    p: Vec3,
    ring: Option<u16>,
    tol_rad: f64,
    clamp: bool,
) -> RefPoint {
    let nan = RefPoint {
        outcome: RefOutcome::NonFinite,
        u: f64::NAN,
        v: f64::NAN,
    };
    if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
        return nan;
    }
    let (x, y, z) = (p.x as f64, p.y as f64, p.z as f64);
    let d = (x * x + y * y + z * z).sqrt();
    let mk = |o| RefPoint {
        outcome: o,
        u: f64::NAN,
        v: f64::NAN,
    };
    if d == 0.0 {
        return mk(RefOutcome::ZeroRange);
    }
    if d < sensor.min_range_m as f64 {
        return mk(RefOutcome::TooNear);
    }
    if d > sensor.max_range_m as f64 {
        return mk(RefOutcome::TooFar);
    }
    let (h, w) = (sensor.rows as f64, sensor.cols as f64);
    let up = (sensor.fov_up_deg as f64).to_radians();
    let down = (sensor.fov_down_deg as f64).to_radians();
    let el = (z / d).asin();
    let mut clamped = false;
    let mut edge_row = None;
    if el > up + tol_rad {
        if !clamp {
            return mk(RefOutcome::AboveFov);
        }
        clamped = true;
        edge_row = Some(0u32);
    } else if el < down - tol_rad {
        if !clamp {
            return mk(RefOutcome::BelowFov);
        }
        clamped = true;
        edge_row = Some(sensor.rows - 1);
    }
    let u = 0.5 * (1.0 - y.atan2(x) / std::f64::consts::PI) * w;
    let col = (u.floor() as i64).rem_euclid(sensor.cols as i64) as u32;
    let (row, v) = match &sensor.beams {
        BeamLayout::Uniform => {
            let v = (1.0 - (el - down) / (up - down)) * h;
            let row = edge_row.unwrap_or_else(|| (v.floor().max(0.0) as u32).min(sensor.rows - 1));
            (row, v)
        }
        BeamLayout::PerBeam {
            elevations_deg,
            row_source,
        } => match row_source {
            RowSource::Ring => match ring {
                Some(r) if (r as u32) < sensor.rows => {
                    // ring i is beam i; rows run top (highest elevation) to bottom
                    let increasing =
                        elevations_deg.len() > 1 && elevations_deg[1] > elevations_deg[0];
                    let row = if increasing {
                        sensor.rows - 1 - r as u32
                    } else {
                        r as u32
                    };
                    (row, el)
                }
                _ => return mk(RefOutcome::BadRing),
            },
            RowSource::NearestElevation => {
                let row = edge_row.unwrap_or_else(|| {
                    // brute force: the beam of nearest elevation, ties to the lower beam
                    let mut best = (f64::INFINITY, f64::INFINITY, 0usize);
                    for (i, e) in elevations_deg.iter().enumerate() {
                        let e = (*e as f64).to_radians();
                        let key = ((el - e).abs(), e);
                        if key.0 < best.0 || (key.0 == best.0 && key.1 < best.1) {
                            best = (key.0, key.1, i);
                        }
                    }
                    // row of beam best.2: rows sorted by decreasing elevation
                    elevations_deg
                        .iter()
                        .filter(|e| (**e as f64).to_radians() > best.1)
                        .count() as u32
                });
                (row, el)
            }
        },
    };
    RefPoint {
        outcome: RefOutcome::Pixel {
            row,
            col,
            range: d,
            clamped,
        },
        u,
        v,
    }
}

/// Nearest-wins image from the reference: pixel -> (range, point index), by sorting.
pub fn reference_image(outcomes: &[RefPoint], cols: u32) -> HashMap<usize, (f64, usize)> {
    let mut hits: Vec<(usize, f64, usize)> = outcomes
        .iter()
        .enumerate()
        .filter_map(|(i, r)| match r.outcome {
            RefOutcome::Pixel {
                row, col, range, ..
            } => Some((row as usize * cols as usize + col as usize, range, i)),
            _ => None,
        })
        .collect();
    hits.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut img = HashMap::new();
    for (k, r, i) in hits {
        img.entry(k).or_insert((r, i));
    }
    img
}

/// Reference rejection counts in the order of `veila_geom::Rejections`'s fields:
/// non_finite, zero_range, too_near, too_far, above_fov, below_fov, bad_ring.
pub fn reference_rejections(outcomes: &[RefPoint]) -> [usize; 7] {
    let mut c = [0usize; 7];
    for r in outcomes {
        let k = match r.outcome {
            RefOutcome::Pixel { .. } => continue,
            RefOutcome::NonFinite => 0,
            RefOutcome::ZeroRange => 1,
            RefOutcome::TooNear => 2,
            RefOutcome::TooFar => 3,
            RefOutcome::AboveFov => 4,
            RefOutcome::BelowFov => 5,
            RefOutcome::BadRing => 6,
        };
        c[k] += 1;
    }
    c
}

pub fn rejections_array(r: &veila_geom::Rejections) -> [usize; 7] {
    [
        r.non_finite,
        r.zero_range,
        r.too_near,
        r.too_far,
        r.above_fov,
        r.below_fov,
        r.bad_ring,
    ]
}

/// Distance of `x` to the nearest integer.
pub fn dist_to_integer(x: f64) -> f64 {
    (x - x.round()).abs()
}

/// A per-beam HDL-32E-like sensor with non-uniform spacing, rows by nearest elevation.
pub fn per_beam_nearest_sensor() -> LidarSensor {
    // denser near the horizon, like many real sensors; decreasing (ring 0 = top)
    let mut el: Vec<f32> = Vec::new();
    let mut e = 10.0f32;
    for i in 0..32 {
        el.push(e);
        e -= if i < 8 {
            2.0
        } else if i < 24 {
            0.8
        } else {
            1.6
        };
    }
    LidarSensor {
        rows: 32,
        cols: 1024,
        fov_up_deg: 11.0,
        fov_down_deg: el[31] - 1.0,
        min_range_m: 0.5,
        max_range_m: 120.0,
        beams: BeamLayout::PerBeam {
            elevations_deg: el,
            row_source: RowSource::NearestElevation,
        },
    }
}

/// KITTI object calibration: P2 (3x4), R0_rect (3x3), Tr_velo_to_cam (3x4), row-major `f64`.
pub struct KittiCalib {
    pub p2: [[f64; 4]; 3],
    pub r0: [[f64; 3]; 3],
    pub tr: [[f64; 4]; 3],
}

/// Parse `P2:`, `R0_rect:` and `Tr_velo_to_cam:` lines of a KITTI object calib file.
pub fn read_kitti_calib(path: &Path) -> KittiCalib {
    let text = std::fs::read_to_string(path).expect("readable calib");
    let row = |key: &str, n: usize| -> Vec<f64> {
        let line = text
            .lines()
            .find(|l| l.starts_with(key))
            .unwrap_or_else(|| panic!("{key} missing"));
        let v: Vec<f64> = line[key.len()..]
            .split_whitespace()
            .map(|t| t.parse().expect("number"))
            .collect();
        assert_eq!(v.len(), n, "{key}");
        v
    };
    let p = row("P2:", 12);
    let r = row("R0_rect:", 9);
    let t = row("Tr_velo_to_cam:", 12);
    let m34 = |v: &[f64]| {
        [
            [v[0], v[1], v[2], v[3]],
            [v[4], v[5], v[6], v[7]],
            [v[8], v[9], v[10], v[11]],
        ]
    };
    KittiCalib {
        p2: m34(&p),
        r0: [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]],
        tr: m34(&t),
    }
}

impl KittiCalib {
    pub fn p2_f32(&self) -> [[f32; 4]; 3] {
        self.p2.map(|r| r.map(|v| v as f32))
    }
    pub fn tr_f32(&self) -> [[f32; 4]; 3] {
        self.tr.map(|r| r.map(|v| v as f32))
    }
    pub fn r0_mat3(&self) -> glam::Mat3 {
        let r = self.r0.map(|r| r.map(|v| v as f32));
        glam::Mat3::from_cols_array_2d(&r).transpose()
    }

    /// Plain `f64` matrix math: `P2 * R0 * Tr * [x y z 1]` -> (u, v, w).
    pub fn project_f64(&self, p: Vec3) -> (f64, f64, f64) {
        let x = [p.x as f64, p.y as f64, p.z as f64, 1.0];
        let mut cam = [0.0f64; 3];
        for i in 0..3 {
            cam[i] = (0..4).map(|j| self.tr[i][j] * x[j]).sum();
        }
        let mut rect = [0.0f64; 4];
        for i in 0..3 {
            rect[i] = (0..3).map(|j| self.r0[i][j] * cam[j]).sum();
        }
        rect[3] = 1.0;
        let mut q = [0.0f64; 3];
        for i in 0..3 {
            q[i] = (0..4).map(|j| self.p2[i][j] * rect[j]).sum();
        }
        (q[0], q[1], q[2])
    }
}
