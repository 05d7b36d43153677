//! **esrp-planner**: the privileged task-and-motion planner for ESRP. Given an episode in any
//! state, [`plan`] returns the actions that, stepped on that episode, end in success within its
//! horizon.
//!
//! The planner reads privileged state (every object's pose and target) and is a baseline and a
//! tool for tests and evaluation, not an ESRP agent proper. It is a pure library: no I/O, no
//! threads, no randomness.
//!
//! # How it plans
//!
//! - The **task planner** (`task`) chooses the order of the objects, nearest first; an object
//!   whose target another object stands on waits for it. When no object can be placed, it moves
//!   the object most in the way (the one the failed searches ran into, or the one on a target)
//!   aside to a buffer pose clear of the remaining targets, and tries again. An object held at
//!   the start is placed, or set down in a buffer pose, first.
//! - The **motion planner** (`search`) is one weighted A* per object over the exact action
//!   lattice: approach, `fetch` (where [`Episode::fetch_candidate`] is that object), carry,
//!   `release`. Its bounds (`bounds`) are consistent; a goal's cost favours a high IoU. When
//!   the object is out of reach, an **approach** (`approach`: a weighted A* to a pose from which
//!   `fetch` takes it, facing it) runs first and the fetch-and-carry search starts there; if
//!   that fails, the search runs from where the agent stood.
//!
//! # Invariants
//!
//! - **Every edge is a real step.** Each search edge is [`Episode::step`] on a clone of the
//!   episode; no rule is re-implemented here, so what the planner finds, the simulator accepts.
//! - **Never a wrong plan.** Before [`plan`] returns a [`Plan`] it replays it on a clone and
//!   checks that every motion is accepted and that the episode succeeds; otherwise it returns
//!   [`PlanFailure::ReplayFailed`].
//! - **Deterministic.** The same state and the same options without a deadline give the same
//!   plan: searches break ties by insertion order and never iterate over hash maps.
//!
//! # Example
//!
//! ```
//! use esrp_core::{CompiledScene, Episode, EpisodeConfig, Scene};
//! use esrp_planner::{PlanOptions, plan};
//!
//! let text = include_str!("../../core/examples/scenes/bedroom.json");
//! let scene = CompiledScene::shared(Scene::from_json(text)?)?;
//! let mut episode = Episode::new(scene, EpisodeConfig::default())?;
//! let found = plan(&episode, &PlanOptions::default())?;
//! for action in found.actions {
//!     episode.step(action)?;
//! }
//! assert!(episode.metrics().success);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]

mod approach;
mod bounds;
mod search;
mod task;

use std::time::{Duration, Instant};

use esrp_core::{Action, Episode};

/// A flag that stops a running [`plan`] call from another thread: clones share it; equal
/// when they are clones of one token.
#[derive(Clone, Debug, Default)]
pub struct CancelToken(std::sync::Arc<std::sync::atomic::AtomicBool>);

impl CancelToken {
    /// A token not cancelled yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Cancels every [`plan`] call that holds a clone of this token.
    pub fn cancel(&self) {
        self.0.store(true, std::sync::atomic::Ordering::Relaxed);
    }

    /// Whether [`CancelToken::cancel`] was called.
    pub fn is_cancelled(&self) -> bool {
        self.0.load(std::sync::atomic::Ordering::Relaxed)
    }
}

impl PartialEq for CancelToken {
    fn eq(&self, other: &Self) -> bool {
        std::sync::Arc::ptr_eq(&self.0, &other.0)
    }
}

