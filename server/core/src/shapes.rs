//! Poses and walls as parry shapes: where the robot's cylinder and an object's frame stand in
//! the world, and a room's walls cut into boxes around its openings. Used by scene compilation
//! (`compile`) and by every collision query (`collision`, which re-exports these functions).

use parry3d::math::{Pose, Rotation, Vector};
use parry3d::shape::{Cuboid, SharedShape};

use crate::geometry::{PlanPoint, signed_area};
use crate::scene::{ObjectPose, Opening, OpeningKind};
use crate::world::{ROBOT_HEIGHT, WallPiece, WallPieceKind};

/// The pose of the robot's collision cylinder for an agent at `position`: centred half the
/// robot's height above the floor.
pub fn robot_pose(position: PlanPoint) -> Pose {
    Pose::translation(position.x, ROBOT_HEIGHT / 2.0, position.z)
}

/// The world pose of an object's frame: at `(x, 0, z)`, turned by `yaw` about +y.
pub fn object_pose(pose: &ObjectPose) -> Pose {
    Pose::from_parts(Vector::new(pose.x, 0.0, pose.z), Rotation::from_rotation_y(pose.yaw))
}

/// A wall piece's box as a parry shape at its world pose.
pub fn wall_collider(piece: &WallPiece) -> (Pose, SharedShape) {
    let [hx, hy, hz] = piece.half_extents;
    (
        Pose::from_parts(Vector::from(piece.center), Rotation::from_rotation_y(piece.yaw)),
        SharedShape::new(Cuboid::new(Vector::new(hx, hy, hz))),
    )
}

/// Cuts the walls of the room with floor polygon `floor` into boxes around its `openings`: one
/// wall of `thickness` outside each edge, `height` tall, reaching past convex corners so that
/// the corners are closed. Door openings keep a [`WallPieceKind::Door`] leaf; windows are holes.
///
/// `floor` must be a simple polygon (either orientation) and the openings valid, as
/// [`CompiledScene::new`] checks them: on a wall of the floor, within its length and height, not
/// overlapping each other. An opening on a wall the floor does not have is ignored.
pub fn wall_pieces(floor: &[PlanPoint], thickness: f64, height: f64, openings: &[Opening]) -> Vec<WallPiece> {
    let n = floor.len();
    let orientation = signed_area(floor).signum();
    let convex_at = |i: usize| {
        let prev = floor[(i + n - 1) % n];
        let here = floor[i];
        let next = floor[(i + 1) % n];
        let cross = (here.x - prev.x) * (next.z - here.z) - (here.z - prev.z) * (next.x - here.x);
        orientation * cross > 0.0
    };
    let openings_by_wall = openings_by_wall(n, openings);
    let mut pieces = Vec::new();
    for (wall, openings) in openings_by_wall.iter().enumerate() {
        let a = floor[wall];
        let b = floor[(wall + 1) % n];
        let length = a.distance(b);
        let d = PlanPoint::new((b.x - a.x) / length, (b.z - a.z) / length);
        let outward = PlanPoint::new(orientation * d.z, -orientation * d.x);
        let yaw = (-d.z).atan2(d.x);
        let start = if convex_at(wall) { -thickness } else { 0.0 };
        let end = length + if convex_at((wall + 1) % n) { thickness } else { 0.0 };
        let mut piece = |u0: f64, u1: f64, y0: f64, y1: f64, kind: WallPieceKind| {
            if u1 - u0 <= 1e-9 || y1 - y0 <= 1e-9 {
                return;
            }
            let u = 0.5 * (u0 + u1);
            let w = 0.5 * thickness;
            pieces.push(WallPiece {
                wall,
                kind,
                center: [a.x + d.x * u + outward.x * w, 0.5 * (y0 + y1), a.z + d.z * u + outward.z * w],
                half_extents: [0.5 * (u1 - u0), 0.5 * (y1 - y0), 0.5 * thickness],
                yaw,
            });
        };
        let mut cursor = start;
        for (_, opening) in openings.iter() {
            let (u0, u1) = (opening.offset, opening.offset + opening.width);
            piece(cursor, u0, 0.0, height, WallPieceKind::Wall);
            piece(u0, u1, 0.0, opening.bottom, WallPieceKind::Wall);
            piece(u0, u1, opening.top, height, WallPieceKind::Wall);
            if opening.kind == OpeningKind::Door {
                piece(u0, u1, opening.bottom, opening.top, WallPieceKind::Door);
            }
            cursor = u1;
        }
        piece(cursor, end, 0.0, height, WallPieceKind::Wall);
    }
    pieces
}

/// The openings of each of the `walls` walls with their indices, sorted along the wall.
pub(crate) fn openings_by_wall(walls: usize, openings: &[Opening]) -> Vec<Vec<(usize, &Opening)>> {
    let mut by_wall: Vec<Vec<(usize, &Opening)>> = vec![Vec::new(); walls];
    for (index, opening) in openings.iter().enumerate() {
        if let Some(wall) = by_wall.get_mut(opening.wall) {
            wall.push((index, opening));
        }
    }
    for wall in &mut by_wall {
        wall.sort_by(|x, y| x.1.offset.total_cmp(&y.1.offset));
    }
    by_wall
}
