//! [`Episode`]: a handle to one live episode on the server ([`crate::EpisodeOptions`] says how
//! to create one).

use std::collections::BTreeMap;
use std::sync::Mutex;

use crate::error::{ClientError, Result};
use crate::proto;
use crate::raw::RawClient;
use crate::types::{
    Action, EpisodeMetrics, Goal, Image, Observation, PlanAnswer, PrivilegedState, SceneSummary, StepResult,
};

/// A live episode on the server. Steps take `&mut self`: one episode's steps happen in order.
///
/// Dropping the handle closes the episode on the server, best effort and without blocking
/// (a task on the current tokio runtime sends `CloseEpisode`); [`Episode::close`] closes it
/// and returns its final metrics, and [`Episode::detach`] keeps it alive. Until then the
/// episode is also in this process's list of live episodes, which
/// [`crate::signals::exit_on_signals`] closes when the process is stopped (a process ending
/// runs no destructor).
#[derive(Debug)]
pub struct Episode {
    id: String,
    raw: RawClient,
    scene: SceneSummary,
    spec: proto::ObservationSpec,
    /// Closed (or detached): nothing to do on drop.
    closed: bool,
}

/// What this process has on servers: the episodes it holds a handle to (not closed, not
/// detached), with the stub each was made through, and its creates in flight. What
/// [`close_live`] closes when the process is stopped.
struct Live {
    episodes: BTreeMap<String, RawClient>,
    /// `CreateEpisode` calls made and not yet answered (or failed).
    creating: usize,
    /// Set by [`close_live`]: no create starts any more.
    stopping: bool,
}

static LIVE: Mutex<Live> = Mutex::new(Live { episodes: BTreeMap::new(), creating: 0, stopping: false });

fn live() -> std::sync::MutexGuard<'static, Live> {
    // The state stays whole whatever panicked while holding it: one change at a time.
    LIVE.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// A `CreateEpisode` in flight, counted until dropped, so that [`close_live`] also waits for
/// the episode it makes; see [`Creating::begin`].
pub(crate) struct Creating(());

impl Creating {
    /// Counts a create about to be made; an error once the process is stopping.
    pub(crate) fn begin() -> Result<Creating> {
        let mut live = live();
        if live.stopping {
            return Err(ClientError::Unavailable("this process is stopping: no episode is created".into()));
        }
        live.creating += 1;
        Ok(Creating(()))
    }

    /// The create made episode `id` through `raw`: it is live from now on (before this count
    /// drops, so that [`close_live`] never misses it).
    pub(crate) fn made(&self, id: &str, raw: &RawClient) {
        live().episodes.insert(id.to_owned(), raw.clone());
    }
}

impl Drop for Creating {
    fn drop(&mut self) {
        live().creating -= 1;
    }
}

/// Forgets episode `id`: it was closed (or detached). A handle forgets its episode once its
/// close is answered, not when sent, so that a process stopped meanwhile still waits for it.
pub(crate) fn forget(id: &str) {
    live().episodes.remove(id);
}

/// Forgets its episode when dropped: when the close it guards is answered, or given up.
struct ForgetOnDrop(String);

impl Drop for ForgetOnDrop {
    fn drop(&mut self) {
        forget(&self.0);
    }
}

