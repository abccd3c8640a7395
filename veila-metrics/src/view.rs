//! A generated scan scored against a real one in a camera's view (what `cargo xtask bench-real`
//! reports per frame, where there are too few frames for set metrics), and camera depth maps
//! scored against LiDAR points.
//!
//! * [`ViewRegions`]: masks of a range grid: the pixels whose rays the camera sees
//!   ([`veila_geom::PinholeCamera::frustum_mask`]), the front half and the front half outside
//!   the view.
//! * [`masked_range_mae`]: range MAE over a mask with its **coverage** (the share of the
//!   reference's returns there that the scan also has: a scan that returns only easy pixels
//!   cannot hide behind its MAE); [`ViewScores`]: that, the front halves' MAEs and the Chamfer
//!   distance in view, as mean and spread over several samples.
//! * [`depth_score`] / [`depth_by_region`]: a per-pixel camera depth map (a depth network's, or
//!   the flat-ground prior's, [`flat_ground_depth`]) at the points' pixels.

use glam::Vec3;
use serde::{Deserialize, Serialize};
use veila_geom::{LidarSensor, PinholeCamera, RangeImage, RayTable};

use crate::error::{Error, Result};

/// `mean ± std` of one figure over samples.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Spread {
    /// Mean (0 for no values).
    pub mean: f64,
    /// Sample standard deviation (0 for fewer than two values).
    pub std: f64,
}

impl Spread {
    /// Mean and sample standard deviation of `v`.
    pub fn of(v: &[f64]) -> Self {
        let n = v.len().max(1) as f64;
        let mean = v.iter().sum::<f64>() / n;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
        Spread {
            mean,
            std: var.sqrt(),
        }
    }
}

/// Masks of a range grid (row-major, `rows x cols`): in a camera's view, in the front half, in
/// the front half outside the view; and the rays' directions.
#[derive(Debug, Clone)]
pub struct ViewRegions {
    /// The rays the camera sees.
    pub view: Vec<bool>,
    /// The front half: the half facing `+x` of the frame the camera's nearest quarter turn
    /// brings forward (`x > 0` for KITTI's LiDAR frame, `y > 0` for nuScenes').
    pub front: Vec<bool>,
    /// `front` and not `view`: what the image does not show of the half ahead.
    pub front_unseen: Vec<bool>,
    dirs: Vec<Vec3>,
}

impl ViewRegions {
    /// The regions of `sensor`'s grid for `camera` (both in the scan's frame); the front half
    /// faces `quarter_turns` quarter turns about `z` from `+x` (counter-clockwise: 1 is `+y`).
    pub fn new(sensor: &LidarSensor, camera: &PinholeCamera, quarter_turns: i32) -> Result<Self> {
        let rays = RayTable::new(sensor).map_err(|e| Error::InvalidParameter {
            name: "sensor",
            reason: e.to_string(),
        })?;
        let dirs = rays.dirs().to_vec();
        let view = camera.frustum_mask(&rays);
        // the ray's coordinate along the front axis, exact for every quarter turn
        let ahead = |d: &Vec3| match quarter_turns.rem_euclid(4) {
            0 => d.x,
            1 => d.y,
            2 => -d.x,
            _ => -d.y,
        };
        let front: Vec<bool> = dirs.iter().map(|d| ahead(d) > 0.0).collect();
        let front_unseen = front.iter().zip(&view).map(|(&f, &v)| f && !v).collect();
        Ok(ViewRegions {
            view,
            front,
            front_unseen,
            dirs,
        })
    }

    /// The points of `scan`'s returns in the view (for the Chamfer distance in view).
    pub fn points_in_view(&self, scan: &RangeImage) -> Vec<Vec3> {
        (0..self.view.len().min(scan.mask.len()))
            .filter(|&i| self.view[i] && scan.mask[i])
            .map(|i| self.dirs[i] * scan.range_m[i])
            .collect()
    }
}

/// `(MAE, coverage)` of `scan` against `reference` over the pixels of `mask`: the mean absolute
/// range difference (m) where both have a return (NaN where none qualifies), and the share of
/// `reference`'s returns in the mask that `scan` also has. An error when the grids differ.
pub fn masked_range_mae(
    mask: &[bool],
    scan: &RangeImage,
    reference: &RangeImage,
) -> Result<(f64, f64)> {
    let n_px = mask.len();
    for (what, len) in [
        ("scan", scan.mask.len()),
        ("reference scan", reference.mask.len()),
    ] {
        if len != n_px {
            return Err(Error::ShapeMismatch {
                what: what.into(),
                expected: format!("{n_px} pixels (the mask's)"),
                got: format!("{len} pixels"),
            });
        }
    }
    let (mut sum, mut n, mut real_n) = (0.0f64, 0usize, 0usize);
    for i in 0..n_px {
        if mask[i] && reference.mask[i] {
            real_n += 1;
            if scan.mask[i] {
                sum += (scan.range_m[i] - reference.range_m[i]).abs() as f64;
                n += 1;
            }
        }
    }
    let mae = if n > 0 { sum / n as f64 } else { f64::NAN };
    Ok((mae, n as f64 / real_n.max(1) as f64))
}

