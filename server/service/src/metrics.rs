//! Prometheus metrics, served as text over HTTP at `/metrics` when `--metrics-listen` is set.
//!
//! | metric | type | what |
//! |---|---|---|
//! | `esrp_steps_total` | counter | steps taken, all episodes and APIs |
//! | `esrp_step_latency_seconds` | histogram | time from receiving a step (or a batch, counted once per step) to its response being ready, rendering included |
//! | `esrp_episodes_created_total` | counter | episodes created |
//! | `esrp_episodes_closed_total` | counter | episodes closed, by reason (`client`, `stream_ended`, `idle`, `unanswered`: a create abandoned before its answer was sent, `unclaimed`: no call named it within `--claim-timeout-seconds` of its create) |
//! | `esrp_live_episodes` | gauge | episodes alive now |
//! | `esrp_render_batch_views` | histogram | views per render batch |
//! | `esrp_render_batch_seconds` | histogram | time to render one batch |
//! | `esrp_render_views_reused_total` | counter | views answered from an episode's last images instead of rendered (steps that changed nothing they show) |
//! | `esrp_token_episodes_created_total` | counter | episodes created, by token name (`token`; `anonymous` without tokens) |
//! | `esrp_token_steps_total` | counter | steps taken, by the token that created the episode |
//! | `esrp_records_written_total` | counter | records written (`--records`), by token |
//! | `esrp_stage_seconds_total` | counter | seconds spent in each stage of stepping, by `stage` (below), summed over the threads that ran it |
//! | `esrp_render_threads` | gauge | the threads rendering batches (`--render-threads`) |
//! | `esrp_render_atlases_created_total` | counter | atlases (a batch's textures and buffers on the device) the renderers made; steady under a steady load once the pool holds the sizes it needs |
//! | `esrp_render_pipeline` | gauge | the batches each render thread may have in flight (`--render-pipeline`) |
//! | `esrp_render_timestamps` | gauge | 1 when the render devices time their drawing with timestamp queries (`--render-timestamps`: by default on a GPU, where the adapter has them), else 0 |
//! | `esrp_render_gpu_seconds_total` | counter | seconds the render devices spent drawing batches, by their own clocks: from the start of a batch's first pass to the end of its last (part of the `render_device` stage; stays 0 without timestamps) |
//! | `esrp_process_cpu_seconds_total` | counter | CPU seconds the server's process has used, all its threads (user and system; Linux: absent elsewhere) |
//! | `esrp_thread_cpu_seconds_total` | counter | the same by thread, summed by `threads`: a thread's name less a trailing number (`esrp-render` for `esrp-render-0`, `esrp-readback`, `esrp-runtime`: the async workers and the blocking pool, planning included; `esrp-generate`, `esrp-records`, the main thread `esrp-server`, and the graphics driver's own threads by their names, which Linux cuts to 15 characters). Read from `/proc/self/task` at each scrape; a thread that ended counts what it had used by the scrape before (Linux; absent elsewhere) |
//! | `esrp_plans_total` | counter | PlanActions calls, by outcome (`planned`, `cached`, `failed`: no plan found, `deadline`: none found in the budget, `busy`: the budget ran out waiting for a planner thread (`--planner-threads` all planning), `cancelled`: the client went away and the planner stopped) |
//!
//! The stages of `esrp_stage_seconds_total`, in the order a step goes through them (divide by
//! `esrp_steps_total` for the seconds per step, or by the wall time for how busy a stage keeps
//! its threads: `esrp-bench --breakdown` prints both):
//!
//! | stage | what |
//! |---|---|
//! | `lock` | waiting for the episodes' locks (another call of the same episode still stepping) |
//! | `take` | taking the steps: the simulation, the collision sweeps, the bookkeeping |
//! | `render_queue` | a view request waiting for a render thread, per request |
//! | `render_encode` | a render thread taking an atlas, writing the uniforms, encoding the passes |
//! | `render_submit` | a render thread submitting the encoded batch to the device and asking for its readback (the driver's work on that thread) |
//! | `render_device` | from a batch's submit until its readback is mapped: the device drawing and copying (and the batches submitted before it), and the wait for it; with `--render-pipeline` above one, batches in flight together each count their own. How much of it the device spent drawing is `esrp_render_gpu_seconds_total` |
//! | `render_extract` | cutting the views' images out of the mapped buffer (a render thread, or its readback thread with `--render-pipeline` above one) |
//! | `answer` | putting the rendered images into the answers |
//!
//! Decoding requests, encoding answers and the transport are tonic's and hyper's, not counted:
//! what is left of a step's latency is theirs.

