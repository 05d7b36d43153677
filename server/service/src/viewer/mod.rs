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
//! | `GET /api/scenes?split=&difficulty=` | scenes to play (at most 1,000) |
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
//! viewer serves only a loopback address (checked at start). A watched episode's frames are made
//! once for all its watchers, after its agent's steps and at most ten a second; each watcher gets
//! the latest when it has taken the previous one, so older frames are dropped, never queued.

use std::collections::HashMap;
use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::Json;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use base64::Engine as _;
use serde::Deserialize;
use serde_json::{Value, json};
use tokio::sync::mpsc;

use crate::auth::Tokens;
use crate::episodes::{EpisodeSummary, Episodes, WatchFrame};
use crate::error::ServiceError;
use crate::types::{Caller, CreateOptions, EpisodeId, Role, SceneChoice, SensorRequest, StepCall};

const INDEX: &str = include_str!("index.html");
const SCRIPT: &str = include_str!("app.js");
const STYLE: &str = include_str!("style.css");

/// The viewer's shared state.
#[derive(Clone)]
struct Viewer {
    episodes: Arc<Episodes>,
    tokens: Arc<Tokens>,
    /// The replays: each episode's record actions and how many of them it has taken.
    replays: Arc<tokio::sync::Mutex<HashMap<EpisodeId, Replay>>>,
    /// The watched episodes' feeds.
    feeds: Feeds,
}

/// A record being replayed.
struct Replay {
    actions: Vec<u8>,
    at: usize,
}

/// The viewer's routes over `episodes`, authenticating with `tokens`.
pub fn router(episodes: Arc<Episodes>, tokens: Arc<Tokens>) -> axum::Router {
    axum::Router::new()
        .route("/", get(|| async { ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], INDEX) }))
        .route("/app.js", get(|| async { ([(header::CONTENT_TYPE, "text/javascript; charset=utf-8")], SCRIPT) }))
        .route("/style.css", get(|| async { ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE) }))
        .route("/api/whoami", get(whoami))
        .route("/api/episodes", get(episodes_now))
        .route("/api/episodes/events", get(episodes_events))
        .route("/api/episodes/{id}/watch", get(watch))
        .route("/api/episodes/{id}/step", post(step))
        .route("/api/episodes/{id}/close", post(close))
        .route("/api/episodes/{id}/record", get(record))
        .route("/api/records", get(records))
        .route("/api/records/{token}/{index}", get(stored_record))
        .route("/api/replay", post(replay))
        .route("/api/replay/{id}/seek", post(seek))
        .route("/api/scenes", get(scenes))
        .route("/api/play", post(play))
        .with_state(Viewer { episodes, tokens, replays: Default::default(), feeds: Default::default() })
}

/// Serves the viewer on `listener` until the task is aborted.
pub async fn serve(
    listener: tokio::net::TcpListener,
    episodes: Arc<Episodes>,
    tokens: Arc<Tokens>,
) -> std::io::Result<()> {
    axum::serve(listener, router(episodes, tokens)).await
}

/// An error answer: a status and a one-line JSON message.
struct Failure(StatusCode, String);

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
fn caller(viewer: &Viewer, headers: &HeaderMap) -> Result<Arc<Caller>, Failure> {
    let given = headers.get(header::AUTHORIZATION).map(|v| v.as_bytes());
    viewer.tokens.identify(given).ok_or_else(|| {
        Failure(StatusCode::UNAUTHORIZED, "missing or unknown bearer token: enter a token the server knows".into())
    })
}

