//! Import of 3D-FRONT houses as ESRP scene pairs, for users who have 3D-FRONT and 3D-FUTURE.
//!
//! # What it reads
//!
//! - `--front DIR`: the house files `<uuid>.json` of 3D-FRONT (every `*.json` directly in the
//!   directory, in name order). From each it reads `furniture[]` (`uid`, `jid`, `category`,
//!   `title`, `bbox` — the model's size), `mesh[]` (`uid`, `type`, flat `xyz`, flat `faces`) and
//!   `scene.room[]` (`type`, `instanceid`, `children[]` with `ref`, `pos`, `rot`, `scale`).
//!   Unknown fields are ignored and missing optional ones defaulted; a file that is not JSON
//!   of that shape is a [`FrontError::HouseJson`] naming it.
//! - `--future DIR`: 3D-FUTURE, either the `3D-FUTURE-model` folder itself or its parent:
//!   `model_info.json` (`model_id`, `super-category`, `category`) and `<jid>/raw_model.obj`.
//!
//! Units are metres and the world is y-up, as in ESRP (SPEC §1). A child's `rot` is a unit
//! quaternion in `[x, y, z, w]` order, as the official 3D-FRONT-ToolBox reads it; the child's
//! geometry is `pos + rot · (scale ⊙ v)`. Rooms' own `pos`/`rot`/`scale` are the identity in
//! the released data and are ignored.
//!
//! # How a room becomes a scene
//!
//! - **Floor**: the room's `Floor` meshes projected on the x–z plane; the outline is the
//!   boundary of the union of their triangles (T-junctions split, shared edges cancelled),
//!   collinear points removed. Disjoint pieces keep the largest outline; an outline that is not
//!   a simple polygon falls back to the bounding rectangle of the floor, with a warning.
//!   Rooms without a floor mesh are skipped (`no_floor_mesh`).
//! - **Walls**: esrp-core draws walls on the floor polygon's edges; thickness
//!   [`WALL_THICKNESS`], height the top of the room's `Wall*` meshes above the floor when that
//!   is between 2.2 and 4 m, else [`DEFAULT_WALL_HEIGHT`].
//! - **Openings**: `Door` and `Window` meshes whose plan points lie within 0.35 m of one floor
//!   edge become openings of that wall (clipped to the wall; overlapping ones dropped).
//! - **Furniture**: every child that refers to a `furniture[]` entry is one object. Its pose is
//!   `pos` on the plan and the yaw of `rot` ([`yaw_from_quaternion`]); its shape is built in a
//!   frame turned by that yaw, so any tilt and the scale stay in the geometry. The shape is the
//!   convex hull of the model's vertices as one [`Part::ConvexHull`] of at most
//!   [`MAX_HULL_POINTS`] points (fewer when the room has many objects, so that the room stays
//!   under [`crate::layout::TRIANGLE_BUDGET`] triangles); a model whose OBJ is missing or
//!   unreadable falls back to a [`Part::Box`] of the furniture's `bbox` with a warning. The
//!   frame is centred on the footprint, and an object standing on the floor (lowest point
//!   within 5 cm of it) is shifted to stand exactly at `y = 0`; higher objects (wall cabinets,
//!   pendant lamps, things on tables) keep their height and can only be fixed.
//! - **Dropped objects** (counted by reason in [`ImportReport::objects_dropped`]): no geometry
//!   at all (`no_geometry`: no OBJ and no `bbox`), flat ones such as rugs (`flat`, under 3 cm
//!   high: they would block every object on them), exact duplicates (`duplicate`: same model at
//!   the same pose, common in 3D-FRONT) and ones whose footprint centre is outside the floor
//!   (`outside_floor`).
//! - **Movable pieces**: a piece is carryable when its 3D-FUTURE category maps onto an ESRP
//!   category ([`movable_category`]: cabinets, shelves, desks and nightstands; chairs;
//!   armchairs and loveseats; piers and stools; side, coffee and end tables, plants and floor
//!   lamps) and it stands on the floor, at most [`MAX_CARRY_SIZE`] across and
//!   [`MAX_CARRY_HEIGHT`] high. Each attempt draws how many (1–6, weighted like the benchmark's
//!   mix) and which (weighted by the paper's category shares) from a [`Dice`] keyed by the
//!   room's id. A chosen piece must be clear of the walls and of every other object by
//!   [`CLEARANCE`] (3D-FRONT pieces often touch or overlap); if it is not, it is nudged up to
//!   0.3 m in 16 directions, and if no nudge frees it, it stays fixed
//!   ([`ImportReport::movable_overlapping`]). Everything not chosen is fixed.
//! - **Skipped rooms** (counted by reason in [`ImportReport::rooms_skipped`]): no floor mesh,
//!   floor under [`MIN_FLOOR_AREA`] (`too_small`), free floor under [`MIN_FREE_FLOOR`]
//!   (`no_free_floor`), no carryable piece (`no_carryable`), every carryable piece stuck
//!   (`movables_overlap`), or backward construction failing in every attempt
//!   (`construction_<reason>`).
//! - **Scenes**: the target layout goes through the same backward construction as the
//!   procedural benchmark ([`crate::backward::construct`]), retried with new attempt numbers;
//!   the id is `3dfront/<house-uuid>/<room-instanceid>`, the split by [`split_for_id`], the
//!   room type 3D-FRONT's.
//!
//! Nothing is written here: [`import`] returns the scenes, and the caller writes them (the
//! `files` module writes atomically), so a malformed input never leaves half a dataset.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};

use esrp_core::geometry::{PlanPoint, point_in_polygon, polygon_is_simple, signed_area};
use esrp_core::{
    AgentStart, Difficulty, FixedObject, Heading, MovableCategory, MovableObject, ObjectPose, Opening, OpeningKind,
    Part, Room, SCENE_SCHEMA, Scene, Shape,
};
use esrp_core::{collision, parry3d};
use parry3d::math::{Pose, Vector};
use parry3d::shape::SharedShape;
use serde::Deserialize;

use crate::backward::{ConstructionParams, Rejection, construct};
use crate::benchmark::{OBJECT_COUNT_MIX, split_for_id};
use crate::dice::Dice;
use crate::layout::{CATEGORY_SHARES, TRIANGLE_BUDGET};

/// Wall thickness of imported rooms, metres.
pub const WALL_THICKNESS: f64 = 0.12;
/// Wall height when the room's wall meshes give none in 2.2–4 m, metres.
pub const DEFAULT_WALL_HEIGHT: f64 = 2.8;
/// The most points of one object's convex hull.
pub const MAX_HULL_POINTS: usize = 64;
/// The largest footprint side of a carryable piece, metres.
pub const MAX_CARRY_SIZE: f64 = 1.2;
/// The greatest height of a carryable piece, metres.
pub const MAX_CARRY_HEIGHT: f64 = 1.3;
/// The clearance a movable piece keeps to walls and other objects in the target layout,
/// metres: twice esrp-core's collision margin.
pub const CLEARANCE: f64 = 0.02;
/// Rooms with less floor than this are skipped, m².
pub const MIN_FLOOR_AREA: f64 = 4.0;
/// Rooms with less floor than this outside the footprints of standing furniture are skipped,
/// m².
pub const MIN_FREE_FLOOR: f64 = 2.0;
/// An object whose lowest point is at most this above the floor stands on it, metres.
const STANDING_TOLERANCE: f64 = 0.05;
/// Objects lower than this are flat (rugs) and dropped, metres.
const FLAT_HEIGHT: f64 = 0.03;
/// Nudge distances tried for an overlapping movable piece, metres.
const NUDGES: [f64; 7] = [0.03, 0.06, 0.1, 0.15, 0.2, 0.25, 0.3];

