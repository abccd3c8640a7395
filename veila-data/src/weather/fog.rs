//! LiDAR fog after Hahner et al., "Fog Simulation on Real LiDAR Point Clouds for 3D Object Detection in
//! Adverse Weather", ICCV 2021: the hard return attenuated by `exp(-2 alpha R0)` against the soft return of
//! the fog itself, from the backscatter integral of the transmitted pulse.
//!
//! # Model
//! Pulse `P_T(t) = P0 sin^2(pi t / (2 tau_H))`, `0 <= t <= 2 tau_H`. The normalised soft return at
//! receiver range `R` for a hard target at `R0` is
//!
//! `I(R; R0) = integral_0^{2 tau_H} sin^2(pi t/(2 tau_H)) exp(-2 alpha r) xi(r) / r^2 H(R0 - r) dt`,
//! `r = R - c t / 2`,
//!
//! with the linear crossover `xi` (0 below `r1` = 0.9 m, 1 above `r2` = 1.0 m). [`FogTable`] stores, per
//! `R0`, the peak over `R`: `(R_fog, I_int)`. A point of intensity `i` then has the fog intensity
//! `i_soft = I_int i R0^2 beta / beta0` (beta = 0.046 / MOR, beta0 = 1e-6 / pi) against the hard
//! intensity `i_hard = i exp(-2 alpha R0)`; the stronger return wins.
//!
//! # How the table is built (start-up, milliseconds)
//! Substituting `r` for `t` turns `I` into a convolution of `g(r) = exp(-2 alpha r) xi(r)/r^2` with the
//! kernel `sin^2(pi (R - r)/(c tau_H)) = 1/2 - 1/2 cos(omega (R - r))`. Expanding the cosine, `I(R; R0)`
//! is a combination of three running integrals of `g`, `g cos(omega r)` and `g sin(omega r)` evaluated at
//! `[max(R - c tau_H, r1), min(R, R0)]`: O(1) per `(R, R0)` once the running integrals are tabulated.
//! For `R0` beyond the unrestricted peak `R*` (~4.6 m) the answer no longer depends on `R0`
//! (saturation), so the table only spans `[0, R*]`. Per point the cost is O(1) (linear interpolation).
//!
//! # Reference-implementation bugs avoided
//! * v1 range noise `R0 / U(R0 - 10, R0 + 10)` breaks for `R0 < 10 m` (zero / negative denominator):
//!   we use the additive v4 noise `R_fog + 10 Beta(2, 20)` m, clamped to stay in front of the target.
//! * `round()` of the attenuated intensity turned every point whose attenuated intensity rounds to 0
//!   into a fog point: we do not round, and compare both returns in the log domain (no underflow).
//! * Robo3D decouples backscatter from extinction (and allows alpha = 0 with beta > 0): here both come
//!   from the one visibility, and fog is inactive (never run) at infinite visibility.
//! * Tables are not snapped to 9 tabulated alphas and not clamped at 200 m: any alpha, any range.

use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// Speed of light, m/s.
pub const SPEED_OF_LIGHT_M_S: f64 = 299_792_458.0;

/// Target differential reflectivity `beta0 = Gamma / pi` with Gamma = 1e-6 (Hahner et al. 2021).
pub const BETA0: f64 = 1e-6 / std::f64::consts::PI;

/// Pulse and receiver-overlap model of the fog simulation (Hahner et al. 2021 defaults).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PulseModel {
    /// Half-power pulse width tau_H, seconds (20 ns: the value with published tables).
    pub tau_h_s: f64,
    /// Crossover start r1 (m): no overlap of transmitter and receiver below.
    pub r1_m: f64,
    /// Crossover end r2 (m): full overlap above.
    pub r2_m: f64,
}

impl Default for PulseModel {
    fn default() -> Self {
        PulseModel {
            tau_h_s: 20e-9,
            r1_m: 0.9,
            r2_m: 1.0,
        }
    }
}

impl PulseModel {
    /// Linear crossover function xi(r).
    pub fn xi(&self, r: f64) -> f64 {
        if r <= self.r1_m {
            0.0
        } else if r >= self.r2_m {
            1.0
        } else {
            (r - self.r1_m) / (self.r2_m - self.r1_m)
        }
    }

    /// Pulse spatial length `c tau_H` (m).
    pub fn length_m(&self) -> f64 {
        SPEED_OF_LIGHT_M_S * self.tau_h_s
    }
}

/// Resolution knobs of the fog table.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FogTableConfig {
    /// Step between tabulated hard-target ranges R0 (m).
    pub r0_step_m: f64,
    /// Step of the receiver-range grid searched for the peak (m); the peak is refined by a parabola.
    pub r_step_m: f64,
    /// Step of the running integrals of the backscatter integrand (m).
    pub quad_step_m: f64,
}

