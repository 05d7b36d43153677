//! PlanActions: esrp-planner (ESRP-PLAN) on an episode's current state.
//!
//! - Only privileged episodes may ask ([`ServiceError::NotPrivileged`]); an ended episode is
//!   [`ServiceError::EpisodeOver`].
//! - Planning runs on a blocking thread, never on the async runtime, and at most one plan per
//!   core runs at once (a semaphore); the time budget (the request's, or `--plan-budget-ms`,
//!   capped at `--max-plan-ms`) counts from the call, waiting for a core included, and a plan
//!   not found within it is [`ServiceError::PlanDeadline`]. A call its client abandons stops
//!   its planner at the next check (the planner's cancel flag), so it frees its core.
//! - The answer (a plan, or why there is none) is cached with the episode, keyed by the exact
//!   states the plan passes through: a later call from any of them (the agent followed the
//!   plan, or reset to its start) answers from the cache without planning; any other state
//!   plans afresh. A deadline is not cached (a larger budget may succeed).

use std::time::{Duration, Instant};

use esrp_core::{Action, Episode};
use esrp_planner::{CancelToken, PlanFailure, PlanOptions, PlanStats};

use super::{EpisodeId, Shared};
use crate::error::ServiceError;

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

/// A planner's answer kept with its episode.
#[derive(Clone, Debug)]
pub struct CachedPlan {
    /// `state_fingerprint` of the state before each action, then after the last one.
    fingerprints: Vec<u64>,
    /// The plan; for a failure, the actions the planner took before it failed (possibly none).
    actions: Vec<Action>,
    stats: PlanStats,
    failure: Option<PlanFailure>,
}

impl CachedPlan {
    /// The answer for an episode now in state `fingerprint`, if it is one the plan passes
    /// through.
    fn answer(&self, fingerprint: u64, max_actions: u32) -> Option<Planned> {
        let at = self.fingerprints.iter().position(|&f| f == fingerprint)?;
        // Where a plan ends the episode has ended; where a failure's partial actions end the
        // planner may find more from there: plan again. (A failure with no actions answers
        // at the state it was planned from.)
        if at >= self.actions.len() && !(self.failure.is_some() && at == 0) {
            return None;
        }
        Some(answer_from(&self.actions[at.min(self.actions.len())..], &self.stats, &self.failure, max_actions, true))
    }

    /// The cached answer for what the planner said from `episode`'s state.
    fn of(episode: &Episode, outcome: &Result<esrp_planner::Plan, esrp_planner::PlanError>) -> Self {
        match outcome {
            Ok(plan) => {
                let (fingerprints, actions) = states_along(episode, &plan.actions);
                CachedPlan { fingerprints, actions, stats: plan.stats.clone(), failure: None }
            }
            Err(e) => {
                let (fingerprints, actions) = states_along(episode, &e.partial);
                CachedPlan { fingerprints, actions, stats: e.stats.clone(), failure: Some(e.reason.clone()) }
            }
        }
    }
}

/// The fingerprints of the states `actions` pass through from `episode` (before each action,
/// then after the last), and the actions that could be taken (all, for a planner's output).
fn states_along(episode: &Episode, actions: &[Action]) -> (Vec<u64>, Vec<Action>) {
    let mut replay = episode.clone();
    let mut fingerprints = Vec::with_capacity(actions.len() + 1);
    fingerprints.push(replay.state_fingerprint());
    let mut taken = Vec::with_capacity(actions.len());
    for &action in actions {
        if replay.step(action).is_err() {
            break;
        }
        taken.push(action);
        fingerprints.push(replay.state_fingerprint());
    }
    (fingerprints, taken)
}

fn answer_from(
    plan: &[Action],
    stats: &PlanStats,
    failure: &Option<PlanFailure>,
    max_actions: u32,
    cached: bool,
) -> Planned {
    let take = if max_actions == 0 { plan.len() } else { plan.len().min(max_actions as usize) };
    let failure_object = match failure {
        Some(PlanFailure::Unreachable { id, .. } | PlanFailure::NoPlacement { id, .. }) => Some(id.clone()),
        _ => None,
    };
    Planned {
        actions: plan[..take].to_vec(),
        reaches_success: failure.is_none(),
        plan_length: plan.len() as u32,
        cached,
        stats: stats.clone(),
        failure: failure.clone(),
        failure_object,
    }
}

