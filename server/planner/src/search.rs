//! The motion planner: one weighted A* over the action lattice that fetches one object and
//! carries it to a goal, every edge a real [`Episode::step`] on a cloned episode.
//!
//! A search has two phases. In the *approach* phase nothing is held and the agent moves and
//! turns; the `fetch` edge exists only where [`Episode::fetch_candidate`] is the searched
//! object. In the *carry* phase the agent moves and turns with the object. The goal is a
//! `release` from a carry state: its cost is one step plus a terminal cost (for a placement,
//! `iou_weight · (1 − IoU)`, so that a slightly longer plan that sets the object down squarely
//! wins over a short one that barely clears the threshold). Because the fetch pose is part of
//! the search, the planner chooses where to grab the object by what the carry then needs.
//!
//! Duplicate states are detected on a key of the agent's pose and the carried object's pose:
//! exact (the bits of the `f64` coordinates) or, with a positive `duplicate_cell`, by cells of
//! that size. Cells can only cost completeness, never correctness: every edge is still a real
//! step, and the caller replays the whole plan before returning it.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};
use std::time::Instant;

use esrp_core::{Action, Episode, EpisodeStatus, Obstacle, OrientedRect, PlanPoint, footprint_iou};

use crate::bounds::{PlacementGeometry, approach_steps, carry_step_length, yaw_offset};

/// What the carried object should end as.
#[derive(Clone, Debug)]
pub(crate) enum Goal {
    /// Placed: released with footprint IoU above the threshold.
    Place,
    /// Set down out of the way, in a buffer pose.
    Buffer(BufferGoal),
}

/// A buffer pose: somewhere the object stops being in the way.
#[derive(Clone, Debug)]
pub(crate) struct BufferGoal {
    /// Footprints the released object must keep at least `clearance` away from (the targets of
    /// the objects still to be placed).
    pub keep_clear: Vec<OrientedRect>,
    /// Metres between the released footprint and every `keep_clear` footprint.
    pub clearance: f64,
    /// Where the object's footprint centre was when it was found in the way.
    pub origin: PlanPoint,
    /// How far, at least, its footprint centre must end from `origin`, metres.
    pub min_shift: f64,
    /// Terminal cost of a release that leaves the object unplaced, in steps (zero for an
    /// object that is not placed now; positive for a placed one, which is better re-placed
    /// clear of the others than put aside).
    pub unplaced_cost: f64,
}

/// The knobs of one search.
#[derive(Clone, Debug)]
pub(crate) struct SearchLimits {
    /// Nodes this search may expand.
    pub max_nodes: u64,
    /// Weight on the heuristic (1 = A*).
    pub weight: f64,
    /// Duplicate-detection cell, metres; 0 for exact keys.
    pub cell: f64,
    /// Terminal cost per unit of IoU short of 1, in steps.
    pub iou_weight: f64,
    /// Nodes expanded after the first goal release is found, at most, looking for a cheaper
    /// one; then the cheapest found is taken.
    pub polish_nodes: u64,
    /// Give up when this instant passes.
    pub deadline: Option<Instant>,
    /// Give up when this is cancelled.
    pub cancel: Option<crate::CancelToken>,
}

/// A path found: the actions (ending with the release) and the episode after them.
#[derive(Clone, Debug)]
pub(crate) struct Found {
    pub actions: Vec<Action>,
    pub end: Episode,
    pub nodes: u64,
    /// The deadline or a cancel stopped the search before it proved `actions` the cheapest.
    pub cut_short: bool,
}

/// Why a search found nothing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Miss {
    /// No pose from which `fetch` takes the object was reached.
    NeverFetched,
    /// The object was fetched but no goal release was reached (search space exhausted).
    NoGoal,
    /// The search's node budget ran out.
    Budget,
    /// The deadline passed, or the caller cancelled.
    Deadline,
}

/// A failed search: why, what it cost, and what stood in its way.
#[derive(Clone, Debug)]
pub(crate) struct NotFound {
    pub miss: Miss,
    pub nodes: u64,
    /// Rejected motions per movable object hit: the likely blockers.
    pub blocker_hits: Vec<u32>,
    /// Whether any node held the object (the fetch pose was found).
    pub fetched: bool,
    /// The smallest lower bound on the steps of a path that the horizon cut off, if any.
    pub cut_by_horizon: Option<u32>,
}

