//! Admissible lower bounds on the steps a search still needs, and the placement geometry they
//! rest on.
//!
//! Every bound here is *consistent*: along any edge of the action lattice it drops by at most
//! the edge's cost of one step, and it is zero only where a goal may be. The tests check both on
//! states sampled by real [`Episode::step`]s, so a weighted A* over these bounds finds plans
//! within its weight of the shortest.
//!
//! # The carry bound
//!
//! While an object is carried its footprint centre `c` is rigidly attached to the agent at a
//! fixed distance `r`. One step moves `c` by at most `max(0.25 m, 2 r sin(11.25°))` (a move, or
//! the chord of a turn's arc), and its yaw changes by one turn of 22.5° per turn. A release
//! places the object only if the footprint IoU with the target exceeds the threshold; for each
//! of the 16 yaws the object can take, [`PlacementGeometry`] knows whether that yaw can place it
//! at all and how far from the target centre its centre may then be. The bound is the fewest
//! steps over the placing yaws of `max(turns to that yaw, moves to that radius)`, plus the
//! release.

use esrp_core::world::MOVE_DISTANCE;
use esrp_core::{Episode, HEADING_COUNT, OrientedRect, PlanPoint, TURN_ANGLE, footprint_iou};

/// Directions sampled on half the circle when measuring a placement radius, beyond the
/// rectangles' own axes.
const RADIUS_DIRECTIONS: usize = 64;

/// Relative slack on a measured placement radius: the radius is sampled in a finite set of
/// directions, so it is grown a little to stay an upper bound.
const RADIUS_SLACK: f64 = 0.03;

/// Absolute slack on a measured placement radius, metres.
const RADIUS_SLACK_ABS: f64 = 0.005;

/// The turns between two yaw offsets of the 16 on the circle (0 to 8).
pub(crate) fn turn_distance(a: u8, b: u8) -> u32 {
    let d = u32::from(a.abs_diff(b)) % u32::from(HEADING_COUNT);
    d.min(u32::from(HEADING_COUNT) - d)
}

/// The turn offset (0–15) of an object whose yaw started at `yaw0` and is `yaw` now: carried
/// objects turn only in whole turns of 22.5°.
pub(crate) fn yaw_offset(yaw0: f64, yaw: f64) -> u8 {
    let turns = ((yaw - yaw0) / TURN_ANGLE).round();
    (turns as i64).rem_euclid(i64::from(HEADING_COUNT)) as u8
}

/// `ceil(x)` for a step count, forgiving the last bits of rounding and never below zero.
fn whole_steps(x: f64) -> u32 {
    if x <= 1e-9 { 0 } else { (x - 1e-9).ceil().min(f64::from(u32::MAX / 4)) as u32 }
}

/// How an object can be placed: for each of the 16 yaws it can take from its current yaw
/// (`yaw0 + k · 22.5°`), whether a release at that yaw can exceed the IoU threshold, and the
/// largest distance between its footprint centre and the target's at which it still can.
#[derive(Clone, Debug)]
pub(crate) struct PlacementGeometry {
    /// The object's yaw when the search began.
    pub yaw0: f64,
    /// The target footprint.
    pub target: OrientedRect,
    /// `radius[k]`: an upper bound on the centre distance of a placing release at yaw offset
    /// `k`, or `None` when no release at that yaw can place the object.
    pub radius: [Option<f64>; HEADING_COUNT as usize],
    /// The object's footprint's circumradius (half its diagonal).
    pub circumradius: f64,
}

impl PlacementGeometry {
    /// The placement geometry of object `object` of `episode`'s scene, from its current yaw.
    pub fn new(episode: &Episode, object: usize) -> Self {
        let scene = episode.compiled();
        let pose = episode.object_poses()[object];
        let threshold = scene.rules().placement_iou;
        let target = scene.movable_footprint(object, &scene.scene().movable_objects[object].target);
        let circumradius = target.half_x.hypot(target.half_z);
        // A rectangle turned by half a turn is the same rectangle: yaw offsets k and k + 8 agree.
        let half = usize::from(HEADING_COUNT / 2);
        let mut radius = [None; HEADING_COUNT as usize];
        for k in 0..half {
            let yaw = pose.yaw + k as f64 * TURN_ANGLE;
            radius[k] = placement_radius(&target, yaw, threshold, circumradius);
            radius[k + half] = radius[k];
        }
        Self { yaw0: pose.yaw, target, radius, circumradius }
    }

    /// Whether any yaw the object can take places it.
    pub fn placeable(&self) -> bool {
        self.radius.iter().any(Option::is_some)
    }

    /// The fewest steps (turns and moves, not the release) to bring a footprint centre at
    /// `center`, at yaw offset `offset`, into a placing pose when one step moves the centre at
    /// most `step`; `None` when no yaw places it.
    pub fn carry_steps(&self, center: PlanPoint, offset: u8, step: f64) -> Option<u32> {
        let distance = center.distance(self.target.center);
        (0..HEADING_COUNT)
            .filter_map(|k| {
                let radius = self.radius[usize::from(k)]?;
                let moves = whole_steps((distance - radius) / step);
                Some(moves.max(turn_distance(offset, k)))
            })
            .min()
    }
}

