//! An episode: the mutable state of one run of the task on a [`CompiledScene`], and the single
//! [`Episode::step`] that advances it.
//!
//! # Exactness
//!
//! The agent's position is not accumulated in floating point: it is the start position plus an
//! integer count of moves along each of the 8 axis pairs of the 16 headings, evaluated in a fixed
//! order. Headings are integers. A carried object's pose is computed from its pose at the fetch
//! and the agent's displacement since, with an exact table rotation. So a motion followed by its
//! inverse restores the state bit for bit, and the same scene and actions give the same state on
//! every machine.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::action::Action;
use crate::collision::{self, Body, Motion, MovableObstacles};
use crate::error::EpisodeError;
use crate::geometry::{OrientedRect, PlanPoint, footprint_iou, rotate_plan};
use crate::heading::{Heading, TURN_ANGLE};
use crate::scene::ObjectPose;
use crate::world::{CAMERA_HEIGHT, CAMERA_HORIZONTAL_FOV, CAMERA_PITCH, CompiledScene, MOVE_DISTANCE, Obstacle};

/// Weights of the reward terms of SPEC §6.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RewardWeights {
    /// Paid once, on success (default 10).
    pub success: f64,
    /// Paid when a release places an object (default 1).
    pub place: f64,
    /// Paid when a fetch takes a placed object off its goal (default −1).
    pub unplace: f64,
    /// Factor of the potential term `D_{t−1} − D_t` of the held object (default 1).
    pub potential: f64,
    /// Paid for each step that ends with an object held (default 0.01).
    pub holding: f64,
    /// Paid on every step (default 0).
    pub living: f64,
}

impl Default for RewardWeights {
    fn default() -> Self {
        Self { success: 10.0, place: 1.0, unplace: -1.0, potential: 1.0, holding: 0.01, living: 0.0 }
    }
}

/// Per-episode settings beyond the scene.
#[derive(Clone, Copy, Debug, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EpisodeConfig {
    /// Overrides the scene's horizon when set.
    pub horizon: Option<u32>,
    /// Reward weights.
    pub reward: RewardWeights,
}

/// Where an episode stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EpisodeStatus {
    /// Steps may be taken.
    Running,
    /// Every object is placed: terminated.
    Succeeded,
    /// The horizon was reached first: truncated.
    Truncated,
}

/// Why an action had no effect, other than a collision.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NoOpReason {
    /// `fetch` while already holding an object.
    AlreadyHolding,
    /// `fetch` with no movable object's footprint within reach.
    NothingInReach,
    /// `release` with nothing held.
    NothingHeld,
}

impl NoOpReason {
    /// A sentence for a person.
    pub fn message(self) -> &'static str {
        match self {
            NoOpReason::AlreadyHolding => "fetch ignored: already holding an object (release it first)",
            NoOpReason::NothingInReach => "fetch ignored: no movable object within reach",
            NoOpReason::NothingHeld => "release ignored: nothing is held",
        }
    }
}

/// The reward of one step, term by term (SPEC §6). `total` is their sum.
#[derive(Clone, Copy, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct RewardTerms {
    /// Success bonus.
    pub success: f64,
    /// Place bonus or unplace penalty.
    pub placement: f64,
    /// Potential-based shaping.
    pub potential: f64,
    /// Holding bonus.
    pub holding: f64,
    /// Living reward.
    pub living: f64,
    /// Sum of the terms.
    pub total: f64,
}

/// What one step did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepOutcome {
    /// The action taken.
    pub action: Action,
    /// Whether the action took effect (false for a collision or a no-op).
    pub accepted: bool,
    /// The first obstacle the rejected motion would have hit.
    pub collided_with: Option<Obstacle>,
    /// Why a fetch or release did nothing.
    pub no_op: Option<NoOpReason>,
    /// The movable object this step fetched.
    pub fetched: Option<usize>,
    /// The movable object this step released.
    pub released: Option<usize>,
    /// Reward of this step, term by term.
    pub reward: RewardTerms,
    /// The episode ended in success.
    pub terminated: bool,
    /// The episode reached its horizon without success.
    pub truncated: bool,
    /// Number of placed objects after the step.
    pub placed_count: usize,
    /// Step counter after the step (1 after the first step).
    pub step_index: u32,
}