fn summary_json(s: &EpisodeSummary) -> Value {
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

fn png_url(rgb: &[u8], side: u32) -> Value {
    if rgb.len() != (side * side * 3) as usize {
        return Value::Null;
    }
    match esrp_render::encode_png_rgb_fast(rgb, side, side) {
        Ok(png) => format!("data:image/png;base64,{}", base64::engine::general_purpose::STANDARD.encode(png)).into(),
        Err(_) => Value::Null,
    }
}

/// The last image a feed encoded, kept while the next frame shows the same pixels (an ego view
/// after a rejected step; the top-down view while nothing moves), so that it is not encoded again.
#[derive(Default)]
struct Encoded {
    rgb: bytes::Bytes,
    url: Value,
}

impl Encoded {
    /// `rgb` (a `side`-pixel square) as a PNG data URL: the one kept if it shows the same pixels.
    fn url(&mut self, rgb: &bytes::Bytes, side: u32) -> Value {
        if self.url.is_null() || self.rgb != *rgb {
            *self = Encoded { rgb: rgb.clone(), url: png_url(rgb, side) };
        }
        self.url.clone()
    }
}

/// A frame as JSON, its images encoded through `ego` and `top_down` (the feed's last images).
fn frame_json(f: &WatchFrame, ego: &mut Encoded, top_down: &mut Encoded) -> Value {
    let mut out = json!({
        "episode": summary_json(&f.summary),
        "ego": ego.url(&f.ego, f.resolution),
        "last_actions": f.last_actions.iter().map(|&(a, ok)| json!({ "action": a, "accepted": ok })).collect::<Vec<_>>(),
    });
    if !f.goal.is_empty() {
        out["goal"] = png_url(&f.goal, f.resolution);
    }
    if let Some(p) = &f.privileged {
        out["top_down"] = top_down.url(&p.top_down, crate::episodes::WATCH_TOP_DOWN);
        out["top_down_side"] = crate::episodes::WATCH_TOP_DOWN.into();
        out["agent_path"] = json!(p.agent_path);
        out["carried_paths"] =
            p.carried_paths.iter().map(|(i, path)| json!({ "object": i, "path": path })).collect::<Vec<_>>().into();
        out["objects"] = p
            .objects
            .iter()
            .map(|o| json!({ "id": o.id, "iou": (o.iou * 1000.0).round() / 1000.0, "placed": o.placed }))
            .collect::<Vec<_>>()
            .into();
        out["rdr"] = ((p.rdr * 10_000.0).round() / 10_000.0).into();
    }
    out
}

async fn whoami(State(viewer): State<Viewer>, headers: HeaderMap) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let open = !viewer.tokens.required();
    Ok(Json(json!({ "caller": &*caller.name, "role": caller.role.as_str(), "open": open })))
}

async fn episodes_now(State(viewer): State<Viewer>, headers: HeaderMap) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let list = viewer.episodes.list(&caller).await;
    Ok(Json(list.iter().map(summary_json).collect::<Vec<_>>().into()))
}

type Events =
    Sse<axum::response::sse::KeepAliveStream<tokio_stream::wrappers::ReceiverStream<Result<Event, Infallible>>>>;

fn events(receiver: mpsc::Receiver<Result<Event, Infallible>>) -> Events {
    Sse::new(tokio_stream::wrappers::ReceiverStream::new(receiver)).keep_alive(KeepAlive::default())
}

/// The list of episodes, sent again whenever it changes (checked twice a second while the
/// page is connected).
async fn episodes_events(State(viewer): State<Viewer>, headers: HeaderMap) -> Result<Events, Failure> {
    let caller = caller(&viewer, &headers)?;
    let (sender, receiver) = mpsc::channel(1);
    tokio::spawn(async move {
        let mut last = String::new();
        loop {
            let list = viewer.episodes.list(&caller).await;
            // Ages change all the time: compare without them.
            let key = list
                .iter()
                .map(|s| format!("{}:{}:{}:{}:{}", s.id, s.steps, s.placed, s.holding, s.ended))
                .collect::<Vec<_>>()
                .join(",");
            if key != last || last.is_empty() {
                let data = Value::from(list.iter().map(summary_json).collect::<Vec<_>>()).to_string();
                if sender.send(Ok(Event::default().event("episodes").data(data))).await.is_err() {
                    return;
                }
                last = if key.is_empty() { "-".into() } else { key };
            }
            tokio::select! {
                () = tokio::time::sleep(Duration::from_millis(500)) => {}
                () = sender.closed() => return,
            }
        }
    });
    Ok(events(receiver))
}

/// Frames a second a watched episode's feed makes at most: a page shows no more, and the
/// rendering they need (an ego and a top-down view each) stays a small share of the render
/// thread's work however fast the agent steps and however many watch.
const FRAMES_PER_SECOND: u64 = 10;

/// What a feed publishes.
enum FeedItem {
    /// Nothing yet.
    Pending,
    /// A frame, as every watcher sees it (`public`) and with the privileged part (`full`).
    Frame { public: String, full: String },
    /// The episode is gone; why.
    Closed(String),
}

/// The feeds of the watched episodes: each episode's frames are made once for all its watchers.
type Feeds = Arc<std::sync::Mutex<HashMap<EpisodeId, tokio::sync::watch::Receiver<Arc<FeedItem>>>>>;