use std::collections::{BTreeMap, HashMap};
use std::net::SocketAddr;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeLabelSet, EncodeMetric};
use prometheus_client::metrics::counter::{ConstCounter, Counter};
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use tokio::net::TcpListener;

/// A stage of stepping.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct StageLabel {
    /// Its name (the table of the module's docs).
    pub stage: &'static str,
}

/// Seconds spent in each stage of stepping (`esrp_stage_seconds_total{stage}`): one counter per
/// stage, held, so that adding to one is an atomic add, with no label lookup.
pub struct Stages {
    /// Waiting for the episodes' locks.
    pub lock: Counter<f64, AtomicU64>,
    /// Taking the steps.
    pub take: Counter<f64, AtomicU64>,
    /// A view request waiting for a render thread.
    pub render_queue: Counter<f64, AtomicU64>,
    /// Encoding a batch.
    pub render_encode: Counter<f64, AtomicU64>,
    /// Submitting a batch.
    pub render_submit: Counter<f64, AtomicU64>,
    /// Waiting for the device and the readback.
    pub render_device: Counter<f64, AtomicU64>,
    /// Extracting the views' images.
    pub render_extract: Counter<f64, AtomicU64>,
    /// Putting the images into the answers.
    pub answer: Counter<f64, AtomicU64>,
}

impl Stages {
    /// Adds `elapsed` to `stage`.
    pub fn add(stage: &Counter<f64, AtomicU64>, elapsed: Duration) {
        stage.inc_by(elapsed.as_secs_f64());
    }
}

/// Why an episode was closed.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct CloseReason {
    /// `client`, `stream_ended` or `idle`.
    pub reason: &'static str,
}

/// A token's name.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct TokenLabel {
    /// The token's name.
    pub token: String,
}

/// How a PlanActions call ended.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct PlanOutcome {
    /// `planned`, `cached`, `failed`, `deadline`, `busy` or `cancelled`.
    pub outcome: &'static str,
}

