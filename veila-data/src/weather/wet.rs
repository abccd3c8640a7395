//! Wet ground after the water-film model of Hahner et al. 2022 (`tools/wet_ground`, used by Robo3D).
//!
//! # Model
//! 1. Ground: the caller's mask, else SemanticKITTI road-like labels (road 40, parking 44, sidewalk 48,
//!    other-ground 49, lane marking 60), else a plane fit (RANSAC, then least squares on the inliers) on
//!    points near the expected road height; points within 0.25 m of the plane are ground. With too few
//!    candidate points the flat-earth plane `z = -sensor_height` is used (reported in the notes).
//! 2. Incidence angle `theta = acos(|n . p| / |p|)` (n the upward plane normal), clamped to 89 deg.
//! 3. Laser power: least squares of `I / cos(theta)` against range on ground points within [10, 70] m
//!    gives `P_out(d) = 15 (a d + b)`; reflectivity `rho = I / cos(theta) / P_out`.
//!    The noise threshold `(a' d + b')` is a line through the 5th percentile of ground intensity per
//!    2 m range bin, times the noise floor.
//! 4. Fresnel power coefficients (n_air = 1.0003, n_water = 1.33) through the film onto ground of
//!    reflectivity `rho` with multiple reflections: `T = T_aw rho T_wa / (1 - rho R_wa)` per
//!    polarisation, `t = max(T_p, T_s)`.
//! 5. Mix with the film fraction `f = clip(depth / 1.2 mm, 0, 1)`: `tw = (1 - f) rho + f t`,
//!    `I_new = clip(P_out cos(theta) tw, 0, I)` (intensity never rises); drop when
//!    `I_new <= f noise_floor (a' d + b') cos(theta)`.
//!
//! # Reference-implementation bugs avoided
//! * `tw = (1 - f) rho + f t / theta` divides by the angle in radians: we use `f t`.
//! * The plane-fit fallback normal `(0, 0, 1)` with `h = -1.55` has the wrong sign: our fallback is the
//!   plane `z = -sensor_height` with the upward normal, and the fitted normal is always made upward.
//! * `cos(theta) -> 0` at grazing incidence blows up `I / cos(theta)`: theta is clamped to 89 deg.
//! * The reference drops weak points even for a dry road; here the threshold scales with `f` (no drops
//!   at `f -> 0`), and the effect never runs for a dry road (the planner leaves it out).
//! * The reference picks the least-populated histogram bin as "minimum intensity": we use a percentile.
//! * Fewer than 1000 ground points made the reference a silent no-op: here the laser-power fit falls back
//!   to a constant (median) and the report says so.

use glam::{DVec3, Vec3};
use rand::Rng;
use serde::{Deserialize, Serialize};

use super::plan::{EffectRecord, LidarEffect};
use super::points::{LidarState, to_f32_intensity};
use super::rng;
use super::spec::Weather;
use crate::{Error, PointCloud, Result};

/// Refractive index of air.
pub const N_AIR: f64 = 1.0003;
/// Refractive index of water.
pub const N_WATER: f64 = 1.33;

/// Wet-ground knobs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct WetGroundConfig {
    /// Pavement texture depth (mm): a film this deep fully covers it.
    pub pavement_depth_mm: f64,
    /// Noise floor factor (Robo3D KITTI: 0.2).
    pub noise_floor: f64,
    /// Laser power factor of the reflectivity estimate (15 in the reference).
    pub power_factor: f64,
    /// Height of the LiDAR above the road (m), for the plane-fit search window and fallback plane.
    pub sensor_height_m: f64,
    /// Distance from the plane within which a point is ground (m).
    pub plane_tolerance_m: f64,
    /// Largest incidence angle used (deg).
    pub max_incidence_deg: f64,
}

impl Default for WetGroundConfig {
    fn default() -> Self {
        WetGroundConfig {
            pavement_depth_mm: 1.2,
            noise_floor: 0.2,
            power_factor: 15.0,
            sensor_height_m: 1.73,
            plane_tolerance_m: 0.25,
            max_incidence_deg: 89.0,
        }
    }
}

