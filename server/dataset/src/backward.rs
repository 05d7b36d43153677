//! Backward construction of initial layouts (SPEC §7) and the expert trajectory.
//!
//! Starting from the target layout, a rule-based agent moves each chosen object away with the
//! esrp-core simulator itself: it plans a path to a pose from which `fetch` takes that object
//! (A* over the action lattice, through the same collision checks as an episode), fetches it,
//! takes random forward/backward/turn steps while carrying it, and releases it where it is
//! clear of its target and where a `fetch` from the same pose would take that same object. Its
//! final pose is the episode's start. The run reversed and inverted is the expert trajectory,
//! and every scene is replayed to success before it is kept.

use std::collections::BinaryHeap;
use std::sync::Arc;

use esrp_core::{
    Action, AgentStart, CompiledScene, Episode, EpisodeConfig, Heading, PlanPoint, Rules, Scene, footprint_iou,
    reverse_trajectory,
};
use rustc_hash::FxHashSet;

use crate::dice::Dice;

/// Why a scene was not produced. Counted by reason in generation reports.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, thiserror::Error)]
pub enum Rejection {
    /// The room could not host enough carryable pieces.
    #[error("too few carryable pieces fit the room")]
    TooFewMovable,
    /// No collision-free start pose for the agent was found.
    #[error("no free floor for the agent to start on")]
    NoAgentStart,
    /// The planner found no path to a pose from which the object can be fetched.
    #[error("object {0} cannot be reached for a fetch")]
    Unreachable(String),
    /// The random carry found no release pose that is clear of the target and fetchable back.
    #[error("no release pose found for object {0}")]
    NoReleaseSpot(String),
    /// The scene failed esrp-core's validation.
    #[error("invalid scene: {0}")]
    Invalid(String),
    /// The expert trajectory did not replay to success.
    #[error("the expert replay did not succeed")]
    ReplayFailed,
    /// The drive to the esrp-bench-v2 start pose was not accepted (esrp-core rules it out).
    #[error("the drive to the start pose was not accepted")]
    StartDrive,
    /// The expert trajectory from the esrp-bench-v2 start pose did not replay to success (the
    /// drive is reversible, so this should not happen).
    #[error("the expert replay from the start pose did not succeed")]
    StartReplay,
}

impl Rejection {
    /// A short stable key for counting rejections by reason.
    pub fn reason(&self) -> &'static str {
        match self {
            Rejection::TooFewMovable => "too_few_movable",
            Rejection::NoAgentStart => "no_agent_start",
            Rejection::Unreachable(_) => "unreachable",
            Rejection::NoReleaseSpot(_) => "no_release_spot",
            Rejection::Invalid(_) => "invalid",
            Rejection::ReplayFailed => "replay_failed",
            Rejection::StartDrive => "start_drive",
            Rejection::StartReplay => "start_replay",
        }
    }
}

/// Parameters of the rule-based agent.
#[derive(Clone, Copy, Debug)]
pub struct ConstructionParams {
    /// Accepted carrying steps taken before the first release attempt (range, inclusive).
    pub carry_steps: (usize, usize),
    /// Most accepted carrying steps before giving up on an object.
    pub max_carry_steps: usize,
    /// A release must leave the object's footprint IoU with its target at most this.
    pub max_release_iou: f64,
    /// ... and its footprint centre at least this far from the target's, metres.
    pub min_release_distance: f64,
    /// Node budget of one path search.
    pub max_search_nodes: usize,
}

impl Default for ConstructionParams {
    fn default() -> Self {
        Self {
            carry_steps: (4, 12),
            max_carry_steps: 40,
            max_release_iou: 0.05,
            min_release_distance: 0.5,
            max_search_nodes: 20_000,
        }
    }
}

/// The horizon of SPEC §5: twice the expert's length rounded up to a multiple of 50, at least
/// 200 steps.
pub fn horizon_for(expert_len: usize) -> u32 {
    let doubled = 2 * expert_len;
    (doubled.div_ceil(50) * 50).max(200) as u32
}