/// Every metric the server keeps. Cheap to update from any thread.
pub struct Metrics {
    registry: Registry,
    /// Steps taken.
    pub steps: Counter,
    /// Step latency, seconds.
    pub step_latency: Histogram,
    /// Episodes created.
    pub created: Counter,
    /// Episodes closed, by reason.
    pub closed: Family<CloseReason, Counter>,
    /// Live episodes (read from the registry at every scrape).
    pub live: Gauge,
    /// Views per render batch.
    pub batch_views: Histogram,
    /// Seconds per render batch.
    pub batch_seconds: Histogram,
    /// PlanActions answers, by outcome.
    pub plans: Family<PlanOutcome, Counter>,
    /// Views answered from an episode's last images instead of rendered.
    pub reused_views: Counter,
    /// Episodes created, by token.
    pub created_by_token: Family<TokenLabel, Counter>,
    /// Steps taken, by token.
    pub steps_by_token: Family<TokenLabel, Counter>,
    /// Records written, by token.
    pub records_by_token: Family<TokenLabel, Counter>,
    /// Seconds spent in each stage of stepping.
    pub stages: Stages,
    /// The threads rendering batches.
    pub render_threads: Gauge,
    /// The batches each render thread may have in flight.
    pub render_pipeline: Gauge,
    /// Atlases the renderers made.
    pub atlases_created: Counter,
    /// Whether the render devices time their drawing (1) or not (0).
    pub render_timestamps: Gauge,
    /// Seconds the render devices spent drawing, by their clocks.
    pub render_gpu_seconds: Counter<f64, AtomicU64>,
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    /// A fresh set of metrics, registered.
    pub fn new() -> Self {
        let steps = Counter::default();
        let step_latency = Histogram::new(exponential_buckets(50e-6, 2.0, 16));
        let created = Counter::default();
        let closed = Family::<CloseReason, Counter>::default();
        let live = Gauge::default();
        let batch_views = Histogram::new(exponential_buckets(1.0, 2.0, 11));
        let batch_seconds = Histogram::new(exponential_buckets(50e-6, 2.0, 16));
        let plans = Family::<PlanOutcome, Counter>::default();
        let reused_views = Counter::default();
        let mut registry = Registry::with_prefix("esrp");
        registry.register("steps", "Steps taken, all episodes and APIs", steps.clone());
        registry.register(
            "step_latency_seconds",
            "Time from receiving a step to its response being ready, rendering included",
            step_latency.clone(),
        );
        registry.register("episodes_created", "Episodes created", created.clone());
        registry.register("episodes_closed", "Episodes closed, by reason", closed.clone());
        registry.register("live_episodes", "Episodes alive now", live.clone());
        registry.register("render_batch_views", "Views per render batch", batch_views.clone());
        registry.register("render_batch_seconds", "Time to render one batch", batch_seconds.clone());
        registry.register("plans", "PlanActions answers, by outcome", plans.clone());
        registry.register(
            "render_views_reused",
            "Views answered from an episode's last images (the step changed nothing they show) instead of rendered",
            reused_views.clone(),
        );
        let created_by_token = Family::<TokenLabel, Counter>::default();
        let steps_by_token = Family::<TokenLabel, Counter>::default();
        let records_by_token = Family::<TokenLabel, Counter>::default();
        registry.register("token_episodes_created", "Episodes created, by token", created_by_token.clone());
        registry.register("token_steps", "Steps taken, by the token that created the episode", steps_by_token.clone());
        registry.register("records_written", "Records written (--records), by token", records_by_token.clone());
        let by_stage = Family::<StageLabel, Counter<f64, AtomicU64>>::default();
        // Each stage's counter made once and held: the family's entries share their counters.
        let stage = |name: &'static str| by_stage.get_or_create(&StageLabel { stage: name }).clone();
        let stages = Stages {
            lock: stage("lock"),
            take: stage("take"),
            render_queue: stage("render_queue"),
            render_encode: stage("render_encode"),
            render_submit: stage("render_submit"),
            render_device: stage("render_device"),
            render_extract: stage("render_extract"),
            answer: stage("answer"),
        };
        registry.register(
            "stage_seconds",
            "Seconds spent in each stage of stepping, summed over the threads that ran it",
            by_stage,
        );
        let render_threads = Gauge::default();
        registry.register("render_threads", "Threads rendering batches (--render-threads)", render_threads.clone());
        let atlases_created = Counter::default();
        registry.register(
            "render_atlases_created",
            "Atlases (a batch's textures and buffers on the device) the renderers made",
            atlases_created.clone(),
        );
        let render_pipeline = Gauge::default();
        registry.register(
            "render_pipeline",
            "Batches each render thread may have in flight (--render-pipeline)",
            render_pipeline.clone(),
        );
        let render_timestamps = Gauge::default();
        registry.register(
            "render_timestamps",
            "1 when the render devices time their drawing with timestamp queries, else 0",
            render_timestamps.clone(),
        );
        let render_gpu_seconds = Counter::<f64, AtomicU64>::default();
        registry.register(
            "render_gpu_seconds",
            "Seconds the render devices spent drawing batches, by their own clocks (part of the render_device stage)",
            render_gpu_seconds.clone(),
        );
        registry.register_collector(Box::new(ThreadCpu::default()));
        Self {
            registry,
            steps,
            step_latency,
            created,
            closed,
            live,
            batch_views,
            batch_seconds,
            plans,
            reused_views,
            created_by_token,
            steps_by_token,
            records_by_token,
            stages,
            render_threads,
            render_pipeline,
            atlases_created,
            render_timestamps,
            render_gpu_seconds,
        }
    }

