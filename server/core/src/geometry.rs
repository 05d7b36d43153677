//! Plan (x–z) geometry: points, oriented rectangles (footprints), exact polygon IoU and the
//! polygon predicates that scene validation needs.
//!
//! Everything here works in the floor plan: a [`PlanPoint`] is `(x, z)` in metres. Rotations
//! follow the world's y-up, right-handed convention (SPEC §1): a yaw `θ` maps the local axis
//! `+x` to `(cos θ, −sin θ)` on the plan.

use serde::{Deserialize, Serialize};

/// A point (or vector) on the floor plan: world `x` and world `z`, in metres.
#[derive(Clone, Copy, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct PlanPoint {
    /// World x, metres.
    pub x: f64,
    /// World z, metres.
    pub z: f64,
}

impl PlanPoint {
    /// A point from its two coordinates.
    pub const fn new(x: f64, z: f64) -> Self {
        Self { x, z }
    }

    /// Euclidean distance to `other`.
    pub fn distance(self, other: PlanPoint) -> f64 {
        (self.x - other.x).hypot(self.z - other.z)
    }

    /// Whether both coordinates are finite.
    pub fn is_finite(self) -> bool {
        self.x.is_finite() && self.z.is_finite()
    }

    fn sub(self, other: PlanPoint) -> PlanPoint {
        PlanPoint::new(self.x - other.x, self.z - other.z)
    }

    fn cross(self, other: PlanPoint) -> f64 {
        self.x * other.z - self.z * other.x
    }
}

/// Rotates a plan vector by yaw `θ` given as its cosine and sine (y-up, right-handed: local
/// `+x` goes to `(cos θ, −sin θ)`, local `+z` to `(sin θ, cos θ)`).
pub fn rotate_plan(v: PlanPoint, cos: f64, sin: f64) -> PlanPoint {
    PlanPoint::new(cos * v.x + sin * v.z, -sin * v.x + cos * v.z)
}

/// An oriented rectangle on the plan: an object's footprint (SPEC §5).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OrientedRect {
    /// Centre of the rectangle.
    pub center: PlanPoint,
    /// Half of the side along the rectangle's local x axis.
    pub half_x: f64,
    /// Half of the side along the rectangle's local z axis.
    pub half_z: f64,
    /// Yaw of the local x axis, radians (same convention as object yaw).
    pub yaw: f64,
}

impl OrientedRect {
    /// Area in square metres.
    pub fn area(&self) -> f64 {
        4.0 * self.half_x * self.half_z
    }

    /// The four corners, counter-clockwise in the `(x, z)` coordinate system (positive
    /// shoelace area).
    pub fn corners(&self) -> [PlanPoint; 4] {
        let (sin, cos) = self.yaw.sin_cos();
        let local = [
            PlanPoint::new(-self.half_x, -self.half_z),
            PlanPoint::new(self.half_x, -self.half_z),
            PlanPoint::new(self.half_x, self.half_z),
            PlanPoint::new(-self.half_x, self.half_z),
        ];
        let mut out = local.map(|p| {
            let r = rotate_plan(p, cos, sin);
            PlanPoint::new(self.center.x + r.x, self.center.z + r.z)
        });
        // A rotation keeps orientation, but mirror the order defensively if the rounding of a
        // degenerate rectangle ever flipped it.
        if signed_area(&out) < 0.0 {
            out.reverse();
        }
        out
    }

    /// Distance from `p` to the closest point of the rectangle (0 inside).
    pub fn distance_to_point(&self, p: PlanPoint) -> f64 {
        let (sin, cos) = self.yaw.sin_cos();
        // Inverse rotation: rotate by −yaw.
        let local = rotate_plan(p.sub(self.center), cos, -sin);
        let dx = (local.x.abs() - self.half_x).max(0.0);
        let dz = (local.z.abs() - self.half_z).max(0.0);
        dx.hypot(dz)
    }
}

/// Signed area of a polygon by the shoelace formula, positive when its vertices run
/// counter-clockwise in the `(x, z)` coordinate system.
///
/// The vertices are taken relative to the first (a fan of triangles from it), so the rounding
/// error scales with the polygon's size, not with its distance from the origin: with absolute
/// coordinates, a 1 × 1.2 m floor at x = z = 10⁵ m measured 1.1999989 m², and at 10⁸ m 2 m².
pub fn signed_area(polygon: &[PlanPoint]) -> f64 {
    let n = polygon.len();
    if n < 3 {
        return 0.0;
    }
    let origin = polygon[0];
    let mut twice = 0.0;
    for i in 1..n - 1 {
        twice += polygon[i].sub(origin).cross(polygon[i + 1].sub(origin));
    }
    0.5 * twice
}

