//! The `dm_env_rpc.v1.Environment` service: ESRP behind the dm_env_rpc protocol, so that
//! `dm_env_rpc`'s `DmEnvAdaptor` (and any other client of that protocol) runs ESRP episodes.
//!
//! A **world** is one ESRP episode with the settings that made it (CreateWorld); a connection
//! **joins** a world to become its only agent (the task is single-agent); each **sequence** of
//! the agent is one run of the episode from its start. Every request is answered by the same
//! [`Episodes`] calls as `esrp.v1` (`create`, `reset`, `step_many`, `close`), in core types, so
//! the rules, the rendering and the limits are the native API's. Tensors and settings convert
//! at this edge ([`convert`]); nothing here builds or decodes an `esrp.v1` message.
//!
//! # Settings
//!
//! CreateWorld accepts (all optional; any other name is an INVALID_ARGUMENT error):
//!
//! | name | tensor | meaning |
//! |---|---|---|
//! | `scene` | string | scene id of the served dataset, not empty (absent: chosen by `split` and `seed`) |
//! | `split` | string `"train"`, `"test"`, `"challenge"` or `"minival"` | split to choose from when `scene` is absent (default test) |
//! | `seed` | integer ≥ 0 | which scene of the split: index `seed mod count` (default 0: the first) |
//! | `horizon` | integer ≥ 0 | step limit; 0 or absent: the scene's own |
//! | `resolution` | integer 16..=512 | square image side in pixels (default 128) |
//! | `ego_depth`, `ego_segmentation`, `current_top_down` | bool | optional sensors (default off) |
//! | `agent` | string | the agent's name in the server's records (at most 200 bytes) |
//!
//! ResetWorld accepts `scene` (switch the world to another scene). JoinWorld and Reset accept
//! no settings.
//!
//! # Specs
//!
//! One action, uid 1: `action`, INT32 scalar, bounds 0..=5 (SPEC §3: 0 move forward, 1 move
//! backward, 2 turn left, 3 turn right, 4 fetch, 5 release). It is required on every step of a
//! running sequence. Observations, uids from 1 in this order: `ego_rgb` UINT8 `[R, R, 3]`,
//! `goal_rgb` UINT8 `[R, R, 3]`, `grasping` BOOL scalar, then the optional sensors
//! (`ego_depth` FLOAT `[R, R]`, `ego_segmentation` UINT32 `[R, R]`, `current_top_down` UINT8
//! `[R, R, 3]`) when on, then `reward` DOUBLE scalar and `discount` DOUBLE scalar in `[0, 1]`.
//!
//! # States
//!
//! A step that starts a sequence (the first after JoinWorld or Reset, or after a step that
//! answered TERMINATED or INTERRUPTED) ignores its actions, restarts the episode unless it is
//! fresh, and answers RUNNING with reward 0. Otherwise the action is taken: success answers
//! TERMINATED (discount 0), reaching the horizon INTERRUPTED (discount 1, a truncation), else
//! RUNNING. A ResetWorld from another connection makes the agent's next step answer
//! INTERRUPTED (with the observations of the new sequence's start) before the new sequence.
//!
//! # Errors and lifetime
//!
//! Errors travel in-band (`EnvironmentResponse.error`, a `google.rpc.Status` with the gRPC
//! code and a message saying what to change) and the stream goes on. A world is its creating
//! token's: only that token (or an admin) may join, reset or destroy it. When a stream ends, its
//! connection leaves its world and the worlds it created are destroyed (their episodes closed);
//! an agent still joined to one of them (from another connection) is answered NOT_FOUND on Step
//! and Reset until it sends LeaveWorld.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::mpsc;
use tokio_stream::StreamExt;
use tonic::{Request, Response, Status, Streaming};

use crate::auth::caller_of;
use crate::episodes::{Episodes, StreamSlot};
use crate::error::ServiceError;
use crate::quote::quoted;
use crate::types::{Caller, EpisodeId, Observation, StepCall};

pub mod convert;
mod error;

pub use convert::{ACTION_NAME, ACTION_UID, CREATE_WORLD_SETTINGS, MAX_ACTION};
use convert::{action_of, create_options, no_settings, observation_tensor, reset_world_scene, specs_of};
pub use error::DmEnvError;

/// Generated protobuf messages and gRPC stubs of `dm_env_rpc.v1` and the `google.rpc` and
/// `google.protobuf` messages it uses (from esrp-proto).
pub use esrp_proto as wire;

