//! `esrp-eval`: runs an agent (the server's planner, the expert, or a random agent) over the
//! scenes of a split and writes one `esrp.results/v1` record per episode (docs/evaluation.md),
//! with a progress bar, resumption, and a summary with the paper's rows beside it.
//!
//! Without `--server` it starts an `esrp-server` (found as `LocalServer` finds one: `ESRP_SERVER_BIN`,
//! beside its own executable, on `PATH`, the workspace's `target/`) and reaches it over a Unix socket
//! (loopback TCP where the temporary folder is too deep for a socket's path).

mod agents;

use std::collections::HashSet;
use std::fs::OpenOptions;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};

use anyhow::{Context, bail};
use clap::Parser;
use clap::builder::TypedValueParser as _;
use esrp_client::results::{self, EpisodeRecord, SCHEMA, Summary, Tally};
use esrp_client::{
    Client, ClientError, Difficulty, LocalServer, SceneFilter, SceneSummary, Split, Tls, reach_or_start,
};
use futures_util::StreamExt as _;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use agents::{AgentKind, AgentSettings};

#[derive(Parser, Debug)]
#[command(
    name = "esrp-eval",
    version,
    about = "Run an agent over the scenes of a split; write one esrp.results/v1 record per episode",
    after_help = "The results schema and the summary are described in docs/evaluation.md."
)]
struct Args {
    /// The agent: the server's planner (ESRP-PLAN), the scene's expert trajectory, or uniform
    /// random actions.
    #[arg(long, value_enum)]
    agent: AgentKind,
    /// The split whose scenes to run.
    #[arg(long, value_enum, default_value_t = SplitArg::Test)]
    split: SplitArg,
    /// Only scenes of this difficulty.
    #[arg(long, value_enum)]
    difficulty: Option<DifficultyArg>,
    /// Only these scene ids (comma-separated), in this order, none twice (a scene is played, and
    /// resumed, once); they must be in the split.
    #[arg(long, value_delimiter = ',')]
    scenes: Vec<String>,
    /// At most this many scenes (after the filters): the first N of the chosen ones (dataset
    /// order, or the order `--scenes` names them in); at least 1.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..).map(|n| n as usize))]
    limit: Option<usize>,
    /// Episodes played at the same time.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=1024))]
    episodes_in_flight: u32,
    /// The results file (JSON Lines). Scenes already in it are skipped.
    #[arg(long)]
    out: PathBuf,
    /// Start the results file over instead of resuming it.
    #[arg(long)]
    fresh: bool,
    /// The summary's Markdown file (default: the results file with `.md`).
    #[arg(long)]
    summary: Option<PathBuf>,
    /// Base seed of seeded agents; scene `id` uses `seed XOR fnv1a64(id)`.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The planner's time budget per call, in milliseconds, 1 to 4294967295 (PlanActions'
    /// budget_ms; the server caps it at its --max-plan-ms, 60000 by default).
    #[arg(long, default_value_t = 60_000, value_parser = clap::value_parser!(u32).range(1..))]
    plan_budget_ms: u32,
    /// Planner calls after the first when an episode goes on after a plan.
    #[arg(long, default_value_t = 2)]
    replans: u32,
    /// A running server (`host:port`, `http://host:port`, `https://host:port`, or `unix:PATH`
    /// for one serving `--listen-unix`);
    /// without it, esrp-eval starts one and talks to it over a Unix domain socket.
    #[arg(long)]
    server: Option<String>,
    /// An argument for the server esrp-eval starts (repeat it for several).
    #[arg(long = "server-arg", allow_hyphen_values = true)]
    server_args: Vec<String>,
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
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum SplitArg {
    Train,
    Test,
    /// A challenge server's hidden split (`--challenge-seed`): one counted attempt per scene.
    Challenge,
    /// The challenge's minival split.
    Minival,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum DifficultyArg {
    Easy,
    Medium,
    Hard,
}

impl From<SplitArg> for Split {
    fn from(s: SplitArg) -> Self {
        match s {
            SplitArg::Train => Split::Train,
            SplitArg::Test => Split::Test,
            SplitArg::Challenge => Split::Challenge,
            SplitArg::Minival => Split::Minival,
        }
    }
}

impl From<DifficultyArg> for Difficulty {
    fn from(d: DifficultyArg) -> Self {
        match d {
            DifficultyArg::Easy => Difficulty::Easy,
            DifficultyArg::Medium => Difficulty::Medium,
            DifficultyArg::Hard => Difficulty::Hard,
        }
    }
}

/// What is wrong with `--scenes`, if anything: an empty id, or an id named more than once (as
/// `esrp eval --scenes` refuses them).
fn scenes_error(scenes: &[String]) -> Option<String> {
    if scenes.iter().any(|id| id.trim().is_empty()) {
        return Some("--scenes names an empty scene id: give scene ids, e.g. esrp-bench-v2/00000".into());
    }
    let mut seen = HashSet::new();
    let mut twice: Vec<&str> = scenes.iter().map(String::as_str).filter(|id| !seen.insert(*id)).collect();
    twice.sort_unstable();
    twice.dedup();
    (!twice.is_empty()).then(|| format!("--scenes lists {} more than once", twice.join(", ")))
}

/// The scenes to run, fixed up front: the split's (filtered), or the ones named, in order.
async fn pick_scenes(client: &Client, args: &Args) -> anyhow::Result<Vec<SceneSummary>> {
    let split = Split::from(args.split);
    let mut filter = SceneFilter { page_size: 1000, ..SceneFilter::split(split) };
    if let Some(d) = args.difficulty {
        filter = filter.difficulty(d.into());
    }
    let listed: Vec<SceneSummary> = tokio_stream::StreamExt::collect::<Result<_, _>>(client.scenes(filter)).await?;
    let mut scenes = if args.scenes.is_empty() {
        listed
    } else {
        let mut picked = Vec::new();
        for id in &args.scenes {
            match listed.iter().find(|s| &s.id == id) {
                Some(s) => picked.push(s.clone()),
                None => bail!(
                    "scene {id:?} is not among the {} scenes of this dataset (check --split and --difficulty)",
                    split.name()
                ),
            }
        }
        picked
    };
    if let Some(limit) = args.limit {
        scenes.truncate(limit);
    }
    if scenes.is_empty() {
        bail!("no scene matches: the {} split has none with these filters", split.name());
    }
    Ok(scenes)
}

/// Reads what an earlier run wrote (dropping a torn last line) and returns the scenes done.
/// Refuses a file of another run: another agent, other settings, privileged episodes of an agent
/// that plays none (Python's `esrp eval --privileged` marks them), and, for an agent that draws
/// random numbers (`seed`: the run's base seed), another base seed or another tool's records
/// (Python's random agent draws other actions from the same seed).
fn resume(
    path: &Path,
    agent: &str,
    config: &serde_json::Map<String, serde_json::Value>,
    privileged: bool,
    seed: Option<u64>,
) -> anyhow::Result<Vec<EpisodeRecord>> {
    if !path.exists() {
        return Ok(Vec::new());
    }
    let read = results::read_records(path)?;
    if read.torn_tail {
        eprintln!("{}: dropping a last line an interruption cut short", path.display());
        results::truncate_to(path, read.complete_bytes)
            .with_context(|| format!("cannot cut the torn last line of {}", path.display()))?;
    }
    if let Some(other) = read.records.iter().find(|r| r.agent != agent) {
        bail!(
            "{} holds results of agent {:?}, not {agent:?}: write to another --out, or pass --fresh to start it over",
            path.display(),
            other.agent
        );
    }
    // One file, one run: the same agent with other settings (a budget, a model) is another run.
    if let Some(other) = read.records.iter().find(|r| &r.agent_config != config) {
        bail!(
            "{} holds results of agent {agent:?} with other settings ({}, not {}): write to another --out, or pass --fresh to start it over",
            path.display(),
            serde_json::Value::Object(other.agent_config.clone()),
            serde_json::Value::Object(config.clone())
        );
    }
    let again = "write to another --out, or pass --fresh to start it over";
    if !privileged && let Some(other) = read.records.iter().find(|r| r.privileged == Some(true)) {
        bail!(
            "{} holds results of agent {agent:?} played privileged ({}), unlike this run: {again}",
            path.display(),
            other.client
        );
    }
    if let Some(seed) = seed {
        for r in &read.records {
            if tool(&r.client) != tool(CLIENT) {
                bail!(
                    "{} holds results of agent {agent:?} written by {}, whose random numbers differ from {}'s for the same seed: {again}",
                    path.display(),
                    r.client,
                    tool(CLIENT)
                );
            }
            let base = r.seed.map(|s| s ^ agents::fnv1a64(&r.scene_id));
            if base != Some(seed) {
                let played = base.map_or_else(|| "without a seed".to_owned(), |b| format!("with --seed {b}"));
                bail!("{} holds results of agent {agent:?} played {played}, not {seed}: {again}", path.display());
            }
        }
    }
    Ok(read.records)
}

/// The `client` of this tool's records.
const CLIENT: &str = concat!("esrp-eval ", env!("CARGO_PKG_VERSION"));

/// The tool of a record's `client`, without its version: `esrp-eval`, `esrp eval (Python)`.
fn tool(client: &str) -> &str {
    match client.rsplit_once(' ') {
        Some((name, version)) if version.starts_with(|c: char| c.is_ascii_digit()) => name,
        _ => client,
    }
}

fn now_rfc3339() -> String {
    humantime::format_rfc3339_seconds(SystemTime::now()).to_string()
}

fn progress_bar(total: u64, done: u64) -> ProgressBar {
    let bar = ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::stderr_with_hz(4));
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:32}] {pos}/{len} episodes, ETA {eta}  {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar.set_position(done);
    bar
}

