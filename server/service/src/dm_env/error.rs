//! Why a dm_env_rpc request failed ([`DmEnvError`]), with its gRPC code; sent in-band as a
//! `google.rpc.Status`.

use tonic::Code;

use crate::error::ServiceError;
use crate::quote::quoted;

/// Why a dm_env_rpc request failed. Sent in-band as a `google.rpc.Status`.
#[derive(Debug, thiserror::Error)]
pub enum DmEnvError {
    /// A failure of the underlying episode call, with the code the native API gives it.
    #[error("{0}")]
    Episode(#[from] ServiceError),
    /// The world name is not a live world.
    #[error(
        "no world {}: it was never created, was destroyed, or its creating connection ended; CreateWorld returns the names",
        quoted(.0)
    )]
    UnknownWorld(String),
    /// Step or Reset before JoinWorld.
    #[error("this connection has not joined a world: send JoinWorld first")]
    NotJoined,
    /// JoinWorld while joined.
    #[error("this connection is already joined to world {}: send LeaveWorld first (one world per connection)", quoted(.0))]
    AlreadyJoined(String),
    /// Step or Reset in a world destroyed while this connection was joined to it (its creating
    /// connection ended).
    #[error(
        "world {} was destroyed while this connection was joined to it (the connection that created it ended): send LeaveWorld, then create or join another world",
        quoted(.0)
    )]
    WorldGone(String),
    /// JoinWorld on a world that has its agent.
    #[error("world {} already has its agent (ESRP is single-agent): create another world", quoted(.0))]
    WorldTaken(String),
    /// DestroyWorld on a world that has an agent.
    #[error("world {} has a joined agent: it must send LeaveWorld before the world can be destroyed", quoted(.0))]
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

impl DmEnvError {
    /// The gRPC status code.
    pub fn code(&self) -> Code {
        match self {
            // The native API's one mapping of episode errors to codes.
            DmEnvError::Episode(error) => error.code(),
            DmEnvError::UnknownWorld(_) | DmEnvError::WorldGone(_) => Code::NotFound,
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

impl From<DmEnvError> for esrp_proto::google::rpc::Status {
    fn from(error: DmEnvError) -> Self {
        Self { code: error.code() as i32, message: error.to_string(), details: Vec::new() }
    }
}
