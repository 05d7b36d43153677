//! `esrp-bench`: end-to-end throughput and latency of esrp-server, client and server on one
//! machine (or against a running server with `--server`).
//!
//! Scenarios (each runs for `--seconds` after a one-second warm-up; except in
//! `stream-1-pipelined`, every client waits for a step's answer before sending that episode's
//! next action, as an agent does):
//!
//! - `unary-1`: one episode, unary `Step`.
//! - `stream-1`: one episode on a `StepStream`.
//! - `stream-1-pipelined`: one episode on a `StepStream` with `--window` (8) steps in flight,
//!   as an agent that sends action chunks, or a replay.
//! - `unary-64`: 64 episodes, one task each, concurrent unary `Step`s.
//! - `streams-64`: 64 episodes, one stream each.
//! - `stream-mux-64`: 64 episodes on one stream, each sending its next step when its answer
//!   comes.
//! - `batch-64`: 64 episodes, one `StepBatch` of 64 steps at a time.
//! - `memory-1000`: the server's resident memory with 1,000 live episodes (local server only).
//!
//! Latency is per step: from sending it to receiving its answer (for a batch, the whole call).
//! Actions are random (seeded); episodes that end are reset.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use esrp_dataset::dice::Dice;
use esrp_server::client::{Client, LocalServer, reach_or_start};
use esrp_server::proto;
use esrp_server::proto::stream_request::Request as Rq;
use esrp_server::proto::stream_response::Response as Rs;
use tokio::sync::mpsc;
use tokio_stream::StreamExt;

#[derive(Parser, Debug)]
#[command(name = "esrp-bench", version, about = "End-to-end throughput and latency of esrp-server")]
struct Args {
    /// A running server (`http://host:port`); without it, esrp-bench starts the `esrp-server`
    /// next to its own executable on a free local port.
    #[arg(long)]
    server: Option<String>,
    /// Path of the server binary to start (default: `esrp-server` beside esrp-bench).
    #[arg(long)]
    server_binary: Option<PathBuf>,
    /// Extra arguments for the started server, e.g. `--server-args=--render-backend=gl`.
    #[arg(long, allow_hyphen_values = true, value_delimiter = ' ')]
    server_args: Vec<String>,
    /// Measured seconds per scenario.
    #[arg(long, default_value_t = 5.0)]
    seconds: f64,
    /// Scenarios to run (comma-separated); all by default.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "unary-1,stream-1,stream-1-pipelined,unary-64,streams-64,stream-mux-64,batch-64,memory-1000"
    )]
    scenarios: Vec<String>,
    /// Steps in flight in `stream-1-pipelined`.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=1024))]
    window: u32,
    /// Episodes of the multi-episode scenarios.
    #[arg(long, default_value_t = 64)]
    episodes: usize,
    /// Bearer token of a server started with `--token` (env ESRP_TOKEN).
    #[arg(long, env = "ESRP_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Write the results as JSON to this file too.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// One scenario's result.
#[derive(Debug, Default, Clone)]
struct Outcome {
    name: String,
    episodes: usize,
    steps: u64,
    seconds: f64,
    latencies: Vec<f64>,
    note: String,
}

impl Outcome {
    fn rate(&self) -> f64 {
        self.steps as f64 / self.seconds.max(1e-9)
    }

    fn percentile(&self, p: f64) -> f64 {
        if self.latencies.is_empty() {
            return f64::NAN;
        }
        let mut sorted = self.latencies.clone();
        sorted.sort_by(f64::total_cmp);
        sorted[((sorted.len() - 1) as f64 * p).round() as usize]
    }
}

/// Uniform random action codes from a seed (the project's portable random source).
struct Actions(Dice);

impl Actions {
    fn new(seed: u64) -> Self {
        Self(Dice::new(seed, 0, 0))
    }

    fn next(&mut self) -> i32 {
        self.0.below(6) as i32
    }
}

/// Episode scenes: test scenes of the served dataset, round robin.
async fn scenes(client: &mut Client, n: usize) -> anyhow::Result<Vec<String>> {
    let page = client
        .list_scenes(proto::ListScenesRequest {
            split: proto::Split::Test as i32,
            page_size: n.min(1000) as u32,
            ..Default::default()
        })
        .await?
        .into_inner();
    if page.scenes.is_empty() {
        bail!("the server has no test scenes");
    }
    Ok((0..n).map(|i| page.scenes[i % page.scenes.len()].id.clone()).collect())
}

