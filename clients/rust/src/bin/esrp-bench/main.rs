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
//! - `soak` (only when named): load held for `--minutes` by `--clients` simulated clients, a
//!   seeded random mix of creates, steps, batches, streams, resets, closes, abandoned calls and
//!   disconnects; it checks that every episode is closed at the end, that the server's live
//!   count is back down and that its resident memory stopped growing after the warm-up (see
//!   `esrp-bench/soak.rs`). esrp-bench exits with an error when the soak fails.
//!
//! Latency is per step: from sending it to receiving its answer (for a batch, the whole call).
//! Everything goes through `esrp-client`, as a Rust agent would.
//! Actions are random (seeded); episodes that end are reset.
//!
//! `--breakdown` prints, under each scenario, where the server's time went by stage (from its
//! metrics: see `breakdown.rs`). Under each scenario's row, a line says how much CPU the client
//! used (core-microseconds per step and cores kept busy, over the measured seconds, all its
//! processes; Linux). `--processes N` runs each scenario in N processes at once
//! against the same server (each with `--episodes` episodes), so that the client is never what
//! is measured on a many-core machine: the row sums their steps.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use breakdown::Breakdown;
use clap::Parser;
use clap::builder::TypedValueParser as _;
use esrp_client::{
    Action, Answer, Client, ClientError, Episode, EpisodeOptions, LocalServer, RandomActions, SceneFilter, Split,
    StepResult, Tls, reach_or_start,
};

mod breakdown;
mod soak;

/// Every scenario `--scenarios` may name.
const SCENARIOS: [&str; 9] = [
    "unary-1",
    "stream-1",
    "stream-1-pipelined",
    "unary-64",
    "streams-64",
    "stream-mux-64",
    "batch-64",
    "memory-1000",
    "soak",
];

/// `--seconds`: a number of seconds above 0 and at most a day.
fn seconds_parser(text: &str) -> Result<f64, String> {
    within(text, 86_400.0, "seconds")
}

/// `--minutes`: a number of minutes above 0 and at most a day.
fn minutes_parser(text: &str) -> Result<f64, String> {
    within(text, 1_440.0, "minutes")
}

/// `text` as a number above 0 and at most `most` (NaN and infinities refused).
fn within(text: &str, most: f64, unit: &str) -> Result<f64, String> {
    let value: f64 = text.parse().map_err(|e| format!("{e}"))?;
    if !(value > 0.0 && value <= most) {
        return Err(format!("{text} is not a number of {unit} above 0 and at most {most}"));
    }
    Ok(value)
}

