//! Triangle meshes built from boxes, cylinders, ellipsoids and quads.
//!
//! A [`Mesh`] is a triangle soup where every triangle points at a [`Surface`]: a [`Material`] plus the
//! SemanticKITTI instance id of the object it belongs to. Composite objects (cars, trees, people) are
//! built by calling the primitive adders with an object-to-world transform.

use glam::{Affine3A, Vec3};

use super::material::Material;

/// What a triangle is made of and which object instance it belongs to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Surface {
    /// The material (albedo, LiDAR reflectivity, class).
    pub material: Material,
    /// SemanticKITTI instance id (0 for stuff classes such as road or building).
    pub instance: u16,
}

/// A triangle soup with one surface index per triangle.
#[derive(Debug, Clone, Default)]
pub struct Mesh {
    /// Triangle vertices in the world frame, metres.
    pub triangles: Vec<[Vec3; 3]>,
    /// Index into [`Mesh::surfaces`] for every triangle.
    pub surface_of: Vec<u32>,
    /// The surfaces referenced by [`Mesh::surface_of`].
    pub surfaces: Vec<Surface>,
}

impl Mesh {
    /// An empty mesh.
    pub fn new() -> Self {
        Self::default()
    }

    /// Number of triangles.
    pub fn len(&self) -> usize {
        self.triangles.len()
    }

    /// True when the mesh has no triangle.
    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Register a surface and return its index for the adders.
    pub fn surface(&mut self, material: Material, instance: u16) -> u32 {
        let s = Surface { material, instance };
        if let Some(i) = self.surfaces.iter().rposition(|x| *x == s) {
            return i as u32;
        }
        self.surfaces.push(s);
        (self.surfaces.len() - 1) as u32
    }

    /// Add one triangle; degenerate (zero-area or non-finite) triangles are skipped.
    pub fn add_triangle(&mut self, a: Vec3, b: Vec3, c: Vec3, surface: u32) {
        let area2 = (b - a).cross(c - a).length_squared();
        if !(area2 > 0.0 && area2.is_finite()) {
            return;
        }
        self.triangles.push([a, b, c]);
        self.surface_of.push(surface);
    }

    /// Add a planar quad `a b c d` (counter-clockwise seen from the side its normal points to).
    pub fn add_quad(&mut self, a: Vec3, b: Vec3, c: Vec3, d: Vec3, surface: u32) {
        self.add_triangle(a, b, c, surface);
        self.add_triangle(a, c, d, surface);
    }

    /// Add an axis-aligned horizontal rectangle `[x0, x1] x [y0, y1]` at height `z`, split into
    /// tiles of at most `tile_m` metres so that the BVH stays tight around large ground areas.
    pub fn add_ground_rect(
        &mut self,
        x0: f32,
        x1: f32,
        y0: f32,
        y1: f32,
        z: f32,
        tile_m: f32,
        surface: u32,
    ) {
        let (x0, x1) = (x0.min(x1), x0.max(x1));
        let (y0, y1) = (y0.min(y1), y0.max(y1));
        let nx = ((x1 - x0) / tile_m).ceil().max(1.0) as usize;
        let ny = ((y1 - y0) / tile_m).ceil().max(1.0) as usize;
        // Vertices shared exactly between neighbouring tiles (same float expression) keep it watertight.
        let xs: Vec<f32> = (0..=nx)
            .map(|i| {
                if i == nx {
                    x1
                } else {
                    x0 + (x1 - x0) * i as f32 / nx as f32
                }
            })
            .collect();
        let ys: Vec<f32> = (0..=ny)
            .map(|j| {
                if j == ny {
                    y1
                } else {
                    y0 + (y1 - y0) * j as f32 / ny as f32
                }
            })
            .collect();
        for i in 0..nx {
            for j in 0..ny {
                self.add_quad(
                    Vec3::new(xs[i], ys[j], z),
                    Vec3::new(xs[i + 1], ys[j], z),
                    Vec3::new(xs[i + 1], ys[j + 1], z),
                    Vec3::new(xs[i], ys[j + 1], z),
                    surface,
                );
            }
        }
    }

