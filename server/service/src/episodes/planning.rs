//! PlanActions: esrp-planner (ESRP-PLAN) on an episode's current state.
//!
//! - Only privileged episodes may ask ([`ServiceError::NotPrivileged`]); an ended episode is
//!   [`ServiceError::EpisodeOver`].
//! - Planning runs on a blocking thread, never on the async runtime, and at most
//!   `--planner-threads` plans (one per core by default) run at once (a semaphore); the time
//!   budget (the request's, or `--plan-budget-ms`, capped at `--max-plan-ms`) counts from the
//!   call, waiting for a planner thread included, and a plan not found within it is
//!   [`ServiceError::PlanDeadline`]; a call that waited the whole budget for a planner thread is
//!   [`ServiceError::PlannersBusy`]. A call its client abandons stops its planner at the next
//!   check (the planner's cancel flag), so it frees its thread (counted busy until then).
//! - The answer (a plan, or why there is none) is cached with the episode, keyed by the exact
//!   states the plan passes through: a later call from any of them (the agent followed the
//!   plan, or reset to its start) answers from the cache without planning; any other state
//!   plans afresh. A deadline is not cached (a larger budget may succeed), nor a plan the
//!   deadline cut short (`PlanStats::cut_short`: a larger budget may find a shorter one), nor an
//!   answer for a scene the episode has left meanwhile (a Reset onto another scene, whose start state may
//!   fingerprint the same: the fingerprint does not cover the scene).

use std::sync::Arc;
use std::time::Instant;

use esrp_planner::{CancelToken, PlanFailure, PlanOptions};

use super::access;
use super::plan_cache::CachedPlan;
use super::state::Episodes;
use crate::error::ServiceError;
use crate::types::{Caller, PlanCall, Planned};

/// Cancels the planner's token when dropped: a call abandoned by its client (its future
/// dropped at an await) stops the planning it started at the planner's next check.
struct CancelOnDrop(CancelToken);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.cancel();
    }
}

/// Plans from the episode's current state (see the module's notes).
pub(super) async fn plan(episodes: &Episodes, caller: &Caller, call: PlanCall) -> Result<Planned, ServiceError> {
    access::may_read_privileged(caller, "PlanActions")?;
    let started = Instant::now();
    let budget = call.budget.unwrap_or(episodes.config.plan_budget()).min(episodes.config.max_plan());
    let deadline = started + budget;
    let (episode, fingerprint) = {
        let shared = episodes.registry.get(&call.episode, caller)?;
        let mut entry = shared.lock().await;
        if !entry.privileged {
            return Err(ServiceError::NotPrivileged(call.episode.clone()));
        }
        entry.last_used = Instant::now();
        entry.ensure_running("plan", &call.episode)?;
        let fingerprint = entry.episode.state_fingerprint();
        if let Some(answer) = entry.plan.as_ref().and_then(|p| p.answer(fingerprint, call.max_actions)) {
            episodes.metrics.count_plan("cached");
            return Ok(answer);
        }
        (entry.episode.clone(), fingerprint)
    };
    let scene = episode.compiled().clone();
    let Ok(permit) = tokio::time::timeout_at(deadline.into(), episodes.planners.clone().acquire_owned()).await else {
        episodes.metrics.count_plan("busy");
        return Err(ServiceError::PlannersBusy {
            budget_ms: budget.as_millis() as u64,
            threads: episodes.config.planner_threads(),
        });
    };
    let permit = permit.map_err(|_| ServiceError::Internal("the planner pool is closed".into()))?;
    let cancel = CancelOnDrop(CancelToken::new());
    let options = PlanOptions { deadline: Some(deadline), cancel: Some(cancel.0.clone()), ..PlanOptions::default() };
    let metrics = episodes.metrics.clone();
    let job = move || {
        // Held until the planner returns, not until the handler does: a call its client abandons
        // leaves its planner running to its next check, and the thread is not free before that.
        let _permit = permit;
        let outcome = esrp_planner::plan(&episode, &options);
        // Counted here: a cancelled call's handler is gone by now.
        if outcome.as_ref().is_err_and(|e| e.reason == PlanFailure::Cancelled) {
            metrics.count_plan("cancelled");
        }
        let cached = CachedPlan::of(&episode, &outcome);
        let keep = !outcome.as_ref().is_ok_and(|plan| plan.stats.cut_short);
        (outcome, cached, keep)
    };
    let (outcome, cached, keep) =
        tokio::task::spawn_blocking(job).await.map_err(|e| ServiceError::Internal(e.to_string()))?;
    drop(cancel);
    if let Err(e) = &outcome
        && matches!(e.reason, PlanFailure::DeadlineExceeded | PlanFailure::Cancelled)
    {
        episodes.metrics.count_plan("deadline");
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
    episodes.metrics.count_plan(if outcome.is_ok() { "planned" } else { "failed" });
    let answer =
        cached.answer(fingerprint, call.max_actions).unwrap_or_else(|| cached.answer_at_start(call.max_actions));
    let answer = Planned { cached: false, ..answer };
    // Keep the answer if the episode is still where the plan starts, on the same scene (it may
    // have moved on, or been reset onto another scene, while the planner ran).
    if keep && let Ok(shared) = episodes.registry.get(&call.episode, caller) {
        let mut entry = shared.lock().await;
        if entry.episode.state_fingerprint() == fingerprint && Arc::ptr_eq(entry.episode.compiled(), &scene) {
            entry.plan = Some(cached);
        }
    }
    Ok(answer)
}
