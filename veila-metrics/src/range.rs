//! Pixel-wise comparison of two range images on the same grid.

use veila_geom::{RangeImage, Region};

/// Mean absolute range difference (metres) over the pixels where both range images have a return,
/// restricted to `region` by each pixel column's azimuth (column `c` of `W` looks along azimuth
/// `π (1 − 2 (c + ½) / W)`, the convention of [`veila_geom::LidarSensor::col_azimuth_rad`]; front is
/// `x > 0`). `None` when the grids differ or no pixel qualifies.
pub fn range_mae(a: &RangeImage, b: &RangeImage, region: Region) -> Option<f64> {
    if (a.rows, a.cols) != (b.rows, b.cols) || a.cols == 0 {
        return None;
    }
    let cols = a.cols as usize;
    let (mut sum, mut n) = (0.0f64, 0usize);
    for i in 0..a.range_m.len().min(b.range_m.len()) {
        if !(a.mask[i] && b.mask[i]) {
            continue;
        }
        let az = std::f64::consts::PI * (1.0 - 2.0 * ((i % cols) as f64 + 0.5) / cols as f64);
        let front = az.cos() > 0.0;
        let keep = match region {
            Region::All => true,
            Region::Front => front,
            Region::Rear => !front,
        };
        if keep {
            sum += f64::from((a.range_m[i] - b.range_m[i]).abs());
            n += 1;
        }
    }
    (n > 0).then(|| sum / n as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(cols: u32, range: Vec<f32>, mask: Vec<bool>) -> RangeImage {
        let mut img = RangeImage::new_empty(1, cols);
        img.range_m = range;
        img.mask = mask;
        img
    }

    #[test]
    fn averages_only_pixels_valid_in_both_and_splits_front_from_rear() {
        // 4 columns: azimuths 135, 45, -45, -135 degrees -> rear, front, front, rear
        let a = image(
            4,
            vec![10.0, 10.0, 10.0, 10.0],
            vec![true, true, true, false],
        );
        let b = image(4, vec![12.0, 11.0, 7.0, 0.0], vec![true, true, true, true]);
        assert_eq!(
            range_mae(&a, &b, Region::All),
            Some((2.0 + 1.0 + 3.0) / 3.0)
        );
        assert_eq!(range_mae(&a, &b, Region::Front), Some(2.0));
        assert_eq!(range_mae(&a, &b, Region::Rear), Some(2.0));
        let none = image(4, vec![0.0; 4], vec![false; 4]);
        assert_eq!(range_mae(&a, &none, Region::All), None);
        assert_eq!(
            range_mae(&a, &image(2, vec![1.0; 2], vec![true; 2]), Region::All),
            None
        );
    }

    #[test]
    fn front_matches_the_sensor_azimuth_of_each_column() {
        let sensor = veila_geom::LidarSensor {
            rows: 1,
            cols: 16,
            ..veila_geom::LidarSensor::hdl64e()
        };
        for c in 0..16u32 {
            let mut range = vec![0.0; 16];
            let mut mask = vec![false; 16];
            range[c as usize] = 5.0;
            mask[c as usize] = true;
            let a = image(16, range, mask.clone());
            let b = image(16, vec![0.0; 16], mask);
            let front = sensor.col_azimuth_rad(c).cos() > 0.0;
            assert_eq!(
                range_mae(&a, &b, Region::Front).is_some(),
                front,
                "column {c}"
            );
            assert_eq!(
                range_mae(&a, &b, Region::Rear).is_some(),
                !front,
                "column {c}"
            );
        }
    }
}
