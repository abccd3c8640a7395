//! Procedural scene generation: streets, lots, street furniture and actors from a [`SceneConfig`]
//! and a seed.
//!
//! World frame: x along the main street, y to its left, z up, metres; the road surface is `z = 0`,
//! sidewalks, gardens and terrain sit at the kerb height. Traffic drives on the right: the ego
//! vehicle drives in +x in the rightmost lane (`y < 0`).

use glam::{Affine3A, Mat3, Vec2, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use veila_geom::{LidarSensor, PinholeCamera};

use super::appearance::Appearance;
use super::camera::{CameraRenderOptions, SimCalib, SimImage};
use super::config::{CameraConfig, Layout, RoadParams, SceneConfig};
use super::curve::RoadCurve;
use super::frame::SceneSnapshot;
use super::hash::splitmix;
use super::lidar::SimScan;
use super::material::stock;
use super::mesh::Mesh;
use super::objects::{self, VehicleKind, yaw};
use super::raycast::Accel;
use crate::Result;
use crate::semantic_kitti::class;

/// Tile size of ground rectangles, metres.
const TILE_M: f32 = 10.0;
/// Height of lane paint above the asphalt, metres (keeps markings ahead of the road in closest-hit).
const PAINT_Z: f32 = 0.003;
/// First random stream of the open roadsides (apart from every stream the older features use).
const OPEN_STREAM: u64 = 0x6f70_0000;
/// First random stream of the open roadsides' tree lines (apart from the other open-side draws, so
/// a scene without them is unchanged).
const TREE_LINE_STREAM: u64 = 0x746c_0000;
/// Random stream of the grade draw.
const GRADE_STREAM: u64 = 0x6772_0000;
/// Length of the vertical curve into the grade, metres.
const VERTICAL_CURVE_M: f32 = 40.0;
/// Random stream of the horizontal curve draw.
const CURVE_STREAM: u64 = 0x6375_0000;
/// Where a bend begins relative to the ego's start, metres along the street.
const CURVE_START_M: std::ops::Range<f32> = -20.0..40.0;
/// Non-ground geometry keeps this far from the inner limit of a bend (its turning centre), metres.
const INNER_MARGIN_M: f32 = 1.0;

/// Triangles in the vertical curve are split until their extent along x is at most this, metres
/// (the piecewise-linear road then deviates from the parabola by under a millimetre at 12 %).
const CURVE_CHORD_M: f32 = 1.0;

/// The main street's height profile: flat up to `x0`, then a parabolic vertical curve over `len`
/// metres into the constant grade `g` (rise over run).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Grade {
    x0: f32,
    len: f32,
    g: f32,
}

impl Grade {
    /// Road height at `x`.
    fn z(&self, x: f32) -> f32 {
        let t = x - self.x0;
        if t <= 0.0 {
            0.0
        } else if t < self.len {
            self.g * t * t / (2.0 * self.len)
        } else {
            self.g * (t - self.len / 2.0)
        }
    }

    /// Road slope (dz/dx) at `x`.
    fn slope(&self, x: f32) -> f32 {
        self.g * ((x - self.x0) / self.len).clamp(0.0, 1.0)
    }

    /// `mesh` with every vertex lifted by the road height at its x. Triangles reaching into the
    /// curve are first split (longest extent along x halved) into pieces of at most
    /// [`CURVE_CHORD_M`]; elsewhere the lift is affine in x and triangles stay whole. Vertical
    /// edges stay vertical.
    fn warp(&self, mesh: &Mesh) -> Mesh {
        let (a, b) = (self.x0, self.x0 + self.len);
        let mut out = Mesh {
            triangles: Vec::with_capacity(mesh.triangles.len()),
            surface_of: Vec::with_capacity(mesh.triangles.len()),
            surfaces: mesh.surfaces.clone(),
        };
        let mut stack = Vec::new();
        for (t, &surf) in mesh.triangles.iter().zip(&mesh.surface_of) {
            stack.push(*t);
            while let Some(t) = stack.pop() {
                let lo = t[0].x.min(t[1].x).min(t[2].x);
                let hi = t[0].x.max(t[1].x).max(t[2].x);
                if hi - lo > CURVE_CHORD_M && hi > a && lo < b {
                    // split the edge that spans the most x at its midpoint (orientation kept)
                    let span = |i: usize| (t[(i + 1) % 3].x - t[i].x).abs();
                    let i = (0..3)
                        .max_by(|&i, &j| span(i).total_cmp(&span(j)))
                        .unwrap_or(0);
                    let (j, k) = ((i + 1) % 3, (i + 2) % 3);
                    let m = (t[i] + t[j]) * 0.5;
                    stack.push([t[i], m, t[k]]);
                    stack.push([m, t[j], t[k]]);
                    continue;
                }
                out.triangles
                    .push(t.map(|v| Vec3::new(v.x, v.y, v.z + self.z(v.x))));
                out.surface_of.push(surf);
            }
        }
        out
    }
}

/// An object in a mesh in road coordinates: its triangles `start..end` and its anchor (s, d). On
/// a curved street a rigid part keeps the road frame at its anchor (it is turned whole with the
/// road there); a bent one (a building, a run of fence) follows the road vertex by vertex.
#[derive(Debug, Clone, Copy)]
struct Part {
    start: usize,
    end: usize,
    anchor: Vec2,
    bent: bool,
}

/// Sorted cut positions along s: every triangle is split at these (see [`clip_slabs`]).
fn cut_planes(grade: Option<&Grade>, curve: Option<&RoadCurve>) -> Vec<f32> {
    let mut planes = Vec::new();
    let mut span = |a: f32, len: f32, step: f32| {
        let n = (len / step).ceil().max(1.0) as usize;
        planes.extend((0..=n).map(|i| {
            if i == n {
                a + len
            } else {
                a + len * i as f32 / n as f32
            }
        }));
    };
    if let Some(g) = grade {
        span(g.x0, g.len, CURVE_CHORD_M);
    }
    if let Some(c) = curve {
        // chords short enough that the sagitta stays at a few millimetres at any offset
        span(
            c.arc_start_m(),
            c.arc_length_m(),
            (c.radius_m() / 50.0).clamp(0.5, 4.0),
        );
    }
    planes.sort_by(f32::total_cmp);
    planes.dedup();
    planes
}

/// The point where the segment `a b` crosses `x`, computed the same way from either end (so that
/// neighbouring triangles split their shared edge at the same point: no cracks).
fn cut(a: Vec3, b: Vec3, x: f32) -> Vec3 {
    let (u, v) = if a.to_array() <= b.to_array() {
        (a, b)
    } else {
        (b, a)
    };
    let t = (x - u.x) / (v.x - u.x);
    let mut p = u + (v - u) * t;
    p.x = x;
    p
}

/// Split triangle `t` at every plane `x = p` of `planes` (sorted) that crosses it and hand the
/// pieces (fans of the clipped polygons, orientation kept) to `emit`.
fn clip_slabs(t: [Vec3; 3], planes: &[f32], emit: &mut impl FnMut([Vec3; 3])) {
    let lo = t[0].x.min(t[1].x).min(t[2].x);
    let hi = t[0].x.max(t[1].x).max(t[2].x);
    let i0 = planes.partition_point(|&p| p <= lo);
    let i1 = planes.partition_point(|&p| p < hi);
    if i0 >= i1 {
        emit(t);
        return;
    }
    let mut bounds = vec![lo];
    bounds.extend_from_slice(&planes[i0..i1]);
    bounds.push(hi);
    let clip = |poly: &[Vec3], x: f32, keep_above: bool| -> Vec<Vec3> {
        let inside = |v: &Vec3| if keep_above { v.x >= x } else { v.x <= x };
        let mut out = Vec::with_capacity(poly.len() + 2);
        for (i, a) in poly.iter().enumerate() {
            let b = &poly[(i + 1) % poly.len()];
            if inside(a) {
                out.push(*a);
            }
            if inside(a) != inside(b) && a.x != x && b.x != x {
                out.push(cut(*a, *b, x));
            }
        }
        out
    };
    for w in bounds.windows(2) {
        let poly = clip(&clip(&t[..], w[0], true), w[1], false);
        for i in 1..poly.len().saturating_sub(1) {
            emit([poly[0], poly[i], poly[i + 1]]);
        }
    }
}