impl WetGroundConfig {
    pub(crate) fn validate(&self) -> Result<()> {
        let ok = self.pavement_depth_mm > 0.0
            && self.noise_floor >= 0.0
            && self.power_factor > 0.0
            && self.sensor_height_m.is_finite()
            && self.plane_tolerance_m > 0.0
            && (0.0..90.0).contains(&self.max_incidence_deg);
        if ok {
            Ok(())
        } else {
            Err(Error::Invalid {
                what: "wet ground config".into(),
                message: format!("{self:?}"),
            })
        }
    }
}

/// A plane `n . p + d = 0` with unit upward normal `n`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundPlane {
    /// Unit normal (z >= 0).
    pub normal: DVec3,
    /// Offset.
    pub d: f64,
}

impl GroundPlane {
    /// The flat-earth plane `z = -height`.
    pub fn flat(height_m: f64) -> Self {
        GroundPlane {
            normal: DVec3::Z,
            d: height_m,
        }
    }

    /// Signed distance of `p` above the plane.
    pub fn distance(&self, p: DVec3) -> f64 {
        self.normal.dot(p) + self.d
    }

    fn from_points(a: DVec3, b: DVec3, c: DVec3) -> Option<Self> {
        let n = (b - a).cross(c - a);
        let len = n.length();
        if !(len > 1e-9) {
            return None;
        }
        let mut n = n / len;
        if n.z < 0.0 {
            n = -n;
        }
        if n.z < 0.8 {
            return None; // steeper than ~37 deg: not a road
        }
        Some(GroundPlane {
            normal: n,
            d: -n.dot(a),
        })
    }
}

/// SemanticKITTI raw ids treated as road surface that can carry a water film.
pub const ROAD_LIKE_LABELS: [u32; 5] = [40, 44, 48, 49, 60];

/// Fit the ground plane: RANSAC (deterministic in `seed`) on points near the expected road height, then a
/// least-squares refit on the inliers. `None` when there are fewer than 50 candidates.
pub fn fit_ground_plane(xyz: &[Vec3], sensor_height_m: f64, seed: u64) -> Option<GroundPlane> {
    let h = sensor_height_m;
    let cand: Vec<DVec3> = xyz
        .iter()
        .map(|p| p.as_dvec3())
        .filter(|p| {
            p.is_finite()
                && p.x > 3.0
                && p.x < 70.0
                && p.y.abs() < 6.0
                && p.z > -h - 0.4 - 0.01 * p.x
                && p.z < -h + 0.4
        })
        .collect();
    if cand.len() < 50 {
        return None;
    }
    let mut rng = rng::stream(seed, 0x31, 0);
    let tol = 0.1;
    let mut best: Option<(usize, GroundPlane)> = None;
    for _ in 0..200 {
        let i = rng.random_range(0..cand.len());
        let j = rng.random_range(0..cand.len());
        let k = rng.random_range(0..cand.len());
        let Some(pl) = GroundPlane::from_points(cand[i], cand[j], cand[k]) else {
            continue;
        };
        let inl = cand.iter().filter(|p| pl.distance(**p).abs() < tol).count();
        if best.is_none_or(|(b, _)| inl > b) {
            best = Some((inl, pl));
        }
    }
    let (_, pl) = best?;
    // least squares z = a x + b y + c on the inliers
    let mut m = [[0.0f64; 3]; 3];
    let mut v = [0.0f64; 3];
    for p in cand.iter().filter(|p| pl.distance(**p).abs() < tol) {
        let row = [p.x, p.y, 1.0];
        for r in 0..3 {
            for c in 0..3 {
                m[r][c] += row[r] * row[c];
            }
            v[r] += row[r] * p.z;
        }
    }
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d0 = det(&m);
    if !(d0.abs() > 1e-9) {
        return Some(pl);
    }
    let mut sol = [0.0; 3];
    for c in 0..3 {
        let mut mc = m;
        for r in 0..3 {
            mc[r][c] = v[r];
        }
        sol[c] = det(&mc) / d0;
    }
    // z = a x + b y + c  <=>  (-a, -b, 1) . p - c = 0
    let n = DVec3::new(-sol[0], -sol[1], 1.0);
    let len = n.length();
    Some(GroundPlane {
        normal: n / len,
        d: -sol[2] / len,
    })
}