impl StepOutcome {
    /// Whether a motion was rejected for a collision.
    pub fn collided(&self) -> bool {
        self.collided_with.is_some()
    }
}

/// The progress stage of SPEC §5.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(into = "u8", try_from = "u8")]
pub enum Stage {
    /// 1: never came within reach of a movable object.
    NeverReached = 1,
    /// 2: came within reach but never fetched.
    NeverFetched = 2,
    /// 3: fetched but did not succeed.
    Fetched = 3,
    /// 4: success.
    Succeeded = 4,
}

impl From<Stage> for u8 {
    fn from(s: Stage) -> u8 {
        s as u8
    }
}

impl TryFrom<u8> for Stage {
    type Error = String;
    fn try_from(v: u8) -> Result<Self, String> {
        match v {
            1 => Ok(Stage::NeverReached),
            2 => Ok(Stage::NeverFetched),
            3 => Ok(Stage::Fetched),
            4 => Ok(Stage::Succeeded),
            other => Err(format!("stage {other} is not in 1..=4")),
        }
    }
}

/// Metrics of one episode so far (SPEC §5). Final once the episode has ended.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeMetrics {
    /// `S`: every object placed.
    pub success: bool,
    /// `OSR = placed / M`.
    pub object_success_rate: f64,
    /// `RDR = D_now / D_start`; 0 when `D_start = 0` (possible only for a hand-made scene with an
    /// object turned on its target's centre; SPEC §5 leaves `0 / 0` open), so that it is always a
    /// number.
    pub remaining_distance_ratio: f64,
    /// Progress stage 1–4.
    pub stage: Stage,
    /// Placed objects.
    pub placed: usize,
    /// Movable objects `M`.
    pub movable_objects: usize,
    /// Steps taken.
    pub steps: u32,
    /// `D_start`, metres.
    pub distance_start: f64,
    /// `D` now, metres.
    pub distance_now: f64,
    /// Sum of the rewards so far.
    pub total_reward: f64,
}

/// The agent's pose.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AgentPose {
    /// Position on the plan.
    pub position: PlanPoint,
    /// Heading index.
    pub heading: Heading,
}

impl AgentPose {
    /// Yaw in radians.
    pub fn yaw(&self) -> f64 {
        self.heading.yaw()
    }

    /// Unit forward vector on the plan: `(cos θ, −sin θ)`.
    pub fn forward(&self) -> PlanPoint {
        PlanPoint::new(self.heading.cos(), -self.heading.sin())
    }
}

/// The egocentric camera (SPEC §2).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EgoCamera {
    /// Eye position `[x, y, z]`.
    pub eye: [f64; 3],
    /// Yaw of the viewing direction (the agent's heading), radians.
    pub yaw: f64,
    /// Downward pitch, radians (positive looks down).
    pub pitch: f64,
    /// Horizontal field of view, radians.
    pub horizontal_fov: f64,
}

/// One movable object in the privileged state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectState {
    /// The object's id.
    pub id: String,
    /// Current pose.
    pub pose: ObjectPose,
    /// Target pose.
    pub target: ObjectPose,
    /// Current footprint.
    pub footprint: OrientedRect,
    /// Target footprint.
    pub target_footprint: OrientedRect,
    /// Footprint IoU with the target.
    pub iou: f64,
    /// Placed (IoU above the threshold and not held).
    pub placed: bool,
    /// Held by the agent.
    pub held: bool,
}

/// A static obstacle's footprint in the privileged state.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StaticObstacle {
    /// Which wall or fixed object.
    pub obstacle: Obstacle,
    /// Its footprint (one per wall piece for walls).
    pub footprint: OrientedRect,
}

