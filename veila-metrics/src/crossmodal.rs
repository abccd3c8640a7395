//! Cross-modal consistency between a generated scan and its conditioning image (the paper's CM-DC and
//! CM-SC).
//!
//! Both metrics project the generated points into the image with
//! [`PinholeCamera::try_project_in_image`](veila_geom::PinholeCamera::try_project_in_image) (points behind
//! the near plane or outside the image are skipped) and read the map at the **nearest pixel**
//! ([`ImagePoint::pixel`](veila_geom::ImagePoint::pixel)). A map may have a different resolution than the
//! camera image (monocular networks often predict at reduced size): pixel coordinates are then rescaled,
//! `u_map = (u + 0.5) · W_map / W_cam - 0.5` (same for `v`), before rounding. With
//! [`ProjectionFilter::zbuffer`] (default) only the nearest projected point of each map pixel is kept, so
//! points hidden behind a surface the camera sees are not compared against that surface.
//!
//! **CM-DC (depth consistency).** Monocular depth is relative, so the map `m` is first aligned to the LiDAR
//! depths `d` (camera-frame `z` of the projected points) over all kept pairs, then
//! `AbsRel = mean_i |m̂_i - d_i| / d_i` (lower is better) with `m̂ = s·m + t`:
//!
//! - [`DepthAlignment::Median`] (default, the standard protocol for scale-ambiguous monocular depth on
//!   KITTI): `s = median(d) / median(m)`, `t = 0`. Robust to outliers.
//! - [`DepthAlignment::LeastSquares`]: `(s, t) = argmin Σ (s·m_i + t - d_i)²` (closed form, MiDaS-style
//!   scale and shift); falls back to `t = 0, s = Σmd/Σm²` when all `m` are equal.
//! - [`DepthAlignment::None`]: `s = 1, t = 0`, for metric depth maps.
//! - [`DepthAlignment::Disparity`]: the map is affine-invariant *inverse* depth (what
//!   Depth-Anything-V2's relative checkpoints and MiDaS predict): `(s, t)` fit `s·m + t` to `1 / d`
//!   by least squares and `m̂ = 1 / (s·m + t)`; pairs where `s·m + t <= 0` count as the largest
//!   possible error, 1.
//!
//! Pixels whose map value is non-finite or `<= 0` are skipped, as are points with LiDAR depth outside
//! `(min_depth_m, max_depth_m)`.
//!
//! **CM-SC (semantic consistency).** The percentage (0–100) of kept points whose per-point label equals the
//! semantic map's label at their pixel. Points or pixels carrying [`ProjectionFilter::ignore_label`] are
//! skipped. Both label sets must use the same label space (map them beforehand).

use glam::Vec3;
use veila_geom::{PinholeCamera, Region};

use crate::{Error, Result, check_finite};

/// A row-major `height x width` image-aligned map.
#[derive(Debug, Clone, Copy)]
pub struct Map2d<'a, T> {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `height * width` values, row-major.
    pub data: &'a [T],
}

impl<'a, T> Map2d<'a, T> {
    /// Wraps `data`, checking its length.
    pub fn new(width: u32, height: u32, data: &'a [T]) -> Result<Self> {
        if width == 0 || height == 0 || data.len() != width as usize * height as usize {
            return Err(Error::ShapeMismatch {
                what: "map".into(),
                expected: format!(
                    "{width} x {height} = {} values (non-empty)",
                    width as usize * height as usize
                ),
                got: format!("{} values", data.len()),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }
}

/// Scale alignment of a relative depth map before the error is taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DepthAlignment {
    /// `s = median(lidar) / median(map)`, `t = 0`.
    #[default]
    Median,
    /// Least-squares scale and shift.
    LeastSquares,
    /// No alignment (metric depth).
    None,
    /// Least-squares scale and shift of the map to inverse depth (relative disparity maps).
    Disparity,
}

/// Which projected points take part.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectionFilter {
    /// Keep only the nearest point per map pixel.
    pub zbuffer: bool,
    /// Points with camera depth `<= min_depth_m` are skipped.
    pub min_depth_m: f32,
    /// Points with camera depth `>= max_depth_m` are skipped.
    pub max_depth_m: f32,
    /// A label that marks unlabelled points / pixels (CM-SC only).
    pub ignore_label: Option<u32>,
    /// Only points of this region are projected.
    pub region: Region,
}

impl Default for ProjectionFilter {
    fn default() -> Self {
        Self {
            zbuffer: true,
            min_depth_m: 0.0,
            max_depth_m: f32::INFINITY,
            ignore_label: None,
            region: Region::All,
        }
    }
}

/// Result of CM-DC.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DepthConsistency {
    /// Mean absolute relative error after alignment.
    pub abs_rel: f64,
    /// Alignment scale `s`.
    pub scale: f64,
    /// Alignment shift `t`.
    pub shift: f64,
    /// Number of compared points.
    pub points: usize,
}