/// `mesh`, built in road coordinates, laid along the curved street: with a grade every vertex is
/// first lifted by the road height at its s; the rigid parts are then moved whole by the road's
/// frame at their anchor, everything else bent through the centreline map vertex by vertex
/// (triangles split at chords along the arc and at 1 m in the vertical curve). With `keep_clear` a
/// rigid part beside the road is moved out along the road's normal by as much as its straight
/// sides would otherwise reach closer to the centreline than laid out (the ends of a long parked
/// vehicle on the inside of a bend), so that it keeps clear of the lanes. On the inside of the bend
/// the map would fold over at the turning centre: ground reaching past it is clipped there, other
/// geometry reaching within [`INNER_MARGIN_M`] of it is dropped (a part as a whole).
fn warp_road(
    mesh: &Mesh,
    parts: &[Part],
    grade: Option<&Grade>,
    curve: &RoadCurve,
    keep_clear: bool,
) -> Mesh {
    let mut out = Mesh {
        triangles: Vec::with_capacity(mesh.triangles.len() * 2),
        surface_of: Vec::with_capacity(mesh.triangles.len() * 2),
        surfaces: mesh.surfaces.clone(),
    };
    let grade_planes = cut_planes(grade, None);
    let all_planes = cut_planes(grade, Some(curve));
    let (side, limit) = curve.inner_limit_m();
    let inner = |v: &Vec3| side * v.y;
    let lift = |v: Vec3| Vec3::new(v.x, v.y, v.z + grade.map_or(0.0, |g| g.z(v.x)));
    let push = |out: &mut Mesh, t: [Vec3; 3], surf: u32| {
        let area2 = (t[1] - t[0]).cross(t[2] - t[0]).length_squared();
        if area2 > 1e-12 && area2.is_finite() {
            out.triangles.push(t);
            out.surface_of.push(surf);
        }
    };
    let bend = |v: Vec3| {
        let v = lift(v);
        let w = curve.to_world(v.x, v.y);
        Vec3::new(w.x, w.y, v.z)
    };
    let mut next_part = parts.iter().peekable();
    let mut i = 0;
    while i < mesh.triangles.len() {
        if let Some(part) = next_part.next_if(|p| p.start == i) {
            let tris = &mesh.triangles[part.start..part.end];
            let surfs = &mesh.surface_of[part.start..part.end];
            i = part.end;
            if tris
                .iter()
                .flatten()
                .any(|v| inner(v) > limit - INNER_MARGIN_M)
            {
                continue;
            }
            if part.bent {
                for (t, &surf) in tris.iter().zip(surfs) {
                    clip_slabs(*t, &all_planes, &mut |p| push(&mut out, p.map(bend), surf));
                }
                continue;
            }
            let (s, d) = (part.anchor.x, part.anchor.y);
            let mut xf = curve.world_from_road_at(s, d);
            if keep_clear && d != 0.0 {
                let away = d.signum();
                let closer = tris
                    .iter()
                    .flatten()
                    .map(|v| {
                        let w = xf.transform_point3(*v);
                        away * (v.y - curve.to_road(Vec2::new(w.x, w.y)).1)
                    })
                    .fold(0.0f32, f32::max);
                if closer > 0.0 {
                    let (_, heading) = curve.centreline(s);
                    let n = Vec3::new(-heading.sin(), heading.cos(), 0.0);
                    xf = Affine3A::from_translation(n * (away * closer)) * xf;
                }
            }
            for (t, &surf) in tris.iter().zip(surfs) {
                clip_slabs(*t, &grade_planes, &mut |p| {
                    push(&mut out, p.map(|v| xf.transform_point3(lift(v))), surf);
                });
            }
            continue;
        }
        let (t, surf) = (mesh.triangles[i], mesh.surface_of[i]);
        i += 1;
        let ground = t[0].z == t[1].z && t[1].z == t[2].z;
        let t = if ground {
            t.map(|v| Vec3::new(v.x, side * inner(&v).min(limit), v.z))
        } else if t.iter().any(|v| inner(v) > limit - INNER_MARGIN_M) {
            continue;
        } else {
            t
        };
        clip_slabs(t, &all_planes, &mut |p| push(&mut out, p.map(bend), surf));
    }
    out
}

/// A moving or movable object: a mesh in its own frame moved along a straight line.
#[derive(Debug, Clone)]
pub struct Actor {
    /// Mesh in the actor's frame (x forward, z up, origin on the ground).
    pub mesh: Mesh,
    /// Position of the actor's origin at time 0, world frame (on a curved street, road
    /// coordinates: distance along the centreline, offset across it, height; see
    /// [`Scene::road_curve`]).
    pub start: Vec3,
    /// Heading (rotation about z) in radians.
    pub heading_rad: f32,
    /// Velocity, world frame, m/s (on a curved street, in road coordinates: `x` the speed along
    /// the actor's lane, which [`Scene::mesh_at`] follows around the bend).
    pub velocity: Vec3,
}

impl Actor {
    /// World-from-actor transform at `time_s` (on a curved street: in road coordinates).
    pub fn world_from_actor(&self, time_s: f32) -> Affine3A {
        Affine3A::from_translation(self.start + self.velocity * time_s) * yaw(self.heading_rad)
    }
}

/// A generated scene: the static world, the actors and the ego trajectory. Deterministic in
/// (config, seed).
#[derive(Debug, Clone)]
pub struct Scene {
    config: SceneConfig,
    seed: u64,
    static_mesh: Mesh,
    actors: Vec<Actor>,
    /// LiDAR pose at time 0.
    ego_pose0: Affine3A,
    ego_velocity: Vec3,
    /// The camera of the scene's rig (the config's, or drawn with [`super::RigConfig`]).
    camera: CameraConfig,
    /// The LiDAR's height above the road.
    lidar_height_m: f32,
    /// The main street's height profile (None: flat).
    grade: Option<Grade>,
    /// The main street's bend (None: straight).
    curve: Option<RoadCurve>,
}

impl Scene {
    /// Generate the scene described by `config` with `seed`.
    pub fn generate(config: &SceneConfig, seed: u64) -> Result<Scene> {
        config.validate()?;
        let road = config.road_params();
        let mut g = Gen::new(config, road, seed);
        match config.layout {
            Layout::Straight | Layout::NarrowStreet | Layout::Open => g.straight(),
            Layout::Junction => g.junction(false),
            Layout::TJunction => g.junction(true),
        }
        g.populate();
        let ego_x = g.ego_x;
        let ego_d = -(road.lanes_per_direction as f32 - 0.5) * road.lane_width_m;
        let (lidar_height_m, camera) =
            config
                .rig
                .draw(seed, config.ego.lidar_height_m, &config.camera);
        let grade = (road.grade_percent != [0.0, 0.0])
            .then(|| {
                let mut rng = g.rng(GRADE_STREAM);
                let [lo, hi] = road.grade_percent;
                let percent = lo + (hi - lo) * rng.random::<f32>();
                Grade {
                    x0: ego_x + rng.random_range(-30.0..50.0f32),
                    len: VERTICAL_CURVE_M,
                    g: percent / 100.0,
                }
            })
            .filter(|grade| grade.g != 0.0);
        let curve = (!config.layout.has_cross_street() && road.curve_probability > 0.0)
            .then(|| {
                let mut rng = g.rng(CURVE_STREAM);
                if rng.random::<f32>() >= road.curve_probability {
                    return None;
                }
                let [r0, r1] = road.curve_radius_m;
                let radius = (r0.ln() + (r1.ln() - r0.ln()) * rng.random::<f32>()).exp();
                let [a0, a1] = road.curve_angle_deg;
                let angle = (a0 + (a1 - a0) * rng.random::<f32>()).to_radians();
                let left = rng.random_bool(0.5);
                let start = ego_x + rng.random_range(CURVE_START_M);
                Some(RoadCurve::new(
                    start,
                    radius.clamp(r0, r1),
                    angle.min(std::f32::consts::PI),
                    left,
                ))
            })
            .flatten();
        let static_mesh = match (&curve, &grade) {
            (Some(curve), _) => warp_road(&g.mesh, &g.parts, grade.as_ref(), curve, true),
            (None, Some(grade)) => grade.warp(&g.mesh),
            (None, None) => g.mesh,
        };
        Ok(Scene {
            config: config.clone(),
            seed,
            static_mesh,
            actors: g.actors,
            ego_pose0: Affine3A::from_translation(Vec3::new(ego_x, ego_d, lidar_height_m)),
            ego_velocity: Vec3::new(config.ego.speed_mps, 0.0, 0.0),
            camera,
            lidar_height_m,
            grade,
            curve,
        })
    }

