//! Polynomial approximations of `atan2` and `asin` for the fast projection path.
//!
//! Both are branch-light minimax-style polynomials evaluated in `f32`. Their largest errors are
//! measured against `f64` references in the tests and printed by the projection benchmark:
//! `atan2_approx` about 2e-6 rad, `asin_approx` about 1e-6 rad (polynomials fitted by
//! `tools/fit_fastmath.py`; `f32` rounding adds a few 1e-7).

use std::f32::consts::{FRAC_PI_2, PI};

/// `atan2(y, x)` to about 2e-6 rad; returns 0 for `(0, 0)` and follows `f32::atan2`'s signs on the
/// negative x axis (`+pi` for `y = +0`, `-pi` for `y = -0`).
#[inline]
#[must_use]
pub fn atan2_approx(y: f32, x: f32) -> f32 {
    let ax = x.abs();
    let ay = y.abs();
    let mx = ax.max(ay);
    let mn = ax.min(ay);
    // branch-free (selects only), so that loops over many points vectorise; at the origin `a = 0`
    // gives atan2(+-0, +0) = +-0 and atan2(+-0, -0) = +-pi, like the standard library
    let a = if mx > 0.0 { mn / mx } else { 0.0 };
    let s = a * a;
    // odd polynomial for atan on [0, 1], fitted by tools/fit_fastmath.py (max error 1.7e-6 rad)
    let p = ((((-0.011_720_769 * s + 0.052_651_43) * s - 0.116_430_14) * s + 0.193_541_78) * s
        - 0.332_623_04)
        * s
        + 0.999_977_2;
    let r = a * p;
    let r = if ay > ax { FRAC_PI_2 - r } else { r };
    let r = if x.is_sign_negative() { PI - r } else { r };
    r.copysign(y)
}

/// `asin(x)` for `x` in `[-1, 1]` to about 1e-6 rad; clamps
/// arguments outside that interval.
#[inline]
#[must_use]
pub fn asin_approx(x: f32) -> f32 {
    let ax = x.abs().min(1.0);
    // fitted by tools/fit_fastmath.py (max error 6.4e-7 rad)
    let p = ((((-0.004_910_084 * ax + 0.020_617_373) * ax - 0.045_924_86) * ax + 0.088_170_16)
        * ax
        - 0.214_542_69)
        * ax
        + 1.570_795_7;
    let r = FRAC_PI_2 - (1.0 - ax).sqrt() * p;
    r.copysign(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atan2_error_is_small_everywhere() {
        let mut worst = 0.0f64;
        for i in 0..20_000 {
            let t = i as f64 / 20_000.0 * std::f64::consts::TAU;
            for r in [1e-3f64, 1.0, 1e4] {
                let (y, x) = ((t.sin() * r) as f32, (t.cos() * r) as f32);
                let exact = f64::from(y).atan2(f64::from(x));
                let err = (f64::from(atan2_approx(y, x)) - exact).abs();
                // compare modulo 2 pi (the seam)
                let err = err.min((err - std::f64::consts::TAU).abs());
                worst = worst.max(err);
            }
        }
        assert!(worst < 4e-6, "worst atan2 error {worst}");
    }

    #[test]
    fn atan2_signs_on_axes_match_std() {
        for (y, x) in [
            (0.0f32, -1.0f32),
            (-0.0, -1.0),
            (0.0, 1.0),
            (-0.0, 1.0),
            (1.0, 0.0),
            (-1.0, 0.0),
        ] {
            assert_eq!(atan2_approx(y, x), y.atan2(x), "atan2({y}, {x})");
        }
        assert_eq!(atan2_approx(0.0, 0.0), 0.0);
    }

    #[test]
    fn asin_error_is_small() {
        let mut worst = 0.0f64;
        for i in 0..=20_000 {
            let x = -1.0 + 2.0 * i as f64 / 20_000.0;
            let err = (f64::from(asin_approx(x as f32)) - x.asin()).abs();
            worst = worst.max(err);
        }
        assert!(worst < 2e-6, "worst asin error {worst}");
    }
}
