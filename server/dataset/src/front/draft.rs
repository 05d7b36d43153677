//! A room drafted as a scene: its floor, walls, openings and pieces placed, the movable ones
//! chosen and cleared, and the target scene.

use std::collections::{HashMap, HashSet};

use esrp_core::geometry::{PlanPoint, point_in_polygon, signed_area};
use esrp_core::{
    AgentStart, Difficulty, FixedObject, Heading, MovableCategory, MovableObject, ObjectPose, Opening, OpeningKind,
    Part, Room, SCENE_SCHEMA, Scene, Shape,
};
use esrp_core::{collision, parry3d};
use parry3d::math::{Pose, Vector};
use parry3d::shape::SharedShape;

use crate::benchmark::{OBJECT_COUNT_MIX, split_for_id};
use crate::dice::Dice;
use crate::layout::{CATEGORY_SHARES, TRIANGLE_BUDGET};

use super::categories::movable_category;
use super::constants::{
    CLEARANCE, DEFAULT_WALL_HEIGHT, FLAT_HEIGHT, MAX_CARRY_HEIGHT, MAX_CARRY_SIZE, MAX_HULL_POINTS, MIN_FLOOR_AREA,
    MIN_FREE_FLOOR, NUDGES, STANDING_TOLERANCE, WALL_THICKNESS,
};
use super::json::{ArchMesh, Child, FrontRoom, Furniture, House};
use super::library::{Library, ModelGeometry, box_corners};
use super::outline::{bounds, floor_outline, plan};
use super::report::ImportReport;
use super::rotation::{normalized, rotate, yaw_from_quaternion};

/// One furniture object of a room, in its own frame.
#[derive(Clone, Debug)]
pub(super) struct Piece {
    pub(super) jid: String,
    pub(super) category: String,
    pub(super) movable: Option<MovableCategory>,
    /// Points in the object's frame (footprint centred, floor at y = 0).
    pub(super) points: Vec<[f64; 3]>,
    /// The shape is the box of the points (bounding-box fallback).
    pub(super) is_box: bool,
    pub(super) pose: ObjectPose,
    /// Size along local x, y (height of the top above the floor) and z.
    pub(super) size: [f64; 3],
    pub(super) standing: bool,
}

impl Piece {
    pub(super) fn carryable(&self) -> bool {
        self.movable.is_some()
            && self.standing
            && self.size[0].max(self.size[2]) <= MAX_CARRY_SIZE
            && self.size[1] <= MAX_CARRY_HEIGHT
    }

    pub(super) fn footprint_area(&self) -> f64 {
        self.size[0] * self.size[2]
    }

    pub(super) fn shape(&self) -> Shape {
        let (lo, hi) = bounds(self.points.iter().copied()).unwrap_or(([0.0; 3], [0.0; 3]));
        if self.is_box {
            let half = [0, 1, 2].map(|k| ((hi[k] - lo[k]) / 2.0).max(0.005));
            let offset = [0, 1, 2].map(|k| (hi[k] + lo[k]) / 2.0);
            Shape::Parts(vec![Part::Box { half_extents: half, offset, yaw: 0.0 }])
        } else {
            Shape::Parts(vec![Part::ConvexHull { points: self.points.clone(), offset: [0.0; 3], yaw: 0.0 }])
        }
    }

    /// The collision shape in the object's frame.
    pub(super) fn collider(&self) -> Option<(Pose, SharedShape)> {
        let (lo, hi) = bounds(self.points.iter().copied())?;
        if self.is_box {
            let half = [0, 1, 2].map(|k| ((hi[k] - lo[k]) / 2.0).max(0.005));
            let centre = [0, 1, 2].map(|k| (hi[k] + lo[k]) / 2.0);
            Some((Pose::translation(centre[0], centre[1], centre[2]), SharedShape::cuboid(half[0], half[1], half[2])))
        } else {
            let vectors: Vec<Vector> = self.points.iter().map(|p| Vector::new(p[0], p[1], p[2])).collect();
            SharedShape::convex_hull(&vectors).map(|s| (Pose::IDENTITY, s))
        }
    }
}

