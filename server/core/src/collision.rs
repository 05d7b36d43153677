//! Collision: every question of the form "does this body fit here?" and "what does this motion
//! hit first?", asked of a [`CompiledScene`] without an [`Episode`](crate::Episode).
//!
//! [`Episode::step`](crate::Episode::step) answers its collision questions only through this
//! module, scene validation checks clearances through it, and the 3D-FRONT importer builds its
//! walls and measures clearances with it; a planner asks the same functions about every edge of
//! its lattice, so a motion it plans is accepted by the simulator, and the other way round.
//!
//! # Poses and bodies
//!
//! [`robot_pose`] and [`object_pose`] turn plan positions and [`ObjectPose`]s into parry
//! [`Pose`]s; [`wall_pieces`] cuts a room's walls into boxes and [`wall_collider`] makes one a
//! parry shape. The moving [`Body`] is the robot at a plan position, carrying at most one movable
//! object at a pose. The other movable objects are [`MovableObstacles`]: their poses and world
//! boxes (the held one's entry is ignored).
//!
//! # Invariants
//!
//! - **The margin.** A body fits when its shapes dilated by the scene's collision margin (see
//!   [`crate::world`]) intersect no exact obstacle shape; a motion is free when the dilated
//!   shapes' sweep touches none. The robot's dilated cylinder and the objects' dilated parts are
//!   built once, in [`CompiledScene`].
//! - **Whole sweeps.** A translation is one linear shape cast per moving part over the whole
//!   move; a rotation (about the robot's vertical axis) is one rotational shape cast per moving
//!   part against each convex obstacle part the arc's box meets, by conservative advancement
//!   (distance queries, each certifying the arc up to the next: no contact is skipped). The
//!   robot itself is skipped in rotations: a cylinder turning about its own axis sweeps no new
//!   space.
//! - **Stricter on doubt.** A shape pair parry cannot query counts as a hit at the start of the
//!   motion (or as too close), so a bug can only reject motions, never let a body through.
//! - **Deterministic.** The same inputs give bit-identical answers: the queries run in a fixed
//!   order and the earliest hit wins, the first found on a tie.

use std::sync::Arc;

use parry3d::bounding_volume::{Aabb, BoundingVolume};
use parry3d::math::{Pose, Vector};
use parry3d::query::{self, NonlinearRigidMotion, ShapeCastOptions};
use parry3d::shape::Shape;

use crate::action::Action;
use crate::geometry::{PlanPoint, rotate_plan};
use crate::heading::{Heading, TURN_ANGLE};
use crate::scene::ObjectPose;
pub use crate::shapes::{object_pose, robot_pose, wall_collider, wall_pieces};
use crate::world::{CompiledScene, MOVE_DISTANCE, Obstacle};

/// Whether two shapes are at least `clearance` apart (`clearance ≥ 0`). Boxes farther apart than
/// that answer without a distance query; a pair parry cannot measure counts as too close.
pub fn separated(pose1: &Pose, shape1: &dyn Shape, pose2: &Pose, shape2: &dyn Shape, clearance: f64) -> bool {
    if !shape1.compute_aabb(pose1).loosened(clearance).intersects(&shape2.compute_aabb(pose2)) {
        return true;
    }
    query::distance(pose1, shape1, pose2, shape2).is_ok_and(|d| d.distance >= clearance)
}

/// The moving body: the robot at `position`, carrying `held` (a movable object's index and its
/// current pose), if anything.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Body {
    /// The robot's position on the plan.
    pub position: PlanPoint,
    /// The held object and its pose.
    pub held: Option<(usize, ObjectPose)>,
}

impl Body {
    /// The robot alone at `position`.
    pub fn robot(position: PlanPoint) -> Self {
        Self { position, held: None }
    }

    fn held_index(&self) -> Option<usize> {
        self.held.map(|(i, _)| i)
    }
}

