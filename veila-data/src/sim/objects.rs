//! Composite object meshes in their own frame: x forward, y left, z up, origin on the ground at the
//! object's footprint centre. Sizes are drawn from `rng`; every object gets its own colour.

use glam::{Affine3A, Mat3, Quat, Vec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::material::{Material, stock};
use super::mesh::Mesh;
use crate::semantic_kitti::class;

/// Kinds of vehicles the generator places.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VehicleKind {
    /// Passenger car (`car`).
    Car,
    /// Van with a continuous body (`car`, as in SemanticKITTI).
    Van,
    /// Truck with a separate cabin (`truck`).
    Truck,
    /// City bus (`bus`).
    Bus,
    /// Trailer or caravan (`other-vehicle`), only parked.
    Trailer,
}

impl VehicleKind {
    /// SemanticKITTI class of a parked vehicle of this kind.
    pub fn class(self) -> u16 {
        match self {
            VehicleKind::Car | VehicleKind::Van => class::CAR,
            VehicleKind::Truck => class::TRUCK,
            VehicleKind::Bus => class::BUS,
            VehicleKind::Trailer => class::OTHER_VEHICLE,
        }
    }
}

const PAINTS: [([f32; 3], f32); 8] = [
    ([0.75, 0.75, 0.75], 0.55),  // white
    ([0.45, 0.46, 0.48], 0.4),   // silver
    ([0.03, 0.03, 0.035], 0.06), // black
    ([0.04, 0.07, 0.2], 0.15),   // dark blue
    ([0.45, 0.04, 0.03], 0.3),   // red
    ([0.2, 0.2, 0.21], 0.2),     // grey
    ([0.05, 0.15, 0.07], 0.15),  // dark green
    ([0.6, 0.45, 0.1], 0.35),    // yellow-brown
];

fn paint(rng: &mut ChaCha8Rng, class: u16) -> Material {
    let (albedo, refl) = PAINTS[rng.random_range(0..PAINTS.len())];
    Material::new(albedo, refl, class)
}

fn relabel(m: Material, class: u16) -> Material {
    m.with_class(class)
}

fn wheel(mesh: &mut Mesh, x: f32, y: f32, r: f32, w: f32, surf: u32) {
    // axis along y: rotate the local z axis onto y
    let xf = Affine3A::from_translation(Vec3::new(x, y - w / 2.0, r))
        * Affine3A::from_quat(Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2));
    mesh.add_cylinder(xf, r, w, 12, surf);
}

