//! Scene compilation: [`CompiledScene::new`] validates a [`Scene`] and builds its collision world
//! (walls, fixed furniture and every movable object's exact and dilated shapes, the robot's
//! bodies, the footprints), then checks the clearances with [`crate::collision`]. Processing over
//! the data of [`crate::world`].

use std::sync::Arc;

use parry3d::bounding_volume::{Aabb, BoundingVolume};
use parry3d::math::{Pose, Rotation, Vector};
use parry3d::shape::{Compound, ConvexPolyhedron, Cuboid, Cylinder, Shape as _, SharedShape, Triangle};

use crate::collision;
use crate::error::{Layout, SceneError};
use crate::geometry::{OrientedRect, PlanPoint, footprint_iou, point_in_polygon, polygon_is_simple, signed_area};
use crate::scene::{Difficulty, Mesh, ObjectPose, Part, SCENE_SCHEMA, Scene, Shape};
use crate::shapes;
use crate::world::{
    CompiledScene, LocalFootprint, MAX_MOVABLE_OBJECTS, MovableGeometry, Obstacle, ROBOT_HEIGHT, ROBOT_RADIUS, Rules,
    WallPiece,
};

fn part_pose(offset: [f64; 3], yaw: f64) -> Pose {
    Pose::from_parts(Vector::new(offset[0], offset[1], offset[2]), Rotation::from_rotation_y(yaw))
}

/// The largest magnitude of any number in a scene (a coordinate or a size in metres, an angle in
/// radians): a kilometre is far beyond any room, and past such magnitudes the collision queries
/// lose every digit of precision (a box of half extent 1e308 made parry's EPA index out of bounds).
pub const MAX_SCENE_NUMBER: f64 = 1_000.0;

/// Checks that every one of `values` is finite and at most [`MAX_SCENE_NUMBER`] in magnitude;
/// `path` names the field in the error.
fn check_number(path: impl FnOnce() -> String, values: &[f64]) -> Result<(), SceneError> {
    if !values.iter().all(|v| v.is_finite()) {
        return Err(SceneError::NonFinite { path: path() });
    }
    match values.iter().find(|v| v.abs() > MAX_SCENE_NUMBER) {
        Some(&value) => Err(SceneError::OutOfRange { path: path(), value, max: MAX_SCENE_NUMBER }),
        None => Ok(()),
    }
}

/// The most floor vertices a scene may have (the built-in rooms have at most 6): the floor's
/// simplicity check takes time quadratic in their number.
pub const MAX_FLOOR_VERTICES: usize = 256;
/// The most wall openings a scene may have.
pub const MAX_OPENINGS: usize = 64;
/// The most fixed objects a scene may have (the built-in scenes have at most 15).
pub const MAX_FIXED_OBJECTS: usize = 256;
/// The most convex parts all of a scene's shapes may have together (the built-in scenes: < 100).
pub const MAX_PARTS: usize = 4_096;
/// The most vertices all of a scene's meshes may have together.
pub const MAX_MESH_VERTICES: usize = 262_144;
/// The most triangles all of a scene's meshes may have together.
pub const MAX_MESH_TRIANGLES: usize = 524_288;

/// The bounds on a scene's size, checked before anything is built from it: what a scene sent
/// inline costs the server (time to check it, memory to hold it) stays bounded.
fn validate_size(scene: &Scene) -> Result<(), SceneError> {
    let shapes = || scene.fixed_objects.iter().map(|o| &o.shape).chain(scene.movable_objects.iter().map(|o| &o.shape));
    let parts = shapes().map(|shape| if let Shape::Parts(parts) = shape { parts.len() } else { 0 }).sum();
    let meshes = || shapes().filter_map(|shape| if let Shape::Mesh(mesh) = shape { Some(mesh) } else { None });
    let checks = [
        ("floor vertices", scene.room.floor.len(), MAX_FLOOR_VERTICES),
        ("wall openings", scene.room.openings.len(), MAX_OPENINGS),
        ("fixed objects", scene.fixed_objects.len(), MAX_FIXED_OBJECTS),
        ("convex parts", parts, MAX_PARTS),
        ("mesh vertices", meshes().map(|m| m.vertices.len()).sum(), MAX_MESH_VERTICES),
        ("mesh triangles", meshes().map(|m| m.triangles.len()).sum(), MAX_MESH_TRIANGLES),
    ];
    match checks.into_iter().find(|&(_, count, max)| count > max) {
        Some((what, count, max)) => Err(SceneError::TooLarge { what, count, max }),
        None => Ok(()),
    }
}