/// The movable objects as obstacles: each one's pose and its exact shape's world box at that
/// pose (kept so that a query meets only the objects near its sweep). The entry of the object a
/// [`Body`] holds is ignored by queries about that body.
///
/// Cloning shares the poses and boxes (copy on write): searches clone an episode per node, and
/// most of their motions move no object.
#[derive(Clone, Debug, PartialEq)]
pub struct MovableObstacles {
    poses: Arc<Vec<ObjectPose>>,
    aabbs: Arc<Vec<Aabb>>,
}

impl MovableObstacles {
    /// The scene's movable objects at `poses`, in scene order.
    ///
    /// # Panics
    ///
    /// If `poses` has more entries than the scene has movable objects.
    pub fn new(scene: &CompiledScene, poses: Vec<ObjectPose>) -> Self {
        let aabbs = poses.iter().enumerate().map(|(i, p)| object_aabb(scene, i, p)).collect();
        Self { poses: Arc::new(poses), aabbs: Arc::new(aabbs) }
    }

    /// The poses, in scene order.
    pub fn poses(&self) -> &[ObjectPose] {
        &self.poses
    }

    /// Moves object `i` to `pose`.
    ///
    /// # Panics
    ///
    /// If `i` is not a movable object of the scene.
    pub fn set(&mut self, scene: &CompiledScene, i: usize, pose: ObjectPose) {
        Arc::make_mut(&mut self.poses)[i] = pose;
        Arc::make_mut(&mut self.aabbs)[i] = object_aabb(scene, i, &pose);
    }

    /// Moves object `i` to `pose` without updating its box: only for the object being carried,
    /// which queries ignore until [`MovableObstacles::set`] puts it down.
    pub(crate) fn carry(&mut self, i: usize, pose: ObjectPose) {
        Arc::make_mut(&mut self.poses)[i] = pose;
    }
}

fn object_aabb(scene: &CompiledScene, i: usize, pose: &ObjectPose) -> Aabb {
    scene.movable_shape(i).compute_aabb(&object_pose(pose))
}

/// What a rejected motion hits first.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// When, as a fraction of the motion in `[0, 1]`.
    pub time: f64,
    /// The obstacle hit.
    pub obstacle: Obstacle,
}

/// The motion of the body over `t ∈ [0, 1]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Motion {
    /// Translation by a plan vector.
    Translate(PlanPoint),
    /// Rotation about the robot's vertical axis by an angle (radians, positive = left).
    Rotate(f64),
}

impl Motion {
    /// The motion of `action` for an agent facing `heading` (SPEC §3), with exactly the
    /// arithmetic of [`Episode::step`](crate::Episode::step); `None` for fetch and release.
    pub fn of(action: Action, heading: Heading) -> Option<Motion> {
        match action {
            Action::MoveForward | Action::MoveBackward => {
                let sign = if action == Action::MoveForward { 1.0 } else { -1.0 };
                Some(Motion::Translate(PlanPoint::new(
                    sign * MOVE_DISTANCE * heading.cos(),
                    -(sign * MOVE_DISTANCE * heading.sin()),
                )))
            }
            Action::TurnLeft => Some(Motion::Rotate(TURN_ANGLE)),
            Action::TurnRight => Some(Motion::Rotate(-TURN_ANGLE)),
            Action::Fetch | Action::Release => None,
        }
    }
}

/// The first obstacle `body` meets anywhere along `motion` in `scene`, with the other movable
/// objects at `obstacles`; `None` when the whole motion is free (SPEC §3). This is the rule
/// [`Episode::step`](crate::Episode::step) applies.
///
/// # Panics
///
/// If `body.held` or `obstacles` name objects the scene does not have.
pub fn first_hit(scene: &CompiledScene, obstacles: &MovableObstacles, body: &Body, motion: Motion) -> Option<Hit> {
    match motion {
        Motion::Translate(d) => first_hit_translating(scene, obstacles, body, d),
        Motion::Rotate(angle) => first_hit_rotating(scene, obstacles, body, angle),
    }
}