/// Something wrong with the input; each variant names the file and says how to fix it.
#[derive(Debug, thiserror::Error)]
pub enum FrontError {
    /// A file or directory could not be read.
    #[error("cannot read {path}: {source}; check that it exists and is readable")]
    Io {
        /// The path.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A house file is not 3D-FRONT JSON.
    #[error(
        "{path} is not a 3D-FRONT house file: {message}; re-extract it from the 3D-FRONT archive or remove it from the directory"
    )]
    HouseJson {
        /// The house file.
        path: PathBuf,
        /// What is wrong, with line and column.
        message: String,
    },
    /// `model_info.json` is not 3D-FUTURE's model list.
    #[error(
        "{path} is not 3D-FUTURE's model_info.json (a list of {{model_id, super-category, category}}): {message}; re-extract it from the 3D-FUTURE archive"
    )]
    ModelInfo {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// No `model_info.json` was found.
    #[error(
        "no model_info.json in {dir} or {dir}/3D-FUTURE-model: pass the 3D-FUTURE directory (the one holding model_info.json and the <jid>/raw_model.obj folders) as --future"
    )]
    MissingModelInfo {
        /// The directory given.
        dir: PathBuf,
    },
    /// The 3D-FRONT directory holds no house file.
    #[error("no house files (*.json) in {dir}: pass the 3D-FRONT directory holding the <uuid>.json files as --front")]
    NoHouses {
        /// The directory given.
        dir: PathBuf,
    },
    /// An OBJ file could not be parsed.
    #[error("{path}, line {line}: {message}")]
    Obj {
        /// The OBJ file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        message: String,
    },
}

/// Options of an import.
#[derive(Clone, Debug)]
pub struct ImportOptions {
    /// Seed of the choice of movable pieces and of backward construction (default 0).
    pub seed: u64,
    /// Attempts per room (new choice and construction each) before it is skipped (default 8).
    pub max_attempts: u64,
    /// Read at most this many houses, in name order (default: all).
    pub max_houses: Option<usize>,
}

impl Default for ImportOptions {
    fn default() -> Self {
        Self { seed: 0, max_attempts: 8, max_houses: None }
    }
}

/// What an import produced and what it left out.
#[derive(Clone, Debug, Default)]
pub struct ImportReport {
    /// The scene pairs, each validated and replayed to success, in house and room order.
    pub scenes: Vec<Scene>,
    /// House files read.
    pub houses: usize,
    /// Rooms seen.
    pub rooms_seen: usize,
    /// Rooms that became a scene.
    pub rooms_imported: usize,
    /// Rooms skipped, by reason (see the module documentation).
    pub rooms_skipped: BTreeMap<String, usize>,
    /// Furniture objects dropped, by reason (see the module documentation).
    pub objects_dropped: BTreeMap<String, usize>,
    /// Movable pieces moved apart from what they overlapped (in scenes that were imported).
    pub objects_nudged: usize,
    /// Carryable pieces kept fixed because no nudge freed them (in scenes that were imported).
    pub movable_overlapping: usize,
    /// Warnings: missing or unreadable models, floor fallbacks, ...
    pub warnings: Vec<String>,
}

impl ImportReport {
    fn skip(&mut self, reason: &str) {
        *self.rooms_skipped.entry(reason.to_owned()).or_insert(0) += 1;
    }

    fn drop_object(&mut self, reason: &str) {
        *self.objects_dropped.entry(reason.to_owned()).or_insert(0) += 1;
    }
}

// ---------------------------------------------------------------------------------------------
// The input formats.

#[derive(Debug, Deserialize)]
struct House {
    #[serde(default)]
    furniture: Vec<Furniture>,
    #[serde(default)]
    mesh: Vec<ArchMesh>,
    scene: HouseScene,
}

#[derive(Debug, Deserialize)]
struct Furniture {
    uid: String,
    #[serde(default)]
    jid: Option<String>,
    #[serde(default)]
    title: Option<String>,
    #[serde(default)]
    category: Option<String>,
    #[serde(default)]
    bbox: Option<Vec<f64>>,
}

#[derive(Debug, Deserialize)]
struct ArchMesh {
    uid: String,
    #[serde(rename = "type", default)]
    kind: String,
    #[serde(default)]
    xyz: Vec<f64>,
    #[serde(default)]
    faces: Vec<u32>,
}

#[derive(Debug, Deserialize)]
struct HouseScene {
    #[serde(default)]
    room: Vec<FrontRoom>,
}

#[derive(Debug, Deserialize)]
struct FrontRoom {
    #[serde(rename = "type", default)]
    room_type: String,
    #[serde(rename = "instanceid", default)]
    instance_id: String,
    #[serde(default)]
    children: Vec<Child>,
}

#[derive(Clone, Debug, Deserialize)]
struct Child {
    #[serde(rename = "ref")]
    reference: String,
    #[serde(default)]
    pos: [f64; 3],
    #[serde(default = "identity_quaternion")]
    rot: [f64; 4],
    #[serde(default = "unit_scale")]
    scale: [f64; 3],
}

fn identity_quaternion() -> [f64; 4] {
    [0.0, 0.0, 0.0, 1.0]
}

fn unit_scale() -> [f64; 3] {
    [1.0; 3]
}

#[derive(Debug, Deserialize)]
struct ModelInfo {
    model_id: String,
    #[serde(rename = "super-category", default)]
    super_category: Option<String>,
    #[serde(default)]
    category: Option<String>,
}

/// A Wavefront OBJ mesh: vertex positions and triangles (polygons fanned).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ObjMesh {
    /// Vertex positions (`v` lines).
    pub vertices: Vec<[f64; 3]>,
    /// Triangles as 0-based indices into `vertices` (`f` lines; `a`, `a/b`, `a//c` and
    /// `a/b/c` references, negative ones relative to the end, polygons fanned from their first
    /// vertex).
    pub triangles: Vec<[u32; 3]>,
}

