//! The `dm_env_rpc.v1.Environment` service: ESRP behind the dm_env_rpc protocol, so that
//! `dm_env_rpc`'s `DmEnvAdaptor` (and any other client of that protocol) runs ESRP episodes.
//!
//! A **world** is one ESRP episode with the settings that made it (CreateWorld); a connection
//! **joins** a world to become its only agent (the task is single-agent); each **sequence** of
//! the agent is one run of the episode from its start. Every request is answered by the same
//! [`Shared`] calls as `esrp.v1` (`create`, `reset`, `step_many`, `close`), so the rules, the
//! rendering and the limits are the native API's.
//!
//! # Settings
//!
//! CreateWorld accepts (all optional; any other name is an INVALID_ARGUMENT error):
//!
//! | name | tensor | meaning |
//! |---|---|---|
//! | `scene` | string | scene id of the served dataset (default: chosen by `split` and `seed`) |
//! | `split` | string `"train"` or `"test"` | split to choose from when `scene` is absent (default test) |
//! | `seed` | integer ≥ 0 | which scene of the split: index `seed mod count` (default 0: the first) |
//! | `horizon` | integer ≥ 0 | step limit; 0 or absent: the scene's own |
//! | `resolution` | integer 16..=512 | square image side in pixels (default 128) |
//! | `ego_depth`, `ego_segmentation`, `current_top_down` | bool | optional sensors (default off) |
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
//! code and a message saying what to change) and the stream goes on. When a stream ends, its
//! connection leaves its world and the worlds it created are destroyed (their episodes closed).

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use bytes::Bytes;
use tokio::sync::mpsc;
use tokio_stream::StreamExt;
use tonic::{Code, Request, Response, Status, Streaming};

use crate::error::ServiceError;
use crate::proto;
use crate::service::Shared;

/// Generated protobuf messages and gRPC stubs of `dm_env_rpc.v1` and the `google.rpc` and
/// `google.protobuf` messages it uses (from esrp-proto).
pub use esrp_proto as wire;

use wire::dm_env_rpc::v1 as dm;
use wire::dm_env_rpc::v1::environment_request::Payload as Rq;
use wire::dm_env_rpc::v1::environment_response::Payload as Rs;
use wire::dm_env_rpc::v1::tensor::Payload as Elements;

/// The uid of the only action.
pub const ACTION_UID: u64 = 1;
/// The action's name in the specs.
pub const ACTION_NAME: &str = "action";
/// The largest action code.
const MAX_ACTION: i32 = 5;

/// Why a dm_env_rpc request failed. Sent in-band as a `google.rpc.Status`.
#[derive(Debug, thiserror::Error)]
pub enum DmEnvError {
    /// A failure of the underlying episode call, with the status the native API gives it.
    #[error("{}", .0.message())]
    Episode(Status),
    /// The world name is not a live world.
    #[error(
        "no world {0:?}: it was never created, was destroyed, or its creating connection ended; CreateWorld returns the names"
    )]
    UnknownWorld(String),
    /// Step or Reset before JoinWorld.
    #[error("this connection has not joined a world: send JoinWorld first")]
    NotJoined,
    /// JoinWorld while joined.
    #[error("this connection is already joined to world {0:?}: send LeaveWorld first (one world per connection)")]
    AlreadyJoined(String),
    /// JoinWorld on a world that has its agent.
    #[error("world {0:?} already has its agent (ESRP is single-agent): create another world")]
    WorldTaken(String),
    /// DestroyWorld on a world that has an agent.
    #[error("world {0:?} has a joined agent: it must send LeaveWorld before the world can be destroyed")]
    WorldInUse(String),
    /// A setting name or value is not accepted.
    #[error("{0}")]
    InvalidSetting(String),
    /// The actions of a running step are wrong.
    #[error("{0}")]
    InvalidAction(String),
    /// A requested observation uid is not in the specs.
    #[error("unknown observation uid {0}: request uids from the JoinWorld specs")]
    UnknownObservation(u64),
    /// An EnvironmentRequest without a payload.
    #[error(
        "empty EnvironmentRequest: set one of create_world, join_world, step, reset, reset_world, leave_world, destroy_world"
    )]
    EmptyRequest,
    /// A request this server does not implement.
    #[error("{0}")]
    Unimplemented(String),
}