/// The first obstacle that `body`, dilated by the collision margin, intersects where it stands,
/// with the other movable objects at `poses`: the static world (walls, then fixed objects, by
/// part) before movable objects, the robot before the held object. `None` when it fits.
///
/// # Panics
///
/// If `body.held` or `poses` name objects the scene does not have.
pub fn obstruction(scene: &CompiledScene, poses: &[ObjectPose], body: &Body) -> Option<Obstacle> {
    let robot = robot_pose(body.position);
    first_intersection(scene, &robot, scene.robot_carried.as_ref(), poses, body.held_index())
        .or_else(|| body.held.and_then(|(i, pose)| object_obstruction(scene, poses, i, &pose)))
}

/// The first obstacle that movable object `i` at `pose`, dilated by the collision margin,
/// intersects, with the other movable objects at `poses` (its own entry is ignored); `None`
/// when it fits there. This is the check of a layout in [`CompiledScene::new`].
///
/// # Panics
///
/// If `i` or `poses` name objects the scene does not have.
pub fn object_obstruction(
    scene: &CompiledScene,
    poses: &[ObjectPose],
    i: usize,
    pose: &ObjectPose,
) -> Option<Obstacle> {
    let placement = object_pose(pose);
    scene.movables[i].carried_parts.iter().find_map(|(part_pose, part)| {
        first_intersection(scene, &(placement * *part_pose), part.as_ref(), poses, Some(i))
    })
}

/// The first obstacle that `shape` at `pose` intersects: the static world, then movable objects
/// at `poses` except `skip`.
fn first_intersection(
    scene: &CompiledScene,
    pose: &Pose,
    shape: &dyn Shape,
    poses: &[ObjectPose],
    skip: Option<usize>,
) -> Option<Obstacle> {
    // Unsupported shape pairs cannot occur with the shapes built here; count one as a hit so
    // that a bug can only make the simulator stricter, never let a body through.
    let hit = query::intersection_test(pose, shape, &Pose::IDENTITY, scene.static_shape())
        .map_or(Some(0), |r| r.intersecting.then_some(r.subshape2));
    if let Some(part) = hit {
        return Some(scene.static_part_owner(part));
    }
    for (j, other) in poses.iter().enumerate() {
        if Some(j) == skip {
            continue;
        }
        let hit = query::intersection_test(pose, shape, &object_pose(other), scene.movable_shape(j))
            .map_or(true, |r| r.intersecting);
        if hit {
            return Some(Obstacle::Movable(j));
        }
    }
    None
}

/// How far along the motion a further hit can still matter: only before the best one so far.
fn until(best: &Option<Hit>) -> f64 {
    best.map_or(1.0, |b| b.time)
}

fn earliest(best: &mut Option<Hit>, candidate: Hit) {
    if best.is_none_or(|b| candidate.time < b.time) {
        *best = Some(candidate);
    }
}

/// The moving body's parts in world coordinates, all dilated by the collision margin: the
/// robot (unless `with_robot` is false), then the held object's parts.
fn for_each_moving_part(scene: &CompiledScene, body: &Body, with_robot: bool, mut f: impl FnMut(&Pose, &dyn Shape)) {
    if with_robot {
        f(&robot_pose(body.position), scene.robot_carried.as_ref());
    }
    if let Some((i, pose)) = body.held {
        let placement = object_pose(&pose);
        for (pose, shape) in &scene.movables[i].carried_parts {
            f(&(placement * *pose), shape.as_ref());
        }
    }
}

/// Translation: one linear shape cast per moving part against the static compound (parry walks
/// its BVH) and against each movable object whose box meets the swept box.
fn first_hit_translating(
    scene: &CompiledScene,
    obstacles: &MovableObstacles,
    body: &Body,
    d: PlanPoint,
) -> Option<Hit> {
    let held = body.held_index();
    let shift = Vector::new(d.x, 0.0, d.z);
    let mut best: Option<Hit> = None;
    for_each_moving_part(scene, body, true, |pose, shape| {
        let start = shape.compute_aabb(pose);
        let swept = start.merged(&Aabb::new(start.mins + shift, start.maxs + shift));
        if let Some((time, part)) = cast_linear(pose, shape, shift, &Pose::IDENTITY, scene.static_shape()) {
            earliest(&mut best, Hit { time, obstacle: scene.static_part_owner(part) });
        }
        for (j, aabb) in obstacles.aabbs.iter().enumerate() {
            if Some(j) == held || !aabb.intersects(&swept) {
                continue;
            }
            let obstacle = scene.movable_shape(j);
            if let Some((time, _)) = cast_linear(pose, shape, shift, &object_pose(&obstacles.poses[j]), obstacle) {
                earliest(&mut best, Hit { time, obstacle: Obstacle::Movable(j) });
            }
        }
    });
    best
}