fn running(tally: &Tally) -> String {
    if tally.episodes == 0 {
        return String::new();
    }
    format!("SR {:.1} %  OSR {:.1} %  RDR {:.3}", 100.0 * tally.sr(), 100.0 * tally.osr(), tally.rdr())
}

/// How long a run waits for a server that stopped answering before it stops.
const SERVER_RETRY: Duration = Duration::from_secs(10);

/// Why the run cannot go on after a call found the server unavailable: the local server exited,
/// or the server stayed unhealthy for [`SERVER_RETRY`]; `None` if it answers again.
async fn server_gone(
    client: &Client,
    address: &str,
    mut local: Option<&mut LocalServer>,
    episodes: usize,
) -> Option<String> {
    let exited = |local: &mut Option<&mut LocalServer>| {
        let status = local.as_mut()?.try_wait()?;
        Some(format!(
            "the local esrp-server {} after {episodes} episodes of this run (its stderr, above, may say why)",
            esrp_client::local::describe_exit(status)
        ))
    };
    if let Some(why) = exited(&mut local) {
        return Some(why);
    }
    if client.wait_healthy(SERVER_RETRY).await.is_ok() {
        return None;
    }
    exited(&mut local).or_else(|| {
        Some(format!(
            "the server at {address} has been unavailable for {} s after {episodes} episodes of this run",
            SERVER_RETRY.as_secs()
        ))
    })
}