/// The feed of episode `id`, started if none runs.
async fn feed_of(viewer: &Viewer, id: &EpisodeId) -> Result<tokio::sync::watch::Receiver<Arc<FeedItem>>, Failure> {
    if let Some(feed) = viewer.feeds.lock().unwrap_or_else(|p| p.into_inner()).get(id)
        && feed.has_changed().is_ok()
    {
        return Ok(feed.clone());
    }
    // The feed's own view of the episode: an admin's (each watcher's right to it was checked).
    let internal = Arc::new(Caller { name: "viewer".into(), role: Role::Admin, max_episodes: None, max_streams: None });
    let changes = viewer.episodes.watch(&internal, id).await?;
    let (sender, receiver) = tokio::sync::watch::channel(Arc::new(FeedItem::Pending));
    let mut feeds = viewer.feeds.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(feed) = feeds.get(id)
        && feed.has_changed().is_ok()
    {
        return Ok(feed.clone()); // another watcher started it meanwhile
    }
    feeds.insert(id.clone(), receiver.clone());
    drop(feeds);
    tokio::spawn(produce(viewer.clone(), internal, id.clone(), changes, sender));
    Ok(receiver)
}

/// Makes an episode's frames while anyone watches: one at once, then one after the agent's
/// steps, at most [`FRAMES_PER_SECOND`] a second; the states in between are skipped.
async fn produce(
    viewer: Viewer,
    internal: Arc<Caller>,
    id: EpisodeId,
    mut changes: tokio::sync::watch::Receiver<u64>,
    out: tokio::sync::watch::Sender<Arc<FeedItem>>,
) {
    let mut goal = Value::Null;
    let (mut ego, mut top_down) = (Encoded::default(), Encoded::default());
    let pause = Duration::from_millis(1000 / FRAMES_PER_SECOND);
    loop {
        changes.mark_unchanged();
        match viewer.episodes.watch_frame(&internal, &id, goal.is_null()).await {
            Ok(frame) => {
                let mut full = frame_json(&frame, &mut ego, &mut top_down);
                if goal.is_null() {
                    goal = full["goal"].clone();
                } else {
                    full["goal"] = goal.clone();
                }
                let mut public = full.clone();
                if let Some(fields) = public.as_object_mut() {
                    for key in PRIVILEGED_KEYS {
                        fields.remove(key);
                    }
                }
                out.send_replace(Arc::new(FeedItem::Frame { public: public.to_string(), full: full.to_string() }));
            }
            Err(e) => {
                out.send_replace(Arc::new(FeedItem::Closed(e.to_string())));
                break;
            }
        }
        tokio::select! {
            () = tokio::time::sleep(pause) => {}
            () = out.closed() => break,
        }
        tokio::select! {
            changed = changes.changed() => {
                if changed.is_err() {
                    out.send_replace(Arc::new(FeedItem::Closed("the episode was closed".into())));
                    break;
                }
            }
            () = out.closed() => break,
        }
    }
    drop(changes);
    viewer.feeds.lock().unwrap_or_else(|p| p.into_inner()).remove(&id);
    viewer.episodes.unwatch(&id).await;
}

/// The frame fields only a caller allowed the privileged state sees.
const PRIVILEGED_KEYS: [&str; 6] = ["top_down", "top_down_side", "agent_path", "carried_paths", "objects", "rdr"];

/// Frames of one episode as the caller may see them: one at once, then one after the agent's
/// steps, at most [`FRAMES_PER_SECOND`] a second, each sent when the page has taken the previous
/// one; `closed` when the episode goes.
async fn watch(State(viewer): State<Viewer>, Path(id): Path<String>, headers: HeaderMap) -> Result<Events, Failure> {
    let caller = caller(&viewer, &headers)?;
    let id = EpisodeId::from(id);
    // The caller's right to watch it (its own episode, or an admin), checked here.
    drop(viewer.episodes.watch(&caller, &id).await?);
    let privileged = caller.role != Role::Agent;
    let mut frames = feed_of(&viewer, &id).await?;
    let (sender, receiver) = mpsc::channel(1);
    tokio::spawn(async move {
        loop {
            let item = frames.borrow_and_update().clone();
            let event = match &*item {
                FeedItem::Pending => None,
                FeedItem::Frame { public, full } => {
                    Some(Event::default().event("frame").data(if privileged { full } else { public }))
                }
                FeedItem::Closed(why) => {
                    let _ = sender.send(Ok(Event::default().event("closed").data(why))).await;
                    break;
                }
            };
            // Waits while the page reads the previous frame: the frames in between are skipped.
            if let Some(event) = event
                && sender.send(Ok(event)).await.is_err()
            {
                break;
            }
            tokio::select! {
                changed = frames.changed() => {
                    if changed.is_err() {
                        let _ = sender.send(Ok(Event::default().event("closed").data("the episode was closed"))).await;
                        break;
                    }
                }
                () = sender.closed() => break,
            }
        }
    });
    Ok(events(receiver))
}

