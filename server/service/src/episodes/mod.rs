//! The episode layer: [`Episodes`] owns the scenes, the live episodes and the render
//! scheduler, and answers calls on episodes in the service's own types ([`crate::types`]:
//! [`EpisodeId`], [`Observation`] with images as `Bytes`, [`StepResult`], ...).
//!
//! **API Boundary**: nothing here knows a protocol. The `esrp.v1` adapter
//! ([`crate::esrp_v1`]) and the `dm_env_rpc.v1` adapter ([`crate::dm_env`]) convert their
//! messages into these types at their edges and back; both get the same rules, rendering and
//! limits because both call the same methods, all listed in the one `impl Episodes` below.
//!
//! - `state`: the fields of [`Episodes`] and the helpers every job uses.
//! - `entry`: one live episode ([`EpisodeEntry`]) and the checks a call makes before it moves.
//! - `observe`: which views an observation needs, the episode's last frames, and the images
//!   put into the observation: one path for creates, resets and steps.
//! - `lifecycle`: create, reset, goal, privileged state, metrics, close.
//! - `stepping`: Step and StepBatch (all or nothing, a batch's resets too) and the steps of a
//!   stream wave (each on its own), rendered as one job.
//! - [`waves`]: which stream requests may be answered together, and answering them.
//! - `planning` and `plan_cache`: PlanActions, the server's planner on an episode's current
//!   state, off the runtime, its answer kept with the episode.
//! - `access`: what each token role may do, asked before a call moves anything (which token
//!   may name which episode is the registry's check, and each token's quotas too).
//! - `viewing`: what the web viewer sees: the live episodes a caller may see, and frames of a
//!   watched one, made only while someone watches.
//! - `recording`: the runs the server records (`--records`) or counts (the challenge's one
//!   attempt per scene and token), ended into `esrp.results/v1` records whatever ends them.
//!
//! Every method that acts for a client takes its [`Caller`]: the token's name, role and quotas.

mod access;
mod entry;
mod lifecycle;
mod observe;
mod plan_cache;
mod planning;
mod recording;
mod state;
mod stepping;
mod viewing;
pub mod waves;

use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::Duration;

pub use entry::{EpisodeEntry, Trail};
pub use lifecycle::Unanswered;
pub use state::{Episodes, MAX_RESOLUTION};
pub use stepping::Stepped;
pub use viewing::{EpisodeSummary, ObjectView, PrivilegedView, WATCH_TOP_DOWN, WatchFrame};
pub use waves::StreamSlot;

use crate::config::Config;
use crate::error::ServiceError;
use crate::metrics::Metrics;
use crate::records::{Attempts, Recorder};
use crate::registry::Registry;
use crate::render::RenderScheduler;
use crate::scenes::SceneStore;
use crate::types::{
    Caller, CreateOptions, Created, EpisodeId, Goal, MetricsSoFar, PlanCall, Planned, Privileged, ResetCall,
    ResetResult, SceneChoice, StepCall, StepResult,
};

/// Everything the adapters may ask of the episode layer.
impl Episodes {
    /// The episode layer of a server with `config`, serving `store` and rendering with `render`,
    /// recording with `recorder` (if any) and counting challenge attempts in `attempts` (those
    /// the recorder read back, at start).
    pub fn new(
        store: SceneStore,
        render: RenderScheduler,
        config: Config,
        metrics: Arc<Metrics>,
        recorder: Option<Recorder>,
        attempts: Attempts,
    ) -> Self {
        let planners = Arc::new(tokio::sync::Semaphore::new(config.planner_threads()));
        let dataset_hash = store.dataset_hash();
        Self {
            store,
            registry: Registry::new(config.max_episodes),
            render,
            config,
            next_stream: AtomicU64::new(1),
            planners,
            metrics,
            recorder,
            attempts,
            dataset_hash,
            streams: Default::default(),
        }
    }

    /// The largest image side a client may ask for: ours, or the renderer's if smaller.
    pub fn max_resolution(&self) -> u32 {
        MAX_RESOLUTION.min(self.render.renderer().max_resolution())
    }

    /// The number of live episodes.
    pub fn live(&self) -> usize {
        self.registry.len()
    }

    /// Whether the episode `id` is live.
    pub fn is_live(&self, id: &EpisodeId) -> bool {
        self.registry.contains(id)
    }

    /// The number of live episodes `caller`'s token created.
    pub fn live_of(&self, caller: &Caller) -> usize {
        self.registry.owned_by(caller)
    }

    /// Creates an episode for `caller`, owned by `stream` if it was created on one (it closes
    /// with it). The caller's role decides whether it may be privileged; a challenge scene
    /// takes the caller's one counted attempt at it.
    pub async fn create(
        self: &Arc<Self>,
        caller: &Arc<Caller>,
        options: CreateOptions,
        stream: Option<u64>,
    ) -> Result<Created, ServiceError> {
        lifecycle::create(self, caller, options, stream).await
    }

