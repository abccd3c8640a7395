//! The horizontal alignment of a curved main street: a tangent, a circular arc, a tangent.
//!
//! A scene is generated in road coordinates: `s` along the main street's centreline (metres of arc
//! length), `d` across it (left positive), z up. On a straight street they are the world's x and y.
//! When the street bends ([`super::RoadConfig::curve_probability`]), [`RoadCurve`] maps them to the
//! world: the centreline runs along +x up to `s = arc_start_m`, turns along a circular arc of
//! radius `radius_m` through `turn_rad` (left for a positive curvature, right for a negative one)
//! and runs straight again along the arc's end tangent. A road point `(s, d)` lies at
//! `centre(s) + d n(s)` with `n` the centreline's left normal; headings are measured from world +x
//! toward +y. There is no transition spiral: the curvature steps from 0 to `1 / radius` at the arc's
//! ends (the centreline's position and heading are continuous).
//!
//! The map is one-to-one for `d` below the radius on the inside of the bend (the turn is at most
//! 180 degrees); the simulator keeps the inner roadside within that (see [`RoadCurve::inner_limit_m`]).

use glam::{Affine3A, DVec2, Mat3, Vec2, Vec3};

/// A tangent - circular arc - tangent centreline (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoadCurve {
    /// Arc length along the centreline where the arc begins, metres.
    arc_start_m: f32,
    /// Signed curvature of the arc, 1/m (positive: turning left).
    curvature: f32,
    /// Length of the arc along the centreline, metres.
    arc_length_m: f32,
}

impl RoadCurve {
    /// A centreline that runs along +x up to `arc_start_m`, then turns through `turn_rad` radians
    /// (`0 < turn_rad <= pi`) on a circle of `radius_m`, to the left when `left`.
    ///
    /// # Panics
    /// When the radius is not positive and finite or the turn is not within `(0, pi]`.
    pub fn new(arc_start_m: f32, radius_m: f32, turn_rad: f32, left: bool) -> RoadCurve {
        assert!(
            radius_m.is_finite() && radius_m > 0.0,
            "curve radius {radius_m} must be positive"
        );
        assert!(
            turn_rad > 0.0 && turn_rad <= std::f32::consts::PI + 1e-6,
            "curve turn {turn_rad} not in (0, pi]"
        );
        let k = 1.0 / radius_m;
        RoadCurve {
            arc_start_m,
            curvature: if left { k } else { -k },
            arc_length_m: radius_m * turn_rad,
        }
    }

    /// Arc length along the centreline where the arc begins, metres.
    pub fn arc_start_m(&self) -> f32 {
        self.arc_start_m
    }

    /// Arc length along the centreline where the arc ends, metres.
    pub fn arc_end_m(&self) -> f32 {
        self.arc_start_m + self.arc_length_m
    }

    /// Length of the arc, metres.
    pub fn arc_length_m(&self) -> f32 {
        self.arc_length_m
    }

    /// Signed curvature of the arc, 1/m (positive: a left turn).
    pub fn curvature(&self) -> f32 {
        self.curvature
    }

    /// Radius of the arc, metres.
    pub fn radius_m(&self) -> f32 {
        1.0 / self.curvature.abs()
    }

    /// True for a left turn.
    pub fn is_left(&self) -> bool {
        self.curvature > 0.0
    }

    /// The angle the street turns through, radians (always positive).
    pub fn turn_rad(&self) -> f32 {
        self.arc_length_m * self.curvature.abs()
    }

    /// Centre of the arc's circle, world frame.
    pub fn centre(&self) -> Vec2 {
        Vec2::new(self.arc_start_m, 1.0 / self.curvature)
    }

    /// The curvature at `s` (0 on the tangents).
    pub fn curvature_at(&self, s: f32) -> f32 {
        if s > self.arc_start_m && s < self.arc_end_m() {
            self.curvature
        } else {
            0.0
        }
    }

    /// How far the road may reach across the centreline on the inside of the bend, metres (the
    /// radius: there the map folds over). Returns `(side, limit)`: `side` is +1 when the inside
    /// is to the left (`d > 0`), -1 when to the right.
    pub fn inner_limit_m(&self) -> (f32, f32) {
        (self.curvature.signum(), self.radius_m())
    }

    /// Centreline position and heading (radians from +x toward +y) at `s`, in f64.
    fn centreline64(&self, s: f32) -> (DVec2, f64) {
        let s = f64::from(s);
        let a = f64::from(self.arc_start_m);
        let k = f64::from(self.curvature);
        let len = f64::from(self.arc_length_m);
        if s <= a {
            return (DVec2::new(s, 0.0), 0.0);
        }
        let u = (s - a).min(len);
        let th = k * u;
        // (1 - cos th) / k written as 2 sin^2(th / 2) / k: exact for gentle curves too
        let half = (0.5 * th).sin();
        let p = DVec2::new(a + th.sin() / k, 2.0 * half * half / k);
        let rest = s - a - u;
        (p + rest * DVec2::new(th.cos(), th.sin()), th)
    }