use wire::dm_env_rpc::v1 as dm;
use wire::dm_env_rpc::v1::environment_request::Payload as Rq;
use wire::dm_env_rpc::v1::environment_response::Payload as Rs;

// Worlds and connections.

/// A world: one ESRP episode and what the dm_env_rpc side keeps beside it.
struct World {
    /// The native episode.
    episode_id: EpisodeId,
    specs: dm::ActionObservationSpecs,
    /// Observation names by uid - 1.
    observation_names: Arc<[String]>,
    /// The connection that created it (the world ends with it).
    creator: u64,
    /// The token that created it: only it (or an admin) may join it.
    owner: Arc<str>,
    /// The joined connection, if any.
    agent: Option<u64>,
    /// Bumped by ResetWorld, so that the agent learns its sequence was interrupted.
    generation: u64,
    /// The first observation of an episode not stepped since it was created or reset: the next
    /// sequence starts from it without restarting the episode.
    fresh: Option<Observation>,
    /// Held by a ResetWorld from its episode's reset to its generation's bump, and by the agent's
    /// Step from its look at the generation to its answer: a step sent while another connection
    /// resets the world is taken before the reset or answered INTERRUPTED after it, never taken
    /// in the new sequence behind the agent's back.
    turn: Arc<tokio::sync::Mutex<()>>,
}

/// The live worlds of every connection, by name.
#[derive(Default)]
pub struct Worlds {
    // A std mutex: held only for map operations, never across an await.
    map: Mutex<HashMap<String, World>>,
    next_connection: AtomicU64,
}

impl Worlds {
    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<String, World>> {
        // Every operation is a single insert, remove or field update, so a poisoned map is
        // still consistent.
        self.map.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// Number of live worlds.
    pub fn len(&self) -> usize {
        self.map().len()
    }

    /// Whether no world is live.
    pub fn is_empty(&self) -> bool {
        self.map().is_empty()
    }
}

/// The world a connection has joined.
struct Joined {
    world: String,
    episode_id: EpisodeId,
    specs: dm::ActionObservationSpecs,
    observation_names: Arc<[String]>,
    /// The world's generation this connection last saw.
    generation: u64,
    /// Whether a sequence is running (its next step takes the action).
    running: bool,
    /// The world's [`World::turn`].
    turn: Arc<tokio::sync::Mutex<()>>,
}

/// One stream: its joined world and the worlds it created.
struct Connection {
    id: u64,
    /// The connection's place in its token's `max_streams`; its caller acts in every call.
    slot: StreamSlot,
    episodes: Arc<Episodes>,
    worlds: Arc<Worlds>,
    joined: Option<Joined>,
}

impl Connection {
    /// Answers requests one by one, in order, until the client closes the stream or goes away;
    /// then leaves and destroys this connection's worlds.
    async fn serve(
        mut self,
        mut inbound: Streaming<dm::EnvironmentRequest>,
        out: mpsc::Sender<Result<dm::EnvironmentResponse, Status>>,
    ) {
        loop {
            let request = match inbound.next().await {
                Some(Ok(request)) => request,
                Some(Err(status)) => {
                    tracing::debug!(connection = self.id, "dm_env_rpc stream ended by the client: {status}");
                    break;
                }
                None => break,
            };
            let payload = match request.payload {
                Some(request) => self.answer(request).await.unwrap_or_else(|e| {
                    tracing::debug!(connection = self.id, "dm_env_rpc request failed: {e}");
                    Rs::Error(e.into())
                }),
                None => Rs::Error(DmEnvError::EmptyRequest.into()),
            };
            if out.send(Ok(dm::EnvironmentResponse { payload: Some(payload) })).await.is_err() {
                break;
            }
        }
        self.finish().await;
    }

