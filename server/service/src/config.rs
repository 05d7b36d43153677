//! Server configuration: command-line flags, each with an `ESRP_*` environment variable.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::builder::{BoolishValueParser, PossibleValuesParser, TypedValueParser};
use clap::{Parser, ValueEnum};
use esrp_dataset::BenchVersion;
use esrp_render::{BackendPreference, DepthBuffers, Rasterizer, Timestamps};

/// Log output format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line.
    Json,
}

/// Configuration of `esrp-server`.
#[derive(Clone, Debug, Parser)]
#[command(name = "esrp-server", version, about = "The ESRP environment server (gRPC)")]
pub struct Config {
    /// Address to listen on (port 0 picks a free port; the bound address is logged and printed).
    #[arg(long, env = "ESRP_LISTEN", default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,
    /// Serve gRPC on this Unix domain socket too, for clients on the same machine (`unix:PATH`):
    /// less kernel work per step than loopback TCP. A socket file left by a killed server is
    /// replaced; the file is removed at stop. Who may connect: the file's permissions (the
    /// umask's; with the usual 022, this user only), and --token as on TCP. Plain HTTP/2 only.
    #[arg(long, env = "ESRP_LISTEN_UNIX", conflicts_with = "tls_cert")]
    pub listen_unix: Option<PathBuf>,
    /// Serve this dataset folder (from `esrp-dataset generate` or `import-3dfront`) instead of
    /// the built-in benchmark.
    #[arg(long, env = "ESRP_DATASET")]
    pub dataset: Option<PathBuf>,
    /// The built-in benchmark: esrp-bench-v2 (the agent starts away from the objects) or
    /// esrp-bench-v1 (it starts within reach of the last object the generator put down; kept
    /// unchanged for published results). Not used with --dataset.
    #[arg(
        long,
        env = "ESRP_BENCHMARK",
        default_value_t = BenchVersion::default(),
        value_parser = PossibleValuesParser::new(BenchVersion::NAMES).try_map(|name| name.parse::<BenchVersion>()),
    )]
    pub benchmark: BenchVersion,
    /// Seed of the built-in benchmark (0 is the published one).
    #[arg(long, env = "ESRP_BENCH_SEED", default_value_t = 0)]
    pub bench_seed: u64,
    /// Where the built-in benchmark's scenes are kept once generated, shared by every server on
    /// the machine (default: $XDG_CACHE_HOME/esrp/scenes, else ~/.cache/esrp/scenes). Not used
    /// with --dataset or for the hidden splits.
    #[arg(long, env = "ESRP_SCENE_CACHE")]
    pub scene_cache: Option<PathBuf>,
    /// Generate every scene on first use, keeping none on disk.
    #[arg(long, env = "ESRP_NO_SCENE_CACHE", value_parser = BoolishValueParser::new())]
    pub no_scene_cache: bool,
    /// Do not generate the built-in benchmark's missing scenes ahead (a background thread at the
    /// lowest CPU priority, test split first, into the scene cache).
    #[arg(long, env = "ESRP_NO_GENERATE_AHEAD", value_parser = BoolishValueParser::new())]
    pub no_generate_ahead: bool,
    /// Most live episodes (at least 1); CreateEpisode beyond it fails with RESOURCE_EXHAUSTED.
    #[arg(long, env = "ESRP_MAX_EPISODES", default_value_t = 4096, value_parser = count_parser(1))]
    pub max_episodes: usize,
    /// Most steps and resets in one StepBatch (and requests in one wave of a stream), at least 1.
    #[arg(long, env = "ESRP_MAX_BATCH", default_value_t = 1024, value_parser = count_parser(1))]
    pub max_batch: usize,
    /// Largest gRPC message, bytes, either way (at least 65,536: a step's answer at 128 px is
    /// about 49 KB).
    #[arg(long, env = "ESRP_MAX_MESSAGE_BYTES", default_value_t = 64 * 1024 * 1024, value_parser = count_parser(65_536))]
    pub max_message_bytes: usize,
    /// Episodes untouched this long are closed, seconds (0: never). Episodes of an open
    /// StepStream are closed with their stream instead.
    #[arg(long, env = "ESRP_IDLE_TIMEOUT", default_value_t = 600)]
    pub idle_timeout_seconds: u64,
    /// Episodes that no call has named this long after their create are closed, seconds (0:
    /// never). A client that gave up on a CreateEpisode after the server sent its answer never
    /// learnt the episode's id, so no one else could close it. Any call naming the episode (Step,
    /// StepBatch, StepStream, Reset, GetGoal, GetMetrics, GetPrivilegedState, PlanActions,
    /// CloseEpisode) claims it for good; episodes created on a StepStream or a dm_env_rpc
    /// connection are claimed by it. The default of five minutes leaves an agent that thinks for
    /// minutes before its first step (a VLM waiting on its model) uncut.
    #[arg(long, env = "ESRP_CLAIM_TIMEOUT", default_value_t = 300)]
    pub claim_timeout_seconds: u64,
    /// Rendering backend: auto (a GPU through Vulkan; otherwise OpenGL, a GPU or Mesa's
    /// llvmpipe on the CPU, which measured faster than lavapipe; otherwise Vulkan's lavapipe),
    /// vulkan (Vulkan only) or gl (OpenGL through EGL only).
    #[arg(
        long,
        env = "ESRP_RENDER_BACKEND",
        default_value_t = BackendPreference::Auto,
        value_parser = PossibleValuesParser::new(BackendPreference::NAMES).try_map(|name| name.parse::<BackendPreference>()),
    )]
    pub render_backend: BackendPreference,
    /// What draws the views' triangles: pipeline (the graphics pipeline: the device's
    /// rasteriser and depth test) or compute (compute shaders: for GPUs with little
    /// fixed-function graphics hardware, such as the H100 and H200; the same images up to a
    /// few edge pixels, and each deterministic).
    #[arg(
        long,
        env = "ESRP_RENDER_RASTERIZER",
        default_value_t = Rasterizer::Pipeline,
        value_parser = PossibleValuesParser::new(Rasterizer::NAMES).try_map(|name| name.parse::<Rasterizer>()),
    )]
    pub render_rasterizer: Rasterizer,
    /// Threads rendering batches (0: auto, one per render device: more measured slower both on
    /// llvmpipe, which rasterises one scene at a time per process, and on an NVIDIA GPU, where
    /// the threads take turns at the device). Each gathers the views that arrived while it was
    /// busy and renders them as one batch; with several, one may encode and extract while
    /// another waits for the device.
    #[arg(long, env = "ESRP_RENDER_THREADS", default_value_t = 0, value_parser = clap::value_parser!(u16).range(0..=64))]
    pub render_threads: u16,
    /// Render devices to open on the adapter (0: auto, one), each with its own queue and a copy
    /// of every scene's geometry; the render threads are spread over them (at least one each).
    /// Several devices render batches at once where one device's queue runs them in turn.
    #[arg(long, env = "ESRP_RENDER_DEVICES", default_value_t = 0, value_parser = clap::value_parser!(u16).range(0..=16))]
    pub render_devices: u16,
    /// Batches each render thread may have in flight, submitted to the device and not yet read
    /// back (0: auto, one). With more than one, a readback thread beside each render thread waits
    /// for the device and extracts the images while the render thread gathers, encodes and
    /// submits the next batch: the device draws one batch while the next is encoded.
    #[arg(long, env = "ESRP_RENDER_PIPELINE", default_value_t = 0, value_parser = clap::value_parser!(u16).range(0..=8))]
    pub render_pipeline: u16,
    /// Whether to time the render devices' drawing: each batch then carries two timestamp
    /// queries (the device's clock at the start and the end of its drawing), read back with its
    /// images, so that the metrics tell the device's drawing from the rest of the wait for it
    /// (`esrp_render_gpu_seconds_total`, `esrp-bench --breakdown`). auto: on a GPU, not on a CPU
    /// renderer (whose drawing is the render thread's own time, and where lavapipe's timestamps
    /// cost about 70 µs a batch); on, off. Never where the adapter lacks timestamp queries.
    #[arg(
        long,
        env = "ESRP_RENDER_TIMESTAMPS",
        default_value_t = Timestamps::Auto,
        value_parser = PossibleValuesParser::new(Timestamps::NAMES).try_map(|name| name.parse::<Timestamps>()),
    )]
    pub render_timestamps: Timestamps,
    /// The depth buffers of the graphics pipeline's passes (one pass per view): shared (one
    /// buffer every pass clears in turn: the least memory, and on a CPU renderer a buffer that
    /// stays in cache; on a GPU each pass waits for the one before it) or per-page (a buffer per
    /// view, 4 bytes a pixel more: a GPU may draw a batch's views at once). The same images
    /// either way.
    #[arg(
        long,
        env = "ESRP_RENDER_DEPTH_BUFFERS",
        default_value_t = DepthBuffers::Shared,
        value_parser = PossibleValuesParser::new(DepthBuffers::NAMES).try_map(|name| name.parse::<DepthBuffers>()),
    )]
    pub render_depth_buffers: DepthBuffers,
    /// Require `authorization: Bearer TOKEN` on every call (not empty: an empty `ESRP_TOKEN`
    /// is refused rather than taken as "no token" or as a token anyone could send). The one
    /// token is an admin named `admin`; --tokens gives several, with roles and quotas.
    #[arg(long, env = "ESRP_TOKEN", hide_env_values = true, value_parser = non_empty_token, conflicts_with = "tokens")]
    pub token: Option<String>,
    /// A token file (TOML): one `[[token]]` table per client with `name`, `secret` or
    /// `secret_sha256`, `role` (`agent`: ordinary episodes only; `trainer`: also privileged
    /// episodes and the planner, never on the challenge; `admin`: everything) and the quotas
    /// `max_episodes` and `max_streams` (docs/challenge.md).
    #[arg(long, env = "ESRP_TOKENS")]
    pub tokens: Option<PathBuf>,
    /// Serve a hidden challenge split generated from this secret (at least 16 characters: it
    /// must not be guessable) by the current benchmark's rules: `--challenge-scenes` scenes of
    /// the test split's distribution, and `--minival-scenes` more in the split `minival`.
    #[arg(long, env = "ESRP_CHALLENGE_SEED", hide_env_values = true, value_parser = ChallengeSecret)]
    pub challenge_seed: Option<String>,
    /// Scenes of the challenge split.
    #[arg(long, env = "ESRP_CHALLENGE_SCENES", default_value_t = 550, value_parser = clap::value_parser!(u32).range(1..=5000))]
    pub challenge_scenes: u32,
    /// Scenes of the minival split (0: none).
    #[arg(long, env = "ESRP_MINIVAL_SCENES", default_value_t = 50, value_parser = clap::value_parser!(u32).range(0..=495))]
    pub minival_scenes: u32,
    /// What episodes on challenge scenes serve tokens other than admins: `paper`, the paper's
    /// observation only (ego and goal images at 128 px and the grasp flag: no reward, reward
    /// terms, placed count, collision, optional sensor, other resolution, reward weights or
    /// metrics before the end), or `full`, what any other scene serves (docs/challenge.md).
    #[arg(long, env = "ESRP_CHALLENGE_OBSERVATIONS", value_enum, default_value_t = Observations::Paper)]
    pub challenge_observations: Observations,
    /// The same for minival scenes.
    #[arg(long, env = "ESRP_MINIVAL_OBSERVATIONS", value_enum, default_value_t = Observations::Paper)]
    pub minival_observations: Observations,
    /// Record episodes in this folder, as esrp.results/v1 lines appended to `DIR/<token>.jsonl`,
    /// each written and synced when its episode ends (see --record).
    #[arg(long, env = "ESRP_RECORDS")]
    pub records: Option<PathBuf>,
    /// The key the server signs its records with (HMAC-SHA256; the file's bytes, at least 16,
    /// e.g. `openssl rand -hex 32`). Default: `DIR/records.key` in the records folder, generated
    /// if missing. Keep it from the participants: with it, `esrp verify --key` tells the
    /// server's records from any other.
    #[arg(long, env = "ESRP_RECORDS_KEY", requires = "records")]
    pub records_key: Option<PathBuf>,
    /// Which episodes --records records: those on the challenge split, or all.
    #[arg(long, env = "ESRP_RECORD", value_enum, default_value_t = crate::records::RecordMode::Challenge, requires = "records")]
    pub record: crate::records::RecordMode,
    /// TLS certificate chain (PEM); needs --tls-key.
    #[arg(long, env = "ESRP_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM); needs --tls-cert.
    #[arg(long, env = "ESRP_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Serve Prometheus metrics over HTTP at `http://ADDR/metrics` (off unless set; port 0
    /// picks a free port, printed at start).
    #[arg(long, env = "ESRP_METRICS_LISTEN")]
    pub metrics_listen: Option<SocketAddr>,
    /// Serve the web viewer at `http://ADDR/` (off unless set; port 0 picks a free port, printed
    /// at start): watch live episodes, play one from the keyboard. Without --token or --tokens
    /// only a loopback address (e.g. 127.0.0.1:8080) is accepted.
    #[arg(long, env = "ESRP_HTTP_LISTEN")]
    pub http_listen: Option<SocketAddr>,
    /// Threads of the async runtime (gRPC, episode bookkeeping); 0: one per core but one, which
    /// leaves a core to the render thread (on 2 cores, one runtime thread measured 5-15 % more
    /// steps/s with 64 episodes than two).
    #[arg(long, env = "ESRP_WORKER_THREADS", default_value_t = 0, value_parser = thread_count_parser())]
    pub worker_threads: usize,
    /// PlanActions: the planning time budget of a call that names none, in milliseconds.
    #[arg(long, env = "ESRP_PLAN_BUDGET_MS", default_value_t = 10_000, value_parser = clap::value_parser!(u64).range(1..))]
    pub plan_budget_ms: u64,
    /// PlanActions: the most planning time a call may ask for, in milliseconds.
    #[arg(long, env = "ESRP_MAX_PLAN_MS", default_value_t = 60_000, value_parser = clap::value_parser!(u64).range(1..))]
    pub max_plan_ms: u64,
    /// Shutdown: how long, after SIGTERM/SIGINT/SIGHUP, calls in flight and open streams may take to
    /// finish, in milliseconds; then the server stops anyway (clients still connected see their
    /// calls fail with UNAVAILABLE) and exits 0.
    #[arg(long, env = "ESRP_SHUTDOWN_GRACE_MS", default_value_t = 5_000)]
    pub shutdown_grace_ms: u64,
    /// Shutdown: also stop, as on SIGTERM, when standard input reaches its end. A parent that
    /// starts the server with a pipe on its stdin (the Rust and Python `LocalServer`s do) takes it
    /// down with it however the parent ends, SIGKILL included: the kernel closes the pipe.
    #[arg(long, env = "ESRP_STOP_ON_STDIN_CLOSE", value_parser = BoolishValueParser::new())]
    pub stop_on_stdin_close: bool,
    /// PlanActions: plans computed at once (each on a thread of its own), up to 1,024; 0: one per
    /// core.
    #[arg(long, env = "ESRP_PLANNER_THREADS", default_value_t = 0, value_parser = thread_count_parser())]
    pub planner_threads: usize,
    /// Log format.
    #[arg(long, env = "ESRP_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,
}

