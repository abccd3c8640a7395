//! Zero-skill baselines and the scan statistics generation quality is judged by next to them.
//!
//! A generated scan is only worth something if it beats what needs no camera image at all:
//!
//! * [`median_scan`]: the per-pixel median range and intensity of a set of training scans, with
//!   the majority ray-drop decision (the "mean training scan" for the same sensor grid);
//! * [`nearest`]: retrieval, the training scan whose image descriptor is nearest (cosine) to
//!   the query's, e.g. in the frozen image encoders' feature space.
//!
//! [`ring_spread`] measures how ragged the ground rings are: real ground rings are smooth, noise is
//! not.

use veila_geom::{LidarSensor, RangeImage};

use crate::error::{Error, Result};

/// The per-pixel median of `scans` (all on one grid): a pixel is a return when at least half of
/// the scans have one there (ties count as a return), its range and intensity are the medians
/// over the scans that have a return there (the mean of the two middle values for an even count).
/// Errors on an empty set or differing grids.
pub fn median_scan(scans: &[&RangeImage]) -> Result<RangeImage> {
    let first = scans
        .first()
        .ok_or_else(|| Error::empty("the set of scans of a median scan"))?;
    let (rows, cols) = (first.rows, first.cols);
    if let Some(s) = scans.iter().find(|s| (s.rows, s.cols) != (rows, cols)) {
        return Err(Error::ShapeMismatch {
            what: "median scan grids".into(),
            expected: format!("{rows} x {cols}"),
            got: format!("{} x {}", s.rows, s.cols),
        });
    }
    let n = rows as usize * cols as usize;
    let mut out = RangeImage::new_empty(rows, cols);
    let mut ranges = Vec::with_capacity(scans.len());
    let mut intensities = Vec::with_capacity(scans.len());
    for p in 0..n {
        ranges.clear();
        intensities.clear();
        for s in scans {
            if s.mask[p] && s.range_m[p].is_finite() {
                ranges.push(s.range_m[p]);
                intensities.push(if s.intensity[p].is_finite() {
                    s.intensity[p]
                } else {
                    0.0
                });
            }
        }
        if !ranges.is_empty() && 2 * ranges.len() >= scans.len() {
            out.mask[p] = true;
            out.range_m[p] = median(&mut ranges);
            out.intensity[p] = median(&mut intensities);
        }
    }
    Ok(out)
}

fn median(v: &mut [f32]) -> f32 {
    v.sort_by(f32::total_cmp);
    let m = v.len() / 2;
    if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    }
}

/// The index of the key nearest to `query` by cosine similarity (the first on ties). Errors on
/// no keys, lengths that differ, or non-finite values.
pub fn nearest(query: &[f32], keys: &[Vec<f32>]) -> Result<usize> {
    let norm = |v: &[f32]| -> Result<f64> {
        if let Some(index) = v.iter().position(|x| !x.is_finite()) {
            return Err(Error::NonFinite {
                what: "retrieval descriptor".into(),
                index,
            });
        }
        Ok(v.iter()
            .map(|x| f64::from(*x) * f64::from(*x))
            .sum::<f64>()
            .sqrt())
    };
    let qn = norm(query)?;
    let mut best: Option<(usize, f64)> = None;
    for (i, k) in keys.iter().enumerate() {
        if k.len() != query.len() {
            return Err(Error::ShapeMismatch {
                what: format!("retrieval descriptor {i}"),
                expected: format!("{} values (the query's)", query.len()),
                got: format!("{} values", k.len()),
            });
        }
        let dot: f64 = k
            .iter()
            .zip(query)
            .map(|(a, b)| f64::from(*a) * f64::from(*b))
            .sum();
        let den = norm(k)? * qn;
        let sim = if den > 0.0 { dot / den } else { 0.0 };
        if best.is_none_or(|(_, b)| sim > b) {
            best = Some((i, sim));
        }
    }
    best.map(|(i, _)| i)
        .ok_or_else(|| Error::empty("the retrieval keys"))
}