/// The checks of a scene's header and object list, before any geometry: its size
/// (`validate_size`), its schema, a non-empty id, 1 to [`MAX_MOVABLE_OBJECTS`] movable objects,
/// the difficulty of that count, a positive horizon, and object ids that are non-empty and unique.
fn validate_header(scene: &Scene) -> Result<(), SceneError> {
    validate_size(scene)?;
    if scene.schema != SCENE_SCHEMA {
        return Err(SceneError::UnknownSchema { found: scene.schema.clone() });
    }
    if scene.id.trim().is_empty() {
        return Err(SceneError::EmptyField { field: "id".into() });
    }
    let count = scene.movable_objects.len();
    if count == 0 {
        return Err(SceneError::NoMovableObjects);
    }
    if count > MAX_MOVABLE_OBJECTS {
        return Err(SceneError::TooManyMovableObjects { count });
    }
    if Difficulty::for_object_count(count) != Some(scene.difficulty) {
        return Err(SceneError::DifficultyMismatch { difficulty: scene.difficulty.as_str(), count });
    }
    if scene.horizon == 0 {
        return Err(SceneError::ZeroHorizon);
    }
    let mut ids = std::collections::HashSet::new();
    for id in scene.fixed_objects.iter().map(|o| &o.id).chain(scene.movable_objects.iter().map(|o| &o.id)) {
        if id.is_empty() {
            return Err(SceneError::EmptyField { field: "object id".into() });
        }
        if !ids.insert(id.as_str()) {
            return Err(SceneError::DuplicateId { id: id.clone() });
        }
    }
    Ok(())
}

/// The walls and the fixed objects as one collision compound, each part's owner, and the fixed
/// objects' footprints.
struct StaticWorld {
    static_world: Compound,
    static_part_owner: Vec<Obstacle>,
    fixed_footprints: Vec<OrientedRect>,
}

/// Builds the [`StaticWorld`] of `scene`: its wall pieces' colliders, then each fixed object's exact
/// parts, checking that its pose is finite and its footprint's centre inside the floor.
fn static_world(
    scene: &Scene,
    floor: &[PlanPoint],
    wall_pieces: &[WallPiece],
    margin: f64,
) -> Result<StaticWorld, SceneError> {
    let mut static_parts: Vec<(Pose, SharedShape)> = Vec::new();
    let mut static_part_owner = Vec::new();
    for piece in wall_pieces {
        static_parts.push(shapes::wall_collider(piece));
        static_part_owner.push(Obstacle::Wall(piece.wall));
    }
    let mut fixed_footprints = Vec::new();
    for (i, object) in scene.fixed_objects.iter().enumerate() {
        let path = format!("fixed_objects[{i}]");
        check_number(|| format!("{path}.pose"), &[object.pose.x, object.pose.z, object.pose.yaw])?;
        let parts = build_parts(&object.id, &path, &object.shape, margin, true)?;
        let footprint = local_footprint(&parts.local_aabb).at(&object.pose);
        if !point_in_polygon(footprint.center, floor) {
            return Err(SceneError::OutsideRoom { object: object.id.clone(), layout: Layout::Initial });
        }
        fixed_footprints.push(footprint);
        let placement = shapes::object_pose(&object.pose);
        for (pose, shape) in parts.exact {
            static_parts.push((placement * pose, shape));
            static_part_owner.push(Obstacle::Fixed(i));
        }
    }
    Ok(StaticWorld { static_world: Compound::new(static_parts), static_part_owner, fixed_footprints })
}

