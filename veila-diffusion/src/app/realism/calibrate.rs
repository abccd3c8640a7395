//! Calibration rows of the realism benchmark: the data floor's true scans put through a known
//! degradation ([`Degradation`]) and scored like a generator's. They say what a realism figure
//! means in pixels: how far FPD, FRD or the texture distance move for 1 % of range noise, or for
//! a 3 x 3 blur of the kind a conditional mean draws, next to the generators' rows.

use std::fmt;
use std::str::FromStr;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use veila_geom::RangeImage;

use super::RealismBench;
use crate::app::bundle::Bundle;
use crate::app::scoring::{SetMetrics, distribution_metrics};
use crate::error::{Error, Result, invalid};

/// Largest blur window (pixels on a side).
pub const MAX_BLUR: usize = 15;
/// Largest range noise (percent of the range, one standard deviation).
pub const MAX_NOISE_PERCENT: f64 = 100.0;

/// A known degradation of a true scan. Empty pixels stay empty and give nothing to their
/// neighbours; intensity and ray drop are left as they are.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Degradation {
    /// Each range multiplied by `exp(percent / 100 · z)`, `z` standard normal: relative noise
    /// of `percent` % (one standard deviation, in log range).
    RangeNoise {
        /// One standard deviation, percent of the range.
        percent: f64,
    },
    /// The log range averaged over a `size` x `size` window of non-empty pixels (wrapping in
    /// azimuth, clamped at the top and bottom rows): the smoothing a conditional mean does.
    Blur {
        /// Pixels on a side, odd.
        size: usize,
        /// Only the pixels whose own range lies in `[lo, hi)` metres change (their windows still
        /// hold every non-empty pixel); `None`: every pixel.
        band_m: Option<(f32, f32)>,
    },
}

impl Degradation {
    /// `scan` degraded; `seed` draws the noise.
    pub fn apply(&self, scan: &RangeImage, seed: u64) -> RangeImage {
        let mut out = scan.clone();
        match *self {
            Degradation::RangeNoise { percent } => {
                let sigma = percent / 100.0;
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                for (r, &m) in out.range_m.iter_mut().zip(&scan.mask) {
                    let z: f64 = StandardNormal.sample(&mut rng);
                    if m {
                        *r = (f64::from(*r) * (sigma * z).exp()) as f32;
                    }
                }
            }
            Degradation::Blur { size, band_m } => {
                let (rows, cols) = (scan.rows as usize, scan.cols as usize);
                let half = (size / 2) as isize;
                let ln: Vec<f64> = scan
                    .range_m
                    .iter()
                    .map(|&r| f64::from(r.max(f32::MIN_POSITIVE)).ln())
                    .collect();
                for y in 0..rows {
                    for x in 0..cols {
                        let r = scan.range_m[y * cols + x];
                        let in_band = band_m.is_none_or(|(lo, hi)| r >= lo && r < hi);
                        if !scan.mask[y * cols + x] || !in_band {
                            continue;
                        }
                        let (mut sum, mut n) = (0.0, 0usize);
                        for dy in -half..=half {
                            let yy = (y as isize + dy).clamp(0, rows as isize - 1) as usize;
                            for dx in -half..=half {
                                let xx = (x as isize + dx).rem_euclid(cols as isize) as usize;
                                let i = yy * cols + xx;
                                if scan.mask[i] {
                                    sum += ln[i];
                                    n += 1;
                                }
                            }
                        }
                        // n >= 1: the pixel itself is in its window
                        out.range_m[y * cols + x] = (sum / n as f64).exp() as f32;
                    }
                }
            }
        }
        out
    }

    /// The row label of the report.
    pub fn label(&self) -> String {
        match self {
            Degradation::RangeNoise { percent } => {
                format!("data floor with {percent} % range noise (calibration)")
            }
            Degradation::Blur { size, band_m } => {
                let band = band_m
                    .map(|(lo, hi)| format!(" where the range is {lo} to {hi} m"))
                    .unwrap_or_default();
                format!("data floor blurred {size} x {size} in log range{band} (calibration)")
            }
        }
    }
}

