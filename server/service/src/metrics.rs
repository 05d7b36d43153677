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

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::Duration;

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
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
