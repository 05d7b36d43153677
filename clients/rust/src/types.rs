//! The values a client sends and receives, typed: actions, observations with zero-copy pixel
//! access, step results, metrics and scene summaries. Each converts from its `esrp.v1` message
//! with a check of what the message must hold, so a malformed answer is a
//! [`ClientError::Protocol`], never a panic.

use std::fmt;
use std::str::FromStr;

use bytes::Bytes;

use crate::error::{ClientError, Result};
use crate::proto;

/// One of the six actions, with the codes of the task's specification (SPEC §3).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[repr(u8)]
pub enum Action {
    /// Move 0.25 m forward.
    MoveForward = 0,
    /// Move 0.25 m backward.
    MoveBackward = 1,
    /// Turn 22.5° left (counter-clockwise seen from above).
    TurnLeft = 2,
    /// Turn 22.5° right.
    TurnRight = 3,
    /// Fetch the nearest movable object within 1.0 m.
    Fetch = 4,
    /// Release the held object where it is.
    Release = 5,
}

impl Action {
    /// All actions, in code order.
    pub const ALL: [Action; 6] = [
        Action::MoveForward,
        Action::MoveBackward,
        Action::TurnLeft,
        Action::TurnRight,
        Action::Fetch,
        Action::Release,
    ];

    /// The action's integer code (0..=5).
    pub fn code(self) -> u8 {
        self as u8
    }

    /// The action's name as the API spells it (`move_forward`, ..., `release`).
    pub fn name(self) -> &'static str {
        match self {
            Action::MoveForward => "move_forward",
            Action::MoveBackward => "move_backward",
            Action::TurnLeft => "turn_left",
            Action::TurnRight => "turn_right",
            Action::Fetch => "fetch",
            Action::Release => "release",
        }
    }
}

impl fmt::Display for Action {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl TryFrom<i64> for Action {
    type Error = ClientError;

    fn try_from(code: i64) -> Result<Self> {
        usize::try_from(code)
            .ok()
            .and_then(|i| Action::ALL.get(i).copied())
            .ok_or_else(|| ClientError::InvalidArgument(format!("no action with code {code}: codes are 0..=5")))
    }
}

impl FromStr for Action {
    type Err = ClientError;

    /// Parses a name (`move_forward`, ...) or a code (`0`..`5`).
    fn from_str(s: &str) -> Result<Self> {
        if let Ok(code) = s.trim().parse::<i64>() {
            return Action::try_from(code);
        }
        Action::ALL.into_iter().find(|a| a.name() == s.trim()).ok_or_else(|| {
            ClientError::InvalidArgument(format!(
                "no action {s:?}: use one of move_forward, move_backward, turn_left, turn_right, fetch, release or a code 0..=5"
            ))
        })
    }
}

/// A split of the dataset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Split {
    /// The training split (90 %).
    Train,
    /// The test split (10 %).
    Test,
    /// A server's hidden challenge split (`--challenge-seed`): one counted attempt per scene.
    Challenge,
    /// The challenge's minival phase: scenes of the same hidden draw, played any number of times.
    Minival,
}

impl Split {
    /// `train`, `test`, `challenge` or `minival`.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
            Split::Challenge => "challenge",
            Split::Minival => "minival",
        }
    }

    pub(crate) fn to_proto(split: Option<Split>) -> i32 {
        (match split {
            None => proto::Split::Unspecified,
            Some(Split::Train) => proto::Split::Train,
            Some(Split::Test) => proto::Split::Test,
            Some(Split::Challenge) => proto::Split::Challenge,
            Some(Split::Minival) => proto::Split::Minival,
        }) as i32
    }

    fn from_proto(value: i32) -> Option<Split> {
        match proto::Split::try_from(value) {
            Ok(proto::Split::Train) => Some(Split::Train),
            Ok(proto::Split::Test) => Some(Split::Test),
            Ok(proto::Split::Challenge) => Some(Split::Challenge),
            Ok(proto::Split::Minival) => Some(Split::Minival),
            _ => None,
        }
    }
}

/// A difficulty level: Easy (1 object), Medium (2–3), Hard (4–6).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Difficulty {
    /// One movable object.
    Easy,
    /// Two or three.
    Medium,
    /// Four to six.
    Hard,
}