/// `noise:P` (P percent of range noise, above 0 and at most 100) or `blur:K` (a K x K window,
/// K odd, 3 to 15), `blur:K:LO-HI` for the pixels whose range is `LO` to `HI` metres alone.
impl FromStr for Degradation {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        let bad = |why: &str| {
            invalid(
                "calibration",
                format!(
                    "`{s}`: {why} (expected noise:P, P above 0 and at most {MAX_NOISE_PERCENT}, or blur:K[:LO-HI], K odd, 3 to {MAX_BLUR}, LO-HI a range band in metres)"
                ),
            )
        };
        let (kind, value) = s.split_once(':').ok_or_else(|| bad("no `:`"))?;
        match kind.trim() {
            "noise" => {
                let percent: f64 = value.trim().parse().map_err(|_| bad("not a number"))?;
                if !(percent > 0.0 && percent <= MAX_NOISE_PERCENT) {
                    return Err(bad("out of range"));
                }
                Ok(Degradation::RangeNoise { percent })
            }
            "blur" => {
                let (value, band) = match value.split_once(':') {
                    Some((v, b)) => (v, Some(b)),
                    None => (value, None),
                };
                let band_m = band
                    .map(|b| {
                        let (lo, hi) =
                            b.split_once('-').ok_or_else(|| bad("no `-` in the band"))?;
                        let num =
                            |t: &str| t.trim().parse::<f32>().map_err(|_| bad("not a number"));
                        let (lo, hi) = (num(lo)?, num(hi)?);
                        if !(lo >= 0.0 && hi > lo && hi.is_finite()) {
                            return Err(bad("the band must be 0 <= LO < HI"));
                        }
                        Ok((lo, hi))
                    })
                    .transpose()?;
                let size: usize = value
                    .trim()
                    .parse()
                    .map_err(|_| bad("not a whole number"))?;
                if !(3..=MAX_BLUR).contains(&size) || size.is_multiple_of(2) {
                    return Err(bad("out of range"));
                }
                Ok(Degradation::Blur { size, band_m })
            }
            _ => Err(bad("unknown kind")),
        }
    }
}

impl fmt::Display for Degradation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Degradation::RangeNoise { percent } => write!(f, "noise:{percent}"),
            Degradation::Blur { size, band_m } => {
                write!(f, "blur:{size}")?;
                match band_m {
                    Some((lo, hi)) => write!(f, ":{lo}-{hi}"),
                    None => Ok(()),
                }
            }
        }
    }
}

