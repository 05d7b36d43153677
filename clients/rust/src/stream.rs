//! [`EpisodeStream`]: a pipelined driver of one `StepStream`. It keeps up to `window` steps of
//! each episode in flight and hands the answers back in request order, so an agent that sends
//! action chunks (or a replay, or many episodes at once) gets its steps taken back to back and
//! rendered in batches, without writing the bookkeeping itself.

use std::collections::{HashMap, VecDeque};

use tokio::sync::mpsc;
use tokio_stream::wrappers::UnboundedReceiverStream;

use crate::error::{ClientError, Result};
use crate::proto;
use crate::proto::stream_request::Request as Rq;
use crate::proto::stream_response::Response as Rs;
use crate::raw::RawClient;
use crate::types::{Action, EpisodeMetrics, EpisodeOptions, Observation, SceneSummary, StepResult};

/// What a stream request did.
#[derive(Clone, Debug, PartialEq)]
pub enum Answer {
    /// An episode was created on the stream (it is closed when the stream ends).
    Created {
        /// Its first observation (with the goal image).
        observation: Observation,
        /// Its scene.
        scene: SceneSummary,
    },
    /// A step was taken.
    Step(StepResult),
    /// An episode was reset; its first observation (with the goal image).
    Reset(Observation),
    /// An episode was closed; its final metrics.
    Closed(EpisodeMetrics),
}

/// One answer of the stream, in request order.
#[derive(Debug)]
pub struct StreamAnswer {
    /// The id [`EpisodeStream`] gave the request (counting from 1 in sending order).
    pub request_id: u64,
    /// The episode the request was about (for a create: the new episode's id, or empty if it
    /// failed).
    pub episode_id: String,
    /// The answer, or the error the server gave this request alone (the stream goes on).
    pub result: Result<Answer>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Create,
    Step,
    Reset,
    Close,
}

/// A request sent and not yet answered.
#[derive(Debug)]
struct Pending {
    request_id: u64,
    kind: Kind,
    episode_id: String,
}

/// A `StepStream` with up to `window` steps of each episode in flight. Sending a step of an
/// episode that already has `window` steps in flight first reads answers (kept, and returned
/// by [`EpisodeStream::next`] in order) until one of its steps is answered. Answers always
/// come in request order, exactly as the same requests made one by one would answer.
///
/// ```no_run
/// # async fn demo(client: esrp_client::Client, episode_id: &str) -> Result<(), esrp_client::ClientError> {
/// use esrp_client::{Action, Answer};
/// let mut stream = client.episode_stream(8).await?;
/// for action in [Action::TurnLeft, Action::MoveForward, Action::Fetch] {
///     stream.step(episode_id, action).await?; // returns at once while fewer than 8 are in flight
/// }
/// while let Some(answer) = stream.next().await? {
///     if let Answer::Step(result) = answer.result? {
///         println!("reward {}", result.reward);
///     }
/// }
/// # Ok(()) }
/// ```
#[derive(Debug)]
pub struct EpisodeStream {
    requests: mpsc::UnboundedSender<proto::StreamRequest>,
    answers: tonic::Streaming<proto::StreamResponse>,
    pending: VecDeque<Pending>,
    /// Answers read while making room for a step, not yet returned by `next`.
    ready: VecDeque<StreamAnswer>,
    steps_in_flight: HashMap<String, usize>,
    window: usize,
    next_request_id: u64,
}

impl EpisodeStream {
    pub(crate) async fn open(mut raw: RawClient, window: usize) -> Result<Self> {
        if window == 0 {
            return Err(ClientError::Config("an episode stream needs a window of at least 1".into()));
        }
        // Unbounded on our side: the window bounds what is in flight, and a bounded channel
        // could block a sender that must first read answers the server is waiting to send.
        let (requests, receiver) = mpsc::unbounded_channel();
        let answers = raw.step_stream(UnboundedReceiverStream::new(receiver)).await?.into_inner();
        Ok(EpisodeStream {
            requests,
            answers,
            pending: VecDeque::new(),
            ready: VecDeque::new(),
            steps_in_flight: HashMap::new(),
            window,
            next_request_id: 1,
        })
    }

    /// The most steps of one episode in flight.
    pub fn window(&self) -> usize {
        self.window
    }

    /// Requests sent and not yet returned by [`EpisodeStream::next`].
    pub fn outstanding(&self) -> usize {
        self.pending.len() + self.ready.len()
    }

    fn send(&mut self, kind: Kind, episode_id: &str, request: Rq) -> Result<u64> {
        let request_id = self.next_request_id;
        self.next_request_id += 1;
        self.requests
            .send(proto::StreamRequest { request_id, request: Some(request) })
            .map_err(|_| ClientError::Unavailable("the stream has ended".into()))?;
        self.pending.push_back(Pending { request_id, kind, episode_id: episode_id.to_owned() });
        if kind == Kind::Step {
            *self.steps_in_flight.entry(episode_id.to_owned()).or_default() += 1;
        }
        Ok(request_id)
    }

    /// Sends a step of `episode_id`; first waits (reading answers) while the episode has
    /// `window` steps in flight. Returns the request's id.
    pub async fn step(&mut self, episode_id: &str, action: Action) -> Result<u64> {
        while self.steps_in_flight.get(episode_id).copied().unwrap_or(0) >= self.window {
            let answer = self.read().await?;
            self.ready.push_back(answer);
        }
        let step = proto::StepRequest {
            episode_id: episode_id.to_owned(),
            action: i32::from(action.code()),
            include_goal: false,
        };
        self.send(Kind::Step, episode_id, Rq::Step(step))
    }

