//! The `soak` scenario: load held over time. Many simulated clients, each a loop over a seeded
//! random mix of calls, for `--minutes`; then checks that every episode the clients created is
//! closed, that the server's live count is back where it started, and that the server's
//! resident memory stopped growing after the warm-up.
//!
//! Each client runs *sessions*: it connects (a fresh HTTP/2 connection), first closes the unary
//! episodes its previous session left open when it disconnected, then makes 5 to 40 operations
//! picked at random (seeded):
//!
//! - create an episode (unary), step one of its episodes 1 to 30 times, step all of them in one
//!   `StepBatch`, reset one (on the same scene or another), close one;
//! - open an `EpisodeStream`, create 1 to 4 episodes on it and pipeline their steps (window 1
//!   to 8), resetting those that end; then close them on the stream or let them die with it, or
//!   drop the stream with requests in flight;
//! - abandon a call: a create, a step or a batch under a deadline of a few milliseconds, its
//!   future dropped when the deadline passes first.
//!
//! A session ends by closing its episodes, or by a disconnect: the connection is dropped (now
//! and then with a step in flight) while its unary episodes stay open on the server; the next
//! session closes them over its new connection.
//!
//! Errors are counted by call and gRPC code. FAILED_PRECONDITION on a step is expected (a step
//! sent after its episode ended: behind the ending step on a stream, or after an abandoned step
//! that may have ended it); any other error fails the run. Steps are random, so episodes end
//! by the horizon now and then and are reset.
//!
//! The choices (scenes, calls, counts, actions, deadlines) come from ChaCha8 keyed by `--seed`
//! and the client's index, so a run repeats the same plan; what the server answers in time
//! (which abandoned calls it finishes) depends on the machine.

use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use esrp_client::{
    Action, Answer, Client, ClientError, Episode, EpisodeOptions, EpisodeStream, LocalServer, RandomActions,
    SceneFilter, SceneSummary, Split,
};
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A call that has no answer after this long counts as hung: an unexpected error.
const NO_ANSWER: Duration = Duration::from_secs(60);
/// Most unary episodes one client holds at a time (creates beyond it close one instead).
const MAX_OWNED: usize = 6;
/// Distinct test scenes the clients play.
const SCENES: usize = 64;
/// The warm-up ends at a fifth of the run, and at 5 minutes at the latest.
const MAX_WARM_UP: Duration = Duration::from_secs(300);
/// How long the cleanup waits for the live count to come back down (streams' episodes close
/// when the server has finished the stream).
const SETTLE: Duration = Duration::from_secs(5);

/// What `soak` does, from esrp-bench's flags.
#[derive(Clone, Debug)]
pub struct Settings {
    /// The server, `http://host:port`.
    pub address: String,
    /// Its bearer token, if it wants one.
    pub token: Option<String>,
    /// Its TLS settings, for an `https://` address.
    pub tls: Option<esrp_client::Tls>,
    /// Minutes of load.
    pub minutes: f64,
    /// Concurrent simulated clients.
    pub clients: usize,
    /// Seed of every client's choices.
    pub seed: u64,
    /// Largest RSS growth from the end of the warm-up to the end of the load, percent.
    pub rss_growth_limit_percent: f64,
    /// The server's `--claim-timeout-seconds`: the cleanup waits that long (and the reaper's
    /// tick) for the episodes of creates abandoned after their answer left to be closed.
    pub claim_timeout: Duration,
}

impl Settings {
    async fn connect(&self) -> Result<Client, ClientError> {
        Client::connect(self.address.clone()).token_opt(self.token.as_deref()).tls_opt(self.tls.clone()).await
    }
}

fn locked<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// An error count's key: which call, which code, and whether the soak expects it.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct ErrorKey {
    /// Unexpected ones sort first.
    expected: bool,
    code: String,
    call: &'static str,
}

/// What every client did, shared by all of them (std mutexes: held for one map update, never
/// across an await).
#[derive(Debug, Default)]
struct Tally {
    /// Steps answered (unary, batch entries, stream), read by the sampler while the load runs.
    steps: AtomicU64,
    /// Calls made, by kind (attempts: errors are counted apart).
    calls: Mutex<BTreeMap<&'static str, u64>>,
    /// Things that happened that are not calls (abandoned calls, disconnects, ended episodes).
    events: Mutex<BTreeMap<&'static str, u64>>,
    errors: Mutex<BTreeMap<ErrorKey, u64>>,
    /// The first few unexpected errors, in full.
    unexpected: Mutex<Vec<String>>,
    created_unary: AtomicU64,
    created_on_streams: AtomicU64,
    /// Unary episodes whose CloseEpisode succeeded.
    closed_unary: AtomicU64,
}

impl Tally {
    fn call(&self, kind: &'static str) {
        *locked(&self.calls).entry(kind).or_default() += 1;
    }

    fn event(&self, kind: &'static str, n: u64) {
        *locked(&self.events).entry(kind).or_default() += n;
    }

    fn steps(&self, n: u64) {
        self.steps.fetch_add(n, Ordering::Relaxed);
    }