/// Rotation: a rotational shape cast ([`cast_rotating`]) of each moving part over the whole arc
/// against each convex obstacle part whose box meets the box swept by the arc.
///
/// The robot is skipped: it is a cylinder turning about its own axis, so a turn sweeps no space
/// it does not already occupy.
fn first_hit_rotating(scene: &CompiledScene, obstacles: &MovableObstacles, body: &Body, angle: f64) -> Option<Hit> {
    let held = body.held_index()?;
    let centre = body.position;
    let mut best: Option<Hit> = None;
    for_each_moving_part(scene, body, false, |pose, shape| {
        let (swept, radius) = arc_swept_aabb(&shape.compute_aabb(pose), centre, angle);
        // No point of the part moves farther than the chord of its arc: an obstacle farther than
        // that from the part's start pose cannot be reached.
        let reach = 2.0 * radius * (0.5 * angle).abs().sin() + 1e-9;
        let motion = NonlinearRigidMotion::new(
            *pose,
            pose.inverse_transform_point(Vector::new(centre.x, pose.translation.y, centre.z)),
            Vector::ZERO,
            Vector::new(0.0, angle, 0.0),
        );
        let check = |obstacle_pose: &Pose, obstacle: &dyn Shape, best: &Option<Hit>| {
            cast_rotating(&motion, shape, radius, reach, obstacle_pose, obstacle, until(best))
        };
        let statics = scene.static_shape();
        for leaf in statics.bvh().intersect_aabb(&swept) {
            let (leaf_pose, leaf_shape) = &statics.shapes()[leaf as usize];
            if let Some(time) = check(leaf_pose, leaf_shape.as_ref(), &best) {
                earliest(&mut best, Hit { time, obstacle: scene.static_part_owner(leaf) });
            }
        }
        for (j, aabb) in obstacles.aabbs.iter().enumerate() {
            if j == held || !aabb.intersects(&swept) {
                continue;
            }
            let placement = object_pose(&obstacles.poses[j]);
            let obstacle = scene.movable_shape(j);
            let local = swept.transform_by(&placement.inverse());
            for leaf in obstacle.bvh().intersect_aabb(&local) {
                let (leaf_pose, leaf_shape) = &obstacle.shapes()[leaf as usize];
                if let Some(time) = check(&(placement * *leaf_pose), leaf_shape.as_ref(), &best) {
                    earliest(&mut best, Hit { time, obstacle: Obstacle::Movable(j) });
                }
            }
        }
    });
    best
}

/// A box that contains everything `aabb` sweeps when rotated by `angle` (radians) about the
/// vertical axis through `centre`, and the largest distance of a point of `aabb` from that axis.
///
/// At every instant the rotated box is the convex hull of its rotated corners, and each corner
/// moves along an arc that lies within the arc's sagitta `ρ(1 − cos(angle/2))` of its chord; so
/// the box of the corners' start and end positions, grown by the largest sagitta, holds it all.
fn arc_swept_aabb(aabb: &Aabb, centre: PlanPoint, angle: f64) -> (Aabb, f64) {
    let (sin, cos) = angle.sin_cos();
    let sagitta_factor = 1.0 - (0.5 * angle).cos();
    let mut mins = aabb.mins;
    let mut maxs = aabb.maxs;
    let mut radius: f64 = 0.0;
    for x in [aabb.mins.x, aabb.maxs.x] {
        for z in [aabb.mins.z, aabb.maxs.z] {
            let rel = PlanPoint::new(x - centre.x, z - centre.z);
            let end = rotate_plan(rel, cos, sin);
            mins.x = mins.x.min(centre.x + end.x);
            mins.z = mins.z.min(centre.z + end.z);
            maxs.x = maxs.x.max(centre.x + end.x);
            maxs.z = maxs.z.max(centre.z + end.z);
            radius = radius.max(rel.x.hypot(rel.z));
        }
    }
    // A hair more, so that rounding never makes the box too small.
    let grow = radius * sagitta_factor + 1e-9;
    (Aabb::new(mins - Vector::new(grow, 0.0, grow), maxs + Vector::new(grow, 0.0, grow)), radius)
}