fn main() -> std::process::ExitCode {
    esrp_client::signals::run_tool("esrp-eval", run())
}

async fn run() -> anyhow::Result<()> {
    let args = Args::parse();
    if let Some(error) = scenes_error(&args.scenes) {
        use clap::CommandFactory as _;
        Args::command().error(clap::error::ErrorKind::ValueValidation, error).exit();
    }
    summary_path(&args)?; // before a server is started or anything is played
    let tls = Tls::from_flags(args.server.as_deref(), args.tls_ca.as_deref(), args.tls_domain.as_deref())?;
    esrp_client::signals::exit_on_signals("esrp-eval")?;
    esrp_client::malloc::keep_freed_memory();
    let (address, mut local) =
        reach_or_start(args.server.as_deref(), None, &esrp_client::local::with_socket(&args.server_args))?;
    let connect = Client::connect(&address).token_opt(args.token.as_deref()).tls_opt(tls);
    let (client, info) = esrp_client::local::first_contact(connect, local.as_mut()).await?;
    eprintln!(
        "esrp-server {} at {address}: dataset {}, renderer {}",
        info.version, info.dataset, info.renderer_adapter
    );

    let scenes = pick_scenes(&client, &args).await?;
    let settings = AgentSettings {
        kind: args.agent,
        plan_budget: Some(Duration::from_millis(u64::from(args.plan_budget_ms))),
        replans: args.replans,
    };
    let recording = Recording {
        agent: args.agent.name(),
        config: settings.config(),
        seeded: settings.kind.seeded(),
        client: CLIENT.to_owned(),
        info: &info,
    };
    let (mut records, mut file) = open_results(&args, &settings, &recording.config)?;
    let out = args.out.clone();
    esrp_client::signals::say_when_stopped(move || {
        let kept = results::read_records(&out).ok()?.records.len();
        let episodes = if kept == 1 { "1 episode".to_owned() } else { format!("{kept} episodes") };
        Some(format!("{} keeps {episodes}: run the same command again to resume", out.display()))
    });
    let done: HashSet<String> = records.iter().map(|r| r.scene_id.clone()).collect();
    let todo: Vec<SceneSummary> = scenes.iter().filter(|s| !done.contains(&s.id)).cloned().collect();
    let wanted: HashSet<&str> = scenes.iter().map(|s| s.id.as_str()).collect();
    let earlier = records.iter().filter(|r| wanted.contains(r.scene_id.as_str())).count();
    if earlier > 0 {
        eprintln!("resuming {}: {earlier} of {} scenes already done", args.out.display(), scenes.len());
    }

    let mut tally = Tally::default();
    records.iter().filter(|r| wanted.contains(r.scene_id.as_str())).for_each(|r| tally.add(r));
    let bar = progress_bar(scenes.len() as u64, earlier as u64);
    let terminal = std::io::stderr().is_terminal();
    let every = (scenes.len() / 20).max(1);
    let started = Instant::now();

    let mut episodes = futures_util::stream::iter(todo.into_iter().map(|scene| {
        let client = client.clone();
        let settings = settings.clone();
        let seed = args.seed ^ agents::fnv1a64(&scene.id);
        async move {
            let clock = Instant::now();
            let played = agents::play(&client, &scene.id, &settings, seed).await;
            (scene, seed, clock.elapsed().as_secs_f64(), played)
        }
    }))
    .buffer_unordered(args.episodes_in_flight as usize);

    // The scenes whose episodes failed, each with whether the server refused it for good.
    let mut failed: Vec<(String, bool)> = Vec::new();
    let mut written = 0;
    while let Some((scene, seed, wall_seconds, played)) = episodes.next().await {
        let played = match played {
            Ok(p) => p,
            Err(e) => {
                let unavailable = e.chain().any(|c| matches!(c.downcast_ref(), Some(ClientError::Unavailable(_))));
                if unavailable && let Some(why) = server_gone(&client, &address, local.as_mut(), written).await {
                    bar.finish_and_clear();
                    bail!("{why}; re-run the same command to resume");
                }
                bar.suspend(|| eprintln!("{}: {e:#}", scene.id));
                let refused = e.chain().any(|c| c.downcast_ref::<ClientError>().is_some_and(ClientError::is_refusal));
                failed.push((scene.id, refused));
                bar.inc(1);
                continue;
            }
        };
        let record = recording.record(&scene, seed, wall_seconds, played);
        results::append_record(&mut file, &record).with_context(|| format!("cannot write {}", args.out.display()))?;
        written += 1;
        tally.add(&record);
        records.push(record);
        bar.inc(1);
        bar.set_message(running(&tally));
        if !terminal && (bar.position() as usize).is_multiple_of(every) {
            eprintln!("{}/{} episodes  {}", bar.position(), scenes.len(), running(&tally));
        }
    }
    bar.finish_and_clear();

    let mine: Vec<EpisodeRecord> = records.into_iter().filter(|r| wanted.contains(r.scene_id.as_str())).collect();
    write_summary(&args, &info, recording.agent, &mine, failed.len(), started)?;
    if !failed.is_empty() {
        bail!("{}", failures(&failed));
    }
    Ok(())
}

