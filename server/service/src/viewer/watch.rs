//! Watching: the live episodes a caller may see (now, and as a stream of changes), and one
//! episode's frames. Each watched episode has one feed that makes its frames for all its
//! watchers; each watcher gets the latest when it has taken the previous one.

use std::sync::Arc;
use std::time::Duration;

use axum::Json;
use axum::extract::{Path, State};
use axum::http::HeaderMap;
use axum::response::sse::Event;
use base64::Engine as _;
use serde_json::{Value, json};
use tokio::sync::mpsc;

use super::state::{Events, Failure, FeedItem, Viewer, caller, events, summary_json};
use crate::episodes::WatchFrame;
use crate::types::{Caller, EpisodeId, Role};

/// The live episodes the caller may see (its own; all for an admin).
pub(super) async fn episodes_now(State(viewer): State<Viewer>, headers: HeaderMap) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let list = viewer.episodes.list(&caller).await;
    Ok(Json(list.iter().map(summary_json).collect::<Vec<_>>().into()))
}

/// The list of episodes, sent again whenever it changes (checked twice a second while the
/// page is connected).
pub(super) async fn episodes_events(State(viewer): State<Viewer>, headers: HeaderMap) -> Result<Events, Failure> {
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
                let admin = full.to_string();
                if frame.outcomes_hidden {
                    hide_outcomes(&mut full);
                }
                let mut public = full.clone();
                if let Some(fields) = public.as_object_mut() {
                    for key in PRIVILEGED_KEYS {
                        fields.remove(key);
                    }
                }
                let (public, full) = (public.to_string(), full.to_string());
                out.send_replace(Arc::new(FeedItem::Frame { public, full, admin }));
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

/// Takes out of a frame what a paper-only episode's client is not told until it ends (its
/// placed count, success and whether each action was accepted), as its watcher's summary does.
fn hide_outcomes(frame: &mut Value) {
    if let Some(episode) = frame.get_mut("episode").and_then(Value::as_object_mut) {
        episode.insert("placed".into(), 0.into());
        episode.insert("success".into(), false.into());
    }
    if let Some(actions) = frame.get_mut("last_actions").and_then(Value::as_array_mut) {
        for action in actions.iter_mut().filter_map(Value::as_object_mut) {
            action.remove("accepted");
        }
    }
}

/// The frame fields only a caller allowed the privileged state sees.
const PRIVILEGED_KEYS: [&str; 6] = ["top_down", "top_down_side", "agent_path", "carried_paths", "objects", "rdr"];

/// Frames of one episode as the caller may see them: one at once, then one after the agent's
/// steps, at most [`FRAMES_PER_SECOND`] a second, each sent when the page has taken the previous
/// one; `closed` when the episode goes.
pub(super) async fn watch(
    State(viewer): State<Viewer>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Events, Failure> {
    let caller = caller(&viewer, &headers)?;
    let id = EpisodeId::from(id);
    // The caller's right to watch it (its own episode, or an admin), checked here.
    drop(viewer.episodes.watch(&caller, &id).await?);
    let (privileged, admin) = (caller.role != Role::Agent, caller.is_admin());
    let mut frames = feed_of(&viewer, &id).await?;
    let (sender, receiver) = mpsc::channel(1);
    tokio::spawn(async move {
        loop {
            let item = frames.borrow_and_update().clone();
            let event = match &*item {
                FeedItem::Pending => None,
                FeedItem::Frame { public, full, admin: unhidden } => {
                    let data = if admin {
                        unhidden
                    } else if privileged {
                        full
                    } else {
                        public
                    };
                    Some(Event::default().event("frame").data(data))
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