    /// Counts an episode created by `token`.
    pub fn count_created_by(&self, token: &str) {
        self.created_by_token.get_or_create(&TokenLabel { token: token.to_owned() }).inc();
    }

    /// Counts `n` steps of episodes of `token`.
    pub fn count_steps_by(&self, token: &str, n: usize) {
        self.steps_by_token.get_or_create(&TokenLabel { token: token.to_owned() }).inc_by(n as u64);
    }

    /// Counts a record written for `token`.
    pub fn count_record(&self, token: &str) {
        self.records_by_token.get_or_create(&TokenLabel { token: token.to_owned() }).inc();
    }

    /// Counts `n` closed episodes.
    pub fn count_closed(&self, reason: &'static str, n: usize) {
        self.closed.get_or_create(&CloseReason { reason }).inc_by(n as u64);
    }

    /// Counts a PlanActions answer.
    pub fn count_plan(&self, outcome: &'static str) {
        self.plans.get_or_create(&PlanOutcome { outcome }).inc();
    }

    /// The OpenMetrics text exposition.
    pub fn encode(&self) -> String {
        let mut text = String::new();
        // Writing into a String cannot fail.
        let _ = prometheus_client::encoding::text::encode(&mut text, &self.registry);
        text
    }

    /// Records the time `steps` steps took together.
    pub fn observe_steps(&self, steps: usize, elapsed: Duration) {
        self.steps.inc_by(steps as u64);
        let seconds = elapsed.as_secs_f64();
        for _ in 0..steps {
            self.step_latency.observe(seconds);
        }
    }
}

/// A group of threads (`esrp_thread_cpu_seconds_total`'s label).
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ThreadsLabel {
    /// The threads' name, less a trailing number.
    threads: String,
}

/// `esrp_process_cpu_seconds_total` and `esrp_thread_cpu_seconds_total`, read from `/proc` at
/// each scrape (Linux; elsewhere neither is written).
#[derive(Debug, Default)]
struct ThreadCpu {
    seen: Mutex<SeenThreads>,
}

/// What [`ThreadCpu`] read at its last scrape.
#[derive(Debug, Default)]
struct SeenThreads {
    /// Each thread's group and CPU seconds, by thread id.
    live: HashMap<u32, (String, f64)>,
    /// The seconds of the threads that have ended since they were seen, by group.
    ended: BTreeMap<String, f64>,
}

impl SeenThreads {
    /// Takes in `now` (thread id, group, seconds, as read) and returns each group's seconds:
    /// its live threads' now, plus what its ended threads had used when last seen. A thread id
    /// seen before with another group or fewer seconds is a new thread that reused the id.
    fn update(&mut self, now: Vec<proc_cpu::ThreadSeconds>) -> BTreeMap<String, f64> {
        let mut live = HashMap::with_capacity(now.len());
        for (tid, group, seconds) in now {
            if let Some((old_group, old)) = self.live.remove(&tid)
                && (old_group != group || old > seconds)
            {
                *self.ended.entry(old_group).or_default() += old;
            }
            live.insert(tid, (group, seconds));
        }
        for (group, seconds) in std::mem::replace(&mut self.live, live).into_values() {
            *self.ended.entry(group).or_default() += seconds;
        }
        let mut groups = self.ended.clone();
        for (group, seconds) in self.live.values() {
            *groups.entry(group.clone()).or_default() += seconds;
        }
        groups
    }
}