#[derive(Parser, Debug)]
#[command(name = "esrp-bench", version, about = "End-to-end throughput and latency of esrp-server")]
struct Args {
    /// A running server (`host:port`, `http://host:port`, `https://host:port`, or `unix:PATH`
    /// for one serving `--listen-unix`);
    /// without it, esrp-bench starts an `esrp-server` (`--server-binary`) on a free local port
    /// (see `--transport`). With `--processes`, several servers
    /// may be named, comma-separated: process i drives server i modulo their number (scale-out
    /// measured with the same clients as one server).
    #[arg(long)]
    server: Option<String>,
    /// Path of the server binary to start (default: found as `LocalServer` does: `ESRP_SERVER_BIN`,
    /// beside esrp-bench or in its parent folder, on `PATH`, then the workspace's `target/`).
    #[arg(long)]
    server_binary: Option<PathBuf>,
    /// Extra arguments for the started server, e.g. `--server-args=--render-backend=gl`.
    #[arg(long, allow_hyphen_values = true, value_delimiter = ' ')]
    server_args: Vec<String>,
    /// How the clients reach the server started here: `tcp` (loopback, as a client on another
    /// machine would, less the network) or `unix` (the server also serves a Unix domain socket,
    /// `--listen-unix`, and the clients connect through it, as the tools and the Python envs do
    /// with a server of their own). A server named by `--server` is reached as its URL says.
    #[arg(long, value_enum, default_value_t = Transport::Tcp)]
    transport: Transport,
    /// Measured seconds per scenario (above 0, at most a day).
    #[arg(long, default_value_t = 5.0, value_parser = seconds_parser)]
    seconds: f64,
    /// Scenarios to run (comma-separated); all but `soak` by default.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "unary-1,stream-1,stream-1-pipelined,unary-64,streams-64,stream-mux-64,batch-64,memory-1000",
        value_parser = clap::builder::PossibleValuesParser::new(SCENARIOS),
    )]
    scenarios: Vec<String>,
    /// Steps in flight in `stream-1-pipelined`.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=1024))]
    window: u32,
    /// Episodes of the multi-episode scenarios (1 to 4,096).
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u16).range(1..=4096).map(usize::from))]
    episodes: usize,
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
    /// Write the results as JSON to this file too.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Minutes of load in `soak` (above 0, at most a day).
    #[arg(long, default_value_t = 5.0, value_parser = minutes_parser)]
    minutes: f64,
    /// Concurrent simulated clients in `soak`.
    #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u32).range(1..=4096))]
    clients: u32,
    /// Seed of the `soak` clients' choices (scenes, calls, actions, deadlines).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// `soak` fails when the server's RSS grows more than this, percent, from the end of the
    /// warm-up (a fifth of the run, at most 5 minutes) to the end of the load.
    #[arg(long, default_value_t = 10.0)]
    rss_growth_limit: f64,
    /// `soak`: the claim timeout of the server named by `--server` (its `--claim-timeout-seconds`),
    /// which the cleanup waits for. A server started here gets `--claim-timeout-seconds 60`
    /// unless `--server-args` sets it (the soak's clients leave some episodes unnamed for many
    /// seconds under load: a shorter timeout closes episodes they still hold).
    #[arg(long, default_value_t = 300)]
    server_claim_timeout: u64,
    /// Print where the server's time went in each scenario, by stage, and how much of the wait
    /// for the device the device spent drawing, where the server times it (its metrics: a
    /// server started here is given `--metrics-listen`; with `--server`, name its endpoint with
    /// `--metrics`).
    #[arg(long)]
    breakdown: bool,
    /// The metrics endpoint of the server named by `--server` (`http://HOST:PORT/metrics`).
    #[arg(long)]
    metrics: Option<String>,
    /// Run each scenario in this many processes at once against the same server, each with
    /// `--episodes` episodes (not `memory-1000` or `soak`).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    processes: u32,
    /// Async runtime threads of each client process in the scenarios of many episodes (1: a
    /// current-thread runtime; 0: auto, one per core with one process, and one per process with
    /// `--processes` above one, the processes spreading the client over the cores: a process's
    /// one connection gains little from more threads, and each hand-off between them costs a
    /// wake-up). The scenarios of one episode always run on one thread.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u16).range(0..=256))]
    client_threads: u16,
    /// Stop (closing this process's episodes) when standard input reaches its end: what the
    /// `--processes` children are started with, on a pipe their parent holds, so that they end
    /// with it however it ends.
    #[arg(long, hide = true)]
    stop_on_stdin_close: bool,
}

/// How the clients reach a server started here (`--transport`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum Transport {
    /// Loopback TCP.
    Tcp,
    /// A Unix domain socket (`--listen-unix`).
    Unix,
}

/// The claim timeout given to a server started here (soak's cleanup waits for it).
const LOCAL_CLAIM_TIMEOUT: u64 = 60;

/// One scenario's result.
#[derive(Debug, Default, Clone)]
struct Outcome {
    name: String,
    episodes: usize,
    steps: u64,
    seconds: f64,
    latencies: Vec<f64>,
    note: String,
    /// Where the server's time went (`--breakdown`).
    breakdown: Option<Breakdown>,
    /// Per process with `--processes`: each one's p50 and p99 latencies, seconds.
    process_percentiles: Vec<(f64, f64)>,
    /// CPU seconds the client used over the measured seconds (all its processes), where it can
    /// tell ([`own_cpu_seconds`]).
    client_cpu: Option<f64>,
}

impl Outcome {
    fn rate(&self) -> f64 {
        self.steps as f64 / self.seconds.max(1e-9)
    }

