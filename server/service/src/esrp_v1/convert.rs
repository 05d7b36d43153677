//! Conversions between `esrp.v1` messages and the core types, at the edge: `TryFrom` for
//! requests (an invalid field is an INVALID_ARGUMENT [`ServiceError`]), `From` for answers.
//! Image pixels move as `Bytes` from the render readback into the messages, never copied.

use bytes::Bytes;
use esrp_core::{Action, CompiledScene, Difficulty, Split};

use crate::error::ServiceError;
use crate::proto;
use crate::types::{
    ACTIONS, CreateOptions, Created, EpisodeId, Goal, MetricsSoFar, Observation, PlanCall, Planned, Privileged,
    ResetCall, ResetResult, SceneChoice, SceneInfo, SensorConfig, SensorRequest, StepCall, StepResult,
};

/// The split of a request: `None` for unspecified.
pub fn split_of(split: i32) -> Result<Option<Split>, ServiceError> {
    match proto::Split::try_from(split) {
        Ok(proto::Split::Unspecified) => Ok(None),
        Ok(proto::Split::Train) => Ok(Some(Split::Train)),
        Ok(proto::Split::Test) => Ok(Some(Split::Test)),
        Ok(proto::Split::Challenge) => Ok(Some(Split::Challenge)),
        Ok(proto::Split::Minival) => Ok(Some(Split::Minival)),
        Err(_) => Err(ServiceError::InvalidArgument(format!(
            "unknown split {split}: use 1 (train), 2 (test), 3 (challenge) or 4 (minival)"
        ))),
    }
}

/// The difficulty of a request: `None` for unspecified.
pub fn difficulty_of(difficulty: i32) -> Result<Option<Difficulty>, ServiceError> {
    match proto::Difficulty::try_from(difficulty) {
        Ok(proto::Difficulty::Unspecified) => Ok(None),
        Ok(proto::Difficulty::Easy) => Ok(Some(Difficulty::Easy)),
        Ok(proto::Difficulty::Medium) => Ok(Some(Difficulty::Medium)),
        Ok(proto::Difficulty::Hard) => Ok(Some(Difficulty::Hard)),
        Err(_) => Err(ServiceError::InvalidArgument(format!("unknown difficulty {difficulty}: use 1, 2 or 3"))),
    }
}

fn split_to_proto(split: Split) -> proto::Split {
    match split {
        Split::Train => proto::Split::Train,
        Split::Test => proto::Split::Test,
        Split::Challenge => proto::Split::Challenge,
        Split::Minival => proto::Split::Minival,
    }
}

fn difficulty_to_proto(d: Difficulty) -> proto::Difficulty {
    match d {
        Difficulty::Easy => proto::Difficulty::Easy,
        Difficulty::Medium => proto::Difficulty::Medium,
        Difficulty::Hard => proto::Difficulty::Hard,
    }
}

impl From<&SceneInfo> for proto::SceneSummary {
    fn from(info: &SceneInfo) -> Self {
        proto::SceneSummary {
            id: info.id.clone(),
            room_type: info.room_type.clone(),
            difficulty: difficulty_to_proto(info.difficulty) as i32,
            split: split_to_proto(info.split) as i32,
            movable_objects: info.movable_objects as u32,
            horizon: info.horizon,
            expert_length: info.expert_length as u32,
        }
    }
}

/// The metrics message of `m`.
pub fn metrics_to_proto(m: &esrp_core::EpisodeMetrics) -> proto::EpisodeMetrics {
    proto::EpisodeMetrics {
        success: m.success,
        object_success_rate: m.object_success_rate,
        remaining_distance_ratio: m.remaining_distance_ratio,
        stage: m.stage as u32,
        placed: m.placed as u32,
        movable_objects: m.movable_objects as u32,
        steps: m.steps,
        total_reward: m.total_reward,
    }
}

fn obstacle_to_proto(o: esrp_core::Obstacle, name: String) -> proto::Obstacle {
    use proto::obstacle::Kind;
    let (kind, index) = match o {
        esrp_core::Obstacle::Wall(i) => (Kind::Wall, i),
        esrp_core::Obstacle::Fixed(i) => (Kind::Fixed, i),
        esrp_core::Obstacle::Movable(i) => (Kind::Movable, i),
    };
    proto::Obstacle { kind: kind as i32, index: index as u32, name }
}