/// A state's identity for duplicate detection.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(crate) struct StateKey {
    agent: [i64; 2],
    heading: u8,
    /// The carried object's position and yaw (`None` in the approach phase).
    held: Option<[i64; 3]>,
}

impl StateKey {
    /// The key of `episode`'s state when only the agent and what it holds can have moved:
    /// exact with `cell == 0`, else by cells of `cell` metres (and the held object's yaw by its
    /// bits, since a carried object only ever turns in whole turns).
    pub(crate) fn of(episode: &Episode, cell: f64) -> Self {
        let agent = episode.agent_pose();
        let quantise = |v: f64| if cell > 0.0 { (v / cell).floor() as i64 } else { v.to_bits() as i64 };
        let held = episode.held().map(|i| {
            let pose = episode.object_poses()[i];
            [quantise(pose.x), quantise(pose.z), pose.yaw.to_bits() as i64]
        });
        Self { agent: [quantise(agent.position.x), quantise(agent.position.z)], heading: agent.heading.index(), held }
    }
}

/// The lower bound on the steps from `episode` to the goal of a search for `object`, or `None`
/// where the goal cannot be reached (a carried object at a yaw that can never be placed).
pub(crate) struct Bound<'a> {
    object: usize,
    goal: &'a Goal,
    geometry: PlacementGeometry,
    reach: f64,
}

impl<'a> Bound<'a> {
    pub(crate) fn new(episode: &Episode, object: usize, goal: &'a Goal) -> Self {
        Self {
            object,
            goal,
            geometry: PlacementGeometry::new(episode, object),
            reach: episode.compiled().rules().fetch_reach,
        }
    }

    /// Steps still needed, at least: consistent and zero only at a goal.
    pub(crate) fn steps(&self, episode: &Episode) -> Option<u32> {
        let scene = episode.compiled();
        let pose = episode.object_poses()[self.object];
        let footprint = scene.movable_footprint(self.object, &pose);
        let agent = episode.agent_pose().position;
        if episode.held() == Some(self.object) {
            let step = carry_step_length(footprint.center.distance(agent));
            let carry = self.carry_steps(footprint.center, yaw_offset(self.geometry.yaw0, pose.yaw), step)?;
            Some(carry + 1)
        } else {
            let approach = approach_steps(footprint.distance_to_point(agent), self.reach);
            let step = carry_step_length(self.reach + self.geometry.circumradius);
            let carry = self.carry_steps(footprint.center, 0, step)?;
            Some(approach + 1 + carry + 1)
        }
    }

    fn carry_steps(&self, center: PlanPoint, offset: u8, step: f64) -> Option<u32> {
        match self.goal {
            Goal::Place => self.geometry.carry_steps(center, offset, step),
            Goal::Buffer(buffer) => {
                let shift = buffer.min_shift - center.distance(buffer.origin);
                Some(if shift <= 1e-9 { 0 } else { (shift / step - 1e-9).ceil().max(0.0) as u32 })
            }
        }
    }

    /// Whether placing is possible at all for the object's yaws.
    pub(crate) fn placeable(&self) -> bool {
        self.geometry.placeable()
    }
}

/// A node of the search tree: its episode until expanded, how it was reached.
struct Node {
    episode: Option<Episode>,
    parent: u32,
    action: Action,
    g: u32,
    key: StateKey,
}

/// A frontier entry: a node to expand or a goal release to accept.
struct Entry {
    priority: f64,
    h: u32,
    seq: u32,
    what: What,
}

enum What {
    Expand(u32),
    Accept(u32),
}

impl PartialEq for Entry {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}

impl Eq for Entry {}

impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        // A max-heap, so reversed: lowest priority, then lowest bound, then oldest first.
        other.priority.total_cmp(&self.priority).then(other.h.cmp(&self.h)).then(other.seq.cmp(&self.seq))
    }
}

impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// A goal release found: the node it follows and the episode after it.
struct Release {
    node: u32,
    end: Episode,
}