    /// Centreline position and heading (radians from +x toward +y) at `s`.
    pub fn centreline(&self, s: f32) -> (Vec2, f32) {
        let (p, th) = self.centreline64(s);
        (p.as_vec2(), th as f32)
    }

    /// World position (x, y) of the road point `(s, d)`.
    pub fn to_world(&self, s: f32, d: f32) -> Vec2 {
        let (p, th) = self.centreline64(s);
        let n = DVec2::new(-th.sin(), th.cos());
        (p + f64::from(d) * n).as_vec2()
    }

    /// The rigid motion that takes the road frame at `(s, d)` (x along the street, y across, as on
    /// a straight street) to the world: a point `(s + u, d + v, z)` near it goes to
    /// `to_world(s, d) + R(heading) (u, v)` at height `z`.
    pub fn world_from_road_at(&self, s: f32, d: f32) -> Affine3A {
        let (_, th) = self.centreline64(s);
        let p = self.to_world(s, d);
        Affine3A::from_translation(Vec3::new(p.x, p.y, 0.0))
            * Affine3A::from_mat3(Mat3::from_rotation_z(th as f32))
            * Affine3A::from_translation(Vec3::new(-s, -d, 0.0))
    }

    /// Road coordinates `(s, d)` of the world point `p` (x, y): its nearest point on the
    /// centreline (the tangents extended without end).
    pub fn to_road(&self, p: Vec2) -> (f32, f32) {
        let p = p.as_dvec2();
        let a = f64::from(self.arc_start_m);
        let k = f64::from(self.curvature);
        let len = f64::from(self.arc_length_m);
        let mut best: Option<(f64, f64)> = None;
        let mut consider = |s: f64, d: f64| {
            if best.is_none_or(|(_, bd)| d.abs() < bd.abs()) {
                best = Some((s, d));
            }
        };
        // the entry tangent
        if p.x <= a {
            consider(p.x, p.y);
        }
        // the arc: p - c = (1 / k - d) (sin th, -cos th)
        let c = DVec2::new(a, 1.0 / k);
        let q = (p - c) * k;
        let th = q.x.atan2(-q.y);
        let u = th / k;
        if (0.0..=len).contains(&u) {
            consider(a + u, (1.0 - q.length()) / k);
        }
        // the exit tangent
        let (e, the) = self.centreline64(self.arc_end_m());
        let t = DVec2::new(the.cos(), the.sin());
        let n = DVec2::new(-the.sin(), the.cos());
        let along = (p - e).dot(t);
        if along >= 0.0 {
            consider(a + len + along, (p - e).dot(n));
        }
        let (s, d) = best.unwrap_or_else(|| {
            // behind both tangents and outside the arc's sector: the nearer arc end
            if (p - DVec2::new(a, 0.0)).length() <= (p - e).length() {
                (p.x.min(a), p.y)
            } else {
                (a + len + along, (p - e).dot(n))
            }
        });
        (s as f32, d as f32)
    }