/// The geometry of each movable object of `scene` (its exact obstacle, its dilated carried parts
/// and its footprint), checking that its poses are finite and its footprint's centre inside the
/// floor in both layouts.
fn movable_geometry(scene: &Scene, floor: &[PlanPoint], margin: f64) -> Result<Vec<MovableGeometry>, SceneError> {
    let mut movables = Vec::with_capacity(scene.movable_objects.len());
    for (i, object) in scene.movable_objects.iter().enumerate() {
        let path = format!("movable_objects[{i}]");
        check_number(|| format!("{path}.pose"), &[object.pose.x, object.pose.z, object.pose.yaw])?;
        check_number(|| format!("{path}.target"), &[object.target.x, object.target.z, object.target.yaw])?;
        let parts = build_parts(&object.id, &path, &object.shape, margin, false)?;
        let footprint = local_footprint(&parts.local_aabb);
        for (layout, pose) in [(Layout::Initial, &object.pose), (Layout::Target, &object.target)] {
            if !point_in_polygon(footprint.at(pose).center, floor) {
                return Err(SceneError::OutsideRoom { object: object.id.clone(), layout });
            }
        }
        movables.push(MovableGeometry {
            obstacle: Compound::new(parts.exact),
            carried_parts: parts.dilated,
            footprint,
        });
    }

    Ok(movables)
}

/// Exact and dilated convex parts of a shape, in the object's frame.
struct PartShapes {
    exact: Vec<(Pose, SharedShape)>,
    dilated: Vec<(Pose, SharedShape)>,
    local_aabb: Aabb,
}

/// Builds a shape's convex parts. A mesh becomes its triangles for a fixed object
/// (`as_triangles`) and its convex hull for a movable one.
fn build_parts(
    object: &str,
    path: &str,
    shape: &Shape,
    margin: f64,
    as_triangles: bool,
) -> Result<PartShapes, SceneError> {
    let invalid = |reason: String| SceneError::InvalidShape { object: object.to_owned(), reason };
    let (exact, dilated) = match shape {
        Shape::Parts(parts) => primitive_parts(parts, path, margin, &invalid)?,
        Shape::Mesh(mesh) => mesh_parts(mesh, path, margin, as_triangles, &invalid)?,
    };
    let mut local_aabb = Aabb::new_invalid();
    for (pose, shape) in &exact {
        local_aabb.merge(&shape.compute_aabb(pose));
    }
    Ok(PartShapes { exact, dilated, local_aabb })
}

/// A shape's exact parts and the same dilated by the collision margin, each with its pose.
type PartPairs = (Vec<(Pose, SharedShape)>, Vec<(Pose, SharedShape)>);

/// The parts of a shape made of boxes, cylinders and convex hulls, each checked (finite, positive
/// sizes, a hull with volume); `invalid` makes the error of a bad part.
fn primitive_parts(
    parts: &[Part],
    path: &str,
    margin: f64,
    invalid: &dyn Fn(String) -> SceneError,
) -> Result<PartPairs, SceneError> {
    let mut exact = Vec::new();
    let mut dilated = Vec::new();
    if parts.is_empty() {
        return Err(invalid("`shape.parts` is empty: give at least one box, cylinder or convex hull".into()));
    }
    for (i, part) in parts.iter().enumerate() {
        let (offset, yaw) = part.placement();
        check_number(|| format!("{path}.shape.parts[{i}].offset"), &offset)?;
        check_number(|| format!("{path}.shape.parts[{i}].yaw"), &[yaw])?;
        let pose = part_pose(offset, yaw);
        let (e, d) = match part {
            Part::Box { half_extents, .. } => {
                check_number(|| format!("{path}.shape.parts[{i}].half_extents"), half_extents)?;
                if half_extents.iter().any(|&h| h <= 0.0) {
                    return Err(invalid(format!("part {i}: box half extents {half_extents:?} must all be positive")));
                }
                let [x, y, z] = *half_extents;
                (SharedShape::new(Cuboid::new(Vector::new(x, y, z))), SharedShape::round_cuboid(x, y, z, margin))
            }
            Part::Cylinder { radius, half_height, .. } => {
                check_number(|| format!("{path}.shape.parts[{i}]"), &[*radius, *half_height])?;
                if *radius <= 0.0 || *half_height <= 0.0 {
                    return Err(invalid(format!("part {i}: cylinder radius and half height must be positive")));
                }
                (
                    SharedShape::new(Cylinder::new(*half_height, *radius)),
                    SharedShape::round_cylinder(*half_height, *radius, margin),
                )
            }
            Part::ConvexHull { points, .. } => {
                for (j, p) in points.iter().enumerate() {
                    check_number(|| format!("{path}.shape.parts[{i}].points[{j}]"), p)?;
                }
                let points: Vec<Vector> = points.iter().map(|p| Vector::new(p[0], p[1], p[2])).collect();
                hull_pair(&points, margin).ok_or_else(|| {
                        invalid(format!("part {i}: the convex hull of its points is degenerate (give at least 4 points not in one plane)"))
                    })?
            }
        };
        exact.push((pose, e));
        dilated.push((pose, d));
    }
    Ok((exact, dilated))
}