    fn percentile(&self, p: f64) -> f64 {
        if !self.process_percentiles.is_empty() {
            // Several processes: the median of their medians, the worst of their p99s.
            let mut of: Vec<f64> =
                self.process_percentiles.iter().map(|&(p50, p99)| if p > 0.5 { p99 } else { p50 }).collect();
            of.sort_by(f64::total_cmp);
            return if p > 0.5 { of[of.len() - 1] } else { of[(of.len() - 1) / 2] };
        }
        if self.latencies.is_empty() {
            return f64::NAN;
        }
        let mut sorted = self.latencies.clone();
        sorted.sort_by(f64::total_cmp);
        sorted[((sorted.len() - 1) as f64 * p).round() as usize]
    }

    /// Whether it measured latencies (itself, or in its processes).
    fn measured(&self) -> bool {
        !self.latencies.is_empty() || !self.process_percentiles.is_empty()
    }

    /// The scenario's row of the printed table (its note alone where it measured no latencies),
    /// and its breakdown under it.
    fn print_row(&self) {
        self.print_measured();
        if let Some(cpu) = self.client_cpu.filter(|_| self.steps > 0) {
            println!(
                "  client CPU: {:.1} core-µs/step, {:.2} cores",
                cpu / self.steps as f64 * 1e6,
                cpu / self.seconds.max(1e-9)
            );
        }
        for line in self.breakdown.iter().flat_map(Breakdown::lines) {
            println!("{line}");
        }
    }

    fn print_measured(&self) {
        if !self.measured() {
            println!("{:<20} {:>8} {}", self.name, self.episodes, self.note);
        } else {
            println!(
                "{:<20} {:>8} {:>9} {:>11.0} {:>9.2} {:>9.2}  {}",
                self.name,
                self.episodes,
                self.steps,
                self.rate(),
                self.percentile(0.5) * 1e3,
                self.percentile(0.99) * 1e3,
                self.note
            );
        }
    }

    /// The scenario's entry of `--json`'s results (rates and latencies null where not measured).
    fn to_json(&self) -> serde_json::Value {
        let measured = self.measured();
        serde_json::json!({
            "scenario": self.name, "episodes": self.episodes, "steps": self.steps, "seconds": self.seconds,
            "steps_per_second": if !measured && self.name != "soak" { None } else { Some(self.rate()) },
            "p50_ms": if measured { Some(self.percentile(0.5) * 1e3) } else { None },
            "p99_ms": if measured { Some(self.percentile(0.99) * 1e3) } else { None },
            "note": self.note,
            "processes": self.process_percentiles.len().max(1),
            "client_cpu_seconds": self.client_cpu,
            "client_cpu_us_per_step": self.client_cpu.filter(|_| self.steps > 0).map(|c| c / self.steps as f64 * 1e6),
            "breakdown": self.breakdown.as_ref().map(Breakdown::to_json),
        })
    }
}

/// Episode scenes: test scenes of the served dataset, round robin.
async fn scenes(client: &Client, n: usize) -> anyhow::Result<Vec<String>> {
    let filter = SceneFilter { page_size: n.min(1000) as u32, ..SceneFilter::split(Split::Test) };
    let mut scenes = std::pin::pin!(client.scenes(filter));
    let mut ids = Vec::new();
    while ids.len() < n.min(1000)
        && let Some(scene) = tokio_stream::StreamExt::next(&mut scenes).await
    {
        ids.push(scene?.id);
    }
    if ids.is_empty() {
        bail!("the server has no test scenes");
    }
    Ok((0..n).map(|i| ids[i % ids.len()].clone()).collect())
}

