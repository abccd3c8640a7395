//! Exact nearest-neighbour queries on a point set through an [`obvhs`] BVH.
//!
//! obvhs builds a binary BVH ([`obvhs::bvh2::Bvh2`], PLOC builder, a light reinsertion pass, leaves collapsed
//! to at most 8 points) over the degenerate boxes of the points; it offers ray and box traversals but no
//! nearest query, so
//! [`PointIndex::nearest`] walks the nodes itself: depth-first branch and bound on the squared point-to-box
//! distance with an explicit stack, nearer child first, pruning every node whose box is farther than the
//! best point found so far.
//!
//! Exactness: box distances are evaluated in `f32` with a relative safety margin of `1e-6` (larger than the
//! worst-case `f32` rounding of a squared distance) and an overflowed box distance never prunes, while the
//! candidate point distances are evaluated in `f64` from the `f32` coordinates. The returned squared
//! distance is therefore the exact `f64` minimum (ties between equidistant points may pick either index),
//! the same value a brute-force `f64` search or `scipy.spatial.cKDTree` gives.

use glam::{Vec3, Vec3A};
use obvhs::{
    aabb::Aabb,
    bvh2::{Bvh2, leaf_collapser::collapse, reinsertion::ReinsertionOptimizer},
    ploc::{PlocBuilder, PlocSearchDistance, SortPrecision},
};
use rayon::prelude::*;

use crate::{Error, Result, check_finite};

/// Result of a nearest-neighbour query.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Nearest {
    /// Squared Euclidean distance, `f64`.
    pub dist2: f64,
    /// Index of the nearest point in the slice the index was built from.
    pub index: usize,
}

/// A BVH over a point set answering exact nearest-neighbour queries.
#[derive(Clone)]
pub struct PointIndex {
    bvh: Bvh2,
    /// Points in BVH primitive order (leaf ranges are contiguous).
    points: Vec<Vec3A>,
    /// `original[k]` is the caller's index of `points[k]`.
    original: Vec<u32>,
    /// Every point of the set in leaf order, duplicates included, when the set has coincident
    /// points (`points` holds each once: a BVH over many copies of one point is a chain as deep
    /// as the copies are many, and every query would walk it).
    all: Option<Vec<Vec3A>>,
}

impl std::fmt::Debug for PointIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PointIndex")
            .field("points", &self.len())
            .field("distinct", &self.points.len())
            .field("nodes", &self.bvh.nodes.len())
            .field("max_depth", &self.bvh.max_depth)
            .finish()
    }
}

/// Points per leaf after collapsing the BVH.
const MAX_LEAF_POINTS: u32 = 8;

#[inline]
fn dist2_f64(a: Vec3A, b: Vec3A) -> f64 {
    let dx = a.x as f64 - b.x as f64;
    let dy = a.y as f64 - b.y as f64;
    let dz = a.z as f64 - b.z as f64;
    dx * dx + dy * dy + dz * dz
}

#[inline]
fn box_dist2(aabb: &Aabb, q: Vec3A) -> f32 {
    let d = (aabb.min - q).max(q - aabb.max).max(Vec3A::ZERO);
    d.length_squared()
}

/// Whether a node whose box lies at squared distance `lb` may still hold a point closer than `best`.
#[inline]
fn may_improve(lb: f32, best: f64) -> bool {
    !lb.is_finite() || (lb as f64) * (1.0 - 1e-6) < best
}

/// [`may_improve`] for a child node of box `aabb` at squared distance `lb` (f32). A box of
/// coincident points (`min == max`, the points themselves) is judged exactly: its points are all
/// at the f64 distance of its corner, so a tie with `best` cannot improve. Without this, many
/// duplicates of one point at the same distance as the best (two sets of coincident points)
/// defeat the safety margin and every query visits every node: quadratic.
#[inline]
fn child_may_improve(aabb: &Aabb, lb: f32, q: Vec3A, best: f64) -> bool {
    if aabb.min == aabb.max {
        return dist2_f64(aabb.min, q) < best;
    }
    may_improve(lb, best)
}

/// The most points one [`PointIndex`] takes (4 Mi: 30 times a KITTI scan). The index and its build
/// need some 300 bytes per point, and Chamfer and MMD-CD hold an index per
/// scan: two scans of 16 Mi points (what a scan file may hold) would need ~10 GB, so they are
/// refused with an error naming the scan before anything is allocated.
pub const MAX_INDEX_POINTS: usize = 1 << 22;

/// Bytes per point of a [`PointIndex`] and its build, roughly (points, boxes, nodes, sort keys).
const INDEX_BYTES_PER_POINT: usize = 300;