/// Farthest-point subsampling of hull vertices down to `cap` points (deterministic).
pub(super) fn subsample(points: Vec<[f64; 3]>, cap: usize) -> Vec<[f64; 3]> {
    if points.len() <= cap {
        return points;
    }
    let distance2 = |a: &[f64; 3], b: &[f64; 3]| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>();
    let first = (0..points.len())
        .max_by(|&a, &b| {
            let sa: f64 = points[a].iter().sum();
            let sb: f64 = points[b].iter().sum();
            sa.total_cmp(&sb).then(b.cmp(&a))
        })
        .unwrap_or(0);
    let mut chosen = vec![first];
    let mut nearest: Vec<f64> = points.iter().map(|p| distance2(p, &points[first])).collect();
    while chosen.len() < cap {
        let far = (0..points.len()).max_by(|&a, &b| nearest[a].total_cmp(&nearest[b]).then(b.cmp(&a))).unwrap_or(0);
        if nearest[far] <= 0.0 {
            break;
        }
        chosen.push(far);
        for (i, p) in points.iter().enumerate() {
            nearest[i] = nearest[i].min(distance2(p, &points[far]));
        }
    }
    chosen.sort_unstable();
    chosen.into_iter().map(|i| points[i]).collect()
}

pub(super) fn round4(v: f64) -> f64 {
    (v * 1e4).round() / 1e4
}

/// A model placed by a child's transform.
#[derive(Debug)]
pub(super) struct Placement {
    /// The object's pose.
    pub(super) pose: ObjectPose,
    /// The points in the object's frame.
    pub(super) local: Vec<[f64; 3]>,
    /// Size along local x, height of the top above the floor, size along local z.
    pub(super) size: [f64; 3],
    /// Whether it stands on the floor (and was shifted to y = 0).
    pub(super) standing: bool,
}

/// Places model-frame points by a child's transform into an object frame turned by the
/// child's yaw, centred on the footprint; `None` for no points or
/// non-finite ones. Objects within 5 cm of the floor at `floor_y` are shifted onto it.
pub(super) fn place(points: &[[f64; 3]], child: &Child, floor_y: f64) -> Option<Placement> {
    let q = normalized(child.rot);
    let yaw = yaw_from_quaternion(child.rot);
    let (sin, cos) = yaw.sin_cos();
    let turned: Vec<[f64; 3]> = points
        .iter()
        .map(|v| {
            let r = rotate(q, [v[0] * child.scale[0], v[1] * child.scale[1], v[2] * child.scale[2]]);
            // Undo the yaw: rotate by −yaw about +y.
            [cos * r[0] - sin * r[2], child.pos[1] + r[1] - floor_y, sin * r[0] + cos * r[2]]
        })
        .collect();
    let (lo, hi) = bounds(turned.iter().copied())?;
    if !(lo.iter().chain(&hi).all(|v| v.is_finite())) {
        return None;
    }
    let (cx, cz) = ((lo[0] + hi[0]) / 2.0, (lo[2] + hi[2]) / 2.0);
    let standing = lo[1] <= STANDING_TOLERANCE;
    let lift = if standing { lo[1] } else { 0.0 };
    let local: Vec<[f64; 3]> =
        turned.iter().map(|p| [round4(p[0] - cx), round4(p[1] - lift), round4(p[2] - cz)]).collect();
    let pose = ObjectPose::new(child.pos[0] + cos * cx + sin * cz, child.pos[2] - sin * cx + cos * cz, yaw);
    let size = [hi[0] - lo[0], hi[1] - lift, hi[2] - lo[2]];
    Some(Placement { pose, local, size, standing })
}

/// A room's target layout before the choice of movable pieces.
pub(super) struct RoomDraft {
    pub(super) floor: Vec<PlanPoint>,
    pub(super) wall_height: f64,
    pub(super) openings: Vec<Opening>,
    pub(super) pieces: Vec<Piece>,
}

/// Collision data of a draft: walls and each piece's shape in its frame.
pub(super) struct Clearances {
    pub(super) walls: Vec<(Pose, SharedShape)>,
    pub(super) colliders: Vec<Option<(Pose, SharedShape)>>,
}

impl Clearances {
    /// The draft's walls as esrp-core builds them (without openings, which only remove wall:
    /// conservative) and its pieces' shapes.
    pub(super) fn of(draft: &RoomDraft) -> Self {
        Self {
            walls: collision::wall_pieces(&draft.floor, WALL_THICKNESS, draft.wall_height, &[])
                .iter()
                .map(collision::wall_collider)
                .collect(),
            colliders: draft.pieces.iter().map(Piece::collider).collect(),
        }
    }

