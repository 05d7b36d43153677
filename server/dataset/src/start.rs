//! The agent's start pose of esrp-bench-v2 (SPEC §7): away from the objects.
//!
//! After its last release the generator's agent, holding nothing, explores the poses it can
//! reach on the action lattice — 0.25 m moves, 22.5° turns, every motion stepped through the
//! same `esrp_core::Episode` as an episode — by a breadth-first search from the release pose.
//! Among the poses found it draws one at random from which every movable object's footprint is
//! at least [`StartRule::min_clearance`] away on the plan (so nothing is within fetch reach), or,
//! where the room has none, takes the pose farthest from them; the heading is drawn among all
//! 16. The agent then drives there along the search's path: that drive, reversed, is the start
//! of the expert trajectory, which brings the agent back to its last release pose.
//!
//! # The search
//!
//! A turn with nothing held never collides (the robot is a cylinder turning about its own
//! axis; esrp-core does not even check it), so reachability is a question about positions: from
//! each position the search tries the 16 moves of 0.25 m (forward along each heading, taken
//! forward or backward, whichever needs fewer turns from the heading the agent arrived with).
//! Positions of the lattice are dense in the plane, so the search keeps one position per cell
//! of a grid — the first one found — and stops after [`StartRule::max_poses`] positions. A cell
//! is keyed by the integer move counts along the 8 axes (relative to the release pose), not by
//! float coordinates, so a search repeated from the same pose reached by a different float path
//! (the validator replays the expert to it) finds the same cells. The grid is coarse first
//! (0.25 m, one move: about 180 positions in a room, a few milliseconds); only where that finds
//! no pose far enough is the search repeated on finer grids ([`StartRule::cells`]), which get
//! through gaps that the first position of a coarse cell misses (one room in twenty: the agent
//! often ends in a pocket of the furniture it has just moved).
//!
//! Each move is stepped with `Episode::step` on a clone of the episode at the parent position:
//! the collision check is esrp-core's, and the positions are the episode's own, so the drive that
//! the search returns replays exactly.

use std::collections::VecDeque;

use esrp_core::{
    Action, AgentStart, CompiledScene, Episode, EpisodeConfig, Heading, ObjectPose, PlanPoint, Scene,
    reverse_trajectory,
};
use rustc_hash::FxHashSet;

use crate::backward::{Construction, Rejection, horizon_for, validate_by_replay};
use crate::dice::Dice;

/// The rule of SPEC §7 for esrp-bench-v2 start poses and the search's limits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StartRule {
    /// A start pose must be at least this far (plan distance) from every movable object's
    /// footprint where the room has such poses, metres (1.5).
    pub min_clearance: f64,
    /// Sides of the grid cells the search keeps one position of, metres, coarse to fine: each
    /// finer grid is searched only if the coarser found no pose [`StartRule::min_clearance`]
    /// away.
    pub cells: [f64; 3],
    /// Most positions one search visits.
    pub max_poses: usize,
}

impl Default for StartRule {
    fn default() -> Self {
        Self { min_clearance: 1.5, cells: [0.25, 0.125, 0.0625], max_poses: 20_000 }
    }
}

/// The plan distance from `position` to the nearest movable object's footprint, the objects at
/// `poses` (infinite without movable objects).
pub fn object_clearance(compiled: &CompiledScene, poses: &[ObjectPose], position: PlanPoint) -> f64 {
    poses
        .iter()
        .enumerate()
        .map(|(i, pose)| compiled.movable_footprint(i, pose).distance_to_point(position))
        .fold(f64::INFINITY, f64::min)
}

/// The plan step of one move forward along heading `j` (`j` in `0..16`), as esrp-core computes it.
fn step_of(j: u8) -> PlanPoint {
    let h = Heading::wrapping(i64::from(j));
    PlanPoint::new(esrp_core::world::MOVE_DISTANCE * h.cos(), -(esrp_core::world::MOVE_DISTANCE * h.sin()))
}

/// A position the search reached.
#[derive(Clone, Debug)]
struct Node {
    /// The episode with the agent there.
    episode: Episode,
    /// Net moves along headings `0..8` since the root (a move along heading `j + 8` counts −1
    /// on `j`).
    counts: [i32; 8],
    /// The node it was reached from (`usize::MAX` for the root).
    parent: usize,
    /// The actions from the parent: turns, then one move.
    edge: Vec<Action>,
    /// Its clearance from the movable objects, metres.
    clearance: f64,
}

