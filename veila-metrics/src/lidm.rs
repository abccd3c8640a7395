//! LiDM's minimum matching distance on BEV occupancy (protocol `lidm`).
//!
//! Following `lidm/eval` of LiDAR-Diffusion (64-beam settings, [`LidmBevConfig::kitti`]):
//!
//! 1. keep points with `-50 < x < 50` and `-50 < y < 50` (strict; no range filter — LiDM's inputs are
//!    already limited to `1 m < r < 56 m` by its range-image round trip);
//! 2. cell `(floor(x / 0.5), floor(y / 0.5))`, occupied cells deduplicated; coordinates shifted by
//!    `ceil(-50 / 0.5) = -100` and divided by the grid size `ceil(100 / 0.5) = 200`, giving 2-D points in
//!    `[0, 1)²`;
//! 3. `CD₂(A, B) = (mean_{a∈A} min_b ‖a-b‖² + mean_{b∈B} min_a ‖a-b‖²) / 2` (squared distances, the two means
//!    **averaged**, as LiDM's `(dist1.mean() + dist2.mean()) / 2` over its CUDA `chamfer_2D`);
//! 4. MMD = mean over reference scans of the minimum `CD₂` to any generated scan. LiDM prints it × 10⁴
//!    ([`LIDM_PAPER_SCALE`]).
//!
//! Because the points live on a grid, nearest distances are read from an exact squared Euclidean distance
//! transform (Felzenszwalb–Huttenlocher) of each occupancy grid, in integer cell units, so every `CD₂` is
//! exact. LiDM's coordinates are `float32`; the difference is below `1e-7` relative.

use glam::Vec3;
use rayon::prelude::*;
use veila_geom::Region;

use crate::{Error, Result, check_finite};

/// Factor by which LiDM prints its MMD (values are reported "× 10⁻⁴").
pub const LIDM_PAPER_SCALE: f64 = 1e4;

/// Grid parameters of the LiDM BEV occupancy.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LidmBevConfig {
    /// Window `(-half_extent_m, half_extent_m)` in x and y.
    pub half_extent_m: f64,
    /// Cell size in metres.
    pub cell_m: f64,
}

impl Default for LidmBevConfig {
    fn default() -> Self {
        Self::kitti()
    }
}

impl LidmBevConfig {
    /// 64-beam (KITTI) setting: ±50 m, 0.5 m cells.
    pub const fn kitti() -> Self {
        Self {
            half_extent_m: 50.0,
            cell_m: 0.5,
        }
    }

    /// 32-beam (nuScenes) setting: ±30 m, 0.5 m cells.
    pub const fn nuscenes() -> Self {
        Self {
            half_extent_m: 30.0,
            cell_m: 0.5,
        }
    }

    /// The 64-beam grid of LiDM's JSD: ±50 m, 0.05 m cells (2000 x 2000).
    pub const fn kitti_jsd() -> Self {
        Self {
            half_extent_m: 50.0,
            cell_m: 0.05,
        }
    }

    /// The 32-beam grid of LiDM's JSD: ±30 m, 0.05 m cells (1200 x 1200).
    pub const fn nuscenes_jsd() -> Self {
        Self {
            half_extent_m: 30.0,
            cell_m: 0.05,
        }
    }

    fn grid(&self) -> Result<(i64, i64)> {
        if !(self.half_extent_m.is_finite()
            && self.half_extent_m > 0.0
            && self.cell_m.is_finite()
            && self.cell_m > 0.0)
        {
            return Err(Error::InvalidParameter {
                name: "LidmBevConfig",
                reason: format!(
                    "half_extent_m {} and cell_m {} must be finite and > 0",
                    self.half_extent_m, self.cell_m
                ),
            });
        }
        let size = ((2.0 * self.half_extent_m) / self.cell_m).ceil();
        if size > 8192.0 {
            return Err(Error::InvalidParameter {
                name: "LidmBevConfig",
                reason: format!("grid of {size} cells per axis"),
            });
        }
        let min_bound = (-self.half_extent_m / self.cell_m).ceil() as i64;
        Ok((size as i64, min_bound))
    }
}

/// The occupied cells of one scan.
#[derive(Debug, Clone, PartialEq)]
pub struct BevOccupancy {
    /// Cells per axis.
    pub size: usize,
    /// Occupied cells as `ix * size + iy`, sorted, unique.
    pub cells: Vec<u32>,
}

/// The LiDM occupancy of the points of one scan in `region`. Errors on non-finite coordinates.
pub fn lidm_bev_occupancy<P: Copy + Into<Vec3>>(
    points: &[P],
    cfg: &LidmBevConfig,
    region: Region,
    what: &str,
) -> Result<BevOccupancy> {
    let (size, min_bound) = cfg.grid()?;
    let h = cfg.half_extent_m;
    let mut cells = Vec::new();
    for (i, &p) in points.iter().enumerate() {
        let p: Vec3 = p.into();
        check_finite(p, what, i)?;
        if !region.contains(p) {
            continue;
        }
        let (x, y) = (p.x as f64, p.y as f64);
        if !(x > -h && x < h && y > -h && y < h) {
            continue;
        }
        let ix = (x / cfg.cell_m).floor() as i64 - min_bound;
        let iy = (y / cfg.cell_m).floor() as i64 - min_bound;
        if (0..size).contains(&ix) && (0..size).contains(&iy) {
            cells.push((ix * size + iy) as u32);
        }
    }
    cells.sort_unstable();
    cells.dedup();
    Ok(BevOccupancy {
        size: size as usize,
        cells,
    })
}