/// Privileged state: for planners and debugging only; an ESRP agent proper must not use it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PrivilegedState {
    /// The agent's pose.
    pub agent: AgentPose,
    /// Index of the held object.
    pub held: Option<usize>,
    /// Every movable object.
    pub objects: Vec<ObjectState>,
    /// Walls and fixed objects.
    pub static_obstacles: Vec<StaticObstacle>,
}

/// The agent's exact position state: integer move counts along the 8 heading axes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct MoveCounts([i32; 8]);

/// `MOVE_DISTANCE · (cos θ_j, −sin θ_j)` for headings `j` in `0..8`; heading `j + 8` moves by
/// the negation.
fn axis_step(j: usize) -> PlanPoint {
    let h = Heading::wrapping(j as i64);
    PlanPoint::new(MOVE_DISTANCE * h.cos(), -(MOVE_DISTANCE * h.sin()))
}

impl MoveCounts {
    fn position(&self, start: PlanPoint) -> PlanPoint {
        let mut dx = 0.0;
        let mut dz = 0.0;
        for (j, &n) in self.0.iter().enumerate() {
            if n != 0 {
                let s = axis_step(j);
                dx += f64::from(n) * s.x;
                dz += f64::from(n) * s.z;
            }
        }
        PlanPoint::new(start.x + dx, start.z + dz)
    }

    fn moved(mut self, heading: Heading, sign: i32) -> Self {
        let k = heading.index() as usize;
        let sign = if k < 8 { sign } else { -sign };
        self.0[k % 8] += sign;
        self
    }
}

/// What the agent holds: the object's pose and the agent's pose at the fetch.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Grip {
    object: usize,
    object_pose: ObjectPose,
    agent_position: PlanPoint,
    agent_heading: Heading,
}

impl Grip {
    /// The held object's pose for an agent at `position` facing `heading`: rigidly attached.
    fn carried_pose(&self, position: PlanPoint, heading: Heading) -> ObjectPose {
        let turns = heading.turns_from(self.agent_heading);
        let turn = Heading::wrapping(i64::from(turns));
        let rel =
            PlanPoint::new(self.object_pose.x - self.agent_position.x, self.object_pose.z - self.agent_position.z);
        let rotated = rotate_plan(rel, turn.cos(), turn.sin());
        // Written so that no displacement and no turn give back the exact fetch pose.
        let dx = (position.x - self.agent_position.x) + (rotated.x - rel.x);
        let dz = (position.z - self.agent_position.z) + (rotated.z - rel.z);
        ObjectPose {
            x: self.object_pose.x + dx,
            z: self.object_pose.z + dz,
            yaw: self.object_pose.yaw + f64::from(turns) * TURN_ANGLE,
        }
    }
}

/// The full mutable state of an episode. Plain data: `Clone`, comparable, hashable by value.
#[derive(Clone, Debug, PartialEq)]
struct State {
    counts: MoveCounts,
    position: PlanPoint,
    heading: Heading,
    grip: Option<Grip>,
    /// Every movable object's pose; the held one's box is refreshed when it is released.
    objects: MovableObstacles,
    /// Shared between clones until one changes (copy on write), like the obstacles.
    placed: Arc<Vec<bool>>,
    steps: u32,
    status: EpisodeStatus,
    ever_in_reach: bool,
    ever_fetched: bool,
    total_reward: f64,
    revision: u64,
}

/// One episode: a compiled scene, a configuration and the state. `Clone` and `Send`; step it
/// from one thread at a time.
#[derive(Clone, Debug)]
pub struct Episode {
    scene: Arc<CompiledScene>,
    config: EpisodeConfig,
    horizon: u32,
    state: State,
    /// Set when the collision library failed during a step or a reset: the state may be half
    /// changed, so the episode takes no more steps (its owner closes it).
    failure: Option<String>,
}

/// The largest magnitude of a reward weight: a step's reward, and a total over any horizon (at most
/// 2^32 steps), stay finite, so that every record holds numbers.
pub const MAX_REWARD_WEIGHT: f64 = 1e6;