impl Difficulty {
    /// `easy`, `medium` or `hard`.
    pub fn name(self) -> &'static str {
        match self {
            Difficulty::Easy => "easy",
            Difficulty::Medium => "medium",
            Difficulty::Hard => "hard",
        }
    }

    pub(crate) fn to_proto(difficulty: Option<Difficulty>) -> i32 {
        (match difficulty {
            None => proto::Difficulty::Unspecified,
            Some(Difficulty::Easy) => proto::Difficulty::Easy,
            Some(Difficulty::Medium) => proto::Difficulty::Medium,
            Some(Difficulty::Hard) => proto::Difficulty::Hard,
        }) as i32
    }

    fn from_proto(value: i32) -> Option<Difficulty> {
        match proto::Difficulty::try_from(value) {
            Ok(proto::Difficulty::Easy) => Some(Difficulty::Easy),
            Ok(proto::Difficulty::Medium) => Some(Difficulty::Medium),
            Ok(proto::Difficulty::Hard) => Some(Difficulty::Hard),
            _ => None,
        }
    }
}

impl fmt::Display for Difficulty {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// An 8-bit image, row-major, `channels` bytes per pixel; the pixels are the bytes of the
/// answer (shared, never copied).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    width: u32,
    height: u32,
    channels: u32,
    data: Bytes,
}

fn checked_len(what: &str, width: u32, height: u32, per_pixel: u64, data: &Bytes) -> Result<()> {
    let expected = u64::from(width) * u64::from(height) * per_pixel;
    if data.len() as u64 != expected || width == 0 || height == 0 {
        return Err(ClientError::Protocol(format!(
            "{what} is {width}x{height} with {per_pixel} bytes per pixel but holds {} bytes",
            data.len()
        )));
    }
    Ok(())
}

impl Image {
    pub(crate) fn from_proto(what: &str, image: proto::Image) -> Result<Self> {
        checked_len(what, image.width, image.height, u64::from(image.channels), &image.data)?;
        Ok(Image { width: image.width, height: image.height, channels: image.channels, data: image.data })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Bytes per pixel (3 for RGB).
    pub fn channels(&self) -> u32 {
        self.channels
    }

    /// The pixel bytes, row-major (`height × width × channels`), shared with the answer.
    pub fn bytes(&self) -> &Bytes {
        &self.data
    }

    /// The bytes of pixel `(x, y)` (`x` to the right, `y` down), or `None` outside the image.
    pub fn pixel(&self, x: u32, y: u32) -> Option<&[u8]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let c = self.channels as usize;
        let start = (y as usize * self.width as usize + x as usize) * c;
        self.data.get(start..start + c)
    }

    /// The image as an [`image::RgbImage`] (copies the pixels); `None` unless it has 3 channels.
    #[cfg(feature = "image")]
    pub fn to_rgb_image(&self) -> Option<image::RgbImage> {
        if self.channels != 3 {
            return None;
        }
        image::RgbImage::from_raw(self.width, self.height, self.data.to_vec())
    }
}

/// A one-channel image of 4-byte little-endian values (`f32` depth or `u32` labels).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ValueImage<T> {
    width: u32,
    height: u32,
    data: Bytes,
    _values: std::marker::PhantomData<T>,
}

/// Egocentric depth, metres along the view axis (`f32`).
pub type DepthImage = ValueImage<f32>;
/// Egocentric instance segmentation: 0 background, then labels as in the API reference (`u32`).
pub type LabelImage = ValueImage<u32>;

/// A 4-byte little-endian value type of a [`ValueImage`].
pub trait PixelValue: Copy {
    /// The value from its little-endian bytes.
    fn from_le(bytes: [u8; 4]) -> Self;
}

impl PixelValue for f32 {
    fn from_le(bytes: [u8; 4]) -> Self {
        f32::from_le_bytes(bytes)
    }
}

impl PixelValue for u32 {
    fn from_le(bytes: [u8; 4]) -> Self {
        u32::from_le_bytes(bytes)
    }
}