/// A count from `least` to `u32::MAX` (what `ServerInfo` can report), as a `usize` setting.
fn count_parser(least: u64) -> impl clap::builder::TypedValueParser<Value = usize> {
    clap::value_parser!(u64).range(least..=u64::from(u32::MAX)).map(|v| v as usize)
}

/// A thread count from 0 (auto) to 1,024, as a `usize` setting.
fn thread_count_parser() -> impl clap::builder::TypedValueParser<Value = usize> {
    clap::value_parser!(u64).range(0..=1024).map(|v| v as usize)
}

impl Config {
    /// The runtime's thread count: `worker_threads`, or for 0 the cores less one (at least 1).
    pub fn worker_threads(&self) -> usize {
        match self.worker_threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()).saturating_sub(1).max(1),
            n => n,
        }
    }

    /// Plans computed at once: `planner_threads`, or for 0 one per core.
    pub fn planner_threads(&self) -> usize {
        match self.planner_threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n,
        }
    }

    /// The default planning budget of a PlanActions call.
    pub fn plan_budget(&self) -> Duration {
        Duration::from_millis(self.plan_budget_ms)
    }

    /// The largest planning budget a PlanActions call gets.
    pub fn max_plan(&self) -> Duration {
        Duration::from_millis(self.max_plan_ms)
    }

    /// The shutdown grace as a duration.
    pub fn shutdown_grace(&self) -> Duration {
        Duration::from_millis(self.shutdown_grace_ms)
    }

    /// The idle timeout as a duration.
    pub fn idle_timeout(&self) -> Duration {
        Duration::from_secs(self.idle_timeout_seconds)
    }

    /// The claim timeout as a duration.
    pub fn claim_timeout(&self) -> Duration {
        Duration::from_secs(self.claim_timeout_seconds)
    }

    /// A configuration with every default, listening on `listen` (tests, embedding).
    pub fn with_listen(listen: SocketAddr) -> Self {
        let mut config = Config::parse_from(["esrp-server"]);
        config.listen = listen;
        config
    }
}

