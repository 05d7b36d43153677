//! The client's errors: one variant per kind of failure a caller may want to handle, each
//! keeping the server's message (which says what to change).

use tonic::Code;

/// Why a call failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The episode or scene does not exist (never did, was closed, or was reaped when idle).
    #[error("not found: {0}")]
    NotFound(String),
    /// The request was malformed (bad action, unknown split, invalid scene, ...).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// The episode has ended (success or horizon): reset it or create a new one. The server's
    /// other FAILED_PRECONDITION refusals come as this kind too, their message saying which: a
    /// challenge scene whose one counted attempt is taken, records asked of a server that keeps
    /// none.
    #[error("episode ended: {0}")]
    EpisodeEnded(String),
    /// A server limit was reached (live episodes, batch size, message size).
    #[error("resource exhausted: {0}")]
    ResourceExhausted(String),
    /// The server wants a bearer token, or a different one.
    #[error("unauthenticated: {0}")]
    Unauthenticated(String),
    /// The call needs a privileged episode.
    #[error("permission denied: {0}")]
    PermissionDenied(String),
    /// The server cannot be reached now (not running, restarting, network down).
    #[error("unavailable: {0}")]
    Unavailable(String),
    /// The call's deadline passed first.
    #[error("deadline exceeded: {0}")]
    DeadlineExceeded(String),
    /// Any other status from the server (INTERNAL, UNKNOWN, ...).
    #[error("server error {code:?}: {message}")]
    Server {
        /// The gRPC status code.
        code: Code,
        /// The server's message.
        message: String,
    },
    /// The connection could not be set up: refused (is esrp-server running there?), TLS
    /// failed, or the address does not resolve.
    #[error("cannot connect: {0} (is esrp-server running there, with the same TLS setting?)")]
    Transport(#[from] tonic::transport::Error),
    /// The client was configured wrongly (a URL that does not parse, a token that is not printable ASCII).
    #[error("configuration: {0}")]
    Config(String),
    /// The server answered something this client cannot read (a missing field, an image whose
    /// size does not match its shape): a version mismatch or a bug.
    #[error("protocol: {0}")]
    Protocol(String),
    /// Starting or reaching a local server process failed.
    #[error("local server: {0}")]
    LocalServer(String),
}

impl ClientError {
    /// The gRPC status code this error stands for (`Unknown` for client-side errors).
    pub fn code(&self) -> Code {
        match self {
            ClientError::NotFound(_) => Code::NotFound,
            ClientError::InvalidArgument(_) => Code::InvalidArgument,
            ClientError::EpisodeEnded(_) => Code::FailedPrecondition,
            ClientError::ResourceExhausted(_) => Code::ResourceExhausted,
            ClientError::Unauthenticated(_) => Code::Unauthenticated,
            ClientError::PermissionDenied(_) => Code::PermissionDenied,
            ClientError::Unavailable(_) => Code::Unavailable,
            ClientError::DeadlineExceeded(_) => Code::DeadlineExceeded,
            ClientError::Server { code, .. } => *code,
            ClientError::Transport(_)
            | ClientError::Config(_)
            | ClientError::Protocol(_)
            | ClientError::LocalServer(_) => Code::Unknown,
        }
    }

    /// Whether the server refused the call for a reason the same call would meet again: an
    /// unknown scene or episode, a malformed request, a missing or wrong token, a role that does
    /// not allow it, an ended episode or a challenge scene already played. Retrying it unchanged
    /// is pointless; the other errors (an unreachable or busy server, a deadline, a server fault)
    /// may pass another time.
    pub fn is_refusal(&self) -> bool {
        matches!(
            self,
            ClientError::NotFound(_)
                | ClientError::InvalidArgument(_)
                | ClientError::EpisodeEnded(_)
                | ClientError::Unauthenticated(_)
                | ClientError::PermissionDenied(_)
        )
    }