impl<T: PixelValue> ValueImage<T> {
    fn new(what: &str, width: u32, height: u32, data: Bytes) -> Result<Self> {
        checked_len(what, width, height, 4, &data)?;
        Ok(ValueImage { width, height, data, _values: std::marker::PhantomData })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The raw little-endian bytes, row-major, shared with the answer.
    pub fn bytes(&self) -> &Bytes {
        &self.data
    }

    /// The value at `(x, y)`, or `None` outside the image.
    pub fn get(&self, x: u32, y: u32) -> Option<T> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let start = (y as usize * self.width as usize + x as usize) * 4;
        let bytes: [u8; 4] = self.data.get(start..start + 4)?.try_into().ok()?;
        Some(T::from_le(bytes))
    }

    /// Every value, row-major.
    pub fn values(&self) -> impl ExactSizeIterator<Item = T> + '_ {
        self.data.chunks_exact(4).map(|c| T::from_le([c[0], c[1], c[2], c[3]]))
    }
}

/// What the agent observes after a step (SPEC §4).
#[derive(Clone, Debug, PartialEq)]
pub struct Observation {
    /// The egocentric RGB view, `R × R × 3`.
    pub ego_rgb: Image,
    /// The top-down image of the target layout: sent at creation and reset, and on steps that
    /// ask for it; it never changes within an episode.
    pub goal_rgb: Option<Image>,
    /// Whether the agent holds an object.
    pub grasping: bool,
    /// Egocentric depth, when the episode's sensor is on.
    pub depth: Option<DepthImage>,
    /// Egocentric instance labels, when the sensor is on.
    pub segmentation: Option<LabelImage>,
    /// A top-down RGB render of the current layout, when the sensor is on.
    pub current_top_down: Option<Image>,
}

impl TryFrom<proto::Observation> for Observation {
    type Error = ClientError;

    fn try_from(o: proto::Observation) -> Result<Self> {
        let ego = o.ego_rgb.ok_or_else(|| ClientError::Protocol("an observation without ego_rgb".into()))?;
        Ok(Observation {
            ego_rgb: Image::from_proto("ego_rgb", ego)?,
            goal_rgb: o.goal_rgb.map(|g| Image::from_proto("goal_rgb", g)).transpose()?,
            grasping: o.grasping,
            depth: o.ego_depth.map(|d| ValueImage::new("ego_depth", d.width, d.height, d.data)).transpose()?,
            segmentation: o
                .ego_segmentation
                .map(|s| ValueImage::new("ego_segmentation", s.width, s.height, s.data))
                .transpose()?,
            current_top_down: o.current_top_down.map(|c| Image::from_proto("current_top_down", c)).transpose()?,
        })
    }
}

/// What a rejected motion would have hit.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Obstacle {
    /// Wall, fixed furniture or a movable object.
    pub kind: ObstacleKind,
    /// Wall index, or index among the fixed or movable objects.
    pub index: u32,
    /// The object's id, or `wall N`.
    pub name: String,
}

/// The kind of an [`Obstacle`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ObstacleKind {
    /// A wall piece.
    Wall,
    /// Fixed furniture.
    Fixed,
    /// Another movable object.
    Movable,
}

impl TryFrom<proto::Obstacle> for Obstacle {
    type Error = ClientError;

    fn try_from(o: proto::Obstacle) -> Result<Self> {
        let kind = match proto::obstacle::Kind::try_from(o.kind) {
            Ok(proto::obstacle::Kind::Wall) => ObstacleKind::Wall,
            Ok(proto::obstacle::Kind::Fixed) => ObstacleKind::Fixed,
            Ok(proto::obstacle::Kind::Movable) => ObstacleKind::Movable,
            _ => return Err(ClientError::Protocol(format!("an obstacle of unknown kind {}", o.kind))),
        };
        Ok(Obstacle { kind, index: o.index, name: o.name })
    }
}

/// A step's reward, term by term (SPEC §6).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RewardTerms {
    /// The success bonus.
    pub success: f64,
    /// Placing (+) or unplacing (−) an object.
    pub placement: f64,
    /// The potential-based shaping term.
    pub potential: f64,
    /// The bonus for holding an object.
    pub holding: f64,
    /// The living reward.
    pub living: f64,
}

