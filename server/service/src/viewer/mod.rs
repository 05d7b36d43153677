//! The web viewer (`--http-listen`): a third adapter over the episode layer, beside `esrp_v1`
//! and `dm_env`, that never goes through gRPC. An axum server serves one page (HTML, CSS and a
//! JS module embedded in the binary: no CDN, no download) and a small JSON API under `/api/`:
//!
//! | route | what |
//! |---|---|
//! | `GET /api/whoami` | the caller's token name and role |
//! | `GET /api/episodes` | the live episodes the caller may see (its own; all for an admin) |
//! | `GET /api/episodes/events` | the same list as a stream of server-sent events, sent when it changes |
//! | `GET /api/episodes/{id}/watch` | frames of one episode as server-sent events, at the agent's pace |
//! | `GET /api/scenes?split=&difficulty=&id=` | scenes to play (`id`: part of the id; an unknown split or difficulty is 400): `{scenes, total}`, the first 1,000 |
//! | `POST /api/play` | a new episode for the caller, driven from the page (agent `human`) |
//! | `POST /api/episodes/{id}/step` | one action of such an episode |
//! | `POST /api/episodes/{id}/close` | closes it |
//! | `GET /api/episodes/{id}/record` | the `esrp.results/v1` record of its last run that ended (played episodes) |
//! | `GET /api/records?scene=` | the server's records (`--records`) the caller may read, of one scene: the latest 500 |
//! | `GET /api/records/{token}/{index}` | one of them, whole |
//! | `POST /api/replay` | a new episode re-running a record's actions, for scrubbing |
//! | `POST /api/replay/{id}/seek` | moves a replay to step k: forward by stepping, back by a reset and stepping again |
//!
//! Every API call needs `authorization: Bearer TOKEN` when the server has tokens; with none, the
//! viewer serves only a loopback address (checked at start). Every failed API call answers a
//! JSON `{"error": "..."}` with its status, a malformed request (bad JSON, a missing field, a
//! path or query that does not parse), an unknown route and a wrong method included. A watched episode's frames are made
//! once for all its watchers, after its agent's steps and at most ten a second; each watcher gets
//! the latest when it has taken the previous one, so older frames are dropped, never queued.
//!
//! The handlers stand in a file per mode: [`watch`] (the episode list and the frames),
//! [`play`] (episodes driven from the page) and [`replay`] (the records and their replays), over
//! [`state`] (what the viewer keeps and what every handler shares).

mod play;
mod replay;
mod state;
mod watch;

use std::sync::Arc;

use axum::extract::Request;
use axum::http::{StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};

use crate::auth::Tokens;
use crate::episodes::Episodes;
use state::Viewer;

const INDEX: &str = include_str!("index.html");
const SCRIPT: &str = include_str!("app.js");
const STYLE: &str = include_str!("style.css");

/// The viewer's routes over `episodes`, authenticating with `tokens`.
pub fn router(episodes: Arc<Episodes>, tokens: Arc<Tokens>) -> axum::Router {
    axum::Router::new()
        .route("/", get(|| async { ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], INDEX) }))
        .route("/app.js", get(|| async { ([(header::CONTENT_TYPE, "text/javascript; charset=utf-8")], SCRIPT) }))
        .route("/style.css", get(|| async { ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE) }))
        .route("/api/whoami", get(state::whoami))
        .route("/api/episodes", get(watch::episodes_now))
        .route("/api/episodes/events", get(watch::episodes_events))
        .route("/api/episodes/{id}/watch", get(watch::watch))
        .route("/api/episodes/{id}/step", post(play::step))
        .route("/api/episodes/{id}/close", post(play::close))
        .route("/api/episodes/{id}/record", get(play::record))
        .route("/api/records", get(replay::records))
        .route("/api/records/{token}/{index}", get(replay::stored_record))
        .route("/api/replay", post(replay::replay))
        .route("/api/replay/{id}/seek", post(replay::seek))
        .route("/api/scenes", get(play::scenes))
        .route("/api/play", post(play::play))
        .fallback(|uri: axum::http::Uri| async move {
            let api = uri.path().starts_with("/api/");
            (StatusCode::NOT_FOUND, if api { "no such API route" } else { "no such page: the viewer is at /" })
        })
        .layer(middleware::from_fn(json_errors))
        .with_state(Viewer { episodes, tokens, replays: Default::default(), feeds: Default::default() })
}

/// Answers every failure of an `/api/` call as `{"error": "..."}`: the handlers' own failures
/// already are; axum's (a body that is not the JSON asked for, a path or query that does not
/// parse, an unknown route, a wrong method) come as plain text or empty, which the page could
/// only show as a bare status.
async fn json_errors(request: Request, next: Next) -> Response {
    let api = request.uri().path().starts_with("/api/");
    let response = next.run(request).await;
    let json =
        response.headers().get(header::CONTENT_TYPE).is_some_and(|v| v.as_bytes().starts_with(b"application/json"));
    if !api || json || !(response.status().is_client_error() || response.status().is_server_error()) {
        return response;
    }
    let (mut parts, body) = response.into_parts();
    let text = axum::body::to_bytes(body, 64 * 1024).await.unwrap_or_default();
    let mut message = String::from_utf8_lossy(&text).trim().to_owned();
    if message.is_empty() {
        message = match parts.status {
            StatusCode::NOT_FOUND => "no such API route".to_owned(),
            // axum adds the `allow` header, naming the one it takes, after this layer.
            StatusCode::METHOD_NOT_ALLOWED => {
                "wrong method for this route: its `allow` header names the one it takes".to_owned()
            }
            status => status.canonical_reason().unwrap_or("failed").to_owned(),
        };
    }
    parts.headers.remove(header::CONTENT_LENGTH);
    parts.headers.insert(header::CONTENT_TYPE, header::HeaderValue::from_static("application/json"));
    let body = serde_json::json!({ "error": message }).to_string();
    (parts, body).into_response()
}

/// Serves the viewer on `listener` until the task is aborted.
pub async fn serve(
    listener: tokio::net::TcpListener,
    episodes: Arc<Episodes>,
    tokens: Arc<Tokens>,
) -> std::io::Result<()> {
    axum::serve(listener, router(episodes, tokens)).await
}
