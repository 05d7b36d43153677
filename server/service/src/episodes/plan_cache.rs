//! The planner's last answer on an episode ([`CachedPlan`]), kept with the episode and keyed by
//! the exact states the plan passes through: a later PlanActions from any of them (the agent
//! followed the plan, or reset to its start) is answered from it without planning.

use esrp_core::{Action, Episode};
use esrp_planner::{PlanFailure, PlanStats};

use crate::types::Planned;

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
    pub fn answer(&self, fingerprint: u64, max_actions: u32) -> Option<Planned> {
        let at = self.fingerprints.iter().position(|&f| f == fingerprint)?;
        // Where a plan ends the episode has ended; where a failure's partial actions end the
        // planner may find more from there: plan again. (A failure with no actions answers
        // at the state it was planned from.)
        if at >= self.actions.len() && !(self.failure.is_some() && at == 0) {
            return None;
        }
        Some(answer_from(&self.actions[at.min(self.actions.len())..], &self.stats, &self.failure, max_actions, true))
    }

    /// The answer from the state it was planned from, for a call of `max_actions`.
    pub fn answer_at_start(&self, max_actions: u32) -> Planned {
        answer_from(&self.actions, &self.stats, &self.failure, max_actions, false)
    }

    /// The cached answer for what the planner said from `episode`'s state.
    pub fn of(episode: &Episode, outcome: &Result<esrp_planner::Plan, esrp_planner::PlanError>) -> Self {
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
