//! The `esrp.v1.Esrp` adapter: thin tonic handlers over [`Episodes`]. Each converts its request
//! into core types at the edge ([`convert`]), calls the episode layer, and converts the answer
//! back; a [`ServiceError`] becomes a `tonic::Status` by its one mapping. StepStream's protocol
//! (`StreamRequest`, `StreamResponse`) ends here: its waves run in
//! [`crate::episodes::waves`].

pub mod answered;
pub mod convert;

use std::pin::Pin;
use std::sync::Arc;

use tokio::sync::mpsc;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

use crate::auth::caller_of;
use crate::episodes::Episodes;
use crate::episodes::waves::{self, WaveAnswer, WaveRequest};
use crate::error::ServiceError;
use crate::proto;
use crate::quote::quoted;
use crate::types::{CreateOptions, EpisodeId, PlanCall, StepCall};

/// The tonic service.
#[derive(Clone)]
pub struct EsrpService {
    episodes: Arc<Episodes>,
}

impl EsrpService {
    /// A service over `episodes`.
    pub fn new(episodes: Arc<Episodes>) -> Self {
        Self { episodes }
    }
}

/// Milliseconds of `duration`, said as the longest a u32 holds when it is longer (49 days).
fn clamp_ms(duration: std::time::Duration) -> u32 {
    u32::try_from(duration.as_millis()).unwrap_or(u32::MAX)
}

/// A StreamRequest as a tagged wave request (the tag is its request id).
fn read_stream_request(r: proto::StreamRequest) -> (u64, WaveRequest) {
    use proto::stream_request::Request as Rq;
    let request = match r.request {
        Some(Rq::Create(c)) => CreateOptions::try_from(c).map_or_else(WaveRequest::Invalid, WaveRequest::Create),
        Some(Rq::Step(s)) => StepCall::try_from(s).map_or_else(WaveRequest::Invalid, WaveRequest::Step),
        Some(Rq::Reset(r)) => {
            let (episode, scene) = convert::reset_of(r);
            WaveRequest::Reset { episode, scene }
        }
        Some(Rq::Close(c)) => WaveRequest::Close(c.episode_id.into()),
        None => WaveRequest::Invalid(ServiceError::InvalidArgument(
            "empty StreamRequest: set create, step, reset or close".into(),
        )),
    };
    (r.request_id, request)
}

/// The StreamResponse of an answer; an error travels in-band with its gRPC code.
fn write_stream_response(request_id: u64, answer: Result<WaveAnswer, ServiceError>) -> proto::StreamResponse {
    use proto::stream_response::Response as Rs;
    let response = match answer {
        Ok(WaveAnswer::Created(c)) => Rs::Created((*c).into()),
        Ok(WaveAnswer::Stepped(s)) => Rs::Step((*s).into()),
        Ok(WaveAnswer::Reset(r)) => Rs::Reset((*r).into()),
        Ok(WaveAnswer::Closed(m)) => {
            Rs::Closed(proto::CloseEpisodeResponse { metrics: Some(convert::metrics_to_proto(&m)) })
        }
        Err(e) => {
            let status = Status::from(e);
            Rs::Error(proto::StreamError { code: status.code() as i32, message: status.message().to_owned() })
        }
    };
    proto::StreamResponse { request_id, response: Some(response) }
}