/// The parts of a mesh: its triangles (`as_triangles`, a fixed object's exact surface) or its
/// convex hull (a movable object's), the vertices checked finite and the triangles' indices in
/// range; `invalid` makes the error of a bad mesh.
fn mesh_parts(
    mesh: &Mesh,
    path: &str,
    margin: f64,
    as_triangles: bool,
    invalid: &dyn Fn(String) -> SceneError,
) -> Result<PartPairs, SceneError> {
    let mut exact = Vec::new();
    let mut dilated = Vec::new();
    for (j, p) in mesh.vertices.iter().enumerate() {
        check_number(|| format!("{path}.shape.mesh.vertices[{j}]"), p)?;
    }
    if mesh.triangles.is_empty() {
        return Err(invalid("`shape.mesh.triangles` is empty".into()));
    }
    let vertices: Vec<Vector> = mesh.vertices.iter().map(|p| Vector::new(p[0], p[1], p[2])).collect();
    for (t, tri) in mesh.triangles.iter().enumerate() {
        if let Some(&bad) = tri.iter().find(|&&v| v as usize >= vertices.len()) {
            return Err(invalid(format!(
                "mesh triangle {t} uses vertex {bad}, but the mesh has only {} vertices",
                vertices.len()
            )));
        }
    }
    if as_triangles {
        for tri in &mesh.triangles {
            let [a, b, c] = tri.map(|v| vertices[v as usize]);
            if (b - a).cross(c - a).length() <= 1e-12 {
                continue; // A degenerate triangle has no surface to hit.
            }
            exact.push((Pose::IDENTITY, SharedShape::new(Triangle::new(a, b, c))));
            dilated.push((Pose::IDENTITY, SharedShape::round_triangle(a, b, c, margin)));
        }
        if exact.is_empty() {
            return Err(invalid("every mesh triangle is degenerate (zero area)".into()));
        }
    } else {
        let (e, d) = hull_pair(&vertices, margin).ok_or_else(|| {
            invalid("the convex hull of the mesh is degenerate (flat or fewer than 4 vertices)".into())
        })?;
        exact.push((Pose::IDENTITY, e));
        dilated.push((Pose::IDENTITY, d));
    }
    Ok((exact, dilated))
}

/// The exact and dilated convex hulls of `points`, or `None` if the hull has no volume (fewer
/// than four points, or all in one plane).
fn hull_pair(points: &[Vector], margin: f64) -> Option<(SharedShape, SharedShape)> {
    let hull = ConvexPolyhedron::from_convex_hull(points)?;
    if hull.mass_properties(1.0).mass() <= 1e-9 {
        return None;
    }
    let dilated = SharedShape::round_convex_hull(points, margin)?;
    Some((SharedShape::new(hull), dilated))
}

