//! `esrp-demo`: a short evaluation against esrp-server. On a few test scenes of the served
//! dataset (a mix of difficulties) it runs two agents and prints per-scene results and
//! SR / OSR / RDR for each:
//!
//! - **expert**: replays each scene's expert trajectory (read from a privileged episode),
//!   pipelined on one `StepStream`; it should succeed everywhere (SR = 1).
//! - **random**: uniform random actions on every scene at once, one `StepBatch` per step, until
//!   the horizon; a floor to compare agents against.
//!
//! Without `--server` it starts an `esrp-server` (found as `LocalServer` finds one: `ESRP_SERVER_BIN`,
//! beside its own executable, on `PATH`, the workspace's `target/`) and reaches it over a Unix socket
//! (loopback TCP where the temporary folder is too deep for a socket's path).

use std::collections::HashMap;

use anyhow::{Context, bail};
use clap::Parser;
use clap::builder::TypedValueParser as _;
use esrp_client::{
    Action, Client, Difficulty, EpisodeMetrics, EpisodeOptions, RandomActions, SceneFilter, SceneSummary, Split, Tls,
    reach_or_start,
};
use tokio_stream::StreamExt;

#[derive(Parser, Debug)]
#[command(name = "esrp-demo", version, about = "Run the expert and a random agent on a few ESRP test scenes")]
struct Args {
    /// A running server (`host:port`, `http://host:port`, `https://host:port`, or `unix:PATH`
    /// for one serving `--listen-unix`);
    /// without it, esrp-demo starts one and talks to it over a Unix domain socket.
    #[arg(long)]
    server: Option<String>,
    /// Number of test scenes (1 to 1,000).
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u16).range(1..=1000).map(usize::from))]
    scenes: usize,
    /// Bearer token of a server started with `--token` (env ESRP_TOKEN).
    #[arg(long, env = "ESRP_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// TLS, for an `https://` --server: the certificate authority to trust (a PEM file; default:
    /// the system's).
    #[arg(long, env = "ESRP_TLS_CA", value_name = "FILE")]
    tls_ca: Option<std::path::PathBuf>,
    /// TLS, for an `https://` --server: the name its certificate must carry (default: the URL's
    /// host).
    #[arg(long, env = "ESRP_TLS_DOMAIN", value_name = "NAME")]
    tls_domain: Option<String>,
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
    fn add(&mut self, m: &EpisodeMetrics) {
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
async fn pick_scenes(client: &Client, n: usize) -> anyhow::Result<Vec<SceneSummary>> {
    let mut by_difficulty: Vec<Vec<SceneSummary>> = Vec::new();
    for difficulty in [Difficulty::Easy, Difficulty::Medium, Difficulty::Hard] {
        let filter = SceneFilter { page_size: n as u32, ..SceneFilter::split(Split::Test).difficulty(difficulty) };
        let first: Vec<_> = client.scenes(filter).take(n).collect::<Result<_, _>>().await?;
        by_difficulty.push(first);
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

/// Replays the expert of `scene` on a stream, all steps sent before reading any answer.
async fn expert(client: &Client, scene: &str) -> anyhow::Result<(usize, EpisodeMetrics)> {
    let (episode, _) = client.create_episode(EpisodeOptions::scene(scene).privileged(true)).await?;
    let actions = episode.privileged_state().await?.expert_trajectory()?;
    let mut stream = client.episode_stream(actions.len().max(1)).await?;
    let results = stream.run(&[(episode.id(), &actions)]).await?.pop().unwrap_or_default();
    let mut metrics = None;
    for result in results {
        metrics = result.context("the server refused an expert step")?.metrics.or(metrics);
    }
    let closed = episode.close().await?;
    Ok((actions.len(), metrics.unwrap_or(closed)))
}

/// Random actions on every scene at once until each episode ends.
async fn random(client: &Client, scenes: &[String], seed: u64) -> anyhow::Result<HashMap<String, EpisodeMetrics>> {
    let mut live = Vec::new();
    for scene in scenes {
        live.push((scene.clone(), client.create_episode(EpisodeOptions::scene(scene)).await?.0));
    }
    let mut actions = RandomActions::new(seed);
    let mut results = HashMap::new();
    while !live.is_empty() {
        let steps: Vec<(&esrp_client::Episode, Action)> =
            live.iter().map(|(_, episode)| (episode, actions.next_action())).collect();
        let responses = client.step_batch(&steps).await?;
        let mut still = Vec::new();
        for ((scene, episode), r) in live.into_iter().zip(responses) {
            match r.metrics {
                Some(m) if r.ended() => {
                    episode.close().await?;
                    results.insert(scene, m);
                }
                _ => still.push((scene, episode)),
            }
        }
        live = still;
    }
    Ok(results)
}

fn main() -> std::process::ExitCode {
    esrp_client::signals::run_tool("esrp-demo", run())
}

async fn run() -> anyhow::Result<()> {
    let args = Args::parse();
    let tls = Tls::from_flags(args.server.as_deref(), args.tls_ca.as_deref(), args.tls_domain.as_deref())?;
    esrp_client::signals::exit_on_signals("esrp-demo")?;
    let (address, mut local) =
        reach_or_start(args.server.as_deref(), None, &esrp_client::local::with_socket::<&str>(&[]))?;
    let connect = Client::connect(&address).token_opt(args.token.as_deref()).tls_opt(tls);
    let (client, info) = esrp_client::local::first_contact(connect, local.as_mut()).await?;
    println!(
        "esrp-server {} at {address}: dataset {}, renderer {} ({})",
        info.version, info.dataset, info.renderer_adapter, info.renderer_backend
    );
    let scenes = pick_scenes(&client, args.scenes).await?;
    let ids: Vec<String> = scenes.iter().map(|s| s.id.clone()).collect();
    let started = std::time::Instant::now();
    let random_results = random(&client, &ids, args.seed).await?;
    let (mut expert_tally, mut random_tally) = (Tally::default(), Tally::default());
    let mut steps = 0usize;
    println!();
    println!(
        "{:<22} {:<17} {:<6} {:>4} {:>6} | {:^22} | {:^22}",
        "scene", "room", "level", "objs", "expert", "expert: done OSR RDR", "random: done OSR RDR"
    );
    for s in &scenes {
        let (length, m) = expert(&client, &s.id).await.with_context(|| format!("expert on {}", s.id))?;
        expert_tally.add(&m);
        let r = &random_results[&s.id];
        random_tally.add(r);
        steps += length + r.steps as usize;
        println!(
            "{:<22} {:<17} {:<6} {:>4} {:>6} | {:>5} {:>6.2} {:>8.3} | {:>5} {:>6.2} {:>8.3}",
            s.id,
            s.room_type,
            s.difficulty.map_or("?", Difficulty::name),
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