    /// Build a scene from explicit geometry (for tests and custom worlds): a static mesh, actors and
    /// a fixed LiDAR pose (world from LiDAR, rigid); `config` supplies sensors, lighting, return
    /// model and frame interval.
    pub fn from_parts(
        config: &SceneConfig,
        seed: u64,
        static_mesh: Mesh,
        actors: Vec<Actor>,
        world_from_lidar: Affine3A,
    ) -> Scene {
        Scene {
            config: config.clone(),
            seed,
            static_mesh,
            actors,
            ego_pose0: world_from_lidar,
            ego_velocity: Vec3::ZERO,
            camera: config.camera,
            lidar_height_m: world_from_lidar.translation.z,
            grade: None,
            curve: None,
        }
    }

    /// Height of the main street's surface at `x` along it, metres: 0 on a flat street, else the
    /// profile of the grade drawn from [`super::RoadConfig::grade_percent`]. On a straight street
    /// `x` is the world x; on a curved one ([`Scene::road_curve`]) the distance along the
    /// centreline (the height is the same across the street).
    pub fn road_height_m(&self, x: f32) -> f32 {
        self.grade.map_or(0.0, |g| g.z(x))
    }

    /// The main street's bend, drawn from [`super::RoadConfig::curve_probability`] (None: the
    /// street is straight): maps road coordinates (distance along the centreline, offset across
    /// it) to the world.
    pub fn road_curve(&self) -> Option<&RoadCurve> {
        self.curve.as_ref()
    }

    /// The main street's grade after its vertical curve, percent (0: flat).
    pub fn grade_percent(&self) -> f32 {
        self.grade.map_or(0.0, |g| g.g * 100.0)
    }

    /// The camera of the scene's rig: the config's camera, with its height (`up_m`) and pitch
    /// (`pitch_down_deg`) drawn when [`super::RigConfig::randomize`] is on. The frames' camera and
    /// calibration are made from it ([`SimCalib::from_config`]).
    pub fn camera_config(&self) -> &CameraConfig {
        &self.camera
    }

    /// The LiDAR's height above the road, metres: the drawn one with
    /// [`super::RigConfig::randomize`], else `ego.lidar_height_m` (for a scene from
    /// [`Scene::from_parts`], the height of its LiDAR pose).
    pub fn lidar_height_m(&self) -> f32 {
        self.lidar_height_m
    }

    /// The configuration the scene was generated from.
    pub fn config(&self) -> &SceneConfig {
        &self.config
    }

    /// The seed the scene was generated with.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The static world (road, buildings, furniture, parked vehicles).
    pub fn static_mesh(&self) -> &Mesh {
        &self.static_mesh
    }

    /// The moving and movable actors.
    pub fn actors(&self) -> &[Actor] {
        &self.actors
    }

    /// Time of frame `index`, seconds.
    pub fn frame_time_s(&self, index: u32) -> f32 {
        index as f32 * self.config.frames.interval_s
    }

    /// LiDAR pose (world from LiDAR: x forward along the ego's heading, z up) at `time_s`. On a
    /// graded street the ego stands on the road at its x, pitched with the road's slope, the LiDAR
    /// its height above the road along the road's normal.
    pub fn world_from_lidar(&self, time_s: f32) -> Affine3A {
        let flat = Affine3A::from_translation(self.ego_velocity * time_s) * self.ego_pose0;
        if let Some(curve) = &self.curve {
            return self.curved_pose(curve, time_s, flat);
        }
        let Some(grade) = self.grade else {
            return flat;
        };
        let p = flat.translation;
        let pitch = grade.slope(p.x).atan();
        let normal = Vec3::new(-pitch.sin(), 0.0, pitch.cos());
        let ground = Vec3::new(p.x, p.y, grade.z(p.x));
        Affine3A::from_translation(ground + normal * p.z)
            * Affine3A::from_rotation_y(-pitch)
            * Affine3A::from_mat3(Mat3::from(flat.matrix3))
    }

    /// The LiDAR pose on a curved street: the ego's pose in road coordinates (`flat`, its
    /// translation at time 0 and its velocity read as distance along the street and offset across
    /// it) moved along its lane: it travels `speed * time_s` metres along the line at its offset,
    /// heading along the road's tangent there, pitched with the grade along its path.
    fn curved_pose(&self, curve: &RoadCurve, time_s: f32, flat: Affine3A) -> Affine3A {
        let p0 = self.ego_pose0.translation;
        let v = self.ego_velocity;
        let s = curve.advance(p0.x, p0.y, v.x * time_s);
        let d = p0.y + v.y * time_s;
        let (z, slope) = self.grade.map_or((0.0, 0.0), |g| (g.z(s), g.slope(s)));
        // the path at offset d is (1 - curvature d) times as long as the centreline beside it
        let pitch = (slope / (1.0 - curve.curvature_at(s) * d)).atan();
        let (_, heading) = curve.centreline(s);
        let w = curve.to_world(s, d);
        let rot = Mat3::from_rotation_z(heading) * Mat3::from_rotation_y(-pitch);
        let normal = rot * Vec3::Z;
        Affine3A::from_translation(Vec3::new(w.x, w.y, z) + normal * flat.translation.z)
            * Affine3A::from_mat3(rot * Mat3::from(flat.matrix3))
    }

    /// The whole world at `time_s` as one mesh (static world plus actors moved; on a graded street
    /// the actors are lifted onto the road's profile like the static world; on a curved street
    /// they move along their lanes in road coordinates, turned with the road).
    pub fn mesh_at(&self, time_s: f32) -> Mesh {
        let mut m = self.static_mesh.clone();
        if let Some(curve) = &self.curve {
            let mut moving = Mesh::new();
            let mut parts = Vec::with_capacity(self.actors.len());
            for a in &self.actors {
                let s = curve.advance(a.start.x, a.start.y, a.velocity.x * time_s);
                let d = a.start.y + a.velocity.y * time_s;
                let z = a.start.z + a.velocity.z * time_s;
                let start = moving.len();
                moving.append_transformed(
                    &a.mesh,
                    Affine3A::from_translation(Vec3::new(s, d, z)) * yaw(a.heading_rad),
                );
                parts.push(Part {
                    start,
                    end: moving.len(),
                    anchor: Vec2::new(s, d),
                    bent: false,
                });
            }
            m.append(&warp_road(
                &moving,
                &parts,
                self.grade.as_ref(),
                curve,
                false,
            ));
            return m;
        }
        match &self.grade {
            None => {
                for a in &self.actors {
                    m.append_transformed(&a.mesh, a.world_from_actor(time_s));
                }
            }
            Some(grade) => {
                let mut moving = Mesh::new();
                for a in &self.actors {
                    moving.append_transformed(&a.mesh, a.world_from_actor(time_s));
                }
                m.append(&grade.warp(&moving));
            }
        }
        m
    }

    /// The world at frame `index`, ready for rendering.
    pub fn snapshot(&self, index: u32) -> SceneSnapshot {
        let time_s = self.frame_time_s(index);
        let mesh = self.mesh_at(time_s);
        // the appearance is drawn per scene (from its seed): the same in every frame; each half
        // alone keeps only its part of the draw
        let cfg = &self.config.appearance;
        let drawn = (cfg.draws_lighting() || cfg.draws_materials())
            .then(|| Appearance::draw(cfg, &self.config.lighting, self.seed));
        let light = drawn.as_ref().filter(|_| cfg.draws_lighting());
        SceneSnapshot {
            accel: Accel::build(&mesh),
            time_s,
            world_from_lidar: self.world_from_lidar(time_s),
            lighting: light.map_or(self.config.lighting, |a| a.lighting),
            overcast: light.map_or(0.0, |a| a.overcast),
            noise_seed: splitmix(self.seed ^ splitmix(u64::from(index).wrapping_add(0x5eed))),
            appearance: drawn.filter(|_| cfg.draws_materials()),
        }
    }

