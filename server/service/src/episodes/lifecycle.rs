//! An episode's life outside its steps: create (and the [`Unanswered`] guard that closes an
//! episode whose create answer never left), reset, the goal image, the privileged state, the
//! metrics so far, close, and the end of a stream that owns episodes.

use std::sync::Arc;
use std::time::Instant;

use esrp_core::{CompiledScene, Episode, EpisodeConfig};

use super::entry::{EpisodeEntry, RunLog};
use super::observe::Observer;
use super::state::Episodes;
use super::{access, recording};
use crate::error::ServiceError;
use crate::types::{
    Caller, CreateOptions, Created, EpisodeId, Goal, MAX_AGENT_LABEL, MetricsSoFar, Observation, Privileged,
    ResetResult, SceneChoice, SensorConfig,
};

/// A created episode whose answer has not reached its client yet: dropping the last clone
/// before [`Unanswered::answered`] closes the episode, unless a call has named it since (its
/// client read the id from the answer's first bytes and used it: the episode is a run like any
/// other, and its counted attempt stays spent). Dropped before [`Unanswered::seen`] (nothing of
/// the answer's observation left), the closed episode was never a run and its attempt is given
/// back; dropped after (its images may have reached the client), it is closed as a run ended
/// there, recorded (`closed_by: "unanswered"`) and counted. Clone (one shared state), so that it
/// can travel in a response's extensions to where the answer is known to be sent.
#[derive(Clone)]
pub struct Unanswered(Arc<Pending>);

/// The episode to close unless answered, with its creator and, if its run took a counted
/// attempt, that attempt's scene (given back with the episode if its client saw nothing of it).
struct Pending(std::sync::Mutex<Option<PendingEpisode>>);

struct PendingEpisode {
    episodes: Arc<Episodes>,
    episode: EpisodeId,
    owner: Arc<Caller>,
    counted_scene: Option<String>,
    /// Whether the answer's observation started to leave: the client may have seen the scene.
    seen: bool,
}

impl Unanswered {
    fn new(episodes: Arc<Episodes>, episode: EpisodeId, owner: Arc<Caller>, counted_scene: Option<String>) -> Self {
        let pending = PendingEpisode { episodes, episode, owner, counted_scene, seen: false };
        Self(Arc::new(Pending(std::sync::Mutex::new(Some(pending)))))
    }

    /// The answer's observation (its images) started to leave: from here on the episode is a
    /// run, closed and recorded if the answer is then given up.
    pub fn seen(&self) {
        if let Some(pending) = self.0.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).as_mut() {
            pending.seen = true;
        }
    }

    /// The answer was sent: the episode stays.
    pub fn answered(&self) {
        self.0.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).take();
    }
}

impl Drop for Pending {
    fn drop(&mut self) {
        let pending = self.0.get_mut().unwrap_or_else(|poisoned| poisoned.into_inner()).take();
        let Some(PendingEpisode { episodes, episode, owner, counted_scene, seen }) = pending else { return };
        let Some(entry) = episodes.registry.take_unclaimed(&episode) else { return };
        episodes.metrics.count_closed("unanswered", 1);
        if !seen {
            if let Some(scene) = counted_scene {
                recording::give_back(&episodes, &owner.name, &scene);
            }
            tracing::debug!(%episode, "closed an episode whose create was abandoned before its answer was sent");
            return;
        }
        tracing::debug!(%episode, "closed an episode whose create was abandoned while its answer was sent");
        let removed = vec![(episode, entry, owner)];
        match tokio::runtime::Handle::try_current() {
            Ok(runtime) => {
                runtime.spawn(async move { recording::close_removed(&episodes, removed, "unanswered").await });
            }
            // No runtime to wait for the record on (never in the server): it is queued as it is.
            Err(_) => {
                for (_, entry, _) in removed {
                    if let Ok(mut entry) = entry.try_lock() {
                        let record = recording::finish(&episodes, &mut entry, Some("unanswered"));
                        drop(recording::write(&episodes, record.into_iter().collect()));
                    }
                }
            }
        }
    }
}

