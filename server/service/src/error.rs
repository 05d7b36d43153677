//! The service's errors and their one exhaustive mapping to gRPC status codes.

use tonic::{Code, Status};

/// Why a call failed.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A request field is malformed.
    #[error("{0}")]
    InvalidArgument(String),
    /// The episode id is unknown or closed.
    #[error("no episode {0:?}: it never existed, was closed, or was closed after being idle")]
    UnknownEpisode(String),
    /// The scene id is not in the served dataset.
    #[error("no scene {0:?} in the served dataset: ListScenes lists the ids")]
    UnknownScene(String),
    /// The episode has ended.
    #[error("{0}")]
    EpisodeOver(String),
    /// The call needs a privileged episode.
    #[error("episode {0} was not created with privileged = true: GetPrivilegedState is for privileged episodes only")]
    NotPrivileged(String),
    /// A server limit was reached.
    #[error("{0}")]
    Exhausted(String),
    /// Rendering failed.
    #[error("rendering failed: {0}")]
    Render(String),
    /// A bug or an unexpected failure.
    #[error("internal error: {0}")]
    Internal(String),
}

impl From<ServiceError> for Status {
    fn from(error: ServiceError) -> Status {
        let code = match &error {
            ServiceError::InvalidArgument(_) => Code::InvalidArgument,
            ServiceError::UnknownEpisode(_) | ServiceError::UnknownScene(_) => Code::NotFound,
            ServiceError::EpisodeOver(_) => Code::FailedPrecondition,
            ServiceError::NotPrivileged(_) => Code::PermissionDenied,
            ServiceError::Exhausted(_) => Code::ResourceExhausted,
            ServiceError::Render(_) | ServiceError::Internal(_) => Code::Internal,
        };
        Status::new(code, error.to_string())
    }
}

impl From<esrp_core::SceneError> for ServiceError {
    fn from(e: esrp_core::SceneError) -> Self {
        ServiceError::InvalidArgument(format!("invalid scene: {e}"))
    }
}

impl From<esrp_core::EpisodeError> for ServiceError {
    fn from(e: esrp_core::EpisodeError) -> Self {
        match e {
            esrp_core::EpisodeError::Finished { .. } => ServiceError::EpisodeOver(e.to_string()),
            esrp_core::EpisodeError::InvalidConfig { .. } => ServiceError::InvalidArgument(e.to_string()),
        }
    }
}

impl From<esrp_render::RenderError> for ServiceError {
    fn from(e: esrp_render::RenderError) -> Self {
        ServiceError::Render(e.to_string())
    }
}