/// Parses a Wavefront OBJ text; `path` only names the file in errors. Lines other than `v` and
/// `f` (normals, texture coordinates, groups, materials) are ignored.
pub fn parse_obj(text: &str, path: &Path) -> Result<ObjMesh, FrontError> {
    let mut mesh = ObjMesh::default();
    for (number, line) in text.lines().enumerate() {
        let error = |message: String| FrontError::Obj { path: path.to_owned(), line: number + 1, message };
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let mut xyz = [0.0_f64; 3];
                for value in &mut xyz {
                    let word = words.next().ok_or_else(|| error("a `v` line needs three coordinates".into()))?;
                    *value = word.parse().map_err(|_| error(format!("`{word}` is not a number")))?;
                    if !value.is_finite() {
                        return Err(error(format!("coordinate `{word}` is not finite")));
                    }
                }
                mesh.vertices.push(xyz);
            }
            Some("f") => {
                let mut corners = Vec::new();
                for word in words {
                    let first = word.split('/').next().unwrap_or_default();
                    let index: i64 = first.parse().map_err(|_| {
                        error(format!("`{word}` is not a vertex reference (`a`, `a/b`, `a//c`, `a/b/c`)"))
                    })?;
                    let count = mesh.vertices.len() as i64;
                    let resolved = if index > 0 { index - 1 } else { count + index };
                    if index == 0 || !(0..count).contains(&resolved) {
                        return Err(error(format!("vertex {index} does not exist: {count} vertices so far")));
                    }
                    corners.push(resolved as u32);
                }
                if corners.len() < 3 {
                    return Err(error(format!("a face needs at least 3 vertices, this one has {}", corners.len())));
                }
                for k in 1..corners.len() - 1 {
                    mesh.triangles.push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            _ => {}
        }
    }
    if mesh.vertices.is_empty() {
        return Err(FrontError::Obj { path: path.to_owned(), line: 0, message: "the file has no vertices".into() });
    }
    Ok(mesh)
}

// ---------------------------------------------------------------------------------------------
// Rotations.

/// Rotates `v` by the unit quaternion `q = [x, y, z, w]`.
fn rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let [x, y, z, w] = q;
    // v' = v + 2w (q × v) + 2 q × (q × v)
    let t = [2.0 * (y * v[2] - z * v[1]), 2.0 * (z * v[0] - x * v[2]), 2.0 * (x * v[1] - y * v[0])];
    [
        v[0] + w * t[0] + (y * t[2] - z * t[1]),
        v[1] + w * t[1] + (z * t[0] - x * t[2]),
        v[2] + w * t[2] + (x * t[1] - y * t[0]),
    ]
}

fn normalized(q: [f64; 4]) -> [f64; 4] {
    let norm = q.iter().map(|c| c * c).sum::<f64>().sqrt();
    if norm.is_finite() && norm > 1e-12 { q.map(|c| c / norm) } else { identity_quaternion() }
}

/// The yaw (SPEC §1: right-handed about +y, local `+x` to `(cos yaw, 0, −sin yaw)`) of a
/// 3D-FRONT rotation `[x, y, z, w]`, normalised first: the heading of the rotated local `+x`
/// projected on the plan (of the rotated `+z` when `+x` points straight up or down). In
/// `(−π, π]`; a zero quaternion is the identity.
pub fn yaw_from_quaternion(rot: [f64; 4]) -> f64 {
    let q = normalized(rot);
    let x_axis = rotate(q, [1.0, 0.0, 0.0]);
    if x_axis[0].hypot(x_axis[2]) > 1e-6 {
        (-x_axis[2]).atan2(x_axis[0])
    } else {
        // Local +z goes to (sin yaw, 0, cos yaw).
        let z_axis = rotate(q, [0.0, 0.0, 1.0]);
        z_axis[0].atan2(z_axis[2])
    }
}

// ---------------------------------------------------------------------------------------------
// Categories.

/// The ESRP category of a 3D-FUTURE model by its `category` and `super-category` (or the
/// house file's own category or title), or `None` for furniture that is never carried (beds,
/// wardrobes, large sofas, dining tables, ceiling and wall lamps, ...). Size is checked apart.
pub fn movable_category(category: &str, super_category: &str) -> Option<MovableCategory> {
    let c = category.to_lowercase();
    let s = super_category.to_lowercase();
    let has = |words: &[&str]| words.iter().any(|w| c.contains(w));
    if has(&["stool", "pier", "ottoman"]) {
        return Some(MovableCategory::PierStool);
    }
    if has(&["armchair", "loveseat", "lazy sofa", "single sofa", "one-seat"]) {
        return Some(MovableCategory::Sofa);
    }
    if has(&["bed", "wardrobe", "sofa", "dining table", "bar", "pendant", "ceiling", "wall lamp"]) {
        return None;
    }
    if has(&["chair"]) {
        return Some(MovableCategory::Chair);
    }
    if has(&["cabinet", "shelf", "desk", "nightstand", "bookcase", "drawer", "chest", "tv stand", "sideboard"])
        || has(&["console", "dressing table"])
    {
        return Some(MovableCategory::CabinetShelfDesk);
    }
    if has(&["coffee table", "side table", "end table", "tea table", "plant", "flower", "vase"])
        || has(&["floor lamp", "table lamp"])
    {
        return Some(MovableCategory::Others);
    }
    match s.as_str() {
        "cabinet/shelf/desk" => Some(MovableCategory::CabinetShelfDesk),
        "chair" => Some(MovableCategory::Chair),
        "pier/stool" => Some(MovableCategory::PierStool),
        _ => None,
    }
}

// ---------------------------------------------------------------------------------------------
// Geometry helpers.

fn plan(p: [f64; 3]) -> PlanPoint {
    PlanPoint::new(p[0], p[2])
}

fn bounds(points: impl IntoIterator<Item = [f64; 3]>) -> Option<([f64; 3], [f64; 3])> {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    let mut any = false;
    for p in points {
        any = true;
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    any.then_some((lo, hi))
}

/// Distance from `p` to segment `a`–`b` and the parameter of the closest point.
fn segment_projection(p: PlanPoint, a: PlanPoint, b: PlanPoint) -> (f64, f64) {
    let (dx, dz) = (b.x - a.x, b.z - a.z);
    let length2 = dx * dx + dz * dz;
    let t = if length2 > 0.0 { ((p.x - a.x) * dx + (p.z - a.z) * dz) / length2 } else { 0.0 };
    let tc = t.clamp(0.0, 1.0);
    (p.distance(PlanPoint::new(a.x + tc * dx, a.z + tc * dz)), t)
}

/// The outline of the union of plan triangles as one counter-clockwise simple polygon, with
/// the number of outlines found; `None` if the largest outline is not a simple polygon.
fn floor_outline(triangles: &[[PlanPoint; 3]]) -> Option<(Vec<PlanPoint>, usize)> {
    // Weld vertices to the millimetre.
    let mut ids: HashMap<(i64, i64), u32> = HashMap::new();
    let mut points: Vec<PlanPoint> = Vec::new();
    let mut weld = |p: PlanPoint| {
        let key = ((p.x * 1000.0).round() as i64, (p.z * 1000.0).round() as i64);
        *ids.entry(key).or_insert_with(|| {
            points.push(p);
            (points.len() - 1) as u32
        })
    };
    let mut welded: Vec<[u32; 3]> = Vec::new();
    for t in triangles {
        let mut w = [weld(t[0]), weld(t[1]), weld(t[2])];
        if w[0] == w[1] || w[1] == w[2] || w[0] == w[2] {
            continue;
        }
        let area = signed_area(&[t[0], t[1], t[2]]);
        if area.abs() < 1e-8 {
            continue;
        }
        if area < 0.0 {
            w.swap(1, 2);
        }
        welded.push(w);
    }
    // Directed edges, split where another vertex lies on them (T-junctions between meshes).
    let mut net: HashMap<(u32, u32), i32> = HashMap::new();
    for tri in &welded {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            let (pa, pb) = (points[a as usize], points[b as usize]);
            let mut on: Vec<(f64, u32)> = (0..points.len() as u32)
                .filter(|&v| v != a && v != b)
                .filter_map(|v| {
                    let (d, t) = segment_projection(points[v as usize], pa, pb);
                    (d < 5e-4 && t > 1e-6 && t < 1.0 - 1e-6).then_some((t, v))
                })
                .collect();
            on.sort_by(|x, y| x.0.total_cmp(&y.0));
            let chain: Vec<u32> = std::iter::once(a).chain(on.into_iter().map(|(_, v)| v)).chain([b]).collect();
            for pair in chain.windows(2) {
                *net.entry((pair[0], pair[1])).or_insert(0) += 1;
                *net.entry((pair[1], pair[0])).or_insert(0) -= 1;
            }
        }
    }
    let mut boundary: Vec<(u32, u32)> = net.iter().filter(|(_, c)| **c > 0).map(|(e, _)| *e).collect();
    boundary.sort_unstable();
    let mut next: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
    for (a, b) in &boundary {
        next.entry(*a).or_default().push(*b);
    }
    let mut loops: Vec<Vec<PlanPoint>> = Vec::new();
    while let Some((&start, _)) = next.iter().find(|(_, v)| !v.is_empty()) {
        let mut ring = vec![start];
        let mut at = start;
        while let Some(to) = next.get_mut(&at).and_then(|v| v.pop()) {
            if to == start || ring.len() > boundary.len() {
                break;
            }
            ring.push(to);
            at = to;
        }
        loops.push(ring.into_iter().map(|v| points[v as usize]).collect());
    }
    let count = loops.len();
    let outline = loops.into_iter().max_by(|a, b| signed_area(a).total_cmp(&signed_area(b)))?;
    let outline = simplify_collinear(outline);
    (outline.len() >= 3 && signed_area(&outline) > 0.0 && polygon_is_simple(&outline)).then_some((outline, count))
}