/// The positions reachable from an episode's pose with nothing held, as the search finds them.
#[derive(Clone, Debug)]
pub struct Reach {
    nodes: Vec<Node>,
    /// The grid's cell side, metres.
    pub cell: f64,
    /// Whether the search stopped at [`StartRule::max_poses`] with positions left to visit.
    pub capped: bool,
}

/// The grid cell of a position `counts` moves away from the root.
fn cell_of(counts: &[i32; 8], cell: f64) -> (i64, i64) {
    let (mut dx, mut dz) = (0.0, 0.0);
    for (j, &n) in counts.iter().enumerate() {
        if n != 0 {
            let s = step_of(j as u8);
            dx += f64::from(n) * s.x;
            dz += f64::from(n) * s.z;
        }
    }
    ((dx / cell).round() as i64, (dz / cell).round() as i64)
}

/// The turns that take `from` to `to` the short way (left on a tie).
fn turns(from: Heading, to: Heading) -> impl Iterator<Item = Action> {
    let left = to.turns_from(from);
    let (action, n) = if left <= 8 { (Action::TurnLeft, left) } else { (Action::TurnRight, 16 - left) };
    std::iter::repeat_n(action, usize::from(n))
}

/// The search of the rule: [`reachable`] on each grid of [`StartRule::cells`] in turn, until one
/// finds a pose [`StartRule::min_clearance`] away. If none does, the search whose farthest pose
/// is farthest (the coarser on a tie): a finer grid keeps other positions, not always farther
/// ones.
pub fn search(start: &Episode, rule: &StartRule) -> Reach {
    let mut best = reachable(start, rule.cells[0], rule.max_poses);
    for &cell in &rule.cells[1..] {
        if best.max_clearance() >= rule.min_clearance {
            break;
        }
        let finer = reachable(start, cell, rule.max_poses);
        if finer.max_clearance() > best.max_clearance() {
            best = finer;
        }
    }
    best
}

/// Breadth-first search over the positions reachable from `start` (which must hold nothing),
/// one per grid cell of side `cell`, at most `max_poses`: the root is `start`'s own position.
pub fn reachable(start: &Episode, cell: f64, max_poses: usize) -> Reach {
    let compiled = start.compiled().clone();
    let root_clearance = object_clearance(&compiled, start.object_poses(), start.agent_pose().position);
    let mut nodes = vec![Node {
        episode: start.clone(),
        counts: [0; 8],
        parent: usize::MAX,
        edge: Vec::new(),
        clearance: root_clearance,
    }];
    let mut seen = FxHashSet::from_iter([cell_of(&[0; 8], cell)]);
    let mut queue = VecDeque::from([0usize]);
    let mut capped = false;
    'search: while let Some(at) = queue.pop_front() {
        for direction in 0..16u8 {
            if nodes.len() >= max_poses {
                capped = true;
                break 'search;
            }
            let mut counts = nodes[at].counts;
            let axis = usize::from(direction % 8);
            counts[axis] += if direction < 8 { 1 } else { -1 };
            let key = cell_of(&counts, cell);
            if seen.contains(&key) {
                continue;
            }
            // Face the direction of travel, or its opposite and back up: the fewer turns.
            let heading = nodes[at].episode.agent_pose().heading;
            let ahead = Heading::wrapping(i64::from(direction));
            let behind = Heading::wrapping(i64::from(direction) + 8);
            let short = |to: Heading| {
                let left = to.turns_from(heading);
                left.min(16 - left)
            };
            let (face, motion) = if short(ahead) <= short(behind) {
                (ahead, Action::MoveForward)
            } else {
                (behind, Action::MoveBackward)
            };
            let mut edge: Vec<Action> = turns(heading, face).collect();
            edge.push(motion);
            let mut episode = nodes[at].episode.clone();
            let accepted = edge.iter().all(|&a| episode.step(a).is_ok_and(|o| o.accepted));
            if !accepted {
                continue;
            }
            seen.insert(key);
            let clearance = object_clearance(&compiled, episode.object_poses(), episode.agent_pose().position);
            nodes.push(Node { episode, counts, parent: at, edge, clearance });
            queue.push_back(nodes.len() - 1);
        }
    }
    Reach { nodes, cell, capped }
}

