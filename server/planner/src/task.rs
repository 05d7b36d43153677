//! The task planner: which object to move next, and which to move out of the way.
//!
//! Rounds: each round tries the objects still to place, nearest first (an object tried in the
//! round before without success goes after the others), and commits the first search that
//! succeeds. An object whose target another unplaced object stands on waits without a search:
//! that object will move when its own turn comes. When a whole round fails, the object most in
//! the way — the one standing on a target, else the one the failed searches' rejected motions
//! hit most — is carried to a buffer pose (clear of the remaining targets, away from where it
//! stood), and the objects it blocked are tried first in the next round. Relocations are
//! bounded, so the planner always ends.

use esrp_core::collision::object_obstruction;
use esrp_core::{Action, Episode, Obstacle};

use crate::approach::{ApproachLimits, approach};
use crate::search::{BufferGoal, Goal, Miss, NotFound, SearchLimits, search};
use crate::{PlanFailure, PlanOptions, PlanStats};

/// Rejected motions counted for an object found standing on another's target: more than any
/// search's hits, so it is moved first.
const ON_TARGET_WEIGHT: u64 = 1 << 32;

/// Relocations of the same object, at most, in one plan.
const MAX_RELOCATIONS_PER_OBJECT: u32 = 3;

/// How buffer poses are tried, strictest first: (clearance from the remaining targets, metres;
/// least distance from where the object stood, metres).
const BUFFER_TIERS: [(f64, f64); 2] = [(0.3, 1.0), (0.0, 0.5)];

/// Steps a placed object's relocation pays for leaving it unplaced: re-placing it clear of the
/// others is better than putting it aside, when it costs fewer extra steps than this.
const UNPLACE_COST: f64 = 8.0;

/// How much more a round may spend per search, after a round whose searches ran out of nodes.
const ESCALATION: u64 = 5;

/// A failed search, as the task planner sees it.
struct Failed {
    failure: PlanFailure,
    /// Whether the whole plan must stop (deadline, total budget).
    fatal: bool,
    /// Whether the search stopped at its own node budget (more nodes might have found it).
    out_of_nodes: bool,
    blocker_hits: Vec<u32>,
}

/// The planner's state: the episode as the plan so far leaves it.
pub(crate) struct TaskPlanner<'a> {
    options: &'a PlanOptions,
    state: Episode,
    start_steps: u32,
    actions: Vec<Action>,
    stats: PlanStats,
    relocations: Vec<u32>,
    /// The per-search node budget now: `max_search_nodes`, or more after a round ran out.
    search_nodes: u64,
}

impl<'a> TaskPlanner<'a> {
    pub(crate) fn new(episode: &Episode, options: &'a PlanOptions) -> Self {
        Self {
            options,
            state: episode.clone(),
            start_steps: episode.steps(),
            actions: Vec::new(),
            stats: PlanStats::default(),
            relocations: vec![0; episode.object_poses().len()],
            search_nodes: options.max_search_nodes,
        }
    }

    /// The actions planned and what they cost.
    pub(crate) fn finish(self) -> (Vec<Action>, PlanStats) {
        (self.actions, self.stats)
    }

