//! The camera side: darkening, headlights, Koschmieder veil, rain streaks, snowflakes, sensor noise.
//!
//! Everything runs in linear light (sRGB decoded once, encoded and quantised to 8 bits once, last), in the
//! order illumination -> atmospheric veil -> particles -> noise -> encode.
//!
//! * **Veil** (Koschmieder): `I = J t + A (1 - t)`, `t = exp(-alpha l)` with the *total* extinction alpha
//!   and `l` the distance along the pixel ray, `l = z sqrt(((u - cx)/fx)^2 + ((v - cy)/fy)^2 + 1)` (not
//!   z). Sky pixels (`z = +inf`) get `t = 0`, pure airlight, computed without `0 * inf`. The airlight `A`
//!   is the configured colour or the Foggy-Cityscapes estimate: 15x15 dark channel, brightest 0.1 %,
//!   the one of median grey value; in the dark it is scaled by the ambient level.
//! * **Darken**: linear light times [`TimeOfDay::ambient_scale`](super::TimeOfDay::ambient_scale).
//! * **Headlights** (optional): `E = I0 max(cos phi, 0)^m / d^2` from a light at a fixed pose in the camera
//!   frame, zero above a low-beam cut-off, times the albedo (the clean linear image), added after
//!   darkening.
//! * **Rain streaks / snowflakes**: particles with the weather's size distribution (Marshall-Palmer /
//!   Gunn-Marshall, diameters >= 1 mm), uniform in the frustum volume between 0.5 and 8 m, each drawn as
//!   a motion-blurred streak of length `fy v T / z` (v = Atlas' drop speed or the snow terminal velocity,
//!   T the exposure) and width `fx D / z`; a pixel is covered for the fraction `w / L` of the exposure,
//!   so its value moves that far toward the particle radiance (the airlight: a drop refracts light from a
//!   wide field of view dominated by the sky). Deterministic in the seed.
//! * **Sensor noise** (dusk / night): heteroscedastic Gaussian, variance `sigma_s x + sigma_r` with
//!   `ln sigma_r = 2.18 ln sigma_s + 1.20` (Brooks et al. 2019 / MAET, mean relation), then a linear
//!   ADC quantisation (10 bits by default).
//!
//! An effect that needs the depth map or the intrinsics and lacks them is an error (never skipped).

use image::RgbImage;
use rand::Rng;
use rand_distr::{Distribution, Exp, StandardNormal};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::camera_config::CameraConfig;
use super::plan::{CameraEffect, EffectRecord, Plan};
use super::rng;
use super::spec::{Weather, marshall_gunn, marshall_palmer, snow_equivalent_rain_rate_mm_h};
use crate::{Error, Result};

/// Pinhole intrinsics (pixels; pixel centres at integer coordinates).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Focal length along u.
    pub fx: f64,
    /// Focal length along v.
    pub fy: f64,
    /// Principal point u.
    pub cx: f64,
    /// Principal point v.
    pub cy: f64,
}

impl Intrinsics {
    /// From a `veila_geom::PinholeCamera` (its `K`).
    pub fn from_camera(cam: &veila_geom::PinholeCamera) -> Self {
        let k = cam.intrinsics;
        Intrinsics {
            fx: k.x_axis.x as f64,
            fy: k.y_axis.y as f64,
            cx: k.z_axis.x as f64,
            cy: k.z_axis.y as f64,
        }
    }

    fn validate(&self) -> Result<()> {
        if [self.fx, self.fy].iter().all(|f| f.is_finite() && *f > 0.0)
            && self.cx.is_finite()
            && self.cy.is_finite()
        {
            Ok(())
        } else {
            Err(Error::Invalid {
                what: "camera intrinsics".into(),
                message: format!("{self:?}"),
            })
        }
    }

    /// Factor turning z depth into distance along the ray through pixel `(u, v)`.
    pub fn ray_factor(&self, u: f64, v: f64) -> f64 {
        let x = (u - self.cx) / self.fx;
        let y = (v - self.cy) / self.fy;
        (x * x + y * y + 1.0).sqrt()
    }
}

/// Per-pixel camera z depth, metres, row-major; `+inf` marks sky (infinitely far).
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// z depth per pixel (> 0, or +inf for sky).
    pub z_m: Vec<f32>,
}