impl Reach {
    /// Number of positions found (the root included).
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    /// Always false: the root is found.
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// The largest clearance among the positions found.
    pub fn max_clearance(&self) -> f64 {
        self.nodes.iter().map(|n| n.clearance).fold(f64::NEG_INFINITY, f64::max)
    }

    /// The positions found with at least `min` clearance, in search order.
    pub fn clear_of(&self, min: f64) -> Vec<usize> {
        (0..self.nodes.len()).filter(|&i| self.nodes[i].clearance >= min).collect()
    }

    /// The first position of largest clearance.
    pub fn farthest(&self) -> usize {
        let mut best = 0;
        for (i, n) in self.nodes.iter().enumerate() {
            if n.clearance > self.nodes[best].clearance {
                best = i;
            }
        }
        best
    }

    /// The actions from the root to position `node`.
    fn path_to(&self, node: usize) -> Vec<Action> {
        let mut edges = Vec::new();
        let mut at = node;
        while at != 0 {
            edges.push(&self.nodes[at].edge);
            at = self.nodes[at].parent;
        }
        edges.into_iter().rev().flatten().copied().collect()
    }
}

/// The start pose chosen for a scene, and the drive to it.
#[derive(Clone, Debug)]
pub struct StartChoice {
    /// The actions from the last release pose to the start pose (the last turns face the drawn
    /// heading).
    pub drive: Vec<Action>,
    /// The episode at the start pose.
    pub episode: Episode,
    /// The start's clearance from the movable objects, metres.
    pub clearance: f64,
    /// True when no reachable pose had the rule's clearance and the farthest was taken.
    pub fallback: bool,
    /// Positions the search found.
    pub searched: usize,
    /// The cell side of the search's grid, metres.
    pub cell: f64,
}

/// Draws the start pose of SPEC §7 from `episode` (the generator after its last release), with
/// `dice`: a position uniformly among those found with the rule's clearance (else the farthest)
/// and a heading uniformly among all 16. `None` only if a final turn (nothing held) were
/// rejected, which esrp-core rules out.
pub fn choose_start(episode: &Episode, dice: &mut Dice, rule: &StartRule) -> Option<StartChoice> {
    let reach = search(episode, rule);
    let clear = reach.clear_of(rule.min_clearance);
    let (node, fallback) = if clear.is_empty() { (reach.farthest(), true) } else { (*dice.pick(&clear), false) };
    let heading = Heading::wrapping(dice.below(16) as i64);
    let mut drive = reach.path_to(node);
    // The node's episode is the caller's stepped along the path; turn it to the drawn heading.
    let mut at = reach.nodes[node].episode.clone();
    for action in turns(at.agent_pose().heading, heading) {
        if !at.step(action).ok()?.accepted {
            return None;
        }
        drive.push(action);
    }
    Some(StartChoice {
        drive,
        clearance: reach.nodes[node].clearance,
        episode: at,
        fallback,
        searched: reach.len(),
        cell: reach.cell,
    })
}

/// How a start pose was chosen, for generation reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StartReport {
    /// The start's clearance from the movable objects, metres.
    pub clearance: f64,
    /// True when no reachable pose had the rule's clearance and the farthest was taken.
    pub fallback: bool,
    /// Positions the search found.
    pub searched: usize,
    /// The cell side of the search's grid, metres.
    pub cell: f64,
    /// Moves and turns of the drive from the last release pose to the start.
    pub drive: usize,
}