    /// Sends a reset of `episode_id` (same scene).
    pub fn reset(&mut self, episode_id: &str) -> Result<u64> {
        let reset = proto::ResetRequest { episode_id: episode_id.to_owned(), scene: None };
        self.send(Kind::Reset, episode_id, Rq::Reset(reset))
    }

    /// Sends a close of `episode_id`.
    pub fn close(&mut self, episode_id: &str) -> Result<u64> {
        let close = proto::CloseEpisodeRequest { episode_id: episode_id.to_owned() };
        self.send(Kind::Close, episode_id, Rq::Close(close))
    }

    /// Sends a create. The episode lives as long as the stream; its id comes in the answer.
    /// Options the server would misread (an empty scene id) fail here, and nothing is sent.
    pub fn create(&mut self, options: &EpisodeOptions) -> Result<u64> {
        options.check()?;
        self.send(Kind::Create, "", Rq::Create(options.to_proto()))
    }

    /// The next answer in request order; `None` when every request sent has been answered.
    /// An error here means the stream itself failed (it cannot go on).
    pub async fn next(&mut self) -> Result<Option<StreamAnswer>> {
        if let Some(answer) = self.ready.pop_front() {
            return Ok(Some(answer));
        }
        if self.pending.is_empty() {
            return Ok(None);
        }
        self.read().await.map(Some)
    }

    /// Reads the answer of the oldest pending request.
    async fn read(&mut self) -> Result<StreamAnswer> {
        let Some(pending) = self.pending.pop_front() else {
            return Err(ClientError::Protocol("read past the last request".into()));
        };
        if pending.kind == Kind::Step
            && let Some(n) = self.steps_in_flight.get_mut(&pending.episode_id)
        {
            *n -= 1;
            if *n == 0 {
                self.steps_in_flight.remove(&pending.episode_id);
            }
        }
        let response =
            self.answers.message().await?.ok_or_else(|| {
                ClientError::Unavailable("the server ended the stream with requests unanswered".into())
            })?;
        if response.request_id != pending.request_id {
            return Err(ClientError::Protocol(format!(
                "answer to request {} where request {} was due",
                response.request_id, pending.request_id
            )));
        }
        let mut episode_id = pending.episode_id;
        let result = match (pending.kind, response.response) {
            (_, Some(Rs::Error(e))) => Err(ClientError::from_code(tonic::Code::from(e.code), e.message)),
            (Kind::Create, Some(Rs::Created(created))) => {
                episode_id = created.episode_id;
                match (created.observation, created.scene) {
                    (Some(o), Some(scene)) => {
                        o.try_into().map(|observation| Answer::Created { observation, scene: scene.into() })
                    }
                    _ => Err(ClientError::Protocol("a create answer without observation or scene".into())),
                }
            }
            (Kind::Step, Some(Rs::Step(step))) => step.try_into().map(Answer::Step),
            (Kind::Reset, Some(Rs::Reset(reset))) => reset
                .observation
                .ok_or_else(|| ClientError::Protocol("a reset answer without observation".into()))
                .and_then(Observation::try_from)
                .map(Answer::Reset),
            (Kind::Close, Some(Rs::Closed(closed))) => closed
                .metrics
                .map(|m| Answer::Closed(m.into()))
                .ok_or_else(|| ClientError::Protocol("a close answer without metrics".into())),
            (kind, other) => Err(ClientError::Protocol(format!("a {kind:?} request answered with {other:?}"))),
        };
        Ok(StreamAnswer { request_id: pending.request_id, episode_id, result })
    }

    /// Takes every episode's actions on this stream, up to `window` steps of each in flight,
    /// episodes interleaved; returns each episode's step results in order (an error for a
    /// step the server refused, e.g. one sent after its episode ended).
    pub async fn run(&mut self, plans: &[(&str, &[Action])]) -> Result<Vec<Vec<Result<StepResult>>>> {
        let index: HashMap<&str, usize> = plans.iter().enumerate().map(|(i, (id, _))| (*id, i)).collect();
        if index.len() != plans.len() {
            return Err(ClientError::Config("each episode may appear once in a run".into()));
        }
        let mut results: Vec<Vec<Result<StepResult>>> =
            plans.iter().map(|(_, a)| Vec::with_capacity(a.len())).collect();
        let collect = |answer: StreamAnswer, results: &mut Vec<Vec<Result<StepResult>>>| -> Result<()> {
            let Some(&i) = index.get(answer.episode_id.as_str()) else {
                return Err(ClientError::Config(format!(
                    "answer for episode {:?} outside the run: read earlier requests with next() first",
                    answer.episode_id
                )));
            };
            results[i].push(answer.result.and_then(|a| match a {
                Answer::Step(step) => Ok(step),
                other => Err(ClientError::Protocol(format!("a step answered with {other:?}"))),
            }));
            Ok(())
        };
        if !self.ready.is_empty() || !self.pending.is_empty() {
            return Err(ClientError::Config("read the stream's earlier answers with next() before a run".into()));
        }
        let longest = plans.iter().map(|(_, a)| a.len()).max().unwrap_or(0);
        for k in 0..longest {
            for (id, actions) in plans {
                if let Some(&action) = actions.get(k) {
                    self.step(id, action).await?;
                }
            }
            while let Some(answer) = self.ready.pop_front() {
                collect(answer, &mut results)?;
            }
        }
        while let Some(answer) = self.next().await? {
            collect(answer, &mut results)?;
        }
        Ok(results)
    }
}
