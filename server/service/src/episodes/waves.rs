//! Streams of requests answered in **waves**: everything a client has already sent, up to a
//! request whose answer would depend on the wave's order of work ([`Wave::admits`]), is
//! answered together, steps first (their views rendered as one job), then creates, resets and
//! closes one by one; answers go back in request order. Waves overlap: while one wave's views
//! render, the next is read and stepped; at most [`WAVES_IN_FLIGHT`] waves wait for their
//! answers, and a stream holds about one message limit of answers beyond one wave.
//!
//! The machinery is written against core types: a protocol's stream handler ([`serve`])
//! passes a function that turns each message into a tag (its request id, say) and a
//! [`WaveRequest`], and one that turns a tag and an answer into its message. The stream's own
//! errors (a message that could not be read, a broken connection) are the protocol's type,
//! passed through as they came.

use std::collections::HashSet;
use std::pin::Pin;
use std::sync::Arc;

use tokio::sync::mpsc;
use tokio_stream::{Stream, StreamExt};

use super::lifecycle;
use super::state::Episodes;
use super::stepping::{self, Stepped};
use crate::error::ServiceError;
use crate::types::{
    Caller, CreateOptions, Created, EpisodeId, Observation, ResetResult, SceneChoice, StepCall, StepResult,
};

/// Waves of a stream whose answers may wait at once: enough to keep the render thread busy
/// while the next wave is read and stepped, few enough to bound what a stream holds.
pub const WAVES_IN_FLIGHT: usize = 4;

/// One request of a stream, in core types.
#[derive(Debug)]
pub enum WaveRequest {
    /// Create an episode (owned by the stream: it closes with it).
    Create(CreateOptions),
    /// Step an episode.
    Step(StepCall),
    /// Restart an episode, on another scene if given.
    Reset {
        /// The episode.
        episode: EpisodeId,
        /// Its new scene, if any.
        scene: Option<SceneChoice>,
    },
    /// Close an episode.
    Close(EpisodeId),
    /// A request that could not be read: it answers its error in place and touches nothing.
    Invalid(ServiceError),
}

/// The answer to one [`WaveRequest`].
#[derive(Debug)]
pub enum WaveAnswer {
    /// An episode was created.
    Created(Box<Created>),
    /// A step was taken.
    Stepped(Box<StepResult>),
    /// An episode was reset.
    Reset(Box<ResetResult>),
    /// An episode was closed, with these final metrics.
    Closed(esrp_core::EpisodeMetrics),
}

/// An upper bound of the encoded size of an observation, bytes.
fn observation_bytes(o: &Observation) -> usize {
    let images = o.ego_rgb.len() + o.goal_rgb.as_ref().map_or(0, |g| g.len());
    let extras = o.depth.as_ref().map_or(0, |d| d.len() * 4)
        + o.segmentation.as_ref().map_or(0, |s| s.len() * 4)
        + o.current_top_down.as_ref().map_or(0, |t| t.len());
    512 + images + extras
}

impl WaveAnswer {
    /// An upper bound of its encoded size, bytes.
    fn bytes(&self) -> usize {
        match self {
            WaveAnswer::Created(c) => observation_bytes(&c.observation) + 512,
            WaveAnswer::Stepped(s) => observation_bytes(&s.observation),
            WaveAnswer::Reset(r) => observation_bytes(&r.observation) + 256,
            WaveAnswer::Closed(_) => 128,
        }
    }
}

/// The requests of one wave, each with its tag: answered together, steps first.
pub struct Wave<T> {
    requests: Vec<(T, WaveRequest)>,
    /// Episodes stepped in the wave.
    stepped: HashSet<EpisodeId>,
    /// Episodes reset or closed in the wave.
    others: HashSet<EpisodeId>,
}

impl<T> Default for Wave<T> {
    fn default() -> Self {
        Self { requests: Vec::new(), stepped: HashSet::new(), others: HashSet::new() }
    }
}

impl<T> Wave<T> {
    /// Whether `r` can join the wave without its answer depending on the wave's order of
    /// work (steps first, then resets and closes): more steps of a stepped episode can (they
    /// run in request order); a create, a step of an episode reset or closed in the wave, or a
    /// reset or close of an episode already in the wave cannot, and opens the next wave.
    pub fn admits(&self, r: &WaveRequest) -> bool {
        match r {
            WaveRequest::Create(_) => false,
            WaveRequest::Step(s) => !self.others.contains(&s.episode),
            WaveRequest::Reset { episode, .. } | WaveRequest::Close(episode) => {
                !self.stepped.contains(episode) && !self.others.contains(episode)
            }
            WaveRequest::Invalid(_) => true,
        }
    }