    async fn answer(&mut self, request: Rq) -> Result<Rs, DmEnvError> {
        match request {
            Rq::CreateWorld(r) => self.create_world(r).await.map(Rs::CreateWorld),
            Rq::JoinWorld(r) => self.join_world(r).map(Rs::JoinWorld),
            Rq::Step(r) => self.step(r).await.map(Rs::Step),
            Rq::Reset(r) => self.reset(r).map(Rs::Reset),
            Rq::ResetWorld(r) => self.reset_world(r).await.map(Rs::ResetWorld),
            Rq::LeaveWorld(_) => {
                self.leave_world();
                Ok(Rs::LeaveWorld(dm::LeaveWorldResponse {}))
            }
            Rq::DestroyWorld(r) => self.destroy_world(r).await.map(Rs::DestroyWorld),
            Rq::Extension(any) => Err(DmEnvError::Unimplemented(format!(
                "extension {} is not implemented: esrp-server has no dm_env_rpc extensions",
                quoted(&any.type_url)
            ))),
        }
    }

    async fn create_world(&mut self, request: dm::CreateWorldRequest) -> Result<dm::CreateWorldResponse, DmEnvError> {
        let options = create_options(request.settings)?;
        // The connection's own, as a StepStream's: never closed as idle while it is open (an agent
        // may think for long between steps), closed when it ends.
        let created = self.episodes.create(&self.slot.caller, options, Some(self.slot.id)).await?;
        // The world holds the episode from here (and closes it with the connection).
        self.episodes.claim(&created.episode);
        let (specs, observation_names) = specs_of(&created.sensors);
        let world_name = format!("esrp-world-{}", uuid::Uuid::new_v4().simple());
        let world = World {
            episode_id: created.episode,
            specs,
            observation_names: observation_names.into(),
            creator: self.id,
            owner: self.slot.caller.name.clone(),
            agent: None,
            generation: 0,
            fresh: Some(created.observation),
            turn: Arc::default(),
        };
        tracing::debug!(connection = self.id, world = %world_name, episode = %world.episode_id, "world created");
        self.worlds.map().insert(world_name.clone(), world);
        Ok(dm::CreateWorldResponse { world_name })
    }

    fn join_world(&mut self, request: dm::JoinWorldRequest) -> Result<dm::JoinWorldResponse, DmEnvError> {
        if let Some(joined) = &self.joined {
            return Err(DmEnvError::AlreadyJoined(joined.world.clone()));
        }
        no_settings("JoinWorld", &request.settings)?;
        let mut map = self.worlds.map();
        let world =
            map.get_mut(&request.world_name).ok_or_else(|| DmEnvError::UnknownWorld(request.world_name.clone()))?;
        may_use(&self.slot.caller, &request.world_name, world)?;
        if world.agent.is_some() {
            return Err(DmEnvError::WorldTaken(request.world_name));
        }
        world.agent = Some(self.id);
        self.joined = Some(Joined {
            world: request.world_name,
            episode_id: world.episode_id.clone(),
            specs: world.specs.clone(),
            observation_names: world.observation_names.clone(),
            generation: world.generation,
            running: false,
            turn: world.turn.clone(),
        });
        Ok(dm::JoinWorldResponse { specs: Some(world.specs.clone()) })
    }

    async fn step(&mut self, request: dm::StepRequest) -> Result<dm::StepResponse, DmEnvError> {
        let joined = self.joined.as_mut().ok_or(DmEnvError::NotJoined)?;
        // Each requested observation once, in the order asked.
        let mut requested: Vec<u64> = Vec::with_capacity(request.requested_observations.len());
        for &uid in &request.requested_observations {
            if uid == 0 || uid > joined.observation_names.len() as u64 {
                return Err(DmEnvError::UnknownObservation(uid));
            }
            if !requested.contains(&uid) {
                requested.push(uid);
            }
        }
        let names = joined.observation_names.clone();
        let respond = |state: dm::EnvironmentStateType, mut observation: Observation, reward: f64, discount: f64| {
            let mut observations = HashMap::with_capacity(requested.len());
            for &uid in &requested {
                let tensor = observation_tensor(&names[uid as usize - 1], &mut observation, reward, discount)?;
                observations.insert(uid, tensor);
            }
            Ok::<_, DmEnvError>(dm::StepResponse { state: state as i32, observations })
        };

        // A ResetWorld sent by another connection interrupts the running sequence; one under way
        // finishes first.
        let _turn = joined.turn.clone().lock_owned().await;
        let reset_by_world = {
            let map = self.worlds.map();
            // Its creating connection ended while this one was joined: the episode is closed.
            let world = map.get(&joined.world).ok_or_else(|| DmEnvError::WorldGone(joined.world.clone()))?;
            (world.generation != joined.generation).then(|| (world.generation, world.fresh.clone()))
        };
        if let Some((generation, fresh)) = reset_by_world {
            joined.generation = generation;
            if joined.running {
                joined.running = false;
                if let Some(observation) = fresh {
                    return respond(dm::EnvironmentStateType::Interrupted, observation, 0.0, 1.0);
                }
            }
        }

        if !joined.running {
            // A new sequence: the actions are ignored.
            let fresh = self.worlds.map().get_mut(&joined.world).and_then(|w| w.fresh.take());
            let observation = match fresh {
                Some(observation) => observation,
                None => self.episodes.reset(&self.slot.caller, &joined.episode_id, None).await?.observation,
            };
            joined.running = true;
            return respond(dm::EnvironmentStateType::Running, observation, 0.0, 1.0);
        }

        let action = action_of(&request.actions)?;
        let include_goal = requested.iter().any(|&uid| names[uid as usize - 1] == "goal_rgb");
        let step = StepCall { episode: joined.episode_id.clone(), action, include_goal };
        let result = self
            .episodes
            .step_many(&self.slot.caller, vec![step])
            .await?
            .pop()
            .ok_or_else(|| ServiceError::Internal("a step without a response".into()))?;
        let outcome = result.outcome;
        let state = if outcome.terminated {
            dm::EnvironmentStateType::Terminated
        } else if outcome.truncated {
            dm::EnvironmentStateType::Interrupted
        } else {
            dm::EnvironmentStateType::Running
        };
        joined.running = state == dm::EnvironmentStateType::Running;
        let discount = if outcome.terminated { 0.0 } else { 1.0 };
        respond(state, result.observation, outcome.reward.total, discount)
    }

