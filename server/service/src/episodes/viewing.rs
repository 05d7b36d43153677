//! What the web viewer sees of the live episodes: a summary of each one a caller may see (its
//! own; every one for an admin), and, for a watched episode, frames made on demand: the agent's
//! ego view (rendered again for the watcher: the pixels its client got), the goal image, and, where the
//! caller may read the episode's privileged state, the current top-down view (rendered only for
//! watchers) with the agent's and the carried objects' paths, each object's IoU and placed flag
//! and the RDR. An episode nobody watches costs one `Option` check a step.

use std::sync::Arc;

use bytes::Bytes;

use super::entry::EpisodeEntry;
use super::observe::Shot;
use super::state::Episodes;
use crate::error::ServiceError;
use crate::types::{Caller, EpisodeId, Role, SceneInfo};

/// The side of the top-down view a watcher gets, pixels.
pub const WATCH_TOP_DOWN: u32 = 256;

/// A live episode as the viewer lists it.
#[derive(Clone, Debug)]
pub struct EpisodeSummary {
    /// Its id.
    pub id: EpisodeId,
    /// Its scene.
    pub scene: SceneInfo,
    /// Steps taken in this run.
    pub steps: u32,
    /// Its horizon.
    pub horizon: u32,
    /// Objects placed now.
    pub placed: usize,
    /// Whether the agent holds an object.
    pub holding: bool,
    /// Whether the run has ended, and in success.
    pub ended: bool,
    /// Whether every object is placed.
    pub success: bool,
    /// The token that created it.
    pub owner: String,
    /// The agent's label.
    pub agent: String,
    /// Seconds since its entry was made (its create or last reset onto another scene).
    pub age_seconds: f64,
}

/// One object of a watched episode.
#[derive(Clone, Debug)]
pub struct ObjectView {
    /// Its id in the scene.
    pub id: String,
    /// Its footprint's IoU with its target.
    pub iou: f64,
    /// Whether it is placed.
    pub placed: bool,
}

/// What a watcher sees of an episode now.
#[derive(Clone, Debug)]
pub struct WatchFrame {
    /// The summary.
    pub summary: EpisodeSummary,
    /// The ego view its client got last, RGB, `resolution` × `resolution`.
    pub ego: Bytes,
    /// The goal image, RGB, `resolution` × `resolution`.
    pub goal: Bytes,
    /// The side of `ego` and `goal`.
    pub resolution: u32,
    /// The last actions: code and whether accepted.
    pub last_actions: Vec<(u8, bool)>,
    /// The privileged part, for a caller that may read it.
    pub privileged: Option<PrivilegedView>,
    /// Whether the episode serves the paper's observation only and has not ended: whoever but an
    /// admin watches it sees no placed count, success or accepted flags (what its client is not
    /// told either). `summary` is as the caller sees it; a feed made for an admin hides the rest.
    pub outcomes_hidden: bool,
}

/// The part of a watch frame only a caller allowed the privileged state sees.
#[derive(Clone, Debug)]
pub struct PrivilegedView {
    /// The current top-down view, RGB, [`WATCH_TOP_DOWN`] pixels square.
    pub top_down: Bytes,
    /// The agent's path, in the top-down view's pixels.
    pub agent_path: Vec<[f32; 2]>,
    /// Each carry's path (object index, pixels).
    pub carried_paths: Vec<(usize, Vec<[f32; 2]>)>,
    /// Each object.
    pub objects: Vec<ObjectView>,
    /// RDR now.
    pub rdr: f64,
}

/// The summary of `entry` as `caller` sees it: a paper-only episode (a hidden scene) shows no
/// placed count or success to anyone but an admin until it has ended.
fn summary_of(id: &EpisodeId, entry: &EpisodeEntry, caller: &Caller) -> EpisodeSummary {
    let mut m = entry.episode.metrics();
    if entry.paper_only && !caller.is_admin() && !entry.episode.is_over() {
        (m.placed, m.success) = (0, false);
    }
    EpisodeSummary {
        id: id.clone(),
        scene: entry.summary.clone(),
        steps: entry.episode.steps(),
        horizon: entry.episode.horizon(),
        placed: m.placed,
        holding: entry.episode.held().is_some(),
        ended: entry.episode.is_over(),
        success: m.success,
        owner: entry.owner.name.to_string(),
        agent: entry.agent.to_string(),
        age_seconds: entry.created.elapsed().as_secs_f64(),
    }
}

/// Whether `caller` may see the privileged part of `entry`: as for GetPrivilegedState, a
/// trainer or an admin, and never on a hidden scene.
fn sees_privileged(caller: &Caller, entry: &EpisodeEntry) -> bool {
    caller.role != Role::Agent && !entry.summary.split.is_hidden()
}

/// The live episodes `caller` may see, oldest first.
pub(super) async fn list(episodes: &Episodes, caller: &Caller) -> Vec<EpisodeSummary> {
    let mut out = Vec::new();
    for (id, shared) in episodes.registry.visible_to(caller) {
        let entry = shared.lock().await;
        out.push(summary_of(&id, &entry, caller));
    }
    out.sort_by(|a, b| b.age_seconds.total_cmp(&a.age_seconds).then_with(|| a.id.cmp(&b.id)));
    out
}