    /// Adds `r`, tagged `tag`.
    pub fn push(&mut self, tag: T, r: WaveRequest) {
        match &r {
            WaveRequest::Step(s) => {
                self.stepped.insert(s.episode.clone());
            }
            WaveRequest::Reset { episode, .. } | WaveRequest::Close(episode) => {
                self.others.insert(episode.clone());
            }
            WaveRequest::Create(_) | WaveRequest::Invalid(_) => {}
        }
        self.requests.push((tag, r));
    }

    /// The number of requests.
    pub fn len(&self) -> usize {
        self.requests.len()
    }

    /// Whether it has no request.
    pub fn is_empty(&self) -> bool {
        self.requests.is_empty()
    }
}

/// A wave's answers, tagged, in request order, once its views are rendered.
type Answers<T> = Pin<Box<dyn std::future::Future<Output = Vec<(T, Result<WaveAnswer, ServiceError>)>> + Send>>;

/// Takes a wave's steps (their views go to the render thread), then its creates, resets and
/// closes one by one; the answers, in request order, come from the returned future, with an
/// upper bound of their encoded size.
pub async fn answer_wave<T: Send + 'static>(
    episodes: &Arc<Episodes>,
    caller: &Arc<Caller>,
    wave: Wave<T>,
    stream: u64,
) -> (Answers<T>, usize) {
    let (tags, requests): (Vec<T>, Vec<WaveRequest>) = wave.requests.into_iter().unzip();
    // Steps first, together, then the rest one by one (in order).
    let mut step_positions = Vec::new();
    let mut steps = Vec::new();
    let mut rest = Vec::new();
    for (i, request) in requests.into_iter().enumerate() {
        match request {
            WaveRequest::Step(s) => {
                step_positions.push(i);
                steps.push(s);
            }
            WaveRequest::Create(options) => rest.push((i, Other::Create(options))),
            WaveRequest::Reset { episode, scene } => rest.push((i, Other::Reset(episode, scene))),
            WaveRequest::Close(episode) => rest.push((i, Other::Close(episode))),
            WaveRequest::Invalid(error) => rest.push((i, Other::Invalid(error))),
        }
    }
    let stepped = if steps.is_empty() { None } else { Some(stepping::step_each(episodes, caller, steps).await) };
    let mut answers: Vec<Option<Result<WaveAnswer, ServiceError>>> = (0..tags.len()).map(|_| None).collect();
    for (i, request) in rest {
        answers[i] = Some(match request {
            Other::Create(options) => lifecycle::create(episodes, caller, options, Some(stream))
                .await
                .map(|c| WaveAnswer::Created(Box::new(c))),
            Other::Reset(episode, scene) => {
                lifecycle::reset(episodes, caller, &episode, scene).await.map(|r| WaveAnswer::Reset(Box::new(r)))
            }
            Other::Close(episode) => lifecycle::close(episodes, caller, &episode).await.map(WaveAnswer::Closed),
            Other::Invalid(error) => Err(error),
        });
    }
    let metrics = episodes.metrics.clone();
    let bytes = stepped.as_ref().map_or(0, Stepped::answer_bytes)
        + answers.iter().flatten().map(|a| a.as_ref().map_or(256, WaveAnswer::bytes) + 16).sum::<usize>();
    let future: Answers<T> = Box::pin(async move {
        if let Some(stepped) = stepped {
            for (&i, result) in step_positions.iter().zip(stepped.finish(&metrics).await) {
                answers[i] = Some(result.map(|s| WaveAnswer::Stepped(Box::new(s))));
            }
        }
        tags.into_iter()
            .zip(answers)
            .map(|(tag, answer)| {
                (tag, answer.unwrap_or_else(|| Err(ServiceError::Internal("a request without an answer".into()))))
            })
            .collect()
    });
    (future, bytes)
}