    fn reset(&mut self, request: dm::ResetRequest) -> Result<dm::ResetResponse, DmEnvError> {
        let joined = self.joined.as_mut().ok_or(DmEnvError::NotJoined)?;
        no_settings("Reset", &request.settings)?;
        if !self.worlds.map().contains_key(&joined.world) {
            return Err(DmEnvError::WorldGone(joined.world.clone()));
        }
        // The episode restarts when the next step starts the next sequence.
        joined.running = false;
        Ok(dm::ResetResponse { specs: Some(joined.specs.clone()) })
    }

    async fn reset_world(&mut self, request: dm::ResetWorldRequest) -> Result<dm::ResetWorldResponse, DmEnvError> {
        let scene = reset_world_scene(request.settings)?;
        let (episode_id, turn) = {
            let map = self.worlds.map();
            let world =
                map.get(&request.world_name).ok_or_else(|| DmEnvError::UnknownWorld(request.world_name.clone()))?;
            // Whose it is, before its episode is named: another token's world stays as it was.
            may_use(&self.slot.caller, &request.world_name, world)?;
            (world.episode_id.clone(), world.turn.clone())
        };
        // No step of the agent's between the reset and the bump of the generation below.
        let _turn = turn.lock_owned().await;
        let reset = self.episodes.reset(&self.slot.caller, &episode_id, scene).await?;
        let mut map = self.worlds.map();
        if let Some(world) = map.get_mut(&request.world_name) {
            world.generation += 1;
            world.fresh = Some(reset.observation);
            // The caller's own next step starts the new sequence, without an INTERRUPTED first.
            if let Some(joined) = self.joined.as_mut().filter(|j| j.world == request.world_name) {
                joined.generation = world.generation;
                joined.running = false;
            }
        }
        Ok(dm::ResetWorldResponse {})
    }

    fn leave_world(&mut self) {
        if let Some(joined) = self.joined.take()
            && let Some(world) = self.worlds.map().get_mut(&joined.world)
            && world.agent == Some(self.id)
        {
            world.agent = None;
        }
    }

    async fn destroy_world(
        &mut self,
        request: dm::DestroyWorldRequest,
    ) -> Result<dm::DestroyWorldResponse, DmEnvError> {
        let world = {
            let mut map = self.worlds.map();
            let world =
                map.get(&request.world_name).ok_or_else(|| DmEnvError::UnknownWorld(request.world_name.clone()))?;
            // Whose it is, before anything is removed: another token's world stays as it was.
            may_use(&self.slot.caller, &request.world_name, world)?;
            if world.agent.is_some() {
                return Err(DmEnvError::WorldInUse(request.world_name));
            }
            map.remove(&request.world_name)
        };
        if let Some(world) = world {
            self.close_episode(world.episode_id).await?;
        }
        Ok(dm::DestroyWorldResponse {})
    }