    fn error(&self, call: &'static str, error: &ClientError, expected: bool) {
        let key = ErrorKey { expected, code: code_name(error), call };
        *locked(&self.errors).entry(key).or_default() += 1;
        let mut unexpected = locked(&self.unexpected);
        if !expected && unexpected.len() < 10 {
            unexpected.push(format!("{call}: {error}"));
        }
    }
}

/// The gRPC name of an error's code (`FAILED_PRECONDITION`); client-side failures by kind.
fn code_name(error: &ClientError) -> String {
    match error {
        ClientError::Transport(_) => return "TRANSPORT".into(),
        ClientError::Protocol(_) => return "PROTOCOL".into(),
        ClientError::Config(_) => return "CONFIG".into(),
        _ => {}
    }
    let mut name = String::new();
    for (i, c) in format!("{:?}", error.code()).chars().enumerate() {
        if c.is_ascii_uppercase() && i > 0 {
            name.push('_');
        }
        name.push(c.to_ascii_uppercase());
    }
    name
}

/// `call`, or DEADLINE_EXCEEDED when it has no answer within [`NO_ANSWER`].
async fn guarded<T>(call: impl Future<Output = Result<T, ClientError>>) -> Result<T, ClientError> {
    tokio::time::timeout(NO_ANSWER, call)
        .await
        .unwrap_or_else(|_| Err(ClientError::DeadlineExceeded(format!("no answer within {NO_ANSWER:?}"))))
}

/// One simulated client.
struct Worker {
    settings: Arc<Settings>,
    scenes: Arc<Vec<String>>,
    tally: Arc<Tally>,
    until: Instant,
    rng: ChaCha8Rng,
    actions: RandomActions,
    /// Unary episodes of the current session.
    owned: Vec<Episode>,
    /// Unary episodes left open by a disconnect, closed by the next session.
    orphans: Vec<(String, SceneSummary)>,
}

/// How one stream operation goes.
#[derive(Clone, Copy, Debug)]
struct StreamPlan {
    window: usize,
    episodes: usize,
    steps_each: usize,
    /// Drop the stream once this many requests are sent, answers unread.
    drop_after: Option<usize>,
    /// Close the episodes on the stream at the end, instead of letting them die with it.
    close_on_stream: bool,
}

impl Worker {
    fn new(index: usize, settings: Arc<Settings>, scenes: Arc<Vec<String>>, tally: Arc<Tally>, until: Instant) -> Self {
        let mut key = [0u8; 32];
        key[..8].copy_from_slice(&settings.seed.to_le_bytes());
        key[8..16].copy_from_slice(&(index as u64).to_le_bytes());
        key[24..].copy_from_slice(b"esrpsoak");
        let mut rng = ChaCha8Rng::from_seed(key);
        let actions = RandomActions::new(rng.next_u64());
        Worker { settings, scenes, tally, until, rng, actions, owned: Vec::new(), orphans: Vec::new() }
    }

    fn load_is_over(&self) -> bool {
        Instant::now() >= self.until
    }

    fn scene(&mut self) -> String {
        self.scenes[self.rng.random_range(0..self.scenes.len())].clone()
    }

    fn pick(&mut self) -> Option<usize> {
        (!self.owned.is_empty()).then(|| self.rng.random_range(0..self.owned.len()))
    }

    /// A deadline short enough that the server usually has not answered yet.
    fn short_deadline(&mut self, most_micros: u64) -> Duration {
        Duration::from_micros(self.rng.random_range(0..=most_micros))
    }