/// A vehicle mesh; returns the mesh and its length (m). `class` is the label to use (the caller
/// passes the `moving-*` id for moving vehicles).
pub fn vehicle(rng: &mut ChaCha8Rng, kind: VehicleKind, class: u16, instance: u16) -> (Mesh, f32) {
    let mut m = Mesh::new();
    let body = m.surface(paint(rng, class), instance);
    let glass = m.surface(relabel(stock::GLASS, class), instance);
    let tyre = m.surface(relabel(stock::TYRE, class), instance);
    let length;
    match kind {
        VehicleKind::Car => {
            let l = rng.random_range(3.9..4.9f32);
            let w = rng.random_range(1.72..1.9f32);
            let h = rng.random_range(1.4..1.62f32);
            let r = 0.31;
            length = l;
            // lower body
            m.add_aabb(
                Vec3::new(-l / 2.0, -w / 2.0, 0.28),
                Vec3::new(l / 2.0, w / 2.0, 0.95),
                body,
            );
            // greenhouse: glass band + roof
            let cab_l = l * rng.random_range(0.48..0.58f32);
            let cab_x = -l * 0.06;
            let roof_z = h - 0.06;
            m.add_aabb(
                Vec3::new(cab_x - cab_l / 2.0, -w / 2.0 + 0.1, 0.95),
                Vec3::new(cab_x + cab_l / 2.0, w / 2.0 - 0.1, roof_z),
                glass,
            );
            m.add_aabb(
                Vec3::new(cab_x - cab_l / 2.0 + 0.05, -w / 2.0 + 0.12, roof_z),
                Vec3::new(cab_x + cab_l / 2.0 - 0.05, w / 2.0 - 0.12, h),
                body,
            );
            for x in [l / 2.0 - 0.8, -l / 2.0 + 0.8] {
                for y in [-w / 2.0 + 0.12, w / 2.0 - 0.12] {
                    wheel(&mut m, x, y, r, 0.22, tyre);
                }
            }
        }
        VehicleKind::Van => {
            let l = rng.random_range(4.8..5.6f32);
            let w = rng.random_range(1.9..2.05f32);
            let h = rng.random_range(1.95..2.5f32);
            length = l;
            m.add_aabb(
                Vec3::new(-l / 2.0, -w / 2.0, 0.32),
                Vec3::new(l / 2.0 - 0.9, w / 2.0, h),
                body,
            );
            // sloped front: bonnet box + windscreen block
            m.add_aabb(
                Vec3::new(l / 2.0 - 0.9, -w / 2.0, 0.32),
                Vec3::new(l / 2.0, w / 2.0, 1.05),
                body,
            );
            m.add_aabb(
                Vec3::new(l / 2.0 - 0.9, -w / 2.0 + 0.08, 1.05),
                Vec3::new(l / 2.0 - 0.35, w / 2.0 - 0.08, h - 0.15),
                glass,
            );
            for x in [l / 2.0 - 0.9, -l / 2.0 + 0.9] {
                for y in [-w / 2.0 + 0.12, w / 2.0 - 0.12] {
                    wheel(&mut m, x, y, 0.34, 0.22, tyre);
                }
            }
        }
        VehicleKind::Truck => {
            let cargo_l = rng.random_range(5.0..8.0f32);
            let w = 2.5;
            let cab_l = 2.2;
            let l = cargo_l + cab_l + 0.3;
            length = l;
            let cargo = m.surface(Material::new([0.7, 0.7, 0.68], 0.5, class), instance);
            let x0 = -l / 2.0;
            m.add_aabb(
                Vec3::new(x0, -w / 2.0, 1.0),
                Vec3::new(x0 + cargo_l, w / 2.0, rng.random_range(3.3..3.9f32)),
                cargo,
            );
            m.add_aabb(Vec3::new(x0, -0.5, 0.6), Vec3::new(l / 2.0, 0.5, 1.0), body); // chassis
            let cx = l / 2.0 - cab_l;
            m.add_aabb(
                Vec3::new(cx, -w / 2.0 + 0.05, 0.6),
                Vec3::new(l / 2.0, w / 2.0 - 0.05, 2.0),
                body,
            );
            m.add_aabb(
                Vec3::new(cx, -w / 2.0 + 0.08, 2.0),
                Vec3::new(l / 2.0 - 0.05, w / 2.0 - 0.08, 2.7),
                glass,
            );
            m.add_aabb(
                Vec3::new(cx, -w / 2.0 + 0.05, 2.7),
                Vec3::new(l / 2.0, w / 2.0 - 0.05, 3.0),
                body,
            );
            for x in [l / 2.0 - 1.2, x0 + 1.0, x0 + 2.4] {
                for y in [-w / 2.0 + 0.15, w / 2.0 - 0.15] {
                    wheel(&mut m, x, y, 0.5, 0.3, tyre);
                }
            }
        }
        VehicleKind::Bus => {
            let l = rng.random_range(11.0..12.5f32);
            let w = 2.55;
            let h = 3.1;
            length = l;
            m.add_aabb(
                Vec3::new(-l / 2.0, -w / 2.0, 0.35),
                Vec3::new(l / 2.0, w / 2.0, 1.2),
                body,
            );
            m.add_aabb(
                Vec3::new(-l / 2.0 + 0.05, -w / 2.0 + 0.03, 1.2),
                Vec3::new(l / 2.0 - 0.05, w / 2.0 - 0.03, 2.5),
                glass,
            );
            m.add_aabb(
                Vec3::new(-l / 2.0, -w / 2.0, 2.5),
                Vec3::new(l / 2.0, w / 2.0, h),
                body,
            );
            for x in [l / 2.0 - 2.5, -l / 2.0 + 3.0] {
                for y in [-w / 2.0 + 0.15, w / 2.0 - 0.15] {
                    wheel(&mut m, x, y, 0.5, 0.3, tyre);
                }
            }
        }
        VehicleKind::Trailer => {
            let l = rng.random_range(4.0..6.5f32);
            let w = rng.random_range(2.0..2.4f32);
            let h = rng.random_range(2.2..2.7f32);
            length = l + 1.0;
            let shell = m.surface(Material::new([0.78, 0.78, 0.75], 0.55, class), instance);
            m.add_aabb(
                Vec3::new(-length / 2.0, -w / 2.0, 0.45),
                Vec3::new(-length / 2.0 + l, w / 2.0, h),
                shell,
            );
            m.add_aabb(
                Vec3::new(-length / 2.0 + l, -0.06, 0.4),
                Vec3::new(length / 2.0, 0.06, 0.5),
                body,
            ); // drawbar
            for y in [-w / 2.0 + 0.15, w / 2.0 - 0.15] {
                wheel(&mut m, -length / 2.0 + l * 0.5, y, 0.33, 0.2, tyre);
            }
        }
    }
    (m, length)
}