impl Episode {
    /// Starts an episode on `scene` with `config`.
    pub fn new(scene: Arc<CompiledScene>, config: EpisodeConfig) -> Result<Self, EpisodeError> {
        let horizon = config.horizon.unwrap_or(scene.scene().horizon);
        if horizon == 0 {
            return Err(EpisodeError::InvalidConfig { reason: "horizon must be at least 1 step".into() });
        }
        let weights = [
            config.reward.success,
            config.reward.place,
            config.reward.unplace,
            config.reward.potential,
            config.reward.holding,
            config.reward.living,
        ];
        if weights.iter().any(|w| !w.is_finite() || w.abs() > MAX_REWARD_WEIGHT) {
            return Err(EpisodeError::InvalidConfig {
                reason: format!(
                    "reward weights must be finite numbers within ±{MAX_REWARD_WEIGHT:e} (a sum over a horizon stays finite)"
                ),
            });
        }
        let state = crate::error::guarded(|| Self::initial_state(&scene))
            .map_err(|message| EpisodeError::Failed { message, steps: 0 })?;
        Ok(Self { scene, config, horizon, state, failure: None })
    }

    fn initial_state(scene: &CompiledScene) -> State {
        let s = scene.scene();
        let start = PlanPoint::new(s.agent.x, s.agent.z);
        let poses: Vec<ObjectPose> = s.movable_objects.iter().map(|o| o.pose).collect();
        let placed: Vec<bool> = (0..poses.len())
            .map(|i| {
                footprint_iou(
                    &scene.movable_footprint(i, &poses[i]),
                    &scene.movable_footprint(i, &s.movable_objects[i].target),
                ) > scene.rules().placement_iou
            })
            .collect();
        let mut state = State {
            counts: MoveCounts([0; 8]),
            position: start,
            heading: s.agent.heading,
            grip: None,
            objects: MovableObstacles::new(scene, poses),
            placed: Arc::new(placed),
            steps: 0,
            status: EpisodeStatus::Running,
            ever_in_reach: false,
            ever_fetched: false,
            total_reward: 0.0,
            revision: 0,
        };
        state.ever_in_reach = Self::any_in_reach(scene, &state);
        state
    }

    /// Puts the episode back at its start, forgetting a failure of the collision library with the
    /// state it left; should building the start fail (it did not in [`Episode::new`]), the
    /// episode keeps its state and takes no more steps.
    pub fn reset(&mut self) {
        let revision = self.state.revision + 1;
        match crate::error::guarded(|| Self::initial_state(&self.scene)) {
            Ok(state) => {
                self.state = state;
                self.failure = None;
            }
            Err(message) => self.failure = Some(message),
        }
        self.state.revision = revision;
    }

    /// Takes one action (SPEC §3). Every action, accepted or not, counts as a step.
    ///
    /// Errors when the episode is already over, or when the collision library fails on this
    /// scene ([`EpisodeError::Failed`]): the episode then takes no more steps.
    pub fn step(&mut self, action: Action) -> Result<StepOutcome, EpisodeError> {
        if let Some(message) = &self.failure {
            return Err(EpisodeError::Failed { message: message.clone(), steps: self.state.steps });
        }
        crate::error::guarded(|| self.step_unguarded(action)).unwrap_or_else(|message| {
            self.failure = Some(message.clone());
            Err(EpisodeError::Failed { message, steps: self.state.steps })
        })
    }

    /// Why the collision library failed on this episode, if it did (it takes no more steps).
    pub fn failure(&self) -> Option<&str> {
        self.failure.as_deref()
    }