    /// Sessions until the load is over; returns the unary episodes still open.
    async fn run(mut self) -> Vec<(String, SceneSummary)> {
        while !self.load_is_over() {
            self.tally.call("connect");
            let client = match guarded(self.settings.connect()).await {
                Ok(client) => client,
                Err(error) => {
                    self.tally.error("connect", &error, false);
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            };
            self.close_orphans(&client).await;
            let operations = self.rng.random_range(5..=40);
            for _ in 0..operations {
                if self.load_is_over() {
                    break;
                }
                self.operation(&client).await;
            }
            if !self.load_is_over() && !self.owned.is_empty() && self.rng.random_bool(0.5) {
                self.disconnect().await;
            } else {
                while !self.owned.is_empty() {
                    let episode = self.owned.swap_remove(0);
                    self.close(episode, false).await;
                }
            }
            // The last handle of this session's connection goes here: the connection closes.
            drop(client);
        }
        self.orphans
    }

    async fn operation(&mut self, client: &Client) {
        match self.rng.random_range(0..100u32) {
            0..12 => self.create(client).await,
            12..38 => self.steps(client).await,
            38..48 => self.batch(client).await,
            48..54 => self.reset_one(client).await,
            54..62 => self.close_one(client).await,
            62..76 => self.stream(client).await,
            76..82 => self.abandoned_create(client).await,
            82..90 => self.abandoned_step(client).await,
            90..94 => self.abandoned_batch(client).await,
            _ => self.metrics_one(client).await,
        }
    }

    async fn create(&mut self, client: &Client) {
        if self.owned.len() >= MAX_OWNED {
            return self.close_random().await;
        }
        let scene = self.scene();
        self.tally.call("create");
        match guarded(client.create_episode(EpisodeOptions::scene(scene))).await {
            Ok((episode, _)) => {
                self.tally.created_unary.fetch_add(1, Ordering::Relaxed);
                self.owned.push(episode);
            }
            Err(error) => self.tally.error("create", &error, false),
        }
    }

    async fn steps(&mut self, client: &Client) {
        let Some(i) = self.pick() else { return self.create(client).await };
        for _ in 0..self.rng.random_range(1..=30) {
            let action = self.actions.next_action();
            self.tally.call("step");
            match guarded(self.owned[i].step(action)).await {
                Ok(result) => {
                    self.tally.steps(1);
                    if result.ended() {
                        self.tally.event("episode_ended", 1);
                        self.reset(i).await;
                    }
                }
                Err(error @ ClientError::EpisodeEnded(_)) => {
                    self.tally.error("step", &error, true);
                    self.reset(i).await;
                }
                Err(error) => {
                    self.tally.error("step", &error, false);
                    return;
                }
            }
        }
    }

    async fn batch(&mut self, client: &Client) {
        if self.owned.is_empty() {
            return self.create(client).await;
        }
        let request: Vec<(&Episode, Action)> = self.owned.iter().map(|e| (e, self.actions.next_action())).collect();
        self.tally.call("step_batch");
        let answer = guarded(client.step_batch(&request)).await;
        self.batch_answered(answer).await;
    }

    /// Counts a batch's answer and resets the episodes that ended (all of them, by asking
    /// each, when the batch was refused because one had).
    async fn batch_answered(&mut self, answer: Result<Vec<esrp_client::StepResult>, ClientError>) {
        match answer {
            Ok(results) => {
                self.tally.steps(results.len() as u64);
                let ended: Vec<usize> = (0..results.len()).filter(|&i| results[i].ended()).collect();
                self.tally.event("episode_ended", ended.len() as u64);
                for i in ended {
                    self.reset(i).await;
                }
            }
            Err(error @ ClientError::EpisodeEnded(_)) => {
                self.tally.error("step_batch", &error, true);
                for i in 0..self.owned.len() {
                    self.tally.call("get_metrics");
                    match guarded(self.owned[i].metrics()).await {
                        Ok((_, true)) => self.reset(i).await,
                        Ok((_, false)) => {}
                        Err(error) => self.tally.error("get_metrics", &error, false),
                    }
                }
            }
            Err(error) => self.tally.error("step_batch", &error, false),
        }
    }

    /// Resets owned episode `i`, on another scene one time in three.
    async fn reset(&mut self, i: usize) {
        if self.rng.random_ratio(1, 3) {
            let scene = self.scene();
            self.tally.call("reset_to_scene");
            if let Err(error) = guarded(self.owned[i].reset_to_scene(scene)).await {
                self.tally.error("reset_to_scene", &error, false);
            }
        } else {
            self.tally.call("reset");
            if let Err(error) = guarded(self.owned[i].reset()).await {
                self.tally.error("reset", &error, false);
            }
        }
    }

    async fn reset_one(&mut self, client: &Client) {
        match self.pick() {
            Some(i) => self.reset(i).await,
            None => self.create(client).await,
        }
    }

    async fn metrics_one(&mut self, client: &Client) {
        let Some(i) = self.pick() else { return self.create(client).await };
        self.tally.call("get_metrics");
        match guarded(self.owned[i].metrics()).await {
            Ok((_, true)) => self.reset(i).await,
            Ok((_, false)) => {}
            Err(error) => self.tally.error("get_metrics", &error, false),
        }
    }

    async fn close(&mut self, episode: Episode, after_reconnect: bool) {
        self.tally.call("close");
        match guarded(episode.close()).await {
            Ok(_) => {
                self.tally.closed_unary.fetch_add(1, Ordering::Relaxed);
                if after_reconnect {
                    self.tally.event("closed_after_reconnect", 1);
                }
            }
            Err(error) => self.tally.error("close", &error, false),
        }
    }

    /// Closes one of the owned episodes, picked at random (nothing when none).
    async fn close_random(&mut self) {
        if let Some(i) = self.pick() {
            let episode = self.owned.swap_remove(i);
            self.close(episode, false).await;
        }
    }

    async fn close_one(&mut self, client: &Client) {
        if self.owned.is_empty() {
            return self.create(client).await;
        }
        self.close_random().await;
    }

    async fn close_orphans(&mut self, client: &Client) {
        for (id, scene) in std::mem::take(&mut self.orphans) {
            self.close(Episode::attach(client, id, scene), true).await;
        }
    }

    /// Drops the session's connection with its unary episodes open (half the time with a step
    /// in flight); the next session closes them.
    async fn disconnect(&mut self) {
        if self.rng.random_bool(0.5)
            && let Some(i) = self.pick()
        {
            let (deadline, action) = (self.short_deadline(5_000), self.actions.next_action());
            self.tally.call("step_short_deadline");
            match tokio::time::timeout(deadline, self.owned[i].step(action)).await {
                Err(_) => self.tally.event("abandoned_step", 1),
                Ok(Ok(_)) => self.tally.steps(1),
                Ok(Err(error @ ClientError::EpisodeEnded(_))) => self.tally.error("step_short_deadline", &error, true),
                Ok(Err(error)) => self.tally.error("step_short_deadline", &error, false),
            }
        }
        self.tally.event("disconnect_with_open_episodes", 1);
        self.tally.event("episodes_left_open_by_disconnects", self.owned.len() as u64);
        self.orphans.extend(self.owned.drain(..).map(|e| {
            let scene = e.scene().clone();
            (e.detach(), scene)
        }));
    }

    async fn abandoned_create(&mut self, client: &Client) {
        let (scene, deadline) = (self.scene(), self.short_deadline(20_000));
        self.tally.call("create_short_deadline");
        match tokio::time::timeout(deadline, client.create_episode(EpisodeOptions::scene(scene))).await {
            Err(_) => self.tally.event("abandoned_create", 1),
            Ok(Ok((episode, _))) => {
                self.tally.created_unary.fetch_add(1, Ordering::Relaxed);
                self.owned.push(episode);
            }
            Ok(Err(error)) => self.tally.error("create_short_deadline", &error, false),
        }
    }

    async fn abandoned_step(&mut self, client: &Client) {
        let Some(i) = self.pick() else { return self.create(client).await };
        let (deadline, action) = (self.short_deadline(10_000), self.actions.next_action());
        self.tally.call("step_short_deadline");
        match tokio::time::timeout(deadline, self.owned[i].step(action)).await {
            // The server may still take the step and end the episode: a later step then
            // answers FAILED_PRECONDITION and resets it.
            Err(_) => self.tally.event("abandoned_step", 1),
            Ok(Ok(result)) => {
                self.tally.steps(1);
                if result.ended() {
                    self.tally.event("episode_ended", 1);
                    self.reset(i).await;
                }
            }
            Ok(Err(error @ ClientError::EpisodeEnded(_))) => {
                self.tally.error("step_short_deadline", &error, true);
                self.reset(i).await;
            }
            Ok(Err(error)) => self.tally.error("step_short_deadline", &error, false),
        }
    }

    async fn abandoned_batch(&mut self, client: &Client) {
        if self.owned.is_empty() {
            return self.create(client).await;
        }
        let deadline = self.short_deadline(10_000);
        let request: Vec<(&Episode, Action)> = self.owned.iter().map(|e| (e, self.actions.next_action())).collect();
        self.tally.call("step_batch_short_deadline");
        let answer = tokio::time::timeout(deadline, client.step_batch(&request)).await;
        drop(request);
        match answer {
            Err(_) => self.tally.event("abandoned_step_batch", 1),
            Ok(answer) => self.batch_answered(answer).await,
        }
    }

    async fn stream(&mut self, client: &Client) {
        let episodes = self.rng.random_range(1..=4);
        let steps_each = self.rng.random_range(5..=60);
        let plan = StreamPlan {
            window: self.rng.random_range(1..=8),
            episodes,
            steps_each,
            drop_after: self.rng.random_ratio(1, 4).then(|| self.rng.random_range(1..=episodes * (steps_each + 1))),
            close_on_stream: self.rng.random_bool(0.5),
        };
        self.tally.call("stream_open");
        let mut stream = match guarded(client.episode_stream(plan.window)).await {
            Ok(stream) => stream,
            Err(error) => return self.tally.error("stream_open", &error, false),
        };
        if let Err(error) = self.drive_stream(&mut stream, plan).await {
            self.tally.error("stream", &error, false);
        }
    }

    /// One stream's life as `plan` says; an error here is the stream's own (it cannot go on).
    /// Sends a random step of `episode` on `stream`, counted, its request remembered as a step.
    async fn stream_step(
        &mut self,
        stream: &mut EpisodeStream,
        episode: &str,
        kinds: &mut HashMap<u64, &'static str>,
    ) -> Result<(), ClientError> {
        self.tally.call("stream_step");
        kinds.insert(stream.step(episode, self.actions.next_action()).await?, "stream_step");
        Ok(())
    }

    /// Drives one stream through `plan`: its creates, its steps and resets, its closes, each
    /// answer counted by what its request was, with the plan's abuses (dropped mid-flight,
    /// left unread) where it has them. One function on purpose: the order of what is sent and
    /// read on the stream is the scenario, and reads top to bottom.
    async fn drive_stream(&mut self, stream: &mut EpisodeStream, plan: StreamPlan) -> Result<(), ClientError> {
        // What each request was, by request id, to count its answer.
        let mut kinds: HashMap<u64, &'static str> = HashMap::new();
        let mut sent = 0usize;
        let dropped = |sent: usize| plan.drop_after.is_some_and(|d| sent >= d);
        for _ in 0..plan.episodes {
            let scene = self.scene();
            self.tally.call("stream_create");
            kinds.insert(stream.create(&EpisodeOptions::scene(scene))?, "stream_create");
            sent += 1;
            if dropped(sent) {
                self.tally.event("stream_dropped_mid_flight", 1);
                return Ok(());
            }
        }
        let mut ids = Vec::with_capacity(plan.episodes);
        while let Some(answer) = guarded(stream.next()).await? {
            kinds.remove(&answer.request_id);
            match answer.result {
                Ok(Answer::Created { .. }) => {
                    self.tally.created_on_streams.fetch_add(1, Ordering::Relaxed);
                    ids.push(answer.episode_id);
                }
                Ok(other) => self.tally.error(
                    "stream_create",
                    &ClientError::Protocol(format!("a create answered with {other:?}")),
                    false,
                ),
                Err(error) => self.tally.error("stream_create", &error, false),
            }
        }
        let index: HashMap<String, usize> = ids.iter().enumerate().map(|(i, id)| (id.clone(), i)).collect();
        let mut left = vec![plan.steps_each; ids.len()];
        // Up to `window` steps of each episode in flight from the start.
        for _ in 0..plan.window {
            for e in 0..ids.len() {
                if left[e] > 0 {
                    left[e] -= 1;
                    self.stream_step(stream, &ids[e], &mut kinds).await?;
                    sent += 1;
                    if dropped(sent) {
                        self.tally.event("stream_dropped_mid_flight", 1);
                        return Ok(());
                    }
                }
            }
        }
        while let Some(answer) = guarded(stream.next()).await? {
            let kind = kinds.remove(&answer.request_id).unwrap_or("stream");
            let Some(&e) = index.get(&answer.episode_id) else {
                let message = format!("an answer about episode {:?}, not one of this stream's", answer.episode_id);
                self.tally.error(kind, &ClientError::Protocol(message), false);
                continue;
            };
            let step_answered = match answer.result {
                Ok(Answer::Step(result)) => {
                    self.tally.steps(1);
                    if result.ended() {
                        self.tally.event("episode_ended", 1);
                        self.tally.call("stream_reset");
                        kinds.insert(stream.reset(&ids[e])?, "stream_reset");
                        sent += 1;
                    }
                    true
                }
                Ok(Answer::Reset(_) | Answer::Closed(_)) => false,
                // A step sent behind the one that ended its episode, before the reset.
                Err(error @ ClientError::EpisodeEnded(_)) if kind == "stream_step" => {
                    self.tally.error(kind, &error, true);
                    true
                }
                Err(error) => {
                    self.tally.error(kind, &error, false);
                    kind == "stream_step"
                }
                Ok(other @ Answer::Created { .. }) => {
                    self.tally.error(kind, &ClientError::Protocol(format!("answered with {other:?}")), false);
                    false
                }
            };
            if step_answered && left[e] > 0 {
                left[e] -= 1;
                self.stream_step(stream, &ids[e], &mut kinds).await?;
                sent += 1;
            }
            if dropped(sent) {
                self.tally.event("stream_dropped_mid_flight", 1);
                return Ok(());
            }
        }
        if plan.close_on_stream {
            for id in &ids {
                self.tally.call("stream_close");
                kinds.insert(stream.close(id)?, "stream_close");
            }
            while let Some(answer) = guarded(stream.next()).await? {
                let kind = kinds.remove(&answer.request_id).unwrap_or("stream");
                match answer.result {
                    Ok(Answer::Closed(_)) => {}
                    Ok(other) => self.tally.error(
                        kind,
                        &ClientError::Protocol(format!("a close answered with {other:?}")),
                        false,
                    ),
                    Err(error) => self.tally.error(kind, &error, false),
                }
            }
            self.tally.event("stream_episodes_closed_on_the_stream", ids.len() as u64);
        } else {
            self.tally.event("stream_episodes_left_to_die_with_it", ids.len() as u64);
        }
        Ok(())
    }
}

/// The server's state at one moment of the run.
#[derive(Clone, Copy, Debug)]
struct Sample {
    /// Seconds since the load started.
    at: f64,
    /// Steps answered so far.
    steps: u64,
    /// Live episodes (`None` if ServerInfo failed).
    live: Option<u32>,
    /// Resident bytes (local server on Linux only).
    rss: Option<u64>,
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / 1_048_576.0
}

fn clock(seconds: f64) -> String {
    let s = seconds.round() as u64;
    format!("{}:{:02}", s / 60, s % 60)
}

/// A soak run's figures and verdict.
#[derive(Debug)]
pub struct Report {
    minutes: f64,
    clients: usize,
    seed: u64,
    /// Seconds the load ran.
    load_seconds: f64,
    steps: u64,
    created_unary: u64,
    created_on_streams: u64,
    closed_unary: u64,
    closed_at_cleanup: u64,
    calls: BTreeMap<&'static str, u64>,
    events: BTreeMap<&'static str, u64>,
    errors: Vec<(ErrorKey, u64)>,
    unexpected_examples: Vec<String>,
    samples: Vec<Sample>,
    warm_up: Option<Sample>,
    end_of_load: Option<Sample>,
    rss_start: Option<u64>,
    rss_after_cleanup: Option<u64>,
    live_before: u32,
    live_after_cleanup: u32,
    rss_growth_limit_percent: f64,
    /// Why the run failed (empty: it passed).
    pub failures: Vec<String>,
    /// What was not checked, and why.
    notes: Vec<String>,
}

impl Report {
    /// Episodes created, unary and on streams.
    pub fn episodes(&self) -> u64 {
        self.created_unary + self.created_on_streams
    }