    /// An error from a status code and message, as a stream's in-band error carries them.
    pub fn from_code(code: Code, message: String) -> Self {
        match code {
            Code::NotFound => ClientError::NotFound(message),
            Code::InvalidArgument | Code::OutOfRange => ClientError::InvalidArgument(message),
            Code::FailedPrecondition => ClientError::EpisodeEnded(message),
            Code::ResourceExhausted => ClientError::ResourceExhausted(message),
            Code::Unauthenticated => ClientError::Unauthenticated(message),
            Code::PermissionDenied => ClientError::PermissionDenied(message),
            Code::Unavailable => ClientError::Unavailable(message),
            Code::DeadlineExceeded => ClientError::DeadlineExceeded(message),
            code => ClientError::Server { code, message },
        }
    }
}

impl From<tonic::Status> for ClientError {
    fn from(status: tonic::Status) -> Self {
        ClientError::from_code(status_code(&status), status_message(&status))
    }
}

/// The code `status` stands for: its own, except that a connection that broke under a call in
/// flight (the server died, the network dropped) is [`Code::Unavailable`], as the other gRPC
/// clients report it. tonic reports it as `Unknown` ("transport error"), with the transport's
/// error as its source; a status the server sent never has a source.
pub fn status_code(status: &tonic::Status) -> Code {
    if status.code() == Code::Unknown && std::error::Error::source(status).is_some() {
        Code::Unavailable
    } else {
        status.code()
    }
}

/// The message of `status`, with the cause of a broken connection (see [`status_code`]) after it.
pub fn status_message(status: &tonic::Status) -> String {
    match std::error::Error::source(status) {
        Some(source) if status.code() == Code::Unknown => {
            let mut message = format!("the connection broke: {}", status.message());
            append_causes(&mut message, source);
            message
        }
        _ => status.message().to_owned(),
    }
}

/// `error` and its causes (its `source()` chain; an `anyhow::Error`'s `as_ref()`) on one line,
/// `: ` between them, line breaks made spaces. A cause whose text is already said (one that
/// repeats the one before it, as hyper's connect errors do, or that an error's own message holds)
/// is left out. What the tools and the server print for an error that ends them.
pub fn one_line(error: &(dyn std::error::Error + 'static)) -> String {
    let mut line = String::new();
    append_causes(&mut line, error);
    line.replace('\n', " ")
}

/// Appends `error` and its causes to `line`, each after `: ` unless its text is already there.
fn append_causes(line: &mut String, error: &(dyn std::error::Error + 'static)) {
    let mut cause = Some(error);
    while let Some(error) = cause {
        let text = error.to_string();
        if !line.contains(&text) {
            if !line.is_empty() {
                line.push_str(": ");
            }
            line.push_str(&text);
        }
        cause = error.source();
    }
}

/// A result of this crate.
pub type Result<T, E = ClientError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::one_line;

    /// An error with a message and an optional cause.
    #[derive(Debug)]
    struct Said(&'static str, Option<Box<Said>>);

    impl std::fmt::Display for Said {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str(self.0)
        }
    }

    impl std::error::Error for Said {
        fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
            self.1.as_deref().map(|s| s as _)
        }
    }

    fn chain(texts: &[&'static str]) -> Said {
        let mut error = None;
        for text in texts.iter().rev() {
            error = Some(Said(text, error.map(Box::new)));
        }
        error.expect("one text at least")
    }

    #[test]
    fn an_error_and_its_causes_make_one_line_without_repeats() {
        let error = chain(&["h:1: cannot\nconnect", "tcp connect", "tcp connect", "refused"]);
        assert_eq!(one_line(&error), "h:1: cannot connect: tcp connect: refused");
        // A cause its error's message already holds is said once.
        let error = chain(&["cannot serve d", "d/manifest.json: No such file", "No such file"]);
        assert_eq!(one_line(&error), "cannot serve d: d/manifest.json: No such file");
    }
}