/// Starts watching the episode `id`: the receiver changes at every step (and reset). Its own
/// token watching it claims it, as a call naming it would: the watcher sees its views, so an
/// abandoned create of it no longer gives its attempt back.
pub(super) async fn subscribe(
    episodes: &Episodes,
    caller: &Caller,
    id: &EpisodeId,
) -> Result<tokio::sync::watch::Receiver<u64>, ServiceError> {
    let shared = episodes.registry.watch(id, caller)?;
    let mut entry = shared.lock().await;
    let watch = entry.watch.get_or_insert_with(|| tokio::sync::watch::channel(0).0);
    Ok(watch.subscribe())
}

/// Stops notifying the episode's watch if nobody watches any more.
pub(super) async fn unsubscribe(episodes: &Episodes, id: &EpisodeId) {
    if let Some(shared) = episodes.registry.peek_any(id) {
        let mut entry = shared.lock().await;
        if entry.watch.as_ref().is_some_and(|w| w.receiver_count() == 0) {
            entry.watch = None;
        }
    }
}

/// What `caller` sees of the episode `id` now (the goal image only if `with_goal`). The views
/// are made from the episode's state under its lock and rendered after it, so the agent steps on
/// meanwhile; the ego view is the one its client got (rendering is deterministic).
pub(super) async fn frame(
    episodes: &Arc<Episodes>,
    caller: &Caller,
    id: &EpisodeId,
    with_goal: bool,
) -> Result<WatchFrame, ServiceError> {
    let shared = episodes.registry.peek(id, caller)?;
    let (mut frame, ego, top_down) = {
        let entry = shared.lock().await;
        let privileged = sees_privileged(caller, &entry);
        let (ego, top_down) = entry.observer.watch_shots(&entry.episode, privileged.then_some(WATCH_TOP_DOWN));
        let (top_down, frame) = match top_down {
            Some((shot, frame)) => (Some(shot), Some(frame)),
            None => (None, None),
        };
        let privileged_view = frame.map(|frame| {
            let scale = f64::from(frame.resolution) / frame.side;
            let to_pixels = |p: &[f32; 2]| {
                [((f64::from(p[0]) - frame.min_x) * scale) as f32, ((f64::from(p[1]) - frame.min_z) * scale) as f32]
            };
            let state = entry.episode.privileged_state();
            PrivilegedView {
                top_down: Bytes::new(),
                agent_path: entry.trail.agent.iter().map(to_pixels).collect(),
                carried_paths: entry
                    .trail
                    .carried
                    .iter()
                    .map(|(i, path)| (*i, path.iter().map(to_pixels).collect()))
                    .collect(),
                objects: state
                    .objects
                    .iter()
                    .map(|o| ObjectView { id: o.id.clone(), iou: o.iou, placed: o.placed })
                    .collect(),
                rdr: entry.episode.metrics().remaining_distance_ratio,
            }
        });
        let frame = WatchFrame {
            summary: summary_of(id, &entry, caller),
            ego: Bytes::new(),
            goal: if with_goal { entry.observer.goal.clone() } else { Bytes::new() },
            resolution: entry.observer.sensors.resolution,
            last_actions: entry.trail.last.iter().copied().collect(),
            privileged: privileged_view,
            outcomes_hidden: entry.paper_only && !entry.episode.is_over(),
        };
        (frame, ego, top_down)
    };
    // Render only what was not made before: usually nothing but a top-down view while an object
    // is carried (the ego view is the one the episode's client got).
    let mut views = Vec::new();
    for shot in [Some(&ego), top_down.as_ref()].into_iter().flatten() {
        if let Shot::Render(view) = shot {
            views.push(view.clone());
        }
    }
    let mut rendered = if views.is_empty() { Vec::new() } else { episodes.render.render(views).await? }.into_iter();
    let missing = || ServiceError::Internal("the renderer answered fewer views than asked".into());
    frame.ego = match ego {
        Shot::Ready(rgb) => rgb,
        Shot::Render(_) => rendered.next().ok_or_else(missing)?.rgb,
    };
    if let (Some(p), Some(shot)) = (frame.privileged.as_mut(), top_down) {
        p.top_down = match shot {
            Shot::Ready(rgb) => rgb,
            Shot::Render(view) => {
                let output = rendered.next().ok_or_else(missing)?;
                let rgb = output.rgb.clone();
                shared.lock().await.observer.watched(view, output);
                rgb
            }
        };
    }
    Ok(frame)
}

/// The record of the last run of the episode `id` that ended, for an episode whose runs keep
/// theirs (the viewer's human play).
pub(super) async fn last_record(
    episodes: &Episodes,
    caller: &Caller,
    id: &EpisodeId,
) -> Result<Option<esrp_results::EpisodeRecord>, ServiceError> {
    let shared = episodes.registry.peek(id, caller)?;
    let entry = shared.lock().await;
    Ok(entry.last_record.clone())
}