/// Samples of one method scored against a reference scan in a camera's view: mean and spread
/// over the samples. The field names are the JSON of `bench-real`'s report.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ViewScores {
    /// Range MAE over the pixels the camera sees, m.
    pub view_mae_m: Spread,
    /// Share of the reference's returns in the view that the scans also have (mean).
    pub view_coverage: f64,
    /// Range MAE of the front half, m; `None` for a reference cropped to the view.
    pub front_mae_m: Option<Spread>,
    /// Range MAE of the front half outside the camera's view (what the image does not show), m;
    /// `None` for a cropped reference and in reports from before 2026-11-26.
    #[serde(default)]
    pub front_unseen_mae_m: Option<Spread>,
    /// Chamfer distance in the camera's view (PyTorch3D's convention, [`crate::chamfer`]), m²
    /// (NaN for a sample without a return there).
    pub view_chamfer_m2: Spread,
}

impl ViewScores {
    /// Scores `scans` against `reference` (all on one grid) in `regions`; `cropped`: the
    /// reference covers the camera's view only, so the front halves are not scored.
    pub fn of(
        regions: &ViewRegions,
        reference: &RangeImage,
        scans: &[RangeImage],
        cropped: bool,
    ) -> Result<Self> {
        let reference_points = regions.points_in_view(reference);
        let (mut view, mut coverage, mut front, mut unseen, mut chamfer) =
            (vec![], vec![], vec![], vec![], vec![]);
        for s in scans {
            let (m, c) = masked_range_mae(&regions.view, s, reference)?;
            view.push(m);
            coverage.push(c);
            front.push(masked_range_mae(&regions.front, s, reference)?.0);
            unseen.push(masked_range_mae(&regions.front_unseen, s, reference)?.0);
            chamfer.push(
                crate::chamfer::chamfer_distance(&regions.points_in_view(s), &reference_points)
                    .map_or(f64::NAN, |c| c.value()),
            );
        }
        Ok(ViewScores {
            view_mae_m: Spread::of(&view),
            view_coverage: Spread::of(&coverage).mean,
            front_mae_m: (!cropped).then(|| Spread::of(&front)),
            front_unseen_mae_m: (!cropped).then(|| Spread::of(&unseen)),
            view_chamfer_m2: Spread::of(&chamfer),
        })
    }
}

/// Camera depth against the LiDAR points that project into the image.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DepthScore {
    /// Mean |predicted - true| / true.
    pub abs_rel: f64,
    /// Mean |predicted - true|, m.
    pub mae_m: f64,
    /// Share of the points with a prediction.
    pub coverage: f64,
}

/// Camera depth in one region of the image: which part of the picture a depth map gets wrong.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RegionDepth {
    /// `left`, `centre` or `right` third, `upper` or `lower` half: e.g. `left upper`.
    pub region: String,
    /// Points in the region.
    pub points: usize,
    /// Median camera depth of the points, m.
    pub real_median_m: f64,
    /// Median predicted depth at those points, m.
    pub predicted_median_m: f64,
    /// Mean |predicted - true| / true over them.
    pub abs_rel: f64,
}

/// The nearest pixel `(u, v)` of every point that projects into `camera`'s image at least 1 m in
/// front of it, with the point's camera depth in metres.
fn pixels_hit<'a>(
    camera: &'a PinholeCamera,
    points: &'a [Vec3],
) -> impl Iterator<Item = (usize, usize, f64)> + 'a {
    let (w, h) = (camera.width as i64, camera.height as i64);
    points.iter().filter_map(move |p| {
        let ip = camera.try_project_in_image(*p)?;
        let (u, v) = (
            (ip.u_px + 0.5).floor() as i64,
            (ip.v_px + 0.5).floor() as i64,
        );
        (ip.depth_m >= 1.0 && u >= 0 && v >= 0 && u < w && v < h).then_some((
            u as usize,
            v as usize,
            ip.depth_m as f64,
        ))
    })
}