impl PointIndex {
    /// Builds the index. Errors on an empty set ([`Error::Empty`]), more than [`MAX_INDEX_POINTS`] points, or a
    /// non-finite coordinate ([`Error::NonFinite`]); `what` names the input in errors.
    pub fn build<P: Copy + Into<Vec3>>(points: &[P], what: &str) -> Result<Self> {
        if points.is_empty() {
            return Err(Error::empty(what));
        }
        if points.len() > MAX_INDEX_POINTS {
            return Err(Error::InvalidParameter {
                name: "points",
                reason: format!(
                    "{what}: {} points, more than the {MAX_INDEX_POINTS} a nearest-neighbour index \
                     takes (about {} GB of memory at that size)",
                    points.len(),
                    MAX_INDEX_POINTS * INDEX_BYTES_PER_POINT / (1 << 30)
                ),
            });
        }
        let mut pts: Vec<Vec3A> = Vec::with_capacity(points.len());
        for (i, &p) in points.iter().enumerate() {
            let p: Vec3 = p.into();
            check_finite(p, what, i)?;
            pts.push(p.into());
        }
        // coincident points once (with how many there are), in the order of the caller's first
        let key = |p: Vec3A| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
        let mut order: Vec<u32> = (0..pts.len() as u32).collect();
        order.par_sort_by_key(|&i| key(pts[i as usize]));
        let mut first: Vec<u32> = Vec::with_capacity(pts.len());
        let mut copies: Vec<u32> = Vec::with_capacity(pts.len());
        for &i in &order {
            match first.last() {
                Some(&f) if key(pts[f as usize]) == key(pts[i as usize]) => {
                    *copies.last_mut().expect("one per first") += 1;
                }
                _ => {
                    first.push(i);
                    copies.push(1);
                }
            }
        }
        drop(order);
        let duplicates = first.len() < pts.len();
        let (pts, caller_index) = if duplicates {
            let mut by_index: Vec<(u32, u32)> = first.iter().copied().zip(copies).collect();
            by_index.sort_unstable();
            copies = by_index.iter().map(|&(_, c)| c).collect();
            let caller: Vec<u32> = by_index.iter().map(|&(i, _)| i).collect();
            (caller.iter().map(|&i| pts[i as usize]).collect(), caller)
        } else {
            (pts, Vec::new())
        };
        let aabbs: Vec<Aabb> = pts.iter().map(|&p| Aabb::from_point(p)).collect();
        let indices: Vec<u32> = (0..pts.len() as u32).collect();
        let mut bvh = PlocBuilder::with_capacity(aabbs.len()).build(
            PlocSearchDistance::Minimum,
            &aabbs,
            indices,
            SortPrecision::U64,
            0,
        );
        // a traversal cost of `MAX_LEAF_POINTS` makes the SAH test always pass (point boxes have no area), so
        // every subtree of at most `MAX_LEAF_POINTS` points becomes one leaf
        // a light reinsertion pass (5 % of the nodes) trades ~10 ms of build for ~20 % faster queries on
        // KITTI scans
        ReinsertionOptimizer::default().run(&mut bvh, 0.05, None);
        collapse(&mut bvh, MAX_LEAF_POINTS, MAX_LEAF_POINTS as f32);
        let prims = bvh.primitive_indices.clone();
        let points: Vec<Vec3A> = prims.iter().map(|&i| pts[i as usize]).collect();
        let (original, all) = if duplicates {
            let all = prims
                .iter()
                .flat_map(|&i| std::iter::repeat_n(pts[i as usize], copies[i as usize] as usize))
                .collect();
            let original = prims.iter().map(|&i| caller_index[i as usize]).collect();
            (original, Some(all))
        } else {
            (prims, None)
        };
        Ok(Self {
            bvh,
            points,
            original,
            all,
        })
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.leaf_points().len()
    }