/// A pedestrian (legs in a random stride), all labelled `class`.
pub fn person(rng: &mut ChaCha8Rng, class: u16, instance: u16) -> Mesh {
    let mut m = Mesh::new();
    let s = rng.random_range(0.9..1.08f32);
    let shirt = [
        [0.5, 0.1, 0.1],
        [0.1, 0.2, 0.45],
        [0.6, 0.6, 0.55],
        [0.1, 0.1, 0.1],
        [0.3, 0.4, 0.2],
    ];
    let top = m.surface(
        Material::new(shirt[rng.random_range(0..shirt.len())], 0.35, class),
        instance,
    );
    let legs = m.surface(Material::new([0.08, 0.09, 0.15], 0.25, class), instance);
    let skin = m.surface(relabel(stock::SKIN, class), instance);
    let stride = rng.random_range(-0.18..0.18f32);
    for (y, dx) in [(0.1, stride), (-0.1, -stride)] {
        m.add_aabb(
            Vec3::new(dx - 0.07, y - 0.07, 0.0),
            Vec3::new(dx + 0.09, y + 0.07, 0.86 * s),
            legs,
        );
    }
    m.add_aabb(
        Vec3::new(-0.12, -0.21, 0.86 * s),
        Vec3::new(0.12, 0.21, 1.45 * s),
        top,
    );
    for y in [0.26, -0.26] {
        m.add_aabb(
            Vec3::new(-0.06, y - 0.05, 0.85 * s),
            Vec3::new(0.06, y + 0.05, 1.42 * s),
            top,
        );
    }
    m.add_ellipsoid(
        Affine3A::from_translation(Vec3::new(0.0, 0.0, 1.58 * s)),
        Vec3::new(0.1, 0.09, 0.12) * s,
        8,
        5,
        skin,
    );
    m
}

/// A cyclist (bicycle and rider, all labelled `class`, i.e. bicyclist or moving-bicyclist).
pub fn cyclist(rng: &mut ChaCha8Rng, class: u16, instance: u16) -> Mesh {
    let mut m = Mesh::new();
    let frame_col = [[0.5, 0.05, 0.05], [0.1, 0.1, 0.1], [0.1, 0.3, 0.5]][rng.random_range(0..3)];
    let frame = m.surface(Material::new(frame_col, 0.35, class), instance);
    let tyre = m.surface(relabel(stock::TYRE, class), instance);
    let top = m.surface(Material::new([0.7, 0.55, 0.1], 0.45, class), instance);
    let legs = m.surface(Material::new([0.08, 0.08, 0.1], 0.25, class), instance);
    let skin = m.surface(relabel(stock::SKIN, class), instance);
    for x in [0.52, -0.52] {
        wheel(&mut m, x, 0.0, 0.34, 0.05, tyre);
    }
    m.add_aabb(
        Vec3::new(-0.5, -0.03, 0.5),
        Vec3::new(0.45, 0.03, 0.6),
        frame,
    );
    m.add_aabb(
        Vec3::new(0.35, -0.03, 0.35),
        Vec3::new(0.42, 0.03, 1.0),
        frame,
    );
    m.add_aabb(
        Vec3::new(0.36, -0.28, 0.98),
        Vec3::new(0.42, 0.28, 1.02),
        frame,
    );
    m.add_aabb(
        Vec3::new(-0.3, -0.1, 0.45),
        Vec3::new(-0.05, 0.1, 0.95),
        legs,
    );
    // rider torso leaning forward
    let torso = Affine3A::from_translation(Vec3::new(-0.05, 0.0, 1.25))
        * Affine3A::from_quat(Quat::from_rotation_y(0.6));
    m.add_box(torso, Vec3::new(0.12, 0.2, 0.3), top);
    m.add_ellipsoid(
        Affine3A::from_translation(Vec3::new(0.2, 0.0, 1.58)),
        Vec3::new(0.11, 0.1, 0.12),
        8,
        5,
        skin,
    );
    m
}