impl Collector for ThreadCpu {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        // Read under the lock: two scrapes at once must take their readings in the order they
        // made them (an older reading after a newer would look like new threads).
        let mut seen = self.seen.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let Some((process, threads)) = proc_cpu::read() else { return Ok(()) };
        let groups = seen.update(threads);
        drop(seen);
        let total = ConstCounter::new(process);
        total.encode(encoder.encode_descriptor(
            "process_cpu_seconds",
            "CPU seconds the server's process has used (user and system, all threads)",
            None,
            total.metric_type(),
        )?)?;
        let mut family = encoder.encode_descriptor(
            "thread_cpu_seconds",
            "CPU seconds of the server's threads, by name less a trailing number",
            None,
            prometheus_client::metrics::MetricType::Counter,
        )?;
        for (threads, seconds) in groups {
            let label = ThreadsLabel { threads };
            ConstCounter::new(seconds).encode(family.encode_family(&label)?)?;
        }
        Ok(())
    }
}

/// The CPU time of this process and of each of its threads, from `/proc/self` (Linux).
mod proc_cpu {
    /// A live thread's id, group and CPU seconds.
    pub(super) type ThreadSeconds = (u32, String, f64);

    /// The process's CPU seconds, and each live thread's; `None` where `/proc/self` cannot be
    /// read (not Linux).
    pub(super) fn read() -> Option<(f64, Vec<ThreadSeconds>)> {
        let tick = ticks_per_second();
        let (_, process) = parse_stat(&std::fs::read_to_string("/proc/self/stat").ok()?, tick)?;
        let mut threads = Vec::new();
        for entry in std::fs::read_dir("/proc/self/task").ok()?.flatten() {
            let Some(tid) = entry.file_name().to_str().and_then(|t| t.parse().ok()) else { continue };
            // A thread that ended since the listing has no stat left to read.
            if let Some((name, seconds)) =
                std::fs::read_to_string(entry.path().join("stat")).ok().and_then(|text| parse_stat(&text, tick))
            {
                threads.push((tid, group(&name), seconds));
            }
        }
        Some((process, threads))
    }

    /// The command name and user + system CPU seconds of a `stat` line (`proc(5)`: fields 2, 14
    /// and 15; the name, in brackets, may itself hold spaces and brackets).
    pub(super) fn parse_stat(text: &str, ticks_per_second: f64) -> Option<(String, f64)> {
        let open = text.find('(')?;
        let close = text.rfind(')')?;
        let name = text.get(open + 1..close)?.to_owned();
        let fields: Vec<&str> = text.get(close + 1..)?.split_whitespace().collect();
        let ticks = |field: usize| fields.get(field - 3)?.parse::<u64>().ok();
        Some((name, (ticks(14)? + ticks(15)?) as f64 / ticks_per_second))
    }

    /// A thread's group: its name less a trailing number and the separator before it
    /// (`esrp-render-3` → `esrp-render`).
    pub(super) fn group(name: &str) -> String {
        let base = name.trim_end_matches(|c: char| c.is_ascii_digit());
        let base = if base.len() < name.len() { base.trim_end_matches(['-', '_', ':', '#', ' ', '.']) } else { base };
        if base.is_empty() { name.to_owned() } else { base.to_owned() }
    }

    /// The kernel's clock ticks per second (`USER_HZ`) that `stat`'s times count in.
    #[allow(unsafe_code)] // Audited: one libc call with no arguments, see the SAFETY note.
    fn ticks_per_second() -> f64 {
        #[cfg(target_os = "linux")]
        {
            // SAFETY: sysconf reads a system setting; it takes no pointers and changes nothing.
            let ticks = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
            if ticks > 0 {
                return ticks as f64;
            }
        }
        100.0
    }
}