/// The median, over elevation bands of `band_deg` below `below_deg` (e.g. 0.5° below −15°), of the
/// interquartile range of the returns' ranges in the band (metres): how far the ground rings are
/// from being rings. Rows are assigned to bands by their beam elevation in `sensor`; bands with
/// fewer than 8 returns are skipped. `None` when no band qualifies or the grid is not `sensor`'s.
pub fn ring_spread(
    scan: &RangeImage,
    sensor: &LidarSensor,
    below_deg: f32,
    band_deg: f32,
) -> Option<f64> {
    if (scan.rows, scan.cols) != (sensor.rows, sensor.cols) || band_deg.is_nan() || band_deg <= 0.0
    {
        return None;
    }
    let cols = scan.cols as usize;
    let mut bands: std::collections::BTreeMap<i64, Vec<f32>> = Default::default();
    for r in 0..scan.rows {
        let elev = sensor.row_elevation_rad(r).to_degrees();
        if elev >= below_deg {
            continue;
        }
        let band = ((elev - below_deg) / band_deg).floor() as i64;
        let row = &scan.range_m[r as usize * cols..(r as usize + 1) * cols];
        let mask = &scan.mask[r as usize * cols..(r as usize + 1) * cols];
        bands.entry(band).or_default().extend(
            row.iter()
                .zip(mask)
                .filter(|(v, m)| **m && v.is_finite())
                .map(|(v, _)| *v),
        );
    }
    let mut iqrs: Vec<f32> = bands
        .into_values()
        .filter(|v| v.len() >= 8)
        .map(|mut v| {
            v.sort_by(f32::total_cmp);
            let q = |f: f32| {
                let x = f * (v.len() - 1) as f32;
                let (lo, hi) = (x.floor() as usize, x.ceil() as usize);
                v[lo] + (v[hi] - v[lo]) * (x - lo as f32)
            };
            q(0.75) - q(0.25)
        })
        .collect();
    if iqrs.is_empty() {
        return None;
    }
    Some(f64::from(median(&mut iqrs)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(cols: u32, range: &[f32], mask: &[bool]) -> RangeImage {
        let mut i = RangeImage::new_empty(1, cols);
        i.range_m = range.to_vec();
        i.intensity = range.iter().map(|r| r / 100.0).collect();
        i.mask = mask.to_vec();
        i
    }

    #[test]
    fn median_scan_takes_medians_over_returns_and_the_majority_drop() {
        let a = img(3, &[1.0, 5.0, 9.0], &[true, true, false]);
        let b = img(3, &[3.0, 7.0, 0.0], &[true, false, false]);
        let c = img(3, &[2.0, 6.0, 4.0], &[true, true, true]);
        let d = img(3, &[10.0, 0.0, 0.0], &[true, false, false]);
        let m = median_scan(&[&a, &b, &c, &d]).unwrap();
        // pixel 0: 4 returns (1, 3, 2, 10) -> 2.5; pixel 1: 2 of 4 (a tie) -> return, median 5.5;
        // pixel 2: 1 of 4 -> dropped
        assert_eq!(m.mask, vec![true, true, false]);
        assert_eq!(m.range_m[..2], [2.5, 5.5]);
        assert!((m.intensity[0] - 0.025).abs() < 1e-7);
        assert_eq!(m.range_m[2], 0.0);
        // odd count
        let m3 = median_scan(&[&a, &b, &c]).unwrap();
        assert_eq!(m3.range_m[0], 2.0);
        assert!(median_scan(&[]).is_err());
        assert!(median_scan(&[&a, &img(2, &[1.0, 1.0], &[true, true])]).is_err());
    }

    #[test]
    fn nearest_is_by_cosine_not_length() {
        let keys = vec![vec![1.0, 0.0], vec![10.0, 1.0], vec![0.0, 1.0]];
        assert_eq!(nearest(&[2.0, 0.1], &keys).unwrap(), 1);
        assert_eq!(nearest(&[0.01, 5.0], &keys).unwrap(), 2);
        assert!(nearest(&[1.0], &keys).is_err());
        assert!(nearest(&[1.0, 0.0], &[]).is_err());
        assert!(nearest(&[f32::NAN, 0.0], &keys).is_err());
    }

    #[test]
    fn ring_spread_is_the_median_iqr_of_the_low_bands() {
        // 4 rows from +2 to -28 degrees (10 degrees apart): rows 2 and 3 lie below -15 degrees
        let sensor = LidarSensor {
            rows: 4,
            cols: 16,
            fov_up_deg: 2.0,
            fov_down_deg: -28.0,
            beams: veila_geom::BeamLayout::Uniform,
            ..LidarSensor::hdl64e()
        };
        let elev: Vec<f32> = (0..4)
            .map(|r| sensor.row_elevation_rad(r).to_degrees())
            .collect();
        assert!(elev[1] > -15.0 && elev[2] < -15.0, "{elev:?}");
        let mut scan = RangeImage::new_empty(4, 16);
        for c in 0..16 {
            // row 1 is wild (above the cut), row 2 spans 4..7.75 m, row 3 is flat at 3 m
            for (r, v) in [(1, 100.0 * c as f32), (2, 4.0 + 0.25 * c as f32), (3, 3.0)] {
                scan.range_m[r * 16 + c] = v;
                scan.mask[r * 16 + c] = true;
            }
        }
        // IQR of 4 + 0.25 k (k = 0..15) = 0.25 * (11.25 - 3.75) = 1.875; of the flat row 0:
        // median of the two bands = 0.9375
        let s = ring_spread(&scan, &sensor, -15.0, 0.5).unwrap();
        assert!((s - 0.9375).abs() < 1e-6, "{s}");
        // a grid that is not the sensor's, or no band with enough returns
        assert_eq!(
            ring_spread(&RangeImage::new_empty(2, 16), &sensor, -15.0, 0.5),
            None
        );
        assert_eq!(
            ring_spread(&RangeImage::new_empty(4, 16), &sensor, -15.0, 0.5),
            None
        );
    }
}