/// Who an entry belongs to and what its run logs.
struct Owner {
    caller: Arc<Caller>,
    agent: Arc<str>,
    run: Option<RunLog>,
}

/// Builds a fresh entry on `scene`, rendering its goal and first observation in one job.
async fn new_entry(
    episodes: &Episodes,
    scene: Arc<CompiledScene>,
    config: EpisodeConfig,
    sensors: SensorConfig,
    privileged: bool,
    owner: Owner,
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
    let mut entry = EpisodeEntry::new(episode, observer, privileged, owner.caller, owner.agent);
    entry.run = owner.run;
    Ok((entry, observation))
}

/// Starts a run of `caller` on the resolved `scene` (the role's rules, the counted attempt),
/// then builds its entry; a failure after the attempt was taken gives it back.
/// An episode's settings that a reset onto another scene keeps.
#[derive(Clone, Copy)]
struct Settings {
    config: EpisodeConfig,
    sensors: SensorConfig,
    privileged: bool,
    keep: bool,
}

async fn start_run(
    episodes: &Episodes,
    caller: &Arc<Caller>,
    agent: Arc<str>,
    scene: Arc<CompiledScene>,
    settings: Settings,
) -> Result<(EpisodeEntry, Observation), ServiceError> {
    let Settings { config, sensors, privileged, keep } = settings;
    let (split, id) = (scene.scene().split, scene.scene().id.clone());
    access::may_play(caller, split, privileged, config.horizon.is_some())?;
    let paper_only = access::paper_only(caller, split, &episodes.config);
    if paper_only {
        access::may_observe(caller, split, &sensors, config.reward != Default::default())?;
    }
    let run = recording::begin(episodes, caller, split, &id, keep)?;
    // Given back unless an entry comes of it: a failed build, and a call dropped while it waits
    // for the journal or the build (its client gave up), leave no episode to hold the attempt.
    let mut taken = run.as_ref().filter(|r| r.counted).map(|_| TakenAttempt {
        episodes,
        token: caller.name.clone(),
        scene: id.clone(),
        kept: false,
    });
    if let Some(run) = run.as_ref().filter(|r| r.counted) {
        // Durable before the episode exists: no crash gives the attempt back.
        recording::claim(episodes, caller, &id, &agent, config, run).await?;
    }
    let owner = Owner { caller: caller.clone(), agent, run };
    let (mut entry, observation) = new_entry(episodes, scene, config, sensors, privileged, owner).await?;
    if let Some(taken) = taken.as_mut() {
        taken.kept = true; // the entry holds it from here (no await until it is in the registry)
    }
    entry.keep_records = keep;
    entry.paper_only = paper_only;
    Ok((entry, observation))
}

/// A counted attempt taken for a run whose entry is being built: given back when dropped unless
/// `kept` (the entry exists and holds it).
struct TakenAttempt<'a> {
    episodes: &'a Episodes,
    token: Arc<str>,
    scene: String,
    kept: bool,
}

impl Drop for TakenAttempt<'_> {
    fn drop(&mut self) {
        if !self.kept {
            recording::give_back(self.episodes, &self.token, &self.scene);
        }
    }
}

/// What a create's answer holds besides its observation (the spec, the scene's summary), bytes:
/// an upper bound.
const CREATE_ANSWER_EXTRA: usize = 4096;

/// Creates an episode, owned by `stream` if it was created on one (it closes with it).
pub(super) async fn create(
    episodes: &Arc<Episodes>,
    caller: &Arc<Caller>,
    options: CreateOptions,
    stream: Option<u64>,
) -> Result<Created, ServiceError> {
    let (created, unanswered) = create_unanswered(episodes, caller, options, stream).await?;
    unanswered.answered();
    Ok(created)
}

