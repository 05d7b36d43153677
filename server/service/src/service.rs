//! The `esrp.v1.Esrp` service: thin handlers over [`Shared`], which owns the scenes, the
//! registry and the render scheduler. Conversions between proto messages and esrp-core types
//! happen here, at the edge; core types never see the proto.

use std::collections::{HashMap, HashSet};
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use bytes::Bytes;
use esrp_core::{Action, CompiledScene, Episode, EpisodeConfig, RewardWeights, Scene, Split};
use esrp_render::{Outputs, ViewOutput};
use tokio::sync::mpsc;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

use crate::config::Config;
use crate::error::ServiceError;
use crate::metrics::Metrics;
use crate::proto;
use crate::registry::{EpisodeEntry, Registry, SensorConfig, SharedEpisode};
use crate::render::{RenderScheduler, RenderTicket, View};
use crate::scenes::{SceneInfo, SceneStore};

/// State shared by every handler.
pub struct Shared {
    /// The served scenes.
    pub store: SceneStore,
    /// Live episodes.
    pub registry: Registry,
    /// The render thread.
    pub render: RenderScheduler,
    /// The configuration.
    pub config: Config,
    next_stream: AtomicU64,
    /// Prometheus metrics.
    pub metrics: Arc<Metrics>,
}

/// Batches of at most this many steps are stepped on the async runtime itself.
const INLINE_STEPS: usize = 4;

/// The largest image side a client may ask for.
pub const MAX_RESOLUTION: u32 = 512;

const ACTIONS: [&str; 6] = ["move_forward", "move_backward", "turn_left", "turn_right", "fetch", "release"];

fn image(rgb: Bytes, resolution: u32) -> proto::Image {
    proto::Image { height: resolution, width: resolution, channels: 3, data: rgb }
}

fn split_of(split: i32) -> Result<Option<Split>, ServiceError> {
    match proto::Split::try_from(split) {
        Ok(proto::Split::Unspecified) => Ok(None),
        Ok(proto::Split::Train) => Ok(Some(Split::Train)),
        Ok(proto::Split::Test) => Ok(Some(Split::Test)),
        Err(_) => Err(ServiceError::InvalidArgument(format!("unknown split {split}: use 1 (train) or 2 (test)"))),
    }
}

fn split_to_proto(split: Split) -> proto::Split {
    match split {
        Split::Train => proto::Split::Train,
        Split::Test => proto::Split::Test,
    }
}

fn difficulty_to_proto(d: esrp_core::Difficulty) -> proto::Difficulty {
    match d {
        esrp_core::Difficulty::Easy => proto::Difficulty::Easy,
        esrp_core::Difficulty::Medium => proto::Difficulty::Medium,
        esrp_core::Difficulty::Hard => proto::Difficulty::Hard,
    }
}

