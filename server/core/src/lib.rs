//! **esrp-core**: the Embodied Scene Rearrangement Planning task itself, as a pure library.
//!
//! An agent (a mobile base, a vertical cylinder of radius 0.30 m) moves in a room in steps of
//! 0.25 m and turns of 22.5°, fetches movable objects within 1.0 m and releases them, until every
//! object's footprint overlaps its target with IoU > 0.3. Every motion is checked for collision
//! along its whole sweep against full 3D shapes, with parry's linear shape cast for translations
//! and a rotational shape cast by conservative advancement over parry's distance queries for
//! rotations, and rejected whole if it would collide. The rules
//! are those of `SPEC.md` §1–6 in the project's shared documents.
//!
//! # Module map
//!
//! - [`scene`]: the scene format `esrp.scene/v1` (plain serde data, documented there with an
//!   example).
//! - [`world`]: the data of a [`CompiledScene`] — the task's constants, rules, obstacles, wall
//!   pieces, footprints and collision shapes; immutable and shared by every episode of a scene.
//! - `compile`: [`CompiledScene::new`] — validation ([`SceneError`]) and building the collision
//!   world, clearances checked through `collision`.
//! - `shapes`: poses and wall boxes as parry shapes, for `compile` and `collision` alike.
//! - [`collision`]: every collision question, asked without an episode — pose conversion, wall
//!   boxes, "does this body fit here" ([`collision::obstruction`]) and "what does this motion hit
//!   first" ([`collision::first_hit`]); [`Episode::step`] and the planners ask the same functions.
//! - [`error`]: [`SceneError`] and [`EpisodeError`], a leaf every module may use.
//! - [`episode`]: [`Episode`] — the mutable state and the one [`Episode::step`]; outcomes,
//!   rewards, metrics, privileged state and the camera pose for renderers.
//! - [`metrics`]: aggregation of episode metrics over many episodes (SR, OSR, RDR, stages,
//!   per difficulty).
//! - [`geometry`]: plan geometry — oriented rectangles, exact polygon IoU, predicates.
//! - [`heading`] and [`action`]: the 16 headings with an exact sine table, and the six actions.
//!
//! # Invariants
//!
//! - **No I/O, no GPU, no network.** The crate reads and writes nothing; parsing JSON from a
//!   string is the only contact with the outside.
//! - **Deterministic and portable.** `f64` state; headings are integers with a literal sine
//!   table; the agent's position is its start plus integer move counts; parry is built with
//!   `enhanced-determinism` (libm, scalar math). Same scene and same actions give bit-identical
//!   states on every run, under any load, and a motion followed by its inverse restores the
//!   state exactly. Across platforms the agent's position and heading and every collision answer
//!   are exact; an object's footprint corners at its yaw, IoU and distances use the standard
//!   library's `sin_cos`, `hypot` and `atan2` (the platform's maths library: glibc on Linux),
//!   so a decision exactly at a threshold (placed, within reach) could differ in its last bit on
//!   another one.
//! - **Nothing panics on input.** Every scene is validated into a typed [`SceneError`] that names
//!   the offending item before any episode exists; a rejected motion is data in the
//!   [`StepOutcome`], not an error; the only step error is stepping a finished episode.
//! - **One simulator.** Dataset generation, the server and the planners all step this code, so
//!   an expert trajectory that replays here replays everywhere.
//! - **Data below processing, no import circle.** `scene`, `error`, `geometry`, `heading` and
//!   `world` are data; `shapes`, `collision`, `compile` and `episode` process it; no module
//!   imports one that imports it (`scripts/module_cycles.py`, run by the tests).
//!
//! # Example
//!
//! ```
//! use esrp_core::{Action, CompiledScene, Episode, EpisodeConfig, Scene};
//!
//! let text = include_str!("../examples/scenes/bedroom.json");
//! let scene = CompiledScene::shared(Scene::from_json(text)?)?;
//! let expert = scene.scene().expert_trajectory.clone();
//! let mut episode = Episode::new(scene, EpisodeConfig::default())?;
//! for action in expert {
//!     episode.step(action)?;
//! }
//! assert!(episode.metrics().success);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]

pub mod action;
pub mod collision;
mod compile;
pub mod episode;
pub mod error;
pub mod geometry;
pub mod heading;
pub mod metrics;
pub mod scene;
mod shapes;
pub mod world;

pub use action::{Action, UnknownAction, reverse_trajectory};
pub use compile::{
    MAX_FIXED_OBJECTS, MAX_FLOOR_VERTICES, MAX_MESH_TRIANGLES, MAX_MESH_VERTICES, MAX_OPENINGS, MAX_PARTS,
    MAX_SCENE_NUMBER,
};
pub use episode::{
    AgentPose, EgoCamera, Episode, EpisodeConfig, EpisodeMetrics, EpisodeStatus, MAX_REWARD_WEIGHT, NoOpReason,
    ObjectState, PrivilegedState, RewardTerms, RewardWeights, Stage, StaticObstacle, StepOutcome,
};
pub use error::{EpisodeError, Layout, SceneError, guarded};
pub use geometry::{OrientedRect, PlanPoint, footprint_iou};
pub use heading::{HEADING_COUNT, Heading, TURN_ANGLE};
pub use metrics::{AggregateMetrics, MetricsSummary};
pub use scene::{
    AgentStart, Difficulty, FixedObject, Mesh, MovableCategory, MovableObject, ObjectPose, Opening, OpeningKind, Part,
    Room, SCENE_SCHEMA, Scene, Shape, Split,
};
pub use world::{CompiledScene, LocalFootprint, Obstacle, Rules, WallPiece, WallPieceKind};

/// Re-export of the collision library, so that users can run their own queries on the shapes
/// this crate builds with the same version.
pub use parry3d;