async fn create(client: &Client, scene: &str) -> anyhow::Result<Episode> {
    Ok(client.create_episode(EpisodeOptions::scene(scene)).await?.0)
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
async fn unary(episodes: &mut Vec<Episode>, window: Window) -> anyhow::Result<(u64, Vec<f64>)> {
    let mut tasks = Vec::new();
    for (i, mut episode) in episodes.drain(..).enumerate() {
        tasks.push(tokio::spawn(async move {
            let mut actions = RandomActions::new(i as u64 + 1);
            let (mut steps, mut latencies) = (0u64, Vec::new());
            loop {
                let t = Instant::now();
                if t >= window.until {
                    break;
                }
                let r = episode.step(actions.next_action()).await?;
                if t >= window.measure_from {
                    steps += 1;
                    latencies.push(t.elapsed().as_secs_f64());
                }
                if r.ended() {
                    episode.reset().await?;
                }
            }
            anyhow::Ok(((steps, latencies), episode))
        }));
    }
    let (mut steps, mut latencies) = (0, Vec::new());
    for task in tasks {
        let ((s, l), episode) = task.await??;
        steps += s;
        latencies.extend(l);
        episodes.push(episode);
    }
    Ok((steps, latencies))
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
    let mut stream = client.episode_stream(window).await?;
    let mut actions = RandomActions::new(seed);
    // Answers come in request order: what each one answers, and when it was sent.
    let mut in_flight: VecDeque<(Instant, usize)> = VecDeque::with_capacity(episodes.len() * (window + 1));
    for _ in 0..window {
        for (e, id) in episodes.iter().enumerate() {
            in_flight.push_back((Instant::now(), e));
            stream.step(id, actions.next_action()).await?;
        }
    }
    let (mut steps, mut latencies) = (0u64, Vec::new());
    while let Some(answer) = stream.next().await? {
        let now = Instant::now();
        let (sent, e) = in_flight.pop_front().context("more answers than requests")?;
        let is_step = match answer.result {
            Ok(Answer::Step(r)) => {
                if sent >= measured.measure_from && now <= measured.until {
                    steps += 1;
                    latencies.push((now - sent).as_secs_f64());
                }
                if r.ended() && now < measured.until {
                    in_flight.push_back((Instant::now(), e));
                    stream.reset(&episodes[e])?;
                }
                true
            }
            Ok(Answer::Reset(_)) => false,
            Err(ClientError::EpisodeEnded(_)) => true,
            Err(error) => bail!("request {} failed: {error}", answer.request_id),
            Ok(other) => bail!("unexpected answer {other:?}"),
        };
        if is_step && now < measured.until {
            in_flight.push_back((Instant::now(), e));
            stream.step(&episodes[e], actions.next_action()).await?;
        }
    }
    Ok((steps, latencies))
}

/// Steps `episodes` with one StepBatch per wave.
async fn batch(client: &Client, episodes: &mut [Episode], window: Window) -> anyhow::Result<(u64, Vec<f64>)> {
    let mut actions = RandomActions::new(7);
    let (mut steps, mut latencies) = (0u64, Vec::new());
    loop {
        let t = Instant::now();
        if t >= window.until {
            break;
        }
        let request: Vec<(&Episode, Action)> = episodes.iter().map(|e| (e, actions.next_action())).collect();
        let responses: Vec<StepResult> = client.step_batch(&request).await?;
        if t >= window.measure_from {
            steps += episodes.len() as u64;
            latencies.extend(std::iter::repeat_n(t.elapsed().as_secs_f64(), episodes.len()));
        }
        for (e, r) in episodes.iter_mut().zip(&responses) {
            if r.ended() {
                e.reset().await?;
            }
        }
    }
    Ok((steps, latencies))
}

async fn close_all(episodes: Vec<Episode>) -> anyhow::Result<()> {
    for e in episodes {
        e.close().await?;
    }
    Ok(())
}

async fn scenario(
    name: &str,
    args: &Args,
    client: &Client,
    server: Option<&LocalServer>,
    metrics: Option<&str>,
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
            let steps: Vec<(&Episode, Action)> = chunk.iter().map(|e| (e, Action::TurnLeft)).collect();
            client.step_batch(&steps).await?;
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
        close_all(episodes).await?;
        return Ok(outcome);
    }
    let window = Window::new(args.seconds);
    // This process's CPU over the measured seconds, read when they start and end.
    let client_cpu = tokio::spawn(async move {
        tokio::time::sleep_until(window.measure_from.into()).await;
        let from = own_cpu_seconds();
        tokio::time::sleep_until(window.until.into()).await;
        Some(own_cpu_seconds()? - from?)
    });
    let ids: Vec<String> = episodes.iter().map(|e| e.id().to_owned()).collect();
    let before = metrics.map(breakdown::scrape).transpose()?;
    let (steps, latencies) = match name {
        "unary-1" | "unary-64" => unary(&mut episodes, window).await?,
        "stream-1" | "stream-mux-64" => stream(client, ids, 3, 1, window).await?,
        "stream-1-pipelined" => stream(client, ids, 5, args.window as usize, window).await?,
        "streams-64" => {
            let mut tasks = Vec::new();
            for (i, e) in ids.into_iter().enumerate() {
                let client = client.clone();
                let e = vec![e];
                tasks.push(tokio::spawn(async move { stream(&client, e, i as u64 + 11, 1, window).await }));
            }
            gather(tasks).await?
        }
        "batch-64" => batch(client, &mut episodes, window).await?,
        other => bail!("unknown scenario {other:?}"),
    };
    if let (Some(before), Some(url)) = (before, metrics) {
        outcome.breakdown = Some(Breakdown::between(&before, &breakdown::scrape(url)?));
    }
    outcome.steps = steps;
    outcome.seconds = args.seconds;
    outcome.latencies = latencies;
    outcome.client_cpu = client_cpu.await.ok().flatten();
    close_all(episodes).await?;
    Ok(outcome)
}