/// What a step did, beside its observation and reward.
#[derive(Clone, Debug, PartialEq)]
pub struct StepInfo {
    /// Whether the action took effect.
    pub accepted: bool,
    /// What a rejected motion would have hit.
    pub collided_with: Option<Obstacle>,
    /// Why a fetch or release did nothing.
    pub no_op: Option<String>,
    /// The movable object fetched by this step.
    pub fetched: Option<u32>,
    /// The movable object released by this step.
    pub released: Option<u32>,
    /// Objects placed after the step.
    pub placed_count: u32,
    /// Steps taken so far, this one included.
    pub step_index: u32,
    /// The reward, term by term.
    pub reward_terms: RewardTerms,
}

impl TryFrom<proto::StepInfo> for StepInfo {
    type Error = ClientError;

    fn try_from(i: proto::StepInfo) -> Result<Self> {
        let terms = i.reward_terms.unwrap_or_default();
        Ok(StepInfo {
            accepted: i.accepted,
            collided_with: i.collided_with.map(Obstacle::try_from).transpose()?,
            no_op: (!i.no_op.is_empty()).then_some(i.no_op),
            fetched: i.fetched,
            released: i.released,
            placed_count: i.placed_count,
            step_index: i.step_index,
            reward_terms: RewardTerms {
                success: terms.success,
                placement: terms.placement,
                potential: terms.potential,
                holding: terms.holding,
                living: terms.living,
            },
        })
    }
}

/// An episode's metrics (SPEC §5).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpisodeMetrics {
    /// Every object placed.
    pub success: bool,
    /// OSR: the share of objects placed.
    pub object_success_rate: f64,
    /// RDR: remaining over initial distance to the targets.
    pub remaining_distance_ratio: f64,
    /// The failure stage, 1..=4 (4: success).
    pub stage: u32,
    /// Objects placed.
    pub placed: u32,
    /// Movable objects of the scene.
    pub movable_objects: u32,
    /// Steps taken.
    pub steps: u32,
    /// The sum of the rewards.
    pub total_reward: f64,
}

impl From<proto::EpisodeMetrics> for EpisodeMetrics {
    fn from(m: proto::EpisodeMetrics) -> Self {
        EpisodeMetrics {
            success: m.success,
            object_success_rate: m.object_success_rate,
            remaining_distance_ratio: m.remaining_distance_ratio,
            stage: m.stage,
            placed: m.placed,
            movable_objects: m.movable_objects,
            steps: m.steps,
            total_reward: m.total_reward,
        }
    }
}

/// The answer to a step.
#[derive(Clone, Debug, PartialEq)]
pub struct StepResult {
    /// The observation after the step.
    pub observation: Observation,
    /// The step's reward.
    pub reward: f64,
    /// Success: every object placed (the episode has ended).
    pub terminated: bool,
    /// The horizon was reached first (the episode has ended).
    pub truncated: bool,
    /// What the step did.
    pub info: StepInfo,
    /// The episode's metrics, set when it has ended.
    pub metrics: Option<EpisodeMetrics>,
}

impl StepResult {
    /// Whether the episode has ended (terminated or truncated).
    pub fn ended(&self) -> bool {
        self.terminated || self.truncated
    }
}

impl TryFrom<proto::StepResponse> for StepResult {
    type Error = ClientError;

    fn try_from(r: proto::StepResponse) -> Result<Self> {
        Ok(StepResult {
            observation: r
                .observation
                .ok_or_else(|| ClientError::Protocol("a step answer without an observation".into()))?
                .try_into()?,
            reward: r.reward,
            terminated: r.terminated,
            truncated: r.truncated,
            info: r.info.ok_or_else(|| ClientError::Protocol("a step answer without info".into()))?.try_into()?,
            metrics: r.metrics.map(EpisodeMetrics::from),
        })
    }
}

/// A scene of the served dataset.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SceneSummary {
    /// The scene's id.
    pub id: String,
    /// Its room type (3D-FRONT's names, e.g. `MasterBedroom`).
    pub room_type: String,
    /// Its difficulty.
    pub difficulty: Option<Difficulty>,
    /// Its split.
    pub split: Option<Split>,
    /// Its movable objects.
    pub movable_objects: u32,
    /// Its step limit (0 in listings of the built-in benchmark until the scene is built).
    pub horizon: u32,
    /// Its expert trajectory's length (0 like `horizon`).
    pub expert_length: u32,
}