impl DepthMap {
    /// Check the size and that every value is > 0 or +inf (NaN, 0 and negatives are errors).
    pub fn validate(&self, width: u32, height: u32) -> Result<()> {
        if self.width != width
            || self.height != height
            || self.z_m.len() != (width as usize) * (height as usize)
        {
            return Err(Error::Mismatch {
                context: "camera depth map".into(),
                message: format!(
                    "image is {width}x{height} but the depth map is {}x{} with {} values",
                    self.width,
                    self.height,
                    self.z_m.len()
                ),
            });
        }
        if let Some((i, z)) = self.z_m.iter().enumerate().find(|(_, z)| !(**z > 0.0)) {
            return Err(Error::Invalid {
                what: "camera depth map".into(),
                message: format!(
                    "pixel ({}, {}) has depth {z} (must be > 0, or +inf for sky)",
                    i % width as usize,
                    i / width as usize
                ),
            });
        }
        Ok(())
    }

    /// Densify sparse samples `(u_px, v_px, z_m)` (e.g. LiDAR points projected into the image): nearest
    /// sample per pixel, linear interpolation in 1/z along each image column between samples, the
    /// topmost sample extended upward and the lowest downward, columns without samples copied from the
    /// nearest column that has some, then a 9x9 box filter on 1/z (a transmission map must be smooth,
    /// as with Foggy Cityscapes' guided filter); with no sample at all, everything is sky (+inf).
    pub fn from_sparse(width: u32, height: u32, samples: &[(f32, f32, f32)]) -> Self {
        let (w, h) = (width as usize, height as usize);
        let mut sparse = vec![f32::INFINITY; w * h];
        for &(u, v, z) in samples {
            if !(z > 0.0 && z.is_finite() && u.is_finite() && v.is_finite()) {
                continue;
            }
            let (c, r) = ((u + 0.5).floor(), (v + 0.5).floor());
            if c < 0.0 || r < 0.0 || c >= w as f32 || r >= h as f32 {
                continue;
            }
            let k = r as usize * w + c as usize;
            sparse[k] = sparse[k].min(z);
        }
        let mut out = vec![f32::INFINITY; w * h];
        let mut has = vec![false; w];
        for c in 0..w {
            let rows: Vec<usize> = (0..h).filter(|&r| sparse[r * w + c].is_finite()).collect();
            if rows.is_empty() {
                continue;
            }
            has[c] = true;
            for r in 0..h {
                let z = match rows.binary_search(&r) {
                    Ok(i) => sparse[rows[i] * w + c],
                    Err(0) => sparse[rows[0] * w + c],
                    Err(i) if i == rows.len() => sparse[rows[i - 1] * w + c],
                    Err(i) => {
                        let (r0, r1) = (rows[i - 1], rows[i]);
                        let (z0, z1) = (sparse[r0 * w + c], sparse[r1 * w + c]);
                        let t = (r - r0) as f32 / (r1 - r0) as f32;
                        1.0 / ((1.0 - t) / z0 + t / z1)
                    }
                };
                out[r * w + c] = z;
            }
        }
        if let Some(first) = has.iter().position(|h| *h) {
            let mut last = first;
            for c in 0..w {
                if has[c] {
                    last = c;
                    continue;
                }
                let next = (c..w).find(|&k| has[k]);
                let src = match next {
                    Some(n) if c < first || (n - c) < (c - last) => n,
                    _ => last,
                };
                for r in 0..h {
                    out[r * w + c] = out[r * w + src];
                }
            }
        }
        // soften the column structure of the fill: box filter (radius 4 px) on inverse depth, so sky
        // (inverse depth 0) blends without infinities
        let rad = 4usize;
        let inv: Vec<f64> = out
            .iter()
            .map(|z| if z.is_finite() { 1.0 / *z as f64 } else { 0.0 })
            .collect();
        let mut tmp = vec![0f64; w * h];
        for r in 0..h {
            for c in 0..w {
                let (a, b) = (c.saturating_sub(rad), (c + rad).min(w - 1));
                tmp[r * w + c] =
                    inv[r * w + a..=r * w + b].iter().sum::<f64>() / (b - a + 1) as f64;
            }
        }
        for c in 0..w {
            for r in 0..h {
                let (a, b) = (r.saturating_sub(rad), (r + rad).min(h - 1));
                let m = (a..=b).map(|k| tmp[k * w + c]).sum::<f64>() / (b - a + 1) as f64;
                out[r * w + c] = if m > 0.0 {
                    (1.0 / m) as f32
                } else {
                    f32::INFINITY
                };
            }
        }
        DepthMap {
            width,
            height,
            z_m: out,
        }
    }
}