fn reward_weights(w: Option<proto::RewardWeights>) -> esrp_core::RewardWeights {
    let d = esrp_core::RewardWeights::default();
    let w = w.unwrap_or_default();
    esrp_core::RewardWeights {
        success: w.success.unwrap_or(d.success),
        place: w.place.unwrap_or(d.place),
        unplace: w.unplace.unwrap_or(d.unplace),
        potential: w.potential.unwrap_or(d.potential),
        holding: w.holding.unwrap_or(d.holding),
        living: w.living.unwrap_or(d.living),
    }
}

impl From<Option<proto::Sensors>> for SensorRequest {
    fn from(s: Option<proto::Sensors>) -> Self {
        let s = s.unwrap_or_default();
        SensorRequest {
            depth: s.ego_depth,
            segmentation: s.ego_segmentation,
            current_top_down: s.current_top_down,
            resolution: (s.resolution != 0).then_some(s.resolution),
        }
    }
}

impl TryFrom<proto::CreateEpisodeRequest> for CreateOptions {
    type Error = ServiceError;

    fn try_from(r: proto::CreateEpisodeRequest) -> Result<Self, ServiceError> {
        use proto::create_episode_request::Scene;
        let scene = match r.scene {
            Some(Scene::SceneJson(json)) => SceneChoice::SceneJson(json),
            Some(Scene::SceneId(id)) if !id.is_empty() => SceneChoice::SceneId(id),
            // The split matters only here, so only here is it checked.
            _ => SceneChoice::FromSplit { split: split_of(r.split)?, seed: r.seed },
        };
        Ok(CreateOptions {
            scene,
            sensors: r.sensors.into(),
            horizon: (r.horizon != 0).then_some(r.horizon),
            reward: reward_weights(r.reward),
            privileged: r.privileged,
            agent: (!r.agent.is_empty()).then_some(r.agent),
            keep_record: false,
        })
    }
}

/// A step request as a step call; `at` locates it in its call for messages.
pub fn step_call(r: proto::StepRequest, at: impl FnOnce() -> String) -> Result<StepCall, ServiceError> {
    let action =
        Action::from_code(i64::from(r.action)).map_err(|error| ServiceError::InvalidAction { at: at(), error })?;
    Ok(StepCall { episode: r.episode_id.into(), action, include_goal: r.include_goal })
}

impl TryFrom<proto::StepRequest> for StepCall {
    type Error = ServiceError;

    fn try_from(r: proto::StepRequest) -> Result<Self, ServiceError> {
        step_call(r, || "step".to_owned())
    }
}

/// The steps of a StepBatch, named `steps[3]` in messages however few the batch holds (a Step
/// alone converts with `StepCall::try_from`, named `step`).
pub fn step_calls(requests: Vec<proto::StepRequest>) -> Result<Vec<StepCall>, ServiceError> {
    requests.into_iter().enumerate().map(|(i, r)| step_call(r, || format!("steps[{i}]"))).collect()
}

/// A reset of a StepBatch.
pub fn reset_call(r: proto::ResetRequest) -> ResetCall {
    let (episode, scene) = reset_of(r);
    ResetCall { episode, scene }
}

/// The episode and new scene, if any, of a reset.
pub fn reset_of(r: proto::ResetRequest) -> (EpisodeId, Option<SceneChoice>) {
    use proto::reset_request::Scene;
    let scene = match r.scene {
        Some(Scene::SceneId(id)) if !id.is_empty() => Some(SceneChoice::SceneId(id)),
        Some(Scene::SceneJson(json)) => Some(SceneChoice::SceneJson(json)),
        _ => None,
    };
    (r.episode_id.into(), scene)
}

fn image(rgb: Bytes, resolution: u32) -> proto::Image {
    proto::Image { height: resolution, width: resolution, channels: 3, data: rgb }
}

/// Little-endian bytes of `values` (the wire form of depth and segmentation).
fn le_bytes<T: Copy, const N: usize>(values: &[T], to_le: fn(T) -> [u8; N]) -> Bytes {
    let mut out = Vec::with_capacity(values.len() * N);
    for &v in values {
        out.extend_from_slice(&to_le(v));
    }
    Bytes::from(out)
}

impl From<Observation> for proto::Observation {
    fn from(o: Observation) -> Self {
        let r = o.resolution;
        proto::Observation {
            ego_rgb: Some(image(o.ego_rgb, r)),
            goal_rgb: o.goal_rgb.map(|g| image(g, r)),
            grasping: o.grasping,
            ego_depth: o.depth.map(|d| proto::FloatImage { height: r, width: r, data: le_bytes(&d, f32::to_le_bytes) }),
            ego_segmentation: o.segmentation.map(|s| proto::LabelImage {
                height: r,
                width: r,
                data: le_bytes(&s, u32::to_le_bytes),
            }),
            current_top_down: o.current_top_down.map(|t| image(t, r)),
        }
    }
}