    fn step_unguarded(&mut self, action: Action) -> Result<StepOutcome, EpisodeError> {
        match self.state.status {
            EpisodeStatus::Running => {}
            EpisodeStatus::Succeeded => {
                return Err(EpisodeError::Finished { reason: "success", steps: self.state.steps });
            }
            EpisodeStatus::Truncated => {
                return Err(EpisodeError::Finished { reason: "horizon reached", steps: self.state.steps });
            }
        }
        let weights = self.config.reward;
        let mut outcome = StepOutcome {
            action,
            accepted: false,
            collided_with: None,
            no_op: None,
            fetched: None,
            released: None,
            reward: RewardTerms::default(),
            terminated: false,
            truncated: false,
            placed_count: 0,
            step_index: 0,
        };
        match action {
            Action::MoveForward | Action::MoveBackward => {
                let sign = if action == Action::MoveForward { 1 } else { -1 };
                let h = self.state.heading;
                let counts = self.state.counts.moved(h, sign);
                let position = counts.position(self.start_position());
                self.try_motion(action, counts, position, h, &mut outcome);
            }
            Action::TurnLeft | Action::TurnRight => {
                let heading =
                    if action == Action::TurnLeft { self.state.heading.left() } else { self.state.heading.right() };
                self.try_motion(action, self.state.counts, self.state.position, heading, &mut outcome);
            }
            Action::Fetch => self.fetch(&mut outcome),
            Action::Release => self.release(&mut outcome),
        }
        if outcome.accepted && action.is_motion() {
            if let Some(grip) = self.state.grip {
                // The potential term: how much closer the held object came to its target.
                let before = self.held_distance_at(grip.object, &self.state.objects.poses()[grip.object]);
                let pose = grip.carried_pose(self.state.position, self.state.heading);
                self.state.objects.carry(grip.object, pose);
                let after = self.held_distance_at(grip.object, &pose);
                outcome.reward.potential = weights.potential * (before - after);
            }
            if !self.state.ever_in_reach {
                self.state.ever_in_reach = Self::any_in_reach(&self.scene, &self.state);
            }
        }
        if self.state.grip.is_some() {
            outcome.reward.holding = weights.holding;
        }
        outcome.reward.living = weights.living;
        self.state.steps += 1;
        outcome.step_index = self.state.steps;
        outcome.placed_count = self.placed_count();
        // Only a release can place an object, so only a release can complete the task. (A scene
        // compiled for backward construction starts with every object placed; that is not a
        // success.)
        if outcome.released.is_some() && outcome.placed_count == self.state.placed.len() {
            self.state.status = EpisodeStatus::Succeeded;
            outcome.terminated = true;
            outcome.reward.success = weights.success;
        } else if self.state.steps >= self.horizon {
            self.state.status = EpisodeStatus::Truncated;
            outcome.truncated = true;
        }
        let r = &mut outcome.reward;
        r.total = r.success + r.placement + r.potential + r.holding + r.living;
        self.state.total_reward += r.total;
        Ok(outcome)
    }

    fn held_distance_at(&self, object: usize, pose: &ObjectPose) -> f64 {
        let target = &self.scene.scene().movable_objects[object].target;
        self.scene.movable_footprint(object, pose).center.distance(self.scene.movable_footprint(object, target).center)
    }

    fn start_position(&self) -> PlanPoint {
        let s = self.scene.scene();
        PlanPoint::new(s.agent.x, s.agent.z)
    }

    fn any_in_reach(scene: &CompiledScene, state: &State) -> bool {
        let reach = scene.rules().fetch_reach;
        state
            .objects
            .poses()
            .iter()
            .enumerate()
            .any(|(i, p)| scene.movable_footprint(i, p).distance_to_point(state.position) <= reach)
    }

    /// Checks the motion of `action` (SPEC §3) with [`collision::first_hit`] and, if it is
    /// free, commits the new agent state.
    fn try_motion(
        &mut self,
        action: Action,
        counts: MoveCounts,
        position: PlanPoint,
        heading: Heading,
        outcome: &mut StepOutcome,
    ) {
        let hit = Motion::of(action, self.state.heading)
            .and_then(|motion| collision::first_hit(&self.scene, &self.state.objects, &self.body(), motion));
        if let Some(hit) = hit {
            outcome.collided_with = Some(hit.obstacle);
            return;
        }
        self.state.counts = counts;
        self.state.position = position;
        self.state.heading = heading;
        self.state.revision += 1;
        outcome.accepted = true;
    }