/// Fresnel power reflectance and transmittance `(R_s, R_p, T_s, T_p)` from medium `n1` into `n2` at
/// incidence `theta` (rad). Total internal reflection gives `(1, 1, 0, 0)`.
pub fn fresnel(n1: f64, n2: f64, theta: f64) -> (f64, f64, f64, f64) {
    let (si, ci) = theta.sin_cos();
    let st = si * n1 / n2;
    if st >= 1.0 {
        return (1.0, 1.0, 0.0, 0.0);
    }
    let ct = (1.0 - st * st).sqrt();
    let rs = (n1 * ci - n2 * ct) / (n1 * ci + n2 * ct);
    let ts = 2.0 * n1 * ci / (n1 * ci + n2 * ct);
    let rp = (n2 * ci - n1 * ct) / (n2 * ci + n1 * ct);
    let tp = 2.0 * n1 * ci / (n2 * ci + n1 * ct);
    let k = if ci > 0.0 { (n2 * ct) / (n1 * ci) } else { 0.0 };
    (rs * rs, rp * rp, ts * ts * k, tp * tp * k)
}

/// Effective reflectivity of ground of reflectivity `rho` under a water film at incidence `theta`:
/// `max` over polarisations of `T_aw rho T_wa / (1 - rho R_wa)`.
pub fn film_reflectivity(rho: f64, theta: f64) -> f64 {
    let rho = rho.clamp(0.05, 1.0);
    let (_, _, ts1, tp1) = fresnel(N_AIR, N_WATER, theta);
    let theta_w = (theta.sin() * N_AIR / N_WATER).clamp(-1.0, 1.0).asin();
    let (rs2, rp2, ts2, tp2) = fresnel(N_WATER, N_AIR, theta_w);
    let s = ts1 * rho * ts2 / (1.0 - rho * rs2);
    let p = tp1 * rho * tp2 / (1.0 - rho * rp2);
    s.max(p)
}

