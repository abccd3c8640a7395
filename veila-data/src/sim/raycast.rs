//! Closest-hit and any-hit ray casting over a triangle mesh through an `obvhs` [`Bvh2`].
//!
//! The BVH only culls: every candidate triangle is tested with our own Möller–Trumbore intersection
//! ([`intersect_triangle`]), which accepts barycentric coordinates down to `-BARY_EPS` so that a ray
//! through an edge shared by two triangles is never lost between them ("watertight enough").

use std::time::Duration;

use glam::{Vec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::bvh2::Bvh2;
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;

use super::mesh::{Mesh, Surface};

/// Barycentric slack of [`intersect_triangle`]: closes cracks between neighbouring triangles.
pub const BARY_EPS: f32 = 1e-6;

/// A ray-triangle intersection in ray parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangleHit {
    /// Distance along the ray (in units of the direction's length).
    pub t: f32,
    /// Barycentric coordinate of `b - a`.
    pub u: f32,
    /// Barycentric coordinate of `c - a`.
    pub v: f32,
}

/// Möller–Trumbore ray-triangle intersection, two-sided, for `t` in `[t_min, t_max]`.
///
/// Returns `None` for a miss, a ray parallel to the triangle's plane, a degenerate triangle or
/// non-finite input.
#[inline]
pub fn intersect_triangle(
    origin: Vec3A,
    dir: Vec3A,
    a: Vec3A,
    e1: Vec3A,
    e2: Vec3A,
    t_min: f32,
    t_max: f32,
) -> Option<TriangleHit> {
    let p = dir.cross(e2);
    let det = e1.dot(p);
    // relative parallel test: |det| tiny compared with |e1||e2||dir|
    if det.abs()
        <= 1e-12 * (e1.length_squared() * e2.length_squared() * dir.length_squared()).sqrt()
        || !det.is_finite()
    {
        return None;
    }
    let inv = 1.0 / det;
    let s = origin - a;
    let u = s.dot(p) * inv;
    if !(-BARY_EPS..=1.0 + BARY_EPS).contains(&u) {
        return None;
    }
    let q = s.cross(e1);
    let v = dir.dot(q) * inv;
    if v < -BARY_EPS || u + v > 1.0 + BARY_EPS {
        return None;
    }
    let t = e2.dot(q) * inv;
    (t >= t_min && t <= t_max).then_some(TriangleHit { t, u, v })
}

/// The closest hit of a ray in a scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray, metres.
    pub t: f32,
    /// Index of the triangle in the mesh the accelerator was built from.
    pub triangle: u32,
    /// Unit geometric normal of the triangle, flipped to face the ray origin.
    pub normal: Vec3,
    /// The surface (material, instance) of the triangle.
    pub surface: Surface,
}

#[derive(Debug, Clone, Copy)]
struct PreTri {
    a: Vec3A,
    e1: Vec3A,
    e2: Vec3A,
}

/// A BVH over the triangles of a [`Mesh`], ready for ray queries.
pub struct Accel {
    bvh: Bvh2,
    /// Triangles in BVH order (`bvh.primitive_indices`), pre-computed for Möller–Trumbore.
    tris: Vec<PreTri>,
    /// Original mesh index of every BVH-ordered triangle.
    original: Vec<u32>,
    /// Surface index per original triangle.
    surface_of: Vec<u32>,
    surfaces: Vec<Surface>,
    num_triangles: usize,
}

impl std::fmt::Debug for Accel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Accel")
            .field("triangles", &self.num_triangles)
            .field("bvh_nodes", &self.bvh.nodes.len())
            .finish()
    }
}

impl Accel {
    /// Build the BVH (obvhs PLOC builder, `fast_build` preset with spatial pre-splits of large
    /// triangles). Deterministic: the same mesh always gives the same tree.
    pub fn build(mesh: &Mesh) -> Self {
        let obvhs_tris: Vec<Triangle> = mesh
            .triangles
            .iter()
            .map(|[a, b, c]| Triangle {
                v0: (*a).into(),
                v1: (*b).into(),
                v2: (*c).into(),
            })
            .collect();
        let (bvh, tris, original) = if obvhs_tris.is_empty() {
            (Bvh2::default(), Vec::new(), Vec::new())
        } else {
            let params = BvhBuildParams {
                pre_split: true,
                ..BvhBuildParams::fast_build()
            };
            let bvh = build_bvh2_from_tris(&obvhs_tris, params, &mut Duration::default());
            let original = bvh.primitive_indices.clone();
            let tris = original
                .iter()
                .map(|&i| {
                    let t = &obvhs_tris[i as usize];
                    PreTri {
                        a: t.v0,
                        e1: t.v1 - t.v0,
                        e2: t.v2 - t.v0,
                    }
                })
                .collect();
            (bvh, tris, original)
        };
        Accel {
            bvh,
            tris,
            original,
            surface_of: mesh.surface_of.clone(),
            surfaces: mesh.surfaces.clone(),
            num_triangles: mesh.len(),
        }
    }

    /// Number of triangles in the scene.
    pub fn num_triangles(&self) -> usize {
        self.num_triangles
    }

    /// Closest hit of the ray `origin + t dir` (`dir` unit length) with `t` in `[t_min, t_max]`.
    pub fn closest_hit(&self, origin: Vec3, dir: Vec3, t_min: f32, t_max: f32) -> Option<Hit> {
        if self.tris.is_empty() || !origin.is_finite() || !dir.is_finite() || dir == Vec3::ZERO {
            return None;
        }
        let (o, d) = (Vec3A::from(origin), Vec3A::from(dir));
        let ray = Ray::new(o, d, t_min, t_max);
        let mut hit = RayHit::none();
        let found = self.bvh.ray_traverse(ray, &mut hit, |r, i| {
            let t = &self.tris[i];
            intersect_triangle(r.origin, r.direction, t.a, t.e1, t.e2, r.tmin, r.tmax)
                .map_or(f32::INFINITY, |h| h.t)
        });
        if !found || !hit.t.is_finite() {
            return None;
        }
        let slot = hit.primitive_id as usize;
        let tri = &self.tris[slot];
        let mut n = Vec3::from(tri.e1.cross(tri.e2)).normalize_or_zero();
        if n.dot(dir) > 0.0 {
            n = -n;
        }
        let triangle = self.original[slot];
        let surface = self.surfaces[self.surface_of[triangle as usize] as usize];
        Some(Hit {
            t: hit.t,
            triangle,
            normal: n,
            surface,
        })
    }

    /// True when anything lies on the ray within `[t_min, t_max]` (shadow rays).
    pub fn occluded(&self, origin: Vec3, dir: Vec3, t_min: f32, t_max: f32) -> bool {
        if self.tris.is_empty() || !origin.is_finite() || !dir.is_finite() || dir == Vec3::ZERO {
            return false;
        }
        let ray = Ray::new(origin.into(), dir.into(), t_min, t_max);
        !self.bvh.ray_traverse_miss(ray, |r, i| {
            let t = &self.tris[i];
            intersect_triangle(r.origin, r.direction, t.a, t.e1, t.e2, r.tmin, r.tmax)
                .map_or(f32::INFINITY, |h| h.t)
        })
    }
}
