//! One live episode and what the service keeps beside it ([`EpisodeEntry`]), and the checks a
//! call makes on it before it moves.

use std::sync::Arc;
use std::time::{Instant, SystemTime};

use esrp_core::{Episode, Scene};

use super::observe::Observer;
use super::plan_cache::CachedPlan;
use crate::error::ServiceError;
use crate::registry::Locked;
use crate::types::{Caller, EpisodeId, SceneInfo};

/// A run of an episode (from its create or reset) that the server records or counts: what its
/// record needs beyond the episode itself.
pub struct RunLog {
    /// Every action taken, as codes.
    pub actions: Vec<u8>,
    /// When the run started.
    pub started: SystemTime,
    /// The same, for its wall time.
    pub clock: Instant,
    /// Whether it is its token's counted attempt at a challenge scene.
    pub counted: bool,
    /// Whether the server keeps a record of it (`--records`).
    pub recorded: bool,
    /// Whether its record stays with the episode once it ends ([`EpisodeEntry::last_record`]).
    pub keep: bool,
    /// Whether it has ended and been recorded (or counted): it is never recorded twice.
    pub finished: bool,
}

/// One live episode: the simulator state and what the service keeps beside it.
pub struct EpisodeEntry {
    /// The simulator state.
    pub episode: Episode,
    /// What its observations are made from, and the last ones made.
    pub observer: Observer,
    /// The scene's summary.
    pub summary: SceneInfo,
    /// Whether GetPrivilegedState and PlanActions are allowed.
    pub privileged: bool,
    /// Last time a call used it.
    pub last_used: Instant,
    /// When it was made (its create, or a reset onto another scene).
    pub created: Instant,
    /// The planner's last answer (PlanActions), reused while the episode follows it.
    pub plan: Option<CachedPlan>,
    /// The token that created it.
    pub owner: Arc<Caller>,
    /// The agent's name its create gave ("unnamed" if none).
    pub agent: Arc<str>,
    /// The current run, when the server records or counts it.
    pub run: Option<RunLog>,
    /// Whether each run keeps its record (the create's `keep_record`).
    pub keep_records: bool,
    /// Whether it serves the paper's observation only (a hidden scene; see `access::paper_only`):
    /// its step answers carry no reward, reward terms, placed count or collision, and its metrics
    /// are read only once it has ended.
    pub paper_only: bool,
    /// The record of the last run that ended, when runs keep theirs.
    pub last_record: Option<esrp_results::EpisodeRecord>,
    /// Where the run went, for viewers (`viewing`).
    pub trail: Trail,
    /// Told of every step while someone watches the episode (`viewing`); `None` otherwise, so
    /// that an unwatched episode costs one check per step.
    pub watch: Option<tokio::sync::watch::Sender<u64>>,
}

/// The most recent actions a viewer is shown.
pub const LAST_ACTIONS: usize = 12;

/// Where a run went: the agent's position after each step, each carried object's positions,
/// and the last actions. A few bytes a step, kept for every episode so that a viewer who
/// arrives late sees the whole path.
#[derive(Default)]
pub struct Trail {
    /// The agent's plan position at the start and after each step.
    pub agent: Vec<[f32; 2]>,
    /// Per object index, its positions while carried (one path per carry, in order).
    pub carried: Vec<(usize, Vec<[f32; 2]>)>,
    /// The last [`LAST_ACTIONS`] actions: code and whether the motion was accepted.
    pub last: std::collections::VecDeque<(u8, bool)>,
    /// The object held after the previous step (a new carry starts a new path).
    held: Option<usize>,
}

impl Trail {
    /// A trail starting where `episode` is.
    pub fn start(episode: &Episode) -> Self {
        let p = episode.agent_pose().position;
        Self { agent: vec![[p.x as f32, p.z as f32]], ..Self::default() }
    }

    /// Adds a step of `episode` that took `action` (accepted or not).
    pub fn step(&mut self, episode: &Episode, action: u8, accepted: bool) {
        let p = episode.agent_pose().position;
        self.agent.push([p.x as f32, p.z as f32]);
        let held = episode.held();
        if let Some(index) = held {
            let o = episode.object_poses()[index];
            let point = [o.x as f32, o.z as f32];
            match self.carried.last_mut() {
                Some((_, path)) if self.held == Some(index) => path.push(point),
                _ => self.carried.push((index, vec![point])),
            }
        }
        self.held = held;
        if self.last.len() == LAST_ACTIONS {
            self.last.pop_front();
        }
        self.last.push_back((action, accepted));
    }
}

/// A live episode as the registry holds it: shared, locked alone.
pub type SharedEpisode = Locked<EpisodeEntry>;

/// A locked episode.
pub type EpisodeGuard = tokio::sync::OwnedMutexGuard<EpisodeEntry>;

impl EpisodeEntry {
    /// A fresh entry for `episode` of `owner`, observed by `observer`.
    pub fn new(episode: Episode, observer: Observer, privileged: bool, owner: Arc<Caller>, agent: Arc<str>) -> Self {
        let summary = summary_of(episode.compiled().scene());
        let trail = Trail::start(&episode);
        Self {
            episode,
            observer,
            summary,
            privileged,
            last_used: Instant::now(),
            created: Instant::now(),
            plan: None,
            owner,
            agent,
            run: None,
            keep_records: false,
            paper_only: false,
            last_record: None,
            trail,
            watch: None,
        }
    }

    /// The one check before any call moves the episode `id` (`at` names the call's step in
    /// messages: "step", "steps[3]", "plan"): an ended episode is [`ServiceError::EpisodeOver`].
    pub fn ensure_running(&self, at: &str, id: &EpisodeId) -> Result<(), ServiceError> {
        if self.episode.is_over() {
            return Err(ServiceError::EpisodeOver {
                at: at.to_owned(),
                episode: id.clone(),
                steps: self.episode.steps(),
            });
        }
        Ok(())
    }

    /// [`EpisodeEntry::ensure_running`], then the size of a step's answer (with the goal image
    /// if `include_goal`), which must fit in `max_message_bytes`; returns that size.
    pub fn ensure_steppable(
        &self,
        at: &str,
        id: &EpisodeId,
        include_goal: bool,
        max_message_bytes: usize,
    ) -> Result<usize, ServiceError> {
        self.ensure_running(at, id)?;
        let bytes = self.observer.sensors.answer_bytes(include_goal);
        if bytes > max_message_bytes {
            return Err(ServiceError::StepAnswerTooLarge { bytes, max: max_message_bytes });
        }
        Ok(bytes)
    }
}

/// The summary of a built scene; a hidden scene's says nothing of its expert trajectory.
pub(super) fn summary_of(scene: &Scene) -> SceneInfo {
    SceneInfo {
        id: scene.id.clone(),
        room_type: scene.room_type.clone(),
        difficulty: scene.difficulty,
        split: scene.split,
        movable_objects: scene.movable_objects.len(),
        horizon: scene.horizon,
        expert_length: if scene.split.is_hidden() { 0 } else { scene.expert_trajectory.len() },
    }
}