impl RealismBench {
    /// A calibration row, one set per fold: the true scans of fold `f + 1` (the data floor's)
    /// put through `degradation` and scored against fold `f` like a generator's, on every metric
    /// but those that compare a scan with its own frame (range MAE, CM-DC, CM-SC), which mean
    /// nothing for the scans of another fold and are not computed.
    pub fn calibration(&self, judge: &Bundle, degradation: Degradation) -> Result<Vec<SetMetrics>> {
        let k = self.num_folds();
        (0..k)
            .map(|f| {
                let scans: Vec<RangeImage> = self.folds[(f + 1) % k]
                    .scans
                    .iter()
                    .enumerate()
                    .map(|(i, s)| degradation.apply(s, (f * 100_003 + i) as u64))
                    .collect();
                let mut m =
                    distribution_metrics(judge, &scans, &self.judges[f], self.nets.as_ref())?;
                self.texture_into(&mut m, &self.folds[f], &scans)?;
                self.memorisation_into(&mut m, &scans)?;
                Ok(m)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 6 x 12 scan: ranges from `f(row, col)`, empty where it gives 0.
    fn scan(f: impl Fn(usize, usize) -> f32) -> RangeImage {
        let mut s = RangeImage::new_empty(6, 12);
        for y in 0..6 {
            for x in 0..12 {
                let r = f(y, x);
                s.range_m[y * 12 + x] = r;
                s.mask[y * 12 + x] = r > 0.0;
            }
        }
        s
    }

    #[test]
    fn range_noise_has_the_asked_spread_in_log_range_and_keeps_the_empty_pixels() {
        let truth = scan(|y, x| {
            if (y + x) % 7 == 0 {
                0.0
            } else {
                5.0 + x as f32
            }
        });
        let d = Degradation::RangeNoise { percent: 3.0 };
        let mut logs = Vec::new();
        for seed in 0..200 {
            let n = d.apply(&truth, seed);
            assert_eq!(n.mask, truth.mask);
            for ((a, b), &m) in n.range_m.iter().zip(&truth.range_m).zip(&truth.mask) {
                if m {
                    logs.push(f64::from(a / b).ln());
                } else {
                    assert_eq!(*a, 0.0);
                }
            }
        }
        let mean = logs.iter().sum::<f64>() / logs.len() as f64;
        let std = (logs.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / logs.len() as f64).sqrt();
        assert!(mean.abs() < 0.002, "mean {mean}");
        assert!((std - 0.03).abs() < 0.0015, "std {std}");
        assert_eq!(d.apply(&truth, 7), d.apply(&truth, 7), "seeded");
        assert_ne!(d.apply(&truth, 7), d.apply(&truth, 8));
    }

    #[test]
    fn blur_averages_log_range_over_non_empty_neighbours_and_wraps_in_azimuth() {
        // brute force: the geometric mean of the window's non-empty pixels, written out
        let truth = scan(|y, x| {
            if y == 2 && x == 5 {
                0.0
            } else {
                1.0 + (y * 12 + x) as f32 * 0.37
            }
        });
        let out = Degradation::Blur {
            size: 3,
            band_m: None,
        }
        .apply(&truth, 0);
        assert_eq!(out.mask, truth.mask);
        let at = |y: usize, x: usize| truth.range_m[y * 12 + x];
        // the seam: column 0's window holds column 11; the top row is clamped (row 0 twice)
        let mut window = Vec::new();
        for yy in [0, 0, 1] {
            for xx in [11, 0, 1] {
                window.push(at(yy, xx));
            }
        }
        let geo =
            |w: &[f32]| (w.iter().map(|r| f64::from(*r).ln()).sum::<f64>() / w.len() as f64).exp();
        assert!((f64::from(out.range_m[0]) - geo(&window)).abs() < 1e-4);
        // beside the empty pixel (2, 5): its window has 8 non-empty pixels
        let mut window = Vec::new();
        for yy in 1..=3 {
            for xx in 3..=5 {
                if (yy, xx) != (2, 5) {
                    window.push(at(yy, xx));
                }
            }
        }
        assert_eq!(window.len(), 8);
        assert!((f64::from(out.range_m[2 * 12 + 4]) - geo(&window)).abs() < 1e-4);
        assert_eq!(out.range_m[2 * 12 + 5], 0.0);
        // a constant scan is a fixed point
        let flat = scan(|_, _| 12.5);
        let b = Degradation::Blur {
            size: 5,
            band_m: None,
        }
        .apply(&flat, 0);
        assert!(b.range_m.iter().all(|r| (r - 12.5).abs() < 1e-4));
        // a band: only the pixels whose own range is in it change, from the same windows
        let banded = Degradation::Blur {
            size: 3,
            band_m: Some((10.0, 20.0)),
        }
        .apply(&truth, 0);
        let mut changed = 0;
        for ((b, o), t) in banded.range_m.iter().zip(&out.range_m).zip(&truth.range_m) {
            if (10.0..20.0).contains(t) {
                assert_eq!(b, o);
                changed += usize::from(b != t);
            } else {
                assert_eq!(b, t);
            }
        }
        assert!(changed > 10, "{changed}");
    }

    #[test]
    fn calibrations_parse_within_their_bounds_and_print_back() {
        for s in [
            "noise:1",
            "noise:0.5",
            "blur:3",
            "blur:15",
            "blur:3:20-120",
            "blur:5:0-7.5",
        ] {
            let d: Degradation = s.parse().unwrap();
            assert_eq!(d.to_string(), s);
        }
        for s in [
            "noise:0",
            "noise:-1",
            "noise:101",
            "noise:nan",
            "blur:4",
            "blur:1",
            "blur:17",
            "blur:3:20",
            "blur:3:20-10",
            "blur:3:-1-5",
            "blur:3:0-inf",
            "blur",
            "sharpen:3",
        ] {
            assert!(s.parse::<Degradation>().is_err(), "{s}");
        }
    }
}