/// Clips the convex polygon `subject` by the convex polygon `clip` (both with positive signed
/// area) with the Sutherland–Hodgman algorithm, returning their intersection.
pub fn clip_convex(subject: &[PlanPoint], clip: &[PlanPoint]) -> Vec<PlanPoint> {
    let mut output: Vec<PlanPoint> = subject.to_vec();
    let mut input = Vec::with_capacity(subject.len() + clip.len());
    for i in 0..clip.len() {
        if output.is_empty() {
            break;
        }
        std::mem::swap(&mut input, &mut output);
        output.clear();
        let a = clip[i];
        let b = clip[(i + 1) % clip.len()];
        let edge = b.sub(a);
        let inside = |p: PlanPoint| edge.cross(p.sub(a)) >= 0.0;
        for j in 0..input.len() {
            let current = input[j];
            let previous = input[(j + input.len() - 1) % input.len()];
            let current_in = inside(current);
            let previous_in = inside(previous);
            if current_in {
                if !previous_in {
                    output.push(segment_line_intersection(previous, current, a, b));
                }
                output.push(current);
            } else if previous_in {
                output.push(segment_line_intersection(previous, current, a, b));
            }
        }
    }
    output
}

fn segment_line_intersection(p: PlanPoint, q: PlanPoint, a: PlanPoint, b: PlanPoint) -> PlanPoint {
    let edge = b.sub(a);
    let dp = edge.cross(p.sub(a));
    let dq = edge.cross(q.sub(a));
    let denominator = dp - dq;
    if denominator == 0.0 {
        return q;
    }
    let t = dp / denominator;
    PlanPoint::new(p.x + t * (q.x - p.x), p.z + t * (q.z - p.z))
}

/// Exact intersection-over-union of two oriented rectangles (SPEC §5), in `[0, 1]`.
///
/// Degenerate rectangles (zero area) have IoU 0 with everything.
pub fn footprint_iou(a: &OrientedRect, b: &OrientedRect) -> f64 {
    let area_a = a.area();
    let area_b = b.area();
    if area_a <= 0.0 || area_b <= 0.0 {
        return 0.0;
    }
    // Cheap rejection: the circumscribed circles do not meet.
    let reach = a.half_x.hypot(a.half_z) + b.half_x.hypot(b.half_z);
    if a.center.distance(b.center) >= reach {
        return 0.0;
    }
    let intersection = signed_area(&clip_convex(&a.corners(), &b.corners())).max(0.0);
    let union = area_a + area_b - intersection;
    (intersection / union).clamp(0.0, 1.0)
}

/// Whether `p` lies inside the simple polygon `polygon` (even–odd rule). Points on the boundary
/// may go either way.
pub fn point_in_polygon(p: PlanPoint, polygon: &[PlanPoint]) -> bool {
    let n = polygon.len();
    let mut inside = false;
    let mut j = n.wrapping_sub(1);
    for i in 0..n {
        let a = polygon[i];
        let b = polygon[j];
        if (a.z > p.z) != (b.z > p.z) {
            let x_cross = (b.x - a.x) * (p.z - a.z) / (b.z - a.z) + a.x;
            if p.x < x_cross {
                inside = !inside;
            }
        }
        j = i;
    }
    inside
}

/// Whether the closed segments `p1–p2` and `q1–q2` cross properly (each one's endpoints strictly
/// on both sides of the other's line).
pub fn segments_cross(p1: PlanPoint, p2: PlanPoint, q1: PlanPoint, q2: PlanPoint) -> bool {
    let d1 = q2.sub(q1).cross(p1.sub(q1));
    let d2 = q2.sub(q1).cross(p2.sub(q1));
    let d3 = p2.sub(p1).cross(q1.sub(p1));
    let d4 = p2.sub(p1).cross(q2.sub(p1));
    (d1 > 0.0) != (d2 > 0.0) && d1 != 0.0 && d2 != 0.0 && (d3 > 0.0) != (d4 > 0.0) && d3 != 0.0 && d4 != 0.0
}

/// Whether the convex polygon `inner` lies inside the simple polygon `outer`: every vertex of
/// `inner` is inside `outer`, no edges cross, and no vertex of `outer` lies strictly inside
/// `inner` (which catches the reflex corner of an L-shaped room poking into a footprint).
pub fn convex_inside_polygon(inner: &[PlanPoint], outer: &[PlanPoint]) -> bool {
    if !inner.iter().all(|&p| point_in_polygon(p, outer)) {
        return false;
    }
    let n = inner.len();
    let m = outer.len();
    for i in 0..n {
        for j in 0..m {
            if segments_cross(inner[i], inner[(i + 1) % n], outer[j], outer[(j + 1) % m]) {
                return false;
            }
        }
    }
    !outer.iter().any(|&v| strictly_inside_convex(v, inner))
}