/// The search for one object.
struct Search<'a> {
    object: usize,
    goal: &'a Goal,
    limits: SearchLimits,
    bound: Bound<'a>,
    threshold: f64,
    nodes: Vec<Node>,
    best_g: HashMap<StateKey, u32>,
    frontier: BinaryHeap<Entry>,
    releases: Vec<Release>,
    seq: u32,
    blocker_hits: Vec<u32>,
    cut_by_horizon: Option<u32>,
    fetched: bool,
    /// Nodes expanded so far (for recording when the first goal was found).
    expanded: u64,
    /// Nodes expanded when the first goal release was found.
    first_release_at: Option<u64>,
    /// The cheapest goal release found: its cost and index.
    best_release: Option<(f64, u32)>,
}

/// Plans from `start` (holding nothing, or holding `object`) to a release of `object` that
/// meets `goal`.
pub(crate) fn search(start: &Episode, object: usize, goal: &Goal, limits: SearchLimits) -> Result<Found, NotFound> {
    let scene = start.compiled();
    let mut search = Search {
        object,
        goal,
        limits,
        bound: Bound::new(start, object, goal),
        threshold: scene.rules().placement_iou,
        nodes: Vec::new(),
        best_g: HashMap::new(),
        frontier: BinaryHeap::new(),
        releases: Vec::new(),
        seq: 0,
        blocker_hits: vec![0; start.object_poses().len()],
        cut_by_horizon: None,
        fetched: start.held() == Some(object),
        expanded: 0,
        first_release_at: None,
        best_release: None,
    };
    search.run(start)
}