/// The closing message of a run whose episodes `failed` (each scene with whether the server
/// refused it for good): those a rerun may play, and those it would be refused again (the
/// reasons were printed as they came). The same words as `esrp eval`'s.
fn failures(failed: &[(String, bool)]) -> String {
    let ids = |refused: bool| {
        let mut ids: Vec<&str> = failed.iter().filter(|f| f.1 == refused).map(|f| f.0.as_str()).collect();
        ids.sort_unstable();
        ids
    };
    let (retry, refused) = (ids(false), ids(true));
    // The words agree with the count: "1 episode ... was ... it", "2 episodes ... were ... them".
    let (n, m) = (retry.len(), refused.len());
    let one = |n: usize, single: &'static str, plural: &'static str| if n == 1 { single } else { plural };
    let again = format!(
        "refused by the server and not recorded, as {} would be again: {}",
        one(m, "it", "they"),
        refused.join(", ")
    );
    let retry_text = format!(
        "{n} {} failed with an error and {} not recorded (rerun to retry {}): {}",
        one(n, "episode", "episodes"),
        one(n, "was", "were"),
        one(n, "it", "them"),
        retry.join(", ")
    );
    match (n, m) {
        (_, 0) => retry_text,
        (0, m) => format!("{m} {} {} {again}", one(m, "episode", "episodes"), one(m, "was", "were")),
        (_, m) => format!("{retry_text}; {m} more {} {again}", one(m, "was", "were")),
    }
}