impl From<ServiceError> for DmEnvError {
    fn from(error: ServiceError) -> Self {
        // The native API's one mapping of episode errors to codes.
        DmEnvError::Episode(Status::from(error))
    }
}

impl DmEnvError {
    /// The gRPC status code.
    pub fn code(&self) -> Code {
        match self {
            DmEnvError::Episode(status) => status.code(),
            DmEnvError::UnknownWorld(_) => Code::NotFound,
            DmEnvError::NotJoined
            | DmEnvError::AlreadyJoined(_)
            | DmEnvError::WorldTaken(_)
            | DmEnvError::WorldInUse(_) => Code::FailedPrecondition,
            DmEnvError::InvalidSetting(_)
            | DmEnvError::InvalidAction(_)
            | DmEnvError::UnknownObservation(_)
            | DmEnvError::EmptyRequest => Code::InvalidArgument,
            DmEnvError::Unimplemented(_) => Code::Unimplemented,
        }
    }
}

impl From<DmEnvError> for wire::google::rpc::Status {
    fn from(error: DmEnvError) -> Self {
        Self { code: error.code() as i32, message: error.to_string(), details: Vec::new() }
    }
}

// Tensors.

/// The element type of `tensor`, for messages.
fn element_type(tensor: &dm::Tensor) -> &'static str {
    match &tensor.payload {
        None => "no payload",
        Some(Elements::Floats(_)) => "FLOAT",
        Some(Elements::Doubles(_)) => "DOUBLE",
        Some(Elements::Int8s(_)) => "INT8",
        Some(Elements::Int32s(_)) => "INT32",
        Some(Elements::Int64s(_)) => "INT64",
        Some(Elements::Uint8s(_)) => "UINT8",
        Some(Elements::Uint32s(_)) => "UINT32",
        Some(Elements::Uint64s(_)) => "UINT64",
        Some(Elements::Bools(_)) => "BOOL",
        Some(Elements::Strings(_)) => "STRING",
        Some(Elements::Protos(_)) => "PROTO",
    }
}

fn element_count(tensor: &dm::Tensor) -> usize {
    match &tensor.payload {
        None => 0,
        Some(Elements::Floats(a)) => a.array.len(),
        Some(Elements::Doubles(a)) => a.array.len(),
        Some(Elements::Int8s(a)) => a.array.len(),
        Some(Elements::Int32s(a)) => a.array.len(),
        Some(Elements::Int64s(a)) => a.array.len(),
        Some(Elements::Uint8s(a)) => a.array.len(),
        Some(Elements::Uint32s(a)) => a.array.len(),
        Some(Elements::Uint64s(a)) => a.array.len(),
        Some(Elements::Bools(a)) => a.array.len(),
        Some(Elements::Strings(a)) => a.array.len(),
        Some(Elements::Protos(a)) => a.array.len(),
    }
}

/// Checks that the setting `name` is a single value (shape `[]`, or only 1 and -1).
fn check_scalar_setting(name: &str, tensor: &dm::Tensor) -> Result<(), DmEnvError> {
    let count = element_count(tensor);
    if count != 1 || tensor.shape.iter().any(|&d| d != 1 && d != -1) {
        return Err(DmEnvError::InvalidSetting(format!(
            "setting {name}: expected a single value, got {count} elements of shape {:?}",
            tensor.shape
        )));
    }
    Ok(())
}