    /// Steps answered.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// Seconds the load ran.
    pub fn seconds(&self) -> f64 {
        self.load_seconds
    }

    /// Episodes live after the cleanup that were not live before the run.
    fn leftover(&self) -> u32 {
        self.live_after_cleanup.saturating_sub(self.live_before)
    }

    fn abandoned_creates(&self) -> u64 {
        self.events.get("abandoned_create").copied().unwrap_or(0)
    }

    /// RSS growth from the end of the warm-up to the end of the load: (MiB, percent).
    fn rss_growth(&self) -> Option<(f64, f64)> {
        let warm = self.warm_up?.rss?;
        let end = self.end_of_load?.rss?;
        let growth = end as f64 - warm as f64;
        Some((growth / 1_048_576.0, 100.0 * growth / warm as f64))
    }

    /// "PASSED" or "FAILED: why".
    pub fn verdict(&self) -> String {
        if self.failures.is_empty() { "PASSED".into() } else { format!("FAILED: {}", self.failures.join("; ")) }
    }

    /// The summary table.
    pub fn print(&self) {
        let rss = |r: Option<u64>| r.map_or("n/a".to_owned(), |b| format!("{:.1} MiB", mib(b)));
        let live = |s: Option<Sample>| s.and_then(|s| s.live).map_or("n/a".to_owned(), |n| n.to_string());
        println!("soak: {} clients, {} min, seed {}: {}", self.clients, self.minutes, self.seed, self.verdict());
        println!("  {:<44} {:>12}", "steps", self.steps);
        println!("  {:<44} {:>12.0}", "steps/s", self.steps as f64 / self.load_seconds.max(1e-9));
        println!(
            "  {:<44} {:>12}   (unary {}, on streams {})",
            "episodes created",
            self.episodes(),
            self.created_unary,
            self.created_on_streams
        );
        println!(
            "  {:<44} {:>12}   (of {}; {} at the final cleanup)",
            "unary episodes closed by the client", self.closed_unary, self.created_unary, self.closed_at_cleanup
        );
        println!("  calls");
        for (kind, n) in &self.calls {
            println!("    {kind:<42} {n:>12}");
        }
        println!("  events");
        for (kind, n) in &self.events {
            println!("    {kind:<42} {n:>12}");
        }
        println!("  errors");
        if self.errors.is_empty() {
            println!("    none");
        }
        for (key, n) in &self.errors {
            let label = format!("{} on {}", key.code, key.call);
            println!("    {label:<42} {n:>12}   {}", if key.expected { "expected" } else { "UNEXPECTED" });
        }
        for example in &self.unexpected_examples {
            println!("    e.g. {example}");
        }
        let warm_at = self.warm_up.map_or(String::new(), |s| format!(" at {}", clock(s.at)));
        println!("  server RSS");
        println!("    {:<42} {:>12}", "at the start", rss(self.rss_start));
        println!("    {:<42} {:>12}", format!("end of warm-up{warm_at}"), rss(self.warm_up.and_then(|s| s.rss)));
        println!("    {:<42} {:>12}", "end of the load", rss(self.end_of_load.and_then(|s| s.rss)));
        println!("    {:<42} {:>12}", "after the cleanup", rss(self.rss_after_cleanup));
        match self.rss_growth() {
            Some((growth, percent)) => println!(
                "    {:<42} {:>+8.1} MiB   ({percent:+.1} %, limit {:.0} %)",
                "growth after the warm-up", growth, self.rss_growth_limit_percent
            ),
            None => println!("    {:<42} {:>12}", "growth after the warm-up", "n/a"),
        }
        println!("  live episodes");
        println!("    {:<42} {:>12}", "before the run", self.live_before);
        println!("    {:<42} {:>12}", format!("end of warm-up{warm_at}"), live(self.warm_up));
        println!("    {:<42} {:>12}", "end of the load", live(self.end_of_load));
        println!("    {:<42} {:>12}", "after the cleanup", self.live_after_cleanup);
        println!(
            "    {:<42} {:>12}   ({} creates abandoned before their answer; each may leave one)",
            "leftover",
            self.leftover(),
            self.abandoned_creates()
        );
        for note in &self.notes {
            println!("  note: {note}");
        }
    }

