//! `esrp-demo`: a short evaluation against esrp-server. On a few test scenes of the served
//! dataset (a mix of difficulties) it runs two agents and prints per-scene results and
//! SR / OSR / RDR for each:
//!
//! - **expert**: replays each scene's expert trajectory (read from a privileged episode),
//!   pipelined on one `StepStream`; it should succeed everywhere (SR = 1).
//! - **random**: uniform random actions on every scene at once, one `StepBatch` per step, until
//!   the horizon; a floor to compare agents against.
//!
//! Without `--server` it starts the `esrp-server` beside its own executable on a free port.

use std::collections::HashMap;

use anyhow::{Context, bail};
use clap::Parser;
use esrp_dataset::dice::Dice;
use esrp_server::client::{Client, connect, reach_or_start};
use esrp_server::proto;
use esrp_server::proto::stream_request::Request as Rq;
use esrp_server::proto::stream_response::Response as Rs;
use tokio_stream::StreamExt;

#[derive(Parser, Debug)]
#[command(name = "esrp-demo", version, about = "Run the expert and a random agent on a few ESRP test scenes")]
struct Args {
    /// A running server (`http://host:port`); without it, esrp-demo starts one.
    #[arg(long)]
    server: Option<String>,
    /// Number of test scenes.
    #[arg(long, default_value_t = 6)]
    scenes: usize,
    /// Bearer token of a server started with `--token` (env ESRP_TOKEN).
    #[arg(long, env = "ESRP_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Seed of the random agent.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

/// SR / OSR / RDR over episodes.
#[derive(Default)]
struct Tally {
    episodes: u32,
    successes: u32,
    osr: f64,
    rdr: f64,
}

impl Tally {
    fn add(&mut self, m: &proto::EpisodeMetrics) {
        self.episodes += 1;
        self.successes += u32::from(m.success);
        self.osr += m.object_success_rate;
        self.rdr += m.remaining_distance_ratio;
    }

    fn line(&self, agent: &str) -> String {
        let n = f64::from(self.episodes.max(1));
        format!(
            "{agent:<8} SR {:.3}  OSR {:.3}  RDR {:.3}  ({} episodes)",
            f64::from(self.successes) / n,
            self.osr / n,
            self.rdr / n,
            self.episodes
        )
    }
}

/// Test scenes, round robin over difficulties so that a short demo sees easy to hard.
async fn pick_scenes(client: &mut Client, n: usize) -> anyhow::Result<Vec<proto::SceneSummary>> {
    let mut by_difficulty: Vec<Vec<proto::SceneSummary>> = Vec::new();
    for difficulty in [proto::Difficulty::Easy, proto::Difficulty::Medium, proto::Difficulty::Hard] {
        let page = client
            .list_scenes(proto::ListScenesRequest {
                split: proto::Split::Test as i32,
                difficulty: difficulty as i32,
                page_size: n as u32,
                page_token: String::new(),
            })
            .await?
            .into_inner();
        by_difficulty.push(page.scenes);
    }
    let mut picked = Vec::new();
    for i in 0..n {
        for list in &by_difficulty {
            if picked.len() < n
                && let Some(s) = list.get(i)
            {
                picked.push(s.clone());
            }
        }
    }
    if picked.is_empty() {
        bail!("the served dataset has no test scenes");
    }
    Ok(picked)
}

fn create(scene: &str, privileged: bool) -> proto::CreateEpisodeRequest {
    proto::CreateEpisodeRequest {
        scene: Some(proto::create_episode_request::Scene::SceneId(scene.to_owned())),
        privileged,
        ..Default::default()
    }
}

/// Replays the expert of `scene` on a stream, all steps sent before reading any answer.
async fn expert(client: &mut Client, scene: &str) -> anyhow::Result<(usize, proto::EpisodeMetrics)> {
    let created = client.create_episode(create(scene, true)).await?.into_inner();
    let state = client
        .get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: created.episode_id.clone() })
        .await?
        .into_inner();
    let actions: Vec<i32> = esrp_core::Scene::from_json(&state.scene_json)
        .context("the server sent a scene this client cannot read")?
        .expert_trajectory
        .iter()
        .map(|a| i32::from(a.code()))
        .collect();
    let (tx, rx) = tokio::sync::mpsc::channel(actions.len() + 1);
    let mut answers = client.step_stream(tokio_stream::wrappers::ReceiverStream::new(rx)).await?.into_inner();
    for (i, &action) in actions.iter().enumerate() {
        let step = proto::StepRequest { episode_id: created.episode_id.clone(), action, include_goal: false };
        tx.send(proto::StreamRequest { request_id: i as u64, request: Some(Rq::Step(step)) }).await?;
    }
    drop(tx);
    let mut metrics = None;
    while let Some(answer) = answers.next().await {
        match answer?.response {
            Some(Rs::Step(step)) => metrics = step.metrics.or(metrics),
            Some(Rs::Error(e)) => bail!("the server refused an expert step: {}", e.message),
            _ => {}
        }
    }
    let closed =
        client.close_episode(proto::CloseEpisodeRequest { episode_id: created.episode_id }).await?.into_inner();
    Ok((actions.len(), metrics.or(closed.metrics).context("no metrics")?))
}