/// Removes repeated points and points on the line through their neighbours (within 1 mm).
fn simplify_collinear(mut polygon: Vec<PlanPoint>) -> Vec<PlanPoint> {
    let mut changed = true;
    while changed && polygon.len() > 3 {
        changed = false;
        let n = polygon.len();
        for i in 0..n {
            let (prev, here, next) = (polygon[(i + n - 1) % n], polygon[i], polygon[(i + 1) % n]);
            let (d, t) = segment_projection(here, prev, next);
            if here.distance(next) < 1e-3 || (d < 1e-3 && (0.0..=1.0).contains(&t)) {
                polygon.remove(i);
                changed = true;
                break;
            }
        }
    }
    polygon
}

// ---------------------------------------------------------------------------------------------
// Models.

/// A model's geometry, cached by jid: the vertices of its convex hull in the model's frame
/// (a hull commutes with scaling and rotation), or why there is none.
#[derive(Clone, Debug)]
enum ModelGeometry {
    Hull(Vec<[f64; 3]>),
    Missing,
}

/// The convex hull vertices of `points`, or their bounding box corners when the hull is
/// degenerate (flat models).
fn hull_vertices(points: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let vectors: Vec<Vector> = points.iter().map(|p| Vector::new(p[0], p[1], p[2])).collect();
    match parry3d::transformation::try_convex_hull(&vectors) {
        Ok((vertices, _)) if vertices.len() >= 4 => vertices.iter().map(|v| [v.x, v.y, v.z]).collect(),
        _ => box_corners(points),
    }
}

fn box_corners(points: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let Some((lo, hi)) = bounds(points.iter().copied()) else { return Vec::new() };
    let mut corners = Vec::with_capacity(8);
    for k in 0..8 {
        corners.push([
            if k & 1 == 0 { lo[0] } else { hi[0] },
            if k & 2 == 0 { lo[1] } else { hi[1] },
            if k & 4 == 0 { lo[2] } else { hi[2] },
        ]);
    }
    corners
}

struct Library {
    model_root: PathBuf,
    info: HashMap<String, (String, String)>,
    models: HashMap<String, ModelGeometry>,
}

impl Library {
    fn open(future_dir: &Path) -> Result<Self, FrontError> {
        let nested = future_dir.join("3D-FUTURE-model");
        let model_root = if nested.is_dir() { nested } else { future_dir.to_owned() };
        let info_path = [future_dir.join("model_info.json"), model_root.join("model_info.json")]
            .into_iter()
            .find(|p| p.is_file())
            .ok_or_else(|| FrontError::MissingModelInfo { dir: future_dir.to_owned() })?;
        let text =
            std::fs::read_to_string(&info_path).map_err(|source| FrontError::Io { path: info_path.clone(), source })?;
        let entries: Vec<ModelInfo> = serde_json::from_str(&text)
            .map_err(|e| FrontError::ModelInfo { path: info_path.clone(), message: e.to_string() })?;
        let info = entries
            .into_iter()
            .map(|m| (m.model_id, (m.category.unwrap_or_default(), m.super_category.unwrap_or_default())))
            .collect();
        Ok(Self { model_root, info, models: HashMap::new() })
    }

    /// The model's hull, reading and caching its OBJ; warns once per model that is missing or
    /// unreadable.
    fn geometry(&mut self, jid: &str, warnings: &mut Vec<String>) -> ModelGeometry {
        if let Some(g) = self.models.get(jid) {
            return g.clone();
        }
        let path = self.model_root.join(jid).join("raw_model.obj");
        let geometry = match std::fs::read_to_string(&path) {
            Ok(text) => match parse_obj(&text, &path) {
                Ok(mesh) => ModelGeometry::Hull(hull_vertices(&mesh.vertices)),
                Err(e) => {
                    warnings.push(format!("model {jid}: {e}; using its bounding box"));
                    ModelGeometry::Missing
                }
            },
            Err(_) => {
                warnings.push(format!("model {jid}: {} is missing; using its bounding box", path.display()));
                ModelGeometry::Missing
            }
        };
        self.models.insert(jid.to_owned(), geometry.clone());
        geometry
    }
}

// ---------------------------------------------------------------------------------------------
// Rooms.

/// One furniture object of a room, in its own frame.
#[derive(Clone, Debug)]
struct Piece {
    jid: String,
    category: String,
    movable: Option<MovableCategory>,
    /// Points in the object's frame (footprint centred, floor at y = 0).
    points: Vec<[f64; 3]>,
    /// The shape is the box of the points (bounding-box fallback).
    is_box: bool,
    pose: ObjectPose,
    /// Size along local x, y (height of the top above the floor) and z.
    size: [f64; 3],
    standing: bool,
}

impl Piece {
    fn carryable(&self) -> bool {
        self.movable.is_some()
            && self.standing
            && self.size[0].max(self.size[2]) <= MAX_CARRY_SIZE
            && self.size[1] <= MAX_CARRY_HEIGHT
    }

    fn footprint_area(&self) -> f64 {
        self.size[0] * self.size[2]
    }