    /// The arc length `s` reached from `s0` by travelling `dist` metres (negative: backwards) along
    /// the line at the constant offset `d` from the centreline (on the arc a line at offset `d` is
    /// `1 - curvature d` times as long as the centreline beside it).
    pub fn advance(&self, s0: f32, d: f32, dist: f32) -> f32 {
        let a = f64::from(self.arc_start_m);
        let len = f64::from(self.arc_length_m);
        let f = (1.0 - f64::from(self.curvature) * f64::from(d)).max(1e-3);
        // path length from the arc start along the offset line, and back
        let path = |s: f64| {
            if s <= a {
                s - a
            } else if s <= a + len {
                (s - a) * f
            } else {
                len * f + (s - a - len)
            }
        };
        let inverse = |l: f64| {
            if l <= 0.0 {
                a + l
            } else if l <= len * f {
                a + l / f
            } else {
                a + len + (l - len * f)
            }
        };
        inverse(path(f64::from(s0)) + f64::from(dist)) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn curves() -> Vec<RoadCurve> {
        vec![
            RoadCurve::new(-10.0, 40.0, 1.5, true),
            RoadCurve::new(5.0, 40.0, 2.0, false),
            RoadCurve::new(-30.0, 600.0, 0.3, true),
            RoadCurve::new(0.0, 120.0, std::f32::consts::PI, false),
        ]
    }

    #[test]
    fn arc_points_lie_on_the_circle_with_tangent_heading() {
        for c in curves() {
            let r = c.radius_m();
            let centre = c.centre();
            for i in 0..=50 {
                let s = c.arc_start_m() + c.arc_length_m() * i as f32 / 50.0;
                let (p, h) = c.centreline(s);
                // at radius r from the centre, after turning through (s - a) / r
                let rel = (p - centre).as_dvec2();
                assert!(
                    (rel.length() - f64::from(r)).abs() < 1e-3 * (f64::from(r) / 100.0).max(1.0),
                    "{c:?} s {s}: |p - c| = {} for r {r}",
                    rel.length()
                );
                let turned = (s - c.arc_start_m()) / r;
                assert!((h.abs() - turned).abs() < 1e-5, "{c:?} s {s}: heading {h}");
                if i > 0 {
                    assert_eq!(
                        h.signum(),
                        c.curvature().signum(),
                        "{c:?} s {s}: turns the wrong way"
                    );
                }
                // the heading is tangent: perpendicular to the radius
                let tangent = DVec2::new(f64::from(h).cos(), f64::from(h).sin());
                assert!(tangent.dot(rel).abs() < 1e-3 * f64::from(r), "{c:?} s {s}");
                // and the closed form of the circle
                let th = f64::from(turned) * f64::from(c.curvature().signum());
                let k = f64::from(c.curvature());
                let want = DVec2::new(
                    f64::from(c.arc_start_m()) + th.sin() / k,
                    (1.0 - th.cos()) / k,
                );
                assert!(
                    (p.as_dvec2() - want).length() < 1e-3,
                    "{c:?} s {s}: {p} vs {want}"
                );
            }
        }
    }

    #[test]
    fn tangents_continue_straight_and_offsets_are_normal() {
        for c in curves() {
            let (p0, h0) = c.centreline(c.arc_start_m() - 7.0);
            assert_eq!((p0, h0), (Vec2::new(c.arc_start_m() - 7.0, 0.0), 0.0));
            let (e, he) = c.centreline(c.arc_end_m());
            let (p, h) = c.centreline(c.arc_end_m() + 25.0);
            assert!((h - he).abs() < 1e-6);
            assert!((p - e - 25.0 * Vec2::new(he.cos(), he.sin())).length() < 1e-3);
            assert!((he.abs() - c.turn_rad()).abs() < 1e-5);
            // the offset line lies along the normal, d to the left
            for s in [
                c.arc_start_m() - 3.0,
                c.arc_start_m() + 0.4 * c.arc_length_m(),
                c.arc_end_m() + 3.0,
            ] {
                let (p, h) = c.centreline(s);
                let w = c.to_world(s, 4.0);
                assert!((w - p - 4.0 * Vec2::new(-h.sin(), h.cos())).length() < 1e-3);
                // the rigid frame agrees with the point map at its anchor and turns with the road
                let xf = c.world_from_road_at(s, 4.0);
                let a = xf.transform_point3(Vec3::new(s, 4.0, 1.0));
                assert!((a - Vec3::new(w.x, w.y, 1.0)).length() < 1e-3);
                let fwd = xf.transform_vector3(Vec3::X);
                assert!((fwd - Vec3::new(h.cos(), h.sin(), 0.0)).length() < 1e-5);
            }
        }
    }

    #[test]
    fn to_road_inverts_to_world_and_advance_measures_the_offset_line() {
        for c in curves() {
            let r = c.radius_m();
            for i in 0..40 {
                let s = c.arc_start_m() - 30.0 + (c.arc_length_m() + 60.0) * i as f32 / 39.0;
                for d in [-0.4 * r.min(30.0), -3.0, 0.0, 2.5, 0.4 * r.min(30.0)] {
                    let w = c.to_world(s, d);
                    let (s2, d2) = c.to_road(w);
                    assert!(
                        (s2 - s).abs() < 2e-3 * r.max(50.0) / 50.0 && (d2 - d).abs() < 2e-3,
                        "{c:?}: ({s}, {d}) -> {w} -> ({s2}, {d2})"
                    );
                }
            }
            // travelling along an offset line: the chord sum matches the distance asked for
            let d = -5.25;
            let s0 = c.arc_start_m() - 10.0;
            let dist = c.arc_length_m() * 0.7 + 20.0;
            let s1 = c.advance(s0, d, dist);
            let n = 4000;
            let mut walked = 0.0f64;
            for i in 0..n {
                let sa = s0 + (s1 - s0) * i as f32 / n as f32;
                let sb = s0 + (s1 - s0) * (i + 1) as f32 / n as f32;
                walked += f64::from((c.to_world(sb, d) - c.to_world(sa, d)).length());
            }
            assert!(
                (walked - f64::from(dist)).abs() < 0.02,
                "{c:?}: walked {walked} of {dist}"
            );
            assert!((c.advance(s1, d, -dist) - s0).abs() < 1e-3);
        }
    }
}
