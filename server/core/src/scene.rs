//! The scene format `esrp.scene/v1`: a room, its fixed and movable objects, the agent's start
//! pose, the horizon and the expert trajectory, as plain serde data.
//!
//! A [`Scene`] is only data: nothing here checks it. [`crate::CompiledScene::new`] validates a
//! scene (see [`crate::SceneError`]) and builds its collision world.
//!
//! # Frames and units
//!
//! Metres and radians; world y-up with the floor at `y = 0`; plan coordinates are `(x, z)`.
//! An object's shape is given in its own frame (y-up, floor at `y = 0`), and its [`ObjectPose`]
//! places that frame on the floor: translation `(x, 0, z)`, then rotation by `yaw` about +y
//! (right-handed: local `+x` goes to `(cos yaw, 0, −sin yaw)`).
//!
//! # Example
//!
//! ```json
//! {
//!   "schema": "esrp.scene/v1",
//!   "id": "example/bedroom-0",
//!   "room_type": "Bedroom",
//!   "difficulty": "easy",
//!   "split": "test",
//!   "room": {
//!     "floor": [[0.0, 0.0], [4.0, 0.0], [4.0, 3.5], [0.0, 3.5]],
//!     "wall_height": 2.6,
//!     "wall_thickness": 0.12,
//!     "openings": [{"kind": "door", "wall": 0, "offset": 0.4, "width": 0.9, "bottom": 0.0, "top": 2.05}]
//!   },
//!   "fixed_objects": [
//!     {"id": "bed-0", "category": "bed", "model": "bed_double",
//!      "shape": {"parts": [{"type": "box", "half_extents": [1.0, 0.25, 0.8], "offset": [0.0, 0.25, 0.0]}]},
//!      "pose": {"x": 2.9, "z": 2.62, "yaw": 0.0}}
//!   ],
//!   "movable_objects": [
//!     {"id": "stool-0", "category": "pier_stool", "model": "stool_round",
//!      "shape": {"parts": [{"type": "cylinder", "radius": 0.2, "half_height": 0.225, "offset": [0.0, 0.225, 0.0]}]},
//!      "pose": {"x": 1.0, "z": 1.0, "yaw": 0.0},
//!      "target": {"x": 1.0, "z": 2.5, "yaw": 0.0}}
//!   ],
//!   "agent": {"x": 2.0, "z": 0.8, "heading": 8},
//!   "horizon": 200,
//!   "expert_trajectory": []
//! }
//! ```
//!
//! A complete example that replays to success is `server/core/examples/scenes/bedroom.json`.

use serde::{Deserialize, Serialize};

use crate::action::Action;
use crate::geometry::PlanPoint;
use crate::heading::Heading;

/// The schema string that every `esrp.scene/v1` document carries in its `schema` field.
pub const SCENE_SCHEMA: &str = "esrp.scene/v1";

/// A scene pair: a room with its fixed furniture, movable objects with their initial and target
/// poses, the agent's start pose, the horizon and the expert trajectory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Always [`SCENE_SCHEMA`]; any other value is rejected, so that a future format is never
    /// misread.
    pub schema: String,
    /// Unique scene id, e.g. `esrp-bench-v1/000123`.
    pub id: String,
    /// 3D-FRONT's room type name, e.g. `MasterBedroom`, `LivingDiningRoom`.
    pub room_type: String,
    /// Difficulty, which must match the number of movable objects (SPEC §5).
    pub difficulty: Difficulty,
    /// Train or test split.
    pub split: Split,
    /// The room: floor polygon and walls.
    pub room: Room,
    /// Furniture that never moves (beds, wardrobes, ...). May be empty.
    #[serde(default)]
    pub fixed_objects: Vec<FixedObject>,
    /// The objects to rearrange: 1 to 6 of them.
    pub movable_objects: Vec<MovableObject>,
    /// The agent's start pose.
    pub agent: AgentStart,
    /// The episode horizon `L` in steps (SPEC §5): an episode truncates when its step counter
    /// reaches it.
    pub horizon: u32,
    /// Action codes (SPEC §3) that take the initial layout to success. Empty when unknown.
    #[serde(default)]
    pub expert_trajectory: Vec<Action>,
}

/// Difficulty by number of movable objects: Easy 1, Medium 2–3, Hard 4–6.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Difficulty {
    /// One movable object.
    Easy,
    /// Two or three movable objects.
    Medium,
    /// Four to six movable objects.
    Hard,
}

impl Difficulty {
    /// Every difficulty, in the order above.
    pub const ALL: [Difficulty; 3] = [Difficulty::Easy, Difficulty::Medium, Difficulty::Hard];

