//! The episode layer: [`Shared`] owns the scenes, the registry and the render scheduler, and
//! answers calls on episodes in core types ([`EpisodeId`], [`esrp_core::Action`],
//! [`Observation`] with images as `Bytes`, [`esrp_core::EpisodeMetrics`], ...).
//!
//! **API Boundary**: nothing here knows a protocol. The `esrp.v1` adapter
//! ([`crate::esrp_v1`]) and the `dm_env_rpc.v1` adapter ([`crate::dm_env`]) convert their
//! messages into these types at their edges and back; both get the same rules, rendering and
//! limits because both call the same functions.
//!
//! - `types`: the core types.
//! - [`stepping`]: Step and StepBatch (all or nothing) and the steps of a stream wave (each on
//!   its own), rendered as one job.
//! - [`waves`]: which stream requests may be answered together, and answering them.
//! - [`planning`]: PlanActions, the server's planner on an episode's current state, off the
//!   runtime, cached per episode.

mod types;

pub mod planning;
pub mod stepping;
pub mod waves;

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use esrp_core::{CompiledScene, Episode, EpisodeConfig, Scene, Split};
use esrp_render::{Outputs, ViewOutput};

pub use planning::{PlanCall, Planned};
pub use stepping::Stepped;
pub use types::{
    ACTIONS, ArraySpec, CreateOptions, Created, ElementType, EpisodeId, Goal, MetricsSoFar, Observation, Privileged,
    ResetResult, SceneChoice, SensorConfig, SensorRequest, StepCall, StepResult,
};

use crate::config::Config;
use crate::error::ServiceError;
use crate::metrics::Metrics;
use crate::registry::{EpisodeEntry, Registry};
use crate::render::{FrameCache, RenderScheduler, View};
use crate::scenes::{SceneInfo, SceneStore};

/// State shared by every handler of both protocols.
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
    /// One permit per plan allowed to run at once (PlanActions).
    planners: tokio::sync::Semaphore,
    /// Prometheus metrics.
    pub metrics: Arc<Metrics>,
}

/// The largest image side a client may ask for.
pub const MAX_RESOLUTION: u32 = 512;

/// A created episode whose answer has not reached its client yet: dropping the last clone
/// before [`Unanswered::answered`] closes the episode. Clone (one shared state), so that it can
/// travel in a response's extensions to where the answer is known to be sent.
#[derive(Clone)]
pub struct Unanswered(Arc<Pending>);

/// The episode to close unless answered.
struct Pending(std::sync::Mutex<Option<(Arc<Shared>, EpisodeId)>>);

impl Unanswered {
    fn new(shared: Arc<Shared>, episode: EpisodeId) -> Self {
        Self(Arc::new(Pending(std::sync::Mutex::new(Some((shared, episode))))))
    }

    /// The answer was sent: the episode stays.
    pub fn answered(&self) {
        self.0.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).take();
    }
}

impl Drop for Pending {
    fn drop(&mut self) {
        let pending = self.0.get_mut().unwrap_or_else(|poisoned| poisoned.into_inner()).take();
        if let Some((shared, episode)) = pending
            && shared.registry.remove(&episode).is_ok()
        {
            shared.metrics.count_closed("unanswered", 1);
            tracing::debug!(%episode, "closed an episode whose create was abandoned before its answer was sent");
        }
    }
}

/// A locked episode.
pub(crate) type EpisodeGuard = tokio::sync::OwnedMutexGuard<EpisodeEntry>;