    /// Always `false` (an index is never empty).
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The points in BVH leaf order: spatially coherent, the best order to query a whole set in.
    pub fn points_in_leaf_order(&self) -> impl ExactSizeIterator<Item = Vec3> + '_ {
        self.leaf_points().iter().map(|&p| p.into())
    }

    /// The nearest indexed point to `query`. A non-finite query gives `dist2 = NaN` or `inf`.
    pub fn nearest(&self, query: Vec3) -> Nearest {
        let mut stack = Vec::with_capacity(self.bvh.max_depth + 2);
        let (d, k, _) = self.nearest_impl(query.into(), f64::INFINITY, u32::MAX, &mut stack);
        Nearest {
            dist2: d,
            index: self
                .original
                .get(k as usize)
                .map_or(usize::MAX, |&i| i as usize),
        }
    }

    /// How many nodes the search for the nearest point to `query` visits (a diagnostic of the
    /// tree's pruning: about its depth for well-spread points, never all of them for duplicates).
    pub fn nodes_visited(&self, query: Vec3) -> usize {
        let mut stack = Vec::with_capacity(self.bvh.max_depth + 2);
        self.nearest_impl(query.into(), f64::INFINITY, u32::MAX, &mut stack)
            .2
    }

    /// Branch and bound from an initial upper bound `(best, best_k)` (`best_k` an internal point index or
    /// `u32::MAX`). Returns the squared distance, the internal index and the nodes visited.
    fn nearest_impl(
        &self,
        q: Vec3A,
        mut best: f64,
        mut best_k: u32,
        stack: &mut Vec<(u32, f32)>,
    ) -> (f64, u32, usize) {
        let nodes = &self.bvh.nodes;
        stack.clear();
        stack.push((0, 0.0));
        let mut visited = 0;
        while let Some((ni, lb)) = stack.pop() {
            if !may_improve(lb, best) {
                continue;
            }
            visited += 1;
            let node = &nodes[ni as usize];
            if node.is_leaf() {
                let start = node.first_index as usize;
                let end = start + node.prim_count as usize;
                for k in start..end {
                    let p = self.points[k];
                    // cheap f32 screen with the same safety margin as the box test, exact f64 distance after
                    if may_improve((p - q).length_squared(), best) {
                        let d = dist2_f64(p, q);
                        if d < best {
                            best = d;
                            best_k = k as u32;
                        }
                    }
                }
                continue;
            }
            let c0 = node.first_index;
            let c1 = c0 + 1;
            let (a0, a1) = (nodes[c0 as usize].aabb(), nodes[c1 as usize].aabb());
            let d0 = box_dist2(a0, q);
            let d1 = box_dist2(a1, q);
            let (near, dn, an, far, df, af) = if d0 <= d1 {
                (c0, d0, a0, c1, d1, a1)
            } else {
                (c1, d1, a1, c0, d0, a0)
            };
            if child_may_improve(af, df, q, best) {
                stack.push((far, df));
            }
            if child_may_improve(an, dn, q, best) {
                stack.push((near, dn));
            }
        }
        (best, best_k, visited)
    }

    /// Squared nearest distances for every query point, in query order (parallel).
    pub fn nearest_dist2_all<P: Copy + Into<Vec3> + Sync>(&self, queries: &[P]) -> Vec<f64> {
        let mut out = vec![0.0; queries.len()];
        out.par_chunks_mut(1024)
            .zip(queries.par_chunks(1024))
            .for_each(|(o, qs)| {
                let mut stack = Vec::with_capacity(self.bvh.max_depth + 2);
                let mut hint = u32::MAX;
                for (slot, &q) in o.iter_mut().zip(qs) {
                    let q: Vec3A = Into::<Vec3>::into(q).into();
                    let (d, k) = self.query_with_hint(q, hint, &mut stack);
                    *slot = d;
                    hint = k;
                }
            });
        out
    }

    #[inline]
    fn query_with_hint(&self, q: Vec3A, hint: u32, stack: &mut Vec<(u32, f32)>) -> (f64, u32) {
        let (b, k) = match self.points.get(hint as usize) {
            Some(&p) => (dist2_f64(p, q), hint),
            None => (f64::INFINITY, u32::MAX),
        };
        let (d, k, _) = self.nearest_impl(q, b, k, stack);
        (d, k)
    }

    /// `Σ_q min_p ‖q - p‖²` over the query points (parallel; deterministic summation order). Consecutive
    /// queries warm-start from the previous query's neighbour, so spatially coherent query orders (scan
    /// order, [`PointIndex::points_in_leaf_order`]) are fastest.
    pub fn sum_nearest_dist2<I>(&self, queries: I) -> f64
    where
        I: IntoParallelIterator,
        I::Iter: IndexedParallelIterator<Item = Vec3>,
    {
        let partial: Vec<f64> = queries
            .into_par_iter()
            .chunks(1024)
            .map(|qs| {
                let mut stack = Vec::with_capacity(self.bvh.max_depth + 2);
                let mut hint = u32::MAX;
                let mut s = 0.0;
                for q in qs {
                    let (d, k) = self.query_with_hint(q.into(), hint, &mut stack);
                    s += d;
                    hint = k;
                }
                s
            })
            .collect();
        partial.iter().sum()
    }

    /// Every point (duplicates included) in leaf order.
    pub(crate) fn leaf_points(&self) -> &[Vec3A] {
        self.all.as_deref().unwrap_or(&self.points)
    }
}

/// Brute-force nearest neighbour (`f64`), the reference the BVH is tested against.
pub fn nearest_brute_force(points: &[Vec3], query: Vec3) -> Option<Nearest> {
    let q: Vec3A = query.into();
    points
        .iter()
        .enumerate()
        .map(|(i, &p)| Nearest {
            dist2: dist2_f64(p.into(), q),
            index: i,
        })
        .min_by(|a, b| a.dist2.total_cmp(&b.dist2))
}
