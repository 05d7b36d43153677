//! Replaying: the server's records a caller may read, one whole, and an episode that re-runs a
//! record's actions, moved to any step on request (the simulator is deterministic).

use std::sync::Arc;

use axum::Json;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, StatusCode};
use serde::Deserialize;
use serde_json::{Value, json};

use super::state::{Failure, MAX_REPLAYS_PER_TOKEN, Replay, ReplaySlot, Viewer, caller};
use crate::error::ServiceError;
use crate::types::{Caller, CreateOptions, EpisodeId, SceneChoice, SensorRequest, StepCall};

/// The most records `/api/records` lists (the latest ones).
const LISTED_RECORDS: usize = 500;

#[derive(Deserialize)]
pub(super) struct RecordsQuery {
    scene: Option<String>,
}

/// The server's records the caller may read (its own; every token's for an admin), of one
/// scene if given, as summaries: the latest [`LISTED_RECORDS`], newest first.
pub(super) async fn records(
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
pub(super) async fn stored_record(
    State(viewer): State<Viewer>,
    Path((token, index)): Path<(String, usize)>,
    headers: HeaderMap,
) -> Result<Json<esrp_results::EpisodeRecord>, Failure> {
    let caller = caller(&viewer, &headers)?;
    Ok(Json(viewer.episodes.stored_record(&caller, &token, index).await?))
}

#[derive(Deserialize)]
pub(super) struct ReplayRequest {
    scene_id: String,
    horizon: Option<u32>,
    actions: Vec<u8>,
}

/// A new episode of the record's scene (and horizon) that re-runs its actions on request.
pub(super) async fn replay(
    State(viewer): State<Viewer>,
    headers: HeaderMap,
    Json(request): Json<ReplayRequest>,
) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    if let Some(bad) = request.actions.iter().find(|&&a| a > 5) {
        return Err(Failure(StatusCode::BAD_REQUEST, format!("actions: {bad} is not an action code (0..5)")));
    }
    {
        // Replays whose episode is gone (closed, reaped) are gone too; a token keeps a few.
        let mut replays = viewer.replays();
        replays.retain(|id, _| viewer.episodes.is_live(id));
        let open = replays.values().filter(|slot| slot.owner == caller.name).count();
        if open >= MAX_REPLAYS_PER_TOKEN {
            return Err(Failure(
                StatusCode::TOO_MANY_REQUESTS,
                format!("{} has {open} replays open, the most a token may: close one first", caller.describe()),
            ));
        }
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
    let replay = Arc::new(tokio::sync::Mutex::new(Replay { actions: request.actions, at: 0 }));
    viewer.replays().insert(created.episode.clone(), ReplaySlot { owner: caller.name.clone(), replay });
    Ok(Json(json!({ "episode": created.episode.as_str(), "scene": created.scene.id, "steps": steps })))
}

#[derive(Deserialize)]
pub(super) struct SeekBody {
    step: usize,
}

/// Moves a replay to step `step` (at most the record's length): forward by taking the record's
/// next actions, back by restarting the episode and taking them again; the simulator is
/// deterministic, so step k always shows the same state.
pub(super) async fn seek(
    State(viewer): State<Viewer>,
    Path(id): Path<String>,
    headers: HeaderMap,
    Json(body): Json<SeekBody>,
) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let id = EpisodeId::from(id);
    let replay = viewer.replays().get(&id).map(|slot| slot.replay.clone());
    let replay =
        replay.ok_or_else(|| Failure(StatusCode::NOT_FOUND, format!("no replay {id}: start one with /api/replay")))?;
    // This replay's lock alone while it steps: other replays and seeks go on meanwhile.
    let mut replay = replay.lock().await;
    let target = body.step.min(replay.actions.len());
    if let Err(error) = move_replay(&viewer, &caller, &id, &mut replay, target).await {
        if matches!(error, ServiceError::UnknownEpisode(_)) {
            // Its episode is gone (closed, or reaped): so is the replay.
            viewer.replays().remove(&id);
        }
        return Err(error.into());
    }
    Ok(Json(json!({ "step": replay.at, "steps": replay.actions.len() })))
}

/// Moves `replay` to step `target`: back by a reset, forward by taking the record's actions.
async fn move_replay(
    viewer: &Viewer,
    caller: &Arc<Caller>,
    id: &EpisodeId,
    replay: &mut Replay,
    target: usize,
) -> Result<(), ServiceError> {
    if target < replay.at {
        viewer.episodes.reset(caller, id, None).await?;
        replay.at = 0;
    }
    while replay.at < target {
        let action = esrp_core::Action::from_code(i64::from(replay.actions[replay.at]))
            .map_err(|e| ServiceError::InvalidArgument(e.to_string()))?;
        let call = StepCall { episode: id.clone(), action, include_goal: false };
        viewer.episodes.step_many(caller, vec![call]).await?;
        replay.at += 1;
    }
    Ok(())
}