/// An error unless `map` has one value per pixel of `camera`'s image.
fn check_map(len: usize, camera: &PinholeCamera) -> Result<()> {
    let px = camera.width as usize * camera.height as usize;
    if len != px {
        return Err(Error::ShapeMismatch {
            what: "depth map".into(),
            expected: format!("{px} pixels ({}x{})", camera.width, camera.height),
            got: format!("{len} pixels"),
        });
    }
    Ok(())
}

/// Scores per-pixel camera depth (`None` = no prediction; row-major, the size of `camera`'s
/// image) against the points' camera depths at their nearest pixels; `None` when no point has a
/// prediction.
pub fn depth_score(
    depth_m: &[Option<f32>],
    camera: &PinholeCamera,
    points: &[Vec3],
) -> Result<Option<DepthScore>> {
    check_map(depth_m.len(), camera)?;
    let w = camera.width as usize;
    let (mut rel, mut abs, mut n, mut total) = (0.0f64, 0.0f64, 0usize, 0usize);
    for (u, v, t) in pixels_hit(camera, points) {
        total += 1;
        if let Some(d) = depth_m[v * w + u] {
            rel += (d as f64 - t).abs() / t;
            abs += (d as f64 - t).abs();
            n += 1;
        }
    }
    Ok((n > 0).then(|| DepthScore {
        abs_rel: rel / n as f64,
        mae_m: abs / n as f64,
        coverage: n as f64 / total as f64,
    }))
}

/// [`depth_score`] of a dense map split into the image's thirds across and halves down (six
/// regions, those without a point left out): a frame's AbsRel is mostly the near road, which a
/// depth network gets right, so the far objects it misses show only here.
pub fn depth_by_region(
    depth_m: &[f32],
    camera: &PinholeCamera,
    points: &[Vec3],
) -> Result<Vec<RegionDepth>> {
    check_map(depth_m.len(), camera)?;
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut cells: Vec<Vec<(f64, f64)>> = vec![Vec::new(); 6];
    for (u, v, t) in pixels_hit(camera, points) {
        let (col, row) = (3 * u / w, 2 * v / h);
        cells[row * 3 + col].push((t, depth_m[v * w + u] as f64));
    }
    let median = |mut x: Vec<f64>| {
        x.sort_by(f64::total_cmp);
        let n = x.len();
        if n % 2 == 1 {
            x[n / 2]
        } else {
            0.5 * (x[n / 2 - 1] + x[n / 2])
        }
    };
    let mut out = Vec::new();
    for (i, c) in cells.into_iter().enumerate() {
        if c.is_empty() {
            continue;
        }
        let abs_rel = c.iter().map(|(t, d)| (d - t).abs() / t).sum::<f64>() / c.len() as f64;
        out.push(RegionDepth {
            region: format!(
                "{} {}",
                ["left", "centre", "right"][i % 3],
                ["upper", "lower"][i / 3]
            ),
            points: c.len(),
            real_median_m: median(c.iter().map(|x| x.0).collect()),
            predicted_median_m: median(c.iter().map(|x| x.1).collect()),
            abs_rel,
        });
    }
    Ok(out)
}