async fn create(client: &mut Client, scene: &str) -> anyhow::Result<String> {
    let request = proto::CreateEpisodeRequest {
        scene: Some(proto::create_episode_request::Scene::SceneId(scene.to_owned())),
        ..Default::default()
    };
    Ok(client.create_episode(request).await?.into_inner().episode_id)
}

fn step(episode_id: &str, action: i32) -> proto::StepRequest {
    proto::StepRequest { episode_id: episode_id.to_owned(), action, include_goal: false }
}

fn ended(r: &proto::StepResponse) -> bool {
    r.terminated || r.truncated
}

async fn reset(client: &mut Client, episode_id: &str) -> anyhow::Result<()> {
    client.reset(proto::ResetRequest { episode_id: episode_id.to_owned(), scene: None }).await?;
    Ok(())
}

/// Measurement window: warm-up, then `seconds` measured.
#[derive(Clone, Copy)]
struct Window {
    measure_from: Instant,
    until: Instant,
}

impl Window {
    fn new(seconds: f64) -> Self {
        let measure_from = Instant::now() + Duration::from_secs(1);
        Self { measure_from, until: measure_from + Duration::from_secs_f64(seconds) }
    }
}

/// Steps `episodes` with unary calls, one task each; returns (steps, latencies) measured.
async fn unary(client: &Client, episodes: Vec<String>, window: Window) -> anyhow::Result<(u64, Vec<f64>)> {
    let mut tasks = Vec::new();
    for (i, id) in episodes.into_iter().enumerate() {
        let mut client = client.clone();
        tasks.push(tokio::spawn(async move {
            let mut actions = Actions::new(i as u64 + 1);
            let (mut steps, mut latencies) = (0u64, Vec::new());
            loop {
                let t = Instant::now();
                if t >= window.until {
                    break;
                }
                let r = client.step(step(&id, actions.next())).await?.into_inner();
                if t >= window.measure_from {
                    steps += 1;
                    latencies.push(t.elapsed().as_secs_f64());
                }
                if ended(&r) {
                    reset(&mut client, &id).await?;
                }
            }
            anyhow::Ok((steps, latencies))
        }));
    }
    gather(tasks).await
}

/// Steps measured and their latencies, seconds.
type Measured = (u64, Vec<f64>);

async fn gather(tasks: Vec<tokio::task::JoinHandle<anyhow::Result<Measured>>>) -> anyhow::Result<(u64, Vec<f64>)> {
    let (mut steps, mut latencies) = (0, Vec::new());
    for task in tasks {
        let (s, l) = task.await??;
        steps += s;
        latencies.extend(l);
    }
    Ok((steps, latencies))
}