/// The largest distance from `target`'s centre at which a rectangle of `target`'s size turned
/// to `yaw` still overlaps it with IoU above `threshold` (grown by the slack), or `None` if it
/// does not even when centred.
///
/// The intersection area of two centrally symmetric convex shapes is largest when their centres
/// coincide and, by Brunn–Minkowski, never grows along a ray leaving that point, so a bisection
/// along each sampled direction finds the boundary.
fn placement_radius(target: &OrientedRect, yaw: f64, threshold: f64, circumradius: f64) -> Option<f64> {
    let at = |offset: PlanPoint| {
        let moved = OrientedRect {
            center: PlanPoint::new(target.center.x + offset.x, target.center.z + offset.z),
            yaw,
            ..*target
        };
        footprint_iou(&moved, target)
    };
    if at(PlanPoint::new(0.0, 0.0)) <= threshold {
        return None;
    }
    // The region is centrally symmetric (both rectangles are), so half the circle covers it:
    // the rectangles' own axes and evenly spaced directions.
    let axes = [target.yaw, yaw].into_iter().flat_map(|a| [a, a + std::f64::consts::FRAC_PI_2]);
    let sampled = (0..RADIUS_DIRECTIONS).map(|i| i as f64 * std::f64::consts::PI / RADIUS_DIRECTIONS as f64);
    let mut largest: f64 = 0.0;
    for angle in axes.chain(sampled) {
        let (sin, cos) = angle.sin_cos();
        let (mut inside, mut outside) = (0.0, 2.0 * circumradius + 1e-6);
        for _ in 0..20 {
            let mid = 0.5 * (inside + outside);
            if at(PlanPoint::new(mid * cos, mid * sin)) > threshold {
                inside = mid;
            } else {
                outside = mid;
            }
        }
        largest = largest.max(outside);
    }
    Some(largest * (1.0 + RADIUS_SLACK) + RADIUS_SLACK_ABS)
}

/// The most a carried footprint centre at distance `r` from the agent's centre moves in one
/// step: a move, or the chord of a turn.
pub(crate) fn carry_step_length(r: f64) -> f64 {
    MOVE_DISTANCE.max(2.0 * r * (0.5 * TURN_ANGLE).sin()) * (1.0 + 1e-9)
}

/// Moves still needed before an agent at footprint distance `distance` from an object can fetch
/// it (reach `reach`).
pub(crate) fn approach_steps(distance: f64, reach: f64) -> u32 {
    whole_steps((distance - reach) / MOVE_DISTANCE)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rect(x: f64, z: f64, half_x: f64, half_z: f64, yaw: f64) -> OrientedRect {
        OrientedRect { center: PlanPoint::new(x, z), half_x, half_z, yaw }
    }

    #[test]
    fn turn_distance_wraps_around_the_circle() {
        for (a, b, expected) in [(0, 0, 0), (0, 1, 1), (0, 15, 1), (3, 11, 8), (2, 14, 4), (15, 0, 1)] {
            assert_eq!(turn_distance(a, b), expected, "{a} -> {b}");
        }
    }

    #[test]
    fn yaw_offset_counts_whole_turns() {
        assert_eq!(yaw_offset(0.3, 0.3), 0);
        assert_eq!(yaw_offset(0.3, 0.3 + 3.0 * TURN_ANGLE), 3);
        assert_eq!(yaw_offset(0.3, 0.3 - TURN_ANGLE), 15);
        assert_eq!(yaw_offset(0.3, 0.3 + 17.0 * TURN_ANGLE), 1);
    }

    /// Monte Carlo: no offset with IoU above the threshold lies beyond the measured radius.
    #[test]
    fn placement_radius_bounds_every_placing_offset() {
        let shapes = [rect(1.0, 2.0, 0.25, 0.25, 0.0), rect(-1.0, 0.5, 0.6, 0.2, 0.4), rect(0.0, 0.0, 0.05, 0.5, 1.1)];
        let mut seed: u64 = 0x9e37_79b9_7f4a_7c15;
        let mut uniform = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for target in shapes {
            let circumradius = target.half_x.hypot(target.half_z);
            for k in 0..16 {
                let yaw = target.yaw + f64::from(k) * TURN_ANGLE + 0.05;
                let Some(radius) = placement_radius(&target, yaw, 0.3, circumradius) else {
                    let centred = OrientedRect { yaw, ..target };
                    assert!(footprint_iou(&centred, &target) <= 0.3);
                    continue;
                };
                for _ in 0..2000 {
                    let (dx, dz) = ((uniform() - 0.5) * 4.0 * circumradius, (uniform() - 0.5) * 4.0 * circumradius);
                    let moved = OrientedRect {
                        center: PlanPoint::new(target.center.x + dx, target.center.z + dz),
                        yaw,
                        ..target
                    };
                    if footprint_iou(&moved, &target) > 0.3 {
                        assert!(dx.hypot(dz) <= radius, "offset ({dx}, {dz}) places beyond radius {radius}");
                    }
                }
            }
        }
    }

    #[test]
    fn a_thin_object_turned_across_its_target_cannot_be_placed() {
        let target = rect(0.0, 0.0, 0.05, 0.6, 0.0);
        assert!(placement_radius(&target, std::f64::consts::FRAC_PI_2, 0.3, 0.61).is_none());
        assert!(placement_radius(&target, 0.0, 0.3, 0.61).is_some());
        assert!(placement_radius(&target, std::f64::consts::PI, 0.3, 0.61).is_some());
    }
}