fn line_fit(xs: &[f64], ys: &[f64]) -> Option<(f64, f64)> {
    let n = xs.len() as f64;
    if xs.len() < 2 {
        return None;
    }
    let mx = xs.iter().sum::<f64>() / n;
    let my = ys.iter().sum::<f64>() / n;
    let sxx: f64 = xs.iter().map(|x| (x - mx) * (x - mx)).sum();
    let sxy: f64 = xs.iter().zip(ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    if !(sxx > 1e-12) {
        return None;
    }
    let a = sxy / sxx;
    Some((a, my - a * mx))
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    let k = ((v.len() - 1) as f64 * q).round() as usize;
    v[k]
}

/// Wet ground on the points of the ground mask (state indices = input indices: runs first).
pub(crate) fn apply_wet_ground(
    st: &mut LidarState,
    cloud: &PointCloud,
    mask_in: Option<&[bool]>,
    weather: &Weather,
    imax: f32,
    cfg: &WetGroundConfig,
) -> Result<EffectRecord> {
    let n = st.xyz.len();
    let mut rec = EffectRecord::new(LidarEffect::WetGround.name());
    // 1. ground mask and plane
    let plane_fit = fit_ground_plane(&st.xyz, cfg.sensor_height_m, weather.seed);
    let plane = match plane_fit {
        Some(p) => p,
        None => {
            rec = rec.note(format!(
                "too few points near the road for a plane fit: flat plane z = -{} m",
                cfg.sensor_height_m
            ));
            GroundPlane::flat(cfg.sensor_height_m)
        }
    };
    let mask: Vec<bool> = match (mask_in, cloud.label.as_ref()) {
        (Some(m), _) => {
            if m.len() != n {
                return Err(Error::Mismatch {
                    context: "wet ground".into(),
                    message: format!("{n} points but a ground mask of {}", m.len()),
                });
            }
            rec = rec.note("ground from the given mask");
            m.to_vec()
        }
        (None, Some(labels)) => {
            rec = rec.note("ground from SemanticKITTI labels (road, parking, sidewalk, other-ground, lane marking)");
            labels
                .iter()
                .map(|l| ROAD_LIKE_LABELS.contains(&(l & 0xFFFF)))
                .collect()
        }
        (None, None) => {
            rec = rec.note(format!(
                "ground from a plane fit (normal {:.4} {:.4} {:.4}, offset {:.3} m, tolerance {} m)",
                plane.normal.x, plane.normal.y, plane.normal.z, plane.d, cfg.plane_tolerance_m
            ));
            st.xyz
                .iter()
                .map(|p| plane.distance(p.as_dvec3()).abs() < cfg.plane_tolerance_m)
                .collect()
        }
    };
    // 2. incidence and power fits
    let max_theta = cfg.max_incidence_deg.to_radians();
    let incidence = |p: DVec3| -> f64 {
        let r = p.length();
        if !(r > 0.0) {
            return 0.0;
        }
        (plane.normal.dot(p).abs() / r)
            .clamp(-1.0, 1.0)
            .acos()
            .min(max_theta)
    };
    let ground: Vec<usize> = (0..n).filter(|&i| mask[i] && st.keep[i]).collect();
    let mut xs = Vec::new();
    let mut ys = Vec::new();
    for &i in &ground {
        let p = st.xyz[i].as_dvec3();
        let r = p.length();
        if (10.0..=70.0).contains(&r) {
            xs.push(r);
            ys.push(st.intensity[i] as f64 / incidence(p).cos());
        }
    }
    let power = match line_fit(&xs, &ys) {
        Some((a, b)) if xs.len() >= 200 && a.is_finite() && b.is_finite() => (a, b),
        _ => {
            let mut all: Vec<f64> = ground
                .iter()
                .map(|&i| st.intensity[i] as f64 / incidence(st.xyz[i].as_dvec3()).cos())
                .filter(|v| v.is_finite())
                .collect();
            let med = if all.is_empty() {
                imax as f64 * 0.1
            } else {
                percentile(&mut all, 0.5)
            };
            rec = rec.note(format!(
                "{} ground points within 10-70 m (< 200): constant laser power from the median",
                xs.len()
            ));
            (0.0, med)
        }
    };
    // noise threshold: 5th percentile of intensity per 2 m bin
    let mut bx = Vec::new();
    let mut by = Vec::new();
    for b in 0..30 {
        let (lo, hi) = (10.0 + 2.0 * b as f64, 12.0 + 2.0 * b as f64);
        let mut v: Vec<f64> = ground
            .iter()
            .filter_map(|&i| {
                let r = st.xyz[i].as_dvec3().length();
                (r >= lo && r < hi).then_some(st.intensity[i] as f64)
            })
            .collect();
        if v.len() >= 10 {
            bx.push(0.5 * (lo + hi));
            by.push(percentile(&mut v, 0.05));
        }
    }
    let noise = line_fit(&bx, &by).unwrap_or((0.0, by.iter().copied().fold(0.0, f64::min)));
    // 3. per point
    let f = (weather.water_depth_mm / cfg.pavement_depth_mm).clamp(0.0, 1.0);
    let (mut changed, mut dropped) = (0u64, 0u64);
    for &i in &ground {
        let p = st.xyz[i].as_dvec3();
        let r = p.length();
        let i0 = st.intensity[i] as f64;
        if !(r > 0.0 && r.is_finite() && i0 > 0.0) {
            continue;
        }
        let theta = incidence(p);
        let c = theta.cos();
        let p_out = (cfg.power_factor * (power.0 * r + power.1)).max(1e-12);
        let rho = i0 / c / p_out;
        let t = film_reflectivity(rho, theta);
        let tw = (1.0 - f) * rho + f * t;
        let i_new = (p_out * c * tw).clamp(0.0, i0);
        let thr = f * cfg.noise_floor * (noise.0 * r + noise.1).max(0.0) * c;
        if i_new <= thr {
            st.keep[i] = false;
            dropped += 1;
        } else {
            st.intensity[i] = to_f32_intensity(i_new, imax);
            changed += 1;
        }
    }
    Ok(rec
        .param("water_depth_mm", weather.water_depth_mm)
        .param("film_fraction", f)
        .param("plane_normal_z", plane.normal.z)
        .param("plane_offset_m", plane.d)
        .param("laser_power_slope", power.0)
        .param("laser_power_intercept", power.1)
        .count("ground_points", ground.len() as u64)
        .count("intensity_reduced", changed)
        .count("dropped", dropped))
}