/// The flat-ground prior in the image ([`veila_geom::flat_ground_depth_map_m`]): each pixel's ray
/// meets the ground plane `height_m` below the (level) LiDAR; `None` at and above the horizon or
/// beyond `max_m`.
pub fn flat_ground_depth(camera: &PinholeCamera, height_m: f32, max_m: f32) -> Vec<Option<f32>> {
    veila_geom::flat_ground_depth_map_m(camera, -height_m)
        .into_iter()
        .map(|d| (d > 0.0 && d <= max_m).then_some(d))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Mat4;

    /// KITTI-like axes: camera `x` right = LiDAR `-y`, `y` down = LiDAR `-z`, `z` forward = LiDAR `+x`.
    fn kitti_axes() -> Mat4 {
        Mat4::from_cols(
            glam::Vec4::new(0., 0., 1., 0.),
            glam::Vec4::new(-1., 0., 0., 0.),
            glam::Vec4::new(0., -1., 0., 0.),
            glam::Vec4::W,
        )
    }

    /// A 1200 x 360 KITTI-size pinhole camera (focal 700 px).
    fn wide_camera(cam_from_lidar: Mat4) -> PinholeCamera {
        let k = [
            [700.0, 0.0, 600.0, 0.0],
            [0.0, 700.0, 180.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        PinholeCamera::new(k, cam_from_lidar, 1200, 360).unwrap()
    }

    #[test]
    fn the_front_half_splits_into_the_view_and_the_unseen_rest() {
        let sensor = LidarSensor::hdl64e();
        let cam = wide_camera(kitti_axes());
        let r = ViewRegions::new(&sensor, &cam, 0).unwrap();
        let n = r.front.len();
        let count = |m: &[bool]| m.iter().filter(|&&b| b).count();
        // a KITTI camera looks along +x: its view lies inside the front half, and the unseen part
        // is the rest of it; 2 atan(600 / 700) = 81.2 degrees of the front half's 180
        for i in 0..n {
            assert!(!r.view[i] || r.front[i], "pixel {i} seen but behind");
            assert_eq!(r.front_unseen[i], r.front[i] && !r.view[i], "pixel {i}");
        }
        // by columns: the camera's 28-degree height cuts the beams too
        let (rows, cols) = (sensor.rows as usize, sensor.cols as usize);
        let any_row = |m: &[bool], c: usize| (0..rows).any(|row| m[row * cols + c]);
        let seen_cols = (0..cols).filter(|&c| any_row(&r.view, c)).count();
        let front_cols = (0..cols).filter(|&c| any_row(&r.front, c)).count();
        let seen_share = seen_cols as f64 / front_cols as f64;
        let expected = 2.0 * (600.0f64 / 700.0).atan().to_degrees() / 180.0;
        assert!(
            (seen_share - expected).abs() < 0.03,
            "{seen_share} vs {expected}"
        );
        // the front MAE is the returns-weighted mix of the seen and unseen parts' MAEs
        let ranges = |k: usize| (0..n).map(|i| 5.0 + (i % k) as f32).collect::<Vec<f32>>();
        let real = RangeImage::try_from_range_m(sensor.rows, sensor.cols, ranges(7)).unwrap();
        let scan = RangeImage::try_from_range_m(sensor.rows, sensor.cols, ranges(5)).unwrap();
        let seen_front: Vec<bool> = (0..n).map(|i| r.front[i] && r.view[i]).collect();
        let (front, _) = masked_range_mae(&r.front, &scan, &real).unwrap();
        let (seen, _) = masked_range_mae(&seen_front, &scan, &real).unwrap();
        let (unseen, _) = masked_range_mae(&r.front_unseen, &scan, &real).unwrap();
        let (ns, nu) = (count(&seen_front) as f64, count(&r.front_unseen) as f64);
        let mix = (seen * ns + unseen * nu) / (ns + nu);
        assert!((front - mix).abs() < 1e-9, "{front} vs {mix}");
    }

    #[test]
    fn flat_ground_depth_points_lie_on_the_plane() {
        let k = [
            [200.0, 0.0, 160.0, 12.0],
            [0.0, 200.0, 48.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        // KITTI-like axes, the camera pitched down by 5 degrees and 0.1 m above the LiDAR
        let axes = kitti_axes();
        let cam_from_lidar = Mat4::from_rotation_x(5f32.to_radians())
            * axes
            * Mat4::from_translation(Vec3::new(0.0, 0.0, -0.1));
        let cam = PinholeCamera::new(k, cam_from_lidar, 320, 96).unwrap();
        let d = flat_ground_depth(&cam, 1.73, 80.0);
        let mut hits = 0;
        for v in 0..96u32 {
            for u in 0..320u32 {
                if let Some(depth) = d[(v * 320 + u) as usize] {
                    hits += 1;
                    let p = cam.try_back_project(u as f32, v as f32, depth).unwrap();
                    assert!((p.z + 1.73).abs() < 1e-3, "{p}");
                    // and projecting it back lands on the pixel
                    let ip = cam.try_project(p).unwrap();
                    assert!((ip.u_px - u as f32).abs() < 1e-2 && (ip.v_px - v as f32).abs() < 1e-2);
                }
            }
        }
        // the lower rows see the ground, the top row does not (pitched 5 deg down, fov ~27 deg)
        assert!(hits > 320 * 30);
        assert!(d[..320].iter().all(|x| x.is_none()));
        // nothing beyond max_m survives
        let near = flat_ground_depth(&cam, 1.73, 10.0);
        assert!(near.iter().flatten().all(|&x| x <= 10.0));
        assert!(near.iter().flatten().count() < hits);
    }

    #[test]
    fn depth_by_region_splits_the_image_and_scores_each_part_apart() {
        let k = [
            [100.0, 0.0, 150.0, 0.0],
            [0.0, 100.0, 50.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        // camera frame = LiDAR frame: z forward, x right, y down
        let cam = PinholeCamera::new(k, Mat4::IDENTITY, 300, 100).unwrap();
        // a map that is right everywhere but the upper left third, where it reads 10 m
        let truth = |u: usize, v: usize| 5.0 + (u + v) as f32 * 0.1;
        let mut map = vec![0.0f32; 300 * 100];
        for v in 0..100 {
            for u in 0..300 {
                map[v * 300 + u] = if u < 100 && v < 50 { 10.0 } else { truth(u, v) };
            }
        }
        // one point at every fifth pixel centre, at the true depth
        let mut pts = Vec::new();
        for v in (0..100).step_by(5) {
            for u in (0..300).step_by(5) {
                let z = truth(u, v);
                pts.push(Vec3::new(
                    (u as f32 - 150.0) * z / 100.0,
                    (v as f32 - 50.0) * z / 100.0,
                    z,
                ));
            }
        }
        let r = depth_by_region(&map, &cam, &pts).unwrap();
        let names: Vec<&str> = r.iter().map(|x| x.region.as_str()).collect();
        assert_eq!(
            names,
            [
                "left upper",
                "centre upper",
                "right upper",
                "left lower",
                "centre lower",
                "right lower"
            ]
        );
        assert_eq!(r.iter().map(|x| x.points).sum::<usize>(), pts.len());
        for x in &r[1..] {
            assert!(x.abs_rel < 1e-4, "{x:?}");
            assert!(
                (x.real_median_m - x.predicted_median_m).abs() < 1e-3,
                "{x:?}"
            );
        }
        // brute force for the upper left: truths 5.0 + (u + v) / 10 over u, v in 0, 5, .., 45
        let t: Vec<f64> = (0..100)
            .step_by(5)
            .flat_map(|u| (0..50).step_by(5).map(move |v| 5.0 + (u + v) as f64 * 0.1))
            .collect();
        let want = t.iter().map(|t| (10.0 - t).abs() / t).sum::<f64>() / t.len() as f64;
        assert!(
            (r[0].abs_rel - want).abs() < 1e-4,
            "{} {want}",
            r[0].abs_rel
        );
        assert_eq!(r[0].predicted_median_m, 10.0);
        // a frame with points in one region reports only that one
        let one = depth_by_region(&map, &cam, &pts[..1]).unwrap();
        assert_eq!(one.len(), 1);
        assert_eq!(one[0].region, "left upper");
    }

    #[test]
    fn a_quarter_turned_front_half_faces_the_turned_axis_and_scores_refuse_other_grids() {
        let sensor = LidarSensor::hdl64e();
        // nuScenes-like: the camera looks along the LiDAR's +y
        let cam = wide_camera(kitti_axes() * Mat4::from_rotation_z(-std::f32::consts::FRAC_PI_2));
        let r = ViewRegions::new(&sensor, &cam, 1).unwrap();
        let rays = RayTable::new(&sensor).unwrap();
        for (i, d) in rays.dirs().iter().enumerate() {
            assert_eq!(r.front[i], d.y > 0.0, "pixel {i}");
            assert!(!r.view[i] || d.y > 0.0, "pixel {i} seen behind the camera");
        }
        assert!(r.view.iter().any(|&v| v));
        // turned twice, the front half is the rear of the unturned one
        let back = ViewRegions::new(&sensor, &cam, 2).unwrap();
        for (i, d) in rays.dirs().iter().enumerate() {
            assert_eq!(back.front[i], -d.x > 0.0, "pixel {i}");
        }
        // scans of another grid are an error, not a panic
        let n = r.view.len();
        let real = RangeImage::try_from_range_m(sensor.rows, sensor.cols, vec![5.0; n]).unwrap();
        let small = RangeImage::try_from_range_m(2, 4, vec![5.0; 8]).unwrap();
        assert!(masked_range_mae(&r.view, &small, &real).is_err());
        assert!(ViewScores::of(&r, &real, &[small], false).is_err());
        // a scan equal to the reference scores 0 with full coverage
        let same = ViewScores::of(&r, &real, &[real.clone(), real.clone()], false).unwrap();
        assert_eq!((same.view_mae_m.mean, same.view_coverage), (0.0, 1.0));
        assert_eq!(
            same.view_chamfer_m2,
            Spread {
                mean: 0.0,
                std: 0.0
            }
        );
        assert!(same.front_mae_m.is_some());
        assert!(
            ViewScores::of(&r, &real, std::slice::from_ref(&real), true)
                .unwrap()
                .front_mae_m
                .is_none()
        );
        // and a depth map of the wrong size is refused
        assert!(depth_score(&[Some(1.0)], &cam, &[glam::Vec3::Y]).is_err());
        assert_eq!(
            Spread::of(&[1.0, 3.0]),
            Spread {
                mean: 2.0,
                std: 2f64.sqrt()
            }
        );
    }
}