/// Runs scenario `name` in `args.processes` copies of this program at once against the server
/// at `address`, each with `--episodes` episodes, and sums them: their steps over the measured
/// seconds; the median of their p50 latencies and the worst of their p99s; the breakdown from
/// before they start to after they end (their creates and closes included).
fn in_processes(name: &str, args: &Args, addresses: &[String], metrics: Option<&str>) -> anyhow::Result<Outcome> {
    let exe = std::env::current_exe().context("this program's path")?;
    // Removed once the processes are done, whether they succeeded, failed or were stopped.
    let made = esrp_client::signals::RemovedOnExit::new(
        std::env::temp_dir().join(format!("esrp-bench-{}-{name}", std::process::id())),
    );
    let dir = made.path();
    std::fs::create_dir_all(dir)?;
    let before = metrics.map(breakdown::scrape).transpose()?;
    let mut children = Vec::new();
    for i in 0..args.processes {
        let json = dir.join(format!("{i}.json"));
        let mut command = std::process::Command::new(&exe);
        command
            .args(["--server", &addresses[i as usize % addresses.len()], "--scenarios", name])
            .args(["--seconds", &args.seconds.to_string(), "--episodes", &args.episodes.to_string()])
            .args(["--window", &args.window.to_string()])
            .args(["--client-threads", &child_threads(args.client_threads).to_string()])
            .arg("--json")
            .arg(&json)
            .arg("--stop-on-stdin-close")
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::null());
        if let Some(token) = &args.token {
            command.env("ESRP_TOKEN", token);
        }
        if let Some(ca) = &args.tls_ca {
            command.arg("--tls-ca").arg(ca);
        }
        if let Some(domain) = &args.tls_domain {
            command.args(["--tls-domain", domain]);
        }
        children.push((command.spawn().context("starting a client process")?, json));
    }
    // The children's stdin pipes, held until every child has ended (`Child::wait` would close a
    // child's own, which stops it): if this process ends first, they stop with it.
    let _pipes: Vec<_> = children.iter_mut().map(|(child, _)| child.stdin.take()).collect();
    let mut outcome =
        Outcome { name: name.to_owned(), seconds: args.seconds, client_cpu: Some(0.0), ..Default::default() };
    for (mut child, json) in children {
        let status = child.wait()?;
        if !status.success() {
            bail!("a client process of {name} failed ({status})");
        }
        let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json)?)?;
        let result = &report["results"][0];
        outcome.episodes += result["episodes"].as_u64().unwrap_or(0) as usize;
        outcome.steps += result["steps"].as_u64().unwrap_or(0);
        let ms = |key: &str| result[key].as_f64().map_or(f64::NAN, |v| v / 1e3);
        outcome.process_percentiles.push((ms("p50_ms"), ms("p99_ms")));
        // Known for all the processes, or not at all.
        outcome.client_cpu = outcome.client_cpu.zip(result["client_cpu_seconds"].as_f64()).map(|(a, b)| a + b);
    }
    drop(made);
    if let (Some(before), Some(url)) = (before, metrics) {
        outcome.breakdown = Some(Breakdown::between(&before, &breakdown::scrape(url)?));
    }
    outcome.note = format!("{} processes", args.processes);
    Ok(outcome)
}