/// The LiDM occupancy in LiDM's own `float32` arithmetic: the window test and `floor(x / cell)` are done
/// on `float32` coordinates with a `float32` cell size, as `lidm/eval/metric_utils.py` does on its
/// `float32` point clouds. For the 0.5 m cells of the MMD this equals [`lidm_bev_occupancy`]; for the
/// 0.05 m cells of the JSD (`0.05` is not a binary fraction) it can differ for points within one
/// `float32` ulp of a cell edge, so the protocol pipelines use this one.
pub fn lidm_bev_occupancy_f32<P: Copy + Into<Vec3>>(
    points: &[P],
    cfg: &LidmBevConfig,
    region: Region,
    what: &str,
) -> Result<BevOccupancy> {
    let (size, min_bound) = cfg.grid()?;
    let h = cfg.half_extent_m as f32;
    let cell = cfg.cell_m as f32;
    let mut cells = Vec::new();
    for (i, &p) in points.iter().enumerate() {
        let p: Vec3 = p.into();
        check_finite(p, what, i)?;
        if !region.contains(p) {
            continue;
        }
        if !(p.x > -h && p.x < h && p.y > -h && p.y < h) {
            continue;
        }
        let ix = (p.x / cell).floor() as i64 - min_bound;
        let iy = (p.y / cell).floor() as i64 - min_bound;
        if (0..size).contains(&ix) && (0..size).contains(&iy) {
            cells.push((ix * size + iy) as u32);
        }
    }
    cells.sort_unstable();
    cells.dedup();
    Ok(BevOccupancy {
        size: size as usize,
        cells,
    })
}

/// LiDM's JSD: every scan adds 1 to each cell it occupies (0.05 m cells in LiDM, see
/// [`LidmBevConfig::kitti_jsd`]), the counts are summed over each set, normalised, and compared with
/// [`crate::dist::jensen_shannon_distance`] (the JS **distance**, `scipy` semantics).
pub fn jsd_lidm(generated: &[BevOccupancy], reference: &[BevOccupancy]) -> Result<f64> {
    let size = generated.first().map(|o| o.size).unwrap_or(0);
    for (set, what) in [(generated, "generated"), (reference, "reference")] {
        if set.is_empty() {
            return Err(Error::empty(format!("{what} set")));
        }
        if let Some(i) = set.iter().position(|o| o.size != size) {
            return Err(Error::ShapeMismatch {
                what: format!("{what} occupancy {i}"),
                expected: format!("{size} cells per axis"),
                got: format!("{}", set[i].size),
            });
        }
        if set.iter().all(|o| o.cells.is_empty()) {
            return Err(Error::NoPointsInWindow {
                what: format!("every {what} scan"),
                window: "LiDM BEV".into(),
            });
        }
    }
    // the two summed volumes over the union of occupied cells (cells empty in both add nothing)
    let mut all: Vec<(u32, bool)> = Vec::new();
    for (set, is_gen) in [(generated, true), (reference, false)] {
        for o in set {
            all.extend(o.cells.iter().map(|&c| (c, is_gen)));
        }
    }
    all.sort_unstable();
    let (mut p, mut q) = (Vec::new(), Vec::new());
    let mut last = None;
    for (c, is_gen) in all {
        if last != Some(c) {
            p.push(0.0);
            q.push(0.0);
            last = Some(c);
        }
        let k = p.len() - 1;
        if is_gen {
            p[k] += 1.0;
        } else {
            q[k] += 1.0;
        }
    }
    crate::dist::jensen_shannon_distance(&p, &q)
}

/// "No occupied cell in this line": larger than any squared distance on a grid of at most 8192 cells per
/// axis, and small enough that `FAR + q²` stays an exact `f64` integer.
const FAR: f64 = 1e12;

/// 1-D squared distance transform, `out[q] = min_p (q - p)² + f[p]` (lower envelope of parabolas,
/// Felzenszwalb & Huttenlocher 2012). `v`, `z` are scratch buffers of length `n` and `n + 1`.
fn edt_1d(f: &[f64], out: &mut [f64], v: &mut [usize], z: &mut [f64]) {
    let n = f.len();
    let inter = |q: usize, p: usize| {
        ((f[q] + (q * q) as f64) - (f[p] + (p * p) as f64)) / (2.0 * q as f64 - 2.0 * p as f64)
    };
    let mut k = 0usize;
    v[0] = 0;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    for q in 1..n {
        let mut s = inter(q, v[k]);
        while s <= z[k] {
            k -= 1;
            s = inter(q, v[k]);
        }
        k += 1;
        v[k] = q;
        z[k] = s;
        z[k + 1] = f64::INFINITY;
    }
    k = 0;
    for q in 0..n {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let d = q as f64 - v[k] as f64;
        out[q] = d * d + f[v[k]];
    }
}