fn string_setting(name: &str, tensor: &dm::Tensor) -> Result<String, DmEnvError> {
    check_scalar_setting(name, tensor)?;
    match &tensor.payload {
        Some(Elements::Strings(a)) => Ok(a.array[0].clone()),
        _ => {
            Err(DmEnvError::InvalidSetting(format!("setting {name}: expected a STRING, got {}", element_type(tensor))))
        }
    }
}

fn bool_setting(name: &str, tensor: &dm::Tensor) -> Result<bool, DmEnvError> {
    check_scalar_setting(name, tensor)?;
    match &tensor.payload {
        Some(Elements::Bools(a)) => Ok(a.array[0]),
        _ => Err(DmEnvError::InvalidSetting(format!("setting {name}: expected a BOOL, got {}", element_type(tensor)))),
    }
}

/// A non-negative integer setting of any integer element type.
fn integer_setting(name: &str, tensor: &dm::Tensor) -> Result<u64, DmEnvError> {
    check_scalar_setting(name, tensor)?;
    let value: i128 = match &tensor.payload {
        Some(Elements::Int8s(a)) => i128::from(a.array[0] as i8),
        Some(Elements::Int32s(a)) => i128::from(a.array[0]),
        Some(Elements::Int64s(a)) => i128::from(a.array[0]),
        Some(Elements::Uint8s(a)) => i128::from(a.array[0]),
        Some(Elements::Uint32s(a)) => i128::from(a.array[0]),
        Some(Elements::Uint64s(a)) => i128::from(a.array[0]),
        _ => {
            return Err(DmEnvError::InvalidSetting(format!(
                "setting {name}: expected an integer, got {}",
                element_type(tensor)
            )));
        }
    };
    u64::try_from(value)
        .map_err(|_| DmEnvError::InvalidSetting(format!("setting {name}: {value} is negative: use 0 or more")))
}

fn u32_setting(name: &str, tensor: &dm::Tensor) -> Result<u32, DmEnvError> {
    let value = integer_setting(name, tensor)?;
    u32::try_from(value).map_err(|_| DmEnvError::InvalidSetting(format!("setting {name}: {value} is too large")))
}

/// Settings sorted by name, so that the first bad one reported does not depend on hash order.
fn sorted(settings: HashMap<String, dm::Tensor>) -> Vec<(String, dm::Tensor)> {
    let mut settings: Vec<(String, dm::Tensor)> = settings.into_iter().collect();
    settings.sort_by(|a, b| a.0.cmp(&b.0));
    settings
}

/// The CreateWorld setting names.
pub const CREATE_WORLD_SETTINGS: [&str; 8] =
    ["scene", "split", "seed", "horizon", "resolution", "ego_depth", "ego_segmentation", "current_top_down"];

/// The native request a CreateWorld's settings ask for.
fn create_request(settings: HashMap<String, dm::Tensor>) -> Result<proto::CreateEpisodeRequest, DmEnvError> {
    let mut request = proto::CreateEpisodeRequest::default();
    let mut sensors = proto::Sensors::default();
    for (name, value) in sorted(settings) {
        match name.as_str() {
            "scene" => {
                request.scene = Some(proto::create_episode_request::Scene::SceneId(string_setting(&name, &value)?))
            }
            "split" => {
                request.split = match string_setting(&name, &value)?.as_str() {
                    "train" => proto::Split::Train as i32,
                    "test" => proto::Split::Test as i32,
                    other => {
                        return Err(DmEnvError::InvalidSetting(format!(
                            "setting split: {other:?} is not a split: use \"train\" or \"test\""
                        )));
                    }
                }
            }
            "seed" => request.seed = integer_setting(&name, &value)?,
            "horizon" => request.horizon = u32_setting(&name, &value)?,
            "resolution" => sensors.resolution = u32_setting(&name, &value)?,
            "ego_depth" => sensors.ego_depth = bool_setting(&name, &value)?,
            "ego_segmentation" => sensors.ego_segmentation = bool_setting(&name, &value)?,
            "current_top_down" => sensors.current_top_down = bool_setting(&name, &value)?,
            other => {
                return Err(DmEnvError::InvalidSetting(format!(
                    "unknown CreateWorld setting {other:?}: the settings are {}",
                    CREATE_WORLD_SETTINGS.join(", ")
                )));
            }
        }
    }
    request.sensors = Some(sensors);
    Ok(request)
}