/// Result of CM-SC.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SemanticConsistency {
    /// Percentage of compared points whose labels agree (0–100).
    pub percent: f64,
    /// Number of compared points.
    pub points: usize,
}

/// `(point index, map pixel index, camera depth)` of every kept projected point.
fn project_points<P: Copy + Into<Vec3>>(
    points: &[P],
    camera: &PinholeCamera,
    map_w: u32,
    map_h: u32,
    filter: &ProjectionFilter,
) -> Result<Vec<(usize, usize, f32)>> {
    let (sx, sy) = (
        map_w as f32 / camera.width as f32,
        map_h as f32 / camera.height as f32,
    );
    let mut hits = Vec::new();
    for (i, &p) in points.iter().enumerate() {
        let p: Vec3 = p.into();
        check_finite(p, "generated points", i)?;
        if !filter.region.contains(p) {
            continue;
        }
        let Some(ip) = camera.try_project_in_image(p) else {
            continue;
        };
        if !(ip.depth_m > filter.min_depth_m && ip.depth_m < filter.max_depth_m) {
            continue;
        }
        let u = (ip.u_px + 0.5) * sx - 0.5;
        let v = (ip.v_px + 0.5) * sy - 0.5;
        let (c, r) = ((u + 0.5).floor(), (v + 0.5).floor());
        if !(c >= 0.0 && r >= 0.0 && c < map_w as f32 && r < map_h as f32) {
            continue;
        }
        hits.push((i, r as usize * map_w as usize + c as usize, ip.depth_m));
    }
    if filter.zbuffer {
        // nearest point per pixel; ties broken by point index for determinism
        hits.sort_unstable_by(|a, b| a.1.cmp(&b.1).then(a.2.total_cmp(&b.2)).then(a.0.cmp(&b.0)));
        hits.dedup_by_key(|h| h.1);
    }
    Ok(hits)
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_unstable_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// CM-DC: depth consistency between generated points and a (relative) monocular depth map.
pub fn cm_depth_consistency<P: Copy + Into<Vec3>>(
    points: &[P],
    camera: &PinholeCamera,
    depth_map: &Map2d<'_, f32>,
    alignment: DepthAlignment,
    filter: &ProjectionFilter,
) -> Result<DepthConsistency> {
    let hits = project_points(points, camera, depth_map.width, depth_map.height, filter)?;
    let mut pairs: Vec<(f64, f64)> = Vec::with_capacity(hits.len());
    for (_, px, d) in hits {
        let m = depth_map.data[px];
        if m.is_finite() && m > 0.0 {
            pairs.push((m as f64, d as f64));
        }
    }
    if pairs.is_empty() {
        return Err(Error::NoPointsInWindow {
            what: "generated scan".into(),
            window: "camera image (with a valid depth-map pixel)".into(),
        });
    }
    // least squares of s·x + t to y over the pairs
    let fit = |xy: &[(f64, f64)]| -> (f64, f64) {
        let n = xy.len() as f64;
        let mx = xy.iter().map(|p| p.0).sum::<f64>() / n;
        let my = xy.iter().map(|p| p.1).sum::<f64>() / n;
        let sxx: f64 = xy.iter().map(|p| (p.0 - mx) * (p.0 - mx)).sum();
        let sxy: f64 = xy.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
        if sxx > 0.0 {
            let s = sxy / sxx;
            (s, my - s * mx)
        } else {
            let s = xy.iter().map(|p| p.0 * p.1).sum::<f64>()
                / xy.iter().map(|p| p.0 * p.0).sum::<f64>();
            (s, 0.0)
        }
    };
    let (scale, shift) = match alignment {
        DepthAlignment::None => (1.0, 0.0),
        DepthAlignment::Median => {
            let mut ms: Vec<f64> = pairs.iter().map(|p| p.0).collect();
            let mut ds: Vec<f64> = pairs.iter().map(|p| p.1).collect();
            (median(&mut ds) / median(&mut ms), 0.0)
        }
        DepthAlignment::LeastSquares => fit(&pairs),
        DepthAlignment::Disparity => {
            let inv: Vec<(f64, f64)> = pairs.iter().map(|&(m, d)| (m, 1.0 / d)).collect();
            fit(&inv)
        }
    };
    let predict = |m: f64| -> Option<f64> {
        let a = scale * m + shift;
        match alignment {
            DepthAlignment::Disparity => (a > 0.0).then(|| 1.0 / a),
            _ => Some(a),
        }
    };
    let abs_rel = pairs
        .iter()
        .map(|&(m, d)| predict(m).map_or(1.0, |p| (p - d).abs() / d))
        .sum::<f64>()
        / pairs.len() as f64;
    Ok(DepthConsistency {
        abs_rel,
        scale,
        shift,
        points: pairs.len(),
    })
}

/// The largest SemanticKITTI train id (`0` ignored, `1..=19` the classes).
pub const MAX_SEMANTIC_KITTI_TRAIN_ID: u32 = 19;

/// The SemanticKITTI raw ids (`semantic-kitti.yaml`'s `labels`): what a raw-id map may hold.
const SEMANTIC_KITTI_RAW_IDS: [u32; 34] = [
    0, 1, 10, 11, 13, 15, 16, 18, 20, 30, 31, 32, 40, 44, 48, 49, 50, 51, 52, 60, 70, 71, 72, 80,
    81, 99, 252, 253, 254, 255, 256, 257, 258, 259,
];

/// Refuse a class map for CM-SC that is not in SemanticKITTI train ids (`0..=19`), the space the
/// per-point labels are in: comparing raw ids (10 car, 40 road, ..., what `veila simulate` writes
/// to `semantic_2/`) with train ids would report near 0 % agreement as if it were a result. The
/// error says whether the map looks like raw ids. `what` names the map.
pub fn check_train_ids(labels: &[u32], what: &str) -> Result<()> {
    let Some(index) = labels.iter().position(|&l| l > MAX_SEMANTIC_KITTI_TRAIN_ID) else {
        return Ok(());
    };
    let raw = labels.iter().all(|l| SEMANTIC_KITTI_RAW_IDS.contains(l));
    Err(Error::LabelSpace {
        what: what.to_string(),
        label: labels[index],
        index,
        space: "SemanticKITTI train (0..=19)",
        hint: if raw {
            "every value is a SemanticKITTI raw id (10 car, 40 road, ...): map it with the learning map (raw ids)".into()
        } else {
            "map the classes to SemanticKITTI train ids first".into()
        },
    })
}

/// CM-SC: semantic agreement between per-point labels of the generated points and a semantic map.
pub fn cm_semantic_consistency<P: Copy + Into<Vec3>, L: Copy + Into<u32>, M: Copy + Into<u32>>(
    points: &[P],
    point_labels: &[L],
    camera: &PinholeCamera,
    semantic_map: &Map2d<'_, M>,
    filter: &ProjectionFilter,
) -> Result<SemanticConsistency> {
    if point_labels.len() != points.len() {
        return Err(Error::ShapeMismatch {
            what: "point labels".into(),
            expected: format!("{} labels (one per point)", points.len()),
            got: format!("{}", point_labels.len()),
        });
    }
    let hits = project_points(
        points,
        camera,
        semantic_map.width,
        semantic_map.height,
        filter,
    )?;
    let (mut agree, mut total) = (0usize, 0usize);
    for (i, px, _) in hits {
        let (lp, lm): (u32, u32) = (point_labels[i].into(), semantic_map.data[px].into());
        if filter.ignore_label.is_some_and(|ig| ig == lp || ig == lm) {
            continue;
        }
        total += 1;
        agree += usize::from(lp == lm);
    }
    if total == 0 {
        return Err(Error::NoPointsInWindow {
            what: "generated scan".into(),
            window: "camera image (labelled)".into(),
        });
    }
    Ok(SemanticConsistency {
        percent: 100.0 * agree as f64 / total as f64,
        points: total,
    })
}

/// Cityscapes train ids (what the `nvidia/segformer-*-finetuned-cityscapes-*` checkpoints predict,
/// 0..=18) to SemanticKITTI train ids (1..=19, 0 = ignored), for CM-SC with a Cityscapes
/// segmenter: road → road, sidewalk → sidewalk, building and wall → building, fence → fence,
/// pole → pole, traffic light and sign → traffic-sign, vegetation → vegetation, terrain → terrain,
/// sky → ignored, person → person, rider → bicyclist, car → car, truck → truck, bus and train →
/// other-vehicle, motorcycle → motorcycle, bicycle → bicycle. Ids outside 0..=18 are ignored.
pub fn cityscapes_to_semantickitti(cityscapes_train_id: u32) -> u32 {
    const MAP: [u32; 19] = [
        9, 11, 13, 13, 14, 18, 19, 19, 15, 17, 0, 6, 7, 1, 4, 5, 5, 3, 2,
    ];
    MAP.get(cityscapes_train_id as usize).copied().unwrap_or(0)
}
