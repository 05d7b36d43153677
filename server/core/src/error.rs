//! Typed errors: what was wrong with a scene or a request, and how to fix it. A leaf: it
//! names no other module of the crate.

/// Which of a scene's two layouts a problem was found in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// Movable objects at their initial poses (`pose`).
    Initial,
    /// Movable objects at their target poses (`target`).
    Target,
}

impl std::fmt::Display for Layout {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Layout::Initial => "initial layout (`pose`)",
            Layout::Target => "target layout (`target`)",
        })
    }
}

/// Why a scene was rejected. Every variant names the offending item.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SceneError {
    /// The text is not a JSON scene of the expected shape.
    #[error("scene JSON is malformed: {message}")]
    Json {
        /// The parser's message, with line and column.
        message: String,
    },
    /// The `schema` field names a format this version does not read (the one it reads is
    /// `crate::scene::SCENE_SCHEMA`; a test in `scene` keeps the message in step with it).
    #[error("unknown scene schema {found:?}: this server reads \"esrp.scene/v1\"")]
    UnknownSchema {
        /// The schema string found.
        found: String,
    },
    /// A number is NaN or infinite.
    #[error("`{path}` is not a finite number: every coordinate and size must be finite")]
    NonFinite {
        /// Where, e.g. `movable_objects[2].pose.x`.
        path: String,
    },
    /// A number is larger in magnitude than any scene needs.
    #[error("`{path}` holds {value:e}: every coordinate and size (metres) and angle (radians) must be within ±{max}")]
    OutOfRange {
        /// Where, e.g. `fixed_objects[0].shape.parts[0].half_extents`.
        path: String,
        /// The number.
        value: f64,
        /// The bound, `MAX_SCENE_NUMBER`.
        max: f64,
    },
    /// A required text field is empty.
    #[error("`{field}` must not be empty")]
    EmptyField {
        /// Which field.
        field: String,
    },
    /// The floor polygon or the wall parameters are unusable.
    #[error("invalid room: {reason}")]
    InvalidRoom {
        /// What is wrong.
        reason: String,
    },
    /// A wall opening is unusable.
    #[error("invalid opening `room.openings[{index}]`: {reason}")]
    InvalidOpening {
        /// Index in `room.openings`.
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// An object's shape is empty or degenerate.
    #[error("object `{object}` has an unusable shape: {reason}")]
    InvalidShape {
        /// The object's id.
        object: String,
        /// What is wrong.
        reason: String,
    },
    /// Two objects share an id.
    #[error("object id `{id}` is used twice: ids must be unique across fixed and movable objects")]
    DuplicateId {
        /// The repeated id.
        id: String,
    },
    /// The scene has no movable object, so there is nothing to rearrange.
    #[error("the scene has no movable object: give it 1 to 6 `movable_objects`")]
    NoMovableObjects,
    /// More floor vertices, objects, parts or mesh elements than a scene may have (the bounds are
    /// `crate::compile`'s `MAX_*` constants).
    #[error("the scene has {count} {what}: at most {max} are allowed")]
    TooLarge {
        /// What is counted, e.g. "floor vertices".
        what: &'static str,
        /// How many there are.
        count: usize,
        /// The bound.
        max: usize,
    },
    /// More than six movable objects.
    #[error("the scene has {count} movable objects: at most 6 are allowed")]
    TooManyMovableObjects {
        /// How many there are.
        count: usize,
    },
    /// `difficulty` disagrees with the number of movable objects.
    #[error("difficulty `{difficulty}` does not match {count} movable object(s): easy is 1, medium 2–3, hard 4–6")]
    DifficultyMismatch {
        /// The declared difficulty.
        difficulty: &'static str,
        /// The number of movable objects.
        count: usize,
    },
    /// An object's footprint centre is not inside the floor polygon.
    #[error("object `{object}` is outside the room in the {layout}: its footprint centre must lie inside `room.floor`")]
    OutsideRoom {
        /// The object's id.
        object: String,
        /// Which layout.
        layout: Layout,
    },
    /// A movable object touches another object or a wall, or is closer than the collision
    /// margin.
    #[error(
        "object `{object}` overlaps `{other}` in the {layout} (or is closer than the collision margin of {margin} m): move them apart"
    )]
    Overlap {
        /// The movable object's id.
        object: String,
        /// The other object's id, or `wall N`.
        other: String,
        /// Which layout.
        layout: Layout,
        /// The collision margin in metres.
        margin: f64,
    },
    /// The agent's start pose is outside the room or in collision.
    #[error("the agent starts in collision with `{obstacle}` (or closer than the collision margin): move `agent`")]
    AgentInCollision {
        /// The obstacle's id, or `wall N`.
        obstacle: String,
    },
    /// The agent's start position is not on the floor.
    #[error("the agent starts outside the room: `agent` must lie inside `room.floor`")]
    AgentOutsideRoom,
    /// Every object is already placed at the start: the episode would be won at step 0.
    #[error("every movable object is already placed in the initial layout: there is nothing to rearrange")]
    AlreadySolved,
    /// The horizon is zero.
    #[error("`horizon` must be at least 1 step")]
    ZeroHorizon,
    /// A rule parameter is out of range.
    #[error("invalid rules: {reason}")]
    InvalidRules {
        /// What is wrong.
        reason: String,
    },
}

/// Why an episode call was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum EpisodeError {
    /// The episode has terminated or been truncated; no more steps are taken.
    #[error("the episode is over ({reason}) after {steps} steps: reset it or create a new one")]
    Finished {
        /// `success` or `horizon reached`.
        reason: &'static str,
        /// Steps taken.
        steps: u32,
    },
    /// The configuration is unusable.
    #[error("invalid episode configuration: {reason}")]
    InvalidConfig {
        /// What is wrong.
        reason: String,
    },
    /// The collision library failed (panicked) on this scene; the episode takes no more steps.
    #[error(
        "the collision check failed on this scene ({message}) after {steps} steps: the episode takes no more \
         steps (its scene's numbers are out of what the library handles)"
    )]
    Failed {
        /// What the library said.
        message: String,
        /// Steps taken before the failure.
        steps: u32,
    },
}

/// Runs `work`, turning a panic in it (the collision library's, on extreme numbers) into its
/// message: the one place the simulator catches panics.
pub fn guarded<T>(work: impl FnOnce() -> T) -> Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(work)).map_err(|payload| {
        payload
            .downcast_ref::<&str>()
            .map(|s| (*s).to_owned())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "a panic without a message".to_owned())
    })
}
