//! The agents of `esrp-eval`: each plays one episode to its end and returns what the record
//! needs. Actions are sent in chunks on a pipelined stream: the planner's plan and the expert's
//! trajectory are known ahead, and the random agent does not look at its observations.

use std::time::Duration;

use anyhow::{Context, bail};
use esrp_client::{
    Action, Client, ClientError, Episode, EpisodeMetrics, EpisodeOptions, PlanAnswer, RandomActions, SceneSummary,
};
use serde_json::{Map, Value, json};

/// Which agent plays.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum AgentKind {
    /// ESRP-PLAN: the server's planner (PlanActions), replanning when the episode goes on.
    Plan,
    /// The scene's expert trajectory.
    Expert,
    /// Uniform random actions, seeded per scene.
    Random,
}

impl AgentKind {
    /// The name in results files.
    pub fn name(self) -> &'static str {
        match self {
            AgentKind::Plan => "plan",
            AgentKind::Expert => "expert",
            AgentKind::Random => "random",
        }
    }

    /// Whether the agent draws random numbers (and so has a per-scene seed).
    pub fn seeded(self) -> bool {
        self == AgentKind::Random
    }

    /// Whether the agent plays privileged episodes (it reads the simulator's state).
    pub fn privileged(self) -> bool {
        matches!(self, AgentKind::Plan | AgentKind::Expert)
    }
}

/// The agents' settings.
#[derive(Clone, Debug)]
pub struct AgentSettings {
    /// The agent.
    pub kind: AgentKind,
    /// The planner's time budget per call (`None`: the server's default).
    pub plan_budget: Option<Duration>,
    /// Planner calls after the first when the episode goes on.
    pub replans: u32,
}

impl AgentSettings {
    /// The settings as the record's `agent_config`.
    pub fn config(&self) -> Map<String, Value> {
        let value = match self.kind {
            AgentKind::Plan => json!({
                "budget_ms": self.plan_budget.map(|b| b.as_millis() as u64),
                "replans": self.replans,
            }),
            AgentKind::Expert | AgentKind::Random => json!({}),
        };
        match value {
            Value::Object(map) => map,
            _ => Map::new(),
        }
    }
}

/// How one episode went.
pub struct Played {
    /// The scene as the created episode reports it (its horizon is known).
    pub scene: SceneSummary,
    /// Final metrics.
    pub metrics: EpisodeMetrics,
    /// Every action taken.
    pub actions: Vec<Action>,
    /// `success`, `horizon` or `agent`.
    pub end: &'static str,
    /// Agent-specific statistics.
    pub stats: Map<String, Value>,
}

/// The steps of `actions` on a stream, until the episode ends. Returns the actions taken and,
/// if the episode ended, its final metrics.
async fn take(
    client: &Client,
    episode: &Episode,
    actions: &[Action],
) -> anyhow::Result<(Vec<Action>, Option<EpisodeMetrics>)> {
    if actions.is_empty() {
        return Ok((Vec::new(), None));
    }
    let mut stream = client.episode_stream(actions.len().min(64)).await?;
    let results = stream.run(&[(episode.id(), actions)]).await?.pop().unwrap_or_default();
    let mut taken = Vec::with_capacity(actions.len());
    for (&action, result) in actions.iter().zip(results) {
        match result {
            Ok(step) => {
                taken.push(action);
                if step.ended() {
                    let metrics = step.metrics.context("an ended step without metrics")?;
                    return Ok((taken, Some(metrics)));
                }
            }
            Err(e) => return Err(e).context(format!("step {} of {}", taken.len() + 1, episode.id())),
        }
    }
    Ok((taken, None))
}

fn end_of(metrics: &EpisodeMetrics) -> &'static str {
    if metrics.success { "success" } else { "horizon" }
}