    /// The agent's moving body now: the robot and what it holds, for [`collision`] queries.
    pub fn body(&self) -> Body {
        let held = self.state.grip.map(|g| (g.object, self.state.objects.poses()[g.object]));
        Body { position: self.state.position, held }
    }

    /// The movable objects as obstacles now, for [`collision`] queries (the held object's entry
    /// is ignored by queries about [`Episode::body`]).
    pub fn obstacles(&self) -> &MovableObstacles {
        &self.state.objects
    }

    fn fetch(&mut self, outcome: &mut StepOutcome) {
        if self.state.grip.is_some() {
            outcome.no_op = Some(NoOpReason::AlreadyHolding);
            return;
        }
        let Some(object) = self.fetch_candidate() else {
            outcome.no_op = Some(NoOpReason::NothingInReach);
            return;
        };
        if self.state.placed[object] {
            outcome.reward.placement = self.config.reward.unplace;
            Arc::make_mut(&mut self.state.placed)[object] = false;
        }
        self.state.grip = Some(Grip {
            object,
            object_pose: self.state.objects.poses()[object],
            agent_position: self.state.position,
            agent_heading: self.state.heading,
        });
        self.state.ever_fetched = true;
        outcome.fetched = Some(object);
        outcome.accepted = true;
    }

    /// The object `fetch` would take now (SPEC §3): the smallest footprint distance within
    /// reach, then the smallest absolute bearing from the forward vector, then the smallest index.
    pub fn fetch_candidate(&self) -> Option<usize> {
        let reach = self.scene.rules().fetch_reach;
        let agent = self.agent_pose();
        let forward = agent.forward();
        let mut best: Option<(f64, f64, usize)> = None;
        for (i, pose) in self.state.objects.poses().iter().enumerate() {
            let footprint = self.scene.movable_footprint(i, pose);
            let distance = footprint.distance_to_point(agent.position);
            if distance > reach {
                continue;
            }
            let to = PlanPoint::new(footprint.center.x - agent.position.x, footprint.center.z - agent.position.z);
            let bearing = (forward.x * to.z - forward.z * to.x).atan2(forward.x * to.x + forward.z * to.z).abs();
            let better = match best {
                None => true,
                Some((d, b, _)) => distance.total_cmp(&d).then(bearing.total_cmp(&b)).is_lt(),
            };
            if better {
                best = Some((distance, bearing, i));
            }
        }
        best.map(|(_, _, i)| i)
    }

    fn release(&mut self, outcome: &mut StepOutcome) {
        let Some(grip) = self.state.grip.take() else {
            outcome.no_op = Some(NoOpReason::NothingHeld);
            return;
        };
        let object = grip.object;
        let carried = self.state.objects.poses()[object];
        let pose = ObjectPose { yaw: wrap_angle(carried.yaw), ..carried };
        self.state.objects.set(&self.scene, object, pose);
        let target = &self.scene.scene().movable_objects[object].target;
        let iou =
            footprint_iou(&self.scene.movable_footprint(object, &pose), &self.scene.movable_footprint(object, target));
        if iou > self.scene.rules().placement_iou {
            Arc::make_mut(&mut self.state.placed)[object] = true;
            outcome.reward.placement = self.config.reward.place;
        }
        outcome.released = Some(object);
        outcome.accepted = true;
    }

    fn placed_count(&self) -> usize {
        self.state.placed.iter().filter(|&&p| p).count()
    }

    /// `D` now: the sum of plan distances between current and target footprint centres.
    pub fn remaining_distance(&self) -> f64 {
        let poses = self.state.objects.poses();
        (0..poses.len()).map(|i| self.held_distance_at(i, &poses[i])).sum()
    }