impl Default for FogTableConfig {
    fn default() -> Self {
        FogTableConfig {
            r0_step_m: 0.02,
            r_step_m: 0.01,
            quad_step_m: 1e-3,
        }
    }
}

impl FogTableConfig {
    fn validate(&self) -> Result<()> {
        for (what, v, lo, hi) in [
            ("r0_step_m", self.r0_step_m, 1e-4, 1.0),
            ("r_step_m", self.r_step_m, 1e-4, 1.0),
            ("quad_step_m", self.quad_step_m, 1e-5, 0.1),
        ] {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return Err(Error::Invalid {
                    what: format!("fog table {what}"),
                    message: format!("{v} (must be in [{lo}, {hi}])"),
                });
            }
        }
        Ok(())
    }
}

/// Running integrals of `g`, `g cos(omega r)`, `g sin(omega r)` on a uniform grid from r1.
struct RunningIntegrals {
    r_start: f64,
    h: f64,
    /// integrands at the nodes: [g, g cos, g sin]
    f: Vec<[f64; 3]>,
    /// cumulative trapezoid integrals from r_start to each node
    cum: Vec<[f64; 3]>,
    omega: f64,
    alpha: f64,
    pulse: PulseModel,
}

impl RunningIntegrals {
    fn new(alpha: f64, pulse: PulseModel, h: f64, r_end: f64) -> Self {
        let omega = 2.0 * std::f64::consts::PI / pulse.length_m();
        let n = ((r_end - pulse.r1_m) / h).ceil() as usize + 2;
        let mut f = Vec::with_capacity(n);
        let mut cum = Vec::with_capacity(n);
        let mut acc = [0.0f64; 3];
        for k in 0..n {
            let r = pulse.r1_m + k as f64 * h;
            let fk = Self::integrand(alpha, &pulse, omega, r);
            if k > 0 {
                let prev: [f64; 3] = f[k - 1];
                for c in 0..3 {
                    acc[c] += 0.5 * h * (prev[c] + fk[c]);
                }
            }
            f.push(fk);
            cum.push(acc);
        }
        RunningIntegrals {
            r_start: pulse.r1_m,
            h,
            f,
            cum,
            omega,
            alpha,
            pulse,
        }
    }

    fn integrand(alpha: f64, pulse: &PulseModel, omega: f64, r: f64) -> [f64; 3] {
        let g = if r <= pulse.r1_m {
            0.0
        } else {
            (-2.0 * alpha * r).exp() * pulse.xi(r) / (r * r)
        };
        let (s, c) = (omega * r).sin_cos();
        [g, g * c, g * s]
    }

    /// Integral from r_start to x (x clamped into the grid), exact for the piecewise-linear integrand.
    fn cumulative(&self, x: f64) -> [f64; 3] {
        if x <= self.r_start {
            return [0.0; 3];
        }
        let u = (x - self.r_start) / self.h;
        let k = (u.floor() as usize).min(self.f.len() - 2);
        let dx = x - (self.r_start + k as f64 * self.h);
        let fx = Self::integrand(self.alpha, &self.pulse, self.omega, x);
        let mut out = self.cum[k];
        for c in 0..3 {
            out[c] += 0.5 * dx * (self.f[k][c] + fx[c]);
        }
        out
    }

    /// `I(R; R0)` (s m^-2); `r0 = f64::INFINITY` for no hard target.
    fn soft_return(&self, r: f64, r0: f64) -> f64 {
        let len = self.pulse.length_m();
        let a = (r - len).max(self.r_start);
        let b = r.min(r0);
        if b <= a {
            return 0.0;
        }
        let ca = self.cumulative(a);
        let cb = self.cumulative(b);
        let g0 = cb[0] - ca[0];
        let gc = cb[1] - ca[1];
        let gs = cb[2] - ca[2];
        let (s, c) = (self.omega * r).sin_cos();
        let v = (2.0 / SPEED_OF_LIGHT_M_S) * 0.5 * (g0 - c * gc - s * gs);
        v.max(0.0)
    }