    fn shape(&self) -> Shape {
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
    fn collider(&self) -> Option<(Pose, SharedShape)> {
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
fn subsample(points: Vec<[f64; 3]>, cap: usize) -> Vec<[f64; 3]> {
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

fn round4(v: f64) -> f64 {
    (v * 1e4).round() / 1e4
}

/// A model placed by a child's transform.
#[derive(Debug)]
struct Placement {
    /// The object's pose.
    pose: ObjectPose,
    /// The points in the object's frame.
    local: Vec<[f64; 3]>,
    /// Size along local x, height of the top above the floor, size along local z.
    size: [f64; 3],
    /// Whether it stands on the floor (and was shifted to y = 0).
    standing: bool,
}

/// Places model-frame points by a child's transform into an object frame turned by the
/// child's yaw, centred on the footprint; `None` for no points or
/// non-finite ones. Objects within 5 cm of the floor at `floor_y` are shifted onto it.
fn place(points: &[[f64; 3]], child: &Child, floor_y: f64) -> Option<Placement> {
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
struct RoomDraft {
    floor: Vec<PlanPoint>,
    wall_height: f64,
    openings: Vec<Opening>,
    pieces: Vec<Piece>,
}

/// Collision data of a draft: walls and each piece's shape in its frame.
struct Clearances {
    walls: Vec<(Pose, SharedShape)>,
    colliders: Vec<Option<(Pose, SharedShape)>>,
}

impl Clearances {
    /// The draft's walls as esrp-core builds them (without openings, which only remove wall:
    /// conservative) and its pieces' shapes.
    fn of(draft: &RoomDraft) -> Self {
        Self {
            walls: collision::wall_pieces(&draft.floor, WALL_THICKNESS, draft.wall_height, &[])
                .iter()
                .map(collision::wall_collider)
                .collect(),
            colliders: draft.pieces.iter().map(Piece::collider).collect(),
        }
    }

    fn world(&self, i: usize, pose: &ObjectPose) -> Option<(Pose, &SharedShape)> {
        let (local, shape) = self.colliders[i].as_ref()?;
        Some((collision::object_pose(pose) * *local, shape))
    }

    /// Whether piece `i` at `pose` is clear by [`CLEARANCE`] of the walls and of every other
    /// piece at `poses`.
    fn is_clear(&self, i: usize, pose: &ObjectPose, poses: &[ObjectPose]) -> bool {
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
fn choose_movables(
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

fn slug(text: &str) -> String {
    let mut s: String = text.to_lowercase().chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '_' }).collect();
    while s.contains("__") {
        s = s.replace("__", "_");
    }
    let s = s.trim_matches('_').to_owned();
    if s.is_empty() { "object".to_owned() } else { s }
}

/// The target layout of one attempt as a scene (agent not yet placed).
fn target_scene(id: &str, room_type: &str, draft: &RoomDraft, chosen: &[usize], poses: &[ObjectPose]) -> Option<Scene> {
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
fn stream_of(id: &str) -> u64 {
    id.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

/// Openings from a room's `Door` and `Window` meshes, mapped onto the nearest floor edge.
fn openings_of(meshes: &[(&ArchMesh, &Child)], floor: &[PlanPoint], floor_y: f64, wall_height: f64) -> Vec<Opening> {
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
fn mesh_points(mesh: &ArchMesh, child: &Child) -> Vec<[f64; 3]> {
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
fn draft_room(
    room: &FrontRoom,
    room_name: &str,
    house: &House,
    library: &mut Library,
    report: &mut ImportReport,
) -> Result<RoomDraft, &'static str> {
    let furniture: HashMap<&str, &Furniture> = house.furniture.iter().map(|f| (f.uid.as_str(), f)).collect();
    let meshes: HashMap<&str, &ArchMesh> = house.mesh.iter().map(|m| (m.uid.as_str(), m)).collect();
    let room_meshes: Vec<(&ArchMesh, &Child)> =
        room.children.iter().filter_map(|c| meshes.get(c.reference.as_str()).map(|m| (*m, c))).collect();

    // Floor.
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
    let floor_y = lo[1];
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
    let floor_area = signed_area(&floor);
    if floor_area < MIN_FLOOR_AREA {
        return Err("too_small");
    }

    // Walls and openings.
    let wall_top = room_meshes
        .iter()
        .filter(|(m, _)| m.kind.starts_with("Wall"))
        .flat_map(|(m, c)| mesh_points(m, c))
        .map(|p| p[1] - floor_y)
        .fold(f64::NEG_INFINITY, f64::max);
    let wall_height = if (2.2..=4.0).contains(&wall_top) { wall_top } else { DEFAULT_WALL_HEIGHT };
    let openings = openings_of(&room_meshes, &floor, floor_y, wall_height);

    // Furniture.
    let children: Vec<(&Furniture, &Child)> =
        room.children.iter().filter_map(|c| furniture.get(c.reference.as_str()).map(|f| (*f, c))).collect();
    let walls_triangles = 12 * 3 * floor.len() + 12 * 2 * openings.len();
    let per_object = TRIANGLE_BUDGET.saturating_sub(walls_triangles) / children.len().max(1);
    let cap = ((per_object + 4) / 2).clamp(8, MAX_HULL_POINTS);
    let mut pieces: Vec<Piece> = Vec::new();
    let mut seen: HashSet<(String, i64, i64, i64)> = HashSet::new();
    for (item, child) in children {
        let jid = item.jid.clone().unwrap_or_default();
        let (category, super_category) = library.info.get(&jid).cloned().unwrap_or_else(|| {
            (item.category.clone().or_else(|| item.title.clone()).unwrap_or_default(), String::new())
        });
        let geometry =
            if jid.is_empty() { ModelGeometry::Missing } else { library.geometry(&jid, &mut report.warnings) };
        let (points, is_box) = match geometry {
            ModelGeometry::Hull(points) => (points, false),
            ModelGeometry::Missing => match item.bbox.as_deref() {
                Some(&[x, y, z]) if x > 0.0 && y > 0.0 && z > 0.0 => {
                    if jid.is_empty() {
                        // (A model that is missing was warned about once, by the library.)
                        report.warnings.push(format!(
                            "{room_name}: furniture {} has no model id; using a box of its bbox",
                            item.uid
                        ));
                    }
                    (box_corners(&[[-x / 2.0, 0.0, -z / 2.0], [x / 2.0, y, z / 2.0]]), true)
                }
                _ => {
                    report.warnings.push(format!(
                        "{room_name}: furniture {} ({jid}) has neither a model nor a bbox; dropped",
                        item.uid
                    ));
                    report.drop_object("no_geometry");
                    continue;
                }
            },
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
        if !point_in_polygon(pose.position(), &floor) {
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
    let covered: f64 = pieces.iter().filter(|p| p.standing).map(Piece::footprint_area).sum();
    if floor_area - covered < MIN_FREE_FLOOR {
        return Err("no_free_floor");
    }
    if !pieces.iter().any(Piece::carryable) {
        return Err("no_carryable");
    }
    Ok(RoomDraft { floor, wall_height, openings, pieces })
}

/// Reads one house file.
fn read_house(path: &Path) -> Result<House, FrontError> {
    let text = std::fs::read_to_string(path).map_err(|source| FrontError::Io { path: path.to_owned(), source })?;
    serde_json::from_str(&text).map_err(|e| FrontError::HouseJson { path: path.to_owned(), message: e.to_string() })
}

/// Imports every room of every house in `front_dir` (3D-FRONT) with models from `future_dir`
/// (3D-FUTURE) as scene pairs, calling `progress(houses_done, houses_total)` after each house.
///
/// Every house file is parsed before any room is built, so a malformed one fails the import
/// before work is spent; a missing or unreadable model is a warning (the object falls back to
/// its bounding box), not an error. Scenes are returned, never written.
pub fn import(
    front_dir: &Path,
    future_dir: &Path,
    options: &ImportOptions,
    progress: &dyn Fn(usize, usize),
) -> Result<ImportReport, FrontError> {
    let entries =
        std::fs::read_dir(front_dir).map_err(|source| FrontError::Io { path: front_dir.to_owned(), source })?;
    let mut paths: Vec<PathBuf> = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|source| FrontError::Io { path: front_dir.to_owned(), source })?;
        let path = entry.path();
        if path.is_file() && path.extension().is_some_and(|e| e == "json") {
            paths.push(path);
        }
    }
    paths.sort();
    if let Some(most) = options.max_houses {
        paths.truncate(most);
    }
    if paths.is_empty() {
        return Err(FrontError::NoHouses { dir: front_dir.to_owned() });
    }
    let mut library = Library::open(future_dir)?;
    let houses: Vec<(String, House)> = paths
        .iter()
        .map(|path| {
            let uuid = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            read_house(path).map(|house| (uuid, house))
        })
        .collect::<Result<_, _>>()?;

    let mut report = ImportReport { houses: houses.len(), ..Default::default() };
    let params = ConstructionParams::default();
    for (done, (uuid, house)) in houses.iter().enumerate() {
        for (index, room) in house.scene.room.iter().enumerate() {
            report.rooms_seen += 1;
            let instance = if room.instance_id.is_empty() { format!("room-{index}") } else { room.instance_id.clone() };
            let id = format!("3dfront/{uuid}/{instance}");
            let room_type = if room.room_type.is_empty() { "OtherRoom" } else { room.room_type.as_str() };
            let draft = match draft_room(room, &id, house, &mut library, &mut report) {
                Ok(draft) => draft,
                Err(reason) => {
                    report.skip(reason);
                    continue;
                }
            };
            let clearances = Clearances::of(&draft);
            let mut last: Result<(), String> = Err("movables_overlap".to_owned());
            for attempt in 0..options.max_attempts.max(1) {
                let mut dice = Dice::new(options.seed, stream_of(&id), attempt);
                let (chosen, poses, nudged, stuck) = choose_movables(&draft, &clearances, &mut dice);
                let Some(target) = target_scene(&id, room_type, &draft, &chosen, &poses) else {
                    continue; // Nothing could be chosen: every candidate is stuck.
                };
                match construct(target, &mut dice, &params) {
                    Ok(scene) => {
                        report.objects_nudged += nudged;
                        report.movable_overlapping += stuck;
                        report.scenes.push(scene);
                        last = Ok(());
                        break;
                    }
                    Err(rejection) => last = Err(construction_reason(&rejection)),
                }
            }
            match last {
                Ok(()) => report.rooms_imported += 1,
                Err(reason) => report.skip(&reason),
            }
        }
        progress(done + 1, houses.len());
    }
    Ok(report)
}

fn construction_reason(rejection: &Rejection) -> String {
    format!("construction_{}", rejection.reason())
}

#[cfg(test)]
mod tests {
    use super::*;

    const HOUSE_UUID: &str = "0a1b2c3d-0000-4000-8000-000000000001";

    fn fixture(part: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/3dfront").join(part)
    }

    fn import_fixture() -> ImportReport {
        let calls = std::cell::Cell::new(0);
        let report = import(&fixture("front"), &fixture("future"), &ImportOptions::default(), &|done, total| {
            calls.set(calls.get() + 1);
            assert_eq!((done, total), (1, 1));
        })
        .expect("the fixture imports");
        assert_eq!(calls.get(), 1, "progress is called once per house");
        report
    }

    #[test]
    fn the_fixture_imports_as_scenes_that_replay_to_success() {
        let report = import_fixture();
        assert_eq!((report.houses, report.rooms_seen, report.rooms_imported), (1, 2, 1));
        // The second room has no floor mesh; the rug is flat.
        assert_eq!(report.rooms_skipped, BTreeMap::from([("no_floor_mesh".to_owned(), 1)]));
        assert_eq!(report.objects_dropped, BTreeMap::from([("flat".to_owned(), 1)]));
        assert_eq!(report.scenes.len(), 1);
        let scene = &report.scenes[0];
        assert_eq!(scene.id, format!("3dfront/{HOUSE_UUID}/MasterBedroom-101"));
        assert_eq!(scene.room_type, "MasterBedroom");
        assert_eq!(scene.split, split_for_id(&scene.id));
        crate::backward::validate_by_replay(scene).expect("the expert replays to success");

        // Two floor meshes with a T-junction between them make one 5 m x 4 m rectangle.
        let floor: Vec<PlanPoint> = scene.room.floor_points();
        assert_eq!(floor.len(), 4, "floor {:?}", scene.room.floor);
        assert!((signed_area(&floor).abs() - 20.0).abs() < 1e-6);
        assert!((scene.room.wall_height - 2.75).abs() < 1e-9);
        // The door mesh on the wall x = 4 becomes a door 0.9 m wide.
        assert_eq!(scene.room.openings.len(), 1, "{:?}", scene.room.openings);
        let door = &scene.room.openings[0];
        assert_eq!(door.kind, OpeningKind::Door);
        let (a, b) = (floor[door.wall], floor[(door.wall + 1) % floor.len()]);
        assert!((a.x - 4.0).abs() < 1e-9 && (b.x - 4.0).abs() < 1e-9);
        assert!((door.width - 0.9).abs() < 1e-6 && (door.top - 2.05).abs() < 1e-9);

        // Bed, two nightstands and a chair; the bed is fixed (too big, not carryable).
        let objects = scene.fixed_objects.len() + scene.movable_objects.len();
        assert_eq!(objects, 4);
        assert!(scene.fixed_objects.iter().any(|o| o.model == "bed-model-0001"));
        assert!(!scene.movable_objects.is_empty());
        for object in &scene.movable_objects {
            assert!(["nightstand-model-0002", "chair-model-0003"].contains(&object.model.as_str()));
        }
        // The nightstand has no OBJ: a box of its bbox, and a warning.
        let nightstand_shapes: Vec<&Shape> = scene
            .fixed_objects
            .iter()
            .map(|o| (&o.model, &o.shape))
            .chain(scene.movable_objects.iter().map(|o| (&o.model, &o.shape)))
            .filter(|(model, _)| model.as_str() == "nightstand-model-0002")
            .map(|(_, shape)| shape)
            .collect();
        assert_eq!(nightstand_shapes.len(), 2);
        for shape in nightstand_shapes {
            let Shape::Parts(parts) = shape else { panic!("a nightstand is {shape:?}") };
            let [Part::Box { half_extents, offset, .. }] = parts.as_slice() else { panic!("parts {parts:?}") };
            assert!((half_extents[0] - 0.25).abs() < 1e-6 && (half_extents[2] - 0.2).abs() < 1e-6);
            assert!((offset[1] - 0.275).abs() < 1e-6, "the box stands on the floor");
        }
        assert!(report.warnings.iter().any(|w| w.contains("nightstand-model-0002") && w.contains("missing")));
        // The chair is a convex hull of its OBJ, standing on the floor.
        let chair = scene
            .fixed_objects
            .iter()
            .map(|o| (&o.model, &o.shape))
            .chain(scene.movable_objects.iter().map(|o| (&o.model, &o.shape)))
            .find(|(model, _)| model.as_str() == "chair-model-0003")
            .map(|(_, shape)| shape.clone());
        let Some(Shape::Parts(parts)) = chair else { panic!("no chair") };
        let [Part::ConvexHull { points, .. }] = parts.as_slice() else { panic!("chair parts {parts:?}") };
        assert!(points.len() >= 8 && points.len() <= MAX_HULL_POINTS);
        let min_y = points.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min);
        assert!(min_y.abs() < 1e-9);

        // Same seed, same scenes.
        assert_eq!(import_fixture().scenes, report.scenes);
    }

    fn box_piece(category: &str, movable: Option<MovableCategory>, size: [f64; 3], x: f64, z: f64) -> Piece {
        let [sx, sy, sz] = size;
        Piece {
            jid: format!("{category}-model"),
            category: category.to_owned(),
            movable,
            points: box_corners(&[[-sx / 2.0, 0.0, -sz / 2.0], [sx / 2.0, sy, sz / 2.0]]),
            is_box: true,
            pose: ObjectPose::new(x, z, 0.0),
            size,
            standing: true,
        }
    }

    #[test]
    fn overlapping_pieces_are_nudged_apart_or_kept_fixed() {
        let floor: Vec<PlanPoint> =
            [(0.0, 0.0), (4.0, 0.0), (4.0, 4.0), (0.0, 4.0)].map(|(x, z)| PlanPoint::new(x, z)).to_vec();
        let wardrobe = box_piece("Wardrobe", None, [1.0, 2.0, 0.6], 1.0, 0.5);
        let stool = Some(MovableCategory::PierStool);
        let draft_with = |stool: Piece| RoomDraft {
            floor: floor.clone(),
            wall_height: 2.8,
            openings: Vec::new(),
            pieces: vec![wardrobe.clone(), stool],
        };

        // A stool 5 cm into the wardrobe's front is moved out and becomes movable.
        let draft = draft_with(box_piece("Stool", stool, [0.4, 0.45, 0.4], 1.0, 0.95));
        let clearances = Clearances::of(&draft);
        let (chosen, poses, nudged, stuck) = choose_movables(&draft, &clearances, &mut Dice::new(0, 1, 0));
        assert_eq!((chosen.as_slice(), nudged, stuck), (&[1][..], 1, 0));
        let moved = poses[1].position().distance(draft.pieces[1].pose.position());
        assert!(moved > 0.05 && moved <= 0.3 + 1e-9, "moved {moved}");
        assert!(clearances.is_clear(1, &poses[1], &poses));
        let target = target_scene("test/nudged", "Bedroom", &draft, &chosen, &poses).unwrap();
        assert_eq!(target.movable_objects.len(), 1);
        let scene = construct(target, &mut Dice::new(0, 1, 0), &ConstructionParams::default())
            .expect("the nudged target layout is valid for backward construction");
        crate::backward::validate_by_replay(&scene).unwrap();

        // A stool deep inside the wardrobe cannot be freed: it stays fixed.
        let draft = draft_with(box_piece("Stool", stool, [0.4, 0.45, 0.4], 1.0, 0.5));
        let (chosen, poses, nudged, stuck) = choose_movables(&draft, &Clearances::of(&draft), &mut Dice::new(0, 1, 0));
        assert_eq!((chosen.len(), nudged, stuck), (0, 0, 1));
        assert!(target_scene("test/stuck", "Bedroom", &draft, &chosen, &poses).is_none());
    }

    #[test]
    fn quaternions_give_the_yaw_of_spec_section_1() {
        let half = std::f64::consts::FRAC_PI_4;
        let cases = [
            ([0.0, 0.0, 0.0, 1.0], 0.0),
            ([0.0, half.sin(), 0.0, half.cos()], std::f64::consts::FRAC_PI_2),
            ([0.0, -half.sin(), 0.0, half.cos()], -std::f64::consts::FRAC_PI_2),
            ([0.0, 1.0, 0.0, 0.0], std::f64::consts::PI),
            ([0.0, -(std::f64::consts::PI / 8.0).sin(), 0.0, (std::f64::consts::PI / 8.0).cos()], -half),
            // Not normalised: the same rotation.
            ([0.0, 2.0 * half.sin(), 0.0, 2.0 * half.cos()], std::f64::consts::FRAC_PI_2),
            // A zero quaternion reads as the identity.
            ([0.0, 0.0, 0.0, 0.0], 0.0),
        ];
        for (rot, yaw) in cases {
            let got = yaw_from_quaternion(rot);
            let wrapped = (got - yaw + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
            assert!(wrapped.abs() < 1e-9, "{rot:?}: yaw {got}, expected {yaw}");
        }
        // A yaw of 90° sends local +x to (0, 0, −1), as SPEC §1 says.
        let turned = rotate(normalized([0.0, half.sin(), 0.0, half.cos()]), [1.0, 0.0, 0.0]);
        assert!(turned[0].abs() < 1e-12 && (turned[2] + 1.0).abs() < 1e-12);
        // A piece tilted 90° about +x keeps its yaw from the x axis.
        assert!(yaw_from_quaternion([half.sin(), 0.0, 0.0, half.cos()]).abs() < 1e-9);
    }

    #[test]
    fn placing_a_model_centres_its_footprint_and_keeps_it_in_the_world() {
        let half = std::f64::consts::FRAC_PI_4;
        let child = Child {
            reference: String::new(),
            pos: [3.0, 0.0, 4.5],
            rot: [0.0, -half.sin(), 0.0, half.cos()],
            scale: [1.1, 1.0, 1.1],
        };
        // A model from x = 0 to 0.45, y = 0.02 to 0.9 (2 cm up: it snaps to the floor), z = ±0.25.
        let points = box_corners(&[[0.0, 0.02, -0.25], [0.45, 0.9, 0.25]]);
        let Placement { pose, local, size, standing } = place(&points, &child, 0.0).unwrap();
        assert!((pose.yaw + std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        // The footprint centre (0.2475, 0) in the scaled model goes to +z in the world.
        assert!((pose.x - 3.0).abs() < 1e-9 && (pose.z - 4.7475).abs() < 1e-9, "{pose:?}");
        assert!(standing);
        assert!((size[0] - 0.495).abs() < 1e-9 && (size[1] - 0.88).abs() < 1e-9 && (size[2] - 0.55).abs() < 1e-9);
        let (lo, hi) = bounds(local.iter().copied()).unwrap();
        assert!((lo[0] + hi[0]).abs() < 1e-9 && (lo[2] + hi[2]).abs() < 1e-9 && lo[1].abs() < 1e-9);
        // An object 0.6 m up (on a table) keeps its height and is not standing.
        let high = Child { pos: [0.0, 0.6, 0.0], ..child };
        let Placement { local, standing, .. } = place(&points, &high, 0.0).unwrap();
        assert!(!standing);
        assert!((local.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min) - 0.62).abs() < 1e-9);
    }

    #[test]
    fn obj_parsing_reads_vertices_and_fans_polygons() {
        let text = "# comment\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0 1.0\nvt 0 0\nvn 0 0 1\ng group\n\
                    f 1/1/1 2/1/1 3/1/1 4/1/1\nf 1//1 3//1 4//1\nf -4 -3 -2\n";
        let mesh = parse_obj(text, Path::new("m.obj")).unwrap();
        assert_eq!(mesh.vertices.len(), 4);
        assert_eq!(mesh.vertices[3], [0.0, 1.0, 0.0]);
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 2, 3], [0, 1, 2]]);

        let check_error = |text: &str, line: usize, says: &str| {
            let error = parse_obj(text, Path::new("bad/raw_model.obj")).unwrap_err();
            let FrontError::Obj { line: at, .. } = &error else { panic!("{error:?}") };
            assert_eq!(*at, line, "{error}");
            let message = error.to_string();
            assert!(message.contains("bad/raw_model.obj") && message.contains(says), "{message}");
        };
        check_error("v 0 0 0\nv 1 0 0\nf 1 2 9\n", 3, "vertex 9 does not exist");
        check_error("v 0 x 0\n", 1, "`x` is not a number");
        check_error("v 0 0\n", 1, "three coordinates");
        check_error("v 0 0 0\nv 1 0 0\nf 1 2\n", 3, "at least 3");
        check_error("v 0 0 0\nf 0 1 1\n", 2, "vertex 0 does not exist");
        check_error("# nothing\n", 0, "no vertices");
    }

    #[test]
    fn malformed_input_is_a_clear_error() {
        let front = tempfile::tempdir().unwrap();
        std::fs::copy(
            fixture("front").join(format!("{HOUSE_UUID}.json")),
            front.path().join(format!("{HOUSE_UUID}.json")),
        )
        .unwrap();
        std::fs::write(front.path().join("broken-house.json"), "{\"furniture\": [{\"uid\": 3}], \"scene\": {}}")
            .unwrap();
        let error = import(front.path(), &fixture("future"), &ImportOptions::default(), &|_, _| {
            panic!("no room is built before every house file parses")
        })
        .unwrap_err();
        let FrontError::HouseJson { path, .. } = &error else { panic!("{error:?}") };
        assert!(path.ends_with("broken-house.json"));
        assert!(error.to_string().contains("broken-house.json"), "{error}");

        std::fs::write(front.path().join("broken-house.json"), "{\"furniture\": [").unwrap();
        let error = import(front.path(), &fixture("future"), &ImportOptions::default(), &|_, _| {}).unwrap_err();
        assert!(matches!(&error, FrontError::HouseJson { path, .. } if path.ends_with("broken-house.json")), "{error}");

        // No model_info.json, no house files.
        let empty = tempfile::tempdir().unwrap();
        let error = import(&fixture("front"), empty.path(), &ImportOptions::default(), &|_, _| {}).unwrap_err();
        assert!(matches!(error, FrontError::MissingModelInfo { .. }), "{error}");
        let error = import(empty.path(), &fixture("future"), &ImportOptions::default(), &|_, _| {}).unwrap_err();
        assert!(matches!(error, FrontError::NoHouses { .. }), "{error}");
        // A model_info.json that is not a list.
        std::fs::write(empty.path().join("model_info.json"), "{\"model_id\": 1}").unwrap();
        let error = import(&fixture("front"), empty.path(), &ImportOptions::default(), &|_, _| {}).unwrap_err();
        assert!(matches!(&error, FrontError::ModelInfo { path, .. } if path.ends_with("model_info.json")), "{error}");
    }

    #[test]
    fn floor_outlines_are_the_boundary_of_the_union() {
        let p = |x: f64, z: f64| PlanPoint::new(x, z);
        // An L-shape from three unit squares, triangulated with mixed windings.
        let squares = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)];
        let mut triangles = Vec::new();
        for (x, z) in squares {
            triangles.push([p(x, z), p(x + 1.0, z), p(x + 1.0, z + 1.0)]);
            triangles.push([p(x, z), p(x, z + 1.0), p(x + 1.0, z + 1.0)]);
        }
        let (outline, count) = floor_outline(&triangles).unwrap();
        assert_eq!(count, 1);
        assert_eq!(outline.len(), 6, "{outline:?}");
        assert!((signed_area(&outline) - 3.0).abs() < 1e-9);
        // Two disjoint pieces: the larger is kept.
        triangles.push([p(5.0, 5.0), p(5.5, 5.0), p(5.5, 5.5)]);
        let (outline, count) = floor_outline(&triangles).unwrap();
        assert_eq!((outline.len(), count), (6, 2));
        // Two squares touching at one corner only: their outline is not simple.
        let bow = [
            [p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0)],
            [p(0.0, 0.0), p(1.0, 1.0), p(0.0, 1.0)],
            [p(1.0, 1.0), p(2.0, 1.0), p(2.0, 2.0)],
            [p(1.0, 1.0), p(2.0, 2.0), p(1.0, 2.0)],
        ];
        assert!(floor_outline(&bow).is_none_or(|(o, _)| polygon_is_simple(&o)));
    }

    #[test]
    fn categories_map_onto_the_papers_groups() {
        let check = |category: &str, super_category: &str, expected: Option<MovableCategory>| {
            assert_eq!(movable_category(category, super_category), expected, "{category} / {super_category}");
        };
        check("Nightstand", "Cabinet/Shelf/Desk", Some(MovableCategory::CabinetShelfDesk));
        check("Bookcase / jewelry Armoire", "Cabinet/Shelf/Desk", Some(MovableCategory::CabinetShelfDesk));
        check("Desk", "Table", Some(MovableCategory::CabinetShelfDesk));
        check("Dining Chair", "Chair", Some(MovableCategory::Chair));
        check("Lounge Chair / Cafe Chair / Office Chair", "Chair", Some(MovableCategory::Chair));
        check("armchair", "Sofa", Some(MovableCategory::Sofa));
        check("Loveseat Sofa", "Sofa", Some(MovableCategory::Sofa));
        check("Three-Seat / Multi-seat Sofa", "Sofa", None);
        check("Footstool / Sofastool / Bed End Stool / Stool", "Pier/Stool", Some(MovableCategory::PierStool));
        check("Barstool", "Chair", Some(MovableCategory::PierStool));
        check("Drawer Chest / Corner cabinet", "Cabinet/Shelf/Desk", Some(MovableCategory::CabinetShelfDesk));
        check(
            "Sideboard / Side Cabinet / Console Table",
            "Cabinet/Shelf/Desk",
            Some(MovableCategory::CabinetShelfDesk),
        );
        check("Coffee Table", "Table", Some(MovableCategory::Others));
        check("Corner/Side Table", "Table", Some(MovableCategory::Others));
        check("Floor Lamp", "Lighting", Some(MovableCategory::Others));
        check("Pendant Lamp", "Lighting", None);
        check("King-size Bed", "Bed", None);
        check("Wardrobe", "Cabinet/Shelf/Desk", None);
        check("Dining Table", "Table", None);
        check("", "", None);
    }
}