    /// The metrics so far (final once the episode has ended).
    pub fn metrics(&self) -> EpisodeMetrics {
        let placed = self.placed_count();
        let count = self.state.placed.len();
        let success = self.state.status == EpisodeStatus::Succeeded;
        let distance_start = self.scene.initial_distance();
        let distance_now = self.remaining_distance();
        let stage = if success {
            Stage::Succeeded
        } else if self.state.ever_fetched {
            Stage::Fetched
        } else if self.state.ever_in_reach {
            Stage::NeverFetched
        } else {
            Stage::NeverReached
        };
        EpisodeMetrics {
            success,
            object_success_rate: placed as f64 / count as f64,
            remaining_distance_ratio: if distance_start > 0.0 { distance_now / distance_start } else { 0.0 },
            stage,
            placed,
            movable_objects: count,
            steps: self.state.steps,
            distance_start,
            distance_now,
            total_reward: self.state.total_reward,
        }
    }

    /// The compiled scene.
    pub fn compiled(&self) -> &Arc<CompiledScene> {
        &self.scene
    }

    /// The configuration.
    pub fn config(&self) -> &EpisodeConfig {
        &self.config
    }

    /// The horizon in force.
    pub fn horizon(&self) -> u32 {
        self.horizon
    }

    /// Where the episode stands.
    pub fn status(&self) -> EpisodeStatus {
        self.state.status
    }

    /// Whether the episode has ended (terminated or truncated).
    pub fn is_over(&self) -> bool {
        self.state.status != EpisodeStatus::Running
    }

    /// Steps taken.
    pub fn steps(&self) -> u32 {
        self.state.steps
    }

    /// The agent's pose.
    pub fn agent_pose(&self) -> AgentPose {
        AgentPose { position: self.state.position, heading: self.state.heading }
    }

    /// The pose the agent would have after `action` if it were accepted, with exactly the
    /// arithmetic of [`Episode::step`] (bit for bit), without checking the motion: the current
    /// pose for `fetch` and `release`. A search can skip the collision check of a motion that
    /// leads to a pose it has already seen.
    pub fn pose_after(&self, action: Action) -> AgentPose {
        let heading = self.state.heading;
        match action {
            Action::MoveForward | Action::MoveBackward => {
                let sign = if action == Action::MoveForward { 1 } else { -1 };
                let position = self.state.counts.moved(heading, sign).position(self.start_position());
                AgentPose { position, heading }
            }
            Action::TurnLeft => AgentPose { position: self.state.position, heading: heading.left() },
            Action::TurnRight => AgentPose { position: self.state.position, heading: heading.right() },
            Action::Fetch | Action::Release => self.agent_pose(),
        }
    }

    /// The held object, if any (the observation's `grasping` flag is `held().is_some()`).
    pub fn held(&self) -> Option<usize> {
        self.state.grip.map(|g| g.object)
    }

    /// Current poses of the movable objects, in scene order.
    pub fn object_poses(&self) -> &[ObjectPose] {
        self.state.objects.poses()
    }

    /// Whether each movable object is placed.
    pub fn placed(&self) -> &[bool] {
        &self.state.placed
    }

    /// A counter that changes whenever what the cameras see changes (agent or objects moved, or
    /// a reset), so renderers can skip unchanged views.
    pub fn revision(&self) -> u64 {
        self.state.revision
    }

    /// The egocentric camera for the current agent pose (SPEC §2).
    pub fn ego_camera(&self) -> EgoCamera {
        EgoCamera {
            eye: [self.state.position.x, CAMERA_HEIGHT, self.state.position.z],
            yaw: self.state.heading.yaw(),
            pitch: CAMERA_PITCH,
            horizontal_fov: CAMERA_HORIZONTAL_FOV,
        }
    }