    /// Add a box `[-half, half]` (all six faces, outward winding) placed by `world_from_box`.
    pub fn add_box(&mut self, world_from_box: Affine3A, half: Vec3, surface: u32) {
        let p = |sx: f32, sy: f32, sz: f32| {
            world_from_box.transform_point3(Vec3::new(sx * half.x, sy * half.y, sz * half.z))
        };
        let c = [
            p(-1.0, -1.0, -1.0),
            p(1.0, -1.0, -1.0),
            p(1.0, 1.0, -1.0),
            p(-1.0, 1.0, -1.0),
            p(-1.0, -1.0, 1.0),
            p(1.0, -1.0, 1.0),
            p(1.0, 1.0, 1.0),
            p(-1.0, 1.0, 1.0),
        ];
        for [a, b, cc, d] in [
            [0, 3, 2, 1], // bottom (-z)
            [4, 5, 6, 7], // top (+z)
            [0, 1, 5, 4], // -y
            [2, 3, 7, 6], // +y
            [1, 2, 6, 5], // +x
            [3, 0, 4, 7], // -x
        ] {
            self.add_quad(c[a], c[b], c[cc], c[d], surface);
        }
    }

    /// Add an axis-aligned box `[min, max]` (no rotation).
    pub fn add_aabb(&mut self, min: Vec3, max: Vec3, surface: u32) {
        let centre = (min + max) * 0.5;
        self.add_box(
            Affine3A::from_translation(centre),
            (max - min) * 0.5,
            surface,
        );
    }

    /// Add a cylinder of `radius` around the local z axis from `z = 0` to `z = height`, with
    /// `segments` sides and both caps, placed by `world_from_local`.
    pub fn add_cylinder(
        &mut self,
        world_from_local: Affine3A,
        radius: f32,
        height: f32,
        segments: u32,
        surface: u32,
    ) {
        self.add_frustum(world_from_local, radius, radius, height, segments, surface);
    }

    /// Add a truncated cone (bottom radius `r0` at `z = 0`, top radius `r1` at `z = height`) with caps.
    pub fn add_frustum(
        &mut self,
        world_from_local: Affine3A,
        r0: f32,
        r1: f32,
        height: f32,
        segments: u32,
        surface: u32,
    ) {
        let n = segments.max(3);
        let ring = |r: f32, z: f32, i: u32| {
            let a = std::f32::consts::TAU * (i % n) as f32 / n as f32;
            world_from_local.transform_point3(Vec3::new(r * a.cos(), r * a.sin(), z))
        };
        let bottom = world_from_local.transform_point3(Vec3::ZERO);
        let top = world_from_local.transform_point3(Vec3::new(0.0, 0.0, height));
        for i in 0..n {
            let (b0, b1) = (ring(r0, 0.0, i), ring(r0, 0.0, i + 1));
            let (t0, t1) = (ring(r1, height, i), ring(r1, height, i + 1));
            self.add_quad(b0, b1, t1, t0, surface);
            self.add_triangle(bottom, b1, b0, surface);
            self.add_triangle(top, t0, t1, surface);
        }
    }

    /// Add an ellipsoid with semi-axes `radii` around the local origin (a UV sphere with `lon`
    /// segments around and `lat` segments from pole to pole), placed by `world_from_local`.
    pub fn add_ellipsoid(
        &mut self,
        world_from_local: Affine3A,
        radii: Vec3,
        lon: u32,
        lat: u32,
        surface: u32,
    ) {
        let (lon, lat) = (lon.max(3), lat.max(2));
        let p = |i: u32, j: u32| {
            let phi = std::f32::consts::TAU * (i % lon) as f32 / lon as f32;
            let theta = std::f32::consts::PI * j as f32 / lat as f32;
            let local = Vec3::new(
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos(),
            ) * radii;
            world_from_local.transform_point3(local)
        };
        for j in 0..lat {
            for i in 0..lon {
                let (a, b, c, d) = (p(i, j), p(i + 1, j), p(i + 1, j + 1), p(i, j + 1));
                // the quads at the poles collapse to triangles; add_triangle skips the degenerate half
                self.add_triangle(a, d, c, surface);
                self.add_triangle(a, c, b, surface);
            }
        }
    }

    /// Append another mesh (its surfaces are merged into this mesh's table).
    pub fn append(&mut self, other: &Mesh) {
        let map: Vec<u32> = other
            .surfaces
            .iter()
            .map(|s| self.surface(s.material, s.instance))
            .collect();
        self.triangles.extend_from_slice(&other.triangles);
        self.surface_of
            .extend(other.surface_of.iter().map(|s| map[*s as usize]));
    }

    /// Append another mesh moved by `world_from_local`.
    pub fn append_transformed(&mut self, other: &Mesh, world_from_local: Affine3A) {
        let map: Vec<u32> = other
            .surfaces
            .iter()
            .map(|s| self.surface(s.material, s.instance))
            .collect();
        self.triangles.extend(
            other
                .triangles
                .iter()
                .map(|t| t.map(|v| world_from_local.transform_point3(v))),
        );
        self.surface_of
            .extend(other.surface_of.iter().map(|s| map[*s as usize]));
    }
}