/// Fails on any setting: for the requests that take none.
fn no_settings(request: &str, settings: &HashMap<String, dm::Tensor>) -> Result<(), DmEnvError> {
    match sorted(settings.clone()).first() {
        None => Ok(()),
        Some((name, _)) => {
            Err(DmEnvError::InvalidSetting(format!("unknown {request} setting {name:?}: {request} takes no settings")))
        }
    }
}

// Specs and observations.

fn data_type(dtype: &str) -> Result<dm::DataType, DmEnvError> {
    match dtype {
        "uint8" => Ok(dm::DataType::Uint8),
        "float32" => Ok(dm::DataType::Float),
        "uint32" => Ok(dm::DataType::Uint32),
        "bool" => Ok(dm::DataType::Bool),
        other => Err(ServiceError::Internal(format!("no dm_env_rpc type for the observation type {other:?}")).into()),
    }
}

/// The specs of a world whose episodes have the native `spec`, and the observation names by
/// uid - 1.
fn specs_of(spec: &proto::ObservationSpec) -> Result<(dm::ActionObservationSpecs, Vec<String>), DmEnvError> {
    let mut observations = Vec::new();
    for array in &spec.arrays {
        observations.push(dm::TensorSpec {
            name: array.name.clone(),
            shape: array.shape.iter().map(|&d| d as i32).collect(),
            dtype: data_type(&array.dtype)? as i32,
            min: None,
            max: None,
        });
    }
    let double = |name: &str, bounds: Option<(f64, f64)>| dm::TensorSpec {
        name: name.to_owned(),
        shape: Vec::new(),
        dtype: dm::DataType::Double as i32,
        min: bounds.map(|b| doubles_value(b.0)),
        max: bounds.map(|b| doubles_value(b.1)),
    };
    observations.push(double("reward", None));
    observations.push(double("discount", Some((0.0, 1.0))));
    let names = observations.iter().map(|s| s.name.clone()).collect();
    let action = dm::TensorSpec {
        name: ACTION_NAME.to_owned(),
        shape: Vec::new(),
        dtype: dm::DataType::Int32 as i32,
        min: Some(int32s_value(0)),
        max: Some(int32s_value(MAX_ACTION)),
    };
    let specs = dm::ActionObservationSpecs {
        actions: HashMap::from([(ACTION_UID, action)]),
        observations: observations.into_iter().enumerate().map(|(i, s)| (i as u64 + 1, s)).collect(),
    };
    Ok((specs, names))
}

fn doubles_value(value: f64) -> dm::tensor_spec::Value {
    dm::tensor_spec::Value {
        payload: Some(dm::tensor_spec::value::Payload::Doubles(dm::tensor::DoubleArray { array: vec![value] })),
    }
}

fn int32s_value(value: i32) -> dm::tensor_spec::Value {
    dm::tensor_spec::Value {
        payload: Some(dm::tensor_spec::value::Payload::Int32s(dm::tensor::Int32Array { array: vec![value] })),
    }
}

fn tensor(shape: Vec<i32>, elements: Elements) -> dm::Tensor {
    dm::Tensor { shape, payload: Some(elements) }
}

fn image_tensor(image: &proto::Image) -> dm::Tensor {
    let shape = vec![image.height as i32, image.width as i32, image.channels as i32];
    tensor(shape, Elements::Uint8s(dm::tensor::Uint8Array { array: image.data.clone() }))
}

fn le_words(data: &Bytes) -> impl Iterator<Item = [u8; 4]> + '_ {
    data.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]])
}