/// Exact squared Euclidean distance (in cells) from every cell to the nearest occupied cell.
pub(crate) fn squared_edt(occ: &BevOccupancy) -> Vec<f64> {
    let n = occ.size;
    let mut grid = vec![FAR; n * n];
    for &c in &occ.cells {
        grid[c as usize] = 0.0;
    }
    let mut f = vec![0.0; n];
    let mut out = vec![0.0; n];
    let mut v = vec![0usize; n];
    let mut z = vec![0.0; n + 1];
    // along iy (contiguous) for each ix
    for ix in 0..n {
        let row = &mut grid[ix * n..(ix + 1) * n];
        f.copy_from_slice(row);
        edt_1d(&f, &mut out, &mut v, &mut z);
        row.copy_from_slice(&out);
    }
    // along ix for each iy
    for iy in 0..n {
        for ix in 0..n {
            f[ix] = grid[ix * n + iy];
        }
        edt_1d(&f, &mut out, &mut v, &mut z);
        for ix in 0..n {
            grid[ix * n + iy] = out[ix];
        }
    }
    grid
}

fn check_occ_set(set: &[BevOccupancy], what: &str, size: usize) -> Result<()> {
    if set.is_empty() {
        return Err(Error::empty(format!("{what} set")));
    }
    for (i, o) in set.iter().enumerate() {
        if o.size != size {
            return Err(Error::ShapeMismatch {
                what: format!("{what} occupancy {i}"),
                expected: format!("{size} cells per axis"),
                got: format!("{}", o.size),
            });
        }
        if o.cells.is_empty() {
            return Err(Error::NoPointsInWindow {
                what: format!("{what} scan {i}"),
                window: "LiDM BEV".into(),
            });
        }
    }
    Ok(())
}

/// LiDM's 2-D Chamfer distance between two occupancies (normalised coordinates, see the module docs).
pub fn chamfer_2d_lidm(a: &BevOccupancy, b: &BevOccupancy) -> Result<f64> {
    check_occ_set(std::slice::from_ref(a), "first", a.size)?;
    check_occ_set(std::slice::from_ref(b), "second", a.size)?;
    let (ea, eb) = (squared_edt(a), squared_edt(b));
    Ok(cd2_with_edts(a, &ea, b, &eb))
}

fn cd2_with_edts(a: &BevOccupancy, ea: &[f64], b: &BevOccupancy, eb: &[f64]) -> f64 {
    let s = (a.size * a.size) as f64;
    let ab: f64 = a.cells.iter().map(|&c| eb[c as usize]).sum::<f64>() / a.cells.len() as f64;
    let ba: f64 = b.cells.iter().map(|&c| ea[c as usize]).sum::<f64>() / b.cells.len() as f64;
    (ab / s + ba / s) / 2.0
}

/// LiDM's MMD: mean over `reference` of the minimum [`chamfer_2d_lidm`] to any of `generated`.
pub fn mmd_lidm(generated: &[BevOccupancy], reference: &[BevOccupancy]) -> Result<f64> {
    let size = generated.first().map(|o| o.size).unwrap_or(0);
    check_occ_set(generated, "generated", size)?;
    check_occ_set(reference, "reference", size)?;
    let mut best = vec![f64::INFINITY; reference.len()];
    // bounded memory: distance transforms of at most BLOCK generated scans at a time
    const BLOCK: usize = 128;
    for block in generated.chunks(BLOCK) {
        let edts: Vec<Vec<f64>> = block.par_iter().map(squared_edt).collect();
        best.par_iter_mut()
            .zip(reference.par_iter())
            .for_each(|(b, r)| {
                let er = squared_edt(r);
                for (g, eg) in block.iter().zip(&edts) {
                    *b = b.min(cd2_with_edts(r, &er, g, eg));
                }
            });
    }
    Ok(best.iter().sum::<f64>() / best.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute(occ: &BevOccupancy) -> Vec<f64> {
        let n = occ.size;
        (0..n * n)
            .map(|c| {
                let (x, y) = ((c / n) as f64, (c % n) as f64);
                occ.cells
                    .iter()
                    .map(|&o| {
                        let (ox, oy) = ((o as usize / n) as f64, (o as usize % n) as f64);
                        (x - ox) * (x - ox) + (y - oy) * (y - oy)
                    })
                    .fold(f64::INFINITY, f64::min)
            })
            .collect()
    }

    #[test]
    fn edt_matches_brute_force() {
        let mut state = 12345u64;
        for trial in 0..20 {
            let n = 7 + trial % 9;
            let mut cells = Vec::new();
            for c in 0..n * n {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                if (state >> 33).is_multiple_of(7) || c == (trial * 13) % (n * n) {
                    cells.push(c as u32);
                }
            }
            let occ = BevOccupancy { size: n, cells };
            assert_eq!(squared_edt(&occ), brute(&occ), "trial {trial}");
        }
    }
}