/// Picks a start pose for the agent on free floor, clear of every footprint.
fn place_agent(scene: &Scene, dice: &mut Dice) -> Option<AgentStart> {
    let floor = scene.room.floor_points();
    let (mut lo, mut hi) = (PlanPoint::new(f64::MAX, f64::MAX), PlanPoint::new(f64::MIN, f64::MIN));
    for p in &floor {
        lo = PlanPoint::new(lo.x.min(p.x), lo.z.min(p.z));
        hi = PlanPoint::new(hi.x.max(p.x), hi.z.max(p.z));
    }
    let clearance = 0.36;
    let footprints: Vec<_> = scene
        .fixed_objects
        .iter()
        .map(|o| (&o.shape, o.pose))
        .chain(scene.movable_objects.iter().map(|o| (&o.shape, o.pose)))
        .map(|(shape, pose)| shape_footprint(shape).at(&pose))
        .collect();
    for _ in 0..60 {
        let p = PlanPoint::new(dice.uniform(lo.x, hi.x), dice.uniform(lo.z, hi.z));
        if !esrp_core::geometry::point_in_polygon(p, &floor) {
            continue;
        }
        let near_wall =
            (0..floor.len()).any(|i| segment_distance(p, floor[i], floor[(i + 1) % floor.len()]) < clearance);
        if near_wall || footprints.iter().any(|f| f.distance_to_point(p) < clearance) {
            continue;
        }
        return Some(AgentStart { x: p.x, z: p.z, heading: Heading::wrapping(dice.below(16) as i64) });
    }
    None
}

fn segment_distance(p: PlanPoint, a: PlanPoint, b: PlanPoint) -> f64 {
    let (dx, dz) = (b.x - a.x, b.z - a.z);
    let t = (((p.x - a.x) * dx + (p.z - a.z) * dz) / (dx * dx + dz * dz)).clamp(0.0, 1.0);
    p.distance(PlanPoint::new(a.x + t * dx, a.z + t * dz))
}

/// The x–z bounding box of a parts shape in its own frame (meshes: of their vertices).
fn shape_footprint(shape: &esrp_core::Shape) -> esrp_core::LocalFootprint {
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    let mut add = |x: f64, z: f64| {
        lo = [lo[0].min(x), lo[1].min(z)];
        hi = [hi[0].max(x), hi[1].max(z)];
    };
    match shape {
        esrp_core::Shape::Parts(parts) => {
            for part in parts {
                let (offset, yaw) = part.placement();
                let (s, c) = yaw.sin_cos();
                let corners: Vec<[f64; 2]> = match part {
                    esrp_core::Part::Box { half_extents: h, .. } => {
                        vec![[-h[0], -h[2]], [h[0], -h[2]], [h[0], h[2]], [-h[0], h[2]]]
                    }
                    esrp_core::Part::Cylinder { radius: r, .. } => vec![[-r, -r], [*r, *r]],
                    esrp_core::Part::ConvexHull { points, .. } => points.iter().map(|q| [q[0], q[2]]).collect(),
                };
                for [x, z] in corners {
                    add(offset[0] + c * x + s * z, offset[2] - s * x + c * z);
                }
            }
        }
        esrp_core::Shape::Mesh(mesh) => mesh.vertices.iter().for_each(|v| add(v[0], v[2])),
    }
    esrp_core::LocalFootprint {
        center: PlanPoint::new(0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])),
        half_x: 0.5 * (hi[0] - lo[0]),
        half_z: 0.5 * (hi[1] - lo[1]),
    }
}

#[derive(PartialEq)]
struct Frontier {
    priority: f64,
    node: usize,
}

impl Eq for Frontier {}

impl Ord for Frontier {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        // Min-heap on priority, then the older node first: deterministic.
        other.priority.total_cmp(&self.priority).then(other.node.cmp(&self.node))
    }
}