impl Search<'_> {
    fn run(&mut self, start: &Episode) -> Result<Found, NotFound> {
        if matches!(self.goal, Goal::Place) && !self.bound.placeable() {
            return Err(self.not_found(Miss::NoGoal, 0));
        }
        self.add(start.clone(), u32::MAX, Action::Release, 0);
        let mut expanded: u64 = 0;
        let miss = loop {
            let Some(entry) = self.frontier.pop() else {
                break if self.fetched { Miss::NoGoal } else { Miss::NeverFetched };
            };
            let node = match entry.what {
                What::Accept(release) => return Ok(self.found(release, expanded, false)),
                What::Expand(node) => node,
            };
            let n = &mut self.nodes[node as usize];
            if self.best_g.get(&n.key).is_some_and(|&g| g < n.g) {
                continue;
            }
            let Some(episode) = n.episode.take() else { continue };
            if expanded >= self.limits.max_nodes {
                break Miss::Budget;
            }
            if self.first_release_at.is_some_and(|at| expanded >= at.saturating_add(self.limits.polish_nodes)) {
                break Miss::Budget;
            }
            if expanded.is_multiple_of(32)
                && (self.limits.deadline.is_some_and(|d| Instant::now() >= d)
                    || self.limits.cancel.as_ref().is_some_and(crate::CancelToken::is_cancelled))
            {
                break Miss::Deadline;
            }
            expanded += 1;
            self.expand(node, &episode, expanded);
        };
        // Out of nodes or time with goals found but not yet proven best: take the best found.
        match self.best_release {
            Some((_, release)) => Ok(self.found(release, expanded, miss == Miss::Deadline)),
            None => Err(self.not_found(miss, expanded)),
        }
    }

    fn not_found(&self, miss: Miss, nodes: u64) -> NotFound {
        NotFound {
            miss,
            nodes,
            blocker_hits: self.blocker_hits.clone(),
            fetched: self.fetched,
            cut_by_horizon: self.cut_by_horizon,
        }
    }

    fn found(&mut self, release: u32, nodes: u64, cut_short: bool) -> Found {
        let Release { node, end } = self.releases.swap_remove(release as usize);
        let mut actions = vec![Action::Release];
        let mut at = node;
        while at != 0 {
            let n = &self.nodes[at as usize];
            actions.push(n.action);
            at = n.parent;
        }
        actions.reverse();
        Found { actions, end, nodes, cut_short }
    }

    fn expand(&mut self, node: u32, episode: &Episode, expanded: u64) {
        self.expanded = expanded;
        let g = self.nodes[node as usize].g + 1;
        let holding = episode.held() == Some(self.object);
        let fetch = !holding && episode.fetch_candidate() == Some(self.object);
        let actions: &[Action] = if fetch {
            &[Action::Fetch, Action::MoveForward, Action::TurnLeft, Action::TurnRight, Action::MoveBackward]
        } else {
            &[Action::MoveForward, Action::TurnLeft, Action::TurnRight, Action::MoveBackward]
        };
        // The inverse of the motion that led here leads back to the parent, reached one step
        // cheaper: duplicate detection would reject it, so do not pay for its collision check.
        let incoming = self.nodes[node as usize].action;
        let back = incoming.is_motion().then(|| incoming.inverse());
        for &action in actions {
            if Some(action) == back {
                continue;
            }
            let mut child = episode.clone();
            let Ok(outcome) = child.step(action) else { continue };
            if !outcome.accepted {
                if let Some(Obstacle::Movable(j)) = outcome.collided_with
                    && let Some(hits) = self.blocker_hits.get_mut(j)
                {
                    *hits += 1;
                }
                continue;
            }
            if action == Action::Fetch {
                self.fetched = true;
            }
            if child.is_over() {
                // Truncated: the horizon cuts this path off.
                let h = self.bound.steps(&child).unwrap_or(0);
                let total = child.steps().saturating_add(h);
                self.cut_by_horizon = Some(self.cut_by_horizon.map_or(total, |c| c.min(total)));
                continue;
            }
            self.add(child, node, action, g);
        }
    }

    /// Adds a state reached with cost `g`: a node to expand unless a state with the same key
    /// was reached as cheaply, and a goal release if releasing here meets the goal.
    fn add(&mut self, episode: Episode, parent: u32, action: Action, g: u32) {
        let Some(h) = self.bound.steps(&episode) else { return };
        let key = StateKey::of(&episode, self.limits.cell);
        if self.best_g.get(&key).is_some_and(|&best| best <= g) {
            return;
        }
        self.best_g.insert(key, g);
        let index = self.nodes.len() as u32;
        if episode.held() == Some(self.object)
            && let Some((end, terminal)) = self.release_here(&episode)
        {
            let release = self.releases.len() as u32;
            let cost = f64::from(g) + 1.0 + terminal;
            self.releases.push(Release { node: index, end });
            self.first_release_at.get_or_insert(self.expanded);
            if self.best_release.is_none_or(|(best, _)| cost < best) {
                self.best_release = Some((cost, release));
            }
            self.push(cost, 0, What::Accept(release));
        }
        self.nodes.push(Node { episode: Some(episode), parent, action, g, key });
        self.push(f64::from(g) + self.limits.weight * f64::from(h), h, What::Expand(index));
    }

    fn push(&mut self, priority: f64, h: u32, what: What) {
        self.seq += 1;
        self.frontier.push(Entry { priority, h, seq: self.seq, what });
    }

    /// If releasing now meets the goal: the episode after the real release and the terminal
    /// cost beyond the release step.
    fn release_here(&self, episode: &Episode) -> Option<(Episode, f64)> {
        let scene = episode.compiled();
        let footprint = scene.movable_footprint(self.object, &episode.object_poses()[self.object]);
        let terminal = match self.goal {
            Goal::Place => {
                let iou = footprint_iou(&footprint, &self.bound.geometry.target);
                if iou <= self.threshold {
                    return None;
                }
                self.limits.iou_weight * (1.0 - iou)
            }
            Goal::Buffer(buffer) => {
                if footprint.center.distance(buffer.origin) < buffer.min_shift
                    || buffer.keep_clear.iter().any(|r| rect_distance(r, &footprint) < buffer.clearance)
                {
                    return None;
                }
                0.0
            }
        };
        let mut end = episode.clone();
        let outcome = end.step(Action::Release).ok()?;
        if !outcome.accepted {
            return None;
        }
        if end.is_over() && end.status() != EpisodeStatus::Succeeded {
            // The release would end the episode at its horizon with objects left.
            return None;
        }
        let placed = end.placed().get(self.object).copied().unwrap_or(false);
        match self.goal {
            Goal::Place => placed.then_some((end, terminal)),
            Goal::Buffer(buffer) => Some((end, if placed { terminal } else { terminal + buffer.unplaced_cost })),
        }
    }
}