/// Serves `GET /metrics` on `listener` until the task is dropped; `refresh` runs before each
/// scrape (to update gauges).
pub async fn serve(
    listener: TcpListener,
    metrics: Arc<Metrics>,
    refresh: impl Fn() + Clone + Send + Sync + 'static,
) -> std::io::Result<()> {
    use axum::http::header::CONTENT_TYPE;
    let address: SocketAddr = listener.local_addr()?;
    tracing::info!(%address, "serving Prometheus metrics at /metrics");
    let app = axum::Router::new().route(
        "/metrics",
        axum::routing::get(move || {
            let metrics = metrics.clone();
            let refresh = refresh.clone();
            async move {
                refresh();
                ([(CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], metrics.encode())
            }
        }),
    );
    axum::serve(listener, app).await
}

#[cfg(test)]
mod tests {
    use super::proc_cpu::{group, parse_stat};
    use super::*;

    #[test]
    fn a_stat_line_gives_its_name_and_seconds_whatever_the_name_holds() {
        let line = "4242 (odd) name (x) S 1 2 3 4 5 6 7 8 9 10 250 50 0 0 20 0 1 0 9 10 11";
        let (name, seconds) = parse_stat(line, 100.0).unwrap();
        assert_eq!(name, "odd) name (x");
        assert!((seconds - 3.0).abs() < 1e-12, "{seconds}");
        assert!(parse_stat("4242 (short) S 1 2", 100.0).is_none());
    }

    #[test]
    fn threads_are_grouped_by_name_less_a_trailing_number() {
        assert_eq!(group("esrp-render-0"), "esrp-render");
        assert_eq!(group("esrp-readback-12"), "esrp-readback");
        assert_eq!(group("llvmpipe-3"), "llvmpipe");
        assert_eq!(group("esrp-server"), "esrp-server");
        assert_eq!(group("tokio-runtime-w"), "tokio-runtime-w");
        assert_eq!(group("42"), "42");
        assert_eq!(group("gpu2"), "gpu");
    }

    #[test]
    fn an_ended_thread_keeps_counting_and_a_reused_id_is_a_new_thread() {
        let mut seen = SeenThreads::default();
        let row = |tid, group: &str, s| (tid, group.to_owned(), s);
        let groups = seen.update(vec![row(1, "a", 1.0), row(2, "b", 2.0), row(3, "b", 0.5)]);
        assert_eq!(groups, BTreeMap::from([("a".into(), 1.0), ("b".into(), 2.5)]));
        // Thread 2 ended; thread 3's id was reused by a new thread of group "a", and thread 1
        // went on working.
        let groups = seen.update(vec![row(1, "a", 1.5), row(3, "a", 0.25)]);
        assert_eq!(groups, BTreeMap::from([("a".into(), 1.75), ("b".into(), 2.5)]));
        // The same id again, with fewer seconds: another new thread.
        let groups = seen.update(vec![row(1, "a", 0.1)]);
        assert_eq!(groups, BTreeMap::from([("a".into(), 1.5 + 0.25 + 0.1), ("b".into(), 2.5)]));
    }

    /// The value of the metric line that starts with `prefix`.
    fn value(text: &str, prefix: &str) -> Option<f64> {
        text.lines().find_map(|l| l.strip_prefix(prefix)?.trim().parse().ok())
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn the_metrics_count_each_thread_groups_cpu_and_keep_an_ended_threads() {
        let metrics = Metrics::new();
        let busy = |name: &str| {
            std::thread::Builder::new()
                .name(name.to_owned())
                .spawn(|| {
                    let start = std::time::Instant::now();
                    let mut x = 0u64;
                    while start.elapsed() < Duration::from_millis(150) {
                        x = std::hint::black_box(x.wrapping_mul(31).wrapping_add(7));
                    }
                    x
                })
                .unwrap()
        };
        let worker = busy("esrp-cputest-7");
        // Seen while it runs, then counted after it ended.
        std::thread::sleep(Duration::from_millis(60));
        let during = metrics.encode();
        assert!(during.contains("# TYPE esrp_thread_cpu_seconds counter"), "{during}");
        let line = "esrp_thread_cpu_seconds_total{threads=\"esrp-cputest\"}";
        let seen = value(&during, line).unwrap_or_else(|| panic!("{during}"));
        worker.join().unwrap();
        let after = metrics.encode();
        let ended = value(&after, line).unwrap_or_else(|| panic!("{after}"));
        assert!(ended >= seen && ended > 0.0, "{seen} then {ended}");
        let process = value(&after, "esrp_process_cpu_seconds_total").unwrap_or_else(|| panic!("{after}"));
        assert!(process >= ended, "the process {process} s, one thread {ended} s");
    }
}