/// How hard [`plan`] may try. Every field has a default that plans the benchmark's test split
/// (see the crate's README for what they cost).
#[derive(Clone, Debug, PartialEq)]
pub struct PlanOptions {
    /// Nodes expanded over all the searches of one [`plan`] call, at most.
    pub max_nodes: u64,
    /// Give up at this instant (checked inside the search loops).
    pub deadline: Option<Instant>,
    /// Give up as soon as this is cancelled (checked with the deadline): a caller that no
    /// longer wants the plan (a server whose client went away) frees the thread at once.
    pub cancel: Option<CancelToken>,
    /// Weight on the heuristic of the weighted A* (1.0: optimal A*; larger: faster, longer
    /// plans). At least 1.
    pub heuristic_weight: f64,
    /// Nodes one search (one object's fetch and carry) may expand, at most. When no object can
    /// be placed within it, the task planner retries once with five times as many before it
    /// moves anything aside.
    pub max_search_nodes: u64,
    /// Duplicate detection by cells of this size, metres; 0 detects only exact duplicates.
    ///
    /// The lattice of agent positions is dense (16 headings × 0.25 m moves), so exact
    /// detection lets a search flood cluttered rooms; cells prune states that differ by less
    /// than a cell. This can only lose plans, never produce a wrong one: every edge is still a
    /// real step.
    pub duplicate_cell: f64,
    /// Terminal cost of a placement, in steps, per unit of footprint IoU short of 1: a plan
    /// that sets the object down squarely is worth up to this many extra steps.
    pub iou_weight: f64,
    /// Nodes one search may expand after it finds its first goal release, looking for a
    /// cheaper one (a higher IoU); then it takes the cheapest found.
    pub polish_nodes: u64,
    /// Moves of objects to buffer poses over one [`plan`] call, at most.
    pub max_relocations: u32,
}

impl Default for PlanOptions {
    fn default() -> Self {
        Self {
            max_nodes: 1_000_000,
            deadline: None,
            cancel: None,
            heuristic_weight: 2.0,
            max_search_nodes: 40_000,
            duplicate_cell: 0.05,
            iou_weight: 12.0,
            polish_nodes: 2_000,
            max_relocations: 8,
        }
    }
}

/// What a [`plan`] call cost.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlanStats {
    /// Search nodes expanded, over all searches.
    pub nodes_expanded: u64,
    /// Searches run (one per attempt to fetch and carry an object).
    pub searches: u32,
    /// Wall-clock time of the call.
    pub elapsed: Duration,
    /// Objects moved to a buffer pose.
    pub objects_relocated: u32,
    /// The deadline (or a cancel) stopped a search that had found a way to place its object
    /// but not yet proven it the cheapest, and the plan took the best found: with more time the
    /// same call may return a shorter plan. Never set without a deadline or a cancel token.
    pub cut_short: bool,
}

/// A plan: actions that, stepped on a clone of the planned episode, end in success.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The actions, in order.
    pub actions: Vec<Action>,
    /// What finding them cost.
    pub stats: PlanStats,
}

/// Why [`plan`] returned no plan, and what it cost to find out.
#[derive(Clone, Debug, thiserror::Error)]
#[error("{reason}")]
pub struct PlanError {
    /// Why.
    pub reason: PlanFailure,
    /// What the attempt cost.
    pub stats: PlanStats,
    /// The actions planned before the failure (each object's fetch, carry and release as its
    /// search found them): stepped on the episode they make the progress the planner made,
    /// for partial credit. Empty when nothing was planned or the plan failed on replay.
    pub partial: Vec<Action>,
}

/// Why no plan was found.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PlanFailure {
    /// The episode has ended: nothing to plan.
    #[error("the episode is already over")]
    EpisodeOver,
    /// No pose from which `fetch` takes the object was reached.
    #[error(
        "object {object} ({id}) is unreachable: no collision-free pose from which fetch takes it was found \
         (raise max_search_nodes, or the objects around it box it in)"
    )]
    Unreachable {
        /// The object's index.
        object: usize,
        /// The object's id.
        id: String,
    },
    /// The object was fetched but no release pose with IoU above the threshold was reached.
    #[error(
        "object {object} ({id}) cannot be placed: no release pose with footprint IoU above the threshold was \
         reached while carrying it (raise max_search_nodes, or something stands on or around its target)"
    )]
    NoPlacement {
        /// The object's index.
        object: usize,
        /// The object's id.
        id: String,
    },
    /// The node budget ran out.
    #[error("the node budget ran out after {nodes} expanded nodes (raise PlanOptions::max_nodes)")]
    BudgetExhausted {
        /// Nodes expanded.
        nodes: u64,
    },
    /// The deadline passed.
    #[error("the deadline passed before a plan was found (give the planner more time)")]
    DeadlineExceeded,
    /// The caller cancelled the planning ([`PlanOptions::cancel`]).
    #[error("the planning was cancelled")]
    Cancelled,
    /// A plan exists (or may) but needs more steps than the horizon leaves.
    #[error("a plan needs at least {steps} steps but only {steps_left} remain before the horizon")]
    TooLong {
        /// Steps the plan needs, at least.
        steps: usize,
        /// Steps left: horizon minus steps taken.
        steps_left: u32,
    },
    /// The options are unusable.
    #[error("invalid planner options: {reason}")]
    InvalidOptions {
        /// What to change.
        reason: String,
    },
    /// A plan was found but did not replay to success: a bug in the planner (please report it
    /// with the scene and the actions that led to the state).
    #[error("internal error: the plan failed on replay at action {step} (a planner bug; please report it)")]
    ReplayFailed {
        /// Index of the first action that was rejected, or the plan's length if it ended
        /// without success.
        step: usize,
    },
}