    /// Render frame `index` with a rig of cameras: the scene's camera (in the returned frame) and
    /// one more per entry of `yaws_deg`, the same camera turned that many degrees about the
    /// LiDAR's vertical axis (positive: to the left; nuScenes' front-left and front-right cameras
    /// sit at about +55 and -55 degrees). The further views come in the order of `yaws_deg`.
    pub fn render_frame_rig(
        &self,
        index: u32,
        yaws_deg: &[f32],
    ) -> Result<(SimFrame, Vec<SimView>)> {
        let frame = self.render_frame(index)?;
        if yaws_deg.is_empty() {
            return Ok((frame, Vec::new()));
        }
        let snap = self.snapshot(index);
        let opts = CameraRenderOptions::from(&self.camera);
        let views = yaws_deg
            .iter()
            .map(|&yaw| {
                // the same camera, its frame turned about the LiDAR's z axis: a point at azimuth
                // `yaw` is where the scene camera sees azimuth 0
                let camera = PinholeCamera {
                    cam_from_lidar: frame.camera.cam_from_lidar
                        * glam::Mat4::from_rotation_z(-yaw.to_radians()),
                    ..frame.camera
                };
                let image = snap.render_camera(&camera, &opts)?;
                Ok(SimView {
                    yaw_deg: yaw,
                    camera,
                    image,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok((frame, views))
    }

    /// The scan of frame `index` alone, with the config's LiDAR and return model: the same
    /// scan as [`Scene::render_frame`]'s, without the camera image, which costs most of a frame
    /// (for models that never look at the camera, such as unconditional ones).
    pub fn render_scan(&self, index: u32) -> Result<SimScan> {
        let sensor = self.config.lidar.sensor()?;
        self.snapshot(index)
            .render_lidar(&sensor, &self.config.lidar.returns)
    }

    /// Render frame `index` with the scene's own sensors (the config's LiDAR, return model and
    /// camera): the paired scan and image without touching files, for training and demo code.
    pub fn render_frame(&self, index: u32) -> Result<SimFrame> {
        let sensor = self.config.lidar.sensor()?;
        let calib = SimCalib::from_config(&self.camera);
        let camera = calib.camera()?;
        let snap = self.snapshot(index);
        let scan = snap.render_lidar(&sensor, &self.config.lidar.returns)?;
        let image = snap.render_camera(&camera, &CameraRenderOptions::from(&self.camera))?;
        Ok(SimFrame {
            index,
            time_s: snap.time_s,
            world_from_lidar: snap.world_from_lidar,
            sensor,
            camera,
            calib,
            scan,
            image,
        })
    }
}

/// A further camera of a rig frame ([`Scene::render_frame_rig`]).
#[derive(Debug, Clone)]
pub struct SimView {
    /// The turn from the scene's camera, degrees (positive: to the left).
    pub yaw_deg: f32,
    /// The camera.
    pub camera: PinholeCamera,
    /// Its image with depth and semantics.
    pub image: SimImage,
}

/// One rendered frame: a LiDAR scan and the paired camera image with their sensors.
#[derive(Debug, Clone)]
pub struct SimFrame {
    /// Frame index.
    pub index: u32,
    /// Time since frame 0, seconds.
    pub time_s: f32,
    /// LiDAR pose (world from LiDAR).
    pub world_from_lidar: Affine3A,
    /// The LiDAR that took the scan.
    pub sensor: LidarSensor,
    /// The camera that took the image (`cam_from_lidar`, intrinsics).
    pub camera: PinholeCamera,
    /// KITTI-style calibration of the rig.
    pub calib: SimCalib,
    /// The scan.
    pub scan: SimScan,
    /// The image with depth and semantics.
    pub image: SimImage,
}

/// A street in its own frame: `s` along the street, `d` across (left positive), z up.
#[derive(Clone, Copy)]
struct StreetFrame {
    world_from_street: Affine3A,
}

impl StreetFrame {
    fn main() -> Self {
        StreetFrame {
            world_from_street: Affine3A::IDENTITY,
        }
    }
    /// The cross street: s along world +y, d along world -x (exact 90 degree rotation).
    fn cross() -> Self {
        StreetFrame {
            world_from_street: Affine3A::from_mat3(Mat3::from_cols(Vec3::Y, -Vec3::X, Vec3::Z)),
        }
    }
    fn p(&self, s: f32, d: f32, z: f32) -> Vec3 {
        self.world_from_street.transform_point3(Vec3::new(s, d, z))
    }
    /// Place an object at (s, d, z) heading `h` (radians from +s toward +d).
    fn place(&self, s: f32, d: f32, z: f32, h: f32) -> Affine3A {
        self.world_from_street * Affine3A::from_translation(Vec3::new(s, d, z)) * yaw(h)
    }
    fn heading(&self, h: f32) -> f32 {
        // the cross street's +s axis is world +y (heading +pi/2)
        if self.world_from_street == Affine3A::IDENTITY {
            h
        } else {
            h + std::f32::consts::FRAC_PI_2
        }
    }
    fn dir(&self, s: f32, d: f32) -> Vec3 {
        self.world_from_street
            .transform_vector3(Vec3::new(s, d, 0.0))
    }
    /// Ground rectangle in street coordinates.
    fn rect(&self, mesh: &mut Mesh, s0: f32, s1: f32, d0: f32, d1: f32, z: f32, surf: u32) {
        let a = self.p(s0, d0, z);
        let b = self.p(s1, d1, z);
        mesh.add_ground_rect(a.x, b.x, a.y, b.y, z, TILE_M, surf);
    }
}

/// Occupied intervals along s on one side of a street (keeps objects apart).
#[derive(Default)]
struct Occupancy(Vec<(f32, f32)>);

impl Occupancy {
    fn free(&self, a: f32, b: f32) -> bool {
        self.0.iter().all(|&(x, y)| b <= x || a >= y)
    }
    fn take(&mut self, a: f32, b: f32) {
        self.0.push((a, b));
    }
}

/// A section of street the population step may use.
#[derive(Clone, Copy)]
struct Section {
    frame: StreetFrame,
    s0: f32,
    s1: f32,
    main: bool,
}

struct Gen<'a> {
    cfg: &'a SceneConfig,
    road: RoadParams,
    seed: u64,
    mesh: Mesh,
    actors: Vec<Actor>,
    sections: Vec<Section>,
    /// s intervals of crosswalk / junction areas on the main street where nothing parks.
    no_parking: Vec<(f32, f32)>,
    next_instance: u16,
    furniture: Vec<Occupancy>,
    /// Street sections whose lots were built so far (numbers the open-roadside draws).
    lot_calls: u64,
    /// The objects in `mesh`: triangle range and anchor (s, d) in road coordinates. A curved
    /// street turns the rigid ones (trees, poles, signs, vehicles) whole with the road at their
    /// anchor and bends the others (buildings, fences, hedges, guardrails) along with it, like the
    /// ground and the markings.
    parts: Vec<Part>,
    /// The ego's position along the main street at frame 0 ([`super::EgoConfig::start_x`]).
    ego_x: f32,
}

impl<'a> Gen<'a> {
    fn new(cfg: &'a SceneConfig, road: RoadParams, seed: u64) -> Self {
        Gen {
            cfg,
            road,
            seed,
            mesh: Mesh::new(),
            actors: Vec::new(),
            sections: Vec::new(),
            no_parking: Vec::new(),
            next_instance: 1,
            furniture: (0..4).map(|_| Occupancy::default()).collect(),
            lot_calls: 0,
            parts: Vec::new(),
            ego_x: cfg.ego.start_x(seed),
        }
    }

    /// Append a rigid object placed by `xf` (its anchor: the translation of `xf`).
    fn put(&mut self, m: &Mesh, xf: Affine3A) {
        self.put_part(m, xf, false);
    }

    /// Append an object placed by `xf` that bends with a curved street (a building, a fence).
    fn put_bent(&mut self, m: &Mesh, xf: Affine3A) {
        self.put_part(m, xf, true);
    }

    fn put_part(&mut self, m: &Mesh, xf: Affine3A, bent: bool) {
        let start = self.mesh.len();
        self.mesh.append_transformed(m, xf);
        self.parts.push(Part {
            start,
            end: self.mesh.len(),
            anchor: Vec2::new(xf.translation.x, xf.translation.y),
            bent,
        });
    }

    /// An independent random stream per purpose, so that changing one count does not reshuffle
    /// everything else.
    fn rng(&self, stream: u64) -> ChaCha8Rng {
        let mut r = ChaCha8Rng::seed_from_u64(self.seed);
        r.set_stream(stream);
        r
    }

    fn instance(&mut self) -> u16 {
        let i = self.next_instance;
        self.next_instance = self.next_instance.wrapping_add(1).max(1);
        i
    }

    fn half_len(&self) -> f32 {
        self.road.length_m / 2.0
    }

    /// Outer extent of the world across a street (terrain reaches this far; further when sides
    /// may be open, to carry their far buildings and trees).
    fn outer_d(&self) -> f32 {
        let r = &self.road;
        let back = if r.open_side_probability > 0.0 && !self.cfg.layout.has_cross_street() {
            r.setback_m.max(r.open_setback_m[1] + 20.0)
        } else {
            r.setback_m
        };
        r.half_carriageway_m() + r.sidewalk_width_m + back + 45.0
    }

    fn straight(&mut self) {
        let h = self.half_len();
        let f = StreetFrame::main();
        let mut rng = self.rng(1);
        self.street_surfaces(f, -h, h, -h, h, true);
        self.lots(&mut rng, f, -h, h);
        self.furniture(&mut rng, f, -h, h, 0);
        self.sections.push(Section {
            frame: f,
            s0: -h,
            s1: h,
            main: true,
        });
    }

    /// Two streets crossing at the origin; with `tee`, the main street (the ego's) ends there and
    /// the cross street's far side is one row of lots across its end, facing the ego.
    fn junction(&mut self, tee: bool) {
        let h = self.half_len();
        let r = self.road;
        let wc = r.half_carriageway_m();
        let sw = r.sidewalk_width_m;
        let mut rng = self.rng(2);
        let main = StreetFrame::main();
        let cross = StreetFrame::cross();
        // junction box
        let road = self.mesh.surface(stock::ROAD, 0);
        main.rect(&mut self.mesh, -wc, wc, -wc, wc, 0.0, road);
        for (f, is_main) in [(main, true), (cross, false)] {
            for (s0, s1) in [(-h, -wc), (wc, h)] {
                if tee && is_main && s0 > 0.0 {
                    // the main street ends at the cross street
                    continue;
                }
                let (ts0, ts1) = if s0 < 0.0 {
                    (s0, -wc - sw)
                } else {
                    (wc + sw, s1)
                };
                self.street_surfaces(f, s0, s1, ts0, ts1, is_main);
                let (l0, l1) = if s0 < 0.0 {
                    (s0, -(wc + sw + r.setback_m + 1.0))
                } else {
                    (wc + sw + r.setback_m + 1.0, s1)
                };
                if tee && !is_main {
                    // the near side only: the far side is one row across, below
                    self.lots_on(&mut rng, f, l0, l1, &[1.0]);
                } else {
                    self.lots(&mut rng, f, l0, l1);
                }
                self.furniture(
                    &mut rng,
                    f,
                    s0 + if s0 < 0.0 { 0.0 } else { 2.0 },
                    s1 - if s0 < 0.0 { 2.0 } else { 0.0 },
                    if is_main { 0 } else { 1 },
                );
                self.sections.push(Section {
                    frame: f,
                    s0,
                    s1,
                    main: is_main,
                });
            }
            self.crosswalks(f, tee && is_main);
        }
        if tee {
            // the cross street's far side (cross frame d < 0, world +x) across the end of the
            // main street: kerb, sidewalk and ground, then the lots facing the ego
            let kh = r.kerb_height_m;
            let walk = self.mesh.surface(stock::SIDEWALK, 0);
            let grass = self.mesh.surface(stock::TERRAIN, 0);
            self.mesh.add_quad(
                cross.p(-wc, -wc, 0.0),
                cross.p(wc, -wc, 0.0),
                cross.p(wc, -wc, kh),
                cross.p(-wc, -wc, kh),
                walk,
            );
            cross.rect(&mut self.mesh, -wc, wc, -wc, -(wc + sw), kh, walk);
            let outer = self.outer_d();
            cross.rect(
                &mut self.mesh,
                -wc - sw,
                wc + sw,
                -(wc + sw),
                -outer,
                kh,
                grass,
            );
            self.lots_on(&mut rng, cross, -h, h, &[-1.0]);
        }
        self.no_parking.push((-wc - 12.0, wc + 12.0));
        // traffic lights on the four corners, facing the approaching traffic of the main street
        for (sx, sy) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
            let light = objects::traffic_light();
            let facing = if sy < 0.0 { std::f32::consts::PI } else { 0.0 };
            let xf = Affine3A::from_translation(Vec3::new(
                sx * (wc + 0.6),
                sy * (wc + 0.6),
                r.kerb_height_m,
            )) * yaw(facing);
            self.put(&light, xf);
        }
    }

    /// Road (with parking strips and markings), kerbs, sidewalks and terrain of one street section.
    /// Terrain covers `[ts0, ts1]` along s when `terrain` is set.
    fn street_surfaces(
        &mut self,
        f: StreetFrame,
        s0: f32,
        s1: f32,
        ts0: f32,
        ts1: f32,
        terrain: bool,
    ) {
        let r = self.road;
        let wl = r.lanes_per_direction as f32 * r.lane_width_m;
        let wc = r.half_carriageway_m();
        let kh = r.kerb_height_m;
        let road = self.mesh.surface(stock::ROAD, 0);
        let parking = self.mesh.surface(stock::PARKING, 0);
        let walk = self.mesh.surface(stock::SIDEWALK, 0);
        let grass = self.mesh.surface(stock::TERRAIN, 0);
        f.rect(&mut self.mesh, s0, s1, -wl, wl, 0.0, road);
        if r.parking_lane {
            f.rect(&mut self.mesh, s0, s1, -wc, -wl, 0.0, parking);
            f.rect(&mut self.mesh, s0, s1, wl, wc, 0.0, parking);
        }
        for side in [-1.0f32, 1.0] {
            // kerb face, split along s like the ground tiles
            let n = ((s1 - s0) / TILE_M).ceil().max(1.0) as usize;
            for i in 0..n {
                let a = s0 + (s1 - s0) * i as f32 / n as f32;
                let b = if i + 1 == n {
                    s1
                } else {
                    s0 + (s1 - s0) * (i + 1) as f32 / n as f32
                };
                let d = side * wc;
                self.mesh.add_quad(
                    f.p(a, d, 0.0),
                    f.p(b, d, 0.0),
                    f.p(b, d, kh),
                    f.p(a, d, kh),
                    walk,
                );
            }
            let (d0, d1) = (side * wc, side * (wc + r.sidewalk_width_m));
            f.rect(&mut self.mesh, s0, s1, d0, d1, kh, walk);
            if terrain && ts1 > ts0 {
                let (e0, e1) = (side * (wc + r.sidewalk_width_m), side * self.outer_d());
                f.rect(&mut self.mesh, ts0, ts1, e0, e1, kh, grass);
            }
        }
        if r.lane_markings {
            self.markings(f, s0, s1);
        }
    }

    fn markings(&mut self, f: StreetFrame, s0: f32, s1: f32) {
        let r = self.road;
        let paint = self.mesh.surface(stock::LANE_MARKING, 0);
        let wl = r.lanes_per_direction as f32 * r.lane_width_m;
        let line = |mesh: &mut Mesh, a: f32, b: f32, d: f32, w: f32| {
            mesh.add_quad(
                f.p(a, d - w / 2.0, PAINT_Z),
                f.p(b, d - w / 2.0, PAINT_Z),
                f.p(b, d + w / 2.0, PAINT_Z),
                f.p(a, d + w / 2.0, PAINT_Z),
                paint,
            );
        };
        // centre line: solid
        line(&mut self.mesh, s0, s1, 0.0, 0.15);
        // edge lines
        let edge = if r.parking_lane { wl } else { wl - 0.3 };
        line(&mut self.mesh, s0, s1, edge, 0.15);
        line(&mut self.mesh, s0, s1, -edge, 0.15);
        // dashed lane separators: 3 m dashes every 9 m
        for k in 1..r.lanes_per_direction {
            let d = k as f32 * r.lane_width_m;
            let mut a = (s0 / 9.0).ceil() * 9.0;
            while a + 3.0 <= s1 {
                line(&mut self.mesh, a, a + 3.0, d, 0.12);
                line(&mut self.mesh, a, a + 3.0, -d, 0.12);
                a += 9.0;
            }
        }
    }

    /// Crosswalks and stop lines on both arms of `f` at the junction (the near arm alone with
    /// `near_only`: a T junction's main street has no far arm).
    fn crosswalks(&mut self, f: StreetFrame, near_only: bool) {
        let r = self.road;
        if !r.lane_markings {
            return;
        }
        let paint = self.mesh.surface(stock::LANE_MARKING, 0);
        let wl = r.lanes_per_direction as f32 * r.lane_width_m;
        let wc = r.half_carriageway_m();
        let arms: &[f32] = if near_only { &[-1.0] } else { &[-1.0, 1.0] };
        for &dir in arms {
            let (a, b) = (wc + 1.0, wc + 4.0);
            let (a, b) = if dir > 0.0 { (a, b) } else { (-b, -a) };
            let mut d = -wl + 0.25;
            while d + 0.5 <= wl {
                self.mesh.add_quad(
                    f.p(a, d, PAINT_Z),
                    f.p(b, d, PAINT_Z),
                    f.p(b, d + 0.5, PAINT_Z),
                    f.p(a, d + 0.5, PAINT_Z),
                    paint,
                );
                d += 1.0;
            }
            // stop line across the lanes approaching the junction on this arm
            let s = dir * (wc + 5.0);
            let (d0, d1) = if dir > 0.0 { (0.1, wl) } else { (-wl, -0.1) };
            self.mesh.add_quad(
                f.p(s - 0.2, d0, PAINT_Z),
                f.p(s + 0.2, d0, PAINT_Z),
                f.p(s + 0.2, d1, PAINT_Z),
                f.p(s - 0.2, d1, PAINT_Z),
                paint,
            );
        }
    }

    /// Buildings and the gaps between them (fences, hedges, bushes) on both sides of `[s0, s1]`.
    fn lots(&mut self, rng: &mut ChaCha8Rng, f: StreetFrame, s0: f32, s1: f32) {
        self.lots_on(rng, f, s0, s1, &[-1.0, 1.0]);
    }

    /// [`Self::lots`] on the given sides of the street (`-1`: `d < 0`, `1`: `d > 0`).
    fn lots_on(&mut self, rng: &mut ChaCha8Rng, f: StreetFrame, s0: f32, s1: f32, sides: &[f32]) {
        let r = self.road;
        let front = r.half_carriageway_m() + r.sidewalk_width_m + r.setback_m;
        let [hmin, hmax] = r.building_height_m;
        let call = self.lot_calls;
        self.lot_calls += 1;
        for &side in sides {
            // the junction's arms keep their lots (open ground there would run into the cross street)
            if !self.cfg.layout.has_cross_street() && self.side_open(call, side) {
                self.open_side(f, s0, s1, side, call);
                continue;
            }
            let mut s = s0 + rng.random_range(0.0..4.0f32);
            while s < s1 - 4.0 {
                if rng.random::<f32>() < r.building_frontage {
                    let w = rng.random_range(8.0..24.0f32).min(s1 - s);
                    let depth = rng.random_range(8.0..18.0f32);
                    let height = rng.random_range(hmin..=hmax);
                    let b = objects::building(rng, w, depth, height);
                    // building frame: facade at local y = 0 faces local +y; turn it to face the street
                    let h = if side > 0.0 {
                        std::f32::consts::PI
                    } else {
                        0.0
                    };
                    self.put_bent(&b, f.place(s + w / 2.0, side * front, r.kerb_height_m, h));
                    s += w + rng.random_range(0.0..1.5f32);
                } else {
                    let w = rng.random_range(4.0..12.0f32).min(s1 - s);
                    let u = rng.random::<f32>();
                    let d = side * (front - 0.4);
                    if u < self.cfg.population.fence_probability {
                        let fe = objects::fence(w, rng.random_range(1.0..2.0f32));
                        self.put_bent(&fe, f.place(s + w / 2.0, d, r.kerb_height_m, 0.0));
                    } else if u < self.cfg.population.fence_probability + 0.35 {
                        let he = objects::hedge(rng, w);
                        self.put_bent(&he, f.place(s + w / 2.0, d, r.kerb_height_m, 0.0));
                    } else if rng.random_bool(0.6) {
                        let t = objects::tree(rng);
                        self.put(
                            &t,
                            f.place(s + w / 2.0, side * (front + 4.0), r.kerb_height_m, 0.0),
                        );
                    }
                    s += w;
                }
            }
            // bushes in front gardens and gaps
            if r.setback_m > 0.8 {
                let n = poisson_count(
                    rng,
                    self.cfg.population.bushes_per_100m * 0.5 * (s1 - s0) / 100.0,
                );
                for _ in 0..n {
                    let bs = rng.random_range(s0..s1);
                    let bd = side * (front - rng.random_range(0.5..r.setback_m.min(3.0)));
                    let b = objects::bush(rng);
                    self.put(&b, f.place(bs, bd, r.kerb_height_m, 0.0));
                }
            }
        }
    }

    /// Whether side `side` of the `call`-th street section is open (its own random stream: the
    /// draw never shifts the other streams, and with probability 0 nothing changes).
    fn side_open(&self, call: u64, side: f32) -> bool {
        let p = self.road.open_side_probability;
        if p <= 0.0 {
            return false;
        }
        let mut rng = self.rng(OPEN_STREAM + 2 * call + u64::from(side > 0.0));
        rng.random::<f32>() < p
    }

    /// An open roadside along `[s0, s1]` on `side`: maybe a guardrail at the road edge, maybe a
    /// far building row, and open ground with trees (a row, clusters, single trees), bushes and
    /// field fences or hedges in front of it.
    fn open_side(&mut self, f: StreetFrame, s0: f32, s1: f32, side: f32, call: u64) {
        let r = self.road;
        let p = self.cfg.population.clone();
        let mut rng = self.rng(OPEN_STREAM + 0x100 + 2 * call + u64::from(side > 0.0));
        let kh = r.kerb_height_m;
        let wc = r.half_carriageway_m();
        let front = wc + r.sidewalk_width_m;
        let len = (s1 - s0).max(0.0);
        // heading that turns an object's local +y toward the road
        let to_road = if side > 0.0 {
            std::f32::consts::PI
        } else {
            0.0
        };
        // (no guardrail beside a parking strip)
        if rng.random::<f32>() < r.guardrail_probability && !r.parking_lane {
            let d = side * (wc + 0.25);
            let mut s = s0 + rng.random_range(0.0..20.0f32);
            while s < s1 - 10.0 {
                let l = rng.random_range(30.0..150.0f32).min(s1 - 1.0 - s);
                if l < 8.0 {
                    break;
                }
                let g = objects::guardrail(l);
                self.put_bent(&g, f.place(s + l / 2.0, d, kh, to_road));
                s += l + rng.random_range(4.0..40.0f32);
            }
        }
        // far buildings: a sparse row well behind the open ground
        let mut reach = 60.0f32;
        if rng.random::<f32>() < r.open_building_probability {
            let [lo, hi] = r.open_setback_m;
            let setback = lo + (hi - lo) * rng.random::<f32>();
            reach = setback - 3.0;
            let [hmin, hmax] = r.building_height_m;
            let mut s = s0 + rng.random_range(0.0..10.0f32);
            while s < s1 - 8.0 {
                let w = rng.random_range(8.0..20.0f32).min(s1 - s);
                if rng.random::<f32>() < r.building_frontage {
                    let depth = rng.random_range(8.0..16.0f32);
                    let height = rng.random_range(hmin..=hmax);
                    let b = objects::building(&mut rng, w, depth, height);
                    let dd = side * (front + setback + rng.random_range(0.0..4.0f32));
                    self.put_bent(&b, f.place(s + w / 2.0, dd, kh, to_road));
                }
                s += w + rng.random_range(2.0..12.0f32);
            }
        }
        let dist = |rng: &mut ChaCha8Rng, a: f32, b: f32| rng.random_range(a..b.max(a + 0.1));
        let tree_at = |g: &mut Self, rng: &mut ChaCha8Rng, s: f32, d_out: f32| {
            let t = objects::tree(rng);
            let k = rng.random_range(0.8..1.6f32);
            g.put(
                &t,
                f.place(s, side * (front + d_out), kh, 0.0) * Affine3A::from_scale(Vec3::splat(k)),
            );
        };
        // a row of trees along the road (an avenue or a windbreak)
        if rng.random_bool(0.4) {
            let d_row = dist(&mut rng, 2.0, reach.min(25.0));
            let spacing = rng.random_range(6.0..14.0f32);
            let mut s = s0 + rng.random_range(0.0..spacing);
            while s < s1 {
                if rng.random_bool(0.8) {
                    let jitter = rng.random_range(-0.8..0.8f32);
                    tree_at(self, &mut rng, s, d_row + jitter);
                }
                s += spacing * rng.random_range(0.85..1.15f32);
            }
        }
        // clusters of trees (copses) at varied distances
        let density = p.trees_per_100m / 8.0;
        let clusters = poisson_count(&mut rng, 2.5 * density * len / 100.0);
        for _ in 0..clusters {
            let cs = rng.random_range(s0..s1.max(s0 + 1e-3));
            let cd = dist(&mut rng, 4.0, reach);
            let spread = rng.random_range(3.0..10.0f32);
            for _ in 0..rng.random_range(3..12u32) {
                let s = (cs + rng.random_range(-spread..spread)).clamp(s0, s1);
                let d = (cd + rng.random_range(-spread..spread) * 0.6).clamp(2.0, reach.max(2.0));
                tree_at(self, &mut rng, s, d);
            }
        }
        // single trees and bushes scattered over the open ground
        for _ in 0..poisson_count(&mut rng, 1.5 * p.trees_per_100m * len / 100.0) {
            let s = rng.random_range(s0..s1.max(s0 + 1e-3));
            let d = dist(&mut rng, 2.0, reach);
            tree_at(self, &mut rng, s, d);
        }
        for _ in 0..poisson_count(&mut rng, p.bushes_per_100m * len / 100.0) {
            let s = rng.random_range(s0..s1.max(s0 + 1e-3));
            let d = dist(&mut rng, 1.0, reach);
            let b = objects::bush(&mut rng);
            self.put(&b, f.place(s, side * (front + d), kh, 0.0));
        }
        // a field boundary: fence or hedge runs with gaps, parallel to the road
        let u = rng.random::<f32>();
        if u < 0.6 {
            let d = dist(&mut rng, 3.0, reach.min(30.0));
            let mut s = s0 + rng.random_range(0.0..20.0f32);
            while s < s1 - 5.0 {
                let l = rng.random_range(15.0..60.0f32).min(s1 - s);
                let m = if rng.random::<f32>() < p.fence_probability {
                    objects::fence(l, rng.random_range(0.9..1.6f32))
                } else {
                    objects::hedge(&mut rng, l)
                };
                self.put_bent(&m, f.place(s + l / 2.0, side * (front + d), kh, 0.0));
                s += l + rng.random_range(5.0..40.0f32);
            }
        }
        self.tree_lines(f, s0, s1, side, call, reach);
    }

    /// Tree lines on an open roadside (with [`PopulationConfig::tree_line_probability`]): runs of
    /// woodland belts parallel to the road, in front of the far building row when there is one.
    fn tree_lines(&mut self, f: StreetFrame, s0: f32, s1: f32, side: f32, call: u64, reach: f32) {
        let p = self.cfg.population.tree_line_probability;
        if p <= 0.0 {
            return;
        }
        let mut rng = self.rng(TREE_LINE_STREAM + 2 * call + u64::from(side > 0.0));
        if rng.random::<f32>() >= p {
            return;
        }
        let r = self.road;
        let front = r.half_carriageway_m() + r.sidewalk_width_m;
        let heights = self.cfg.population.tree_line_height_m;
        let to_road = if side > 0.0 {
            std::f32::consts::PI
        } else {
            0.0
        };
        // one distance per side (a woodland edge runs along the road), varied a little per run
        let d_side = rng.random_range(2.0..reach.clamp(2.1, 50.0));
        let mut s = s0 + rng.random_range(0.0..30.0f32);
        while s < s1 - 10.0 {
            let l = rng.random_range(30.0..150.0f32).min(s1 - s);
            let d = (d_side + rng.random_range(-3.0..3.0f32)).max(1.0);
            // (not through the far building row)
            let depth = rng.random_range(4.0..14.0f32).min((reach - d).max(2.0));
            let m = objects::tree_line(&mut rng, l, depth, heights);
            self.put_bent(
                &m,
                f.place(s + l / 2.0, side * (front + d), r.kerb_height_m, to_road),
            );
            s += l + rng.random_range(0.0..30.0f32);
        }
    }

    /// Trees, street lights and signs along the kerb of both sides.
    fn furniture(&mut self, rng: &mut ChaCha8Rng, f: StreetFrame, s0: f32, s1: f32, occ: usize) {
        let r = self.road;
        let p = &self.cfg.population;
        let wc = r.half_carriageway_m();
        let kh = r.kerb_height_m;
        let len = (s1 - s0).max(0.0);
        let d_kerb = (0.6f32).min(r.sidewalk_width_m * 0.4);
        for (kind, per100) in [
            (0u8, p.trees_per_100m),
            (1, p.poles_per_100m),
            (2, p.signs_per_100m),
        ] {
            let n = poisson_count(rng, per100 * len / 100.0);
            for _ in 0..n {
                let side = if rng.random_bool(0.5) { 1.0f32 } else { -1.0 };
                let si = usize::from(side > 0.0);
                let s = rng.random_range(s0..s1.max(s0 + 1e-3));
                let (clear, d_off) = match kind {
                    0 => (3.0, d_kerb + 0.3),
                    _ => (1.0, d_kerb),
                };
                let slot = &mut self.furniture[(occ * 2 + si) % 4];
                if !slot.free(s - clear, s + clear) {
                    continue;
                }
                slot.take(s - clear, s + clear);
                let d = side * (wc + d_off);
                let (m, h) = match kind {
                    0 => (objects::tree(rng), 0.0),
                    // the light's arm points to local +y: toward the road
                    1 => (
                        objects::street_light(rng),
                        if side > 0.0 {
                            std::f32::consts::PI
                        } else {
                            0.0
                        },
                    ),
                    // signs face the traffic approaching on that side
                    _ => (
                        objects::traffic_sign(rng),
                        if side > 0.0 {
                            0.0
                        } else {
                            std::f32::consts::PI
                        },
                    ),
                };
                self.put(&m, f.place(s, d, kh, h));
            }
        }
    }

    fn vehicle_kind(&self, rng: &mut ChaCha8Rng, parked: bool) -> VehicleKind {
        let p = &self.cfg.population;
        let u = rng.random::<f32>();
        if parked && rng.random::<f32>() < p.trailer_fraction {
            return VehicleKind::Trailer;
        }
        if u < p.van_fraction {
            VehicleKind::Van
        } else if u < p.van_fraction + p.truck_fraction {
            VehicleKind::Truck
        } else if u < p.van_fraction + p.truck_fraction + p.bus_fraction {
            VehicleKind::Bus
        } else {
            VehicleKind::Car
        }
    }

    /// Parked vehicles, moving vehicles, pedestrians and cyclists.
    fn populate(&mut self) {
        let r = self.road;
        let p = self.cfg.population.clone();
        let wl = r.lanes_per_direction as f32 * r.lane_width_m;
        let wc = r.half_carriageway_m();
        let lw = r.lane_width_m;
        let kh = r.kerb_height_m;
        let one_way = !r.parking_lane && self.cfg.layout == Layout::NarrowStreet;
        let sections = self.sections.clone();

        // parked vehicles: in the parking strips, or along the left kerb on the carriageway
        let mut rng = self.rng(10);
        for sec in &sections {
            let sides: &[f32] = if r.parking_lane {
                &[-1.0, 1.0]
            } else if one_way {
                &[1.0]
            } else {
                &[]
            };
            for &side in sides {
                let d = if r.parking_lane {
                    side * (wl + r.parking_width_m / 2.0)
                } else {
                    side * (wc - 1.0)
                };
                let mean_gap = if p.parked_vehicles_per_100m > 0.0 {
                    100.0 / (p.parked_vehicles_per_100m / 2.0)
                } else {
                    f32::INFINITY
                };
                let mut s = sec.s0 + rng.random_range(0.0..6.0f32);
                while s < sec.s1 && mean_gap.is_finite() {
                    let kind = self.vehicle_kind(&mut rng, true);
                    let inst = self.instance();
                    let (m, len) = objects::vehicle(&mut rng, kind, kind.class(), inst);
                    let (a, b) = (s, s + len);
                    let blocked = b > sec.s1 - 1.0
                        || (sec.main && self.no_parking.iter().any(|&(x, y)| b > x && a < y));
                    if !blocked {
                        let h = if side > 0.0 && rng.random_bool(0.5) {
                            std::f32::consts::PI
                        } else {
                            0.0
                        };
                        self.put(&m, sec.frame.place(s + len / 2.0, d, 0.0, h));
                    }
                    // exponential-ish gaps around the mean spacing
                    let gap = (mean_gap - 4.5).max(0.8)
                        * (-rng.random::<f32>().max(1e-6).ln()).min(4.0)
                        + 0.8;
                    s = b + gap;
                }
            }
        }

        // moving vehicles: one speed per lane (no overtaking inside a lane), spacing >= 12 m
        let mut rng = self.rng(11);
        let main = sections
            .iter()
            .filter(|s| s.main)
            .copied()
            .collect::<Vec<_>>();
        let cross = sections
            .iter()
            .filter(|s| !s.main)
            .copied()
            .collect::<Vec<_>>();
        let lanes_fwd = r.lanes_per_direction;
        // frame, d, dir, speed, s-range where vehicles start, is ego lane
        type Lane = (StreetFrame, f32, f32, f32, (f32, f32), bool);
        let mut lanes: Vec<Lane> = Vec::new();
        let all = (-self.half_len() * 0.8, self.half_len() * 0.8);
        // a T junction's main street ends at the cross street: its traffic starts short of it
        let main_range = if self.cfg.layout == Layout::TJunction {
            (all.0, (-(wc + 16.0)).max(all.0))
        } else {
            all
        };
        let ego_lane_d = -(lanes_fwd as f32 - 0.5) * lw;
        for k in 0..lanes_fwd {
            let d = -(k as f32 + 0.5) * lw;
            let ego = (d - ego_lane_d).abs() < 1e-3;
            let speed = if ego {
                self.cfg.ego.speed_mps
            } else {
                rng.random_range(6.0..14.0f32)
            };
            lanes.push((StreetFrame::main(), d, 1.0, speed, main_range, ego));
            if !one_way {
                lanes.push((
                    StreetFrame::main(),
                    -d,
                    -1.0,
                    rng.random_range(6.0..14.0f32),
                    main_range,
                    false,
                ));
            }
        }
        if !cross.is_empty() {
            for k in 0..lanes_fwd {
                let d = (k as f32 + 0.5) * lw;
                lanes.push((
                    StreetFrame::cross(),
                    -d,
                    1.0,
                    rng.random_range(5.0..11.0f32),
                    all,
                    false,
                ));
                lanes.push((
                    StreetFrame::cross(),
                    d,
                    -1.0,
                    rng.random_range(5.0..11.0f32),
                    all,
                    false,
                ));
            }
        }
        let mut taken: Vec<Vec<f32>> = vec![Vec::new(); lanes.len()];
        let mut placed = 0;
        let mut tries = 0;
        while placed < p.moving_vehicles && tries < p.moving_vehicles * 40 + 40 && !lanes.is_empty()
        {
            tries += 1;
            let li = rng.random_range(0..lanes.len());
            let (frame, d, dir, speed, (lo, hi), ego) = lanes[li];
            let s = if hi > lo {
                rng.random_range(lo..hi)
            } else {
                lo
            };
            if ego && (s - self.ego_x).abs() < 18.0 {
                continue;
            }
            if taken[li].iter().any(|&o| (o - s).abs() < 16.0) {
                continue;
            }
            taken[li].push(s);
            let kind = self.vehicle_kind(&mut rng, false);
            let inst = self.instance();
            let (m, _) = objects::vehicle(&mut rng, kind, class::moving(kind.class()), inst);
            let heading = frame.heading(if dir > 0.0 { 0.0 } else { std::f32::consts::PI });
            self.actors.push(Actor {
                mesh: m,
                start: frame.p(s, d, 0.0),
                heading_rad: heading,
                velocity: frame.dir(dir * speed, 0.0),
            });
            placed += 1;
        }

        // pedestrians on the sidewalks (some crossing at the junction)
        let mut rng = self.rng(12);
        let sw = r.sidewalk_width_m;
        for i in 0..p.pedestrians {
            let sec = sections[rng.random_range(0..sections.len())];
            let side = if rng.random_bool(0.5) { 1.0f32 } else { -1.0 };
            let inner = (wc + 1.1).min(wc + sw * 0.5);
            let outer = (wc + sw - 0.35).max(inner + 1e-3);
            let d = side * rng.random_range(inner..outer);
            let s = rng.random_range(sec.s0..sec.s1);
            let standing = rng.random::<f32>() < p.standing_fraction;
            let crossing = !standing && cross.len() + main.len() > 2 && i % 5 == 4;
            let inst = self.instance();
            let cls = if standing {
                class::PERSON
            } else {
                class::moving(class::PERSON)
            };
            let m = objects::person(&mut rng, cls, inst);
            let speed = if standing {
                0.0
            } else {
                rng.random_range(0.8..1.6f32)
            };
            if crossing {
                // on a crosswalk of the main street, walking across it
                // (a T junction has the near crosswalk alone)
                let far = rng.random_bool(0.5) && self.cfg.layout != Layout::TJunction;
                let s_cw = if far { wc + 2.5 } else { -(wc + 2.5) };
                let d0 = rng.random_range(-wl..wl);
                let dir = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
                self.actors.push(Actor {
                    mesh: m,
                    start: Vec3::new(s_cw, d0, 0.0),
                    heading_rad: dir * std::f32::consts::FRAC_PI_2,
                    velocity: Vec3::new(0.0, dir * speed, 0.0),
                });
                continue;
            }
            let dir = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let heading = if standing {
                rng.random_range(-3.1..3.1f32)
            } else if dir > 0.0 {
                0.0
            } else {
                std::f32::consts::PI
            };
            self.actors.push(Actor {
                mesh: m,
                start: sec.frame.p(s, d, kh),
                heading_rad: sec.frame.heading(heading),
                velocity: sec.frame.dir(dir * speed, 0.0),
            });
        }

        // cyclists near the right edge of the carriageway
        let mut rng = self.rng(13);
        for _ in 0..p.cyclists {
            let sec = sections[rng.random_range(0..sections.len())];
            let dir = if one_way || rng.random_bool(0.6) {
                1.0f32
            } else {
                -1.0
            };
            let d = -dir * (wl - 0.7);
            let s = rng.random_range(sec.s0..sec.s1);
            let speed = rng.random_range(3.5..6.5f32);
            let inst = self.instance();
            let m = objects::cyclist(&mut rng, class::moving(class::BICYCLIST), inst);
            self.actors.push(Actor {
                mesh: m,
                start: sec.frame.p(s, d, 0.0),
                heading_rad: sec
                    .frame
                    .heading(if dir > 0.0 { 0.0 } else { std::f32::consts::PI }),
                velocity: sec.frame.dir(dir * speed, 0.0),
            });
        }
    }
}

/// A Poisson-distributed count with mean `lambda` (inversion; fine for the small means used here).
fn poisson_count(rng: &mut ChaCha8Rng, lambda: f32) -> u32 {
    if lambda.is_nan() || lambda <= 0.0 {
        return 0;
    }
    if lambda > 50.0 {
        // normal approximation
        let z: f32 = rand_distr::Distribution::sample(&rand_distr::StandardNormal, rng);
        return (lambda + z * lambda.sqrt()).round().max(0.0) as u32;
    }
    let l = (-f64::from(lambda)).exp();
    let mut k = 0;
    let mut p = 1.0f64;
    loop {
        p *= rng.random::<f64>();
        if p <= l {
            return k;
        }
        k += 1;
    }
}
