//! The values the episode layer speaks: ids, what a protocol adapter converts its messages into
//! and out of, and the answers. Plain data, the leaf of the crate's modules: it imports no other
//! module of the service, and nothing here knows a protocol.

use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use esrp_core::{Action, Difficulty, EpisodeMetrics, RewardWeights, Split, StepOutcome};
use esrp_planner::{PlanFailure, PlanStats};

/// The id of a live episode: 32 lowercase hex digits (a random 128-bit UUID), unguessable.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct EpisodeId(String);

impl EpisodeId {
    /// A fresh random id.
    pub fn random() -> Self {
        Self(uuid::Uuid::new_v4().simple().to_string())
    }

    /// The id as text.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl From<String> for EpisodeId {
    /// Any text names an episode; an id the registry never gave is simply unknown.
    fn from(id: String) -> Self {
        Self(id)
    }
}

impl From<&str> for EpisodeId {
    fn from(id: &str) -> Self {
        Self(id.to_owned())
    }
}

impl From<EpisodeId> for String {
    fn from(id: EpisodeId) -> Self {
        id.0
    }
}

impl std::fmt::Display for EpisodeId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// Which scene an episode plays.
#[derive(Clone, Debug, PartialEq)]
pub enum SceneChoice {
    /// A scene of the served dataset, by id.
    SceneId(String),
    /// A scene given as esrp-scene-v1 JSON.
    SceneJson(String),
    /// A scene of `split` (test if `None`): index `seed mod count` among that split's scenes.
    FromSplit {
        /// The split to choose from.
        split: Option<Split>,
        /// Which of its scenes.
        seed: u64,
    },
}

/// The sensors a client asks for; [`SensorConfig`] once validated.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SensorRequest {
    /// Egocentric depth.
    pub depth: bool,
    /// Egocentric instance segmentation.
    pub segmentation: bool,
    /// Top-down view of the current layout.
    pub current_top_down: bool,
    /// Square image side, pixels; `None` for the default (128).
    pub resolution: Option<u32>,
}

/// The sensors of an episode, validated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SensorConfig {
    /// Egocentric depth.
    pub depth: bool,
    /// Egocentric instance segmentation.
    pub segmentation: bool,
    /// Top-down view of the current layout.
    pub current_top_down: bool,
    /// Square image side, pixels.
    pub resolution: u32,
}

/// How to create an episode.
#[derive(Clone, Debug, PartialEq)]
pub struct CreateOptions {
    /// Its scene.
    pub scene: SceneChoice,
    /// Its sensors.
    pub sensors: SensorRequest,
    /// Step limit; `None` for the scene's own.
    pub horizon: Option<u32>,
    /// Reward weights.
    pub reward: RewardWeights,
    /// Whether GetPrivilegedState is allowed.
    pub privileged: bool,
    /// The agent's name for the server's records (`None`: "unnamed"); at most
    /// [`MAX_AGENT_LABEL`] bytes.
    pub agent: Option<String>,
    /// Keep each run's record with the episode once it ends (and write it to the server's
    /// records, if it keeps any, whatever `--record` says): the web viewer's human play.
    pub keep_record: bool,
}

/// The longest agent label a create may give, bytes.
pub const MAX_AGENT_LABEL: usize = 200;

/// What a token may do.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Ordinary episodes only: no privileged episodes, privileged state, plans or expert
    /// trajectories, on any split.
    Agent,
    /// Also privileged episodes and the planner, but never on the challenge's scenes.
    Trainer,
    /// Everything, including other tokens' episodes.
    Admin,
}

impl Role {
    /// `agent`, `trainer` or `admin`.
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Agent => "agent",
            Role::Trainer => "trainer",
            Role::Admin => "admin",
        }
    }
}

/// Who makes a call: its token's name, role and quotas. A server without tokens takes every
/// call for [`Caller::anonymous`], an admin.
#[derive(Debug, PartialEq, Eq)]
pub struct Caller {
    /// The token's name (logs, metrics, records; a file name of `--records`).
    pub name: Arc<str>,
    /// What it may do.
    pub role: Role,
    /// Most live episodes at once (`None`: only the server's limit).
    pub max_episodes: Option<usize>,
    /// Most open streams (StepStream, dm_env_rpc connections) at once.
    pub max_streams: Option<usize>,
}

