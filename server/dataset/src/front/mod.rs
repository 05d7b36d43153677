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
//!   convex hull of the model's vertices as one [`Part::ConvexHull`](esrp_core::Part::ConvexHull) of at most
//!   [`MAX_HULL_POINTS`] points (fewer when the room has many objects, so that the room stays
//!   under [`crate::layout::TRIANGLE_BUDGET`] triangles); a model whose OBJ is missing or
//!   unreadable falls back to a [`Part::Box`](esrp_core::Part::Box) of the furniture's `bbox` with a warning. The
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
//!   the id is `3dfront/<house-uuid>/<room-instanceid>`, the split by [`split_for_id`](crate::benchmark::split_for_id), the
//!   room type 3D-FRONT's.
//!
//! Nothing is written here: [`import`] returns the scenes, and the caller writes them (the
//! `files` module writes atomically), so a malformed input never leaves half a dataset.

use std::path::{Path, PathBuf};

use crate::backward::{ConstructionParams, Rejection, construct};
use crate::dice::Dice;

mod categories;
mod constants;
mod draft;
mod error;
mod json;
mod library;
mod obj;
mod outline;
mod report;
mod rotation;

pub use categories::movable_category;
pub use constants::{
    CLEARANCE, DEFAULT_WALL_HEIGHT, MAX_CARRY_HEIGHT, MAX_CARRY_SIZE, MAX_HULL_POINTS, MIN_FLOOR_AREA, MIN_FREE_FLOOR,
    WALL_THICKNESS,
};
use draft::{Clearances, choose_movables, draft_room, stream_of, target_scene};
pub use error::FrontError;
use json::House;
use library::Library;

pub use obj::{ObjMesh, parse_obj};
pub use report::ImportReport;

pub use rotation::yaw_from_quaternion;

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
    use std::collections::BTreeMap;

    use esrp_core::geometry::{PlanPoint, polygon_is_simple, signed_area};
    use esrp_core::{MovableCategory, ObjectPose, OpeningKind, Part, Shape};

    use super::draft::{Piece, Placement, RoomDraft, place};
    use super::json::Child;
    use super::library::box_corners;
    use super::outline::{bounds, floor_outline};
    use super::rotation::{normalized, rotate};
    use super::*;
    use crate::benchmark::split_for_id;

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