/// Closes every episode this process holds a live handle to, each `CloseEpisode` at once, and
/// those its creates in flight make, until none is left or `deadline`; no create starts from
/// the first call on. Returns how many could not be closed: a call that failed (one that found
/// the episode gone counts as closed: its handle's own close came first), or that was still
/// unanswered at the deadline. The handles stay: their own close or drop later finds the episode
/// gone on the server. For a process about to exit (see [`crate::signals`]).
pub(crate) async fn close_live(deadline: tokio::time::Instant) -> usize {
    let mut not_closed = 0;
    loop {
        let (episodes, creating) = {
            let mut live = live();
            live.stopping = true;
            (std::mem::take(&mut live.episodes), live.creating)
        };
        if episodes.is_empty() {
            if creating == 0 {
                return not_closed;
            }
            if tokio::time::Instant::now() >= deadline {
                return not_closed + creating;
            }
            tokio::time::sleep(std::time::Duration::from_millis(5)).await;
            continue;
        }
        let count = episodes.len();
        let calls = episodes.into_iter().map(|(episode_id, mut raw)| async move {
            match raw.close_episode(proto::CloseEpisodeRequest { episode_id }).await {
                Ok(_) => true,
                Err(status) => status.code() == tonic::Code::NotFound,
            }
        });
        match tokio::time::timeout_at(deadline, futures_util::future::join_all(calls)).await {
            Ok(answers) => not_closed += answers.iter().filter(|&&closed| !closed).count(),
            Err(_) => {
                let live = live();
                return not_closed + count + live.episodes.len() + live.creating;
            }
        }
    }
}

fn missing(what: &str) -> ClientError {
    ClientError::Protocol(format!("the answer has no {what}"))
}

impl Episode {
    /// The handle of the episode `created` describes, made by [`crate::Client::create_episode`]
    /// (whose create already counted it live); on an answer without its scene or a readable
    /// observation, an error, and the handle dropped (which closes the episode).
    pub(crate) fn created(raw: RawClient, created: proto::CreateEpisodeResponse) -> Result<(Episode, Observation)> {
        let scene = created.scene.map(SceneSummary::from);
        let episode = Episode {
            id: created.episode_id,
            raw,
            scene: scene.clone().unwrap_or_default(),
            spec: created.spec.unwrap_or_default(),
            closed: false,
        };
        if scene.is_none() {
            return Err(missing("scene"));
        }
        let observation = created.observation.ok_or_else(|| missing("observation"))?.try_into()?;
        Ok((episode, observation))
    }

    /// A handle to the live episode `id` (made by another handle that was detached, or by
    /// another client), over `client` (a `&Client`, or its [`RawClient`]). It closes the
    /// episode on drop like any handle.
    pub fn attach(client: impl Into<RawClient>, id: impl Into<String>, scene: SceneSummary) -> Episode {
        let episode = Episode { id: id.into(), raw: client.into(), scene, spec: Default::default(), closed: false };
        live().episodes.insert(episode.id.clone(), episode.raw.clone());
        episode
    }

    /// The episode's id (32 hex digits).
    pub fn id(&self) -> &str {
        &self.id
    }

    /// The scene it plays.
    pub fn scene(&self) -> &SceneSummary {
        &self.scene
    }

    /// The arrays of its observations (names, shapes, dtypes) and the action names, as the
    /// server described them at creation (empty for an attached handle).
    pub fn spec(&self) -> &proto::ObservationSpec {
        &self.spec
    }

    /// Takes `action`.
    pub async fn step(&mut self, action: Action) -> Result<StepResult> {
        self.step_request(action, false).await
    }

    /// Takes `action`; the answer's observation carries the goal image too.
    pub async fn step_with_goal(&mut self, action: Action) -> Result<StepResult> {
        self.step_request(action, true).await
    }

    async fn step_request(&mut self, action: Action, include_goal: bool) -> Result<StepResult> {
        let request =
            proto::StepRequest { episode_id: self.id.clone(), action: i32::from(action.code()), include_goal };
        self.raw.clone().step(request).await?.into_inner().try_into()
    }

    /// Restarts the episode on the same scene; returns the first observation (with the goal).
    pub async fn reset(&mut self) -> Result<Observation> {
        self.reset_request(None).await
    }

    /// Restarts the episode on another served scene (an empty `scene_id` is a
    /// [`ClientError::InvalidArgument`]; [`Episode::reset`] restarts the same scene).
    pub async fn reset_to_scene(&mut self, scene_id: impl Into<String>) -> Result<Observation> {
        let scene_id = scene_id.into();
        if scene_id.is_empty() {
            return Err(crate::types::empty_scene_id());
        }
        self.reset_request(Some(proto::reset_request::Scene::SceneId(scene_id))).await
    }

