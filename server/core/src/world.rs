//! The compiled scene's data: the task's constants, [`Rules`], obstacles, wall pieces, footprints
//! and [`CompiledScene`] with its accessors. Building one (validation, shapes) is `compile`'s
//! job, and asking it collision questions is [`crate::collision`]'s: this module names neither.
//!
//! A [`CompiledScene`] is immutable and shared (behind an `Arc`) by every episode of the same
//! scene. It holds the static world (walls and fixed furniture, one parry [`Compound`] with its
//! BVH), each movable object's shape twice — exact, for when it is an obstacle, and dilated by
//! the collision margin, for when it is carried — and the robot's dilated body.
//!
//! # The collision margin
//!
//! A motion is rejected when the moving body would come within `collision_margin` of an
//! obstacle. The moving shapes are the exact shapes dilated by the margin (parry's round shapes:
//! the Minkowski sum with a ball), so a cast at zero distance between a dilated moving shape and
//! an exact obstacle is a cast at the margin between the exact shapes. Linear (translation) and
//! rotational casts use the same shapes, so both obey the same margin.

use parry3d::math::Pose;
use parry3d::shape::{Compound, SharedShape};

use crate::error::SceneError;
use crate::geometry::{OrientedRect, PlanPoint, rotate_plan};
use crate::heading::Heading;
use crate::scene::{ObjectPose, Scene};

/// The robot's collision radius, metres (SPEC §2).
pub const ROBOT_RADIUS: f64 = 0.30;
/// The robot's collision height, metres (SPEC §2).
pub const ROBOT_HEIGHT: f64 = 1.10;
/// Length of one move, metres (SPEC §3).
pub const MOVE_DISTANCE: f64 = 0.25;
/// Height of the egocentric camera above the floor, metres (SPEC §2).
pub const CAMERA_HEIGHT: f64 = 1.25;
/// Downward pitch of the egocentric camera, radians (20°, SPEC §2).
pub const CAMERA_PITCH: f64 = 20.0 * std::f64::consts::PI / 180.0;
/// Horizontal field of view of the egocentric camera, radians (90°, SPEC §2).
pub const CAMERA_HORIZONTAL_FOV: f64 = std::f64::consts::FRAC_PI_2;
/// The most movable objects a scene may have (SPEC §7).
pub const MAX_MOVABLE_OBJECTS: usize = 6;

/// The task's rule parameters (SPEC §3, §5). Every field has the SPEC's default.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Rules {
    /// Safety margin of the continuous collision checks, metres (default 0.01).
    pub collision_margin: f64,
    /// Fetch reach: footprint distance from the agent's centre, metres (default 1.0).
    pub fetch_reach: f64,
    /// An object is placed when its footprint IoU with its target exceeds this (default 0.3).
    pub placement_iou: f64,
}

impl Default for Rules {
    fn default() -> Self {
        Self { collision_margin: 0.01, fetch_reach: 1.0, placement_iou: 0.3 }
    }
}

impl Rules {
    pub(crate) fn validate(&self) -> Result<(), SceneError> {
        let bad = |reason: String| Err(SceneError::InvalidRules { reason });
        if !(self.collision_margin.is_finite() && self.collision_margin > 0.0 && self.collision_margin <= 0.1) {
            return bad(format!("collision_margin {} must be in (0, 0.1] metres", self.collision_margin));
        }
        if !(self.fetch_reach.is_finite() && self.fetch_reach > 0.0 && self.fetch_reach <= 5.0) {
            return bad(format!("fetch_reach {} must be in (0, 5] metres", self.fetch_reach));
        }
        if !(self.placement_iou.is_finite() && (0.0..1.0).contains(&self.placement_iou)) {
            return bad(format!("placement_iou {} must be in [0, 1)", self.placement_iou));
        }
        Ok(())
    }
}

/// Something the agent can hit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", content = "index", rename_all = "snake_case")]
pub enum Obstacle {
    /// Wall `i` (floor polygon edge `i`), doors included.
    Wall(usize),
    /// Fixed object `i` of `fixed_objects`.
    Fixed(usize),
    /// Movable object `i` of `movable_objects`.
    Movable(usize),
}

/// What a piece of wall is, for drawing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WallPieceKind {
    /// Plain wall.
    Wall,
    /// A closed door leaf set into the wall.
    Door,
}

/// One box of wall, in world coordinates: the walls of a room cut around their openings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct WallPiece {
    /// Index of the wall (floor polygon edge).
    pub wall: usize,
    /// Wall or door.
    pub kind: WallPieceKind,
    /// Centre `[x, y, z]`.
    pub center: [f64; 3],
    /// Half sizes along the piece's local x (along the wall), y (up) and z (through the wall).
    pub half_extents: [f64; 3],
    /// Yaw of the piece's local x axis, radians.
    pub yaw: f64,
}

impl WallPiece {
    /// The piece's footprint on the plan.
    pub fn footprint(&self) -> OrientedRect {
        OrientedRect {
            center: PlanPoint::new(self.center[0], self.center[2]),
            half_x: self.half_extents[0],
            half_z: self.half_extents[2],
            yaw: self.yaw,
        }
    }
}