/// What episodes on a hidden split serve (`--challenge-observations`, `--minival-observations`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Observations {
    /// The paper's observation only: the ego and goal images at 128 px and the grasp flag.
    Paper,
    /// Everything an episode on any other split serves.
    Full,
}

impl Observations {
    /// `paper` or `full`.
    pub fn as_str(self) -> &'static str {
        match self {
            Observations::Paper => "paper",
            Observations::Full => "full",
        }
    }
}

/// `--challenge-seed`'s value: at least 16 characters, so that no one can guess it from the
/// hash the records carry.
/// `--challenge-seed`'s parser: at least 16 characters. Its refusal does not quote the value, as
/// clap's errors do: the seed is a secret, and a refused one may be a typo of the real one.
#[derive(Clone, Copy, Debug)]
struct ChallengeSecret;

impl clap::builder::TypedValueParser for ChallengeSecret {
    type Value = String;

    fn parse_ref(
        &self,
        cmd: &clap::Command,
        _arg: Option<&clap::Arg>,
        value: &std::ffi::OsStr,
    ) -> Result<String, clap::Error> {
        let refuse = |why: &str| {
            clap::Error::raw(
                clap::error::ErrorKind::InvalidValue,
                format!("--challenge-seed (ESRP_CHALLENGE_SEED): {why} (the value is a secret: it is not shown)\n"),
            )
            .with_cmd(cmd)
        };
        let value = value.to_str().ok_or_else(|| refuse("not UTF-8"))?;
        if value.trim().chars().count() < 16 {
            return Err(refuse("give at least 16 characters, e.g. `openssl rand -hex 16`"));
        }
        Ok(value.to_owned())
    }
}