    /// Peak of `I(R; R0)` over R in `[lo, hi]`: grid search then parabolic refinement.
    fn peak(&self, r0: f64, lo: f64, hi: f64, step: f64) -> (f64, f64) {
        let n = (((hi - lo) / step).ceil() as usize).max(2);
        let mut best = (lo, 0.0f64, 0usize);
        let mut vals = Vec::with_capacity(n + 1);
        for k in 0..=n {
            let r = lo + (hi - lo) * k as f64 / n as f64;
            let v = self.soft_return(r, r0);
            vals.push(v);
            if v > best.1 {
                best = (r, v, k);
            }
        }
        if best.1 <= 0.0 {
            return (0.0, 0.0);
        }
        let k = best.2;
        if k == 0 || k == n {
            return (best.0, best.1);
        }
        let dr = (hi - lo) / n as f64;
        // golden-section refinement inside the bracket [r_{k-1}, r_{k+1}] (the function is not smooth at
        // R = R0, so a parabola alone can overshoot)
        let (mut a, mut b) = (best.0 - dr, best.0 + dr);
        let g = 0.5 * (5f64.sqrt() - 1.0);
        let mut x1 = b - g * (b - a);
        let mut x2 = a + g * (b - a);
        let mut f1 = self.soft_return(x1, r0);
        let mut f2 = self.soft_return(x2, r0);
        for _ in 0..40 {
            if f1 < f2 {
                a = x1;
                x1 = x2;
                f1 = f2;
                x2 = a + g * (b - a);
                f2 = self.soft_return(x2, r0);
            } else {
                b = x2;
                x2 = x1;
                f2 = f1;
                x1 = b - g * (b - a);
                f1 = self.soft_return(x1, r0);
            }
            if b - a < 1e-7 {
                break;
            }
        }
        let (r, v) = if f1 > f2 { (x1, f1) } else { (x2, f2) };
        if v >= best.1 {
            (r, v)
        } else {
            (best.0, best.1)
        }
    }
}

/// The fog look-up table for one extinction coefficient: per hard-target range R0, the range `R_fog` and
/// normalised strength `I_int` (s m^-2) of the fog's soft return.
#[derive(Debug, Clone, PartialEq)]
pub struct FogTable {
    alpha_per_m: f64,
    pulse: PulseModel,
    r0_step_m: f64,
    /// (R_fog, I_int) at R0 = k * r0_step
    entries: Vec<(f64, f64)>,
    /// Unrestricted peak (R0 = infinity): used for every R0 beyond the table.
    saturated: (f64, f64),
}

impl FogTable {
    /// Build the table for `alpha_per_m` (> 0) with the default pulse model.
    pub fn new(alpha_per_m: f64, cfg: &FogTableConfig) -> Result<Self> {
        Self::with_pulse(alpha_per_m, PulseModel::default(), cfg)
    }

    /// Build the table with an explicit pulse model.
    pub fn with_pulse(alpha_per_m: f64, pulse: PulseModel, cfg: &FogTableConfig) -> Result<Self> {
        cfg.validate()?;
        if !(alpha_per_m.is_finite() && alpha_per_m > 0.0 && alpha_per_m <= 10.0) {
            return Err(Error::Invalid {
                what: "fog extinction coefficient".into(),
                message: format!("{alpha_per_m} m^-1 (must be in (0, 10])"),
            });
        }
        if !(pulse.tau_h_s > 0.0 && pulse.r1_m > 0.0 && pulse.r2_m > pulse.r1_m) {
            return Err(Error::Invalid {
                what: "fog pulse model".into(),
                message: format!("{pulse:?} (need tau_H > 0, 0 < r1 < r2)"),
            });
        }
        let len = pulse.length_m();
        // the unrestricted peak lies within a few pulse lengths of the crossover
        let search_hi = pulse.r2_m + 3.0 * len;
        let ri = RunningIntegrals::new(alpha_per_m, pulse, cfg.quad_step_m, search_hi + 1.0);
        let saturated = ri.peak(f64::INFINITY, pulse.r1_m, search_hi, cfg.r_step_m);
        let r0_max = saturated.0;
        let n = (r0_max / cfg.r0_step_m).ceil() as usize + 1;
        let entries = (0..=n)
            .map(|k| {
                let r0 = k as f64 * cfg.r0_step_m;
                if r0 >= r0_max {
                    saturated
                } else if r0 <= pulse.r1_m {
                    (0.0, 0.0)
                } else {
                    ri.peak(r0, pulse.r1_m, r0, cfg.r_step_m)
                }
            })
            .collect();
        Ok(FogTable {
            alpha_per_m,
            pulse,
            r0_step_m: cfg.r0_step_m,
            entries,
            saturated,
        })
    }

    /// The extinction coefficient this table was built for (m^-1).
    pub fn alpha_per_m(&self) -> f64 {
        self.alpha_per_m
    }

    /// The pulse model.
    pub fn pulse(&self) -> &PulseModel {
        &self.pulse
    }

    /// Number of tabulated R0 values.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True when the table is empty (never, for a successfully built table).
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The saturated entry `(R_fog, I_int)` used for every R0 past the unrestricted peak.
    pub fn saturated(&self) -> (f64, f64) {
        self.saturated
    }