/// A request of a wave answered on its own, after the wave's steps.
enum Other {
    Create(CreateOptions),
    Reset(EpisodeId, Option<SceneChoice>),
    Close(EpisodeId),
    Invalid(ServiceError),
}

/// The next item of the stream if it is ready now, without waiting: `None` if not ready,
/// `Some(None)` at the end.
fn ready_now<S: Stream + Unpin>(inbound: &mut S) -> Option<Option<S::Item>> {
    let waker = std::task::Waker::noop();
    let mut cx = std::task::Context::from_waker(waker);
    match Pin::new(inbound).poll_next(&mut cx) {
        std::task::Poll::Ready(item) => Some(item),
        std::task::Poll::Pending => None,
    }
}

/// A wave's answers as messages, in request order, once its views are rendered (or the error
/// that ended the stream).
type Messages<M, E> = Pin<Box<dyn std::future::Future<Output = Vec<Result<M, E>>> + Send>>;

/// A wave's answers as messages, and the permits of the stream's byte budget it holds until
/// they are sent.
type Outgoing<M, E> = (Messages<M, E>, Option<tokio::sync::OwnedSemaphorePermit>);

/// Serves one stream: reads `inbound` in waves (everything already sent, see
/// [`Wave::admits`]), each message made a tagged request by `read`; answers each wave
/// ([`answer_wave`]) and sends each answer, made a message by `write`, down `out` in
/// request order. An unreadable message (too large, not protobuf) or a broken connection (an
/// `E` of the inbound stream) ends the stream after passing the error on. When the stream
/// ends, after every answer is sent (or the client is gone), its episodes close. `slot` is
/// the stream's place in its caller's `max_streams`, held until then.
pub async fn serve<S, I, M, T, E>(
    episodes: Arc<Episodes>,
    slot: StreamSlot,
    mut inbound: S,
    out: mpsc::Sender<Result<M, E>>,
    read: fn(I) -> (T, WaveRequest),
    write: fn(T, Result<WaveAnswer, ServiceError>) -> M,
) where
    S: Stream<Item = Result<I, E>> + Unpin + Send,
    M: Send + 'static,
    T: Send + 'static,
    E: std::fmt::Display + Send + 'static,
{
    let stream = slot.id;
    // Answers of each wave, in wave order, to a task that sends them in order. Each wave
    // holds permits of the stream's budget of answer bytes until its answers are sent.
    let (answers, mut waiting) = mpsc::channel::<Outgoing<M, E>>(WAVES_IN_FLIGHT);
    let budget_kib = (episodes.config.max_message_bytes / 1024).clamp(1, u32::MAX as usize) as u32;
    let budget = Arc::new(tokio::sync::Semaphore::new(budget_kib as usize));
    let sender = tokio::spawn(async move {
        while let Some((wave, permit)) = waiting.recv().await {
            for answer in wave.await {
                if out.send(answer).await.is_err() {
                    return;
                }
            }
            drop(permit);
        }
    });
    let failed = |status: E| -> Outgoing<M, E> { (Box::pin(std::future::ready(vec![Err(status)])), None) };
    let mut pending: Option<(T, WaveRequest)> = None;
    loop {
        let (tag, first) = match pending.take() {
            Some(r) => r,
            None => match inbound.next().await {
                Some(Ok(message)) => read(message),
                Some(Err(status)) => {
                    // An unreadable request (too large, not protobuf) or a broken
                    // connection: say why, if anyone still listens, and end the stream.
                    tracing::debug!(stream, "stream ended: {status}");
                    let _ = answers.send(failed(status)).await;
                    break;
                }
                None => break,
            },
        };
        // Gather a wave: requests already received, up to one that must wait for the
        // wave's answers (see `Wave::admits`).
        let mut wave = Wave::default();
        wave.push(tag, first);
        let mut end: Option<Option<E>> = None;
        while wave.len() < episodes.config.max_batch {
            match ready_now(&mut inbound) {
                Some(Some(Ok(message))) => {
                    let (tag, r) = read(message);
                    if !wave.admits(&r) {
                        pending = Some((tag, r));
                        break;
                    }
                    wave.push(tag, r);
                }
                // The end, or an unreadable request: answer the wave, then end as above.
                Some(Some(Err(status))) => {
                    end = Some(Some(status));
                    break;
                }
                Some(None) => {
                    end = Some(None);
                    break;
                }
                None => break,
            }
        }
        let (wave, bytes) = answer_wave(&episodes, &slot.caller, wave, stream).await;
        let wave: Messages<M, E> =
            Box::pin(async move { wave.await.into_iter().map(|(tag, answer)| Ok(write(tag, answer))).collect() });
        // Wait while the answers of earlier waves hold the stream's byte budget (a wave
        // larger than the whole budget waits for all of it), so that a client that sends
        // faster than it reads cannot make the server hold more than about one message
        // limit of answers per stream, beyond one wave.
        let kib = (bytes / 1024).clamp(1, budget_kib as usize) as u32;
        let Ok(permit) = budget.clone().acquire_many_owned(kib).await else { break };
        // The sender has stopped: the client is gone.
        if answers.send((wave, Some(permit))).await.is_err() {
            break;
        }
        if let Some(end) = end {
            if let Some(status) = end {
                tracing::debug!(stream, "stream ended: {status}");
                let _ = answers.send(failed(status)).await;
            }
            break;
        }
    }
    // Every answer is sent (or the client is gone) before the stream's episodes close.
    drop(answers);
    let _ = sender.await;
    lifecycle::end_stream(&episodes, stream).await;
    drop(slot);
}