/// `--token`'s value: anything but an empty or blank string.
fn non_empty_token(value: &str) -> Result<String, String> {
    if value.trim().is_empty() {
        return Err("the token is empty: give a non-empty token, or unset ESRP_TOKEN (and drop --token) to serve \
                    without one"
            .to_owned());
    }
    Ok(value.to_owned())
}

/// `error`, clap's refusal of the command line `args` of `command`, with a tip that names the
/// environment variable the refused value came from, when it came from one: clap's message names
/// only the flag (`--max-episodes`), which a value set by `ESRP_MAX_EPISODES` in a container's
/// environment does not show.
pub fn tell_the_variable(mut error: clap::Error, command: &clap::Command, args: &[std::ffi::OsString]) -> clap::Error {
    use clap::error::{ContextKind, ContextValue};
    let Some(ContextValue::String(refused)) = error.get(ContextKind::InvalidArg) else { return error };
    let Some(long) = refused.split_whitespace().next().and_then(|flag| flag.strip_prefix("--")).map(str::to_owned)
    else {
        return error;
    };
    let flag = format!("--{long}");
    let given = args.iter().filter_map(|a| a.to_str()).any(|a| a == flag || a.starts_with(&format!("{flag}=")));
    let mut arguments = command.get_arguments().chain(command.get_subcommands().flat_map(|c| c.get_arguments()));
    let variable = arguments.find(|arg| arg.get_long() == Some(long.as_str())).and_then(|arg| arg.get_env());
    if let Some(variable) = variable
        && !given
        && std::env::var_os(variable).is_some()
    {
        let tip = format!("this value comes from the environment variable {}", variable.to_string_lossy());
        error.insert(ContextKind::Suggested, ContextValue::StyledStrs(vec![tip.into()]));
    }
    error
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_render_backend_flag_takes_the_renderer_s_names() {
        let parse = |args: &[&str]| Config::try_parse_from([&["esrp-server"], args].concat());
        assert_eq!(parse(&[]).unwrap().render_backend, BackendPreference::Auto);
        for (name, backend) in [("vulkan", BackendPreference::Vulkan), ("gl", BackendPreference::Gl)] {
            assert_eq!(parse(&["--render-backend", name]).unwrap().render_backend, backend);
        }
        let error = parse(&["--render-backend", "metal"]).unwrap_err().to_string();
        assert!(error.contains("auto, vulkan, gl"), "{error}");
        assert_eq!(parse(&[]).unwrap().render_rasterizer, Rasterizer::Pipeline);
        assert_eq!(parse(&["--render-rasterizer", "compute"]).unwrap().render_rasterizer, Rasterizer::Compute);
        let error = parse(&["--render-rasterizer", "ray"]).unwrap_err().to_string();
        assert!(error.contains("pipeline, compute"), "{error}");
        assert_eq!(parse(&[]).unwrap().render_timestamps, Timestamps::Auto);
        for (name, timestamps) in [("on", Timestamps::On), ("off", Timestamps::Off), ("auto", Timestamps::Auto)] {
            assert_eq!(parse(&["--render-timestamps", name]).unwrap().render_timestamps, timestamps);
        }
        let error = parse(&["--render-timestamps", "yes"]).unwrap_err().to_string();
        assert!(error.contains("auto, on, off"), "{error}");
        assert_eq!(parse(&[]).unwrap().render_depth_buffers, DepthBuffers::Shared);
        let per_page = parse(&["--render-depth-buffers", "per-page"]).unwrap().render_depth_buffers;
        assert_eq!(per_page, DepthBuffers::PerPage);
        let error = parse(&["--render-depth-buffers", "many"]).unwrap_err().to_string();
        assert!(error.contains("shared, per-page"), "{error}");
    }

    #[test]
    fn render_threads_default_to_auto_and_stay_within_reason() {
        let parse = |args: &[&str]| Config::try_parse_from([&["esrp-server"], args].concat());
        assert_eq!(parse(&[]).unwrap().render_threads, 0);
        assert_eq!(parse(&["--render-threads", "4"]).unwrap().render_threads, 4);
        assert!(parse(&["--render-threads", "65"]).is_err());
        assert!(parse(&["--render-threads", "-1"]).is_err());
        assert_eq!(parse(&[]).unwrap().render_devices, 0);
        assert_eq!(parse(&["--render-devices", "2"]).unwrap().render_devices, 2);
        assert!(parse(&["--render-devices", "17"]).is_err());
        assert_eq!(parse(&[]).unwrap().render_pipeline, 0);
        assert_eq!(parse(&["--render-pipeline", "3"]).unwrap().render_pipeline, 3);
        assert!(parse(&["--render-pipeline", "9"]).is_err());
    }

    #[test]
    fn an_empty_token_is_refused() {
        let parse = |args: &[&str]| Config::try_parse_from([&["esrp-server"], args].concat());
        assert_eq!(parse(&[]).unwrap().token, None);
        assert_eq!(parse(&["--token", "s3cret"]).unwrap().token.as_deref(), Some("s3cret"));
        for empty in ["", "  "] {
            let error = parse(&["--token", empty]).unwrap_err().to_string();
            assert!(error.contains("the token is empty") && error.contains("unset ESRP_TOKEN"), "{error}");
        }
    }

    #[test]
    fn challenge_and_records_flags_are_checked() {
        let parse = |args: &[&str]| Config::try_parse_from([&["esrp-server"], args].concat());
        let config = parse(&[]).unwrap();
        assert_eq!((config.challenge_seed, config.challenge_scenes, config.minival_scenes), (None, 550, 50));
        assert_eq!(config.record, crate::records::RecordMode::Challenge);
        let short = parse(&["--challenge-seed", "secret-1234"]).unwrap_err().to_string();
        assert!(short.contains("--challenge-seed (ESRP_CHALLENGE_SEED): give at least 16 characters"), "{short}");
        assert!(!short.contains("secret-1234"), "the refusal quotes the secret: {short}");
        assert!(parse(&["--challenge-seed", "0123456789abcdef"]).is_ok());
        let both = parse(&["--token", "a", "--tokens", "t.toml"]).unwrap_err().to_string();
        assert!(both.contains("cannot be used with"), "{both}");
        let alone = parse(&["--record", "all"]).unwrap_err().to_string();
        assert!(alone.contains("--records"), "{alone}");
        assert!(parse(&["--records", "r", "--record", "all"]).is_ok());
        assert!(parse(&["--challenge-scenes", "0"]).is_err());
    }
}