/// The summary of a built scene.
fn info_of_scene(scene: &Scene) -> SceneInfo {
    SceneInfo {
        id: scene.id.clone(),
        room_type: scene.room_type.clone(),
        difficulty: scene.difficulty,
        split: scene.split,
        movable_objects: scene.movable_objects.len(),
        horizon: scene.horizon,
        expert_length: scene.expert_trajectory.len(),
    }
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

/// The observation of `entry` without its rendered images ([`attach_images`] adds them).
fn observation(entry: &EpisodeEntry, include_goal: bool) -> Observation {
    Observation {
        resolution: entry.sensors.resolution,
        grasping: entry.episode.held().is_some(),
        goal_rgb: include_goal.then(|| entry.goal.clone()),
        ..Default::default()
    }
}

/// Puts the rendered views of an observation (as [`observation_views`] asked for them) in it.
/// The pixels move: RGB is the readback's `Bytes`, never copied.
fn attach_images(observation: &mut Observation, sensors: &SensorConfig, outputs: Vec<ViewOutput>) {
    let mut outputs = outputs.into_iter();
    if let Some(ego) = outputs.next() {
        observation.depth = ego.depth;
        observation.segmentation = ego.segmentation;
        observation.ego_rgb = ego.rgb;
    }
    if sensors.current_top_down {
        observation.current_top_down = outputs.next().map(|v| v.rgb);
    }
}

impl Shared {
    /// Shared state for a server with `config`, serving `store` and rendering with `render`.
    pub fn new(store: SceneStore, render: RenderScheduler, config: Config, metrics: Arc<Metrics>) -> Self {
        let planners = tokio::sync::Semaphore::new(config.planner_threads());
        Self {
            store,
            registry: Registry::new(config.max_episodes),
            render,
            config,
            next_stream: AtomicU64::new(1),
            planners,
            metrics,
        }
    }

    /// The largest image side a client may ask for: ours, or the renderer's if smaller.
    pub fn max_resolution(&self) -> u32 {
        MAX_RESOLUTION.min(self.render.renderer().max_resolution())
    }

    /// Validates the sensors a client asked for.
    fn sensors(&self, request: SensorRequest) -> Result<SensorConfig, ServiceError> {
        let resolution = request.resolution.unwrap_or(esrp_render::DEFAULT_RESOLUTION);
        let max = self.max_resolution();
        if !(16..=max).contains(&resolution) {
            return Err(ServiceError::InvalidResolution { resolution, max });
        }
        Ok(SensorConfig {
            depth: request.depth,
            segmentation: request.segmentation,
            current_top_down: request.current_top_down,
            resolution,
        })
    }

    /// Resolves a scene choice into a compiled scene (on a blocking thread: a scene may be
    /// generated or parsed).
    async fn resolve_scene(self: &Arc<Self>, choice: SceneChoice) -> Result<Arc<CompiledScene>, ServiceError> {
        let this = self.clone();
        let job = move || -> Result<Arc<CompiledScene>, ServiceError> {
            let index = match choice {
                SceneChoice::SceneJson(json) => {
                    let scene = Scene::from_json(&json)?;
                    return Ok(Arc::new(CompiledScene::new(scene, esrp_core::Rules::default())?));
                }
                SceneChoice::SceneId(id) => this.store.index_of(&id)?,
                SceneChoice::FromSplit { split, seed } => {
                    let split = split.unwrap_or(Split::Test);
                    let candidates = this.store.indices_of_split(split);
                    if candidates.is_empty() {
                        return Err(ServiceError::EmptySplit(split));
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
    ) -> Result<(EpisodeEntry, Observation), ServiceError> {
        let episode = Episode::new(scene.clone(), config)?;
        let handle = self.render.upload(scene.clone()).await?;
        let frame = handle.top_down_frame(sensors.resolution);
        let targets: Vec<esrp_core::ObjectPose> = scene.scene().movable_objects.iter().map(|o| o.target).collect();
        let mut entry = EpisodeEntry {
            episode,
            scene: handle.clone(),
            summary: info_of_scene(scene.scene()),
            sensors,
            privileged,
            goal: bytes::Bytes::new(),
            frame,
            last_used: Instant::now(),
            plan: None,
            frames: FrameCache::default(),
        };
        let first = observation_views(&entry);
        let mut views = vec![View::top_down(&handle, &targets, sensors.resolution)];
        views.extend(first.iter().cloned());
        let mut outputs = self.render.render(views).await?;
        let goal = outputs.remove(0);
        entry.goal = goal.rgb;
        entry.frames.store(first, &outputs);
        let mut observation = observation(&entry, true);
        attach_images(&mut observation, &sensors, outputs);
        Ok((entry, observation))
    }

    /// Creates an episode, owned by `stream` if it was created on one (it closes with it).
    pub async fn create(
        self: &Arc<Self>,
        options: CreateOptions,
        stream: Option<u64>,
    ) -> Result<Created, ServiceError> {
        let (created, unanswered) = self.create_unanswered(options, stream).await?;
        unanswered.answered();
        Ok(created)
    }

    /// Creates an episode that lives only if its answer reaches the client: the episode is
    /// closed when the returned [`Unanswered`] (and every clone of it) is dropped before
    /// [`Unanswered::answered`] is called. A client that gives up on a create (its deadline
    /// expires while the episode renders or its answer travels) never learns the id, so
    /// nothing else could close the episode before the idle reaper, and it would count
    /// against `--max-episodes` meanwhile.
    pub async fn create_unanswered(
        self: &Arc<Self>,
        options: CreateOptions,
        stream: Option<u64>,
    ) -> Result<(Created, Unanswered), ServiceError> {
        if self.registry.len() >= self.registry.max_episodes() {
            return Err(ServiceError::TooManyEpisodes { max: self.registry.max_episodes() });
        }
        let sensors = self.sensors(options.sensors)?;
        let config = EpisodeConfig { horizon: options.horizon, reward: options.reward };
        let scene = self.resolve_scene(options.scene).await?;
        let (entry, observation) = self.new_entry(scene, config, sensors, options.privileged).await?;
        let summary = entry.summary.clone();
        let episode = self.registry.insert(entry, stream)?;
        self.metrics.created.inc();
        tracing::debug!(%episode, scene = %summary.id, "episode created");
        // No await from the insertion to here: the guard exists as soon as the episode does.
        let unanswered = Unanswered::new(self.clone(), episode.clone());
        Ok((Created { episode, sensors, observation, scene: summary }, unanswered))
    }

    /// Restarts an episode, on another scene if `scene` is given (its settings stay).
    ///
    /// A Reset abandoned by its client (the call dropped at an await) leaves nothing
    /// half-done: the episode is locked throughout; without a new scene it is restarted in
    /// one step before the render is awaited (the abandoned call leaves it restarted, exactly
    /// as an answered one, and a Reset is idempotent), and with a new scene the fresh entry
    /// replaces the old one only after every await, so until then the episode is untouched.
    pub async fn reset(
        self: &Arc<Self>,
        episode: &EpisodeId,
        scene: Option<SceneChoice>,
    ) -> Result<ResetResult, ServiceError> {
        let shared = self.registry.get(episode)?;
        let mut entry = shared.lock().await;
        let Some(scene) = scene else {
            entry.episode.reset();
            entry.last_used = Instant::now();
            let views = observation_views(&entry);
            let outputs = match entry.frames.lookup(&views) {
                Some(outputs) => {
                    self.metrics.reused_views.inc_by(outputs.len() as u64);
                    outputs
                }
                None => {
                    let outputs = self.render.render(views.clone()).await?;
                    entry.frames.store(views, &outputs);
                    outputs
                }
            };
            let mut observation = observation(&entry, true);
            attach_images(&mut observation, &entry.sensors, outputs);
            return Ok(ResetResult { observation, scene: entry.summary.clone() });
        };
        let scene = self.resolve_scene(scene).await?;
        let (fresh, observation) =
            self.new_entry(scene, *entry.episode.config(), entry.sensors, entry.privileged).await?;
        *entry = fresh;
        Ok(ResetResult { observation, scene: entry.summary.clone() })
    }

    /// The episode `id`, locked, marked used now.
    async fn locked(&self, id: &EpisodeId) -> Result<EpisodeGuard, ServiceError> {
        let mut entry = self.registry.get(id)?.lock_owned().await;
        entry.last_used = Instant::now();
        Ok(entry)
    }

    /// The goal image of an episode.
    pub async fn goal(&self, id: &EpisodeId) -> Result<Goal, ServiceError> {
        let entry = self.locked(id).await?;
        Ok(Goal { rgb: entry.goal.clone(), resolution: entry.sensors.resolution, frame: entry.frame })
    }

    /// The privileged state of a privileged episode.
    pub async fn privileged_state(&self, id: &EpisodeId) -> Result<Privileged, ServiceError> {
        let shared = self.registry.get(id)?;
        let mut entry = shared.lock().await;
        if !entry.privileged {
            return Err(ServiceError::NotPrivileged(id.clone()));
        }
        entry.last_used = Instant::now();
        Ok(Privileged { state: entry.episode.privileged_state(), scene: entry.episode.compiled().clone() })
    }

    /// The metrics of an episode so far.
    pub async fn metrics(&self, id: &EpisodeId) -> Result<MetricsSoFar, ServiceError> {
        let entry = self.locked(id).await?;
        Ok(MetricsSoFar { metrics: entry.episode.metrics(), ended: entry.episode.is_over() })
    }

    /// Closes an episode; returns its metrics.
    pub async fn close(&self, id: &EpisodeId) -> Result<esrp_core::EpisodeMetrics, ServiceError> {
        let shared = self.registry.remove(id)?;
        self.metrics.count_closed("client", 1);
        let entry = shared.lock().await;
        Ok(entry.episode.metrics())
    }

    /// Gives a stream a fresh id for owning its episodes.
    pub fn stream_id(&self) -> u64 {
        self.next_stream.fetch_add(1, Ordering::Relaxed)
    }

    /// Closes the episodes of a finished stream.
    pub fn end_stream(&self, stream: u64) {
        let closed = self.registry.remove_stream(stream);
        self.metrics.count_closed("stream_ended", closed);
        if closed > 0 {
            tracing::debug!(stream, closed, "closed the episodes of a finished stream");
        }
    }
}