/// An object's footprint in its own frame: the x–z extent of its model's bounding box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalFootprint {
    /// Centre of the bounding box on the object's local plan.
    pub center: PlanPoint,
    /// Half extent along local x.
    pub half_x: f64,
    /// Half extent along local z.
    pub half_z: f64,
}

impl LocalFootprint {
    /// The footprint placed at `pose` (SPEC §5).
    pub fn at(&self, pose: &ObjectPose) -> OrientedRect {
        let (sin, cos) = pose.yaw.sin_cos();
        let c = rotate_plan(self.center, cos, sin);
        OrientedRect {
            center: PlanPoint::new(pose.x + c.x, pose.z + c.z),
            half_x: self.half_x,
            half_z: self.half_z,
            yaw: pose.yaw,
        }
    }
}

/// A movable object's collision data.
#[derive(Clone)]
pub(crate) struct MovableGeometry {
    /// Exact shape in the object's frame, as an obstacle (a compound of convex parts).
    pub obstacle: Compound,
    /// Parts dilated by the margin, in the object's frame, for when it is carried.
    pub carried_parts: Vec<(Pose, SharedShape)>,
    /// Footprint in the object's frame.
    pub footprint: LocalFootprint,
}

/// A validated scene with its collision world, ready for episodes. Immutable; share it with
/// `Arc` between every episode of the scene.
pub struct CompiledScene {
    pub(crate) scene: Scene,
    pub(crate) rules: Rules,
    pub(crate) floor: Vec<PlanPoint>,
    pub(crate) wall_pieces: Vec<WallPiece>,
    pub(crate) static_world: Compound,
    pub(crate) static_part_owner: Vec<Obstacle>,
    pub(crate) fixed_footprints: Vec<OrientedRect>,
    pub(crate) movables: Vec<MovableGeometry>,
    pub(crate) robot_carried: SharedShape,
    pub(crate) robot_exact: SharedShape,
    pub(crate) initial_distance: f64,
}

impl std::fmt::Debug for CompiledScene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CompiledScene").field("id", &self.scene.id).field("rules", &self.rules).finish_non_exhaustive()
    }
}

fn obstacle_name(scene: &Scene, obstacle: Obstacle) -> String {
    match obstacle {
        Obstacle::Wall(i) => format!("wall {i}"),
        Obstacle::Fixed(i) => scene.fixed_objects[i].id.clone(),
        Obstacle::Movable(i) => scene.movable_objects[i].id.clone(),
    }
}

impl CompiledScene {
    /// The scene as given.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The rules this scene was compiled under.
    pub fn rules(&self) -> &Rules {
        &self.rules
    }

    /// The floor polygon.
    pub fn floor(&self) -> &[PlanPoint] {
        &self.floor
    }

    /// The walls cut around their openings, in world coordinates.
    pub fn wall_pieces(&self) -> &[WallPiece] {
        &self.wall_pieces
    }

    /// Footprints of the fixed objects, in scene order.
    pub fn fixed_footprints(&self) -> &[OrientedRect] {
        &self.fixed_footprints
    }

    /// Movable object `i`'s footprint at `pose`.
    pub fn movable_footprint(&self, i: usize, pose: &ObjectPose) -> OrientedRect {
        self.movables[i].footprint.at(pose)
    }

    /// Movable object `i`'s footprint in its own frame.
    pub fn movable_local_footprint(&self, i: usize) -> LocalFootprint {
        self.movables[i].footprint
    }

    /// `D` at the start (SPEC §5): the sum over objects of the plan distance between footprint
    /// centres at the initial and target poses.
    pub fn initial_distance(&self) -> f64 {
        self.initial_distance
    }

    /// Human-readable name of an obstacle: the object's id or `wall N`.
    pub fn obstacle_name(&self, obstacle: Obstacle) -> String {
        obstacle_name(&self.scene, obstacle)
    }

    /// The wall or fixed object that part `part` of [`CompiledScene::static_shape`] belongs to.
    pub fn static_part_owner(&self, part: u32) -> Obstacle {
        self.static_part_owner.get(part as usize).copied().unwrap_or(Obstacle::Wall(0))
    }

    /// The robot's exact collision cylinder (for independent checks).
    pub fn robot_shape(&self) -> &SharedShape {
        &self.robot_exact
    }

    /// The exact collision shape of movable object `i` in its own frame: a compound of its
    /// convex parts (a mesh becomes its convex hull).
    pub fn movable_shape(&self, i: usize) -> &Compound {
        &self.movables[i].obstacle
    }

    /// The static world (walls and fixed objects) as one compound in world coordinates; its
    /// part `i` belongs to [`CompiledScene::static_part_owner`]`(i)`.
    pub fn static_shape(&self) -> &Compound {
        &self.static_world
    }

    /// The start heading.
    pub fn start_heading(&self) -> Heading {
        self.scene.agent.heading
    }
}