/// Steps `episodes` on one stream with `window` steps of each episode in flight: every answer
/// sends that episode's next step (window 1 is an agent that waits for each observation;
/// more is an agent that sends action chunks, or a replay). An episode that ends is reset on
/// the stream; steps already sent behind its end answer FAILED_PRECONDITION and are not counted.
async fn stream(
    client: &Client,
    episodes: Vec<String>,
    seed: u64,
    window: usize,
    measured: Window,
) -> anyhow::Result<Measured> {
    let mut client = client.clone();
    let in_flight_max = episodes.len() * (window + 1);
    let (tx, rx) = mpsc::channel::<proto::StreamRequest>(in_flight_max + 1);
    let mut inbound = client.step_stream(tokio_stream::wrappers::ReceiverStream::new(rx)).await?.into_inner();
    let mut actions = Actions::new(seed);
    // Answers come in request order: what each one answers, and when it was sent.
    let mut in_flight: VecDeque<(Instant, usize, bool)> = VecDeque::with_capacity(in_flight_max);
    let mut next_id = 0u64;
    let mut send = async |e: usize, is_step: bool, in_flight: &mut VecDeque<(Instant, usize, bool)>| {
        next_id += 1;
        let request = if is_step {
            Rq::Step(step(&episodes[e], actions.next()))
        } else {
            Rq::Reset(proto::ResetRequest { episode_id: episodes[e].clone(), scene: None })
        };
        in_flight.push_back((Instant::now(), e, is_step));
        tx.send(proto::StreamRequest { request_id: next_id, request: Some(request) }).await
    };
    for _ in 0..window {
        for e in 0..episodes.len() {
            send(e, true, &mut in_flight).await?;
        }
    }
    let (mut steps, mut latencies) = (0u64, Vec::new());
    while let Some((sent, e, is_step)) = in_flight.pop_front() {
        let response = inbound.next().await.context("the stream ended")??;
        let now = Instant::now();
        match response.response {
            Some(Rs::Step(r)) => {
                if sent >= measured.measure_from && now <= measured.until {
                    steps += 1;
                    latencies.push((now - sent).as_secs_f64());
                }
                if ended(&r) && now < measured.until {
                    send(e, false, &mut in_flight).await?;
                }
            }
            Some(Rs::Reset(_)) => {}
            Some(Rs::Error(error)) if is_step && error.code == tonic::Code::FailedPrecondition as i32 => {}
            Some(Rs::Error(error)) => bail!("{} failed: {}", if is_step { "step" } else { "reset" }, error.message),
            other => bail!("unexpected answer {other:?}"),
        }
        if is_step && now < measured.until {
            send(e, true, &mut in_flight).await?;
        }
    }
    Ok((steps, latencies))
}

/// Steps `episodes` with one StepBatch per wave.
async fn batch(client: &Client, episodes: Vec<String>, window: Window) -> anyhow::Result<(u64, Vec<f64>)> {
    let mut client = client.clone();
    let mut actions = Actions::new(7);
    let (mut steps, mut latencies) = (0u64, Vec::new());
    loop {
        let t = Instant::now();
        if t >= window.until {
            break;
        }
        let request = proto::StepBatchRequest { steps: episodes.iter().map(|e| step(e, actions.next())).collect() };
        let responses = client.step_batch(request).await?.into_inner().responses;
        if t >= window.measure_from {
            steps += episodes.len() as u64;
            latencies.extend(std::iter::repeat_n(t.elapsed().as_secs_f64(), episodes.len()));
        }
        for (e, r) in episodes.iter().zip(&responses) {
            if ended(r) {
                reset(&mut client, e).await?;
            }
        }
    }
    Ok((steps, latencies))
}

async fn close_all(client: &mut Client, episodes: &[String]) -> anyhow::Result<()> {
    for e in episodes {
        client.close_episode(proto::CloseEpisodeRequest { episode_id: e.clone() }).await?;
    }
    Ok(())
}

async fn scenario(
    name: &str,
    args: &Args,
    client: &mut Client,
    server: Option<&LocalServer>,
) -> anyhow::Result<Outcome> {
    let n = match name {
        "unary-1" | "stream-1" | "stream-1-pipelined" => 1,
        "memory-1000" => 1000,
        _ => args.episodes,
    };
    let ids = scenes(client, n).await?;
    let before = server.and_then(LocalServer::resident_bytes);
    let mut episodes = Vec::with_capacity(n);
    for scene in &ids {
        episodes.push(create(client, scene).await?);
    }
    let mut outcome = Outcome { name: name.to_owned(), episodes: n, ..Default::default() };
    if name == "memory-1000" {
        // One step each, so that every episode has rendered and holds its state.
        for chunk in episodes.chunks(250) {
            client.step_batch(proto::StepBatchRequest { steps: chunk.iter().map(|e| step(e, 2)).collect() }).await?;
        }
        match (before, server.and_then(LocalServer::resident_bytes)) {
            (Some(b), Some(a)) => {
                outcome.note = format!(
                    "server RSS {:.0} MiB -> {:.0} MiB with {n} live episodes: {:.2} MiB per episode",
                    b as f64 / 1048576.0,
                    a as f64 / 1048576.0,
                    a.saturating_sub(b) as f64 / n as f64 / 1048576.0
                )
            }
            _ => outcome.note = "needs a local server on Linux (no --server)".into(),
        }
        close_all(client, &episodes).await?;
        return Ok(outcome);
    }
    let window = Window::new(args.seconds);
    let (steps, latencies) = match name {
        "unary-1" | "unary-64" => unary(client, episodes.clone(), window).await?,
        "stream-1" | "stream-mux-64" => stream(client, episodes.clone(), 3, 1, window).await?,
        "stream-1-pipelined" => stream(client, episodes.clone(), 5, args.window as usize, window).await?,
        "streams-64" => {
            let mut tasks = Vec::new();
            for (i, e) in episodes.iter().enumerate() {
                let client = client.clone();
                let e = vec![e.clone()];
                tasks.push(tokio::spawn(async move { stream(&client, e, i as u64 + 11, 1, window).await }));
            }
            gather(tasks).await?
        }
        "batch-64" => batch(client, episodes.clone(), window).await?,
        other => bail!("unknown scenario {other:?}"),
    };
    outcome.steps = steps;
    outcome.seconds = args.seconds;
    outcome.latencies = latencies;
    close_all(client, &episodes).await?;
    Ok(outcome)
}