/// Plays `scene` with `settings` (seeded with `seed` if the agent draws random numbers).
pub async fn play(client: &Client, scene: &str, settings: &AgentSettings, seed: u64) -> anyhow::Result<Played> {
    let privileged = settings.kind.privileged();
    // The agent's name labels the episode in a recording server's records.
    let options = EpisodeOptions::scene(scene).privileged(privileged).agent(settings.kind.name());
    let (episode, _) = client.create_episode(options).await?;
    let summary = episode.scene().clone();
    let played = match settings.kind {
        AgentKind::Expert => expert(client, &episode).await,
        AgentKind::Random => random(client, &episode, seed).await,
        AgentKind::Plan => plan(client, &episode, settings).await,
    };
    // Close whatever happened; an error of the agent comes first.
    let closed = episode.close().await;
    let (actions, metrics, end, stats) = played?;
    let metrics = match metrics {
        Some(m) => m,
        None => closed.context("closing the episode")?,
    };
    Ok(Played { scene: summary, metrics, actions, end, stats })
}

type Outcome = (Vec<Action>, Option<EpisodeMetrics>, &'static str, Map<String, Value>);

async fn expert(client: &Client, episode: &Episode) -> anyhow::Result<Outcome> {
    let trajectory = episode.privileged_state().await?.expert_trajectory()?;
    let (actions, metrics) = take(client, episode, &trajectory).await?;
    // An expert that ends before its trajectory does, or does not end, is reported as is.
    let end = metrics.as_ref().map_or("agent", end_of);
    Ok((actions, metrics, end, Map::new()))
}

async fn random(client: &Client, episode: &Episode, seed: u64) -> anyhow::Result<Outcome> {
    const CHUNK: u32 = 32;
    let horizon = episode.scene().horizon;
    if horizon == 0 {
        bail!("the server did not report the horizon of {}", episode.scene().id);
    }
    let mut draw = RandomActions::new(seed);
    let mut actions = Vec::new();
    loop {
        let left = horizon.saturating_sub(actions.len() as u32);
        let chunk: Vec<Action> = draw.by_ref().take(CHUNK.min(left.max(1)) as usize).collect();
        let (taken, metrics) = take(client, episode, &chunk).await?;
        actions.extend(taken);
        if let Some(m) = metrics {
            let end = end_of(&m);
            return Ok((actions, Some(m), end, Map::new()));
        }
    }
}

async fn plan(client: &Client, episode: &Episode, settings: &AgentSettings) -> anyhow::Result<Outcome> {
    let mut actions = Vec::new();
    let (mut calls, mut nodes, mut seconds, mut relocated) = (0u32, 0u64, 0.0f64, 0u32);
    let mut failure: Option<(String, String)> = None;
    let mut metrics = None;
    while calls <= settings.replans {
        calls += 1;
        let answer: PlanAnswer = match episode.plan_actions(0, settings.plan_budget).await {
            Ok(answer) => answer,
            Err(ClientError::DeadlineExceeded(message)) => {
                failure = Some(("deadline_exceeded".into(), message));
                break;
            }
            Err(e) => return Err(e).context("PlanActions"),
        };
        if !answer.cached {
            nodes += answer.stats.nodes_expanded;
            seconds += answer.stats.planning_seconds;
            relocated += answer.stats.objects_relocated;
        }
        // A failure may come with the actions the planner took before it failed: step them
        // (they place what they can) and ask again from there.
        failure = answer.failure.map(|reason| (reason.name().to_owned(), answer.failure_message.clone()));
        if answer.actions.is_empty() {
            break;
        }
        let (taken, ended) = take(client, episode, &answer.actions).await?;
        actions.extend(taken);
        if ended.is_some() {
            metrics = ended;
            break;
        }
    }
    let end = metrics.as_ref().map_or("agent", end_of);
    let mut stats = Map::new();
    stats.insert("plan_calls".into(), json!(calls));
    stats.insert("nodes_expanded".into(), json!(nodes));
    stats.insert("planning_seconds".into(), json!(seconds));
    stats.insert("objects_relocated".into(), json!(relocated));
    stats.insert("failure".into(), failure.as_ref().map_or(Value::Null, |(name, _)| json!(name)));
    stats.insert("failure_message".into(), failure.map_or(Value::Null, |(_, message)| json!(message)));
    Ok((actions, metrics, end, stats))
}

/// FNV-1a, 64 bits, over `text`'s UTF-8 bytes (docs/evaluation.md, "Seeds").
pub fn fnv1a64(text: &str) -> u64 {
    text.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}