/// The results file's records so far (the earlier run's, checked to be the same run's:
/// [`resume`]; none with `--fresh`, which removes the file), and the file open for appending,
/// its folder made.
fn open_results(
    args: &Args,
    settings: &AgentSettings,
    config: &serde_json::Map<String, serde_json::Value>,
) -> anyhow::Result<(Vec<EpisodeRecord>, std::fs::File)> {
    if args.fresh && args.out.exists() {
        std::fs::remove_file(&args.out).with_context(|| format!("cannot remove {}", args.out.display()))?;
    }
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let kind = settings.kind;
    let seed = kind.seeded().then_some(args.seed);
    let records = resume(&args.out, kind.name(), config, kind.privileged(), seed)?;
    let file = OpenOptions::new()
        .create(true)
        .append(true)
        .open(&args.out)
        .with_context(|| format!("cannot open {}", args.out.display()))?;
    Ok((records, file))
}

/// What every record of this run shares: the agent, its settings, the client and the server.
struct Recording<'a> {
    agent: &'static str,
    config: serde_json::Map<String, serde_json::Value>,
    /// Whether the agent draws from its seed (the record keeps the seed only then).
    seeded: bool,
    client: String,
    info: &'a esrp_client::ServerInfo,
}

impl Recording<'_> {
    /// The `esrp.results/v1` record of one played episode of `scene`.
    fn record(&self, scene: &SceneSummary, seed: u64, wall_seconds: f64, played: agents::Played) -> EpisodeRecord {
        let m = &played.metrics;
        EpisodeRecord {
            schema: SCHEMA.to_owned(),
            scene_id: scene.id.clone(),
            dataset: self.info.dataset.clone(),
            split: scene.split.map_or("unknown", Split::name).to_owned(),
            room_type: scene.room_type.clone(),
            difficulty: scene.difficulty.map_or("unknown", Difficulty::name).to_owned(),
            objects: scene.movable_objects,
            agent: self.agent.to_owned(),
            agent_config: self.config.clone(),
            seed: self.seeded.then_some(seed),
            success: m.success,
            osr: m.object_success_rate,
            rdr: m.remaining_distance_ratio,
            stage: m.stage,
            placed: m.placed,
            steps: m.steps,
            horizon: played.scene.horizon,
            end: played.end.to_owned(),
            total_reward: m.total_reward,
            actions: played.actions.iter().map(|a| a.code()).collect(),
            wall_seconds,
            agent_stats: played.stats,
            server_version: self.info.version.clone(),
            client: self.client.clone(),
            finished_at: now_rfc3339(),
            privileged: None,
            token: None,
            started_at: None,
            dataset_hash: None,
            counted: None,
            reward_weights: None,
            observations: None,
            signature: None,
        }
    }
}