    pub(super) fn world(&self, i: usize, pose: &ObjectPose) -> Option<(Pose, &SharedShape)> {
        let (local, shape) = self.colliders[i].as_ref()?;
        Some((collision::object_pose(pose) * *local, shape))
    }

    /// Whether piece `i` at `pose` is clear by [`CLEARANCE`] of the walls and of every other
    /// piece at `poses`.
    pub(super) fn is_clear(&self, i: usize, pose: &ObjectPose, poses: &[ObjectPose]) -> bool {
        let Some((world, shape)) = self.world(i, pose) else { return false };
        let apart = |other_pose: &Pose, other: &SharedShape| {
            collision::separated(&world, shape.as_ref(), other_pose, other.as_ref(), CLEARANCE)
        };
        self.walls.iter().all(|(p, s)| apart(p, s))
            && poses.iter().enumerate().filter(|(j, _)| *j != i).all(|(j, other)| match self.world(j, other) {
                Some((p, s)) => apart(&p, s),
                None => true,
            })
    }
}

/// Chooses the movable pieces for one attempt: the indices chosen and the poses of every
/// piece (chosen ones possibly nudged), with counts of nudged and stuck pieces.
pub(super) fn choose_movables(
    draft: &RoomDraft,
    clearances: &Clearances,
    dice: &mut Dice,
) -> (Vec<usize>, Vec<ObjectPose>, usize, usize) {
    let mut poses: Vec<ObjectPose> = draft.pieces.iter().map(|p| p.pose).collect();
    let mut candidates: Vec<usize> = (0..draft.pieces.len()).filter(|&i| draft.pieces[i].carryable()).collect();
    let most = candidates.len().min(esrp_core::world::MAX_MOVABLE_OBJECTS);
    let count_weights: Vec<f64> = OBJECT_COUNT_MIX.iter().take(most).map(|(_, n)| *n as f64).collect();
    let wanted = 1 + dice.weighted(&count_weights);
    let share = |c: MovableCategory| CATEGORY_SHARES.iter().find(|(k, _)| *k == c).map_or(1.0, |(_, w)| *w);
    let (mut chosen, mut nudged, mut stuck) = (Vec::new(), 0, 0);
    while chosen.len() < wanted && !candidates.is_empty() {
        let weights: Vec<f64> = candidates
            .iter()
            .map(|&i| {
                let category = draft.pieces[i].movable.unwrap_or(MovableCategory::Others);
                let same = candidates.iter().filter(|&&j| draft.pieces[j].movable == Some(category)).count();
                share(category) / same as f64
            })
            .collect();
        let i = candidates.swap_remove(dice.weighted(&weights));
        let original = poses[i];
        if clearances.is_clear(i, &original, &poses) {
            chosen.push(i);
            continue;
        }
        let freed = NUDGES.iter().find_map(|&distance| {
            (0..16).find_map(|k| {
                let angle = k as f64 * std::f64::consts::PI / 8.0;
                let pose = ObjectPose::new(
                    original.x + distance * angle.cos(),
                    original.z - distance * angle.sin(),
                    original.yaw,
                );
                (point_in_polygon(pose.position(), &draft.floor) && clearances.is_clear(i, &pose, &poses))
                    .then_some(pose)
            })
        });
        match freed {
            Some(pose) => {
                poses[i] = pose;
                chosen.push(i);
                nudged += 1;
            }
            None => stuck += 1,
        }
    }
    chosen.sort_unstable();
    (chosen, poses, nudged, stuck)
}

pub(super) fn slug(text: &str) -> String {
    let mut s: String = text.to_lowercase().chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '_' }).collect();
    while s.contains("__") {
        s = s.replace("__", "_");
    }
    let s = s.trim_matches('_').to_owned();
    if s.is_empty() { "object".to_owned() } else { s }
}