/// What the camera pipeline reads.
#[derive(Debug, Clone, Copy)]
pub struct CameraInput<'a> {
    /// The image (sRGB, 8 bits).
    pub image: &'a RgbImage,
    /// z depth per pixel (needed by the veil and the headlights).
    pub depth: Option<&'a DepthMap>,
    /// Intrinsics (needed by the veil, headlights and particles).
    pub intrinsics: Option<Intrinsics>,
}

/// A weather-processed image and what ran.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraOutput {
    /// The image.
    pub image: RgbImage,
    /// What each effect did.
    pub records: Vec<EffectRecord>,
}

/// sRGB decode of one 8-bit value.
pub fn srgb_to_linear(v: u8) -> f32 {
    crate::srgb::srgb_to_linear(v as f32 / 255.0)
}

/// sRGB encode of a linear value (clamped to [0, 1]; NaN -> 0) to 8 bits, rounding to nearest.
pub fn linear_to_srgb(x: f32) -> u8 {
    crate::srgb::linear_to_srgb_u8(x)
}

/// Airlight estimate (linear RGB): dark channel with a 15x15 minimum filter, the brightest 0.1 % of it,
/// and among those the pixel of median grey value.
pub fn estimate_airlight(lin: &[f32], width: usize, height: usize) -> [f32; 3] {
    if width == 0 || height == 0 {
        return [1.0; 3];
    }
    let dark: Vec<f32> = lin
        .chunks_exact(3)
        .map(|p| p[0].min(p[1]).min(p[2]))
        .collect();
    let rad = 7usize;
    let mut tmp = vec![0f32; width * height];
    for r in 0..height {
        for c in 0..width {
            let (a, b) = (c.saturating_sub(rad), (c + rad).min(width - 1));
            tmp[r * width + c] = dark[r * width + a..=r * width + b]
                .iter()
                .copied()
                .fold(f32::INFINITY, f32::min);
        }
    }
    let mut dc = vec![0f32; width * height];
    for r in 0..height {
        let (a, b) = (r.saturating_sub(rad), (r + rad).min(height - 1));
        for c in 0..width {
            dc[r * width + c] = (a..=b)
                .map(|k| tmp[k * width + c])
                .fold(f32::INFINITY, f32::min);
        }
    }
    let mut idx: Vec<usize> = (0..dc.len()).collect();
    let mut n = ((dc.len() as f64 * 0.001).ceil() as usize).max(1);
    if n.is_multiple_of(2) {
        n += 1;
    }
    let n = n.min(dc.len());
    let brighter = |x: &usize, y: &usize| dc[*y].total_cmp(&dc[*x]).then(x.cmp(y));
    if n < idx.len() {
        idx.select_nth_unstable_by(n - 1, brighter);
    }
    let mut top: Vec<usize> = idx.into_iter().take(n).collect();
    let grey = |i: usize| lin[3 * i] + lin[3 * i + 1] + lin[3 * i + 2];
    top.sort_by(|&x, &y| grey(x).total_cmp(&grey(y)).then(x.cmp(&y)));
    let m = top[top.len() / 2];
    [lin[3 * m], lin[3 * m + 1], lin[3 * m + 2]]
}

/// Atlas et al. 1973 terminal fall speed of a rain drop of diameter `d_mm` (m/s).
pub fn rain_drop_speed_m_s(d_mm: f64) -> f64 {
    (9.65 - 10.3 * (-0.6 * d_mm).exp()).max(0.0)
}

