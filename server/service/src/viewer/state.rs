//! What the viewer keeps between requests (the watched episodes' feeds, the replays) and what
//! every handler shares: the caller's token check, the error answer, an episode's summary and
//! the event-stream answer.

use std::collections::HashMap;
use std::convert::Infallible;
use std::sync::Arc;

use axum::Json;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};
use tokio::sync::mpsc;

use crate::auth::Tokens;
use crate::episodes::{EpisodeSummary, Episodes};
use crate::error::ServiceError;
use crate::types::{Caller, EpisodeId};

/// The viewer's shared state.
#[derive(Clone)]
pub(super) struct Viewer {
    pub(super) episodes: Arc<Episodes>,
    pub(super) tokens: Arc<Tokens>,
    /// The replays: each episode's record actions and how many of them it has taken. The map's
    /// lock is held only to find, add or remove a replay (a std lock: never across an await); a
    /// seek steps holding its own replay's lock alone, so that it blocks no other replay.
    pub(super) replays: Arc<std::sync::Mutex<HashMap<EpisodeId, ReplaySlot>>>,
    /// The watched episodes' feeds.
    pub(super) feeds: Feeds,
}

impl Viewer {
    /// The replays' map, whatever a panicking holder left.
    pub(super) fn replays(&self) -> std::sync::MutexGuard<'_, HashMap<EpisodeId, ReplaySlot>> {
        self.replays.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// A record being replayed.
pub(super) struct Replay {
    pub(super) actions: Vec<u8>,
    pub(super) at: usize,
}

/// A replay in the viewer's map: the token that started it, and the replay behind its own lock.
#[derive(Clone)]
pub(super) struct ReplaySlot {
    pub(super) owner: Arc<str>,
    pub(super) replay: Arc<tokio::sync::Mutex<Replay>>,
}

/// The most replays one token may have open at once.
pub const MAX_REPLAYS_PER_TOKEN: usize = 4;

/// What a feed publishes.
pub(super) enum FeedItem {
    /// Nothing yet.
    Pending,
    /// A frame, as every watcher sees it (`public`), with the privileged part (`full`), and as an
    /// admin sees it (`admin`: `full` with what a paper-only episode hides from others).
    Frame { public: String, full: String, admin: String },
    /// The episode is gone; why.
    Closed(String),
}

/// The feeds of the watched episodes: each episode's frames are made once for all its watchers.
pub(super) type Feeds = Arc<std::sync::Mutex<HashMap<EpisodeId, tokio::sync::watch::Receiver<Arc<FeedItem>>>>>;

/// An error answer: a status and a one-line JSON message.
pub(super) struct Failure(pub(super) StatusCode, pub(super) String);

impl IntoResponse for Failure {
    fn into_response(self) -> Response {
        (self.0, Json(json!({ "error": self.1 }))).into_response()
    }
}

impl From<ServiceError> for Failure {
    fn from(e: ServiceError) -> Self {
        use tonic::Code;
        let status = match e.code() {
            Code::InvalidArgument => StatusCode::BAD_REQUEST,
            Code::NotFound => StatusCode::NOT_FOUND,
            Code::PermissionDenied => StatusCode::FORBIDDEN,
            Code::FailedPrecondition => StatusCode::CONFLICT,
            Code::ResourceExhausted => StatusCode::TOO_MANY_REQUESTS,
            _ => StatusCode::INTERNAL_SERVER_ERROR,
        };
        Failure(status, e.to_string())
    }
}

/// The caller of a request: its bearer token, known to the server.
pub(super) fn caller(viewer: &Viewer, headers: &HeaderMap) -> Result<Arc<Caller>, Failure> {
    let given = headers.get(header::AUTHORIZATION).map(|v| v.as_bytes());
    viewer.tokens.identify(given).ok_or_else(|| {
        Failure(StatusCode::UNAUTHORIZED, "missing or unknown bearer token: enter a token the server knows".into())
    })
}

/// An episode's summary as the page lists it.
pub(super) fn summary_json(s: &EpisodeSummary) -> Value {
    json!({
        "id": s.id.as_str(),
        "scene": s.scene.id,
        "room_type": s.scene.room_type,
        "difficulty": s.scene.difficulty.as_str(),
        "split": s.scene.split.as_str(),
        "objects": s.scene.movable_objects,
        "steps": s.steps,
        "horizon": s.horizon,
        "placed": s.placed,
        "holding": s.holding,
        "ended": s.ended,
        "success": s.success,
        "owner": s.owner,
        "agent": s.agent,
        "age_seconds": (s.age_seconds * 10.0).round() / 10.0,
    })
}

/// An event stream answer.
pub(super) type Events =
    Sse<axum::response::sse::KeepAliveStream<tokio_stream::wrappers::ReceiverStream<Result<Event, Infallible>>>>;

/// The events sent through `receiver`, kept alive while none come.
pub(super) fn events(receiver: mpsc::Receiver<Result<Event, Infallible>>) -> Events {
    Sse::new(tokio_stream::wrappers::ReceiverStream::new(receiver)).keep_alive(KeepAlive::default())
}

/// The caller's token name and role, and whether the server is open (has no tokens).
pub(super) async fn whoami(State(viewer): State<Viewer>, headers: HeaderMap) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let open = !viewer.tokens.required();
    Ok(Json(json!({ "caller": &*caller.name, "role": caller.role.as_str(), "open": open })))
}