fn local_footprint(aabb: &Aabb) -> LocalFootprint {
    LocalFootprint {
        center: PlanPoint::new(0.5 * (aabb.mins.x + aabb.maxs.x), 0.5 * (aabb.mins.z + aabb.maxs.z)),
        half_x: 0.5 * (aabb.maxs.x - aabb.mins.x),
        half_z: 0.5 * (aabb.maxs.z - aabb.mins.z),
    }
}

/// Each opening on a wall of the floor, within its length and height, and clear of the other
/// openings of its wall.
fn validate_openings(scene: &Scene, floor: &[PlanPoint]) -> Result<(), SceneError> {
    let n = floor.len();
    let height = scene.room.wall_height;
    for (index, opening) in scene.room.openings.iter().enumerate() {
        let invalid = |reason: String| SceneError::InvalidOpening { index, reason };
        check_number(
            || format!("room.openings[{index}]"),
            &[opening.offset, opening.width, opening.bottom, opening.top],
        )?;
        if opening.wall >= n {
            return Err(invalid(format!(
                "wall {} does not exist: the floor has {n} edges (walls 0..{n})",
                opening.wall
            )));
        }
        let length = floor[opening.wall].distance(floor[(opening.wall + 1) % n]);
        if opening.offset < 0.0 || opening.width <= 0.0 || opening.offset + opening.width > length {
            return Err(invalid(format!(
                "it spans {}..{} m along wall {}, which is {length:.3} m long",
                opening.offset,
                opening.offset + opening.width,
                opening.wall
            )));
        }
        if !(opening.bottom >= 0.0 && opening.top > opening.bottom && opening.top <= height) {
            return Err(invalid(format!(
                "bottom {} and top {} must satisfy 0 <= bottom < top <= wall height {height}",
                opening.bottom, opening.top
            )));
        }
    }
    for (wall, openings) in shapes::openings_by_wall(n, &scene.room.openings).iter().enumerate() {
        for pair in openings.windows(2) {
            if pair[1].1.offset < pair[0].1.offset + pair[0].1.width {
                return Err(SceneError::InvalidOpening {
                    index: pair[1].0,
                    reason: format!("it overlaps opening {} on wall {wall}", pair[0].0),
                });
            }
        }
    }
    Ok(())
}

fn validate_room(scene: &Scene) -> Result<Vec<PlanPoint>, SceneError> {
    let room = &scene.room;
    for (i, p) in room.floor.iter().enumerate() {
        check_number(|| format!("room.floor[{i}]"), p)?;
    }
    check_number(|| "room.wall_height".into(), &[room.wall_height])?;
    check_number(|| "room.wall_thickness".into(), &[room.wall_thickness])?;
    let invalid = |reason: String| Err(SceneError::InvalidRoom { reason });
    let floor = room.floor_points();
    if floor.len() < 3 {
        return invalid(format!("`room.floor` has {} vertices: a floor polygon needs at least 3", floor.len()));
    }
    if !polygon_is_simple(&floor) {
        return invalid("`room.floor` is not a simple polygon: its edges cross, touch or repeat a vertex".into());
    }
    if signed_area(&floor).abs() < 1.0 {
        return invalid("`room.floor` encloses less than 1 m²".into());
    }
    if room.wall_height < ROBOT_HEIGHT || room.wall_height > 20.0 {
        return invalid(format!(
            "`room.wall_height` {} must be between the robot's height {ROBOT_HEIGHT} m and 20 m",
            room.wall_height
        ));
    }
    if !(0.01..=1.0).contains(&room.wall_thickness) {
        return invalid(format!("`room.wall_thickness` {} must be between 0.01 and 1 m", room.wall_thickness));
    }
    Ok(floor)
}

impl CompiledScene {
    /// Validates `scene` under `rules` and builds its collision world.
    ///
    /// Checks, each with its own [`SceneError`]: schema, finite numbers, room and openings,
    /// non-empty shapes, unique ids, 1–6 movable objects matching the difficulty, every
    /// object's footprint centre inside the room, movable objects' 3D shapes clear (by the
    /// collision margin) of walls, fixed objects and each other in both layouts, the agent
    /// inside the room and clear of everything, not every object already placed, and a positive
    /// horizon. (A footprint's corners may reach past the floor polygon — a round stool turned
    /// 45° has a bounding box wider than itself — but never its 3D shape, which the wall
    /// clearance check keeps inside.)
    pub fn new(scene: Scene, rules: Rules) -> Result<Self, SceneError> {
        let compiled = Self::for_backward_construction(scene, rules)?;
        compiled.check_not_solved()?;
        Ok(compiled)
    }