/// The observation `name` of a step: from the native observation, or the reward and discount.
fn observation_tensor(
    name: &str,
    observation: &proto::Observation,
    reward: f64,
    discount: f64,
) -> Result<dm::Tensor, DmEnvError> {
    let found = match name {
        "ego_rgb" => observation.ego_rgb.as_ref().map(image_tensor),
        "goal_rgb" => observation.goal_rgb.as_ref().map(image_tensor),
        "current_top_down" => observation.current_top_down.as_ref().map(image_tensor),
        "grasping" => {
            Some(tensor(Vec::new(), Elements::Bools(dm::tensor::BoolArray { array: vec![observation.grasping] })))
        }
        "ego_depth" => observation.ego_depth.as_ref().map(|d| {
            let array = le_words(&d.data).map(f32::from_le_bytes).collect();
            tensor(vec![d.height as i32, d.width as i32], Elements::Floats(dm::tensor::FloatArray { array }))
        }),
        "ego_segmentation" => observation.ego_segmentation.as_ref().map(|s| {
            let array = le_words(&s.data).map(u32::from_le_bytes).collect();
            tensor(vec![s.height as i32, s.width as i32], Elements::Uint32s(dm::tensor::Uint32Array { array }))
        }),
        "reward" => Some(tensor(Vec::new(), Elements::Doubles(dm::tensor::DoubleArray { array: vec![reward] }))),
        "discount" => Some(tensor(Vec::new(), Elements::Doubles(dm::tensor::DoubleArray { array: vec![discount] }))),
        _ => None,
    };
    found.ok_or_else(|| ServiceError::Internal(format!("the episode returned no {name} observation")).into())
}

/// The action of a running step: uid 1, an INT32 scalar in 0..=5.
fn action_of(actions: &HashMap<u64, dm::Tensor>) -> Result<i32, DmEnvError> {
    if let Some(uid) = actions.keys().find(|&&uid| uid != ACTION_UID) {
        return Err(DmEnvError::InvalidAction(format!(
            "unknown action uid {uid}: the only action is uid {ACTION_UID} ({ACTION_NAME:?})"
        )));
    }
    let Some(action) = actions.get(&ACTION_UID) else {
        return Err(DmEnvError::InvalidAction(format!(
            "the action (uid {ACTION_UID}) is required on every step of a running sequence: send an INT32 scalar 0..=5"
        )));
    };
    let Some(Elements::Int32s(values)) = &action.payload else {
        return Err(DmEnvError::InvalidAction(format!(
            "action: expected an INT32 tensor, got {}",
            element_type(action)
        )));
    };
    if !action.shape.is_empty() {
        return Err(DmEnvError::InvalidAction(format!(
            "action: expected a scalar (shape []), got shape {:?}",
            action.shape
        )));
    }
    let [value] = values.array[..] else {
        return Err(DmEnvError::InvalidAction(format!("action: expected one element, got {}", values.array.len())));
    };
    if !(0..=MAX_ACTION).contains(&value) {
        return Err(DmEnvError::InvalidAction(format!(
            "action: {value} is out of range: use 0 move_forward, 1 move_backward, 2 turn_left, 3 turn_right, 4 fetch or 5 release"
        )));
    }
    Ok(value)
}

// Worlds and connections.

/// A world: one ESRP episode and what the dm_env_rpc side keeps beside it.
struct World {
    /// The native episode.
    episode_id: String,
    specs: dm::ActionObservationSpecs,
    /// Observation names by uid - 1.
    observation_names: Arc<[String]>,
    /// The connection that created it (the world ends with it).
    creator: u64,
    /// The joined connection, if any.
    agent: Option<u64>,
    /// Bumped by ResetWorld, so that the agent learns its sequence was interrupted.
    generation: u64,
    /// The first observation of an episode not stepped since it was created or reset: the next
    /// sequence starts from it without restarting the episode.
    fresh: Option<proto::Observation>,
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
    episode_id: String,
    specs: dm::ActionObservationSpecs,
    observation_names: Arc<[String]>,
    /// The world's generation this connection last saw.
    generation: u64,
    /// Whether a sequence is running (its next step takes the action).
    running: bool,
}