impl From<&SensorConfig> for proto::ObservationSpec {
    fn from(sensors: &SensorConfig) -> Self {
        let arrays = sensors
            .observation_spec()
            .into_iter()
            .map(|a| proto::ArraySpec { name: a.name.into(), shape: a.shape, dtype: a.element_type.name().into() })
            .collect();
        proto::ObservationSpec { arrays, actions: ACTIONS.iter().map(|a| (*a).to_owned()).collect() }
    }
}

impl From<StepResult> for proto::StepResponse {
    fn from(s: StepResult) -> Self {
        let outcome = s.outcome;
        proto::StepResponse {
            observation: Some(s.observation.into()),
            reward: outcome.reward.total,
            terminated: outcome.terminated,
            truncated: outcome.truncated,
            info: Some(proto::StepInfo {
                accepted: outcome.accepted,
                collided_with: outcome
                    .collided_with
                    .map(|o| obstacle_to_proto(o, s.collided_with_name.unwrap_or_default())),
                no_op: outcome.no_op.map(|r| r.message().to_owned()).unwrap_or_default(),
                fetched: outcome.fetched.map(|i| i as u32),
                released: outcome.released.map(|i| i as u32),
                placed_count: outcome.placed_count as u32,
                step_index: outcome.step_index,
                reward_terms: Some(proto::RewardTerms {
                    success: outcome.reward.success,
                    placement: outcome.reward.placement,
                    potential: outcome.reward.potential,
                    holding: outcome.reward.holding,
                    living: outcome.reward.living,
                }),
            }),
            metrics: s.metrics.as_ref().map(metrics_to_proto),
        }
    }
}

impl From<Created> for proto::CreateEpisodeResponse {
    fn from(c: Created) -> Self {
        proto::CreateEpisodeResponse {
            episode_id: c.episode.into(),
            spec: Some((&c.sensors).into()),
            observation: Some(c.observation.into()),
            scene: Some((&c.scene).into()),
        }
    }
}

impl From<ResetResult> for proto::ResetResponse {
    fn from(r: ResetResult) -> Self {
        proto::ResetResponse { observation: Some(r.observation.into()), scene: Some((&r.scene).into()) }
    }
}

impl From<Goal> for proto::GetGoalResponse {
    fn from(g: Goal) -> Self {
        proto::GetGoalResponse {
            goal_rgb: Some(image(g.rgb, g.resolution)),
            frame: g.frame.map(|f| proto::TopDownFrame {
                min_x: f.min_x,
                min_z: f.min_z,
                metres_per_pixel: f.metres_per_pixel(),
                resolution: f.resolution,
            }),
        }
    }
}

impl From<MetricsSoFar> for proto::GetMetricsResponse {
    fn from(m: MetricsSoFar) -> Self {
        proto::GetMetricsResponse { metrics: Some(metrics_to_proto(&m.metrics)), ended: m.ended }
    }
}

impl From<Privileged> for proto::GetPrivilegedStateResponse {
    fn from(p: Privileged) -> Self {
        let (state, compiled): (_, &CompiledScene) = (p.state, &p.scene);
        let footprint = |f: &esrp_core::OrientedRect| proto::Footprint {
            center_x: f.center.x,
            center_z: f.center.z,
            half_x: f.half_x,
            half_z: f.half_z,
            yaw: f.yaw,
        };
        let pose = |p: &esrp_core::ObjectPose| proto::Pose2 { x: p.x, z: p.z, yaw: p.yaw };
        proto::GetPrivilegedStateResponse {
            agent_x: state.agent.position.x,
            agent_z: state.agent.position.z,
            agent_heading: u32::from(state.agent.heading.index()),
            held: state.held.map(|i| i as u32),
            objects: state
                .objects
                .iter()
                .zip(&compiled.scene().movable_objects)
                .map(|(o, m)| proto::ObjectState {
                    id: o.id.clone(),
                    category: m.category.as_str().to_owned(),
                    pose: Some(pose(&o.pose)),
                    target: Some(pose(&o.target)),
                    footprint: Some(footprint(&o.footprint)),
                    target_footprint: Some(footprint(&o.target_footprint)),
                    iou: o.iou,
                    placed: o.placed,
                    held: o.held,
                })
                .collect(),
            static_obstacles: state
                .static_obstacles
                .iter()
                .map(|s| proto::StaticObstacle {
                    obstacle: Some(obstacle_to_proto(s.obstacle, compiled.obstacle_name(s.obstacle))),
                    footprint: Some(footprint(&s.footprint)),
                })
                .collect(),
            floor: compiled.floor().iter().flat_map(|p| [p.x, p.z]).collect(),
            scene_json: compiled.scene().to_json_pretty(),
        }
    }
}

