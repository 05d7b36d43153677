//! [`Episode`]: a handle to one live episode on the server, and [`EpisodeOptions`], how to
//! create one.

use crate::client::Client;
use crate::error::{ClientError, Result};
use crate::proto;
use crate::types::{
    Action, EpisodeMetrics, Goal, Image, Observation, PlanAnswer, PrivilegedState, SceneSummary, Sensors, Split,
    StepResult,
};

/// Which scene an episode plays.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SceneChoice {
    /// A scene of the served dataset, by id.
    Id(String),
    /// An inline scene (`esrp.scene/v1` JSON).
    Json(String),
    /// A scene of `split` picked deterministically from `seed` (index `seed mod count`).
    Seeded {
        /// The split (test when `None`).
        split: Option<Split>,
        /// The seed.
        seed: u64,
    },
}

/// How to create an episode: the scene, the horizon, the reward weights, the sensors and
/// whether privileged state may be read.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeOptions {
    /// The scene.
    pub scene: SceneChoice,
    /// The step limit; 0: the scene's own.
    pub horizon: u32,
    /// Reward weights (the server's defaults for fields left `None`).
    pub reward: Option<proto::RewardWeights>,
    /// Optional sensors and the image size.
    pub sensors: Sensors,
    /// Allow [`Episode::privileged_state`].
    pub privileged: bool,
}

impl EpisodeOptions {
    /// An episode of the served scene `id`.
    pub fn scene(id: impl Into<String>) -> Self {
        Self::with_scene(SceneChoice::Id(id.into()))
    }

    /// An episode of an inline scene (`esrp.scene/v1` JSON).
    pub fn scene_json(json: impl Into<String>) -> Self {
        Self::with_scene(SceneChoice::Json(json.into()))
    }

    /// An episode of a scene of `split` chosen from `seed`.
    pub fn seeded(split: Split, seed: u64) -> Self {
        Self::with_scene(SceneChoice::Seeded { split: Some(split), seed })
    }

    fn with_scene(scene: SceneChoice) -> Self {
        EpisodeOptions { scene, horizon: 0, reward: None, sensors: Sensors::default(), privileged: false }
    }

    /// Sets the step limit (0: the scene's own).
    pub fn horizon(mut self, horizon: u32) -> Self {
        self.horizon = horizon;
        self
    }

    /// Sets the sensors and image size.
    pub fn sensors(mut self, sensors: Sensors) -> Self {
        self.sensors = sensors;
        self
    }

    /// Sets the reward weights.
    pub fn reward(mut self, reward: proto::RewardWeights) -> Self {
        self.reward = Some(reward);
        self
    }

    /// Allows reading the privileged state (for planners and debugging).
    pub fn privileged(mut self, privileged: bool) -> Self {
        self.privileged = privileged;
        self
    }

    /// The `CreateEpisode` request these options make.
    pub fn to_proto(&self) -> proto::CreateEpisodeRequest {
        use proto::create_episode_request::Scene;
        let (scene, split, seed) = match &self.scene {
            SceneChoice::Id(id) => (Some(Scene::SceneId(id.clone())), None, 0),
            SceneChoice::Json(json) => (Some(Scene::SceneJson(json.clone())), None, 0),
            SceneChoice::Seeded { split, seed } => (None, *split, *seed),
        };
        proto::CreateEpisodeRequest {
            scene,
            split: Split::to_proto(split),
            seed,
            horizon: self.horizon,
            reward: self.reward,
            sensors: Some(proto::Sensors {
                ego_depth: self.sensors.ego_depth,
                ego_segmentation: self.sensors.ego_segmentation,
                current_top_down: self.sensors.current_top_down,
                resolution: self.sensors.resolution,
            }),
            privileged: self.privileged,
        }
    }
}

/// A live episode on the server. Steps take `&mut self`: one episode's steps happen in order.
///
/// Dropping the handle closes the episode on the server, best effort and without blocking
/// (a task on the current tokio runtime sends `CloseEpisode`); [`Episode::close`] closes it
/// and returns its final metrics, and [`Episode::detach`] keeps it alive.
#[derive(Debug)]
pub struct Episode {
    id: String,
    client: Client,
    scene: SceneSummary,
    spec: proto::ObservationSpec,
    /// Closed (or detached): nothing to do on drop.
    closed: bool,
}

fn missing(what: &str) -> ClientError {
    ClientError::Protocol(format!("the answer has no {what}"))
}

impl Episode {
    pub(crate) fn created(client: Client, created: proto::CreateEpisodeResponse) -> Result<(Episode, Observation)> {
        let episode = Episode {
            id: created.episode_id,
            client,
            scene: created.scene.ok_or_else(|| missing("scene"))?.into(),
            spec: created.spec.unwrap_or_default(),
            closed: false,
        };
        // On an unreadable observation the handle is dropped here, which closes the episode.
        let observation = created.observation.ok_or_else(|| missing("observation"))?.try_into()?;
        Ok((episode, observation))
    }

    /// A handle to the live episode `id` (made by another handle that was detached, or by
    /// another client). It closes the episode on drop like any handle.
    pub fn attach(client: &Client, id: impl Into<String>, scene: SceneSummary) -> Episode {
        Episode { id: id.into(), client: client.clone(), scene, spec: Default::default(), closed: false }
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
        self.client.raw().step(request).await?.into_inner().try_into()
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
        let answer = self.client.raw().reset(proto::ResetRequest { episode_id: self.id.clone(), scene }).await?;
        let answer = answer.into_inner();
        if let Some(scene) = answer.scene {
            self.scene = scene.into();
        }
        answer.observation.ok_or_else(|| missing("observation"))?.try_into()
    }

    /// The goal image and its frame on the floor.
    pub async fn goal(&self) -> Result<Goal> {
        let answer =
            self.client.raw().get_goal(proto::GetGoalRequest { episode_id: self.id.clone() }).await?.into_inner();
        Ok(Goal {
            image: Image::from_proto("goal_rgb", answer.goal_rgb.ok_or_else(|| missing("goal image"))?)?,
            frame: answer.frame.ok_or_else(|| missing("frame"))?,
        })
    }

    /// The episode's metrics now, and whether it has ended.
    pub async fn metrics(&self) -> Result<(EpisodeMetrics, bool)> {
        let answer =
            self.client.raw().get_metrics(proto::GetMetricsRequest { episode_id: self.id.clone() }).await?.into_inner();
        Ok((answer.metrics.ok_or_else(|| missing("metrics"))?.into(), answer.ended))
    }

    /// The privileged state (only for episodes created with `privileged`; otherwise
    /// [`ClientError::PermissionDenied`]).
    pub async fn privileged_state(&self) -> Result<PrivilegedState> {
        let request = proto::GetPrivilegedStateRequest { episode_id: self.id.clone() };
        Ok(PrivilegedState(self.client.raw().get_privileged_state(request).await?.into_inner()))
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
        self.client.raw().plan_actions(request).await?.into_inner().try_into()
    }

    /// Closes the episode; returns its metrics at that moment.
    pub async fn close(mut self) -> Result<EpisodeMetrics> {
        self.closed = true;
        let answer = self
            .client
            .raw()
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
            let mut raw = self.client.raw();
            let episode_id = std::mem::take(&mut self.id);
            runtime.spawn(async move {
                let _ = raw.close_episode(proto::CloseEpisodeRequest { episode_id }).await;
            });
        }
    }
}