/// Random actions on every scene at once until each episode ends.
async fn random(
    client: &mut Client,
    scenes: &[String],
    seed: u64,
) -> anyhow::Result<HashMap<String, proto::EpisodeMetrics>> {
    let mut live = Vec::new();
    for scene in scenes {
        live.push((scene.clone(), client.create_episode(create(scene, false)).await?.into_inner().episode_id));
    }
    let mut dice = Dice::new(seed, 0, 0);
    let mut results = HashMap::new();
    while !live.is_empty() {
        let steps = live
            .iter()
            .map(|(_, id)| proto::StepRequest {
                episode_id: id.clone(),
                action: dice.below(6) as i32,
                include_goal: false,
            })
            .collect();
        let responses = client.step_batch(proto::StepBatchRequest { steps }).await?.into_inner().responses;
        let mut still = Vec::new();
        for ((scene, id), r) in live.into_iter().zip(responses) {
            match r.metrics {
                Some(m) if r.terminated || r.truncated => {
                    client.close_episode(proto::CloseEpisodeRequest { episode_id: id }).await?;
                    results.insert(scene, m);
                }
                _ => still.push((scene, id)),
            }
        }
        live = still;
    }
    Ok(results)
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let (address, _local) = reach_or_start(args.server.as_deref(), None, &[])?;
    let mut client = connect(&address, args.token.as_deref()).await?;
    let info = client.server_info(proto::ServerInfoRequest {}).await?.into_inner();
    println!(
        "esrp-server {} at {address}: dataset {}, renderer {} ({})",
        info.version, info.dataset, info.renderer_adapter, info.renderer_backend
    );
    let scenes = pick_scenes(&mut client, args.scenes).await?;
    let ids: Vec<String> = scenes.iter().map(|s| s.id.clone()).collect();
    let started = std::time::Instant::now();
    let random_results = random(&mut client, &ids, args.seed).await?;
    let (mut expert_tally, mut random_tally) = (Tally::default(), Tally::default());
    let mut steps = 0usize;
    println!();
    println!(
        "{:<22} {:<17} {:<6} {:>4} {:>6} | {:^22} | {:^22}",
        "scene", "room", "level", "objs", "expert", "expert: done OSR RDR", "random: done OSR RDR"
    );
    for s in &scenes {
        let (length, m) = expert(&mut client, &s.id).await.with_context(|| format!("expert on {}", s.id))?;
        expert_tally.add(&m);
        let r = &random_results[&s.id];
        random_tally.add(r);
        steps += length + r.steps as usize;
        let level = match proto::Difficulty::try_from(s.difficulty).unwrap_or_default() {
            proto::Difficulty::Easy => "easy",
            proto::Difficulty::Medium => "medium",
            proto::Difficulty::Hard => "hard",
            proto::Difficulty::Unspecified => "?",
        };
        println!(
            "{:<22} {:<17} {:<6} {:>4} {:>6} | {:>5} {:>6.2} {:>8.3} | {:>5} {:>6.2} {:>8.3}",
            s.id,
            s.room_type,
            level,
            s.movable_objects,
            length,
            if m.success { "yes" } else { "no" },
            m.object_success_rate,
            m.remaining_distance_ratio,
            if r.success { "yes" } else { "no" },
            r.object_success_rate,
            r.remaining_distance_ratio
        );
    }
    println!();
    println!("{}", expert_tally.line("expert"));
    println!("{}", random_tally.line("random"));
    let seconds = started.elapsed().as_secs_f64();
    println!("{steps} steps in {seconds:.1} s ({:.0} steps/s, rendering included)", steps as f64 / seconds);
    if expert_tally.successes != expert_tally.episodes {
        bail!("the expert failed on some scene: the simulator and the dataset disagree");
    }
    Ok(())
}