/// The client's async runtime for a scenario: one thread for one episode (one agent process
/// with one connection; a multi-threaded runtime would add a thread hand-off to every step),
/// one per core for many.
fn runtime_for(scenario: &str) -> std::io::Result<tokio::runtime::Runtime> {
    if scenario.ends_with("-1") || scenario.ends_with("-1-pipelined") {
        tokio::runtime::Builder::new_current_thread().enable_all().build()
    } else {
        tokio::runtime::Builder::new_multi_thread().enable_all().build()
    }
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let (address, local) = reach_or_start(args.server.as_deref(), args.server_binary.clone(), &args.server_args)?;
    let connect = async || esrp_server::client::connect(&address, args.token.as_deref()).await;
    let info = runtime_for("")?.block_on(async {
        anyhow::Ok(connect().await?.server_info(proto::ServerInfoRequest {}).await?.into_inner())
    })?;
    let cpus = std::thread::available_parallelism().map_or(0, |n| n.get());
    let cpu_model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|c| {
            c.lines().find(|l| l.starts_with("model name")).map(|l| l.split(':').nth(1).unwrap_or("").trim().to_owned())
        })
        .unwrap_or_default();
    println!(
        "esrp-bench against {address}: esrp-server {}, renderer {} ({}), dataset {}",
        info.version, info.renderer_adapter, info.renderer_backend, info.dataset
    );
    println!("client machine: {cpus} CPUs, {cpu_model}");
    println!("{:<20} {:>8} {:>9} {:>11} {:>9} {:>9}", "scenario", "episodes", "steps", "steps/s", "p50 ms", "p99 ms");
    let mut results = Vec::new();
    for name in &args.scenarios {
        let outcome = runtime_for(name)?
            .block_on(async { scenario(name, &args, &mut connect().await?, local.as_ref()).await })
            .with_context(|| format!("scenario {name}"))?;
        if outcome.latencies.is_empty() {
            println!("{:<20} {:>8} {}", outcome.name, outcome.episodes, outcome.note);
        } else {
            println!(
                "{:<20} {:>8} {:>9} {:>11.0} {:>9.2} {:>9.2}",
                outcome.name,
                outcome.episodes,
                outcome.steps,
                outcome.rate(),
                outcome.percentile(0.5) * 1e3,
                outcome.percentile(0.99) * 1e3
            );
        }
        results.push(outcome);
    }
    if let Some(path) = &args.json {
        let rows: Vec<serde_json::Value> = results
            .iter()
            .map(|o| {
                serde_json::json!({
                    "scenario": o.name, "episodes": o.episodes, "steps": o.steps, "seconds": o.seconds,
                    "steps_per_second": if o.latencies.is_empty() { None } else { Some(o.rate()) },
                    "p50_ms": if o.latencies.is_empty() { None } else { Some(o.percentile(0.5) * 1e3) },
                    "p99_ms": if o.latencies.is_empty() { None } else { Some(o.percentile(0.99) * 1e3) },
                    "note": o.note,
                })
            })
            .collect();
        let report = serde_json::json!({
            "server": address, "renderer": info.renderer_adapter, "backend": info.renderer_backend,
            "cpus": cpus, "cpu": cpu_model, "results": rows,
        });
        std::fs::write(path, serde_json::to_string_pretty(&report)?)?;
    }
    Ok(())
}