type StreamOut = Pin<Box<dyn Stream<Item = Result<proto::StreamResponse, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl proto::esrp_server::Esrp for EsrpService {
    async fn server_info(
        &self,
        request: Request<proto::ServerInfoRequest>,
    ) -> Result<Response<proto::ServerInfoResponse>, Status> {
        let caller = caller_of(&request);
        let s = &self.episodes;
        let renderer = s.render.renderer();
        let info = renderer.adapter_info();
        Ok(Response::new(proto::ServerInfoResponse {
            version: env!("CARGO_PKG_VERSION").to_owned(),
            renderer_adapter: info.name.clone(),
            renderer_backend: format!("{:?}", info.backend).to_lowercase(),
            software_renderer: renderer.is_software(),
            limits: Some(proto::ServerLimits {
                // The flags keep the first three within u32; a longer idle timeout than u32 seconds
                // (136 years) is said as the longest.
                max_episodes: u32::try_from(s.config.max_episodes).unwrap_or(u32::MAX),
                max_batch: u32::try_from(s.config.max_batch).unwrap_or(u32::MAX),
                max_message_bytes: u32::try_from(s.config.max_message_bytes).unwrap_or(u32::MAX),
                idle_timeout_seconds: u32::try_from(s.config.idle_timeout_seconds).unwrap_or(u32::MAX),
                max_resolution: s.max_resolution(),
                plan_budget_ms: clamp_ms(s.config.plan_budget().min(s.config.max_plan())),
                max_plan_ms: clamp_ms(s.config.max_plan()),
            }),
            live_episodes: s.live() as u32,
            dataset: s.store.name().to_owned(),
            caller: caller.name.to_string(),
            role: caller.role.as_str().to_owned(),
            challenge: s.store.has_hidden(),
            recording: s.recorder.as_ref().map_or("", |r| r.mode().as_str()).to_owned(),
            renderer_rasterizer: renderer.rasterizer().name().to_owned(),
        }))
    }

    async fn describe_dataset(
        &self,
        _: Request<proto::DescribeDatasetRequest>,
    ) -> Result<Response<proto::DescribeDatasetResponse>, Status> {
        let store = &self.episodes.store;
        let [by_split, by_difficulty, by_room_type] = store.counts();
        Ok(Response::new(proto::DescribeDatasetResponse {
            name: store.name().to_owned(),
            scenes: store.infos().len() as u32,
            by_split: by_split.into_iter().collect(),
            by_difficulty: by_difficulty.into_iter().collect(),
            by_room_type: by_room_type.into_iter().collect(),
            source: store.description().to_owned(),
        }))
    }

    async fn list_scenes(
        &self,
        request: Request<proto::ListScenesRequest>,
    ) -> Result<Response<proto::ListScenesResponse>, Status> {
        let r = request.into_inner();
        let split = convert::split_of(r.split)?;
        let difficulty = convert::difficulty_of(r.difficulty)?;
        let page_size = match r.page_size {
            0 => 100,
            n @ 1..=1000 => n as usize,
            n => return Err(ServiceError::InvalidArgument(format!("page_size {n} is too large: at most 1000")).into()),
        };
        let start: usize = if r.page_token.is_empty() {
            0
        } else {
            r.page_token.parse().map_err(|_| {
                ServiceError::InvalidArgument(format!(
                    "page_token {} is not one this server gave",
                    quoted(&r.page_token)
                ))
            })?
        };
        let infos = self.episodes.store.infos();
        let mut scenes = Vec::new();
        let mut next = infos.len();
        for (i, info) in infos.iter().enumerate().skip(start) {
            if split.is_some_and(|s| s != info.split) || difficulty.is_some_and(|d| d != info.difficulty) {
                continue;
            }
            if scenes.len() == page_size {
                next = i;
                break;
            }
            scenes.push(info.into());
        }
        let next_page_token = if next < infos.len() { next.to_string() } else { String::new() };
        Ok(Response::new(proto::ListScenesResponse { scenes, next_page_token }))
    }

    async fn create_episode(
        &self,
        request: Request<proto::CreateEpisodeRequest>,
    ) -> Result<Response<proto::CreateEpisodeResponse>, Status> {
        let caller = caller_of(&request);
        let options = CreateOptions::try_from(request.into_inner())?;
        // The episode lives only if this answer is sent ([`answered`]): a dropped call, or a
        // dropped answer, drops the guard and closes the episode.
        let (created, unanswered) = self.episodes.create_unanswered(&caller, options, None).await?;
        let mut response = Response::new(created.into());
        response.extensions_mut().insert(unanswered);
        Ok(response)
    }

    async fn reset(&self, request: Request<proto::ResetRequest>) -> Result<Response<proto::ResetResponse>, Status> {
        let caller = caller_of(&request);
        let (episode, scene) = convert::reset_of(request.into_inner());
        Ok(Response::new(self.episodes.reset(&caller, &episode, scene).await?.into()))
    }

    async fn step(&self, request: Request<proto::StepRequest>) -> Result<Response<proto::StepResponse>, Status> {
        let caller = caller_of(&request);
        let step = StepCall::try_from(request.into_inner())?;
        let result = self.episodes.step_many(&caller, vec![step]).await?.pop();
        let result = result.ok_or_else(|| ServiceError::Internal("a step without an answer".into()))?;
        Ok(Response::new(result.into()))
    }

    async fn step_batch(
        &self,
        request: Request<proto::StepBatchRequest>,
    ) -> Result<Response<proto::StepBatchResponse>, Status> {
        let caller = caller_of(&request);
        let proto::StepBatchRequest { steps, resets } = request.into_inner();
        // The limit first: a batch too large is refused before any of it is read.
        self.episodes.check_batch_len(steps.len() + resets.len())?;
        let resets = resets.into_iter().map(convert::reset_call).collect();
        let (stepped, reset) = self.episodes.step_batch(&caller, convert::step_calls(steps)?, resets).await?;
        Ok(Response::new(proto::StepBatchResponse {
            responses: stepped.into_iter().map(Into::into).collect(),
            resets: reset.into_iter().map(Into::into).collect(),
        }))
    }

    type StepStreamStream = StreamOut;

    async fn step_stream(
        &self,
        request: Request<Streaming<proto::StreamRequest>>,
    ) -> Result<Response<Self::StepStreamStream>, Status> {
        // The quota first: a stream beyond the token's max_streams is refused as a whole.
        let slot = self.episodes.open_stream(caller_of(&request))?;
        let (out, receiver) = mpsc::channel(256);
        let episodes = self.episodes.clone();
        tokio::spawn(waves::serve(
            episodes,
            slot,
            request.into_inner(),
            out,
            read_stream_request,
            write_stream_response,
        ));
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(receiver))))
    }

    async fn get_goal(
        &self,
        request: Request<proto::GetGoalRequest>,
    ) -> Result<Response<proto::GetGoalResponse>, Status> {
        let caller = caller_of(&request);
        let episode = EpisodeId::from(request.into_inner().episode_id);
        Ok(Response::new(self.episodes.goal(&caller, &episode).await?.into()))
    }

    async fn get_privileged_state(
        &self,
        request: Request<proto::GetPrivilegedStateRequest>,
    ) -> Result<Response<proto::GetPrivilegedStateResponse>, Status> {
        let caller = caller_of(&request);
        let episode = EpisodeId::from(request.into_inner().episode_id);
        Ok(Response::new(self.episodes.privileged_state(&caller, &episode).await?.into()))
    }

    async fn plan_actions(
        &self,
        request: Request<proto::PlanActionsRequest>,
    ) -> Result<Response<proto::PlanActionsResponse>, Status> {
        let caller = caller_of(&request);
        let call = PlanCall::from(request.into_inner());
        Ok(Response::new(self.episodes.plan(&caller, call).await?.into()))
    }

    async fn get_metrics(
        &self,
        request: Request<proto::GetMetricsRequest>,
    ) -> Result<Response<proto::GetMetricsResponse>, Status> {
        let caller = caller_of(&request);
        let episode = EpisodeId::from(request.into_inner().episode_id);
        Ok(Response::new(self.episodes.metrics(&caller, &episode).await?.into()))
    }

    async fn close_episode(
        &self,
        request: Request<proto::CloseEpisodeRequest>,
    ) -> Result<Response<proto::CloseEpisodeResponse>, Status> {
        let caller = caller_of(&request);
        let episode = EpisodeId::from(request.into_inner().episode_id);
        let metrics = self.episodes.close(&caller, &episode).await?;
        Ok(Response::new(proto::CloseEpisodeResponse { metrics: Some(convert::metrics_to_proto(&metrics)) }))
    }
}