/// Draw one motion-blurred particle: from `(u, v)` along `(du, dv)` (unit) for `len` px, `width` px wide.
fn draw_streak(
    lin: &mut [f32],
    w: usize,
    h: usize,
    u: f64,
    v: f64,
    dir: (f64, f64),
    len: f64,
    width: f64,
    colour: [f32; 3],
) -> bool {
    let len = len.max(width).max(1.0);
    // fraction of the exposure a pixel on the path is covered, times sub-pixel area coverage
    let tau = (width.min(1.0) * (width.max(1.0) / len)).min(1.0) as f32;
    if !(tau > 0.0) {
        return false;
    }
    let half_w = (width * 0.5).max(0.5);
    let steps = len.ceil() as usize + 1;
    let (nx, ny) = (-dir.1, dir.0);
    let mut last = usize::MAX;
    let mut drew = false;
    for s in 0..steps {
        let t = s as f64 * len / (steps - 1).max(1) as f64;
        let (pu, pv) = (u + dir.0 * t, v + dir.1 * t);
        let across = half_w.ceil() as i64;
        for k in -across + 1..across {
            let (qu, qv) = (pu + nx * k as f64, pv + ny * k as f64);
            let (c, r) = ((qu + 0.5).floor(), (qv + 0.5).floor());
            if c < 0.0 || r < 0.0 || c >= w as f64 || r >= h as f64 {
                continue;
            }
            let i = r as usize * w + c as usize;
            if i == last {
                continue;
            }
            last = i;
            for ch in 0..3 {
                let x = &mut lin[3 * i + ch];
                *x += tau * (colour[ch] - *x);
            }
            drew = true;
        }
    }
    drew
}

/// Particle kinds for [`draw_particles`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Particles {
    Rain,
    Snow,
}

fn draw_particles(
    lin: &mut [f32],
    w: usize,
    h: usize,
    k: &Intrinsics,
    weather: &Weather,
    cfg: &CameraConfig,
    kind: Particles,
    colour: [f32; 3],
) -> Result<EffectRecord> {
    let (n0, lambda, speed_const, tag, name) = match kind {
        Particles::Rain => {
            let (n0, l) = marshall_palmer(weather.rain_rate_mm_h);
            (
                n0,
                l,
                None,
                rng::tag::CAMERA_RAIN,
                CameraEffect::RainStreaks.name(),
            )
        }
        Particles::Snow => {
            let r = snow_equivalent_rain_rate_mm_h(
                weather.snowfall_rate_mm_h,
                weather.snow_terminal_velocity_m_s,
            );
            let (n0, l) = marshall_gunn(r);
            (
                n0,
                l,
                Some(weather.snow_terminal_velocity_m_s),
                rng::tag::CAMERA_SNOW,
                CameraEffect::Snowflakes.name(),
            )
        }
    };
    let d_vis = 1.0; // mm
    let (z0, z1) = (0.5f64, 8.0f64);
    let per_m3 = n0 / lambda * (-lambda * d_vis).exp();
    let volume = (w as f64 / k.fx) * (h as f64 / k.fy) * (z1.powi(3) - z0.powi(3)) / 3.0;
    let expected = per_m3 * volume;
    let mut rng = rng::stream(weather.seed, tag, 0);
    let mut count = expected.floor() as usize;
    if rng.random::<f64>() < expected - count as f64 {
        count += 1;
    }
    let capped = count > cfg.max_particles;
    let count = count.min(cfg.max_particles);
    let exp = Exp::new(lambda).map_err(|e| Error::Invalid {
        what: "particle sizes".into(),
        message: e.to_string(),
    })?;
    // one wind slant per image: +-15 deg for rain, +-30 deg for snow
    let max_slant: f64 = if kind == Particles::Rain { 15.0 } else { 30.0 };
    let slant = (rng.random::<f64>() * 2.0 - 1.0) * max_slant.to_radians();
    let dir = (slant.sin(), slant.cos());
    let mut drawn = 0u64;
    for _ in 0..count {
        let z = (z0.powi(3) + rng.random::<f64>() * (z1.powi(3) - z0.powi(3))).cbrt();
        let u = rng.random::<f64>() * w as f64 - 0.5;
        let v = rng.random::<f64>() * h as f64 - 0.5;
        let d_mm = d_vis + exp.sample(&mut rng).min(20.0);
        let speed = speed_const.unwrap_or_else(|| rain_drop_speed_m_s(d_mm));
        let len = k.fy * speed * cfg.exposure_s / z;
        let width = k.fx * d_mm * 1e-3 / z;
        if draw_streak(lin, w, h, u, v - len / 2.0, dir, len, width, colour) {
            drawn += 1;
        }
    }
    let mut rec = EffectRecord::new(name)
        .param("particles_per_m3_d_ge_1mm", per_m3)
        .param("frustum_volume_m3", volume)
        .param("slant_rad", slant)
        .count("particles_drawn", drawn);
    if capped {
        rec = rec.note(format!(
            "particle count {expected:.0} capped at max_particles = {}",
            cfg.max_particles
        ));
    }
    Ok(rec)
}