    /// `(R_fog [m], I_int [s m^-2])` for a hard target at `r0_m`, O(1) by linear interpolation.
    /// Non-finite or non-positive ranges give `(0, 0)` (no fog return).
    pub fn lookup(&self, r0_m: f64) -> (f64, f64) {
        if !(r0_m > 0.0) {
            return (0.0, 0.0);
        }
        let u = r0_m / self.r0_step_m;
        let k = u.floor();
        if k as usize + 1 >= self.entries.len() || !u.is_finite() {
            return self.saturated;
        }
        let k = k as usize;
        let w = u - k as f64;
        let (ra, ia) = self.entries[k];
        let (rb, ib) = self.entries[k + 1];
        if ia == 0.0 || ib == 0.0 {
            // do not interpolate a range between "no return" (R = 0) and a real return
            let r = if ia == 0.0 { rb } else { ra };
            return (r, ia * (1.0 - w) + ib * w);
        }
        (ra + w * (rb - ra), ia + w * (ib - ia))
    }
}

/// The backscatter integral `I(R; R0)` by direct composite Simpson quadrature in t with `n` (even)
/// intervals — the slow reference the table is checked against. `r0_m = f64::INFINITY` for no target.
pub fn backscatter_integral_direct(
    alpha_per_m: f64,
    r_m: f64,
    r0_m: f64,
    pulse: &PulseModel,
    n: usize,
) -> f64 {
    let n = (n.max(2) + 1) & !1;
    let t_end = 2.0 * pulse.tau_h_s;
    let h = t_end / n as f64;
    let f = |t: f64| {
        let r = r_m - SPEED_OF_LIGHT_M_S * t / 2.0;
        if r <= pulse.r1_m || r > r0_m {
            return 0.0;
        }
        let s = (std::f64::consts::PI * t / (2.0 * pulse.tau_h_s)).sin();
        s * s * (-2.0 * alpha_per_m * r).exp() * pulse.xi(r) / (r * r)
    };
    let mut acc = f(0.0) + f(t_end);
    for k in 1..n {
        let w = if k % 2 == 1 { 4.0 } else { 2.0 };
        acc += w * f(k as f64 * h);
    }
    acc * h / 3.0
}

/// Peak over R of [`backscatter_integral_direct`] on a fine grid of step `r_step_m` (slow reference).
pub fn backscatter_peak_direct(
    alpha_per_m: f64,
    r0_m: f64,
    pulse: &PulseModel,
    r_step_m: f64,
    n: usize,
) -> (f64, f64) {
    let hi = if r0_m.is_finite() {
        r0_m
    } else {
        pulse.r2_m + 3.0 * pulse.length_m()
    };
    let mut best = (0.0, 0.0);
    let mut r = pulse.r1_m;
    while r <= hi {
        let v = backscatter_integral_direct(alpha_per_m, r, r0_m, pulse, n);
        if v > best.1 {
            best = (r, v);
        }
        r += r_step_m;
    }
    best
}

/// Outcome of the fog model for one point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FogOutcome {
    /// The hard return survives with this (attenuated) intensity.
    Hard {
        /// Attenuated intensity `i exp(-2 alpha R0)`.
        intensity: f64,
    },
    /// The fog return is stronger: the point moves to `range_m` (before range noise) with `intensity`.
    Fog {
        /// Peak range of the fog return, m.
        range_m: f64,
        /// Fog return intensity (uncapped).
        intensity: f64,
    },
}

/// The per-point decision of Hahner et al. 2021, in the log domain (no underflow at any range):
/// fog wins when `ln I_int + 2 ln R0 + ln(beta/beta0) > -2 alpha R0` (independent of `i > 0`).
/// A point with zero range, zero intensity or a non-finite value keeps its intensity (times the
/// attenuation where that is finite).
pub fn fog_point(table: &FogTable, beta_per_m: f64, r0_m: f64, intensity: f64) -> FogOutcome {
    let alpha = table.alpha_per_m;
    if !(r0_m > 0.0 && r0_m.is_finite()) {
        return FogOutcome::Hard { intensity };
    }
    let ln_att = -2.0 * alpha * r0_m;
    let hard = intensity * ln_att.exp();
    if !(intensity > 0.0) || !intensity.is_finite() || beta_per_m <= 0.0 {
        return FogOutcome::Hard { intensity: hard };
    }
    let (r_fog, i_int) = table.lookup(r0_m);
    if i_int <= 0.0 {
        return FogOutcome::Hard { intensity: hard };
    }
    let ln_gain = i_int.ln() + 2.0 * r0_m.ln() + (beta_per_m / BETA0).ln();
    if ln_gain > ln_att {
        FogOutcome::Fog {
            range_m: r_fog,
            intensity: (ln_gain + intensity.ln()).exp(),
        }
    } else {
        FogOutcome::Hard { intensity: hard }
    }
}