#[derive(Deserialize)]
struct SceneQuery {
    split: Option<String>,
    difficulty: Option<String>,
}

async fn scenes(
    State(viewer): State<Viewer>,
    Query(q): Query<SceneQuery>,
    headers: HeaderMap,
) -> Result<Json<Value>, Failure> {
    caller(&viewer, &headers)?;
    let split = q.split.filter(|s| !s.is_empty());
    let difficulty = q.difficulty.filter(|s| !s.is_empty());
    let list: Vec<Value> = viewer
        .episodes
        .store
        .infos()
        .iter()
        .filter(|s| split.as_deref().is_none_or(|x| x == s.split.as_str()))
        .filter(|s| difficulty.as_deref().is_none_or(|x| x == s.difficulty.as_str()))
        .take(1000)
        .map(|s| {
            json!({ "id": s.id, "room_type": s.room_type, "difficulty": s.difficulty.as_str(),
                    "split": s.split.as_str(), "objects": s.movable_objects })
        })
        .collect();
    Ok(Json(list.into()))
}

#[derive(Deserialize)]
struct PlayRequest {
    scene: String,
}

/// A new episode of `scene` for the caller, labelled `human`.
async fn play(
    State(viewer): State<Viewer>,
    headers: HeaderMap,
    Json(request): Json<PlayRequest>,
) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let options = CreateOptions {
        scene: SceneChoice::SceneId(request.scene),
        sensors: SensorRequest::default(),
        horizon: None,
        reward: Default::default(),
        privileged: false,
        agent: Some("human".into()),
        keep_record: true,
    };
    let created = viewer.episodes.create(&caller, options, None).await?;
    viewer.episodes.claim(&created.episode);
    Ok(Json(json!({ "episode": created.episode.as_str(), "scene": created.scene.id })))
}

#[derive(Deserialize)]
struct StepBody {
    action: u8,
}

async fn step(
    State(viewer): State<Viewer>,
    Path(id): Path<String>,
    headers: HeaderMap,
    Json(body): Json<StepBody>,
) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let action = esrp_core::Action::from_code(i64::from(body.action))
        .map_err(|e| Failure(StatusCode::BAD_REQUEST, format!("action: {e}")))?;
    let call = StepCall { episode: EpisodeId::from(id), action, include_goal: false };
    let result = viewer.episodes.step_many(&caller, vec![call]).await?.pop();
    let result = result.ok_or_else(|| Failure(StatusCode::INTERNAL_SERVER_ERROR, "a step without an answer".into()))?;
    let o = result.outcome;
    let metrics = result.metrics.map(|m| {
        json!({ "success": m.success, "osr": m.object_success_rate, "rdr": m.remaining_distance_ratio,
                "stage": m.stage as u32, "steps": m.steps })
    });
    Ok(Json(json!({
        "step": o.step_index,
        "accepted": o.accepted,
        "placed": o.placed_count,
        "terminated": o.terminated,
        "truncated": o.truncated,
        "metrics": metrics,
    })))
}

async fn close(
    State(viewer): State<Viewer>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let m = viewer.episodes.close(&caller, &EpisodeId::from(id)).await?;
    Ok(Json(json!({ "success": m.success, "osr": m.object_success_rate, "steps": m.steps })))
}