/// Creates an episode that lives only if its answer reaches the client (see
/// `Episodes::create_unanswered`).
pub(super) async fn create_unanswered(
    episodes: &Arc<Episodes>,
    caller: &Arc<Caller>,
    options: CreateOptions,
    stream: Option<u64>,
) -> Result<(Created, Unanswered), ServiceError> {
    // The limits first (cheap), and again at the insertion (exact under races).
    episodes.registry.check_room(caller)?;
    let sensors = episodes.sensors(options.sensors)?;
    // Refused before anything is built: the answer could not be sent.
    let (bytes, max) = (sensors.answer_bytes(true) + CREATE_ANSWER_EXTRA, episodes.config.max_message_bytes);
    if bytes > max {
        return Err(ServiceError::CreateAnswerTooLarge { bytes, max });
    }
    let config = EpisodeConfig { horizon: options.horizon, reward: options.reward };
    let agent = options.agent.as_deref().filter(|a| !a.is_empty()).unwrap_or("unnamed");
    if agent.len() > MAX_AGENT_LABEL {
        return Err(ServiceError::InvalidArgument(format!(
            "agent is {} bytes long: name the agent in at most {MAX_AGENT_LABEL} bytes",
            agent.len()
        )));
    }
    let agent: Arc<str> = agent.into();
    let scene = episodes.resolve_scene(options.scene).await?;
    let (entry, observation) = start_run(
        episodes,
        caller,
        agent,
        scene,
        Settings { config, sensors, privileged: options.privileged, keep: options.keep_record },
    )
    .await?;
    let summary = entry.summary.clone();
    let counted_scene = entry.run.as_ref().filter(|r| r.counted).map(|_| summary.id.clone());
    let episode = match episodes.registry.insert(entry, stream, caller) {
        Ok(episode) => episode,
        Err(e) => {
            if let Some(scene) = &counted_scene {
                recording::give_back(episodes, &caller.name, scene);
            }
            return Err(e);
        }
    };
    episodes.metrics.created.inc();
    episodes.metrics.count_created_by(&caller.name);
    tracing::debug!(%episode, scene = %summary.id, token = %caller.name, "episode created");
    // No await from the insertion to here: the guard exists as soon as the episode does.
    let unanswered = Unanswered::new(episodes.clone(), episode.clone(), caller.clone(), counted_scene);
    Ok((Created { episode, sensors, observation, scene: summary }, unanswered))
}

/// Restarts an episode, on another scene if `scene` is given (see `Episodes::reset`).
pub(super) async fn reset(
    episodes: &Arc<Episodes>,
    caller: &Arc<Caller>,
    episode: &EpisodeId,
    scene: Option<SceneChoice>,
) -> Result<ResetResult, ServiceError> {
    // An unknown episode is refused before its new scene is read.
    episodes.registry.get(episode, caller)?;
    let scene = episodes.resolve_new_scene(scene).await?;
    reset_to(episodes, caller, episode, scene).await
}