impl PlanFailure {
    /// A short stable name of the failure's kind (`unreachable`, `no_placement`,
    /// `budget_exhausted`, `deadline_exceeded`, `cancelled`, `too_long`, `episode_over`,
    /// `invalid_options`, `replay_failed`), for reports and logs.
    pub fn name(&self) -> &'static str {
        match self {
            PlanFailure::EpisodeOver => "episode_over",
            PlanFailure::Unreachable { .. } => "unreachable",
            PlanFailure::NoPlacement { .. } => "no_placement",
            PlanFailure::BudgetExhausted { .. } => "budget_exhausted",
            PlanFailure::DeadlineExceeded => "deadline_exceeded",
            PlanFailure::Cancelled => "cancelled",
            PlanFailure::TooLong { .. } => "too_long",
            PlanFailure::InvalidOptions { .. } => "invalid_options",
            PlanFailure::ReplayFailed { .. } => "replay_failed",
        }
    }
}

/// Plans from `episode`'s current state: actions that, stepped on a clone of it, end in
/// [`esrp_core::EpisodeStatus::Succeeded`] within the horizon.
///
/// The agent may be anywhere, holding an object or not, with some objects placed. The plan has
/// been replayed before it is returned: every motion in it is accepted and it ends in success.
pub fn plan(episode: &Episode, options: &PlanOptions) -> Result<Plan, PlanError> {
    let started = Instant::now();
    let mut planner = task::TaskPlanner::new(episode, options);
    let result = options_problem(options).map_or_else(|| planner.run(), Err);
    let (actions, mut stats) = planner.finish();
    let result = result.and_then(|()| replay(episode, &actions));
    stats.elapsed = started.elapsed();
    match result {
        Ok(()) => Ok(Plan { actions, stats }),
        Err(reason @ PlanFailure::ReplayFailed { .. }) => Err(PlanError { reason, stats, partial: Vec::new() }),
        Err(reason) => Err(PlanError { reason, stats, partial: actions }),
    }
}

fn options_problem(options: &PlanOptions) -> Option<PlanFailure> {
    let reason = if !(options.heuristic_weight.is_finite() && options.heuristic_weight >= 1.0) {
        format!("heuristic_weight {} must be a finite number of at least 1", options.heuristic_weight)
    } else if !(options.duplicate_cell.is_finite() && options.duplicate_cell >= 0.0) {
        format!("duplicate_cell {} must be a finite number of metres, at least 0", options.duplicate_cell)
    } else if !(options.iou_weight.is_finite() && options.iou_weight >= 0.0) {
        format!("iou_weight {} must be a finite number, at least 0", options.iou_weight)
    } else {
        return None;
    };
    Some(PlanFailure::InvalidOptions { reason })
}

/// Steps `actions` on a clone of `episode`: every motion must be accepted, every fetch and
/// release take effect, and the episode must end in success.
fn replay(episode: &Episode, actions: &[Action]) -> Result<(), PlanFailure> {
    let mut replayed = episode.clone();
    for (step, &action) in actions.iter().enumerate() {
        match replayed.step(action) {
            Ok(outcome) if outcome.accepted => {}
            _ => return Err(PlanFailure::ReplayFailed { step }),
        }
    }
    if replayed.status() == esrp_core::EpisodeStatus::Succeeded {
        Ok(())
    } else {
        Err(PlanFailure::ReplayFailed { step: actions.len() })
    }
}