    async fn reset_request(&mut self, scene: Option<proto::reset_request::Scene>) -> Result<Observation> {
        let answer = self.raw.clone().reset(proto::ResetRequest { episode_id: self.id.clone(), scene }).await?;
        let answer = answer.into_inner();
        if let Some(scene) = answer.scene {
            self.scene = scene.into();
        }
        answer.observation.ok_or_else(|| missing("observation"))?.try_into()
    }

    /// The goal image and its frame on the floor (no frame on a hidden scene served with the
    /// paper's observation only, until the episode has ended).
    pub async fn goal(&self) -> Result<Goal> {
        let answer =
            self.raw.clone().get_goal(proto::GetGoalRequest { episode_id: self.id.clone() }).await?.into_inner();
        Ok(Goal {
            image: Image::from_proto("goal_rgb", answer.goal_rgb.ok_or_else(|| missing("goal image"))?)?,
            frame: answer.frame,
        })
    }

    /// The episode's metrics now, and whether it has ended.
    pub async fn metrics(&self) -> Result<(EpisodeMetrics, bool)> {
        let answer =
            self.raw.clone().get_metrics(proto::GetMetricsRequest { episode_id: self.id.clone() }).await?.into_inner();
        Ok((answer.metrics.ok_or_else(|| missing("metrics"))?.into(), answer.ended))
    }

    /// The privileged state (only for episodes created with `privileged`; otherwise
    /// [`ClientError::PermissionDenied`]).
    pub async fn privileged_state(&self) -> Result<PrivilegedState> {
        let request = proto::GetPrivilegedStateRequest { episode_id: self.id.clone() };
        Ok(PrivilegedState(self.raw.clone().get_privileged_state(request).await?.into_inner()))
    }

    /// Asks the server's planner (ESRP-PLAN) for the next actions from the episode's current
    /// state: at most `max_actions` of them (0: the whole plan), within `budget` of planning
    /// time (`None`: the server's default; the server caps it). Only for episodes created with
    /// `privileged` ([`ClientError::PermissionDenied`] otherwise); a plan not found in time is
    /// [`ClientError::DeadlineExceeded`]; no plan at all is an answer with
    /// [`PlanAnswer::failure`] set.
    pub async fn plan_actions(&self, max_actions: u32, budget: Option<std::time::Duration>) -> Result<PlanAnswer> {
        let budget_ms = budget.map_or(0, |b| u32::try_from(b.as_millis()).unwrap_or(u32::MAX).max(1));
        let request = proto::PlanActionsRequest { episode_id: self.id.clone(), max_actions, budget_ms };
        self.raw.clone().plan_actions(request).await?.into_inner().try_into()
    }

    /// Closes the episode; returns its metrics at that moment.
    pub async fn close(mut self) -> Result<EpisodeMetrics> {
        self.closed = true;
        let _forget = ForgetOnDrop(self.id.clone());
        let answer = self
            .raw
            .clone()
            .close_episode(proto::CloseEpisodeRequest { episode_id: self.id.clone() })
            .await?
            .into_inner();
        Ok(answer.metrics.ok_or_else(|| missing("metrics"))?.into())
    }

    /// Gives up the handle without closing the episode; returns its id (see [`Episode::attach`]).
    pub fn detach(mut self) -> String {
        self.closed = true;
        forget(&self.id);
        std::mem::take(&mut self.id)
    }
}

impl Drop for Episode {
    fn drop(&mut self) {
        if self.closed {
            return;
        }
        // Best effort, never blocking: outside a runtime (or while it shuts down) the server's
        // idle reaper closes the episode instead.
        let forget = ForgetOnDrop(std::mem::take(&mut self.id));
        if let Ok(runtime) = tokio::runtime::Handle::try_current() {
            let mut raw = self.raw.clone();
            runtime.spawn(async move {
                let _ = raw.close_episode(proto::CloseEpisodeRequest { episode_id: forget.0.clone() }).await;
                drop(forget);
            });
        }
    }
}