/// One stream: its joined world and the worlds it created.
struct Connection {
    id: u64,
    shared: Arc<Shared>,
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
                "extension {:?} is not implemented: esrp-server has no dm_env_rpc extensions",
                any.type_url
            ))),
        }
    }

    async fn create_world(&mut self, request: dm::CreateWorldRequest) -> Result<dm::CreateWorldResponse, DmEnvError> {
        let request = create_request(request.settings)?;
        let created = self.shared.create(request, None).await?;
        let (specs, observation_names) = specs_of(&created.spec.unwrap_or_default())?;
        let world_name = format!("esrp-world-{}", uuid::Uuid::new_v4().simple());
        let world = World {
            episode_id: created.episode_id,
            specs,
            observation_names: observation_names.into(),
            creator: self.id,
            agent: None,
            generation: 0,
            fresh: created.observation,
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
        let respond =
            |state: dm::EnvironmentStateType, observation: &proto::Observation, reward: f64, discount: f64| {
                let mut observations = HashMap::with_capacity(requested.len());
                for &uid in &requested {
                    observations
                        .insert(uid, observation_tensor(&names[uid as usize - 1], observation, reward, discount)?);
                }
                Ok::<_, DmEnvError>(dm::StepResponse { state: state as i32, observations })
            };

        // A ResetWorld sent by another connection interrupts the running sequence.
        let reset_by_world = {
            let map = self.worlds.map();
            map.get(&joined.world)
                .filter(|w| w.generation != joined.generation)
                .map(|w| (w.generation, w.fresh.clone()))
        };
        if let Some((generation, fresh)) = reset_by_world {
            joined.generation = generation;
            if joined.running {
                joined.running = false;
                if let Some(observation) = fresh {
                    return respond(dm::EnvironmentStateType::Interrupted, &observation, 0.0, 1.0);
                }
            }
        }

        if !joined.running {
            // A new sequence: the actions are ignored.
            let fresh = self.worlds.map().get_mut(&joined.world).and_then(|w| w.fresh.take());
            let observation = match fresh {
                Some(observation) => observation,
                None => {
                    let reset = proto::ResetRequest { episode_id: joined.episode_id.clone(), scene: None };
                    self.shared.reset(reset).await?.observation.unwrap_or_default()
                }
            };
            joined.running = true;
            return respond(dm::EnvironmentStateType::Running, &observation, 0.0, 1.0);
        }

        let action = action_of(&request.actions)?;
        let include_goal = requested.iter().any(|&uid| names[uid as usize - 1] == "goal_rgb");
        let step = proto::StepRequest { episode_id: joined.episode_id.clone(), action, include_goal };
        let response = self
            .shared
            .step_many(vec![step])
            .await?
            .pop()
            .ok_or_else(|| ServiceError::Internal("a step without a response".into()))?;
        let state = if response.terminated {
            dm::EnvironmentStateType::Terminated
        } else if response.truncated {
            dm::EnvironmentStateType::Interrupted
        } else {
            dm::EnvironmentStateType::Running
        };
        joined.running = state == dm::EnvironmentStateType::Running;
        let discount = if response.terminated { 0.0 } else { 1.0 };
        respond(state, &response.observation.unwrap_or_default(), response.reward, discount)
    }

    fn reset(&mut self, request: dm::ResetRequest) -> Result<dm::ResetResponse, DmEnvError> {
        let joined = self.joined.as_mut().ok_or(DmEnvError::NotJoined)?;
        no_settings("Reset", &request.settings)?;
        // The episode restarts when the next step starts the next sequence.
        joined.running = false;
        Ok(dm::ResetResponse { specs: Some(joined.specs.clone()) })
    }

    async fn reset_world(&mut self, request: dm::ResetWorldRequest) -> Result<dm::ResetWorldResponse, DmEnvError> {
        let mut scene = None;
        for (name, value) in sorted(request.settings) {
            match name.as_str() {
                "scene" => scene = Some(proto::reset_request::Scene::SceneId(string_setting(&name, &value)?)),
                other => {
                    return Err(DmEnvError::InvalidSetting(format!(
                        "unknown ResetWorld setting {other:?}: the only one is \"scene\""
                    )));
                }
            }
        }
        let episode_id = {
            let map = self.worlds.map();
            map.get(&request.world_name)
                .map(|w| w.episode_id.clone())
                .ok_or_else(|| DmEnvError::UnknownWorld(request.world_name.clone()))?
        };
        let reset = self.shared.reset(proto::ResetRequest { episode_id, scene }).await?;
        let mut map = self.worlds.map();
        if let Some(world) = map.get_mut(&request.world_name) {
            world.generation += 1;
            world.fresh = reset.observation;
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

    async fn close_episode(&self, episode_id: String) -> Result<(), DmEnvError> {
        match self.shared.close(proto::CloseEpisodeRequest { episode_id }).await {
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
    }
}

/// The tonic service.
#[derive(Clone)]
pub struct DmEnvService {
    shared: Arc<Shared>,
    worlds: Arc<Worlds>,
}

impl DmEnvService {
    /// A service over `shared`, with no worlds yet.
    pub fn new(shared: Arc<Shared>) -> Self {
        Self { shared, worlds: Arc::new(Worlds::default()) }
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
        let (out, receiver) = mpsc::channel(16);
        let connection = Connection {
            id: self.worlds.next_connection.fetch_add(1, Ordering::Relaxed),
            shared: self.shared.clone(),
            worlds: self.worlds.clone(),
            joined: None,
        };
        tokio::spawn(connection.serve(request.into_inner(), out));
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(receiver))))
    }
}