fn summary_of_info(info: &SceneInfo) -> proto::SceneSummary {
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

fn summary_of_scene(scene: &Scene) -> proto::SceneSummary {
    proto::SceneSummary {
        id: scene.id.clone(),
        room_type: scene.room_type.clone(),
        difficulty: difficulty_to_proto(scene.difficulty) as i32,
        split: split_to_proto(scene.split) as i32,
        movable_objects: scene.movable_objects.len() as u32,
        horizon: scene.horizon,
        expert_length: scene.expert_trajectory.len() as u32,
    }
}

fn metrics_to_proto(m: &esrp_core::EpisodeMetrics) -> proto::EpisodeMetrics {
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

fn obstacle_to_proto(scene: &CompiledScene, o: esrp_core::Obstacle) -> proto::Obstacle {
    use proto::obstacle::Kind;
    let (kind, index) = match o {
        esrp_core::Obstacle::Wall(i) => (Kind::Wall, i),
        esrp_core::Obstacle::Fixed(i) => (Kind::Fixed, i),
        esrp_core::Obstacle::Movable(i) => (Kind::Movable, i),
    };
    proto::Obstacle { kind: kind as i32, index: index as u32, name: scene.obstacle_name(o) }
}

fn reward_weights(w: Option<proto::RewardWeights>) -> RewardWeights {
    let d = RewardWeights::default();
    let w = w.unwrap_or_default();
    RewardWeights {
        success: w.success.unwrap_or(d.success),
        place: w.place.unwrap_or(d.place),
        unplace: w.unplace.unwrap_or(d.unplace),
        potential: w.potential.unwrap_or(d.potential),
        holding: w.holding.unwrap_or(d.holding),
        living: w.living.unwrap_or(d.living),
    }
}

fn sensors(s: Option<proto::Sensors>, max_resolution: u32) -> Result<SensorConfig, ServiceError> {
    let s = s.unwrap_or_default();
    let resolution = if s.resolution == 0 { esrp_render::DEFAULT_RESOLUTION } else { s.resolution };
    if !(16..=max_resolution).contains(&resolution) {
        return Err(ServiceError::InvalidArgument(format!(
            "sensors.resolution {resolution} is out of range: use 16 to {max_resolution} pixels (0 means 128)"
        )));
    }
    Ok(SensorConfig {
        depth: s.ego_depth,
        segmentation: s.ego_segmentation,
        current_top_down: s.current_top_down,
        resolution,
    })
}

fn spec(sensors: &SensorConfig) -> proto::ObservationSpec {
    let r = sensors.resolution;
    let array =
        |name: &str, shape: Vec<u32>, dtype: &str| proto::ArraySpec { name: name.into(), shape, dtype: dtype.into() };
    let mut arrays = vec![
        array("ego_rgb", vec![r, r, 3], "uint8"),
        array("goal_rgb", vec![r, r, 3], "uint8"),
        array("grasping", vec![], "bool"),
    ];
    if sensors.depth {
        arrays.push(array("ego_depth", vec![r, r], "float32"));
    }
    if sensors.segmentation {
        arrays.push(array("ego_segmentation", vec![r, r], "uint32"));
    }
    if sensors.current_top_down {
        arrays.push(array("current_top_down", vec![r, r, 3], "uint8"));
    }
    proto::ObservationSpec { arrays, actions: ACTIONS.iter().map(|a| (*a).to_owned()).collect() }
}

fn f32_bytes(values: &[f32]) -> Bytes {
    let mut out = Vec::with_capacity(values.len() * 4);
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    Bytes::from(out)
}

fn u32_bytes(values: &[u32]) -> Bytes {
    let mut out = Vec::with_capacity(values.len() * 4);
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    Bytes::from(out)
}

/// The views an observation of `entry` needs: the ego view, then the current top-down view if
/// that sensor is on.
fn observation_views(entry: &EpisodeEntry) -> Vec<View> {
    let outputs = Outputs { depth: entry.sensors.depth, segmentation: entry.sensors.segmentation };
    let poses = entry.episode.object_poses();
    let mut views = vec![View::ego(&entry.scene, entry.episode.ego_camera(), poses, outputs, entry.sensors.resolution)];
    if entry.sensors.current_top_down {
        views.push(View::top_down(&entry.scene, poses, entry.sensors.resolution));
    }
    views
}

/// An upper bound of the encoded size of one step's response, bytes.
fn response_size(sensors: &SensorConfig, include_goal: bool) -> usize {
    let pixels = (sensors.resolution as usize).pow(2);
    let mut bytes = 512 + pixels * 3;
    bytes += usize::from(sensors.depth) * pixels * 4;
    bytes += usize::from(sensors.segmentation) * pixels * 4;
    bytes += usize::from(sensors.current_top_down) * pixels * 3;
    bytes += usize::from(include_goal) * pixels * 3;
    bytes
}

fn observation(entry: &EpisodeEntry, outputs: Vec<ViewOutput>, include_goal: bool) -> proto::Observation {
    let mut observation = proto::Observation {
        grasping: entry.episode.held().is_some(),
        goal_rgb: include_goal.then(|| entry.goal.clone()),
        ..Default::default()
    };
    attach_images(&mut observation, &entry.sensors, outputs);
    observation
}

/// Puts the rendered views of an observation (as [`observation_views`] asked for them) in it.
fn attach_images(observation: &mut proto::Observation, sensors: &SensorConfig, outputs: Vec<ViewOutput>) {
    let r = sensors.resolution;
    let mut outputs = outputs.into_iter();
    if let Some(ego) = outputs.next() {
        observation.ego_depth =
            ego.depth.as_deref().map(|d| proto::FloatImage { height: r, width: r, data: f32_bytes(d) });
        observation.ego_segmentation =
            ego.segmentation.as_deref().map(|s| proto::LabelImage { height: r, width: r, data: u32_bytes(s) });
        observation.ego_rgb = Some(image(ego.rgb, r));
    }
    if sensors.current_top_down {
        observation.current_top_down = outputs.next().map(|v| image(v.rgb, r));
    }
}

/// The error of stepping an episode that has ended (`at` locates the step in its call).
fn episode_over(at: &str, id: &str, steps: u32) -> ServiceError {
    ServiceError::EpisodeOver(format!("{at}: episode {id} has ended after {steps} steps: Reset it or create a new one"))
}

/// A locked episode.
type EpisodeGuard = tokio::sync::OwnedMutexGuard<EpisodeEntry>;

/// A step to take: where it is in its call (for messages), its episode (an index into the
/// call's locked episodes), its action and whether its answer carries the goal image.
struct PlannedStep {
    at: String,
    episode: usize,
    action: Action,
    include_goal: bool,
}

/// A step taken: its answer without images, the views that make them, and the sensors that
/// say how they fit in the answer.
struct TakenStep {
    response: proto::StepResponse,
    /// An upper bound of the answer's encoded size.
    bytes: usize,
    views: Vec<View>,
    view_count: usize,
    sensors: SensorConfig,
}

/// Takes `plan` in order on the locked `guards` (`ids` names them): each step sees the state
/// the previous one left, and one that cannot be taken answers its error without moving.
fn take_planned(
    guards: &mut [EpisodeGuard],
    ids: &[String],
    plan: Vec<Result<PlannedStep, ServiceError>>,
    max_message_bytes: usize,
) -> Vec<Result<TakenStep, ServiceError>> {
    plan.into_iter()
        .map(|step| {
            let step = step?;
            let g = &mut guards[step.episode];
            if g.episode.is_over() {
                return Err(episode_over(&step.at, &ids[step.episode], g.episode.steps()));
            }
            let bytes = response_size(&g.sensors, step.include_goal);
            if bytes > max_message_bytes {
                return Err(ServiceError::Exhausted(format!(
                    "the answer to this step would take about {:.1} MB, over the {:.1} MB message limit \
                     (--max-message-bytes): ask for fewer sensors, a smaller resolution or no goal image",
                    bytes as f64 / 1e6,
                    max_message_bytes as f64 / 1e6
                )));
            }
            let outcome = g.episode.step(step.action)?;
            let views = observation_views(g);
            Ok(TakenStep {
                response: step_response(g, outcome, step.include_goal),
                bytes,
                view_count: views.len(),
                views,
                sensors: g.sensors,
            })
        })
        .collect()
}

/// Steps taken, their views being rendered.
pub struct Stepped {
    taken: Vec<Result<TakenStep, ServiceError>>,
    render: RenderTicket,
    started: Instant,
}

impl Stepped {
    /// `n` steps that all failed with an internal `error` (nothing moved).
    fn failed(n: usize, error: &ServiceError) -> Self {
        // Not "internal error: internal error: …".
        let message = match error {
            ServiceError::Internal(m) => m.clone(),
            other => other.to_string(),
        };
        Stepped {
            taken: (0..n).map(|_| Err(ServiceError::Internal(message.clone()))).collect(),
            render: RenderTicket::nothing(),
            started: Instant::now(),
        }
    }

    /// An upper bound of the encoded size of the answers.
    fn answer_bytes(&self) -> usize {
        self.taken.iter().map(|t| t.as_ref().map_or(256, |t| t.bytes)).sum()
    }

    /// Waits for the rendering and answers every step, in order.
    pub async fn finish(self, metrics: &Metrics) -> Vec<Result<proto::StepResponse, ServiceError>> {
        let Stepped { taken, render, started } = self;
        let rendered = render.wait().await;
        metrics.observe_steps(taken.iter().filter(|t| t.is_ok()).count(), started.elapsed());
        match rendered {
            Ok(outputs) => {
                let mut outputs = outputs.into_iter();
                taken
                    .into_iter()
                    .map(|t| {
                        let mut t = t?;
                        let mine: Vec<ViewOutput> = outputs.by_ref().take(t.view_count).collect();
                        if let Some(observation) = &mut t.response.observation {
                            attach_images(observation, &t.sensors, mine);
                        }
                        Ok(t.response)
                    })
                    .collect()
            }
            // The steps were taken: they answer the failure (and must not be retaken).
            Err(e) => {
                let message = match e {
                    ServiceError::Render(m) => m,
                    other => other.to_string(),
                };
                taken.into_iter().map(|t| t.and_then(|_| Err(ServiceError::Render(message.clone())))).collect()
            }
        }
    }
}

/// The answer to a step just taken on `g`, without its images.
fn step_response(g: &EpisodeEntry, outcome: esrp_core::StepOutcome, include_goal: bool) -> proto::StepResponse {
    let compiled = g.episode.compiled();
    let ended = outcome.terminated || outcome.truncated;
    proto::StepResponse {
        observation: Some(observation(g, Vec::new(), include_goal)),
        reward: outcome.reward.total,
        terminated: outcome.terminated,
        truncated: outcome.truncated,
        info: Some(proto::StepInfo {
            accepted: outcome.accepted,
            collided_with: outcome.collided_with.map(|o| obstacle_to_proto(compiled, o)),
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
        metrics: ended.then(|| metrics_to_proto(&g.episode.metrics())),
    }
}

impl Shared {
    /// Shared state for a server with `config`, serving `store` and rendering with `render`.
    pub fn new(store: SceneStore, render: RenderScheduler, config: Config, metrics: Arc<Metrics>) -> Self {
        Self {
            store,
            registry: Registry::new(config.max_episodes),
            render,
            config,
            next_stream: AtomicU64::new(1),
            metrics,
        }
    }

    /// The largest image side a client may ask for: ours, or the renderer's if smaller.
    pub fn max_resolution(&self) -> u32 {
        MAX_RESOLUTION.min(self.render.renderer().max_resolution())
    }

    /// Resolves a request's scene choice into a compiled scene.
    async fn resolve_scene(
        self: &Arc<Self>,
        scene_id: Option<String>,
        scene_json: Option<String>,
        split: i32,
        seed: u64,
    ) -> Result<Arc<CompiledScene>, ServiceError> {
        let this = self.clone();
        let job = move || -> Result<Arc<CompiledScene>, ServiceError> {
            if let Some(json) = scene_json {
                let scene = Scene::from_json(&json)?;
                return Ok(Arc::new(CompiledScene::new(scene, esrp_core::Rules::default())?));
            }
            let index = match scene_id {
                Some(id) if !id.is_empty() => this.store.index_of(&id)?,
                _ => {
                    let split = split_of(split)?.unwrap_or(Split::Test);
                    let candidates = this.store.indices_of_split(split);
                    if candidates.is_empty() {
                        return Err(ServiceError::InvalidArgument(format!(
                            "the served dataset has no {} scenes: choose another split or a scene_id",
                            split.as_str()
                        )));
                    }
                    candidates[(seed % candidates.len() as u64) as usize]
                }
            };
            this.store.compiled(index)
        };
        tokio::task::spawn_blocking(job).await.map_err(|e| ServiceError::Internal(e.to_string()))?
    }

    /// Builds a fresh entry on `scene`, rendering its goal and first observation.
    async fn new_entry(
        self: &Arc<Self>,
        scene: Arc<CompiledScene>,
        config: EpisodeConfig,
        sensors: SensorConfig,
        privileged: bool,
    ) -> Result<(EpisodeEntry, proto::Observation), ServiceError> {
        let episode = Episode::new(scene.clone(), config)?;
        let handle = self.render.upload(scene.clone()).await?;
        let frame = handle.top_down_frame(sensors.resolution);
        let targets: Vec<esrp_core::ObjectPose> = scene.scene().movable_objects.iter().map(|o| o.target).collect();
        let mut entry = EpisodeEntry {
            episode,
            scene: handle.clone(),
            summary: summary_of_scene(scene.scene()),
            sensors,
            privileged,
            goal: proto::Image::default(),
            frame,
            last_used: Instant::now(),
        };
        let mut views = vec![View::top_down(&handle, &targets, sensors.resolution)];
        views.extend(observation_views(&entry));
        let mut outputs = self.render.render(views).await?;
        let goal = outputs.remove(0);
        entry.goal = image(goal.rgb, sensors.resolution);
        let observation = observation(&entry, outputs, true);
        Ok((entry, observation))
    }

    /// CreateEpisode.
    pub async fn create(
        self: &Arc<Self>,
        request: proto::CreateEpisodeRequest,
        stream: Option<u64>,
    ) -> Result<proto::CreateEpisodeResponse, ServiceError> {
        if self.registry.len() >= self.registry.max_episodes() {
            return Err(ServiceError::Exhausted(format!(
                "the server holds its maximum of {} live episodes: close some (CloseEpisode) or raise --max-episodes",
                self.registry.max_episodes()
            )));
        }
        let (scene_id, scene_json) = match request.scene {
            Some(proto::create_episode_request::Scene::SceneId(id)) => (Some(id), None),
            Some(proto::create_episode_request::Scene::SceneJson(json)) => (None, Some(json)),
            None => (None, None),
        };
        let sensors = sensors(request.sensors, self.max_resolution())?;
        let config = EpisodeConfig {
            horizon: (request.horizon != 0).then_some(request.horizon),
            reward: reward_weights(request.reward),
        };
        let scene = self.resolve_scene(scene_id, scene_json, request.split, request.seed).await?;
        let (entry, observation) = self.new_entry(scene, config, sensors, request.privileged).await?;
        let summary = entry.summary.clone();
        let spec = spec(&entry.sensors);
        let episode_id = self.registry.insert(entry, stream)?;
        self.metrics.created.inc();
        tracing::debug!(episode = %episode_id, scene = %summary.id, "episode created");
        Ok(proto::CreateEpisodeResponse {
            episode_id,
            spec: Some(spec),
            observation: Some(observation),
            scene: Some(summary),
        })
    }

    /// Reset.
    pub async fn reset(self: &Arc<Self>, request: proto::ResetRequest) -> Result<proto::ResetResponse, ServiceError> {
        let shared = self.registry.get(&request.episode_id)?;
        let mut entry = shared.lock().await;
        let (scene_id, scene_json) = match request.scene {
            Some(proto::reset_request::Scene::SceneId(id)) if !id.is_empty() => (Some(id), None),
            Some(proto::reset_request::Scene::SceneJson(json)) => (None, Some(json)),
            _ => (None, None),
        };
        if scene_id.is_none() && scene_json.is_none() {
            entry.episode.reset();
            entry.last_used = Instant::now();
            let outputs = self.render.render(observation_views(&entry)).await?;
            let observation = observation(&entry, outputs, true);
            return Ok(proto::ResetResponse { observation: Some(observation), scene: Some(entry.summary.clone()) });
        }
        let scene = self.resolve_scene(scene_id, scene_json, 0, 0).await?;
        let (fresh, observation) =
            self.new_entry(scene, *entry.episode.config(), entry.sensors, entry.privileged).await?;
        *entry = fresh;
        Ok(proto::ResetResponse { observation: Some(observation), scene: Some(entry.summary.clone()) })
    }

    /// Step and StepBatch, all or nothing: validates the whole batch (every action, one step per
    /// episode, no ended episode, an answer that fits in a message) before any episode moves,
    /// then steps every episode and renders every view in one batch.
    pub async fn step_many(
        self: &Arc<Self>,
        requests: Vec<proto::StepRequest>,
    ) -> Result<Vec<proto::StepResponse>, ServiceError> {
        if requests.len() > self.config.max_batch {
            return Err(ServiceError::Exhausted(format!(
                "a batch of {} steps exceeds the limit of {} (--max-batch)",
                requests.len(),
                self.config.max_batch
            )));
        }
        // "steps[3]" in a batch, "step" alone.
        let batch = requests.len() > 1;
        let at = |i: usize| if batch { format!("steps[{i}]") } else { "step".to_owned() };
        let mut seen = HashSet::new();
        let mut episodes = Vec::with_capacity(requests.len());
        let mut plan = Vec::with_capacity(requests.len());
        for (i, r) in requests.iter().enumerate() {
            let action = Action::from_code(i64::from(r.action))
                .map_err(|e| ServiceError::InvalidArgument(format!("{}.action: {e}", at(i))))?;
            if !seen.insert(r.episode_id.as_str()) {
                return Err(ServiceError::InvalidArgument(format!(
                    "{}: episode {} appears twice in one batch: send one step per episode",
                    at(i),
                    r.episode_id
                )));
            }
            episodes.push((r.episode_id.clone(), self.registry.get(&r.episode_id)?));
            plan.push(Ok(PlannedStep { at: at(i), episode: i, action, include_goal: r.include_goal }));
        }
        let max_message_bytes = self.config.max_message_bytes;
        let check = |guards: &[EpisodeGuard], plan: &[Result<PlannedStep, ServiceError>]| {
            if let Some(i) = plan.iter().position(Result::is_err) {
                return Err(ServiceError::UnknownEpisode(requests[i].episode_id.clone()));
            }
            let mut response_bytes = 0usize;
            for (i, g) in guards.iter().enumerate() {
                if g.episode.is_over() {
                    return Err(episode_over(&at(i), &requests[i].episode_id, g.episode.steps()));
                }
                response_bytes += response_size(&g.sensors, requests[i].include_goal);
            }
            // Refuse, before anything moves, a batch whose answer could not be sent.
            if response_bytes > max_message_bytes {
                return Err(ServiceError::Exhausted(format!(
                    "the answer to these {} steps would take about {:.1} MB, over the {:.1} MB message limit \
                     (--max-message-bytes): send fewer steps per call, or ask for goal images less often",
                    requests.len(),
                    response_bytes as f64 / 1e6,
                    max_message_bytes as f64 / 1e6
                )));
            }
            Ok(())
        };
        self.run_steps(episodes, plan, check).await?.into_iter().collect()
    }

    /// Takes the steps of a StepStream wave, each answered on its own: an episode may be
    /// stepped several times (in request order, each step seeing the state the previous one
    /// left), a bad step answers its error without disturbing the others, and every view of
    /// the wave is rendered as one job. Returns once the steps are taken; the answers come
    /// from [`Stepped::finish`]. The caller bounds the number of requests (`--max-batch`).
    pub async fn step_each(self: &Arc<Self>, requests: Vec<proto::StepRequest>) -> Stepped {
        let mut episodes: Vec<(String, SharedEpisode)> = Vec::new();
        let mut index: HashMap<&str, usize> = HashMap::new();
        let mut plan = Vec::with_capacity(requests.len());
        for r in &requests {
            let planned = Action::from_code(i64::from(r.action))
                .map_err(|e| ServiceError::InvalidArgument(format!("step.action: {e}")))
                .and_then(|action| {
                    let episode = match index.get(r.episode_id.as_str()) {
                        Some(&e) => e,
                        None => {
                            episodes.push((r.episode_id.clone(), self.registry.get(&r.episode_id)?));
                            index.insert(&r.episode_id, episodes.len() - 1);
                            episodes.len() - 1
                        }
                    };
                    Ok(PlannedStep { at: "step".to_owned(), episode, action, include_goal: r.include_goal })
                });
            plan.push(planned);
        }
        match self.take_steps(episodes, plan, |_, _| Ok(())).await {
            Ok(stepped) => stepped,
            Err(e) => Stepped::failed(requests.len(), &e),
        }
    }

    /// [`Shared::take_steps`], then waits for the rendering.
    async fn run_steps(
        self: &Arc<Self>,
        episodes: Vec<(String, SharedEpisode)>,
        plan: Vec<Result<PlannedStep, ServiceError>>,
        check: impl FnOnce(&[EpisodeGuard], &[Result<PlannedStep, ServiceError>]) -> Result<(), ServiceError>,
    ) -> Result<Vec<Result<proto::StepResponse, ServiceError>>, ServiceError> {
        Ok(self.take_steps(episodes, plan, check).await?.finish(&self.metrics).await)
    }

    /// Locks `episodes` (in id order, so that concurrent calls cannot deadlock), turns the
    /// steps of any closed while this call waited into NOT_FOUND, runs `check` on the locked
    /// episodes and the plan (its error fails the whole call before anything moves), takes the
    /// planned steps in order (a few inline, more on a blocking thread), hands all their views
    /// to the render thread as one job and unlocks the episodes: the views are snapshots, so
    /// the episodes may take their next steps while these render.
    async fn take_steps(
        self: &Arc<Self>,
        episodes: Vec<(String, SharedEpisode)>,
        mut plan: Vec<Result<PlannedStep, ServiceError>>,
        check: impl FnOnce(&[EpisodeGuard], &[Result<PlannedStep, ServiceError>]) -> Result<(), ServiceError>,
    ) -> Result<Stepped, ServiceError> {
        let started = Instant::now();
        let mut order: Vec<usize> = (0..episodes.len()).collect();
        order.sort_by(|&a, &b| episodes[a].0.cmp(&episodes[b].0));
        let mut slots: Vec<Option<EpisodeGuard>> = (0..episodes.len()).map(|_| None).collect();
        for &e in &order {
            slots[e] = Some(episodes[e].1.clone().lock_owned().await);
        }
        let mut guards: Vec<EpisodeGuard> = slots.into_iter().flatten().collect();
        // Closed (or reaped) while this call waited for its lock.
        for (e, (id, _)) in episodes.iter().enumerate() {
            if self.registry.get(id).is_err() {
                for step in plan.iter_mut().filter(|s| s.as_ref().is_ok_and(|s| s.episode == e)) {
                    *step = Err(ServiceError::UnknownEpisode(id.clone()));
                }
            }
        }
        check(&guards, &plan)?;
        let ids: Vec<String> = episodes.into_iter().map(|(id, _)| id).collect();
        let max_message_bytes = self.config.max_message_bytes;
        // A step costs microseconds (a rejected turn, the worst case, well under 0.1 ms): a few
        // run inline, which spares a thread hand-off per step; more go to a blocking thread so
        // that the runtime never stalls.
        let mut taken = if plan.len() <= INLINE_STEPS {
            take_planned(&mut guards, &ids, plan, max_message_bytes)
        } else {
            let (guards_back, taken) = tokio::task::spawn_blocking(move || {
                let taken = take_planned(&mut guards, &ids, plan, max_message_bytes);
                (guards, taken)
            })
            .await
            .map_err(|e| ServiceError::Internal(e.to_string()))?;
            guards = guards_back;
            taken
        };
        let views: Vec<View> =
            taken.iter_mut().filter_map(|t| t.as_mut().ok()).flat_map(|t| std::mem::take(&mut t.views)).collect();
        let render = self.render.submit(views);
        let now = Instant::now();
        for g in &mut guards {
            g.last_used = now;
        }
        Ok(Stepped { taken, render, started })
    }

    /// The episode `id`, locked.
    async fn locked(&self, id: &str) -> Result<tokio::sync::OwnedMutexGuard<EpisodeEntry>, ServiceError> {
        Ok(self.registry.get(id)?.lock_owned().await)
    }

    /// CloseEpisode.
    pub async fn close(
        &self,
        request: proto::CloseEpisodeRequest,
    ) -> Result<proto::CloseEpisodeResponse, ServiceError> {
        let shared = self.registry.remove(&request.episode_id)?;
        self.metrics.count_closed("client", 1);
        let entry = shared.lock().await;
        Ok(proto::CloseEpisodeResponse { metrics: Some(metrics_to_proto(&entry.episode.metrics())) })
    }

    /// Gives a stream a fresh id for owning its episodes.
    fn stream_id(&self) -> u64 {
        self.next_stream.fetch_add(1, Ordering::Relaxed)
    }

    /// Serves one StepStream: requests are read in waves (everything already sent, see
    /// [`Wave::admits`]), the steps of a wave are taken in request order and their views
    /// rendered as one job, and the answers go back in request order. Waves overlap: while one
    /// wave's views render, the next wave is read and stepped (its answers wait for the
    /// earlier ones); at most [`WAVES_IN_FLIGHT`] waves wait for their answers.
    async fn serve_stream(
        self: Arc<Self>,
        mut inbound: Streaming<proto::StreamRequest>,
        out: mpsc::Sender<Result<proto::StreamResponse, Status>>,
    ) {
        let stream = self.stream_id();
        // Answers of each wave, in wave order, to a task that sends them in order. Each wave
        // holds permits of the stream's budget of answer bytes until its answers are sent.
        let (answers, mut waiting) =
            mpsc::channel::<(WaveAnswers, Option<tokio::sync::OwnedSemaphorePermit>)>(WAVES_IN_FLIGHT);
        let budget_kib = (self.config.max_message_bytes / 1024).clamp(1, u32::MAX as usize) as u32;
        let budget = Arc::new(tokio::sync::Semaphore::new(budget_kib as usize));
        let sender = tokio::spawn(async move {
            while let Some((wave, permit)) = waiting.recv().await {
                for answer in wave.await {
                    if out.send(answer).await.is_err() {
                        return;
                    }
                }
                drop(permit);
            }
        });
        let failed = |status: Status| -> (WaveAnswers, Option<tokio::sync::OwnedSemaphorePermit>) {
            (Box::pin(std::future::ready(vec![Err(status)])), None)
        };
        let mut pending: Option<proto::StreamRequest> = None;
        loop {
            let first = match pending.take() {
                Some(r) => r,
                None => match inbound.next().await {
                    Some(Ok(r)) => r,
                    Some(Err(status)) => {
                        // An unreadable request (too large, not protobuf) or a broken
                        // connection: say why, if anyone still listens, and end the stream.
                        tracing::debug!(stream, "stream ended: {status}");
                        let _ = answers.send(failed(status)).await;
                        break;
                    }
                    None => break,
                },
            };
            // Gather a wave: requests already received, up to one that must wait for the
            // wave's answers (see `Wave::admits`).
            let mut wave = Wave::default();
            wave.push(first);
            let mut end: Option<Option<Status>> = None;
            while wave.requests.len() < self.config.max_batch {
                match futures_now(&mut inbound) {
                    Some(Some(Ok(r))) => {
                        if !wave.admits(&r) {
                            pending = Some(r);
                            break;
                        }
                        wave.push(r);
                    }
                    // The end, or an unreadable request: answer the wave, then end as above.
                    Some(Some(Err(status))) => {
                        end = Some(Some(status));
                        break;
                    }
                    Some(None) => {
                        end = Some(None);
                        break;
                    }
                    None => break,
                }
            }
            let (wave, bytes) = self.answer_wave(wave.requests, stream).await;
            // Wait while the answers of earlier waves hold the stream's byte budget (a wave
            // larger than the whole budget waits for all of it), so that a client that sends
            // faster than it reads cannot make the server hold more than about one message
            // limit of answers per stream, beyond one wave.
            let kib = (bytes / 1024).clamp(1, budget_kib as usize) as u32;
            let Ok(permit) = budget.clone().acquire_many_owned(kib).await else { break };
            // The sender has stopped: the client is gone.
            if answers.send((wave, Some(permit))).await.is_err() {
                break;
            }
            if let Some(end) = end {
                if let Some(status) = end {
                    tracing::debug!(stream, "stream ended: {status}");
                    let _ = answers.send(failed(status)).await;
                }
                break;
            }
        }
        // Every answer is sent (or the client is gone) before the stream's episodes close.
        drop(answers);
        let _ = sender.await;
        let closed = self.registry.remove_stream(stream);
        self.metrics.count_closed("stream_ended", closed);
        if closed > 0 {
            tracing::debug!(stream, closed, "closed the episodes of a finished stream");
        }
    }

    /// Takes a wave's steps (their views go to the render thread), then its creates, resets
    /// and closes one by one; the answers, in request order, come from the returned future,
    /// with an upper bound of their encoded size.
    async fn answer_wave(self: &Arc<Self>, wave: Vec<proto::StreamRequest>, stream: u64) -> (WaveAnswers, usize) {
        use proto::stream_request::Request as Rq;
        use proto::stream_response::Response as Rs;
        // Steps first, together, then the rest one by one (in order).
        let step_ids: Vec<usize> = (0..wave.len()).filter(|&i| matches!(wave[i].request, Some(Rq::Step(_)))).collect();
        let steps: Vec<proto::StepRequest> = step_ids
            .iter()
            .filter_map(|&i| match &wave[i].request {
                Some(Rq::Step(s)) => Some(s.clone()),
                _ => None,
            })
            .collect();
        let stepped = if steps.is_empty() { None } else { Some(self.step_each(steps).await) };
        let mut answers: Vec<Option<Rs>> = (0..wave.len()).map(|_| None).collect();
        for (i, request) in wave.iter().enumerate() {
            answers[i] = match request.request.clone() {
                Some(Rq::Create(c)) => Some(self.create(c, Some(stream)).await.map_or_else(stream_error, Rs::Created)),
                Some(Rq::Reset(r)) => Some(self.reset(r).await.map_or_else(stream_error, Rs::Reset)),
                Some(Rq::Close(c)) => Some(self.close(c).await.map_or_else(stream_error, Rs::Closed)),
                Some(Rq::Step(_)) => None,
                None => Some(stream_error(ServiceError::InvalidArgument(
                    "empty StreamRequest: set create, step, reset or close".into(),
                ))),
            };
        }
        let ids: Vec<u64> = wave.iter().map(|r| r.request_id).collect();
        let metrics = self.metrics.clone();
        let bytes = stepped.as_ref().map_or(0, Stepped::answer_bytes)
            + answers.iter().flatten().map(|a| a.encoded_len() + 16).sum::<usize>();
        let future: WaveAnswers = Box::pin(async move {
            if let Some(stepped) = stepped {
                for (&i, result) in step_ids.iter().zip(stepped.finish(&metrics).await) {
                    answers[i] = Some(result.map_or_else(stream_error, Rs::Step));
                }
            }
            ids.into_iter()
                .zip(answers)
                .map(|(request_id, response)| Ok(proto::StreamResponse { request_id, response }))
                .collect()
        });
        (future, bytes)
    }
}

/// Waves of a StepStream whose answers may wait at once: enough to keep the render thread
/// busy while the next wave is read and stepped, few enough to bound what a stream holds.
const WAVES_IN_FLIGHT: usize = 4;

/// A wave's answers, in request order, once its views are rendered.
type WaveAnswers = Pin<Box<dyn std::future::Future<Output = Vec<Result<proto::StreamResponse, Status>>> + Send>>;

fn stream_error(e: ServiceError) -> proto::stream_response::Response {
    let status = Status::from(e);
    proto::stream_response::Response::Error(proto::StreamError {
        code: status.code() as i32,
        message: status.message().to_owned(),
    })
}

/// The requests of one StepStream wave: answered together, steps first.
#[derive(Default)]
struct Wave {
    requests: Vec<proto::StreamRequest>,
    /// Episodes stepped in the wave.
    stepped: HashSet<String>,
    /// Episodes reset or closed in the wave.
    others: HashSet<String>,
}

impl Wave {
    /// Whether `r` can join the wave without its answer depending on the wave's order of
    /// work (steps first, then resets and closes): more steps of a stepped episode can (they
    /// run in request order); a create, a step of an episode reset or closed in the wave, or a
    /// reset or close of an episode already in the wave cannot, and opens the next wave.
    fn admits(&self, r: &proto::StreamRequest) -> bool {
        use proto::stream_request::Request as Rq;
        match &r.request {
            Some(Rq::Create(_)) => false,
            Some(Rq::Step(s)) => !self.others.contains(&s.episode_id),
            Some(Rq::Reset(proto::ResetRequest { episode_id, .. }))
            | Some(Rq::Close(proto::CloseEpisodeRequest { episode_id })) => {
                !self.stepped.contains(episode_id) && !self.others.contains(episode_id)
            }
            None => true,
        }
    }

    fn push(&mut self, r: proto::StreamRequest) {
        use proto::stream_request::Request as Rq;
        match &r.request {
            Some(Rq::Step(s)) => {
                self.stepped.insert(s.episode_id.clone());
            }
            Some(Rq::Reset(proto::ResetRequest { episode_id, .. }))
            | Some(Rq::Close(proto::CloseEpisodeRequest { episode_id })) => {
                self.others.insert(episode_id.clone());
            }
            _ => {}
        }
        self.requests.push(r);
    }
}

/// The next item of the stream if it is ready now, without waiting: `None` if not ready,
/// `Some(None)` at the end.
fn futures_now(inbound: &mut Streaming<proto::StreamRequest>) -> Option<Option<Result<proto::StreamRequest, Status>>> {
    let waker = std::task::Waker::noop();
    let mut cx = std::task::Context::from_waker(waker);
    match Pin::new(inbound).poll_next(&mut cx) {
        std::task::Poll::Ready(item) => Some(item),
        std::task::Poll::Pending => None,
    }
}

/// The tonic service.
#[derive(Clone)]
pub struct EsrpService {
    shared: Arc<Shared>,
}

impl EsrpService {
    /// A service over `shared`.
    pub fn new(shared: Arc<Shared>) -> Self {
        Self { shared }
    }
}

type StreamOut = Pin<Box<dyn Stream<Item = Result<proto::StreamResponse, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl proto::esrp_server::Esrp for EsrpService {
    async fn server_info(
        &self,
        _: Request<proto::ServerInfoRequest>,
    ) -> Result<Response<proto::ServerInfoResponse>, Status> {
        let s = &self.shared;
        let renderer = s.render.renderer();
        let info = renderer.adapter_info();
        Ok(Response::new(proto::ServerInfoResponse {
            version: env!("CARGO_PKG_VERSION").to_owned(),
            renderer_adapter: info.name.clone(),
            renderer_backend: format!("{:?}", info.backend).to_lowercase(),
            software_renderer: renderer.is_software(),
            limits: Some(proto::ServerLimits {
                max_episodes: s.config.max_episodes as u32,
                max_batch: s.config.max_batch as u32,
                max_message_bytes: s.config.max_message_bytes as u32,
                idle_timeout_seconds: s.config.idle_timeout_seconds as u32,
                max_resolution: s.max_resolution(),
            }),
            live_episodes: s.registry.len() as u32,
            dataset: s.store.name().to_owned(),
        }))
    }

    async fn describe_dataset(
        &self,
        _: Request<proto::DescribeDatasetRequest>,
    ) -> Result<Response<proto::DescribeDatasetResponse>, Status> {
        let store = &self.shared.store;
        let [by_split, by_difficulty, by_room_type] = store.counts();
        Ok(Response::new(proto::DescribeDatasetResponse {
            name: store.name().to_owned(),
            scenes: store.infos().len() as u32,
            by_split: by_split.into_iter().collect(),
            by_difficulty: by_difficulty.into_iter().collect(),
            by_room_type: by_room_type.into_iter().collect(),
            source: store.description().to_owned(),
        }))
    }

    async fn list_scenes(
        &self,
        request: Request<proto::ListScenesRequest>,
    ) -> Result<Response<proto::ListScenesResponse>, Status> {
        let r = request.into_inner();
        let split = split_of(r.split)?;
        let difficulty = match proto::Difficulty::try_from(r.difficulty) {
            Ok(proto::Difficulty::Unspecified) => None,
            Ok(proto::Difficulty::Easy) => Some(esrp_core::Difficulty::Easy),
            Ok(proto::Difficulty::Medium) => Some(esrp_core::Difficulty::Medium),
            Ok(proto::Difficulty::Hard) => Some(esrp_core::Difficulty::Hard),
            Err(_) => {
                return Err(ServiceError::InvalidArgument(format!(
                    "unknown difficulty {}: use 1, 2 or 3",
                    r.difficulty
                ))
                .into());
            }
        };
        let page_size = match r.page_size {
            0 => 100,
            n @ 1..=1000 => n as usize,
            n => return Err(ServiceError::InvalidArgument(format!("page_size {n} is too large: at most 1000")).into()),
        };
        let start: usize = if r.page_token.is_empty() {
            0
        } else {
            r.page_token.parse().map_err(|_| {
                ServiceError::InvalidArgument(format!("page_token {:?} is not one this server gave", r.page_token))
            })?
        };
        let infos = self.shared.store.infos();
        let mut scenes = Vec::new();
        let mut next = infos.len();
        for (i, info) in infos.iter().enumerate().skip(start) {
            if split.is_some_and(|s| s != info.split) || difficulty.is_some_and(|d| d != info.difficulty) {
                continue;
            }
            if scenes.len() == page_size {
                next = i;
                break;
            }
            scenes.push(summary_of_info(info));
        }
        let next_page_token = if next < infos.len() { next.to_string() } else { String::new() };
        Ok(Response::new(proto::ListScenesResponse { scenes, next_page_token }))
    }

    async fn create_episode(
        &self,
        request: Request<proto::CreateEpisodeRequest>,
    ) -> Result<Response<proto::CreateEpisodeResponse>, Status> {
        Ok(Response::new(self.shared.create(request.into_inner(), None).await?))
    }

    async fn reset(&self, request: Request<proto::ResetRequest>) -> Result<Response<proto::ResetResponse>, Status> {
        Ok(Response::new(self.shared.reset(request.into_inner()).await?))
    }

    async fn step(&self, request: Request<proto::StepRequest>) -> Result<Response<proto::StepResponse>, Status> {
        let mut responses = self.shared.step_many(vec![request.into_inner()]).await?;
        Ok(Response::new(responses.remove(0)))
    }

    async fn step_batch(
        &self,
        request: Request<proto::StepBatchRequest>,
    ) -> Result<Response<proto::StepBatchResponse>, Status> {
        let responses = self.shared.step_many(request.into_inner().steps).await?;
        Ok(Response::new(proto::StepBatchResponse { responses }))
    }

    type StepStreamStream = StreamOut;

    async fn step_stream(
        &self,
        request: Request<Streaming<proto::StreamRequest>>,
    ) -> Result<Response<Self::StepStreamStream>, Status> {
        let (out, receiver) = mpsc::channel(256);
        let shared = self.shared.clone();
        tokio::spawn(shared.serve_stream(request.into_inner(), out));
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(receiver))))
    }

    async fn get_goal(
        &self,
        request: Request<proto::GetGoalRequest>,
    ) -> Result<Response<proto::GetGoalResponse>, Status> {
        let mut entry = self.shared.locked(&request.into_inner().episode_id).await?;
        entry.last_used = Instant::now();
        let f = entry.frame;
        Ok(Response::new(proto::GetGoalResponse {
            goal_rgb: Some(entry.goal.clone()),
            frame: Some(proto::TopDownFrame {
                min_x: f.min_x,
                min_z: f.min_z,
                metres_per_pixel: f.metres_per_pixel(),
                resolution: f.resolution,
            }),
        }))
    }

    async fn get_privileged_state(
        &self,
        request: Request<proto::GetPrivilegedStateRequest>,
    ) -> Result<Response<proto::GetPrivilegedStateResponse>, Status> {
        let id = request.into_inner().episode_id;
        let mut entry = self.shared.locked(&id).await?;
        if !entry.privileged {
            return Err(ServiceError::NotPrivileged(id).into());
        }
        entry.last_used = Instant::now();
        let compiled = entry.episode.compiled().clone();
        let state = entry.episode.privileged_state();
        let footprint = |f: &esrp_core::OrientedRect| proto::Footprint {
            center_x: f.center.x,
            center_z: f.center.z,
            half_x: f.half_x,
            half_z: f.half_z,
            yaw: f.yaw,
        };
        let pose = |p: &esrp_core::ObjectPose| proto::Pose2 { x: p.x, z: p.z, yaw: p.yaw };
        Ok(Response::new(proto::GetPrivilegedStateResponse {
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
                    obstacle: Some(obstacle_to_proto(&compiled, s.obstacle)),
                    footprint: Some(footprint(&s.footprint)),
                })
                .collect(),
            floor: compiled.floor().iter().flat_map(|p| [p.x, p.z]).collect(),
            scene_json: compiled.scene().to_json_pretty(),
        }))
    }

    async fn get_metrics(
        &self,
        request: Request<proto::GetMetricsRequest>,
    ) -> Result<Response<proto::GetMetricsResponse>, Status> {
        let mut entry = self.shared.locked(&request.into_inner().episode_id).await?;
        entry.last_used = Instant::now();
        Ok(Response::new(proto::GetMetricsResponse {
            metrics: Some(metrics_to_proto(&entry.episode.metrics())),
            ended: entry.episode.is_over(),
        }))
    }

    async fn close_episode(
        &self,
        request: Request<proto::CloseEpisodeRequest>,
    ) -> Result<Response<proto::CloseEpisodeResponse>, Status> {
        Ok(Response::new(self.shared.close(request.into_inner()).await?))
    }
}
