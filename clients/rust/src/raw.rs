//! [`RawClient`]: the generated `esrp.v1` stub with the bearer token attached ([`Bearer`]), the
//! one connection type every handle ([`crate::Client`], [`crate::Episode`],
//! [`crate::EpisodeStream`]) calls through.

use tonic::transport::Channel;

use crate::error::{ClientError, Result};
use crate::proto::esrp_client::EsrpClient;

/// Adds `authorization: Bearer TOKEN` to every call when a token is set.
#[derive(Clone, Debug, Default)]
pub struct Bearer(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl Bearer {
    /// Sends `authorization: Bearer TOKEN` with every call, or nothing without a token.
    pub fn new(token: Option<&str>) -> Result<Self> {
        match token {
            None => Ok(Bearer(None)),
            Some(token) => format!("Bearer {token}")
                .parse()
                .map(|v| Bearer(Some(v)))
                .map_err(|_| ClientError::Config("the token must be printable ASCII (no control characters)".into())),
        }
    }
}

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request.metadata_mut().insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// The generated `esrp.v1` stub with the bearer token attached: every RPC, unwrapped, for
/// what the typed API does not cover.
pub type RawClient = EsrpClient<tonic::service::interceptor::InterceptedService<Channel, Bearer>>;
