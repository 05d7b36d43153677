//! The approach: a weighted A* that brings the agent, holding nothing, to a pose from which
//! `fetch` takes one object with the agent facing it — every edge a real [`Episode::step`].
//!
//! The task planner runs it before an object's fetch-and-carry search when the object is out of
//! reach. The fetch-and-carry search's bound must hold for a fetch from any pose in reach, so it
//! assumes the carry of the farthest possible grip; when the agent starts far away, every
//! approach state then looks cheaper than the carry that follows the fetch, and the search
//! expands the whole room's approach states (positions × 16 headings) before it carries. The
//! approach alone has no carry to underestimate: its bound (the moves to come within reach) is
//! tight in open floor, and it ends where the fetch-and-carry search then starts within reach,
//! as from the start of an esrp-bench-v1 scene.

use std::collections::{BinaryHeap, HashMap};
use std::time::Instant;

use esrp_core::{Action, Episode};

use crate::bounds::approach_steps;
use crate::search::StateKey;

/// The largest angle between the agent's forward vector and the direction to the object's
/// footprint centre at the end of an approach (30°, as the dataset's generator fetches).
const FACING: f64 = std::f64::consts::FRAC_PI_6;

/// The knobs of one approach.
#[derive(Clone, Debug)]
pub(crate) struct ApproachLimits {
    /// Nodes it may expand.
    pub max_nodes: u64,
    /// Weight on the bound (1 = A*).
    pub weight: f64,
    /// Duplicate-detection cell, metres (0: exact keys).
    pub cell: f64,
    /// Give up at this instant.
    pub deadline: Option<Instant>,
    /// Give up when this is cancelled.
    pub cancel: Option<crate::CancelToken>,
}

/// An approach found (or not) and its cost.
pub(crate) struct Approach {
    /// The motions, or `None` when no such pose was reached within the limits.
    pub actions: Option<Vec<Action>>,
    /// Nodes expanded.
    pub nodes: u64,
}

/// The absolute angle between `episode`'s forward vector and the direction to `object`'s
/// footprint centre.
fn bearing(episode: &Episode, object: usize) -> f64 {
    let agent = episode.agent_pose();
    let centre = episode.compiled().movable_footprint(object, &episode.object_poses()[object]).center;
    let (f, dx, dz) = (agent.forward(), centre.x - agent.position.x, centre.z - agent.position.z);
    (f.x * dz - f.z * dx).atan2(f.x * dx + f.z * dz).abs()
}

/// Whether the approach is done: `fetch` would take `object`, the agent facing it.
fn arrived(episode: &Episode, object: usize) -> bool {
    episode.fetch_candidate() == Some(object) && bearing(episode, object) <= FACING
}

/// A lower bound on the motions left: the moves to come within reach of the footprint (turns
/// are left out: a move changes the bearing too). Consistent: a move changes the footprint
/// distance by at most its length, a turn not at all.
fn bound(episode: &Episode, object: usize, reach: f64) -> u32 {
    let footprint = episode.compiled().movable_footprint(object, &episode.object_poses()[object]);
    approach_steps(footprint.distance_to_point(episode.agent_pose().position), reach)
}

struct Entry {
    priority: f64,
    seq: u32,
    node: u32,
}

impl PartialEq for Entry {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == std::cmp::Ordering::Equal
    }
}

impl Eq for Entry {}

impl Ord for Entry {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        // A max-heap, so reversed: lowest priority first, then the oldest.
        other.priority.total_cmp(&self.priority).then(other.seq.cmp(&self.seq))
    }
}

impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

/// Plans the motions from `start` (holding nothing) to a pose from which `fetch` takes
/// `object`, facing it. Deterministic.
pub(crate) fn approach(start: &Episode, object: usize, limits: &ApproachLimits) -> Approach {
    if arrived(start, object) {
        return Approach { actions: Some(Vec::new()), nodes: 0 };
    }
    let reach = start.compiled().rules().fetch_reach;
    // Nodes: (episode until expanded, parent, action, cost so far).
    let mut nodes: Vec<(Option<Episode>, u32, Action, u32)> = vec![(Some(start.clone()), u32::MAX, Action::Fetch, 0)];
    let mut best_g: HashMap<StateKey, u32> = HashMap::from([(StateKey::of(start, limits.cell), 0)]);
    let mut frontier = BinaryHeap::from([Entry { priority: 0.0, seq: 0, node: 0 }]);
    let mut seq = 0;
    let mut expanded: u64 = 0;
    while let Some(Entry { node, .. }) = frontier.pop() {
        let Some(episode) = nodes[node as usize].0.take() else { continue };
        if expanded >= limits.max_nodes {
            break;
        }
        if expanded.is_multiple_of(32)
            && (limits.deadline.is_some_and(|d| Instant::now() >= d)
                || limits.cancel.as_ref().is_some_and(crate::CancelToken::is_cancelled))
        {
            break;
        }
        expanded += 1;
        let g = nodes[node as usize].3 + 1;
        let back = nodes[node as usize].2;
        for action in [Action::MoveForward, Action::TurnLeft, Action::TurnRight, Action::MoveBackward] {
            // The inverse of the motion that led here leads back to the parent (the root's
            // `Fetch` has no motion inverse).
            if action == back.inverse() {
                continue;
            }
            let mut child = episode.clone();
            if !child.step(action).is_ok_and(|o| o.accepted) || child.is_over() {
                continue;
            }
            let key = StateKey::of(&child, limits.cell);
            if best_g.get(&key).is_some_and(|&best| best <= g) {
                continue;
            }
            best_g.insert(key, g);
            if arrived(&child, object) {
                let mut actions = vec![action];
                let mut at = node;
                while at != 0 {
                    actions.push(nodes[at as usize].2);
                    at = nodes[at as usize].1;
                }
                actions.reverse();
                return Approach { actions: Some(actions), nodes: expanded };
            }
            let h = bound(&child, object, reach);
            seq += 1;
            frontier.push(Entry {
                priority: f64::from(g) + limits.weight * f64::from(h),
                seq,
                node: nodes.len() as u32,
            });
            nodes.push((Some(child), node, action, g));
        }
    }
    Approach { actions: None, nodes: expanded }
}