/// The client's async runtime for a scenario: one thread for one episode (one agent process
/// with one connection; a multi-threaded runtime would add a thread hand-off to every step), and
/// for many, `threads` threads (`--client-threads`: 1 a current-thread runtime, 0 one per core).
fn runtime_for(scenario: &str, threads: u16) -> std::io::Result<tokio::runtime::Runtime> {
    if scenario.ends_with("-1") || scenario.ends_with("-1-pipelined") || threads == 1 {
        tokio::runtime::Builder::new_current_thread().enable_all().build()
    } else {
        let mut builder = tokio::runtime::Builder::new_multi_thread();
        if threads > 1 {
            builder.worker_threads(usize::from(threads));
        }
        builder.enable_all().build()
    }
}

/// The `--client-threads` of each client process that [`in_processes`] starts: the one given,
/// or for auto (0) one each.
fn child_threads(client_threads: u16) -> u16 {
    if client_threads == 0 { 1 } else { client_threads }
}

/// The claim timeout the soak's cleanup waits for: `--server-claim-timeout` for a server named by
/// `--server`; for a server started here, the one `--server-args` sets, or else
/// [`LOCAL_CLAIM_TIMEOUT`], added to `server_args`.
fn claim_timeout(args: &Args, server_args: &mut Vec<String>) -> anyhow::Result<u64> {
    let claim_flag = |a: &String| a.starts_with("--claim-timeout-seconds");
    Ok(match server_args.iter().position(claim_flag) {
        _ if args.server.is_some() => args.server_claim_timeout,
        Some(i) => {
            let value =
                server_args[i].split_once('=').map(|(_, v)| v.to_owned()).or_else(|| server_args.get(i + 1).cloned());
            value.and_then(|v| v.parse().ok()).context("--server-args --claim-timeout-seconds needs a number")?
        }
        None => {
            server_args.extend(["--claim-timeout-seconds".to_owned(), LOCAL_CLAIM_TIMEOUT.to_string()]);
            LOCAL_CLAIM_TIMEOUT
        }
    })
}

/// CPU seconds this process has used so far (user and system, all its threads), where it can
/// tell (Linux with glibc: `getrusage`).
#[allow(unsafe_code)] // Audited: one libc call that fills the struct it is given, see the SAFETY notes.
fn own_cpu_seconds() -> Option<f64> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
        // SAFETY: getrusage writes one `rusage` where the pointer points, which is one, and
        // touches nothing else.
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr()) } == 0 {
            // SAFETY: a `rusage` of plain integers, zeroed and then filled by getrusage.
            let usage = unsafe { usage.assume_init() };
            let seconds = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
            return Some(seconds(usage.ru_utime) + seconds(usage.ru_stime));
        }
    }
    None
}

/// This machine's CPU model (`/proc/cpuinfo`), or nothing where it cannot be read.
fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|c| {
            c.lines().find(|l| l.starts_with("model name")).map(|l| l.split(':').nth(1).unwrap_or("").trim().to_owned())
        })
        .unwrap_or_default()
}

fn main() -> std::process::ExitCode {
    esrp_client::signals::exit_status("esrp-bench", run())
}