/// The target layout of one attempt as a scene (agent not yet placed).
pub(super) fn target_scene(
    id: &str,
    room_type: &str,
    draft: &RoomDraft,
    chosen: &[usize],
    poses: &[ObjectPose],
) -> Option<Scene> {
    let difficulty = Difficulty::for_object_count(chosen.len())?;
    let mut fixed_objects = Vec::new();
    let mut movable_objects = Vec::new();
    for (i, piece) in draft.pieces.iter().enumerate() {
        let object_id = format!("{}-{i}", slug(&piece.category));
        match piece.movable.filter(|_| chosen.contains(&i)) {
            Some(category) => movable_objects.push(MovableObject {
                id: object_id,
                category,
                model: piece.jid.clone(),
                shape: piece.shape(),
                pose: poses[i],
                target: poses[i],
            }),
            None => fixed_objects.push(FixedObject {
                id: object_id,
                category: piece.category.clone(),
                model: piece.jid.clone(),
                shape: piece.shape(),
                pose: poses[i],
            }),
        }
    }
    Some(Scene {
        schema: SCENE_SCHEMA.to_owned(),
        id: id.to_owned(),
        room_type: room_type.to_owned(),
        difficulty,
        split: split_for_id(id),
        room: Room {
            floor: draft.floor.iter().map(|p| [p.x, p.z]).collect(),
            wall_height: draft.wall_height,
            wall_thickness: WALL_THICKNESS,
            openings: draft.openings.clone(),
        },
        fixed_objects,
        movable_objects,
        agent: AgentStart { x: 0.0, z: 0.0, heading: Heading::default() },
        horizon: 200,
        expert_trajectory: Vec::new(),
    })
}

/// FNV-1a, 64 bits: the room's random stream from its id.
pub(super) fn stream_of(id: &str) -> u64 {
    id.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

/// Openings from a room's `Door` and `Window` meshes, mapped onto the nearest floor edge.
pub(super) fn openings_of(
    meshes: &[(&ArchMesh, &Child)],
    floor: &[PlanPoint],
    floor_y: f64,
    wall_height: f64,
) -> Vec<Opening> {
    let n = floor.len();
    let mut openings: Vec<Opening> = Vec::new();
    for (mesh, child) in meshes {
        let kind = match mesh.kind.as_str() {
            "Door" => OpeningKind::Door,
            "Window" => OpeningKind::Window,
            _ => continue,
        };
        let points = mesh_points(mesh, child);
        let Some((lo, hi)) = bounds(points.iter().copied()) else { continue };
        let best = (0..n)
            .filter_map(|wall| {
                let (a, b) = (floor[wall], floor[(wall + 1) % n]);
                let length = a.distance(b);
                let mut worst: f64 = 0.0;
                let (mut t0, mut t1) = (f64::INFINITY, f64::NEG_INFINITY);
                for p in &points {
                    let (dx, dz) = ((b.x - a.x) / length, (b.z - a.z) / length);
                    let along = (p[0] - a.x) * dx + (p[2] - a.z) * dz;
                    let across = ((p[0] - a.x) * dz - (p[2] - a.z) * dx).abs();
                    worst = worst.max(across);
                    t0 = t0.min(along);
                    t1 = t1.max(along);
                }
                (worst <= 0.35).then_some((wall, worst, t0.max(0.05), t1.min(length - 0.05)))
            })
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let Some((wall, _, start, end)) = best else { continue };
        let bottom = if kind == OpeningKind::Door { 0.0 } else { (lo[1] - floor_y).max(0.0) };
        let top = (hi[1] - floor_y).min(wall_height - 0.01);
        if end - start >= 0.3 && top - bottom >= 0.2 {
            openings.push(Opening { kind, wall, offset: start, width: end - start, bottom, top });
        }
    }
    openings.sort_by(|a, b| a.wall.cmp(&b.wall).then(a.offset.total_cmp(&b.offset)));
    let mut kept: Vec<Opening> = Vec::new();
    for o in openings {
        if kept.last().is_some_and(|k| k.wall == o.wall && o.offset < k.offset + k.width + 0.01) {
            continue;
        }
        kept.push(o);
    }
    kept
}

/// A mesh's vertices placed by its child's transform.
pub(super) fn mesh_points(mesh: &ArchMesh, child: &Child) -> Vec<[f64; 3]> {
    let q = normalized(child.rot);
    mesh.xyz
        .chunks_exact(3)
        .map(|v| {
            let r = rotate(q, [v[0] * child.scale[0], v[1] * child.scale[1], v[2] * child.scale[2]]);
            [r[0] + child.pos[0], r[1] + child.pos[1], r[2] + child.pos[2]]
        })
        .collect()
}

/// Builds one room's draft, or the reason it is skipped.
pub(super) fn draft_room(
    room: &FrontRoom,
    room_name: &str,
    house: &House,
    library: &mut Library,
    report: &mut ImportReport,
) -> Result<RoomDraft, &'static str> {
    let meshes: HashMap<&str, &ArchMesh> = house.mesh.iter().map(|m| (m.uid.as_str(), m)).collect();
    let room_meshes: Vec<(&ArchMesh, &Child)> =
        room.children.iter().filter_map(|c| meshes.get(c.reference.as_str()).map(|m| (*m, c))).collect();
    let (floor, floor_y) = draft_floor(&room_meshes, room_name, report)?;
    let floor_area = signed_area(&floor);
    if floor_area < MIN_FLOOR_AREA {
        return Err("too_small");
    }
    let wall_height = wall_height(&room_meshes, floor_y);
    let openings = openings_of(&room_meshes, &floor, floor_y, wall_height);
    let furniture: HashMap<&str, &Furniture> = house.furniture.iter().map(|f| (f.uid.as_str(), f)).collect();
    let children: Vec<(&Furniture, &Child)> =
        room.children.iter().filter_map(|c| furniture.get(c.reference.as_str()).map(|f| (*f, c))).collect();
    // Each piece's hull is cut to its share of the triangles the walls leave.
    let walls_triangles = 12 * 3 * floor.len() + 12 * 2 * openings.len();
    let per_object = TRIANGLE_BUDGET.saturating_sub(walls_triangles) / children.len().max(1);
    let cap = ((per_object + 4) / 2).clamp(8, MAX_HULL_POINTS);
    let pieces = draft_pieces(&children, room_name, &floor, floor_y, cap, library, report);
    let covered: f64 = pieces.iter().filter(|p| p.standing).map(Piece::footprint_area).sum();
    if floor_area - covered < MIN_FREE_FLOOR {
        return Err("no_free_floor");
    }
    if !pieces.iter().any(Piece::carryable) {
        return Err("no_carryable");
    }
    Ok(RoomDraft { floor, wall_height, openings, pieces })
}