impl From<proto::SceneSummary> for SceneSummary {
    fn from(s: proto::SceneSummary) -> Self {
        SceneSummary {
            id: s.id,
            room_type: s.room_type,
            difficulty: Difficulty::from_proto(s.difficulty),
            split: Split::from_proto(s.split),
            movable_objects: s.movable_objects,
            horizon: s.horizon,
            expert_length: s.expert_length,
        }
    }
}

/// The optional sensors of an episode, and its image size.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Sensors {
    /// Egocentric depth (float32 metres).
    pub ego_depth: bool,
    /// Egocentric instance segmentation.
    pub ego_segmentation: bool,
    /// A top-down render of the current layout.
    pub current_top_down: bool,
    /// Square image side in pixels; 0 means 128.
    pub resolution: u32,
}

/// The server's version, renderer and limits.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ServerInfo {
    /// The server's version.
    pub version: String,
    /// The renderer's adapter, e.g. `llvmpipe (LLVM 15.0.6, 256 bits)`.
    pub renderer_adapter: String,
    /// `vulkan` or `gl`.
    pub renderer_backend: String,
    /// What draws the triangles: `pipeline` or `compute` (empty from an older server).
    pub renderer_rasterizer: String,
    /// Whether the renderer runs on the CPU.
    pub software_renderer: bool,
    /// The served dataset's name.
    pub dataset: String,
    /// Episodes alive now.
    pub live_episodes: u32,
    /// The server's limits.
    pub limits: proto::ServerLimits,
}

impl From<proto::ServerInfoResponse> for ServerInfo {
    fn from(i: proto::ServerInfoResponse) -> Self {
        ServerInfo {
            version: i.version,
            renderer_adapter: i.renderer_adapter,
            renderer_backend: i.renderer_backend,
            renderer_rasterizer: i.renderer_rasterizer,
            software_renderer: i.software_renderer,
            dataset: i.dataset,
            live_episodes: i.live_episodes,
            limits: i.limits.unwrap_or_default(),
        }
    }
}

/// The goal image and where it lies on the floor.
#[derive(Clone, Debug, PartialEq)]
pub struct Goal {
    /// The top-down image of the target layout.
    pub image: Image,
    /// The image's frame: pixel ↔ floor coordinates. `None` on a hidden scene served with the
    /// paper's observation only, until the episode has ended (it gives the room's size in
    /// metres, which the paper's agent is not told).
    pub frame: Option<proto::TopDownFrame>,
}

/// The privileged state of an episode (agent and object poses, targets, obstacles, the scene
/// JSON): for planners and debugging, not for ESRP agents proper.
#[derive(Clone, Debug, PartialEq)]
pub struct PrivilegedState(pub proto::GetPrivilegedStateResponse);

impl PrivilegedState {
    /// The scene's expert trajectory, read from the scene JSON (`expert_trajectory`, action
    /// names or codes).
    pub fn expert_trajectory(&self) -> Result<Vec<Action>> {
        let scene: serde_json::Value = serde_json::from_str(&self.0.scene_json)
            .map_err(|e| ClientError::Protocol(format!("the privileged scene JSON does not parse: {e}")))?;
        let Some(list) = scene.get("expert_trajectory").and_then(|t| t.as_array()) else {
            return Err(ClientError::Protocol("the privileged scene JSON has no expert_trajectory list".into()));
        };
        list.iter()
            .map(|a| match a {
                serde_json::Value::String(name) => name.parse(),
                serde_json::Value::Number(n) => n
                    .as_i64()
                    .ok_or_else(|| ClientError::Protocol(format!("expert action {n} is not an integer")))
                    .and_then(Action::try_from),
                other => Err(ClientError::Protocol(format!("expert action {other} is neither a name nor a code"))),
            })
            .collect::<Result<_>>()
            .map_err(|e| ClientError::Protocol(format!("the expert trajectory does not read: {e}")))
    }
}

impl std::ops::Deref for PrivilegedState {
    type Target = proto::GetPrivilegedStateResponse;

    fn deref(&self) -> &Self::Target {
        &self.0
    }
}