    /// The difficulty that SPEC §5 assigns to a scene with `movable_objects` objects, if any.
    pub fn for_object_count(movable_objects: usize) -> Option<Self> {
        match movable_objects {
            1 => Some(Self::Easy),
            2 | 3 => Some(Self::Medium),
            4..=6 => Some(Self::Hard),
            _ => None,
        }
    }

    /// Lower-case name as in the JSON (`easy`, `medium`, `hard`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Easy => "easy",
            Self::Medium => "medium",
            Self::Hard => "hard",
        }
    }
}

impl std::str::FromStr for Difficulty {
    type Err = String;
    /// A difficulty by its name ([`Difficulty::as_str`]).
    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|d| d.as_str() == name)
            .ok_or_else(|| format!("{name:?} is not a difficulty: use easy, medium or hard"))
    }
}

/// Dataset split.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    /// Training scenes (90 %).
    Train,
    /// Test scenes (10 %).
    Test,
    /// A server's hidden challenge split: scenes drawn like the test split's from a secret seed,
    /// scored by the server (one counted attempt per scene and token).
    Challenge,
    /// The challenge's minival phase: more scenes of the same secret draw, which may be played
    /// any number of times.
    Minival,
}

impl Split {
    /// Every split, in the order above.
    pub const ALL: [Split; 4] = [Split::Train, Split::Test, Split::Challenge, Split::Minival];

    /// Lower-case name as in the JSON (`train`, `test`, `challenge`, `minival`).
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Train => "train",
            Self::Test => "test",
            Self::Challenge => "challenge",
            Self::Minival => "minival",
        }
    }

    /// Whether the split is hidden (challenge or minival): its scenes are seen only through
    /// observations.
    pub fn is_hidden(self) -> bool {
        matches!(self, Self::Challenge | Self::Minival)
    }
}

impl std::str::FromStr for Split {
    type Err = String;
    /// A split by its name ([`Split::as_str`]).
    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|s| s.as_str() == name)
            .ok_or_else(|| format!("{name:?} is not a split: use train, test, challenge or minival"))
    }
}

/// The room: a floor polygon whose edges carry walls.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Room {
    /// Floor polygon `[x, z]`, a simple polygon in either winding (rectangles, L-shapes, ...).
    /// Edge `i` runs from vertex `i` to vertex `i + 1` and carries wall `i`, which stands
    /// outside the polygon: the polygon is the free floor.
    pub floor: Vec<[f64; 2]>,
    /// Height of the walls, metres.
    pub wall_height: f64,
    /// Thickness of the walls, metres.
    pub wall_thickness: f64,
    /// Doors and windows in the walls.
    #[serde(default)]
    pub openings: Vec<Opening>,
}

impl Room {
    /// The floor polygon as plan points.
    pub fn floor_points(&self) -> Vec<PlanPoint> {
        self.floor.iter().map(|p| PlanPoint::new(p[0], p[1])).collect()
    }
}

/// An opening in a wall.
///
/// A **door** is drawn as a closed door leaf set into the wall and collides like the wall: the
/// agent never leaves the room. A **window** is a hole between `bottom` and `top`; the wall
/// below and above it still collides. **[decision]**
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Opening {
    /// Door or window.
    pub kind: OpeningKind,
    /// Index of the wall (floor polygon edge) it is in.
    pub wall: usize,
    /// Distance from the wall's first vertex to the near side of the opening, metres.
    pub offset: f64,
    /// Width along the wall, metres.
    pub width: f64,
    /// Height of the opening's bottom above the floor (0 for doors), metres.
    pub bottom: f64,
    /// Height of the opening's top above the floor, metres.
    pub top: f64,
}

/// Kind of wall opening.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OpeningKind {
    /// A closed door (collides like the wall).
    Door,
    /// A window (a hole in the wall between its bottom and top).
    Window,
}

/// A pose on the floor: position `(x, z)` and yaw about +y.
#[derive(Clone, Copy, Debug, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectPose {
    /// World x, metres.
    pub x: f64,
    /// World z, metres.
    pub z: f64,
    /// Yaw, radians, right-handed about +y.
    pub yaw: f64,
}

impl ObjectPose {
    /// A pose from its parts.
    pub const fn new(x: f64, z: f64, yaw: f64) -> Self {
        Self { x, z, yaw }
    }

    /// The position on the plan.
    pub fn position(&self) -> PlanPoint {
        PlanPoint::new(self.x, self.z)
    }
}

/// The agent's start pose: a position and a heading index (SPEC §1).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentStart {
    /// World x, metres.
    pub x: f64,
    /// World z, metres.
    pub z: f64,
    /// Heading index `k` in `0..16`, yaw `k × 22.5°`.
    pub heading: Heading,
}