/// The record of a played episode's last run that ended, as one `esrp.results/v1` line.
async fn record(State(viewer): State<Viewer>, Path(id): Path<String>, headers: HeaderMap) -> Result<Response, Failure> {
    let caller = caller(&viewer, &headers)?;
    match viewer.episodes.last_record(&caller, &EpisodeId::from(id)).await? {
        Some(record) => {
            let mut line = serde_json::to_string(&record)
                .map_err(|e| Failure(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
            line.push('\n');
            Ok(([(header::CONTENT_TYPE, "application/x-ndjson")], line).into_response())
        }
        None => {
            Err(Failure(StatusCode::NOT_FOUND, "no record yet: a played episode has one once a run of it ends".into()))
        }
    }
}

/// The most records `/api/records` lists (the latest ones).
const LISTED_RECORDS: usize = 500;

#[derive(Deserialize)]
struct RecordsQuery {
    scene: Option<String>,
}

/// The server's records the caller may read (its own; every token's for an admin), of one
/// scene if given, as summaries: the latest [`LISTED_RECORDS`], newest first.
async fn records(
    State(viewer): State<Viewer>,
    headers: HeaderMap,
    Query(query): Query<RecordsQuery>,
) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let scene = query.scene.map(|s| s.trim().to_owned()).filter(|s| !s.is_empty());
    let mut found = viewer.episodes.stored_records(&caller, scene).await?;
    found.sort_by(|a, b| b.record.finished_at.cmp(&a.record.finished_at));
    let total = found.len();
    let listed: Vec<Value> = found
        .iter()
        .take(LISTED_RECORDS)
        .map(|s| {
            let r = &s.record;
            json!({
                "token": s.token,
                "index": s.index,
                "scene_id": r.scene_id,
                "agent": r.agent,
                "success": r.success,
                "steps": r.steps,
                "horizon": r.horizon,
                "finished_at": r.finished_at,
                "counted": r.counted,
            })
        })
        .collect();
    Ok(Json(json!({ "records": listed, "total": total })))
}

/// One record of the server's records, whole (`esrp.results/v1`).
async fn stored_record(
    State(viewer): State<Viewer>,
    Path((token, index)): Path<(String, usize)>,
    headers: HeaderMap,
) -> Result<Json<esrp_results::EpisodeRecord>, Failure> {
    let caller = caller(&viewer, &headers)?;
    Ok(Json(viewer.episodes.stored_record(&caller, &token, index).await?))
}

#[derive(Deserialize)]
struct ReplayRequest {
    scene_id: String,
    horizon: Option<u32>,
    actions: Vec<u8>,
}

/// A new episode of the record's scene (and horizon) that re-runs its actions on request.
async fn replay(
    State(viewer): State<Viewer>,
    headers: HeaderMap,
    Json(request): Json<ReplayRequest>,
) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    if let Some(bad) = request.actions.iter().find(|&&a| a > 5) {
        return Err(Failure(StatusCode::BAD_REQUEST, format!("actions: {bad} is not an action code (0..5)")));
    }
    let options = CreateOptions {
        scene: SceneChoice::SceneId(request.scene_id),
        sensors: SensorRequest::default(),
        horizon: request.horizon.filter(|&h| h > 0),
        reward: Default::default(),
        privileged: false,
        agent: Some("replay".into()),
        keep_record: false,
    };
    let created = viewer.episodes.create(&caller, options, None).await?;
    viewer.episodes.claim(&created.episode);
    let steps = request.actions.len();
    viewer.replays.lock().await.insert(created.episode.clone(), Replay { actions: request.actions, at: 0 });
    Ok(Json(json!({ "episode": created.episode.as_str(), "scene": created.scene.id, "steps": steps })))
}

#[derive(Deserialize)]
struct SeekBody {
    step: usize,
}

/// Moves a replay to step `step` (at most the record's length): forward by taking the record's
/// next actions, back by restarting the episode and taking them again; the simulator is
/// deterministic, so step k always shows the same state.
async fn seek(
    State(viewer): State<Viewer>,
    Path(id): Path<String>,
    headers: HeaderMap,
    Json(body): Json<SeekBody>,
) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let id = EpisodeId::from(id);
    let mut replays = viewer.replays.lock().await;
    let replay = replays
        .get_mut(&id)
        .ok_or_else(|| Failure(StatusCode::NOT_FOUND, format!("no replay {id}: start one with /api/replay")))?;
    let target = body.step.min(replay.actions.len());
    if target < replay.at {
        viewer.episodes.reset(&caller, &id, None).await?;
        replay.at = 0;
    }
    while replay.at < target {
        let action = esrp_core::Action::from_code(i64::from(replay.actions[replay.at]))
            .map_err(|e| Failure(StatusCode::BAD_REQUEST, e.to_string()))?;
        let call = StepCall { episode: id.clone(), action, include_goal: false };
        viewer.episodes.step_many(&caller, vec![call]).await?;
        replay.at += 1;
    }
    Ok(Json(json!({ "step": replay.at, "steps": replay.actions.len() })))
}