    /// The report as JSON (esrp-bench's `--json`).
    pub fn to_json(&self) -> serde_json::Value {
        let samples: Vec<serde_json::Value> = self
            .samples
            .iter()
            .map(|s| serde_json::json!({"seconds": s.at, "steps": s.steps, "live_episodes": s.live, "rss_mib": s.rss.map(mib)}))
            .collect();
        let errors: Vec<serde_json::Value> = self
            .errors
            .iter()
            .map(|(k, n)| serde_json::json!({"call": k.call, "code": k.code, "expected": k.expected, "count": n}))
            .collect();
        serde_json::json!({
            "minutes": self.minutes, "clients": self.clients, "seed": self.seed,
            "passed": self.failures.is_empty(), "failures": self.failures, "notes": self.notes,
            "load_seconds": self.load_seconds, "steps": self.steps,
            "steps_per_second": self.steps as f64 / self.load_seconds.max(1e-9),
            "episodes_created": {"unary": self.created_unary, "on_streams": self.created_on_streams},
            "unary_episodes_closed": self.closed_unary, "closed_at_cleanup": self.closed_at_cleanup,
            "calls": self.calls, "events": self.events, "errors": errors,
            "unexpected_error_examples": self.unexpected_examples,
            "rss_mib": {
                "start": self.rss_start.map(mib),
                "end_of_warm_up": self.warm_up.and_then(|s| s.rss).map(mib),
                "warm_up_seconds": self.warm_up.map(|s| s.at),
                "end_of_load": self.end_of_load.and_then(|s| s.rss).map(mib),
                "after_cleanup": self.rss_after_cleanup.map(mib),
                "growth_mib": self.rss_growth().map(|g| g.0),
                "growth_percent": self.rss_growth().map(|g| g.1),
                "growth_limit_percent": self.rss_growth_limit_percent,
            },
            "live_episodes": {
                "before": self.live_before,
                "end_of_warm_up": self.warm_up.and_then(|s| s.live),
                "end_of_load": self.end_of_load.and_then(|s| s.live),
                "after_cleanup": self.live_after_cleanup,
                "leftover": self.leftover(),
                "abandoned_creates": self.abandoned_creates(),
            },
            "samples": samples,
        })
    }
}

/// Test scenes for the clients, at most [`SCENES`].
async fn test_scenes(client: &Client) -> anyhow::Result<Vec<String>> {
    let filter = SceneFilter { page_size: SCENES as u32, ..SceneFilter::split(Split::Test) };
    let mut scenes = std::pin::pin!(client.scenes(filter));
    let mut ids = Vec::new();
    while ids.len() < SCENES
        && let Some(scene) = tokio_stream::StreamExt::next(&mut scenes).await
    {
        ids.push(scene?.id);
    }
    if ids.is_empty() {
        bail!("the server has no test scenes");
    }
    Ok(ids)
}

async fn sample(client: &Client, tally: &Tally, server: Option<&LocalServer>, start: Instant) -> Sample {
    tally.call("server_info");
    let live = match guarded(client.server_info()).await {
        Ok(info) => Some(info.live_episodes),
        Err(error) => {
            tally.error("server_info", &error, false);
            None
        }
    };
    Sample {
        at: start.elapsed().as_secs_f64(),
        steps: tally.steps.load(Ordering::Relaxed),
        live,
        rss: server.and_then(LocalServer::resident_bytes),
    }
}

/// Runs the soak: `settings.clients` clients for `settings.minutes`, sampling the server every
/// few seconds and printing a line per minute (per fifth of the run when shorter than 5
/// minutes); then the cleanup and the checks. It stays one function: its phases (load and
/// sampling, cleanup, the checks against the samples) share the tallies and samples, and read in
/// the order they run.
pub async fn run(settings: Settings, server: Option<&LocalServer>) -> anyhow::Result<Report> {
    if !(settings.minutes > 0.0 && settings.minutes.is_finite()) || settings.clients == 0 {
        bail!("soak needs --minutes above 0 and --clients of at least 1");
    }
    let settings = Arc::new(settings);
    let monitor = settings.connect().await.context("connecting the monitor")?;
    let scenes = Arc::new(test_scenes(&monitor).await?);
    let live_before = monitor.server_info().await?.live_episodes;
    let rss_start = server.and_then(LocalServer::resident_bytes);
    let tally = Arc::new(Tally::default());

    let load = Duration::from_secs_f64(settings.minutes * 60.0);
    let warm_up = (load / 5).min(MAX_WARM_UP);
    let report_every = (load / 5).min(Duration::from_secs(60));
    let sample_every = (report_every / 12).max(Duration::from_millis(250));
    let start = Instant::now();
    let until = start + load;
    let workers: Vec<_> = (0..settings.clients)
        .map(|i| tokio::spawn(Worker::new(i, settings.clone(), scenes.clone(), tally.clone(), until).run()))
        .collect();

    println!(
        "soak: {} clients for {} min, seed {}; a line every {} (warm-up until {})",
        settings.clients,
        settings.minutes,
        settings.seed,
        clock(report_every.as_secs_f64()),
        clock(warm_up.as_secs_f64())
    );
    let mut samples: Vec<Sample> = Vec::new();
    let mut warm_up_sample = None;
    let mut last_report = Sample { at: 0.0, steps: 0, live: Some(live_before), rss: rss_start };
    let mut next_sample = start + sample_every;
    let mut next_report = report_every.as_secs_f64();
    loop {
        tokio::time::sleep_until(next_sample.min(until).into()).await;
        let s = sample(&monitor, &tally, server, start).await;
        samples.push(s);
        if warm_up_sample.is_none() && s.at >= warm_up.as_secs_f64() {
            warm_up_sample = Some(s);
        }
        let done = Instant::now() >= until;
        if s.at >= next_report || done {
            let rate = (s.steps - last_report.steps) as f64 / (s.at - last_report.at).max(1e-9);
            println!(
                "  {:>6}  {:>8.0} steps/s  {:>5} live episodes  RSS {}",
                clock(s.at),
                rate,
                s.live.map_or("?".to_owned(), |n| n.to_string()),
                s.rss.map_or("n/a".to_owned(), |b| format!("{:.1} MiB", mib(b)))
            );
            last_report = s;
            next_report += report_every.as_secs_f64();
        }
        if done {
            break;
        }
        next_sample += sample_every;
    }
    let end_of_load = samples.last().copied();
    let load_seconds = start.elapsed().as_secs_f64();

    // Stop: each client finishes its operation and hands back the unary episodes still open.
    let mut still_open = Vec::new();
    for worker in workers {
        still_open.extend(worker.await.context("a soak client panicked")?);
    }
    let load_seconds = load_seconds.max(end_of_load.map_or(0.0, |s| s.at));
    // Close every episode still tracked, over a fresh connection.
    let cleanup = settings.connect().await.context("connecting for the cleanup")?;
    let mut closed_at_cleanup = 0;
    for (id, scene) in still_open {
        tally.call("close");
        match guarded(Episode::attach(&cleanup, id, scene).close()).await {
            Ok(_) => {
                tally.closed_unary.fetch_add(1, Ordering::Relaxed);
                closed_at_cleanup += 1;
            }
            Err(error) => tally.error("close", &error, false),
        }
    }
    // Streams' episodes close when the server has finished their stream, and the episodes of
    // creates abandoned after their answer left when no call has claimed them within the
    // server's claim timeout (its reaper ticks every second at least): wait for both.
    let settle_until = Instant::now() + SETTLE + settings.claim_timeout;
    let mut live_after_cleanup = monitor.server_info().await?.live_episodes;
    while live_after_cleanup > live_before && Instant::now() < settle_until {
        tokio::time::sleep(Duration::from_millis(200)).await;
        live_after_cleanup = monitor.server_info().await?.live_episodes;
    }
    let rss_after_cleanup = server.and_then(LocalServer::resident_bytes);

    let mut report = Report {
        minutes: settings.minutes,
        clients: settings.clients,
        seed: settings.seed,
        load_seconds,
        steps: tally.steps.load(Ordering::Relaxed),
        created_unary: tally.created_unary.load(Ordering::Relaxed),
        created_on_streams: tally.created_on_streams.load(Ordering::Relaxed),
        closed_unary: tally.closed_unary.load(Ordering::Relaxed),
        closed_at_cleanup,
        calls: locked(&tally.calls).clone(),
        events: locked(&tally.events).clone(),
        errors: locked(&tally.errors).iter().map(|(k, n)| (k.clone(), *n)).collect(),
        unexpected_examples: locked(&tally.unexpected).clone(),
        samples,
        warm_up: warm_up_sample,
        end_of_load,
        rss_start,
        rss_after_cleanup,
        live_before,
        live_after_cleanup,
        rss_growth_limit_percent: settings.rss_growth_limit_percent,
        failures: Vec::new(),
        notes: Vec::new(),
    };
    judge(&mut report, &settings, server.is_some());
    Ok(report)
}

/// Fills in the report's failures and notes.
fn judge(report: &mut Report, settings: &Settings, local: bool) {
    let unexpected: u64 = report.errors.iter().filter(|(k, _)| !k.expected).map(|(_, n)| n).sum();
    if unexpected > 0 {
        report.failures.push(format!("{unexpected} unexpected errors"));
    }
    if report.closed_unary != report.created_unary {
        report.failures.push(format!(
            "{} of the {} unary episodes created were not closed",
            report.created_unary - report.closed_unary.min(report.created_unary),
            report.created_unary
        ));
    }
    let leftover = report.leftover();
    if leftover > 0 {
        report.failures.push(format!(
            "{leftover} episodes still live {} s after the cleanup ({} creates were abandoned by their client)",
            (SETTLE + settings.claim_timeout).as_secs(),
            report.abandoned_creates()
        ));
    }
    match report.rss_growth() {
        Some((growth, percent)) if percent > settings.rss_growth_limit_percent => report.failures.push(format!(
            "server RSS grew {growth:.1} MiB ({percent:.1} %) after the warm-up, above the limit of {:.0} %",
            settings.rss_growth_limit_percent
        )),
        Some(_) => {}
        None if local => report.notes.push("the server's RSS could not be read (Linux only): not checked".into()),
        None => report.notes.push("RSS needs a local server (no --server): not checked".into()),
    }
    if !local {
        report.notes.push(
            "against a shared server, other clients' episodes change the live count: the leftover check \
             compares with the count before the run"
                .into(),
        );
    }
}