/// Finishes an esrp-bench-v2 scene from a [`Construction`] (esrp-bench-v1's scene and the
/// generator's state after its last release): the agent drives to a start pose drawn by
/// [`choose_start`], and the expert trajectory is the generator's run and the drive, reversed
/// and inverted — the reversed drive back to the last release pose, then esrp-bench-v1's expert.
/// The horizon follows the expert's new length, and the scene is replayed to success.
pub fn start_away(
    construction: Construction,
    dice: &mut Dice,
    rule: &StartRule,
) -> Result<(Scene, StartReport), Rejection> {
    let Construction { mut scene, episode, mut run } = construction;
    let choice = choose_start(&episode, dice, rule).ok_or(Rejection::StartDrive)?;
    let agent = choice.episode.agent_pose();
    scene.agent = AgentStart { x: agent.position.x, z: agent.position.z, heading: agent.heading };
    run.extend_from_slice(&choice.drive);
    scene.expert_trajectory = reverse_trajectory(&run);
    scene.horizon = horizon_for(scene.expert_trajectory.len());
    validate_by_replay(&scene).map_err(|_| Rejection::StartReplay)?;
    let report = StartReport {
        clearance: choice.clearance,
        fallback: choice.fallback,
        searched: choice.searched,
        cell: choice.cell,
        drive: choice.drive.len(),
    };
    Ok((scene, report))
}

/// Why a scene's start pose breaks the esrp-bench-v2 rule.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum StartViolation {
    /// The scene does not compile.
    #[error("invalid scene: {0}")]
    Invalid(String),
    /// The expert trajectory never fetches.
    #[error("the expert trajectory has no fetch")]
    NoFetch,
    /// The expert's drive to its first fetch was not accepted.
    #[error("the expert's drive to its first fetch is not accepted at step {0}")]
    DriveRejected(usize),
    /// The start is too close and the room has a reachable pose far enough.
    #[error(
        "the start is {clearance:.3} m from the nearest object; a reachable pose {best:.3} m away exists (rule: {min} m)"
    )]
    TooClose {
        /// The start's clearance.
        clearance: f64,
        /// The best clearance the search found.
        best: f64,
        /// The rule's clearance.
        min: f64,
    },
}

/// Checks that `scene`'s start pose satisfies the esrp-bench-v2 rule: at least
/// [`StartRule::min_clearance`] from every movable footprint, or, where it is closer, no pose
/// that the rule's [`search`] finds from the expert's first-fetch pose (nothing held, the
/// initial layout) is farther from the objects than the start (within a micrometre).
pub fn check_start(scene: &Scene, rule: &StartRule) -> Result<f64, StartViolation> {
    let compiled = CompiledScene::shared(scene.clone()).map_err(|e| StartViolation::Invalid(e.to_string()))?;
    let poses: Vec<ObjectPose> = scene.movable_objects.iter().map(|o| o.pose).collect();
    let clearance = object_clearance(&compiled, &poses, PlanPoint::new(scene.agent.x, scene.agent.z));
    if clearance >= rule.min_clearance {
        return Ok(clearance);
    }
    let first_fetch =
        scene.expert_trajectory.iter().position(|a| *a == Action::Fetch).ok_or(StartViolation::NoFetch)?;
    let config = EpisodeConfig { horizon: Some(u32::MAX), ..Default::default() };
    let mut episode = Episode::new(compiled, config).map_err(|e| StartViolation::Invalid(e.to_string()))?;
    for (i, &action) in scene.expert_trajectory[..first_fetch].iter().enumerate() {
        if !episode.step(action).is_ok_and(|o| o.accepted) {
            return Err(StartViolation::DriveRejected(i));
        }
    }
    let best = search(&episode, rule).max_clearance();
    if clearance + 1e-6 >= best {
        Ok(clearance)
    } else {
        Err(StartViolation::TooClose { clearance, best, min: rule.min_clearance })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turns_take_the_short_way() {
        let h = |k| Heading::wrapping(k);
        assert_eq!(turns(h(0), h(3)).collect::<Vec<_>>(), vec![Action::TurnLeft; 3]);
        assert_eq!(turns(h(0), h(13)).collect::<Vec<_>>(), vec![Action::TurnRight; 3]);
        assert_eq!(turns(h(5), h(5)).count(), 0);
        assert_eq!(turns(h(2), h(10)).collect::<Vec<_>>(), vec![Action::TurnLeft; 8]);
    }

    #[test]
    fn cells_are_keyed_by_counts() {
        assert_eq!(cell_of(&[0; 8], 0.25), (0, 0));
        assert_eq!(cell_of(&[1, 0, 0, 0, 0, 0, 0, 0], 0.25), (1, 0));
        // Forward along heading 4 (90°, left) is −z.
        assert_eq!(cell_of(&[0, 0, 0, 0, 2, 0, 0, 0], 0.25), (0, -2));
    }
}