/// Restarts an episode on its scene, or on `scene` (resolved).
pub(super) async fn reset_to(
    episodes: &Arc<Episodes>,
    caller: &Arc<Caller>,
    episode: &EpisodeId,
    scene: Option<Arc<CompiledScene>>,
) -> Result<ResetResult, ServiceError> {
    let shared = episodes.registry.get(episode, caller)?;
    let mut entry = shared.lock().await;
    let Some(scene) = scene else {
        // A new run on the same scene: a counted scene is refused here (its attempt is taken).
        let owner = entry.owner.clone();
        let run = recording::begin(episodes, &owner, entry.summary.split, &entry.summary.id, entry.keep_records)?;
        let record = recording::finish(episodes, &mut entry, Some("reset"));
        entry.run = run;
        entry.episode.reset();
        entry.trail = super::entry::Trail::start(&entry.episode);
        if let Some(watch) = &entry.watch {
            watch.send_replace(0);
        }
        entry.last_used = Instant::now();
        let prepared = entry.observer.prepare(&entry.episode, true);
        episodes.metrics.reused_views.inc_by(prepared.reused() as u64);
        for written in recording::write(episodes, record.into_iter().collect()) {
            written.wait().await;
        }
        let rendered = episodes.render.render(prepared.views().to_vec()).await?;
        let observation = prepared.finish(&mut rendered.into_iter());
        return Ok(ResetResult { observation, scene: entry.summary.clone() });
    };
    let config = *entry.episode.config();
    let (owner, agent) = (entry.owner.clone(), entry.agent.clone());
    let settings =
        Settings { config, sensors: entry.observer.sensors, privileged: entry.privileged, keep: entry.keep_records };
    let (fresh, observation) = start_run(episodes, &owner, agent, scene, settings).await?;
    let record = recording::finish(episodes, &mut entry, Some("reset"));
    let watch = entry.watch.take();
    *entry = fresh;
    // Its watchers follow it onto the new scene.
    if let Some(watch) = watch {
        watch.send_replace(0);
        entry.watch = Some(watch);
    }
    for written in recording::write(episodes, record.into_iter().collect()) {
        written.wait().await;
    }
    Ok(ResetResult { observation, scene: entry.summary.clone() })
}

/// The goal image of an episode, and its frame on the floor unless the episode serves the
/// paper's observation only and has not ended: the frame gives the room's size and position in
/// metres, which the paper's agent is not told.
pub(super) async fn goal(episodes: &Episodes, caller: &Caller, id: &EpisodeId) -> Result<Goal, ServiceError> {
    let entry = episodes.locked(caller, id).await?;
    let observer = &entry.observer;
    let frame = (!entry.paper_only || entry.episode.is_over()).then_some(observer.frame);
    Ok(Goal { rgb: observer.goal.clone(), resolution: observer.sensors.resolution, frame })
}

/// The privileged state of a privileged episode.
pub(super) async fn privileged_state(
    episodes: &Episodes,
    caller: &Caller,
    id: &EpisodeId,
) -> Result<Privileged, ServiceError> {
    access::may_read_privileged(caller, "GetPrivilegedState")?;
    let shared = episodes.registry.get(id, caller)?;
    let mut entry = shared.lock().await;
    if !entry.privileged {
        return Err(ServiceError::NotPrivileged(id.clone()));
    }
    entry.last_used = Instant::now();
    Ok(Privileged { state: entry.episode.privileged_state(), scene: entry.episode.compiled().clone() })
}

/// The metrics of an episode so far.
pub(super) async fn metrics(
    episodes: &Episodes,
    caller: &Caller,
    id: &EpisodeId,
) -> Result<MetricsSoFar, ServiceError> {
    let entry = episodes.locked(caller, id).await?;
    let ended = entry.episode.is_over();
    access::may_read_metrics(caller, entry.summary.split, entry.paper_only, ended)?;
    Ok(MetricsSoFar { metrics: entry.episode.metrics(), ended })
}

/// Closes an episode; returns its metrics.
pub(super) async fn close(
    episodes: &Episodes,
    caller: &Caller,
    id: &EpisodeId,
) -> Result<esrp_core::EpisodeMetrics, ServiceError> {
    let shared = episodes.registry.remove(id, caller)?;
    episodes.metrics.count_closed("client", 1);
    let mut entry = shared.lock().await;
    let record = recording::finish(episodes, &mut entry, Some("client"));
    for written in recording::write(episodes, record.into_iter().collect()) {
        written.wait().await;
    }
    Ok(entry.episode.metrics())
}

/// Closes the episodes of a finished stream.
pub(super) async fn end_stream(episodes: &Episodes, stream: u64) {
    let closed = episodes.registry.remove_stream(stream);
    episodes.metrics.count_closed("stream_ended", closed.len());
    if !closed.is_empty() {
        tracing::debug!(stream, closed = closed.len(), "closed the episodes of a finished stream");
    }
    recording::close_removed(episodes, closed, "stream").await;
}