impl From<proto::PlanActionsRequest> for PlanCall {
    fn from(r: proto::PlanActionsRequest) -> Self {
        PlanCall {
            episode: r.episode_id.into(),
            max_actions: r.max_actions,
            budget: (r.budget_ms > 0).then(|| std::time::Duration::from_millis(u64::from(r.budget_ms))),
        }
    }
}

impl From<Planned> for proto::PlanActionsResponse {
    fn from(p: Planned) -> Self {
        use esrp_planner::PlanFailure as F;
        let failure = match &p.failure {
            None => proto::PlanFailure::Unspecified,
            Some(F::Unreachable { .. }) => proto::PlanFailure::Unreachable,
            Some(F::NoPlacement { .. }) => proto::PlanFailure::NoPlacement,
            Some(F::TooLong { .. }) => proto::PlanFailure::TooLong,
            // Deadlines, cancels and ended episodes are statuses, never answers; a budget of
            // nodes is what is left.
            Some(_) => proto::PlanFailure::BudgetExhausted,
        };
        proto::PlanActionsResponse {
            actions: p.actions.iter().map(|a| i32::from(a.code())).collect(),
            reaches_success: p.reaches_success,
            plan_length: p.plan_length,
            cached: p.cached,
            stats: Some(proto::PlanStats {
                nodes_expanded: p.stats.nodes_expanded,
                searches: p.stats.searches,
                planning_seconds: p.stats.elapsed.as_secs_f64(),
                objects_relocated: p.stats.objects_relocated,
            }),
            failure: failure as i32,
            failure_message: p.failure.as_ref().map(ToString::to_string).unwrap_or_default(),
            failure_object: p.failure_object.unwrap_or_default(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn create_requests_convert_and_the_split_matters_only_without_a_scene() {
        let request = |scene, split| proto::CreateEpisodeRequest { scene, split, seed: 5, ..Default::default() };
        use proto::create_episode_request::Scene;
        let by_id = CreateOptions::try_from(request(Some(Scene::SceneId("s".into())), 99)).unwrap();
        assert_eq!(by_id.scene, SceneChoice::SceneId("s".into()));
        let by_split = CreateOptions::try_from(request(Some(Scene::SceneId(String::new())), 1)).unwrap();
        assert_eq!(by_split.scene, SceneChoice::FromSplit { split: Some(Split::Train), seed: 5 });
        let error = CreateOptions::try_from(request(None, 99)).unwrap_err().to_string();
        assert!(error.contains("unknown split 99"), "{error}");
        assert_eq!((by_id.horizon, by_id.sensors.resolution), (None, None));
    }

    #[test]
    fn step_batches_name_the_step_with_a_bad_action() {
        let step = |action| proto::StepRequest { episode_id: "e".into(), action, include_goal: false };
        let error = step_calls(vec![step(0), step(9)]).unwrap_err().to_string();
        assert!(error.starts_with("steps[1].action: unknown action code 9"), "{error}");
        let error = step_calls(vec![step(-1)]).unwrap_err().to_string();
        assert!(error.starts_with("steps[0].action: "), "{error}");
        let error = StepCall::try_from(step(-1)).unwrap_err().to_string();
        assert!(error.starts_with("step.action: "), "{error}");
        assert_eq!(StepCall::try_from(step(2)).unwrap().action, Action::TurnLeft);
    }

    #[test]
    fn observations_keep_their_pixel_buffers() {
        let rgb = Bytes::from(vec![7u8; 2 * 2 * 3]);
        let observation = Observation {
            resolution: 2,
            ego_rgb: rgb.clone(),
            depth: Some(vec![1.5; 4]),
            segmentation: Some(vec![3; 4]),
            ..Default::default()
        };
        let message = proto::Observation::from(observation);
        let ego = message.ego_rgb.unwrap();
        assert_eq!(ego.data.as_ptr(), rgb.as_ptr(), "the RGB buffer is shared, not copied");
        assert_eq!((ego.height, ego.width, ego.channels), (2, 2, 3));
        assert_eq!(&message.ego_depth.unwrap().data[..4], &1.5f32.to_le_bytes());
        assert_eq!(&message.ego_segmentation.unwrap().data[..4], &3u32.to_le_bytes());
        assert!(message.goal_rgb.is_none() && message.current_top_down.is_none());
    }
}