/// The tonic server of [`DmEnvService`] over `shared`, with the configured message limits.
pub fn server(shared: Arc<Shared>) -> dm::environment_server::EnvironmentServer<DmEnvService> {
    let limit = shared.config.max_message_bytes;
    dm::environment_server::EnvironmentServer::new(DmEnvService::new(shared))
        .max_decoding_message_size(limit)
        .max_encoding_message_size(limit)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn int64(value: i64) -> dm::Tensor {
        tensor(Vec::new(), Elements::Int64s(dm::tensor::Int64Array { array: vec![value] }))
    }

    fn int32(shape: Vec<i32>, values: Vec<i32>) -> dm::Tensor {
        tensor(shape, Elements::Int32s(dm::tensor::Int32Array { array: values }))
    }

    fn string(value: &str) -> dm::Tensor {
        tensor(Vec::new(), Elements::Strings(dm::tensor::StringArray { array: vec![value.to_owned()] }))
    }

    /// Parses `settings`; the request's summary or the error's message must contain `expected`.
    fn check_settings(settings: Vec<(&str, dm::Tensor)>, expected: &str) {
        let settings = settings.into_iter().map(|(k, v)| (k.to_owned(), v)).collect();
        let got = match create_request(settings) {
            Ok(r) => format!(
                "scene={:?} split={} seed={} horizon={} sensors={:?}",
                r.scene, r.split, r.seed, r.horizon, r.sensors
            ),
            Err(e) => e.to_string(),
        };
        assert!(got.contains(expected), "{got:?} does not contain {expected:?}");
    }

    #[test]
    fn create_world_settings_map_to_the_native_request() {
        check_settings(vec![], "scene=None split=0 seed=0 horizon=0");
        check_settings(vec![("scene", string("a/1"))], "SceneId(\"a/1\")");
        check_settings(vec![("split", string("train")), ("seed", int64(7))], "split=1 seed=7");
        check_settings(vec![("horizon", int32(vec![], vec![9]))], "horizon=9");
        check_settings(vec![("resolution", int64(64))], "resolution: 64");
        check_settings(vec![("seed", int64(-1))], "setting seed: -1 is negative");
        check_settings(vec![("split", string("dev"))], "not a split");
        check_settings(vec![("scene", int64(3))], "setting scene: expected a STRING, got INT64");
        check_settings(vec![("seed", int32(vec![2], vec![1, 2]))], "expected a single value, got 2 elements");
        check_settings(vec![("zeta", int64(1)), ("alpha", int64(1))], "unknown CreateWorld setting \"alpha\"");
    }

    fn check_action(tensor: Option<dm::Tensor>, expected: Result<i32, &str>) {
        let actions = tensor.map(|t| HashMap::from([(ACTION_UID, t)])).unwrap_or_default();
        match (action_of(&actions), expected) {
            (Ok(got), Ok(want)) => assert_eq!(got, want),
            (Err(e), Err(want)) => assert!(e.to_string().contains(want), "{e} does not contain {want:?}"),
            (got, want) => panic!("got {got:?}, expected {want:?}"),
        }
    }

    #[test]
    fn the_action_is_an_int32_scalar_from_0_to_5() {
        check_action(Some(int32(vec![], vec![0])), Ok(0));
        check_action(Some(int32(vec![], vec![5])), Ok(5));
        check_action(Some(int32(vec![], vec![6])), Err("6 is out of range"));
        check_action(Some(int32(vec![], vec![-1])), Err("-1 is out of range"));
        check_action(Some(int32(vec![1], vec![1])), Err("expected a scalar"));
        check_action(Some(int32(vec![], vec![1, 2])), Err("expected one element, got 2"));
        check_action(Some(int64(1)), Err("expected an INT32 tensor, got INT64"));
        check_action(None, Err("is required"));
        let extra = HashMap::from([(ACTION_UID, int32(vec![], vec![1])), (7, int64(1))]);
        assert!(action_of(&extra).unwrap_err().to_string().contains("unknown action uid 7"));
    }

    #[test]
    fn specs_number_the_native_observations_then_reward_and_discount() {
        let array = |name: &str, shape: Vec<u32>, dtype: &str| proto::ArraySpec {
            name: name.into(),
            shape,
            dtype: dtype.into(),
        };
        let arrays = vec![
            array("ego_rgb", vec![8, 8, 3], "uint8"),
            array("grasping", vec![], "bool"),
            array("ego_depth", vec![8, 8], "float32"),
        ];
        let (specs, names) = specs_of(&proto::ObservationSpec { arrays, actions: Vec::new() }).unwrap();
        assert_eq!(names, ["ego_rgb", "grasping", "ego_depth", "reward", "discount"]);
        assert_eq!(specs.observations[&3].dtype, dm::DataType::Float as i32);
        assert_eq!(specs.observations[&5].max, Some(doubles_value(1.0)));
        assert_eq!(specs.actions[&ACTION_UID].max, Some(int32s_value(MAX_ACTION)));
        let unknown = proto::ObservationSpec { arrays: vec![array("x", vec![], "float64")], actions: Vec::new() };
        assert!(specs_of(&unknown).is_err());
    }

    #[test]
    fn errors_carry_their_grpc_code() {
        let status = wire::google::rpc::Status::from(DmEnvError::from(ServiceError::UnknownScene("s".into())));
        assert_eq!((status.code, status.message.contains("no scene \"s\"")), (Code::NotFound as i32, true));
        assert_eq!(wire::google::rpc::Status::from(DmEnvError::NotJoined).code, Code::FailedPrecondition as i32);
        assert_eq!(wire::google::rpc::Status::from(DmEnvError::EmptyRequest).code, Code::InvalidArgument as i32);
    }
}