    /// Privileged state: for planners and debugging only.
    pub fn privileged_state(&self) -> PrivilegedState {
        let scene = self.scene.scene();
        let held = self.held();
        let objects = scene
            .movable_objects
            .iter()
            .enumerate()
            .map(|(i, object)| {
                let footprint = self.scene.movable_footprint(i, &self.state.objects.poses()[i]);
                let target_footprint = self.scene.movable_footprint(i, &object.target);
                ObjectState {
                    id: object.id.clone(),
                    pose: self.state.objects.poses()[i],
                    target: object.target,
                    footprint,
                    target_footprint,
                    iou: footprint_iou(&footprint, &target_footprint),
                    placed: self.state.placed[i],
                    held: held == Some(i),
                }
            })
            .collect();
        let static_obstacles = self
            .scene
            .wall_pieces()
            .iter()
            .map(|p| StaticObstacle { obstacle: Obstacle::Wall(p.wall), footprint: p.footprint() })
            .chain(
                self.scene
                    .fixed_footprints()
                    .iter()
                    .enumerate()
                    .map(|(i, f)| StaticObstacle { obstacle: Obstacle::Fixed(i), footprint: *f }),
            )
            .collect();
        PrivilegedState { agent: self.agent_pose(), held, objects, static_obstacles }
    }

    /// A fingerprint of the whole state, equal for equal states (determinism checks).
    pub fn state_fingerprint(&self) -> u64 {
        use std::hash::{Hash, Hasher};
        let mut h = std::collections::hash_map::DefaultHasher::new();
        self.state.counts.hash(&mut h);
        self.state.position.x.to_bits().hash(&mut h);
        self.state.position.z.to_bits().hash(&mut h);
        self.state.heading.hash(&mut h);
        self.held().hash(&mut h);
        for p in self.state.objects.poses() {
            [p.x.to_bits(), p.z.to_bits(), p.yaw.to_bits()].hash(&mut h);
        }
        self.state.placed.hash(&mut h);
        self.state.steps.hash(&mut h);
        self.state.total_reward.to_bits().hash(&mut h);
        h.finish()
    }

    /// Whether the state (not the step counter or rewards) is bit-identical to `other`'s.
    pub fn same_state(&self, other: &Episode) -> bool {
        let (a, b) = (&self.state, &other.state);
        a.counts == b.counts
            && a.position.x.to_bits() == b.position.x.to_bits()
            && a.position.z.to_bits() == b.position.z.to_bits()
            && a.heading == b.heading
            && a.grip == b.grip
            && a.placed == b.placed
            && a.objects.poses().len() == b.objects.poses().len()
            && a.objects.poses().iter().zip(b.objects.poses()).all(|(p, q)| {
                p.x.to_bits() == q.x.to_bits() && p.z.to_bits() == q.z.to_bits() && p.yaw.to_bits() == q.yaw.to_bits()
            })
    }
}

/// Wraps an angle into `(−π, π]`.
fn wrap_angle(angle: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    let wrapped = (angle + PI).rem_euclid(TAU) - PI;
    if wrapped <= -PI { wrapped + TAU } else { wrapped }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_angle_lands_in_range() {
        use std::f64::consts::PI;
        for a in [-7.0, -PI, -1.0, 0.0, 1.0, PI, 4.0, 13.0] {
            let w = wrap_angle(a);
            assert!(w > -PI && w <= PI, "{a} -> {w}");
            assert!(((w - a) / (2.0 * PI)).fract().abs() < 1e-9 || ((w - a) / (2.0 * PI)).fract().abs() > 1.0 - 1e-9);
        }
    }

    #[test]
    fn move_counts_are_exactly_reversible() {
        let start = PlanPoint::new(0.1, 0.7);
        let mut counts = MoveCounts([0; 8]);
        for k in 0..16 {
            counts = counts.moved(Heading::wrapping(k), 1);
        }
        for k in (0..16).rev() {
            counts = counts.moved(Heading::wrapping(k), -1);
        }
        assert_eq!(counts.position(start), start);
        // Heading j + 8 moves exactly opposite to heading j.
        let a = MoveCounts([0; 8]).moved(Heading::wrapping(3), 1).position(start);
        let b = MoveCounts([0; 8]).moved(Heading::wrapping(11), -1).position(start);
        assert_eq!(a, b);
    }
}