fn strictly_inside_convex(p: PlanPoint, convex: &[PlanPoint]) -> bool {
    let n = convex.len();
    let orientation = signed_area(convex).signum();
    (0..n).all(|i| {
        let a = convex[i];
        let b = convex[(i + 1) % n];
        orientation * b.sub(a).cross(p.sub(a)) > 1e-12
    })
}

/// Whether the polygon is simple: no two non-adjacent edges cross or touch.
pub fn polygon_is_simple(polygon: &[PlanPoint]) -> bool {
    let n = polygon.len();
    if n < 3 {
        return false;
    }
    for i in 0..n {
        let a1 = polygon[i];
        let a2 = polygon[(i + 1) % n];
        if a1 == a2 {
            return false;
        }
        for j in (i + 1)..n {
            let adjacent = j == i + 1 || (i == 0 && j == n - 1);
            if adjacent {
                continue;
            }
            let b1 = polygon[j];
            let b2 = polygon[(j + 1) % n];
            if segments_cross(a1, a2, b1, b2) || segments_touch(a1, a2, b1, b2) {
                return false;
            }
        }
    }
    true
}

fn segments_touch(p1: PlanPoint, p2: PlanPoint, q1: PlanPoint, q2: PlanPoint) -> bool {
    let on = |a: PlanPoint, b: PlanPoint, p: PlanPoint| {
        b.sub(a).cross(p.sub(a)) == 0.0
            && p.x >= a.x.min(b.x)
            && p.x <= a.x.max(b.x)
            && p.z >= a.z.min(b.z)
            && p.z <= a.z.max(b.z)
    };
    on(p1, p2, q1) || on(p1, p2, q2) || on(q1, q2, p1) || on(q1, q2, p2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_4;

    fn rect(x: f64, z: f64, half_x: f64, half_z: f64, yaw: f64) -> OrientedRect {
        OrientedRect { center: PlanPoint::new(x, z), half_x, half_z, yaw }
    }

    fn check_iou(a: OrientedRect, b: OrientedRect, expected: f64) {
        let got = footprint_iou(&a, &b);
        assert!((got - expected).abs() < 1e-12, "IoU of {a:?} and {b:?}: got {got}, expected {expected}");
        let swapped = footprint_iou(&b, &a);
        assert!((swapped - expected).abs() < 1e-12, "IoU not symmetric: {got} vs {swapped}");
    }

    #[test]
    fn iou_hand_computed_cases() {
        // Identical.
        check_iou(rect(1.0, 2.0, 0.5, 0.3, 0.7), rect(1.0, 2.0, 0.5, 0.3, 0.7), 1.0);
        // Disjoint.
        check_iou(rect(0.0, 0.0, 0.5, 0.5, 0.0), rect(3.0, 0.0, 0.5, 0.5, 0.0), 0.0);
        // Touching edges only: zero intersection.
        check_iou(rect(0.0, 0.0, 0.5, 0.5, 0.0), rect(1.0, 0.0, 0.5, 0.5, 0.0), 0.0);
        // Unit squares shifted by half a side: intersection 0.5, union 1.5.
        check_iou(rect(0.0, 0.0, 0.5, 0.5, 0.0), rect(0.5, 0.0, 0.5, 0.5, 0.0), 1.0 / 3.0);
        // Shifted diagonally by half a side: intersection 0.25, union 1.75.
        check_iou(rect(0.0, 0.0, 0.5, 0.5, 0.0), rect(0.5, 0.5, 0.5, 0.5, 0.0), 0.25 / 1.75);
        // A unit square and the same square turned 45° about the same centre: the intersection
        // is a regular octagon of area 2(√2 − 1), the union 2 − 2(√2 − 1).
        let octagon = 2.0 * (2f64.sqrt() - 1.0);
        check_iou(rect(0.0, 0.0, 0.5, 0.5, 0.0), rect(0.0, 0.0, 0.5, 0.5, FRAC_PI_4), octagon / (2.0 - octagon));
        // Contained: a 1×1 square inside a 2×2 square, rotated: IoU = 1/4.
        check_iou(rect(0.0, 0.0, 1.0, 1.0, 0.3), rect(0.0, 0.0, 0.5, 0.5, 1.1), 0.25);
        // A 2×1 rectangle and the same turned 90°: cross of area 1, union 3.
        check_iou(rect(0.0, 0.0, 1.0, 0.5, 0.0), rect(0.0, 0.0, 1.0, 0.5, std::f64::consts::FRAC_PI_2), 1.0 / 3.0);
        // Degenerate.
        check_iou(rect(0.0, 0.0, 0.0, 0.5, 0.0), rect(0.0, 0.0, 0.5, 0.5, 0.0), 0.0);
    }

    #[test]
    fn corners_follow_the_yaw_convention() {
        // A yaw of 90° maps local +x to world −z.
        let r = rect(0.0, 0.0, 1.0, 0.0, std::f64::consts::FRAC_PI_2);
        let corners = r.corners();
        assert!(corners.iter().any(|c| (c.x).abs() < 1e-12 && (c.z + 1.0).abs() < 1e-12));
    }

    #[test]
    fn point_distance_to_rectangle() {
        let r = rect(1.0, 1.0, 0.5, 0.25, 0.0);
        assert_eq!(r.distance_to_point(PlanPoint::new(1.2, 1.1)), 0.0);
        assert!((r.distance_to_point(PlanPoint::new(2.5, 1.0)) - 1.0).abs() < 1e-12);
        assert!((r.distance_to_point(PlanPoint::new(2.5, 2.25)) - 2f64.sqrt()).abs() < 1e-12);
        let turned = rect(0.0, 0.0, 0.5, 0.25, std::f64::consts::FRAC_PI_2);
        // Turned 90°: the long side now runs along z.
        assert!((turned.distance_to_point(PlanPoint::new(0.0, 1.5)) - 1.0).abs() < 1e-12);
        assert!((turned.distance_to_point(PlanPoint::new(1.25, 0.0)) - 1.0).abs() < 1e-12);
    }

    /// Regression: the area was summed from absolute coordinates, so far from the origin it
    /// lost every digit that mattered (the floor check accepted or refused the wrong rooms).
    #[test]
    fn signed_area_is_exact_far_from_the_origin() {
        for offset in [0.0, 1e3, 1e5, 1e7, 1e8, -1e8] {
            let at = |x: f64, z: f64| PlanPoint::new(offset + x, offset + z);
            let rectangle = [at(0.0, 0.0), at(1.0, 0.0), at(1.0, 1.2), at(0.0, 1.2)];
            let area = signed_area(&rectangle);
            assert!((area - 1.2).abs() < 1e-6, "a 1 × 1.2 rectangle at {offset}: {area}");
            let reversed: Vec<PlanPoint> = rectangle.iter().rev().copied().collect();
            assert!((signed_area(&reversed) + 1.2).abs() < 1e-6, "clockwise at {offset}");
            // A non-convex L of area 12.
            let l_shape = [at(0.0, 0.0), at(4.0, 0.0), at(4.0, 2.0), at(2.0, 2.0), at(2.0, 4.0), at(0.0, 4.0)];
            assert!((signed_area(&l_shape) - 12.0).abs() < 1e-6, "L at {offset}");
        }
    }

    #[test]
    fn polygon_predicates() {
        let l_shape = [
            PlanPoint::new(0.0, 0.0),
            PlanPoint::new(4.0, 0.0),
            PlanPoint::new(4.0, 2.0),
            PlanPoint::new(2.0, 2.0),
            PlanPoint::new(2.0, 4.0),
            PlanPoint::new(0.0, 4.0),
        ];
        assert!(polygon_is_simple(&l_shape));
        assert!(point_in_polygon(PlanPoint::new(1.0, 3.0), &l_shape));
        assert!(!point_in_polygon(PlanPoint::new(3.0, 3.0), &l_shape));
        let inside = rect(1.0, 1.0, 0.5, 0.5, 0.0).corners();
        assert!(convex_inside_polygon(&inside, &l_shape));
        // Corners all inside, but the reflex corner (2, 2) pokes into the rectangle.
        let around_reflex =
            [PlanPoint::new(1.5, 1.5), PlanPoint::new(2.4, 1.5), PlanPoint::new(2.4, 1.9), PlanPoint::new(1.5, 2.4)];
        assert!(!convex_inside_polygon(&around_reflex, &l_shape));
        let bow_tie =
            [PlanPoint::new(0.0, 0.0), PlanPoint::new(1.0, 1.0), PlanPoint::new(1.0, 0.0), PlanPoint::new(0.0, 1.0)];
        assert!(!polygon_is_simple(&bow_tie));
    }
}