/// Why the server's planner found no plan ([`PlanAnswer::failure`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PlanFailure {
    /// No pose from which `fetch` takes an object.
    Unreachable,
    /// No release pose places an object.
    NoPlacement,
    /// The search's node budget ran out.
    BudgetExhausted,
    /// A plan exists but does not fit the steps left before the horizon.
    TooLong,
    /// A reason this client does not know (a newer server).
    Other(i32),
}

impl PlanFailure {
    /// The reason's name as results files spell it (`unreachable`, `no_placement`,
    /// `budget_exhausted`, `too_long`, `other`).
    pub fn name(self) -> &'static str {
        match self {
            PlanFailure::Unreachable => "unreachable",
            PlanFailure::NoPlacement => "no_placement",
            PlanFailure::BudgetExhausted => "budget_exhausted",
            PlanFailure::TooLong => "too_long",
            PlanFailure::Other(_) => "other",
        }
    }

    fn from_proto(code: i32) -> Option<Self> {
        match proto::PlanFailure::try_from(code) {
            Ok(proto::PlanFailure::Unspecified) => None,
            Ok(proto::PlanFailure::Unreachable) => Some(PlanFailure::Unreachable),
            Ok(proto::PlanFailure::NoPlacement) => Some(PlanFailure::NoPlacement),
            Ok(proto::PlanFailure::BudgetExhausted) => Some(PlanFailure::BudgetExhausted),
            Ok(proto::PlanFailure::TooLong) => Some(PlanFailure::TooLong),
            Err(_) => Some(PlanFailure::Other(code)),
        }
    }
}

/// What the planning that made a plan cost.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PlanStats {
    /// Search nodes expanded.
    pub nodes_expanded: u64,
    /// Searches run.
    pub searches: u32,
    /// Planning time on the server.
    pub planning_seconds: f64,
    /// Blockers moved aside to a buffer pose.
    pub objects_relocated: u32,
}

/// The server planner's answer ([`crate::Episode::plan_actions`]).
#[derive(Clone, Debug, PartialEq)]
pub struct PlanAnswer {
    /// The next actions of the plan (all of it, or at most the number asked for); with a
    /// [`PlanAnswer::failure`], the next of the actions the planner took before it failed
    /// (they place what they can; possibly none).
    pub actions: Vec<Action>,
    /// Whether the plan ends in success.
    pub reaches_success: bool,
    /// Length of the whole plan from the episode's current state.
    pub plan_length: u32,
    /// The plan was made by an earlier call and the episode has followed it.
    pub cached: bool,
    /// The cost of the planning that made the plan.
    pub stats: PlanStats,
    /// Why there is no plan, if there is none.
    pub failure: Option<PlanFailure>,
    /// The failure in the server's words (empty when a plan was found).
    pub failure_message: String,
    /// The id of the object a failure is about, if any.
    pub failure_object: Option<String>,
}

impl TryFrom<proto::PlanActionsResponse> for PlanAnswer {
    type Error = ClientError;

    fn try_from(r: proto::PlanActionsResponse) -> Result<Self> {
        let actions = r
            .actions
            .iter()
            .map(|&code| Action::try_from(i64::from(code)))
            .collect::<Result<Vec<_>>>()
            .map_err(|e| ClientError::Protocol(format!("the planner's answer holds a bad action: {e}")))?;
        let stats = r.stats.map_or_else(PlanStats::default, |s| PlanStats {
            nodes_expanded: s.nodes_expanded,
            searches: s.searches,
            planning_seconds: s.planning_seconds,
            objects_relocated: s.objects_relocated,
        });
        Ok(PlanAnswer {
            actions,
            reaches_success: r.reaches_success,
            plan_length: r.plan_length,
            cached: r.cached,
            stats,
            failure: PlanFailure::from_proto(r.failure),
            failure_message: r.failure_message,
            failure_object: (!r.failure_object.is_empty()).then_some(r.failure_object),
        })
    }
}

/// Which scene an episode plays.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SceneChoice {
    /// A scene of the served dataset, by id.
    Id(String),
    /// An inline scene (`esrp.scene/v1` JSON).
    Json(String),
    /// A scene of `split` picked deterministically from `seed` (index `seed mod count`).
    Seeded {
        /// The split (test when `None`).
        split: Option<Split>,
        /// The seed.
        seed: u64,
    },
}