fn run() -> anyhow::Result<()> {
    let args = Args::parse();
    if let Some(path) = &args.json {
        // Where the figures go is checked before the benchmark runs, not after.
        std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .with_context(|| format!("--json: cannot write {}", path.display()))?;
    }
    esrp_client::signals::exit_on_signals("esrp-bench")?;
    if args.stop_on_stdin_close {
        esrp_client::signals::exit_when_stdin_closes("esrp-bench")?;
    }
    esrp_client::malloc::keep_freed_memory();
    let mut server_args = args.server_args.clone();
    let claim_timeout = claim_timeout(&args, &mut server_args)?;
    if args.transport == Transport::Unix {
        if args.server.is_some() {
            bail!("--transport unix is for the server started here: name a server's socket as --server unix:PATH");
        }
        let path = esrp_client::local::socket_path();
        server_args.extend(["--listen-unix".to_owned(), path.display().to_string()]);
    }
    if args.breakdown && args.server.is_none() && !server_args.iter().any(|a| a.starts_with("--metrics-listen")) {
        server_args.extend(["--metrics-listen".to_owned(), "127.0.0.1:0".to_owned()]);
    }
    let named: Vec<String> =
        args.server.iter().flat_map(|s| s.split(',')).map(|s| s.trim().to_owned()).filter(|s| !s.is_empty()).collect();
    let mut tls = None;
    for server in named.iter().map(|s| Some(s.as_str())).chain(named.is_empty().then_some(None)) {
        tls = Tls::from_flags(server, args.tls_ca.as_deref(), args.tls_domain.as_deref())?;
    }
    if named.len() > 1 && args.processes < 2 {
        bail!("several servers need --processes (process i drives server i modulo their number)");
    }
    let (address, mut local) =
        reach_or_start(named.first().map(String::as_str), args.server_binary.clone(), &server_args)?;
    let addresses = if named.is_empty() { vec![address.clone()] } else { named };
    let metrics = match (&args.metrics, &local) {
        (Some(url), _) => Some(url.clone()),
        (None, Some(local)) => local.metrics.clone(),
        (None, None) => None,
    };
    if args.breakdown && metrics.is_none() {
        bail!("--breakdown needs the server's metrics: give --metrics URL with --server");
    }
    let metrics = metrics.filter(|_| args.breakdown);
    let connect = || Client::connect(&address).token_opt(args.token.as_deref()).tls_opt(tls.clone());
    let info = runtime_for("", args.client_threads)?
        .block_on(async { anyhow::Ok(esrp_client::local::first_contact(connect(), local.as_mut()).await?.1) })?;
    let cpus = std::thread::available_parallelism().map_or(0, |n| n.get());
    let cpu_model = cpu_model();
    println!(
        "esrp-bench against {address}: esrp-server {}, renderer {} ({}, {} rasterizer), dataset {}",
        info.version, info.renderer_adapter, info.renderer_backend, info.renderer_rasterizer, info.dataset
    );
    println!("client machine: {cpus} CPUs, {cpu_model}");
    if args.scenarios.iter().any(|name| name != "soak") {
        println!(
            "{:<20} {:>8} {:>9} {:>11} {:>9} {:>9}",
            "scenario", "episodes", "steps", "steps/s", "p50 ms", "p99 ms"
        );
    }
    let mut results = Vec::new();
    let mut soaks = Vec::new();
    for name in &args.scenarios {
        if name == "soak" {
            let settings = soak::Settings {
                address: address.clone(),
                token: args.token.clone(),
                tls: tls.clone(),
                minutes: args.minutes,
                clients: args.clients as usize,
                seed: args.seed,
                rss_growth_limit_percent: args.rss_growth_limit,
                claim_timeout: Duration::from_secs(claim_timeout),
            };
            let runtime = runtime_for(name, args.client_threads)?;
            let report = esrp_client::signals::block_on(&runtime, soak::run(settings, local.as_ref()))
                .context("scenario soak")?;
            report.print();
            results.push(Outcome {
                name: name.clone(),
                episodes: report.episodes() as usize,
                steps: report.steps(),
                seconds: report.seconds(),
                note: report.verdict(),
                ..Default::default()
            });
            soaks.push(report);
            continue;
        }
        let outcome = if args.processes > 1 && name != "memory-1000" {
            in_processes(name, &args, &addresses, metrics.as_deref())
        } else {
            let runtime = runtime_for(name, args.client_threads)?;
            esrp_client::signals::block_on(&runtime, async {
                scenario(name, &args, &connect().await?, local.as_ref(), metrics.as_deref()).await
            })
        }
        .with_context(|| format!("scenario {name}"))?;
        outcome.print_row();
        results.push(outcome);
    }
    if let Some(path) = &args.json {
        let report = serde_json::json!({
            "server": address, "renderer": info.renderer_adapter, "backend": info.renderer_backend,
            "rasterizer": info.renderer_rasterizer,
            "cpus": cpus, "cpu": cpu_model, "results": results.iter().map(Outcome::to_json).collect::<Vec<_>>(),
            "soak": soaks.iter().map(soak::Report::to_json).collect::<Vec<_>>(),
        });
        std::fs::write(path, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    let failed: Vec<String> = soaks.iter().filter(|r| !r.failures.is_empty()).map(soak::Report::verdict).collect();
    if !failed.is_empty() {
        bail!("soak {}", failed.join("; "));
    }
    Ok(())
}