/// An open stream's place in its caller's `max_streams` quota: given back when dropped.
pub struct StreamSlot {
    episodes: Arc<Episodes>,
    /// The stream's caller.
    pub caller: Arc<Caller>,
    /// The stream's id: the episodes created with it are the stream's (no idle reaping; closed
    /// when it ends, `Episodes::end_stream`).
    pub id: u64,
}

impl StreamSlot {
    /// Opens a stream for `caller`, within its `max_streams` quota.
    pub fn open(episodes: &Arc<Episodes>, caller: Arc<Caller>) -> Result<Self, ServiceError> {
        let mut streams = episodes.streams.lock().unwrap_or_else(|p| p.into_inner());
        let open = streams.entry(caller.name.clone()).or_default();
        if let Some(limit) = caller.max_streams
            && *open >= limit
        {
            return Err(ServiceError::Quota {
                caller: caller.describe(),
                what: "streams",
                quota: "max_streams",
                limit,
            });
        }
        *open += 1;
        let id = episodes.next_stream.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        Ok(Self { episodes: episodes.clone(), caller, id })
    }
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        let mut streams = self.episodes.streams.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(open) = streams.get_mut(&self.caller.name) {
            *open = open.saturating_sub(1);
            if *open == 0 {
                streams.remove(&self.caller.name);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step(episode: &str) -> WaveRequest {
        WaveRequest::Step(StepCall {
            episode: episode.into(),
            action: esrp_core::Action::TurnLeft,
            include_goal: false,
        })
    }

    fn reset(episode: &str) -> WaveRequest {
        WaveRequest::Reset { episode: episode.into(), scene: None }
    }

    /// Pushes `requests` in order; each must be admitted as `expected` says (a refused one is
    /// not pushed).
    fn check(requests: Vec<(WaveRequest, bool)>) {
        let mut wave = Wave::default();
        for (i, (request, expected)) in requests.into_iter().enumerate() {
            assert_eq!(wave.admits(&request), expected, "request {i}: {request:?}");
            if expected {
                wave.push(i, request);
            }
        }
    }

    #[test]
    fn a_wave_admits_what_its_order_of_work_cannot_change() {
        // Several steps of one episode run in request order.
        check(vec![(step("a"), true), (step("a"), true), (step("b"), true)]);
        // A reset or close of a stepped episode waits for the next wave, and so does a step
        // of an episode reset in the wave.
        check(vec![(step("a"), true), (reset("a"), false), (WaveRequest::Close("a".into()), false)]);
        check(vec![(reset("a"), true), (step("a"), false), (reset("a"), false), (reset("b"), true)]);
        // A create always opens the next wave; an unreadable request answers in place.
        let create = WaveRequest::Create(CreateOptions {
            scene: SceneChoice::FromSplit { split: None, seed: 0 },
            sensors: Default::default(),
            horizon: None,
            reward: Default::default(),
            privileged: false,
            agent: None,
            keep_record: false,
        });
        check(vec![
            (step("a"), true),
            (create, false),
            (WaveRequest::Invalid(ServiceError::Internal("x".into())), true),
        ]);
    }
}