    /// Plans until every object is placed.
    pub(crate) fn run(&mut self) -> Result<(), PlanFailure> {
        if self.state.is_over() {
            return Err(PlanFailure::EpisodeOver);
        }
        if let Some(held) = self.state.held() {
            self.settle_held(held)?;
        }
        let mut first: Vec<usize> = Vec::new();
        let mut tried_before: Vec<usize> = Vec::new();
        loop {
            if self.state.status() == esrp_core::EpisodeStatus::Succeeded {
                return Ok(());
            }
            if self.state.is_over() {
                return Err(self.too_long(0));
            }
            let count = self.state.object_poses().len();
            let mut blockers = vec![0u64; count];
            let mut failed: Vec<usize> = Vec::new();
            let mut last_failure = None;
            let mut placed_one = false;
            let mut out_of_nodes = false;
            for object in self.order(&first, &tried_before) {
                if let Some(occupant) = self.occupant(object) {
                    blockers[occupant] = blockers[occupant].saturating_add(ON_TARGET_WEIGHT);
                    if !self.state.placed()[occupant] {
                        // It moves when its own turn comes; no search needed now.
                        failed.push(object);
                        continue;
                    }
                }
                match self.attempt(object, Goal::Place) {
                    Ok(()) => {
                        placed_one = true;
                        break;
                    }
                    Err(f) if f.fatal => return Err(f.failure),
                    Err(f) => {
                        for (j, &hits) in f.blocker_hits.iter().enumerate() {
                            if j != object {
                                blockers[j] = blockers[j].saturating_add(u64::from(hits));
                            }
                        }
                        failed.push(object);
                        out_of_nodes |= f.out_of_nodes;
                        last_failure = Some(f.failure);
                    }
                }
            }
            if placed_one {
                first.clear();
                tried_before = failed;
                self.search_nodes = self.options.max_search_nodes;
                continue;
            }
            if out_of_nodes && self.search_nodes == self.options.max_search_nodes {
                // Cheap searches first; before moving anything aside, search harder.
                self.search_nodes = self.options.max_search_nodes.saturating_mul(ESCALATION);
                first = failed;
                tried_before.clear();
                continue;
            }
            if !self.relocate_a_blocker(&blockers)? {
                return Err(last_failure.unwrap_or_else(|| self.no_placement(failed.first().copied().unwrap_or(0))));
            }
            first = failed;
            tried_before.clear();
            self.search_nodes = self.options.max_search_nodes;
        }
    }