/// Where the summary goes: `--summary`, else `--out` with `.md`; an error when that is the
/// results file itself (`--out run.md`, or `--summary` naming it): the summary would overwrite it.
fn summary_path(args: &Args) -> anyhow::Result<PathBuf> {
    let path = args.summary.clone().unwrap_or_else(|| args.out.with_extension("md"));
    let absolute = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    if absolute(&path) == absolute(&args.out) {
        bail!(
            "the summary would overwrite the results in {}: give --out a .jsonl file, or --summary another path",
            args.out.display()
        );
    }
    Ok(path)
}

/// Prints the run's summary (with how many of its episodes failed and were not recorded) and
/// writes it as markdown (`--summary`, else beside `--out`).
fn write_summary(
    args: &Args,
    info: &esrp_client::ServerInfo,
    agent: &str,
    records: &[EpisodeRecord],
    failed: usize,
    started: Instant,
) -> anyhow::Result<()> {
    let summary = Summary { agent: agent.to_owned(), ..Summary::of(records) };
    let more = if failed > 0 { format!(", {failed} more failed (not recorded)") } else { String::new() };
    println!(
        "{agent} on {} scenes of {}{more} ({:.0} s):",
        records.len(),
        info.dataset,
        started.elapsed().as_secs_f64()
    );
    print!("{}", summary.text());
    let summary_path = summary_path(args)?;
    let title = format!("{agent} on {} ({} split)", info.dataset, Split::from(args.split).name());
    let mut markdown = summary.markdown(&title);
    markdown.push_str(&format!(
        "\nWritten by esrp-eval {} against esrp-server {} ({} renderer) on {}; results in `{}`.\n",
        env!("CARGO_PKG_VERSION"),
        info.version,
        info.renderer_adapter,
        now_rfc3339(),
        args.out.file_name().map_or_else(|| args.out.display().to_string(), |n| n.to_string_lossy().into_owned())
    ));
    std::fs::write(&summary_path, markdown).with_context(|| format!("cannot write {}", summary_path.display()))?;
    println!("summary: {}", summary_path.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::failures;

    #[test]
    fn the_closing_message_tells_what_a_rerun_can_play() {
        let failed =
            |list: &[(&str, bool)]| list.iter().map(|&(id, refused)| (id.to_owned(), refused)).collect::<Vec<_>>();
        assert_eq!(
            failures(&failed(&[("b", false), ("a", false)])),
            "2 episodes failed with an error and were not recorded (rerun to retry them): a, b"
        );
        assert_eq!(
            failures(&failed(&[("c", true)])),
            "1 episode was refused by the server and not recorded, as it would be again: c"
        );
        assert_eq!(
            failures(&failed(&[("a", false), ("c", true)])),
            "1 episode failed with an error and was not recorded (rerun to retry it): a; 1 more was refused by the \
             server and not recorded, as it would be again: c"
        );
        assert_eq!(
            failures(&failed(&[("c", true), ("a", false), ("b", true)])),
            "1 episode failed with an error and was not recorded (rerun to retry it): a; 2 more were refused by \
             the server and not recorded, as they would be again: b, c"
        );
    }
}