impl PartialOrd for Frontier {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

/// The largest angle between the agent's heading and the direction to the object it fetches:
/// the rule-based agent faces what it takes, so that backing up pulls the object out.
const MAX_FETCH_BEARING: f64 = std::f64::consts::FRAC_PI_6;

/// The absolute angle between the agent's forward vector and the direction to object
/// `target`'s footprint centre.
fn bearing_to(e: &Episode, target: usize) -> f64 {
    let agent = e.agent_pose();
    let centre = e.compiled().movable_footprint(target, &e.object_poses()[target]).center;
    let (f, dx, dz) = (agent.forward(), centre.x - agent.position.x, centre.z - agent.position.z);
    (f.x * dz - f.z * dx).atan2(f.x * dx + f.z * dz).abs()
}

/// Whether the agent can fetch `target` now, facing it.
fn can_fetch_facing(e: &Episode, target: usize) -> bool {
    e.fetch_candidate() == Some(target) && bearing_to(e, target) <= MAX_FETCH_BEARING
}

/// Plans a short (weighted A*) sequence of motions after which `fetch` takes object `target`
/// with the agent facing it, or `None` within the node budget. Nothing is held during the
/// search.
pub fn plan_to_fetch(start: &Episode, target: usize, max_nodes: usize) -> Option<Vec<Action>> {
    if can_fetch_facing(start, target) {
        return Some(Vec::new());
    }
    let reach = start.compiled().rules().fetch_reach;
    // Moves still needed to come within reach, plus turns still needed to face the object.
    let heuristic = |e: &Episode| {
        let footprint = e.compiled().movable_footprint(target, &e.object_poses()[target]);
        let moves =
            (footprint.distance_to_point(e.agent_pose().position) - reach).max(0.0) / esrp_core::world::MOVE_DISTANCE;
        let turns = ((bearing_to(e, target) - MAX_FETCH_BEARING).max(0.0) / esrp_core::TURN_ANGLE).floor();
        moves + turns
    };
    let key = |p: esrp_core::AgentPose| {
        ((p.position.x / 0.02).round() as i64, (p.position.z / 0.02).round() as i64, p.heading.index())
    };
    // Nodes: (episode, parent, action, cost so far).
    let mut nodes: Vec<(Episode, usize, Action, f64)> = vec![(start.clone(), usize::MAX, Action::Fetch, 0.0)];
    let mut seen = FxHashSet::from_iter([key(start.agent_pose())]);
    let mut frontier = BinaryHeap::from([Frontier { priority: heuristic(start), node: 0 }]);
    while let Some(Frontier { node, .. }) = frontier.pop() {
        if nodes.len() > max_nodes {
            return None;
        }
        for action in [Action::MoveForward, Action::TurnLeft, Action::TurnRight, Action::MoveBackward] {
            // A motion into a pose already seen is skipped whether or not it is accepted, so it
            // is skipped before its collision check (`pose_after` is the pose `step` gives).
            let pose_key = key(nodes[node].0.pose_after(action));
            if seen.contains(&pose_key) {
                continue;
            }
            let mut next = nodes[node].0.clone();
            let Ok(outcome) = next.step(action) else { continue };
            if !outcome.accepted {
                continue;
            }
            seen.insert(pose_key);
            let cost = nodes[node].3 + 1.0;
            if can_fetch_facing(&next, target) {
                let mut path = vec![action];
                let mut at = node;
                while at != 0 {
                    path.push(nodes[at].2);
                    at = nodes[at].1;
                }
                path.reverse();
                return Some(path);
            }
            let priority = cost + 1.5 * heuristic(&next);
            nodes.push((next, node, action, cost));
            frontier.push(Frontier { priority, node: nodes.len() - 1 });
        }
    }
    None
}

/// Runs backward construction on `target` (a scene whose movable objects stand at their
/// targets), returning the finished scene: initial layout, agent start, expert trajectory and
/// horizon, validated by esrp-core and replayed to success. The agent starts where the
/// generator released its last object (esrp-bench-v1's rule).
pub fn construct(target: Scene, dice: &mut Dice, params: &ConstructionParams) -> Result<Scene, Rejection> {
    construct_run(target, dice, params).map(|c| c.scene)
}

/// A finished backward construction: the scene of [`construct`] and the generator's state after
/// its last release, from which esrp-bench-v2 drives the agent away ([`crate::start`]).
#[derive(Clone, Debug)]
pub struct Construction {
    /// The scene, starting at the last release pose, validated and replayed to success.
    pub scene: Scene,
    /// The generator's episode after its last release (nothing held).
    pub episode: Episode,
    /// The generator's accepted actions from its first fetch to its last release: the expert
    /// trajectory is this reversed and inverted.
    pub run: Vec<Action>,
}

/// [`construct`], keeping the generator's final state and run.
pub fn construct_run(
    mut target: Scene,
    dice: &mut Dice,
    params: &ConstructionParams,
) -> Result<Construction, Rejection> {
    target.agent = place_agent(&target, dice).ok_or(Rejection::NoAgentStart)?;
    let compiled = CompiledScene::for_backward_construction(target.clone(), Rules::default()).map_err(|e| match e {
        esrp_core::SceneError::AgentInCollision { .. } | esrp_core::SceneError::AgentOutsideRoom => {
            Rejection::NoAgentStart
        }
        other => Rejection::Invalid(other.to_string()),
    })?;
    let config = EpisodeConfig { horizon: Some(u32::MAX), ..Default::default() };
    let mut episode = Episode::new(Arc::new(compiled), config).map_err(|e| Rejection::Invalid(e.to_string()))?;
    let mut run: Vec<Action> = Vec::new();
    let mut order: Vec<usize> = (0..target.movable_objects.len()).collect();
    dice.shuffle(&mut order);
    for object in order {
        let id = target.movable_objects[object].id.clone();
        let path = plan_to_fetch(&episode, object, params.max_search_nodes)
            .ok_or_else(|| Rejection::Unreachable(id.clone()))?;
        for action in path {
            step_recorded(&mut episode, action, &mut run);
        }
        let fetched = step_recorded(&mut episode, Action::Fetch, &mut run);
        if !fetched {
            return Err(Rejection::Unreachable(id));
        }
        carry_away(&mut episode, object, dice, params, &mut run).ok_or(Rejection::NoReleaseSpot(id))?;
    }
    let mut scene = target;
    for (object, pose) in scene.movable_objects.iter_mut().zip(episode.object_poses()) {
        object.pose = *pose;
    }
    let agent = episode.agent_pose();
    scene.agent = AgentStart { x: agent.position.x, z: agent.position.z, heading: agent.heading };
    // The approach to the first object is not part of the demonstration: reversed, it would
    // trail after the final release, which already ends the episode in success.
    let first_fetch = run.iter().position(|a| *a == Action::Fetch).unwrap_or(0);
    run.drain(..first_fetch);
    scene.expert_trajectory = reverse_trajectory(&run);
    scene.horizon = horizon_for(scene.expert_trajectory.len());
    validate_by_replay(&scene)?;
    Ok(Construction { scene, episode, run })
}

/// Steps `action`, recording it when it took effect; returns whether it did.
fn step_recorded(episode: &mut Episode, action: Action, run: &mut Vec<Action>) -> bool {
    match episode.step(action) {
        Ok(outcome) if outcome.accepted => {
            run.push(action);
            true
        }
        _ => false,
    }
}

/// Random forward/backward/turn steps with the object held, then a release where it is clear of
/// its target and where a fetch from the same pose takes it back.
fn carry_away(
    episode: &mut Episode,
    object: usize,
    dice: &mut Dice,
    params: &ConstructionParams,
    run: &mut Vec<Action>,
) -> Option<()> {
    let wanted = params.carry_steps.0 + dice.below(params.carry_steps.1 - params.carry_steps.0 + 1);
    let mut taken = 0;
    let mut tries = 0;
    while taken < params.max_carry_steps && tries < 6 * params.max_carry_steps {
        tries += 1;
        if taken >= wanted && release_is_good(episode, object, params) {
            return step_recorded(episode, Action::Release, run).then_some(());
        }
        // Mostly pull the object back out of its place, with turns to swing it aside.
        let action = match dice.below(10) {
            0..=4 => Action::MoveBackward,
            5 => Action::MoveForward,
            6 | 7 => Action::TurnLeft,
            _ => Action::TurnRight,
        };
        if step_recorded(episode, action, run) {
            taken += 1;
        }
    }
    None
}

fn release_is_good(episode: &Episode, object: usize, params: &ConstructionParams) -> bool {
    let compiled = episode.compiled();
    let pose = episode.object_poses()[object];
    let target = compiled.scene().movable_objects[object].target;
    let now = compiled.movable_footprint(object, &pose);
    let goal = compiled.movable_footprint(object, &target);
    if footprint_iou(&now, &goal) > params.max_release_iou
        || now.center.distance(goal.center) < params.min_release_distance
    {
        return false;
    }
    let mut after = episode.clone();
    after.step(Action::Release).is_ok_and(|o| o.accepted) && after.fetch_candidate() == Some(object)
}

/// Validates a finished scene with esrp-core and replays its expert trajectory to success.
pub fn validate_by_replay(scene: &Scene) -> Result<(), Rejection> {
    let compiled = CompiledScene::shared(scene.clone()).map_err(|e| Rejection::Invalid(e.to_string()))?;
    let mut episode =
        Episode::new(compiled, EpisodeConfig::default()).map_err(|e| Rejection::Invalid(e.to_string()))?;
    for &action in &scene.expert_trajectory {
        if episode.is_over() {
            break;
        }
        episode.step(action).map_err(|_| Rejection::ReplayFailed)?;
    }
    if episode.metrics().success { Ok(()) } else { Err(Rejection::ReplayFailed) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn horizon_rule() {
        assert_eq!(horizon_for(10), 200);
        assert_eq!(horizon_for(100), 200);
        assert_eq!(horizon_for(101), 250);
        assert_eq!(horizon_for(130), 300);
    }
}