/// The distance between two oriented rectangles (0 when they touch or overlap).
pub(crate) fn rect_distance(a: &OrientedRect, b: &OrientedRect) -> f64 {
    if footprint_iou(a, b) > 0.0 {
        return 0.0;
    }
    // Disjoint convex polygons are closest at a vertex of one of them.
    let from_a = a.corners().iter().map(|&p| b.distance_to_point(p)).fold(f64::INFINITY, f64::min);
    let from_b = b.corners().iter().map(|&p| a.distance_to_point(p)).fold(f64::INFINITY, f64::min);
    from_a.min(from_b)
}

#[cfg(test)]
pub(crate) mod tests {
    use std::sync::Arc;

    use esrp_core::{CompiledScene, EpisodeConfig};

    use super::*;

    /// Benchmark scene `index` at its start.
    pub(crate) fn bench_episode(index: usize) -> Episode {
        let scene = esrp_dataset::Benchmark::new(esrp_dataset::BenchVersion::V1, esrp_dataset::DEFAULT_SEED)
            .generate(index)
            .expect("the scene generates")
            .scene;
        let compiled = CompiledScene::new(scene, esrp_core::Rules::default()).expect("a valid scene");
        Episode::new(Arc::new(compiled), EpisodeConfig::default()).expect("a valid configuration")
    }

    fn limits() -> SearchLimits {
        SearchLimits {
            max_nodes: 40_000,
            weight: 2.0,
            cell: 0.05,
            iou_weight: 12.0,
            polish_nodes: 2_000,
            deadline: None,
            cancel: None,
        }
    }

    /// A tiny deterministic random source for sampling walks.
    struct XorShift(u64);

