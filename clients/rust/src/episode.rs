//! [`Episode`]: a handle to one live episode on the server ([`crate::EpisodeOptions`] says how
//! to create one).

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
/// and returns its final metrics, and [`Episode::detach`] keeps it alive.
#[derive(Debug)]
pub struct Episode {
    id: String,
    raw: RawClient,
    scene: SceneSummary,
    spec: proto::ObservationSpec,
    /// Closed (or detached): nothing to do on drop.
    closed: bool,
}

fn missing(what: &str) -> ClientError {
    ClientError::Protocol(format!("the answer has no {what}"))
}

impl Episode {
    pub(crate) fn created(raw: RawClient, created: proto::CreateEpisodeResponse) -> Result<(Episode, Observation)> {
        let episode = Episode {
            id: created.episode_id,
            raw,
            scene: created.scene.ok_or_else(|| missing("scene"))?.into(),
            spec: created.spec.unwrap_or_default(),
            closed: false,
        };
        // On an unreadable observation the handle is dropped here, which closes the episode.
        let observation = created.observation.ok_or_else(|| missing("observation"))?.try_into()?;
        Ok((episode, observation))
    }

    /// A handle to the live episode `id` (made by another handle that was detached, or by
    /// another client), over `client` (a `&Client`, or its [`RawClient`]). It closes the
    /// episode on drop like any handle.
    pub fn attach(client: impl Into<RawClient>, id: impl Into<String>, scene: SceneSummary) -> Episode {
        Episode { id: id.into(), raw: client.into(), scene, spec: Default::default(), closed: false }
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

    /// Restarts the episode on another served scene.
    pub async fn reset_to_scene(&mut self, scene_id: impl Into<String>) -> Result<Observation> {
        self.reset_request(Some(proto::reset_request::Scene::SceneId(scene_id.into()))).await
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
        if let Ok(runtime) = tokio::runtime::Handle::try_current() {
            let mut raw = self.raw.clone();
            let episode_id = std::mem::take(&mut self.id);
            runtime.spawn(async move {
                let _ = raw.close_episode(proto::CloseEpisodeRequest { episode_id }).await;
            });
        }
    }
}