    /// The objects still to place, in the order to try them: `first` (those a relocation just
    /// freed), then those not tried in the last round, then the rest; within each group the
    /// nearest (agent to object plus object to target) first.
    fn order(&self, first: &[usize], tried_before: &[usize]) -> Vec<usize> {
        let scene = self.state.compiled();
        let agent = self.state.agent_pose().position;
        let mut unplaced: Vec<(u8, f64, usize)> = (0..self.state.object_poses().len())
            .filter(|&i| !self.state.placed()[i])
            .map(|i| {
                let footprint = scene.movable_footprint(i, &self.state.object_poses()[i]);
                let target = scene.movable_footprint(i, &scene.scene().movable_objects[i].target);
                let distance = footprint.distance_to_point(agent) + footprint.center.distance(target.center);
                let group = if first.contains(&i) {
                    0
                } else if tried_before.contains(&i) {
                    2
                } else {
                    1
                };
                (group, distance, i)
            })
            .collect();
        unplaced.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(a.2.cmp(&b.2)));
        unplaced.into_iter().map(|(_, _, i)| i).collect()
    }

    /// Another movable object that `object`, set exactly on its target, would collide with.
    fn occupant(&self, object: usize) -> Option<usize> {
        let scene = self.state.compiled();
        let target = scene.scene().movable_objects[object].target;
        match object_obstruction(scene, self.state.object_poses(), object, &target) {
            Some(Obstacle::Movable(j)) if self.state.held() != Some(j) => Some(j),
            _ => None,
        }
    }

    /// Deals with an object held at the start: places it, or else sets it down in a buffer.
    fn settle_held(&mut self, held: usize) -> Result<(), PlanFailure> {
        match self.attempt(held, Goal::Place) {
            Ok(()) => Ok(()),
            Err(f) if f.fatal => Err(f.failure),
            Err(f) => {
                for tier in BUFFER_TIERS {
                    match self.attempt(held, self.buffer_goal(held, tier)) {
                        Ok(()) => {
                            self.relocations[held] += 1;
                            self.stats.objects_relocated += 1;
                            return Ok(());
                        }
                        Err(g) if g.fatal => return Err(g.failure),
                        Err(_) => {}
                    }
                }
                Err(f.failure)
            }
        }
    }

    /// Moves the most obstructive object that may still be moved to a buffer pose; false when
    /// none could be.
    fn relocate_a_blocker(&mut self, blockers: &[u64]) -> Result<bool, PlanFailure> {
        let total: u32 = self.relocations.iter().sum();
        if total >= self.options.max_relocations {
            return Ok(false);
        }
        let mut candidates: Vec<usize> = (0..blockers.len())
            .filter(|&j| blockers[j] > 0 && self.relocations[j] < MAX_RELOCATIONS_PER_OBJECT)
            .collect();
        candidates.sort_by(|&a, &b| blockers[b].cmp(&blockers[a]).then(a.cmp(&b)));
        for blocker in candidates {
            for tier in BUFFER_TIERS {
                match self.attempt(blocker, self.buffer_goal(blocker, tier)) {
                    Ok(()) => {
                        self.relocations[blocker] += 1;
                        self.stats.objects_relocated += 1;
                        return Ok(true);
                    }
                    Err(f) if f.fatal => return Err(f.failure),
                    Err(_) => {}
                }
            }
        }
        Ok(false)
    }

    /// A buffer pose for `object`: clear of the other unplaced objects' targets by the tier's
    /// clearance, and its tier's distance away from where it stands.
    fn buffer_goal(&self, object: usize, (clearance, min_shift): (f64, f64)) -> Goal {
        let scene = self.state.compiled();
        let keep_clear = (0..self.state.object_poses().len())
            .filter(|&i| i != object && !self.state.placed()[i])
            .map(|i| scene.movable_footprint(i, &scene.scene().movable_objects[i].target))
            .collect();
        let origin = scene.movable_footprint(object, &self.state.object_poses()[object]).center;
        let unplaced_cost = if self.state.placed()[object] { UNPLACE_COST } else { 0.0 };
        Goal::Buffer(BufferGoal { keep_clear, clearance, origin, min_shift, unplaced_cost })
    }

    /// One search for `object`; on success its actions are committed.
    fn attempt(&mut self, object: usize, goal: Goal) -> Result<(), Failed> {
        let remaining = self.options.max_nodes.saturating_sub(self.stats.nodes_expanded);
        if remaining == 0 {
            return Err(Failed {
                failure: PlanFailure::BudgetExhausted { nodes: self.stats.nodes_expanded },
                fatal: true,
                out_of_nodes: true,
                blocker_hits: Vec::new(),
            });
        }
        let limits = SearchLimits {
            max_nodes: remaining.min(self.search_nodes),
            weight: self.options.heuristic_weight,
            cell: self.options.duplicate_cell,
            iou_weight: self.options.iou_weight,
            polish_nodes: self.options.polish_nodes,
            deadline: self.options.deadline,
            cancel: self.options.cancel.clone(),
        };
        // Out of reach: approach first (see `approach`), then the fetch-and-carry search from
        // there; if that fails, the search from here as ever.
        if self.state.held().is_none() && self.state.fetch_candidate() != Some(object) {
            if let Some(done) = self.approach_then_search(object, &goal, &limits) {
                return done;
            }
            if self.options.max_nodes <= self.stats.nodes_expanded {
                return Err(Failed {
                    failure: PlanFailure::BudgetExhausted { nodes: self.stats.nodes_expanded },
                    fatal: true,
                    out_of_nodes: true,
                    blocker_hits: Vec::new(),
                });
            }
        }
        let remaining = self.options.max_nodes.saturating_sub(self.stats.nodes_expanded);
        let limits = SearchLimits { max_nodes: remaining.min(self.search_nodes), ..limits };
        self.stats.searches += 1;
        let max_nodes = limits.max_nodes;
        match search(&self.state, object, &goal, limits) {
            Ok(found) => {
                self.stats.nodes_expanded += found.nodes;
                self.stats.cut_short |= found.cut_short;
                self.actions.extend_from_slice(&found.actions);
                self.state = found.end;
                Ok(())
            }
            Err(not_found) => {
                self.stats.nodes_expanded += not_found.nodes;
                Err(self.failed(object, not_found, max_nodes < self.search_nodes))
            }
        }
    }

    /// An approach to a pose from which `fetch` takes `object`, facing it, then the
    /// fetch-and-carry search from there. `Some` when done: committed, or a fatal failure;
    /// `None` to search from where the agent stands.
    fn approach_then_search(
        &mut self,
        object: usize,
        goal: &Goal,
        limits: &SearchLimits,
    ) -> Option<Result<(), Failed>> {
        let approach_limits = ApproachLimits {
            max_nodes: self.options.max_nodes.saturating_sub(self.stats.nodes_expanded).min(self.search_nodes),
            weight: limits.weight,
            cell: limits.cell,
            deadline: limits.deadline,
            cancel: limits.cancel.clone(),
        };
        let found = approach(&self.state, object, &approach_limits);
        self.stats.nodes_expanded += found.nodes;
        let path = found.actions?;
        let mut there = self.state.clone();
        if !path.iter().all(|&a| there.step(a).is_ok_and(|o| o.accepted)) || there.is_over() {
            return None;
        }
        let remaining = self.options.max_nodes.saturating_sub(self.stats.nodes_expanded);
        let limits = SearchLimits { max_nodes: remaining.min(self.search_nodes), ..limits.clone() };
        self.stats.searches += 1;
        match search(&there, object, goal, limits) {
            Ok(found) => {
                self.stats.nodes_expanded += found.nodes;
                self.stats.cut_short |= found.cut_short;
                self.actions.extend_from_slice(&path);
                self.actions.extend_from_slice(&found.actions);
                self.state = found.end;
                Some(Ok(()))
            }
            Err(not_found) => {
                self.stats.nodes_expanded += not_found.nodes;
                (not_found.miss == Miss::Deadline).then(|| Err(self.failed(object, not_found, false)))
            }
        }
    }

    fn failed(&self, object: usize, not_found: NotFound, total_budget_bound: bool) -> Failed {
        let (failure, fatal) = match not_found.miss {
            Miss::Deadline if self.options.cancel.as_ref().is_some_and(crate::CancelToken::is_cancelled) => {
                (PlanFailure::Cancelled, true)
            }
            Miss::Deadline => (PlanFailure::DeadlineExceeded, true),
            Miss::Budget if total_budget_bound => {
                (PlanFailure::BudgetExhausted { nodes: self.stats.nodes_expanded }, true)
            }
            _ => match not_found.cut_by_horizon {
                Some(steps) => (self.too_long(steps), false),
                None if not_found.fetched => (self.no_placement(object), false),
                None => (self.unreachable(object), false),
            },
        };
        Failed { failure, fatal, out_of_nodes: not_found.miss == Miss::Budget, blocker_hits: not_found.blocker_hits }
    }

    /// The plan needs at least `until_step` steps from the episode's start (or more than the
    /// horizon leaves, if 0).
    fn too_long(&self, until_step: u32) -> PlanFailure {
        let steps_left = self.state.horizon().saturating_sub(self.start_steps);
        let needed = until_step.saturating_sub(self.start_steps).max(steps_left.saturating_add(1));
        PlanFailure::TooLong { steps: needed as usize, steps_left }
    }

    fn no_placement(&self, object: usize) -> PlanFailure {
        PlanFailure::NoPlacement { object, id: self.id(object) }
    }

    fn unreachable(&self, object: usize) -> PlanFailure {
        PlanFailure::Unreachable { object, id: self.id(object) }
    }

    fn id(&self, object: usize) -> String {
        self.state.compiled().scene().movable_objects.get(object).map(|o| o.id.clone()).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::search::tests::bench_episode;

    /// A buffer goal keeps clear of the targets of the other objects still to be placed, and
    /// costs leaving a placed object unplaced.
    #[test]
    fn buffer_goals_keep_clear_of_the_other_unplaced_targets() {
        let episode = bench_episode(117);
        let scene = episode.compiled().clone();
        let count = episode.object_poses().len();
        assert!(count >= 2);
        let options = PlanOptions::default();
        let planner = TaskPlanner::new(&episode, &options);
        let Goal::Buffer(goal) = planner.buffer_goal(0, BUFFER_TIERS[0]) else { panic!("a buffer goal") };
        let expected: Vec<_> = (1..count)
            .filter(|&i| !episode.placed()[i])
            .map(|i| scene.movable_footprint(i, &scene.scene().movable_objects[i].target))
            .collect();
        assert_eq!(goal.keep_clear, expected);
        assert_eq!(goal.origin, scene.movable_footprint(0, &episode.object_poses()[0]).center);
        assert_eq!((goal.clearance, goal.min_shift), BUFFER_TIERS[0]);
        assert_eq!(goal.unplaced_cost, if episode.placed()[0] { UNPLACE_COST } else { 0.0 });
    }

    /// Nearest first; objects a relocation freed before all; those tried last round after.
    #[test]
    fn order_puts_freed_objects_first_and_retried_ones_last() {
        let episode = bench_episode(117);
        let options = PlanOptions::default();
        let planner = TaskPlanner::new(&episode, &options);
        let natural = planner.order(&[], &[]);
        assert!(natural.len() >= 2);
        let last = *natural.last().expect("objects");
        assert_eq!(planner.order(&[last], &[])[0], last);
        let first = natural[0];
        assert_eq!(planner.order(&[], &[first]).last(), Some(&first));
    }
}