/// The room's floor outline, counter-clockwise, and the floor's height: the outline of its floor
/// meshes' triangles (the largest where there are several, their bounding rectangle where they
/// make no simple polygon), or `no_floor_mesh`.
fn draft_floor(
    room_meshes: &[(&ArchMesh, &Child)],
    room_name: &str,
    report: &mut ImportReport,
) -> Result<(Vec<PlanPoint>, f64), &'static str> {
    let mut triangles = Vec::new();
    let mut floor_points = Vec::new();
    for (mesh, child) in room_meshes.iter().filter(|(m, _)| m.kind == "Floor") {
        let points = mesh_points(mesh, child);
        for face in mesh.faces.chunks_exact(3) {
            let corners = [0, 1, 2].map(|k| points.get(face[k] as usize).copied());
            if let [Some(a), Some(b), Some(c)] = corners {
                triangles.push([plan(a), plan(b), plan(c)]);
            } else {
                report.warnings.push(format!("{room_name}: floor mesh {} has a face past its vertices", mesh.uid));
            }
        }
        floor_points.extend(points);
    }
    let Some((lo, hi)) = bounds(floor_points.iter().copied()) else { return Err("no_floor_mesh") };
    if triangles.is_empty() {
        return Err("no_floor_mesh");
    }
    let floor = match floor_outline(&triangles) {
        Some((outline, count)) => {
            if count > 1 {
                report.warnings.push(format!("{room_name}: the floor has {count} outlines; keeping the largest"));
            }
            outline
        }
        None => {
            report
                .warnings
                .push(format!("{room_name}: the floor outline is not a simple polygon; using its bounding rectangle"));
            [(lo[0], lo[2]), (hi[0], lo[2]), (hi[0], hi[2]), (lo[0], hi[2])].map(|(x, z)| PlanPoint::new(x, z)).to_vec()
        }
    };
    let floor = if signed_area(&floor) < 0.0 { floor.into_iter().rev().collect() } else { floor };
    Ok((floor, lo[1]))
}