fn missing(effect: CameraEffect, what: &str) -> Error {
    Error::MissingInput {
        effect: effect.name().to_string(),
        input: what.to_string(),
    }
}

/// Run the camera pipeline of `plan` (empty pipeline: an exact copy, no random draw).
pub fn apply_camera(
    plan: &Plan,
    weather: &Weather,
    cfg: &CameraConfig,
    input: CameraInput<'_>,
) -> Result<CameraOutput> {
    let img = input.image;
    if plan.camera.is_empty() {
        return Ok(CameraOutput {
            image: img.clone(),
            records: Vec::new(),
        });
    }
    let (w, h) = (img.width() as usize, img.height() as usize);
    // check every input first: fail before doing any work
    for &e in &plan.camera {
        for need in e.required_inputs() {
            match need {
                super::plan::Input::DepthMap => {
                    let d = input.depth.ok_or_else(|| missing(e, "a depth map"))?;
                    d.validate(img.width(), img.height())?;
                }
                super::plan::Input::Intrinsics => {
                    input
                        .intrinsics
                        .ok_or_else(|| missing(e, "camera intrinsics"))?
                        .validate()?;
                }
                _ => {}
            }
        }
    }
    let lut: Vec<f32> = (0..=255u8).map(srgb_to_linear).collect();
    let clean: Vec<f32> = img.as_raw().par_iter().map(|&v| lut[v as usize]).collect();
    let mut lin = clean.clone();
    let ambient = weather.time_of_day.ambient_scale() as f32;
    let needs_airlight = plan.camera.iter().any(|e| {
        matches!(
            e,
            CameraEffect::Veil | CameraEffect::RainStreaks | CameraEffect::Snowflakes
        )
    });
    let (air_day, air_note) = match (cfg.airlight, needs_airlight) {
        (Some(a), _) => (a, "airlight: configured"),
        (None, true) => (
            estimate_airlight(&clean, w, h),
            "airlight: dark-channel estimate",
        ),
        (None, false) => ([1.0; 3], ""),
    };
    let air = air_day.map(|a| a * ambient);
    let alpha = plan.extinction.total_per_m();
    let mut records = Vec::new();
    for &e in &plan.camera {
        let rec = match e {
            CameraEffect::Darken => {
                lin.par_iter_mut().for_each(|x| *x *= ambient);
                EffectRecord::new(e.name()).param("ambient_scale", ambient as f64)
            }
            CameraEffect::Headlights => {
                let hl = cfg.headlights.unwrap_or_default();
                let (Some(depth), Some(k)) = (input.depth, input.intrinsics) else {
                    return Err(missing(e, "a depth map and intrinsics"));
                };
                let tilt = hl.tilt_down_deg.to_radians();
                let axis = glam::DVec3::new(0.0, tilt.sin(), tilt.cos());
                let pos = glam::DVec3::from_array(hl.position_m);
                let cutoff_sin = hl.cutoff_above_horizontal_deg.to_radians().sin();
                lin.par_chunks_mut(3 * w)
                    .zip(clean.par_chunks(3 * w))
                    .enumerate()
                    .for_each(|(r, (row, cl))| {
                        for c in 0..w {
                            let z = depth.z_m[r * w + c] as f64;
                            if !z.is_finite() {
                                continue;
                            }
                            let p = glam::DVec3::new(
                                (c as f64 - k.cx) / k.fx * z,
                                (r as f64 - k.cy) / k.fy * z,
                                z,
                            );
                            let v = p - pos;
                            let d2 = v.length_squared().max(1e-4);
                            // low-beam cut-off: no light above the lamp's horizontal plane (+ cut-off angle)
                            if v.y < -cutoff_sin * d2.sqrt() {
                                continue;
                            }
                            let cosphi = (v.dot(axis) / d2.sqrt()).max(0.0);
                            let e_irr = (hl.intensity * cosphi.powf(hl.exponent) / d2) as f32;
                            for ch in 0..3 {
                                row[3 * c + ch] += cl[3 * c + ch] * e_irr;
                            }
                        }
                    });
                EffectRecord::new(e.name())
                    .param("intensity", hl.intensity)
                    .param("exponent", hl.exponent)
            }
            CameraEffect::Veil => {
                let (Some(depth), Some(k)) = (input.depth, input.intrinsics) else {
                    return Err(missing(e, "a depth map and intrinsics"));
                };
                let sky = std::sync::atomic::AtomicU64::new(0);
                lin.par_chunks_mut(3 * w).enumerate().for_each(|(r, row)| {
                    let mut s = 0;
                    for c in 0..w {
                        let z = depth.z_m[r * w + c] as f64;
                        let t = if alpha <= 0.0 {
                            1.0
                        } else if z.is_infinite() {
                            s += 1;
                            0.0
                        } else {
                            (-alpha * z * k.ray_factor(c as f64, r as f64)).exp()
                        } as f32;
                        // flush f32 denormals (dense fog, far pixels) to an exact 0
                        let t = if t < f32::MIN_POSITIVE { 0.0 } else { t };
                        for ch in 0..3 {
                            let x = &mut row[3 * c + ch];
                            *x = *x * t + air[ch] * (1.0 - t);
                        }
                    }
                    sky.fetch_add(s, std::sync::atomic::Ordering::Relaxed);
                });
                let mut rec = EffectRecord::new(e.name())
                    .param("alpha_per_m", alpha)
                    .param("airlight_r", air[0] as f64)
                    .param("airlight_g", air[1] as f64)
                    .param("airlight_b", air[2] as f64)
                    .count("sky_pixels", sky.into_inner());
                if !air_note.is_empty() {
                    rec = rec.note(air_note);
                }
                rec
            }
            CameraEffect::RainStreaks | CameraEffect::Snowflakes => {
                let k = input
                    .intrinsics
                    .ok_or_else(|| missing(e, "camera intrinsics"))?;
                let kind = if e == CameraEffect::RainStreaks {
                    Particles::Rain
                } else {
                    Particles::Snow
                };
                let colour = if kind == Particles::Snow {
                    air.map(|a| 0.9 * a)
                } else {
                    air
                };
                draw_particles(&mut lin, w, h, &k, weather, cfg, kind, colour)?
            }
            CameraEffect::SensorNoise => {
                let sigma_s: f64 = if ambient < 0.1 { 8e-3 } else { 2e-3 };
                let sigma_r = (2.18 * sigma_s.ln() + 1.20).exp();
                let levels = ((1u64 << cfg.adc_bits.clamp(1, 24)) - 1) as f32;
                let seed = weather.seed;
                lin.par_chunks_mut(3 * w).enumerate().for_each(|(r, row)| {
                    let mut rng = rng::stream(seed, rng::tag::CAMERA_NOISE, r as u64);
                    for x in row.iter_mut() {
                        let var = sigma_s * (*x as f64).max(0.0) + sigma_r;
                        let n: f64 = StandardNormal.sample(&mut rng);
                        let y = (*x as f64 + var.sqrt() * n).clamp(0.0, 1.0) as f32;
                        *x = (y * levels).round() / levels;
                    }
                });
                EffectRecord::new(e.name())
                    .param("shot_noise_sigma_s", sigma_s)
                    .param("read_noise_sigma_r", sigma_r)
                    .param("adc_bits", cfg.adc_bits as f64)
            }
        };
        records.push(rec);
    }
    let raw: Vec<u8> = lin.par_iter().map(|&x| linear_to_srgb(x)).collect();
    let image =
        RgbImage::from_raw(img.width(), img.height(), raw).ok_or_else(|| Error::Invalid {
            what: "camera output".into(),
            message: "buffer size mismatch".into(),
        })?;
    Ok(CameraOutput { image, records })
}