    /// Records the counted attempts a crash cut (journaled, never recorded) and counts them:
    /// called once at start, before anything is served. Returns how many there were.
    pub fn recover_attempts(&self) -> Result<usize, ServiceError> {
        recording::recover(self)
    }

    /// Creates an episode that lives only if its answer reaches the client: the episode is
    /// closed when the returned [`Unanswered`] (and every clone of it) is dropped before
    /// [`Unanswered::answered`] is called. A client that gives up on a create (its deadline
    /// expires while the episode renders or its answer travels) never learns the id, so
    /// nothing else could close the episode before the idle reaper, and it would count
    /// against `--max-episodes` meanwhile.
    pub async fn create_unanswered(
        self: &Arc<Self>,
        caller: &Arc<Caller>,
        options: CreateOptions,
        stream: Option<u64>,
    ) -> Result<(Created, Unanswered), ServiceError> {
        lifecycle::create_unanswered(self, caller, options, stream).await
    }

    /// Claims the episode `id` for its creator (a dm_env_rpc world holds it), if it is live:
    /// it is then never closed as unclaimed.
    pub fn claim(&self, id: &EpisodeId) {
        self.registry.claim(id);
    }

    /// Restarts an episode, on another scene if `scene` is given (its settings stay).
    ///
    /// A Reset abandoned by its client (the call dropped at an await) leaves nothing
    /// half-done: the episode is locked throughout; without a new scene it is restarted in
    /// one step before the render is awaited (the abandoned call leaves it restarted, exactly
    /// as an answered one, and a Reset is idempotent), and with a new scene the fresh entry
    /// replaces the old one only after every await, so until then the episode is untouched.
    ///
    /// A reset starts a new run: the old run is recorded as ended there (if the server records
    /// it), and a challenge scene is a new attempt (refused for a counted scene).
    pub async fn reset(
        self: &Arc<Self>,
        caller: &Arc<Caller>,
        episode: &EpisodeId,
        scene: Option<SceneChoice>,
    ) -> Result<ResetResult, ServiceError> {
        lifecycle::reset(self, caller, episode, scene).await
    }

    /// Refuses a StepBatch longer than `--max-batch`. [`Episodes::step_many`] checks it too;
    /// an adapter calls it first to refuse such a batch before reading its steps.
    pub fn check_batch_len(&self, steps: usize) -> Result<(), ServiceError> {
        stepping::check_batch_len(self, steps)
    }

    /// Steps, all or nothing: validates the whole batch (at most `--max-batch` steps, one per
    /// episode, no ended episode, an answer that fits in a message) before any episode moves,
    /// then steps every episode and renders every view in one job. Messages name a step `step`
    /// when it is alone (Step), `steps[i]` among several; a StepBatch goes through
    /// [`Episodes::step_batch`], which names them `steps[i]` however few there are.
    pub async fn step_many(
        self: &Arc<Self>,
        caller: &Caller,
        steps: Vec<StepCall>,
    ) -> Result<Vec<StepResult>, ServiceError> {
        let batch = steps.len() > 1;
        stepping::step_many(self, caller, steps, batch).await
    }

    /// StepBatch with resets: `steps` and `resets` (each episode once in all, at most
    /// `--max-batch` together) are validated whole before anything moves (as
    /// [`Episodes::step_many`] does, the answer's size counting the resets' answers too; the
    /// reset episodes known, their new scenes read), then the steps are taken and the resets
    /// after them, in order, while the steps' views render. A reset that still fails (a
    /// challenge scene whose attempt is taken) fails the call, the steps taken.
    pub async fn step_batch(
        self: &Arc<Self>,
        caller: &Arc<Caller>,
        steps: Vec<StepCall>,
        resets: Vec<ResetCall>,
    ) -> Result<(Vec<StepResult>, Vec<ResetResult>), ServiceError> {
        stepping::step_batch(self, caller, steps, resets).await
    }

    /// Takes the steps of a stream wave, each answered on its own: an episode may be stepped
    /// several times (in order, each step seeing the state the previous one left), a bad step
    /// answers its error without disturbing the others, and every view of the wave is
    /// rendered as one job. Returns once the steps are taken; the answers come from
    /// [`Stepped::finish`]. The caller bounds the number of steps (`--max-batch`).
    pub async fn step_each(self: &Arc<Self>, caller: &Caller, steps: Vec<StepCall>) -> Stepped {
        stepping::step_each(self, caller, steps).await
    }

    /// The goal image of an episode.
    pub async fn goal(&self, caller: &Caller, id: &EpisodeId) -> Result<Goal, ServiceError> {
        lifecycle::goal(self, caller, id).await
    }