/// A tree: trunk (`trunk`) and crown (`vegetation`).
pub fn tree(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::new();
    let trunk = m.surface(stock::TRUNK, 0);
    let leaves = m.surface(stock::VEGETATION, 0);
    let h = rng.random_range(2.2..4.0f32);
    let r = rng.random_range(0.12..0.28f32);
    m.add_frustum(Affine3A::IDENTITY, r, r * 0.7, h + 0.5, 8, trunk);
    let cr = Vec3::new(
        rng.random_range(1.4..2.8f32),
        0.0,
        rng.random_range(1.6..3.2f32),
    );
    let radii = Vec3::new(cr.x, cr.x * rng.random_range(0.85..1.15f32), cr.z);
    m.add_ellipsoid(
        Affine3A::from_translation(Vec3::new(0.0, 0.0, h + radii.z * 0.8)),
        radii,
        12,
        7,
        leaves,
    );
    m
}

/// A tree line: a belt of dense woodland `length` along local x and `depth` deep along -y (its
/// front at y = 0 faces +y, the road), crowns from 1 m above the ground or lower up to a top drawn
/// in `height_m` (`vegetation`; trunks hidden behind undergrowth). Unlike [`tree`]'s single crowns
/// on bare trunks it reads as a continuous wall of foliage, as a real woodland edge or a tall
/// hedgerow does: the simulated streets otherwise show such a wall only as a near facade.
pub fn tree_line(rng: &mut ChaCha8Rng, length: f32, depth: f32, height_m: [f32; 2]) -> Mesh {
    let mut m = Mesh::new();
    let leaves = m.surface(stock::VEGETATION, 0);
    let [h_lo, h_hi] = height_m;
    let half = length / 2.0;
    // undergrowth along the front: an uneven band 2-4 m high that closes the gaps between crowns
    let mut x = -half;
    while x < half {
        let l = rng.random_range(3.0..9.0f32).min(half - x);
        let h = rng.random_range(2.0..4.0f32);
        m.add_aabb(
            Vec3::new(x, -rng.random_range(0.8..2.0f32), 0.0),
            Vec3::new(x + l, 0.0, h),
            leaves,
        );
        x += l;
    }
    // crowns in staggered rows across the depth, each reaching from near the ground to its top
    let rows = ((depth / 4.0).ceil() as u32).clamp(1, 4);
    for row in 0..rows {
        let y = -(row as f32 + 0.5) * depth / rows as f32;
        let mut x = -half + rng.random_range(0.0..3.0f32);
        while x < half {
            let top = rng.random_range(h_lo..h_hi.max(h_lo + 0.1));
            let bottom = rng.random_range(0.0..1.5f32).min(top * 0.3);
            let rz = (top - bottom) / 2.0;
            let rx = rng.random_range(2.0..4.5f32).min(rz.max(1.5));
            let ry = rx * rng.random_range(0.8..1.2f32);
            m.add_ellipsoid(
                // (no crown bulges past the front toward the road)
                Affine3A::from_translation(Vec3::new(x, y.min(-ry), bottom + rz)),
                Vec3::new(rx, ry, rz),
                10,
                6,
                leaves,
            );
            x += rx * rng.random_range(0.9..1.4f32);
        }
    }
    m
}