/// The error for an empty scene id, which the protocol reads as "no scene".
pub(crate) fn empty_scene_id() -> ClientError {
    ClientError::InvalidArgument(
        "the scene id is empty: give the id of a served scene (Client::list_scenes lists them), or pick one with EpisodeOptions::seeded".into(),
    )
}

/// How to create an episode: the scene, the horizon, the reward weights, the sensors and
/// whether privileged state may be read.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeOptions {
    /// The scene.
    pub scene: SceneChoice,
    /// The step limit; 0: the scene's own.
    pub horizon: u32,
    /// Reward weights (the server's defaults for fields left `None`).
    pub reward: Option<proto::RewardWeights>,
    /// Optional sensors and the image size.
    pub sensors: Sensors,
    /// Allow [`crate::Episode::privileged_state`].
    pub privileged: bool,
    /// The agent's name, kept in the server's records of the episode (empty: "unnamed").
    pub agent: String,
}

impl EpisodeOptions {
    /// An episode of the served scene `id` (an empty `id` fails the create with
    /// [`ClientError::InvalidArgument`]).
    pub fn scene(id: impl Into<String>) -> Self {
        Self::with_scene(SceneChoice::Id(id.into()))
    }

    /// An episode of an inline scene (`esrp.scene/v1` JSON).
    pub fn scene_json(json: impl Into<String>) -> Self {
        Self::with_scene(SceneChoice::Json(json.into()))
    }

    /// An episode of a scene of `split` chosen from `seed`.
    pub fn seeded(split: Split, seed: u64) -> Self {
        Self::with_scene(SceneChoice::Seeded { split: Some(split), seed })
    }

    fn with_scene(scene: SceneChoice) -> Self {
        EpisodeOptions {
            scene,
            horizon: 0,
            reward: None,
            sensors: Sensors::default(),
            privileged: false,
            agent: String::new(),
        }
    }

    /// Sets the step limit (0: the scene's own).
    pub fn horizon(mut self, horizon: u32) -> Self {
        self.horizon = horizon;
        self
    }

    /// Sets the sensors and image size.
    pub fn sensors(mut self, sensors: Sensors) -> Self {
        self.sensors = sensors;
        self
    }

    /// Sets the reward weights.
    pub fn reward(mut self, reward: proto::RewardWeights) -> Self {
        self.reward = Some(reward);
        self
    }

    /// Allows reading the privileged state (for planners and debugging).
    pub fn privileged(mut self, privileged: bool) -> Self {
        self.privileged = privileged;
        self
    }

    /// Names the agent in the server's records of the episode (`--records`), e.g.
    /// `"my-planner v2"`: at most 200 bytes.
    pub fn agent(mut self, agent: impl Into<String>) -> Self {
        self.agent = agent.into();
        self
    }

    /// Refuses options the server would read as something else: an empty scene id is the
    /// protocol's "no scene", which the server answers with a scene of the test split.
    pub(crate) fn check(&self) -> Result<()> {
        match &self.scene {
            SceneChoice::Id(id) if id.is_empty() => Err(empty_scene_id()),
            _ => Ok(()),
        }
    }

    /// The `CreateEpisode` request these options make.
    pub fn to_proto(&self) -> proto::CreateEpisodeRequest {
        use proto::create_episode_request::Scene;
        let (scene, split, seed) = match &self.scene {
            SceneChoice::Id(id) => (Some(Scene::SceneId(id.clone())), None, 0),
            SceneChoice::Json(json) => (Some(Scene::SceneJson(json.clone())), None, 0),
            SceneChoice::Seeded { split, seed } => (None, *split, *seed),
        };
        proto::CreateEpisodeRequest {
            scene,
            split: Split::to_proto(split),
            seed,
            horizon: self.horizon,
            reward: self.reward,
            sensors: Some(proto::Sensors {
                ego_depth: self.sensors.ego_depth,
                ego_segmentation: self.sensors.ego_segmentation,
                current_top_down: self.sensors.current_top_down,
                resolution: self.sensors.resolution,
            }),
            privileged: self.privileged,
            agent: self.agent.clone(),
        }
    }
}