/// A piece of furniture that never moves.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FixedObject {
    /// Unique id within the scene (shared with the movable objects' ids).
    pub id: String,
    /// Free-form category, e.g. `bed`, `wardrobe`.
    pub category: String,
    /// Name of the model it was built from (informative), e.g. `bed_double_a`.
    #[serde(default)]
    pub model: String,
    /// Its 3D shape in its own frame.
    pub shape: Shape,
    /// Where it stands.
    pub pose: ObjectPose,
}

/// An object the agent must put at its target pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MovableObject {
    /// Unique id within the scene.
    pub id: String,
    /// The paper's category group (rendering colour, statistics).
    pub category: MovableCategory,
    /// Name of the model it was built from (informative), e.g. `chair_dining_b`.
    #[serde(default)]
    pub model: String,
    /// Its 3D shape in its own frame. A mesh collides as its convex hull when the object moves
    /// or is an obstacle.
    pub shape: Shape,
    /// Initial pose.
    pub pose: ObjectPose,
    /// Target pose.
    pub target: ObjectPose,
}

/// The paper's categories of movable objects (its Fig. 4).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MovableCategory {
    /// Cabinets, shelves and desks.
    CabinetShelfDesk,
    /// Chairs of every kind.
    Chair,
    /// Armchairs and small sofas.
    Sofa,
    /// Piers and stools.
    PierStool,
    /// Everything else: side tables, plants, lamps, ...
    Others,
}

impl MovableCategory {
    /// All categories, in a fixed order.
    pub const ALL: [MovableCategory; 5] =
        [Self::CabinetShelfDesk, Self::Chair, Self::Sofa, Self::PierStool, Self::Others];

    /// The snake-case name as in the JSON.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::CabinetShelfDesk => "cabinet_shelf_desk",
            Self::Chair => "chair",
            Self::Sofa => "sofa",
            Self::PierStool => "pier_stool",
            Self::Others => "others",
        }
    }
}

/// A 3D shape in an object's frame (y-up, floor at y = 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Shape {
    /// A union of convex parts.
    Parts(Vec<Part>),
    /// A triangle mesh.
    Mesh(Mesh),
}

/// One convex part of a [`Shape::Parts`], placed in the object's frame by `offset` (its centre)
/// and `yaw` (about +y).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum Part {
    /// A box.
    Box {
        /// Half sizes along its local x, y and z.
        half_extents: [f64; 3],
        /// Centre in the object's frame.
        #[serde(default)]
        offset: [f64; 3],
        /// Yaw about +y, radians.
        #[serde(default)]
        yaw: f64,
    },
    /// A vertical cylinder (axis along +y).
    Cylinder {
        /// Radius.
        radius: f64,
        /// Half of its height.
        half_height: f64,
        /// Centre in the object's frame.
        #[serde(default)]
        offset: [f64; 3],
        /// Yaw about +y, radians (irrelevant for collision, kept for rendering).
        #[serde(default)]
        yaw: f64,
    },
    /// The convex hull of a point set.
    ConvexHull {
        /// At least four points, not all in one plane.
        points: Vec<[f64; 3]>,
        /// Translation applied to the points.
        #[serde(default)]
        offset: [f64; 3],
        /// Yaw about +y applied to the points, radians.
        #[serde(default)]
        yaw: f64,
    },
}

impl Part {
    /// The part's placement in the object's frame: offset and yaw.
    pub fn placement(&self) -> ([f64; 3], f64) {
        match self {
            Part::Box { offset, yaw, .. }
            | Part::Cylinder { offset, yaw, .. }
            | Part::ConvexHull { offset, yaw, .. } => (*offset, *yaw),
        }
    }
}

/// A triangle mesh in the object's frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mesh {
    /// Vertex positions.
    pub vertices: Vec<[f64; 3]>,
    /// Triangles as indices into `vertices`, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
}

impl Scene {
    /// Parses a scene from JSON. Only the syntax and field types are checked here; use
    /// [`crate::CompiledScene::new`] to validate it.
    pub fn from_json(text: &str) -> Result<Scene, crate::SceneError> {
        serde_json::from_str(text).map_err(|e| crate::SceneError::Json { message: e.to_string() })
    }

    /// The scene as pretty-printed JSON.
    pub fn to_json_pretty(&self) -> String {
        // Serialising plain data with string keys cannot fail.
        serde_json::to_string_pretty(self).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_unknown_schema_message_names_the_schema_read() {
        let message = crate::SceneError::UnknownSchema { found: "esrp.scene/v2".into() }.to_string();
        assert!(message.ends_with(&format!("this server reads {SCENE_SCHEMA:?}")), "{message}");
    }
}