/// Cancels the planner's token when dropped: a call abandoned by its client (its future
/// dropped at an await) stops the planning it started at the planner's next check.
struct CancelOnDrop(CancelToken);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.cancel();
    }
}

impl Shared {
    /// Plans from the episode's current state (see the module's notes).
    pub async fn plan(&self, call: PlanCall) -> Result<Planned, ServiceError> {
        let started = Instant::now();
        let budget = call.budget.unwrap_or(self.config.plan_budget()).min(self.config.max_plan());
        let deadline = started + budget;
        let (episode, fingerprint) = {
            let shared = self.registry.get(&call.episode)?;
            let mut entry = shared.lock().await;
            if !entry.privileged {
                return Err(ServiceError::NotPrivileged(call.episode.clone()));
            }
            entry.last_used = Instant::now();
            if entry.episode.is_over() {
                return Err(ServiceError::EpisodeOver {
                    at: "plan".into(),
                    episode: call.episode.clone(),
                    steps: entry.episode.steps(),
                });
            }
            let fingerprint = entry.episode.state_fingerprint();
            if let Some(answer) = entry.plan.as_ref().and_then(|p| p.answer(fingerprint, call.max_actions)) {
                self.metrics.count_plan("cached");
                return Ok(answer);
            }
            (entry.episode.clone(), fingerprint)
        };
        let permit = tokio::time::timeout_at(deadline.into(), self.planners.acquire())
            .await
            .map_err(|_| ServiceError::PlanDeadline { budget_ms: budget.as_millis() as u64 })?
            .map_err(|_| ServiceError::Internal("the planner pool is closed".into()))?;
        let cancel = CancelOnDrop(CancelToken::new());
        let options =
            PlanOptions { deadline: Some(deadline), cancel: Some(cancel.0.clone()), ..PlanOptions::default() };
        let metrics = self.metrics.clone();
        let job = move || {
            let outcome = esrp_planner::plan(&episode, &options);
            // Counted here: a cancelled call's handler is gone by now.
            if outcome.as_ref().is_err_and(|e| e.reason == PlanFailure::Cancelled) {
                metrics.count_plan("cancelled");
            }
            let cached = CachedPlan::of(&episode, &outcome);
            (outcome, cached)
        };
        let (outcome, cached) =
            tokio::task::spawn_blocking(job).await.map_err(|e| ServiceError::Internal(e.to_string()))?;
        drop(permit);
        drop(cancel);
        if let Err(e) = &outcome
            && matches!(e.reason, PlanFailure::DeadlineExceeded | PlanFailure::Cancelled)
        {
            self.metrics.count_plan("deadline");
            return Err(ServiceError::PlanDeadline { budget_ms: budget.as_millis() as u64 });
        }
        if let Err(e) = &outcome
            && matches!(
                e.reason,
                PlanFailure::EpisodeOver | PlanFailure::InvalidOptions { .. } | PlanFailure::ReplayFailed { .. }
            )
        {
            return Err(ServiceError::Internal(format!("planner: {}", e.reason)));
        }
        self.metrics.count_plan(if outcome.is_ok() { "planned" } else { "failed" });
        let answer = cached
            .answer(fingerprint, call.max_actions)
            .unwrap_or_else(|| answer_from(&cached.actions, &cached.stats, &cached.failure, call.max_actions, false));
        let answer = Planned { cached: false, ..answer };
        // Keep the answer if the episode is still where the plan starts (it may have moved on
        // while the planner ran).
        if let Ok(shared) = self.registry.get(&call.episode) {
            let mut entry = shared.lock().await;
            if entry.episode.state_fingerprint() == fingerprint {
                entry.plan = Some(cached);
            }
        }
        Ok(answer)
    }
}