/// A linear shape cast of a moving part by `shift` (over `t ∈ [0, 1]`) against an obstacle: the
/// time of impact and the obstacle's sub-shape hit, or `None` if the whole motion is free.
fn cast_linear(
    pose: &Pose,
    shape: &dyn Shape,
    shift: Vector,
    obstacle_pose: &Pose,
    obstacle: &dyn Shape,
) -> Option<(f64, u32)> {
    let options = ShapeCastOptions {
        max_time_of_impact: 1.0,
        target_distance: 0.0,
        stop_at_penetration: true,
        compute_impact_geometry_on_penetration: false,
    };
    // An unsupported pair cannot occur with the shapes this crate builds; count it as a hit at
    // the start so that a bug makes the simulator stricter, never lets a body through.
    match query::cast_shapes(pose, shift, shape, obstacle_pose, Vector::ZERO, obstacle, options) {
        Ok(Some(hit)) => Some((hit.time_of_impact, hit.subshape2)),
        Ok(None) => None,
        Err(_) => Some((0.0, 0)),
    }
}

/// Gaps at or below this (metres) count as contact in a rotation's conservative advancement:
/// far below anything the scenes resolve, far above the distance query's rounding.
const ROTATION_CONTACT: f64 = 1e-7;

/// Conservative-advancement steps one rotating part may take against one obstacle part before
/// the pair counts as a hit. Steps shrink with the gap: an arc that grazes an obstacle just above
/// [`ROTATION_CONTACT`] takes on the order of ten thousand; anything else, far fewer.
const ROTATION_MAX_STEPS: u32 = 100_000;

/// A rotational shape cast of a part turning by `motion` (about the vertical axis, no point of
/// the part farther than `radius` from it) against a fixed convex obstacle part over
/// `t ∈ [0, until]`: the time of impact, or `None` if that part of the arc is free.
///
/// Conservative advancement: at a gap `d`, no point of the part can close it while turning by
/// less than `2·asin(d / 2·radius)` (a point's chord), so the part advances by that much and
/// measures again, until it has turned the whole way or the gap is [`ROTATION_CONTACT`]. Every
/// pose it skips is certified free by the distance measured before it, so no contact on the arc
/// is missed — unlike parry's nonlinear cast, which trusts a separating axis found at the start
/// and can miss a contact in the middle of an arc whose ends are both clear. A start farther
/// than `reach` (the largest chord) answers after one distance query.
fn cast_rotating(
    motion: &NonlinearRigidMotion,
    shape: &dyn Shape,
    radius: f64,
    reach: f64,
    obstacle_pose: &Pose,
    obstacle: &dyn Shape,
    until: f64,
) -> Option<f64> {
    let turn = motion.angvel.y.abs();
    let mut t = 0.0;
    for step in 0..ROTATION_MAX_STEPS {
        // An unsupported pair cannot occur with the shapes this crate builds; count it as a hit
        // so that a bug makes the simulator stricter, never lets a body through.
        let Ok(gap) = query::distance(&motion.position_at_time(t), shape, obstacle_pose, obstacle) else {
            return Some(t);
        };
        let gap = gap.distance;
        if gap <= ROTATION_CONTACT {
            return Some(t);
        }
        if step == 0 && gap > reach {
            return None;
        }
        if t >= until {
            return None;
        }
        let safe = 2.0 * (0.5 * gap / radius).min(1.0).asin();
        t = (t + safe / turn).min(until);
    }
    Some(t)
}