impl Caller {
    /// The caller of a server without tokens: an admin named `anonymous`.
    pub fn anonymous() -> Arc<Caller> {
        Arc::new(Caller { name: "anonymous".into(), role: Role::Admin, max_episodes: None, max_streams: None })
    }

    /// Whether it is an admin.
    pub fn is_admin(&self) -> bool {
        self.role == Role::Admin
    }

    /// `token "alice" (role agent)`, for messages.
    pub fn describe(&self) -> String {
        format!("token {:?} (role {})", &*self.name, self.role.as_str())
    }
}

/// The element type of an observation array.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ElementType {
    /// `u8` (images).
    Uint8,
    /// `f32` (depth).
    Float32,
    /// `u32` (segmentation ids).
    Uint32,
    /// `bool` (grasping).
    Bool,
}

impl ElementType {
    /// Its numpy name: `uint8`, `float32`, `uint32` or `bool`.
    pub fn name(self) -> &'static str {
        match self {
            ElementType::Uint8 => "uint8",
            ElementType::Float32 => "float32",
            ElementType::Uint32 => "uint32",
            ElementType::Bool => "bool",
        }
    }
}

/// One array of an observation.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ArraySpec {
    /// Its name (`ego_rgb`, `goal_rgb`, `grasping`, `ego_depth`, `ego_segmentation`,
    /// `current_top_down`).
    pub name: &'static str,
    /// Its shape.
    pub shape: Vec<u32>,
    /// Its element type.
    pub element_type: ElementType,
}

/// The action names by code (SPEC §3).
pub const ACTIONS: [&str; 6] = ["move_forward", "move_backward", "turn_left", "turn_right", "fetch", "release"];

impl SensorConfig {
    /// The arrays of an observation of these sensors, in order: `ego_rgb`, `goal_rgb`,
    /// `grasping`, then the optional sensors that are on.
    pub fn observation_spec(&self) -> Vec<ArraySpec> {
        let r = self.resolution;
        let array = |name, shape, element_type| ArraySpec { name, shape, element_type };
        let mut arrays = vec![
            array("ego_rgb", vec![r, r, 3], ElementType::Uint8),
            array("goal_rgb", vec![r, r, 3], ElementType::Uint8),
            array("grasping", vec![], ElementType::Bool),
        ];
        if self.depth {
            arrays.push(array("ego_depth", vec![r, r], ElementType::Float32));
        }
        if self.segmentation {
            arrays.push(array("ego_segmentation", vec![r, r], ElementType::Uint32));
        }
        if self.current_top_down {
            arrays.push(array("current_top_down", vec![r, r, 3], ElementType::Uint8));
        }
        arrays
    }

    /// An upper bound of the encoded size of one step's answer, bytes.
    pub fn answer_bytes(&self, include_goal: bool) -> usize {
        let pixels = (self.resolution as usize).pow(2);
        let mut bytes = 512 + pixels * 3;
        bytes += usize::from(self.depth) * pixels * 4;
        bytes += usize::from(self.segmentation) * pixels * 4;
        bytes += usize::from(self.current_top_down) * pixels * 3;
        bytes += usize::from(include_goal) * pixels * 3;
        bytes
    }
}

/// What an agent observes: images as they came from the render readback (`Bytes`, shared,
/// never copied on their way to a message), square with side `resolution`, row-major, top row
/// first.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Observation {
    /// Square image side, pixels.
    pub resolution: u32,
    /// Egocentric RGB, 3 bytes a pixel.
    pub ego_rgb: Bytes,
    /// The goal (top-down view of the target layout), where asked for.
    pub goal_rgb: Option<Bytes>,
    /// Whether the agent holds an object.
    pub grasping: bool,
    /// Egocentric view depth, metres, where the sensor is on.
    pub depth: Option<Vec<f32>>,
    /// Egocentric instance segmentation ids, where the sensor is on.
    pub segmentation: Option<Vec<u32>>,
    /// Top-down view of the current layout, where the sensor is on.
    pub current_top_down: Option<Bytes>,
}

/// A step to take.
#[derive(Clone, Debug, PartialEq)]
pub struct StepCall {
    /// The episode.
    pub episode: EpisodeId,
    /// The action.
    pub action: Action,
    /// Whether the answer carries the goal image.
    pub include_goal: bool,
}