    async fn close_episode(&self, episode_id: EpisodeId) -> Result<(), DmEnvError> {
        match self.episodes.close(&self.slot.caller, &episode_id).await {
            // Closed already, as idle.
            Ok(_) | Err(ServiceError::UnknownEpisode(_)) => Ok(()),
            Err(e) => Err(e.into()),
        }
    }

    /// Leaves the joined world and destroys the worlds this connection created.
    async fn finish(mut self) {
        self.leave_world();
        let created: Vec<World> = {
            let mut map = self.worlds.map();
            let names: Vec<String> =
                map.iter().filter(|(_, w)| w.creator == self.id).map(|(name, _)| name.clone()).collect();
            names.iter().filter_map(|name| map.remove(name)).collect()
        };
        let count = created.len();
        for world in created {
            if let Err(e) = self.close_episode(world.episode_id).await {
                tracing::warn!(connection = self.id, "cannot close the episode of a world: {e}");
            }
        }
        if count > 0 {
            tracing::debug!(
                connection = self.id,
                worlds = count,
                "destroyed the worlds of a finished dm_env_rpc connection"
            );
        }
        // Whatever the connection still owns (none, unless a close above failed).
        self.episodes.end_stream(self.slot.id).await;
    }
}

/// The tonic service.
#[derive(Clone)]
pub struct DmEnvService {
    episodes: Arc<Episodes>,
    worlds: Arc<Worlds>,
}

/// Refuses `caller` a world another token created (an admin may use any): joining, resetting or
/// destroying it is its owner's alone.
fn may_use(caller: &Caller, world_name: &str, world: &World) -> Result<(), DmEnvError> {
    if caller.is_admin() || world.owner == caller.name {
        return Ok(());
    }
    Err(ServiceError::Denied(format!(
        "world {} belongs to another token: {} may join, reset or destroy only the worlds it created",
        quoted(world_name),
        caller.describe()
    ))
    .into())
}

impl DmEnvService {
    /// A service over `episodes`, with no worlds yet.
    pub fn new(episodes: Arc<Episodes>) -> Self {
        Self { episodes, worlds: Arc::new(Worlds::default()) }
    }

    /// The live worlds.
    pub fn worlds(&self) -> &Worlds {
        &self.worlds
    }
}

type ResponseStream =
    std::pin::Pin<Box<dyn tokio_stream::Stream<Item = Result<dm::EnvironmentResponse, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl dm::environment_server::Environment for DmEnvService {
    type ProcessStream = ResponseStream;

    async fn process(
        &self,
        request: Request<Streaming<dm::EnvironmentRequest>>,
    ) -> Result<Response<Self::ProcessStream>, Status> {
        // The quota first: a connection beyond the token's max_streams is refused as a whole.
        let slot = self.episodes.open_stream(caller_of(&request))?;
        let (out, receiver) = mpsc::channel(16);
        let connection = Connection {
            id: self.worlds.next_connection.fetch_add(1, Ordering::Relaxed),
            slot,
            episodes: self.episodes.clone(),
            worlds: self.worlds.clone(),
            joined: None,
        };
        tokio::spawn(connection.serve(request.into_inner(), out));
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(receiver))))
    }
}

/// The tonic server of [`DmEnvService`] over `episodes`, with the configured message limits.
pub fn server(episodes: Arc<Episodes>) -> dm::environment_server::EnvironmentServer<DmEnvService> {
    let limit = episodes.config.max_message_bytes;
    dm::environment_server::EnvironmentServer::new(DmEnvService::new(episodes))
        .max_decoding_message_size(limit)
        .max_encoding_message_size(limit)
}

#[cfg(test)]
mod tests {
    use tonic::Code;

    use super::*;

    #[test]
    fn errors_carry_their_grpc_code() {
        let status = wire::google::rpc::Status::from(DmEnvError::from(ServiceError::UnknownScene("s".into())));
        assert_eq!((status.code, status.message.contains("no scene \"s\"")), (Code::NotFound as i32, true));
        assert_eq!(wire::google::rpc::Status::from(DmEnvError::NotJoined).code, Code::FailedPrecondition as i32);
        assert_eq!(wire::google::rpc::Status::from(DmEnvError::EmptyRequest).code, Code::InvalidArgument as i32);
    }
}