/// The height of the room's walls above the floor: their meshes' top where it is between 2.2 m
/// and 4 m, else [`DEFAULT_WALL_HEIGHT`].
fn wall_height(room_meshes: &[(&ArchMesh, &Child)], floor_y: f64) -> f64 {
    let wall_top = room_meshes
        .iter()
        .filter(|(m, _)| m.kind.starts_with("Wall"))
        .flat_map(|(m, c)| mesh_points(m, c))
        .map(|p| p[1] - floor_y)
        .fold(f64::NEG_INFINITY, f64::max);
    if (2.2..=4.0).contains(&wall_top) { wall_top } else { DEFAULT_WALL_HEIGHT }
}

/// The room's furniture (`children`) as pieces placed on the floor, each hull cut to at most
/// `cap` points. A piece without geometry, flat, a duplicate of one already kept (same model and
/// pose to the centimetre), or standing outside the floor is dropped and counted in `report`.
fn draft_pieces(
    children: &[(&Furniture, &Child)],
    room_name: &str,
    floor: &[PlanPoint],
    floor_y: f64,
    cap: usize,
    library: &mut Library,
    report: &mut ImportReport,
) -> Vec<Piece> {
    let mut pieces: Vec<Piece> = Vec::new();
    let mut seen: HashSet<(String, i64, i64, i64)> = HashSet::new();
    for &(item, child) in children {
        let jid = item.jid.clone().unwrap_or_default();
        let (category, super_category) = library.info.get(&jid).cloned().unwrap_or_else(|| {
            (item.category.clone().or_else(|| item.title.clone()).unwrap_or_default(), String::new())
        });
        let Some((points, is_box)) = furniture_points(item, &jid, room_name, library, report) else {
            report.drop_object("no_geometry");
            continue;
        };
        let Some(Placement { pose, local, size, standing }) = place(&points, child, floor_y) else {
            report.drop_object("no_geometry");
            continue;
        };
        if size[1] - local.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min) < FLAT_HEIGHT {
            report.drop_object("flat");
            continue;
        }
        let key = (
            jid.clone(),
            (pose.x * 100.0).round() as i64,
            (pose.z * 100.0).round() as i64,
            (pose.yaw * 100.0).round() as i64,
        );
        if !seen.insert(key) {
            report.drop_object("duplicate");
            continue;
        }
        if !point_in_polygon(pose.position(), floor) {
            report.drop_object("outside_floor");
            continue;
        }
        let points = if is_box { local } else { subsample(local, cap) };
        let category = if category.is_empty() { "object".to_owned() } else { category };
        let movable = movable_category(&category, &super_category);
        let mut piece = Piece { jid, category, movable, points, is_box, pose, size, standing };
        if !piece.is_box && piece.collider().is_none() {
            piece.is_box = true;
        }
        pieces.push(piece);
    }
    pieces
}

/// A furniture item's points in its model's frame and whether they are a box: its model's hull,
/// or where the model is missing, the box of its bbox (warned about), or `None` (warned about)
/// where it has neither.
fn furniture_points(
    item: &Furniture,
    jid: &str,
    room_name: &str,
    library: &mut Library,
    report: &mut ImportReport,
) -> Option<(Vec<[f64; 3]>, bool)> {
    let geometry = if jid.is_empty() { ModelGeometry::Missing } else { library.geometry(jid, &mut report.warnings) };
    match geometry {
        ModelGeometry::Hull(points) => Some((points, false)),
        ModelGeometry::Missing => match item.bbox.as_deref() {
            Some(&[x, y, z]) if x > 0.0 && y > 0.0 && z > 0.0 => {
                if jid.is_empty() {
                    // (A model that is missing was warned about once, by the library.)
                    report
                        .warnings
                        .push(format!("{room_name}: furniture {} has no model id; using a box of its bbox", item.uid));
                }
                Some((box_corners(&[[-x / 2.0, 0.0, -z / 2.0], [x / 2.0, y, z / 2.0]]), true))
            }
            _ => {
                report.warnings.push(format!(
                    "{room_name}: furniture {} ({jid}) has neither a model nor a bbox; dropped",
                    item.uid
                ));
                None
            }
        },
    }
}