    /// The privileged state of a privileged episode (trainer and admin tokens only).
    pub async fn privileged_state(&self, caller: &Caller, id: &EpisodeId) -> Result<Privileged, ServiceError> {
        lifecycle::privileged_state(self, caller, id).await
    }

    /// Plans from the episode's current state with the server's planner (see `planning`;
    /// trainer and admin tokens only).
    pub async fn plan(&self, caller: &Caller, call: PlanCall) -> Result<Planned, ServiceError> {
        planning::plan(self, caller, call).await
    }

    /// The metrics of an episode so far.
    pub async fn metrics(&self, caller: &Caller, id: &EpisodeId) -> Result<MetricsSoFar, ServiceError> {
        lifecycle::metrics(self, caller, id).await
    }

    /// Closes an episode; returns its metrics. Its run is recorded as ended here.
    pub async fn close(&self, caller: &Caller, id: &EpisodeId) -> Result<esrp_core::EpisodeMetrics, ServiceError> {
        lifecycle::close(self, caller, id).await
    }

    /// The live episodes `caller` may see (its own; all for an admin), oldest first.
    pub async fn list(&self, caller: &Caller) -> Vec<EpisodeSummary> {
        viewing::list(self, caller).await
    }

    /// Starts watching the episode `id` (`caller`'s, or any for an admin): the receiver
    /// changes at every step and reset. Its creator watching it claims it, as a call naming it
    /// would (see [`Unanswered`]). Call [`Episodes::unwatch`] when the watcher leaves.
    pub async fn watch(
        &self,
        caller: &Caller,
        id: &EpisodeId,
    ) -> Result<tokio::sync::watch::Receiver<u64>, ServiceError> {
        viewing::subscribe(self, caller, id).await
    }

    /// Stops telling the episode `id` of its steps if no watcher is left.
    pub async fn unwatch(&self, id: &EpisodeId) {
        viewing::unsubscribe(self, id).await
    }

    /// What `caller` sees of the episode `id` now: its ego view, the goal image (with
    /// `with_goal`), and where the caller may read its privileged state, the current top-down
    /// view with the paths, each object's IoU and the RDR.
    pub async fn watch_frame(
        self: &Arc<Self>,
        caller: &Caller,
        id: &EpisodeId,
        with_goal: bool,
    ) -> Result<WatchFrame, ServiceError> {
        viewing::frame(self, caller, id, with_goal).await
    }

    /// The record of the last run of the episode `id` that ended, if its runs keep theirs
    /// (created with `keep_record`, the viewer's human play).
    pub async fn last_record(
        &self,
        caller: &Caller,
        id: &EpisodeId,
    ) -> Result<Option<esrp_results::EpisodeRecord>, ServiceError> {
        viewing::last_record(self, caller, id).await
    }

    /// Opens a stream (StepStream, a dm_env_rpc connection) for `caller`, within its
    /// `max_streams`; the slot is given back when dropped.
    pub fn open_stream(self: &Arc<Self>, caller: Arc<Caller>) -> Result<StreamSlot, ServiceError> {
        StreamSlot::open(self, caller)
    }

    /// Closes the episodes a stream (`StreamSlot::id`) still owns, as it ends.
    pub async fn end_stream(&self, stream: u64) {
        lifecycle::end_stream(self, stream).await;
    }

    /// Closes the episodes not owned by a stream and idle for longer than `idle`; returns how
    /// many (counted in the metrics as closed `idle`; their runs recorded as ended).
    pub async fn reap_idle(&self, idle: Duration) -> usize {
        let reaped = self.registry.reap(|entry| entry.last_used.elapsed() > idle);
        let n = reaped.len();
        if n > 0 {
            self.metrics.count_closed("idle", n);
            recording::close_removed(self, reaped, "idle").await;
        }
        n
    }

    /// Closes the episodes that no call has named within `timeout` of their creation (their
    /// client never learnt their id: a create abandoned after its answer left); returns how
    /// many (counted in the metrics as closed `unclaimed`; their runs recorded as ended).
    pub async fn reap_unclaimed(&self, timeout: Duration) -> usize {
        let reaped = self.registry.reap_unclaimed(timeout);
        let n = reaped.len();
        if n > 0 {
            self.metrics.count_closed("unclaimed", n);
            recording::close_removed(self, reaped, "unclaimed").await;
        }
        n
    }

    /// Closes every episode (at shutdown, after the calls have drained), recording each run
    /// as ended there, then stops the records writer once every record is on disk; returns
    /// how many episodes were closed.
    pub async fn close_all(&self) -> usize {
        let closed = self.registry.remove_all();
        let n = closed.len();
        if n > 0 {
            self.metrics.count_closed("shutdown", n);
            recording::close_removed(self, closed, "shutdown").await;
        }
        if let Some(recorder) = &self.recorder {
            recorder.stop();
        }
        n
    }
}