    impl XorShift {
        fn below(&mut self, n: usize) -> usize {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 % n as u64) as usize
        }
    }

    const MOTIONS: [Action; 4] = [Action::MoveForward, Action::MoveBackward, Action::TurnLeft, Action::TurnRight];

    /// The bound of a place search drops by at most one per real step and is at most one where
    /// a release places the object (consistency, hence admissibility), on states along the
    /// planner's own paths and on random walks off them, approaching and carrying.
    #[test]
    fn the_place_bound_is_consistent_on_sampled_states() {
        let mut rng = XorShift(0x2545_f491_4f6c_dd1d);
        let mut checked = 0;
        for index in [50, 117] {
            let start = bench_episode(index);
            for object in 0..start.object_poses().len() {
                let bound = Bound::new(&start, object, &Goal::Place);
                let found = search(&start, object, &Goal::Place, limits()).expect("a path");
                let mut on_path = start.clone();
                let total = found.actions.len() as u32;
                for (i, &action) in found.actions.iter().enumerate() {
                    let h = bound.steps(&on_path).expect("a bound on the path");
                    assert!(h <= total - i as u32, "scene {index} object {object}: h {h} beyond the path's rest");
                    // Random walks off the path, checking every edge out of every state met.
                    let mut walker = on_path.clone();
                    for _ in 0..6 {
                        checked += check_edges(&bound, object, &walker);
                        let mut next = walker.clone();
                        if next.step(MOTIONS[rng.below(4)]).is_ok_and(|o| o.accepted) && !next.is_over() {
                            walker = next;
                        }
                    }
                    on_path.step(action).expect("a running episode");
                }
            }
        }
        assert!(checked > 500, "only {checked} edges checked");
    }

    /// Checks `h(s) ≤ 1 + h(s')` on every accepted edge out of `state`; the edges checked.
    fn check_edges(bound: &Bound<'_>, object: usize, state: &Episode) -> usize {
        let Some(h) = bound.steps(state) else { return 0 };
        let mut checked = 0;
        for action in Action::ALL {
            let mut next = state.clone();
            let Ok(outcome) = next.step(action) else { continue };
            if !outcome.accepted || next.held().is_some_and(|held| held != object) {
                continue;
            }
            checked += 1;
            if action == Action::Release {
                if next.placed()[object] {
                    assert!(h <= 1, "{h} steps bound where a release places the object");
                }
                continue;
            }
            if let Some(h_next) = bound.steps(&next) {
                assert!(h <= 1 + h_next, "{action:?} drops the bound from {h} to {h_next}");
            }
        }
        checked
    }

    #[test]
    fn exact_keys_identify_states_reached_by_commuting_paths() {
        let start = bench_episode(7);
        let run = |actions: &[Action]| {
            let mut e = start.clone();
            actions.iter().all(|&a| e.step(a).is_ok_and(|o| o.accepted)).then_some(e)
        };
        let mut compared = 0;
        for first in [Action::MoveForward, Action::MoveBackward] {
            for turn in [Action::TurnLeft, Action::TurnRight] {
                let back = turn.inverse();
                // Two moves along two headings, in either order: the same integer move counts.
                let (Some(a), Some(b)) = (run(&[turn, first, back, first]), run(&[first, turn, first, back])) else {
                    continue;
                };
                assert_eq!(StateKey::of(&a, 0.0), StateKey::of(&b, 0.0));
                assert_eq!(StateKey::of(&a, 0.05), StateKey::of(&b, 0.05));
                assert!(a.same_state(&b));
                // One more turn is another state.
                let mut c = a.clone();
                c.step(Action::TurnLeft).expect("a running episode");
                assert_ne!(StateKey::of(&a, 0.0), StateKey::of(&c, 0.0));
                assert_ne!(StateKey::of(&a, 0.05), StateKey::of(&c, 0.05));
                compared += 1;
            }
        }
        assert!(compared > 0, "no commuting pair was free of collisions");
        // Holding the object is another state than standing in the same pose without it.
        let mut held = start.clone();
        if held.step(Action::Fetch).is_ok_and(|o| o.accepted) {
            assert_ne!(StateKey::of(&start, 0.0), StateKey::of(&held, 0.0));
        }
        // Exact keys tell apart positions a cell would merge.
        let mut moved = start.clone();
        for action in [Action::TurnLeft, Action::MoveForward, Action::TurnRight, Action::MoveBackward] {
            moved.step(action).expect("a running episode");
        }
        if moved.agent_pose().position != start.agent_pose().position {
            assert_ne!(StateKey::of(&start, 0.0), StateKey::of(&moved, 0.0));
        }
    }

    #[test]
    fn rect_distance_of_simple_rectangles() {
        let r = |x: f64, z: f64, yaw: f64| OrientedRect { center: PlanPoint::new(x, z), half_x: 0.5, half_z: 0.5, yaw };
        for (a, b, expected) in [
            (r(0.0, 0.0, 0.0), r(0.5, 0.0, 0.0), 0.0),
            (r(0.0, 0.0, 0.0), r(2.0, 0.0, 0.0), 1.0),
            (r(0.0, 0.0, 0.0), r(2.0, 2.0, 0.0), 2f64.sqrt()),
            (r(0.0, 0.0, 0.0), r(2.0, 0.0, std::f64::consts::FRAC_PI_4), 1.5 - 0.5 * 2f64.sqrt()),
        ] {
            assert!((rect_distance(&a, &b) - expected).abs() < 1e-9, "{a:?} {b:?}");
            assert!((rect_distance(&b, &a) - expected).abs() < 1e-9, "{b:?} {a:?}");
        }
    }

    /// A buffer search sets the object down away from where it stood and clear of the
    /// footprints it must keep clear of, and lets go of it.
    #[test]
    fn a_buffer_release_is_shifted_and_clear() {
        let start = bench_episode(50);
        let scene = start.compiled();
        let object = 0;
        let other_target = scene.movable_footprint(1, &scene.scene().movable_objects[1].target);
        let origin = scene.movable_footprint(object, &start.object_poses()[object]).center;
        let own_target = scene.movable_footprint(object, &scene.scene().movable_objects[object].target);
        let goal = Goal::Buffer(BufferGoal {
            keep_clear: vec![other_target, own_target],
            clearance: 0.3,
            origin,
            min_shift: 1.0,
            unplaced_cost: 0.0,
        });
        let found = search(&start, object, &goal, limits()).expect("a buffer pose");
        assert_eq!(found.actions.last(), Some(&Action::Release));
        assert_eq!(found.end.held(), None);
        let footprint = scene.movable_footprint(object, &found.end.object_poses()[object]);
        assert!(footprint.center.distance(origin) >= 1.0);
        assert!(rect_distance(&footprint, &other_target) >= 0.3);
        assert!(rect_distance(&footprint, &own_target) >= 0.3);
        // The same path replays on the start episode.
        let mut replay = start.clone();
        for &action in &found.actions {
            assert!(replay.step(action).is_ok_and(|o| o.accepted));
        }
        assert!(replay.same_state(&found.end));
    }
}
