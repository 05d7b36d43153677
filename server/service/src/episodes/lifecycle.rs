//! An episode's life outside its steps: create (and the [`Unanswered`] guard that closes an
//! episode whose create answer never left), reset, the goal image, the privileged state, the
//! metrics so far, close, and the end of a stream that owns episodes.

use std::sync::Arc;
use std::time::Instant;

use esrp_core::{CompiledScene, Episode, EpisodeConfig};

use super::entry::EpisodeEntry;
use super::observe::Observer;
use super::state::Episodes;
use crate::error::ServiceError;
use crate::types::{
    CreateOptions, Created, EpisodeId, Goal, MetricsSoFar, Observation, Privileged, ResetResult, SceneChoice,
    SensorConfig,
};

/// A created episode whose answer has not reached its client yet: dropping the last clone
/// before [`Unanswered::answered`] closes the episode. Clone (one shared state), so that it can
/// travel in a response's extensions to where the answer is known to be sent.
#[derive(Clone)]
pub struct Unanswered(Arc<Pending>);

/// The episode to close unless answered.
struct Pending(std::sync::Mutex<Option<(Arc<Episodes>, EpisodeId)>>);

impl Unanswered {
    fn new(episodes: Arc<Episodes>, episode: EpisodeId) -> Self {
        Self(Arc::new(Pending(std::sync::Mutex::new(Some((episodes, episode))))))
    }

    /// The answer was sent: the episode stays.
    pub fn answered(&self) {
        self.0.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).take();
    }
}

impl Drop for Pending {
    fn drop(&mut self) {
        let pending = self.0.get_mut().unwrap_or_else(|poisoned| poisoned.into_inner()).take();
        if let Some((episodes, episode)) = pending
            && episodes.registry.remove(&episode).is_ok()
        {
            episodes.metrics.count_closed("unanswered", 1);
            tracing::debug!(%episode, "closed an episode whose create was abandoned before its answer was sent");
        }
    }
}

/// Builds a fresh entry on `scene`, rendering its goal and first observation in one job.
async fn new_entry(
    episodes: &Episodes,
    scene: Arc<CompiledScene>,
    config: EpisodeConfig,
    sensors: SensorConfig,
    privileged: bool,
) -> Result<(EpisodeEntry, Observation), ServiceError> {
    let episode = Episode::new(scene.clone(), config)?;
    let handle = episodes.render.upload(scene).await?;
    let mut observer = Observer::new(handle, sensors);
    let first = observer.prepare(&episode, true);
    let mut views = vec![observer.goal_view(&episode)];
    views.extend(first.views().iter().cloned());
    let mut outputs = episodes.render.render(views).await?.into_iter();
    let goal = outputs.next().ok_or_else(|| ServiceError::Render("no goal image came back".into()))?;
    observer.goal = goal.rgb;
    let mut observation = first.finish(&mut outputs);
    observation.goal_rgb = Some(observer.goal.clone());
    Ok((EpisodeEntry::new(episode, observer, privileged), observation))
}

/// Creates an episode, owned by `stream` if it was created on one (it closes with it).
pub(super) async fn create(
    episodes: &Arc<Episodes>,
    options: CreateOptions,
    stream: Option<u64>,
) -> Result<Created, ServiceError> {
    let (created, unanswered) = create_unanswered(episodes, options, stream).await?;
    unanswered.answered();
    Ok(created)
}

/// Creates an episode that lives only if its answer reaches the client (see
/// `Episodes::create_unanswered`).
pub(super) async fn create_unanswered(
    episodes: &Arc<Episodes>,
    options: CreateOptions,
    stream: Option<u64>,
) -> Result<(Created, Unanswered), ServiceError> {
    if episodes.registry.len() >= episodes.registry.max_episodes() {
        return Err(ServiceError::TooManyEpisodes { max: episodes.registry.max_episodes() });
    }
    let sensors = episodes.sensors(options.sensors)?;
    let config = EpisodeConfig { horizon: options.horizon, reward: options.reward };
    let scene = episodes.resolve_scene(options.scene).await?;
    let (entry, observation) = new_entry(episodes, scene, config, sensors, options.privileged).await?;
    let summary = entry.summary.clone();
    let episode = episodes.registry.insert(entry, stream)?;
    episodes.metrics.created.inc();
    tracing::debug!(%episode, scene = %summary.id, "episode created");
    // No await from the insertion to here: the guard exists as soon as the episode does.
    let unanswered = Unanswered::new(episodes.clone(), episode.clone());
    Ok((Created { episode, sensors, observation, scene: summary }, unanswered))
}

/// Restarts an episode, on another scene if `scene` is given (see `Episodes::reset`).
pub(super) async fn reset(
    episodes: &Arc<Episodes>,
    episode: &EpisodeId,
    scene: Option<SceneChoice>,
) -> Result<ResetResult, ServiceError> {
    let shared = episodes.registry.get(episode)?;
    let mut entry = shared.lock().await;
    let Some(scene) = scene else {
        entry.episode.reset();
        entry.last_used = Instant::now();
        let prepared = entry.observer.prepare(&entry.episode, true);
        episodes.metrics.reused_views.inc_by(prepared.reused() as u64);
        let rendered = episodes.render.render(prepared.views().to_vec()).await?;
        let observation = prepared.finish(&mut rendered.into_iter());
        return Ok(ResetResult { observation, scene: entry.summary.clone() });
    };
    let scene = episodes.resolve_scene(scene).await?;
    let config = *entry.episode.config();
    let (fresh, observation) = new_entry(episodes, scene, config, entry.observer.sensors, entry.privileged).await?;
    *entry = fresh;
    Ok(ResetResult { observation, scene: entry.summary.clone() })
}

/// The goal image of an episode.
pub(super) async fn goal(episodes: &Episodes, id: &EpisodeId) -> Result<Goal, ServiceError> {
    let entry = episodes.locked(id).await?;
    let observer = &entry.observer;
    Ok(Goal { rgb: observer.goal.clone(), resolution: observer.sensors.resolution, frame: observer.frame })
}

/// The privileged state of a privileged episode.
pub(super) async fn privileged_state(episodes: &Episodes, id: &EpisodeId) -> Result<Privileged, ServiceError> {
    let shared = episodes.registry.get(id)?;
    let mut entry = shared.lock().await;
    if !entry.privileged {
        return Err(ServiceError::NotPrivileged(id.clone()));
    }
    entry.last_used = Instant::now();
    Ok(Privileged { state: entry.episode.privileged_state(), scene: entry.episode.compiled().clone() })
}

/// The metrics of an episode so far.
pub(super) async fn metrics(episodes: &Episodes, id: &EpisodeId) -> Result<MetricsSoFar, ServiceError> {
    let entry = episodes.locked(id).await?;
    Ok(MetricsSoFar { metrics: entry.episode.metrics(), ended: entry.episode.is_over() })
}

/// Closes an episode; returns its metrics.
pub(super) async fn close(episodes: &Episodes, id: &EpisodeId) -> Result<esrp_core::EpisodeMetrics, ServiceError> {
    let shared = episodes.registry.remove(id)?;
    episodes.metrics.count_closed("client", 1);
    let entry = shared.lock().await;
    Ok(entry.episode.metrics())
}

/// Closes the episodes of a finished stream.
pub(super) fn end_stream(episodes: &Episodes, stream: u64) {
    let closed = episodes.registry.remove_stream(stream);
    episodes.metrics.count_closed("stream_ended", closed);
    if closed > 0 {
        tracing::debug!(stream, closed, "closed the episodes of a finished stream");
    }
}