/// A bush (`vegetation`).
pub fn bush(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::new();
    let leaves = m.surface(stock::VEGETATION, 0);
    let r = Vec3::new(
        rng.random_range(0.5..1.4f32),
        rng.random_range(0.5..1.4f32),
        rng.random_range(0.4..1.0f32),
    );
    m.add_ellipsoid(
        Affine3A::from_translation(Vec3::new(0.0, 0.0, r.z * 0.7)),
        r,
        10,
        5,
        leaves,
    );
    m
}

/// A street light: a pole with an arm toward +y (the road) and a lamp, all `pole`.
pub fn street_light(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::new();
    let pole = m.surface(stock::POLE, 0);
    let h = rng.random_range(5.5..8.0f32);
    m.add_frustum(Affine3A::IDENTITY, 0.1, 0.07, h, 8, pole);
    let arm = rng.random_range(1.0..2.0f32);
    m.add_aabb(
        Vec3::new(-0.04, 0.0, h - 0.08),
        Vec3::new(0.04, arm, h),
        pole,
    );
    m.add_aabb(
        Vec3::new(-0.15, arm - 0.5, h - 0.2),
        Vec3::new(0.15, arm, h - 0.05),
        pole,
    );
    m
}

/// A traffic sign facing +x: a post (`pole`) and a plate (`traffic-sign`).
pub fn traffic_sign(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::new();
    let pole = m.surface(stock::POLE, 0);
    let colours = [
        [0.7, 0.05, 0.05],
        [0.05, 0.15, 0.6],
        [0.8, 0.7, 0.1],
        [0.8, 0.8, 0.8],
    ];
    let plate = m.surface(
        Material::new(
            colours[rng.random_range(0..colours.len())],
            0.95,
            class::TRAFFIC_SIGN,
        ),
        0,
    );
    let h = rng.random_range(2.0..2.6f32);
    m.add_cylinder(Affine3A::IDENTITY, 0.04, h, 6, pole);
    if rng.random_bool(0.5) {
        // round plate: a thin disc facing +x
        let xf = Affine3A::from_translation(Vec3::new(0.05, 0.0, h + 0.3))
            * Affine3A::from_quat(Quat::from_rotation_y(std::f32::consts::FRAC_PI_2));
        m.add_cylinder(xf, 0.32, 0.03, 16, plate);
    } else {
        m.add_aabb(
            Vec3::new(0.05, -0.32, h),
            Vec3::new(0.08, 0.32, h + 0.64),
            plate,
        );
    }
    m
}

/// A traffic light facing +x: a pole and a signal head (labelled `traffic-sign`).
pub fn traffic_light() -> Mesh {
    let mut m = Mesh::new();
    let pole = m.surface(stock::POLE, 0);
    let head = m.surface(
        Material::new([0.05, 0.05, 0.05], 0.2, class::TRAFFIC_SIGN),
        0,
    );
    m.add_cylinder(Affine3A::IDENTITY, 0.07, 3.0, 8, pole);
    m.add_aabb(Vec3::new(0.0, -0.17, 2.9), Vec3::new(0.3, 0.17, 3.85), head);
    m
}

/// A fence segment of `length` along local x, `height` high (`fence`).
pub fn fence(length: f32, height: f32) -> Mesh {
    let mut m = Mesh::new();
    let f = m.surface(stock::FENCE, 0);
    m.add_aabb(
        Vec3::new(-length / 2.0, -0.03, 0.0),
        Vec3::new(length / 2.0, 0.03, height),
        f,
    );
    m
}