/// A reset to take (in a StepBatch).
#[derive(Clone, Debug, PartialEq)]
pub struct ResetCall {
    /// The episode.
    pub episode: EpisodeId,
    /// Its new scene, if any.
    pub scene: Option<SceneChoice>,
}

/// The answer to a step.
#[derive(Clone, Debug, PartialEq)]
pub struct StepResult {
    /// What the agent observes after the step.
    pub observation: Observation,
    /// What the step did: reward terms, collision, no-op, fetch and release, termination.
    pub outcome: StepOutcome,
    /// The name of the obstacle a rejected motion hit, if any.
    pub collided_with_name: Option<String>,
    /// The episode's final metrics, if this step ended it.
    pub metrics: Option<EpisodeMetrics>,
}

impl StepResult {
    /// Empties what the paper's agent does not observe: the reward and its terms, the placed
    /// count, whether the action took effect, the collision and its obstacle, a fetch's or a
    /// release's outcome. The step index, the end flags and the final metrics stay.
    pub fn keep_paper_observation(&mut self) {
        let outcome = &mut self.outcome;
        outcome.reward = Default::default();
        outcome.placed_count = 0;
        outcome.accepted = false;
        outcome.collided_with = None;
        outcome.no_op = None;
        outcome.fetched = None;
        outcome.released = None;
        self.collided_with_name = None;
    }
}

/// The answer to a create.
#[derive(Clone, Debug)]
pub struct Created {
    /// The new episode.
    pub episode: EpisodeId,
    /// Its sensors.
    pub sensors: SensorConfig,
    /// Its first observation (with the goal image).
    pub observation: Observation,
    /// Its scene.
    pub scene: SceneInfo,
}

/// The answer to a reset.
#[derive(Clone, Debug)]
pub struct ResetResult {
    /// The first observation of the new run (with the goal image).
    pub observation: Observation,
    /// Its scene.
    pub scene: SceneInfo,
}

/// An episode's goal image and its pixel ↔ floor mapping.
#[derive(Clone, Debug)]
pub struct Goal {
    /// Top-down view of the target layout, RGB.
    pub rgb: Bytes,
    /// Its side, pixels.
    pub resolution: u32,
    /// Its pixel ↔ floor mapping; `None` on a paper-only episode that has not ended (the room's
    /// size in metres is not part of the paper's observation).
    pub frame: Option<esrp_render::TopDownFrame>,
}

/// An episode's privileged state and the scene it refers to.
pub struct Privileged {
    /// The state.
    pub state: esrp_core::PrivilegedState,
    /// The scene.
    pub scene: Arc<esrp_core::CompiledScene>,
}

/// The metrics of an episode so far.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MetricsSoFar {
    /// The metrics.
    pub metrics: EpisodeMetrics,
    /// Whether the episode has ended (the metrics are final).
    pub ended: bool,
}

/// A scene's summary, known without building it where possible.
#[derive(Clone, Debug)]
pub struct SceneInfo {
    /// Scene id.
    pub id: String,
    /// Room type.
    pub room_type: String,
    /// Difficulty.
    pub difficulty: Difficulty,
    /// Split.
    pub split: Split,
    /// Movable objects.
    pub movable_objects: usize,
    /// Horizon and expert length, once known (0 until the scene is built).
    pub horizon: u32,
    /// Expert trajectory length, once known.
    pub expert_length: usize,
}

/// A PlanActions call.
#[derive(Clone, Debug)]
pub struct PlanCall {
    /// The episode.
    pub episode: EpisodeId,
    /// At most this many next actions; 0: all.
    pub max_actions: u32,
    /// The time budget; `None`: the server's default.
    pub budget: Option<Duration>,
}

/// The answer to a PlanActions call.
#[derive(Clone, Debug)]
pub struct Planned {
    /// The next actions (at most `max_actions`); with a failure, the next of the actions the
    /// planner took before it failed (they place what they can).
    pub actions: Vec<Action>,
    /// Whether the plan ends in success (false: there is no plan, see `failure`).
    pub reaches_success: bool,
    /// Length of the whole plan from the current state.
    pub plan_length: u32,
    /// Answered from the cache.
    pub cached: bool,
    /// The cost of the planning that made the answer.
    pub stats: PlanStats,
    /// Why there is no plan.
    pub failure: Option<PlanFailure>,
    /// The id of the object a failure is about.
    pub failure_object: Option<String>,
}
