//! Chamfer distance in PyTorch3D's convention and the minimum matching distance (MMD-CD).
//!
//! `CD(A, B) = mean_{a∈A} min_{b∈B} ‖a-b‖² + mean_{b∈B} min_{a∈A} ‖a-b‖²` — squared distances, each
//! direction averaged over its own points, the two means **summed** (`pytorch3d.loss.chamfer_distance` with
//! its defaults `point_reduction="mean"`, `batch_reduction="mean"`, single pair). All points are used, no
//! range filter. Nearest neighbours come from the BVH of [`crate::nn`]; sums are in `f64`.
//!
//! MMD-CD (minimum matching distance, Achlioptas et al. 2018): for each reference scan the smallest Chamfer
//! distance to any generated scan, averaged over the reference scans.

use glam::Vec3;
use rayon::prelude::*;

use crate::nn::PointIndex;
use crate::{Error, Result};

/// The two directions of a Chamfer distance.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Chamfer {
    /// `mean_{a∈A} min_{b∈B} ‖a-b‖²`.
    pub a_to_b: f64,
    /// `mean_{b∈B} min_{a∈A} ‖a-b‖²`.
    pub b_to_a: f64,
}

impl Chamfer {
    /// `a_to_b + b_to_a` (PyTorch3D's value).
    pub fn value(&self) -> f64 {
        self.a_to_b + self.b_to_a
    }
}

/// Chamfer distance between two point sets (builds both BVHs). Errors on empty sets or non-finite points.
pub fn chamfer_distance<P: Copy + Into<Vec3> + Sync>(a: &[P], b: &[P]) -> Result<Chamfer> {
    let (ia, ib) = rayon::join(
        || PointIndex::build(a, "first point set"),
        || PointIndex::build(b, "second point set"),
    );
    let (ia, ib) = (ia?, ib?);
    // query in the caller's order (scan order is spatially coherent, which the warm start exploits)
    let (sab, sba) = rayon::join(
        || ib.sum_nearest_dist2(a.par_iter().map(|&p| p.into())),
        || ia.sum_nearest_dist2(b.par_iter().map(|&p| p.into())),
    );
    Ok(Chamfer {
        a_to_b: sab / a.len() as f64,
        b_to_a: sba / b.len() as f64,
    })
}

/// Chamfer distance between two indexed point sets (each set is queried in its own leaf order).
pub fn chamfer_distance_indexed(a: &PointIndex, b: &PointIndex) -> Chamfer {
    let (sab, sba) = rayon::join(
        || b.sum_nearest_dist2(a.leaf_points().par_iter().map(|&p| Vec3::from(p))),
        || a.sum_nearest_dist2(b.leaf_points().par_iter().map(|&p| Vec3::from(p))),
    );
    Chamfer {
        a_to_b: sab / a.len() as f64,
        b_to_a: sba / b.len() as f64,
    }
}

/// MMD-CD: `mean_{r∈reference} min_{g∈generated} CD(g, r)`.
pub fn minimum_matching_distance(
    generated: &[PointIndex],
    reference: &[PointIndex],
) -> Result<f64> {
    if generated.is_empty() {
        return Err(Error::empty("generated set"));
    }
    if reference.is_empty() {
        return Err(Error::empty("reference set"));
    }
    let mins: Vec<f64> = reference
        .par_iter()
        .map(|r| {
            generated
                .iter()
                .map(|g| chamfer_distance_indexed(g, r).value())
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    Ok(mins.iter().sum::<f64>() / mins.len() as f64)
}