/// A guardrail of `length` along local x (`fence`, as SemanticKITTI labels guardrails): a steel
/// beam 0.45-0.75 m above the ground whose face is at local `y = 0` facing +y (the road), on posts
/// every 2 m behind it.
pub fn guardrail(length: f32) -> Mesh {
    let mut m = Mesh::new();
    let steel = m.surface(stock::GUARDRAIL, 0);
    m.add_aabb(
        Vec3::new(-length / 2.0, -0.08, 0.45),
        Vec3::new(length / 2.0, 0.0, 0.75),
        steel,
    );
    let posts = (length / 2.0).floor().max(1.0) as i32;
    let step = length / posts as f32;
    for i in 0..=posts {
        let x = -length / 2.0 + i as f32 * step;
        m.add_aabb(
            Vec3::new(x - 0.05, -0.2, 0.0),
            Vec3::new(x + 0.05, -0.08, 0.7),
            steel,
        );
    }
    m
}

/// A hedge of `length` along local x (`vegetation`).
pub fn hedge(rng: &mut ChaCha8Rng, length: f32) -> Mesh {
    let mut m = Mesh::new();
    let f = m.surface(stock::VEGETATION, 0);
    let h = rng.random_range(0.8..1.8f32);
    let w = rng.random_range(0.5..0.9f32);
    m.add_aabb(
        Vec3::new(-length / 2.0, -w / 2.0, 0.0),
        Vec3::new(length / 2.0, w / 2.0, h),
        f,
    );
    m
}

/// Window glass of buildings.
pub(crate) const WINDOW: Material = Material::new([0.04, 0.05, 0.06], 0.1, class::BUILDING);
/// Roofs of buildings.
pub(crate) const ROOF: Material = Material::new([0.15, 0.13, 0.12], 0.15, class::BUILDING);

const FACADES: [([f32; 3], f32); 6] = [
    ([0.62, 0.56, 0.45], 0.65),
    ([0.72, 0.72, 0.7], 0.75),
    ([0.42, 0.19, 0.13], 0.5),
    ([0.42, 0.42, 0.42], 0.55),
    ([0.7, 0.62, 0.35], 0.65),
    ([0.55, 0.6, 0.62], 0.6),
];

/// A building of `width` along local x, `depth` along -y (the facade at y = 0 faces +y, the street)
/// and `height`, with windows on the street facade (all `building`).
pub fn building(rng: &mut ChaCha8Rng, width: f32, depth: f32, height: f32) -> Mesh {
    let mut m = Mesh::new();
    let (albedo, refl) = FACADES[rng.random_range(0..FACADES.len())];
    let wall = m.surface(Material::new(albedo, refl, class::BUILDING), 0);
    let window = m.surface(WINDOW, 0);
    let roof = m.surface(ROOF, 0);
    m.add_aabb(
        Vec3::new(-width / 2.0, -depth, 0.0),
        Vec3::new(width / 2.0, 0.0, height - 0.3),
        wall,
    );
    m.add_aabb(
        Vec3::new(-width / 2.0 - 0.1, -depth - 0.1, height - 0.3),
        Vec3::new(width / 2.0 + 0.1, 0.1, height),
        roof,
    );
    // windows: a grid on the street facade, 2 cm proud of the wall
    let storey = rng.random_range(2.9..3.4f32);
    let spacing = rng.random_range(2.2..3.2f32);
    let (ww, wh) = (spacing * 0.5, storey * 0.45);
    let nx = ((width - 1.0) / spacing).floor().max(0.0) as i32;
    let ny = ((height - 1.5) / storey).floor().max(0.0) as i32;
    let x_start = -(nx as f32 - 1.0) * spacing / 2.0;
    for j in 0..ny {
        let z0 = 1.0 + j as f32 * storey;
        for i in 0..nx {
            let xc = x_start + i as f32 * spacing;
            let y = 0.02;
            m.add_quad(
                Vec3::new(xc - ww / 2.0, y, z0),
                Vec3::new(xc + ww / 2.0, y, z0),
                Vec3::new(xc + ww / 2.0, y, z0 + wh),
                Vec3::new(xc - ww / 2.0, y, z0 + wh),
                window,
            );
        }
    }
    m
}

/// Rotation about z by `heading` radians (x forward turns toward y).
pub fn yaw(heading: f32) -> Affine3A {
    Affine3A::from_mat3(Mat3::from_rotation_z(heading))
}