    /// Like [`CompiledScene::new`], but accepts an initial layout in which every object is
    /// already placed: the starting point of backward construction (SPEC §7), where the
    /// generator begins at the target layout and moves objects away. Every other check applies.
    pub fn for_backward_construction(scene: Scene, rules: Rules) -> Result<Self, SceneError> {
        rules.validate()?;
        validate_header(&scene)?;
        let floor = validate_room(&scene)?;
        validate_openings(&scene, &floor)?;
        let room = &scene.room;
        let wall_pieces = shapes::wall_pieces(&floor, room.wall_thickness, room.wall_height, &room.openings);
        let margin = rules.collision_margin;
        let StaticWorld { static_world, static_part_owner, fixed_footprints } =
            static_world(&scene, &floor, &wall_pieces, margin)?;
        let movables = movable_geometry(&scene, &floor, margin)?;
        let agent = PlanPoint::new(scene.agent.x, scene.agent.z);
        check_number(|| "agent".into(), &[agent.x, agent.z])?;
        if !point_in_polygon(agent, &floor) {
            return Err(SceneError::AgentOutsideRoom);
        }
        let initial_distance = scene
            .movable_objects
            .iter()
            .zip(&movables)
            .map(|(o, g)| g.footprint.at(&o.pose).center.distance(g.footprint.at(&o.target).center))
            .sum();
        let compiled = CompiledScene {
            robot_carried: SharedShape::round_cylinder(ROBOT_HEIGHT / 2.0, ROBOT_RADIUS, margin),
            robot_exact: SharedShape::cylinder(ROBOT_HEIGHT / 2.0, ROBOT_RADIUS),
            scene,
            rules,
            floor,
            wall_pieces,
            static_world,
            static_part_owner,
            fixed_footprints,
            movables,
            initial_distance,
        };
        compiled.check_clearances()?;
        Ok(compiled)
    }

    /// Movable objects must be clear of everything by the margin in both layouts, and the agent
    /// clear of everything in the initial layout.
    fn check_clearances(&self) -> Result<(), SceneError> {
        let margin = self.rules.collision_margin;
        for layout in [Layout::Initial, Layout::Target] {
            let poses: Vec<ObjectPose> = self
                .scene
                .movable_objects
                .iter()
                .map(|o| if layout == Layout::Initial { o.pose } else { o.target })
                .collect();
            for (i, pose) in poses.iter().enumerate() {
                if let Some(other) = collision::object_obstruction(self, &poses, i, pose) {
                    return Err(SceneError::Overlap {
                        object: self.scene.movable_objects[i].id.clone(),
                        other: self.obstacle_name(other),
                        layout,
                        margin,
                    });
                }
            }
            if layout == Layout::Initial {
                let robot = collision::Body::robot(PlanPoint::new(self.scene.agent.x, self.scene.agent.z));
                if let Some(other) = collision::obstruction(self, &poses, &robot) {
                    return Err(SceneError::AgentInCollision { obstacle: self.obstacle_name(other) });
                }
            }
        }
        Ok(())
    }

    fn check_not_solved(&self) -> Result<(), SceneError> {
        let placed = self.scene.movable_objects.iter().zip(&self.movables).all(|(o, g)| {
            footprint_iou(&g.footprint.at(&o.pose), &g.footprint.at(&o.target)) > self.rules.placement_iou
        });
        if placed { Err(SceneError::AlreadySolved) } else { Ok(()) }
    }

    /// Validates and compiles a scene under the default rules, behind an `Arc`.
    pub fn shared(scene: Scene) -> Result<Arc<Self>, SceneError> {
        Self::new(scene, Rules::default()).map(Arc::new)
    }
}
