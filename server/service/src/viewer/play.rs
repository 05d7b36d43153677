//! Playing from the page: the scenes to choose from, a new episode for the caller (agent
//! `human`), its steps, its close and the record of its last run.

use axum::Json;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use esrp_core::{Difficulty, Split};
use serde::Deserialize;
use serde_json::{Value, json};

use super::state::{Failure, Viewer, caller};
use crate::types::{CreateOptions, EpisodeId, SceneChoice, SensorRequest, StepCall};

#[derive(Deserialize)]
pub(super) struct SceneQuery {
    split: Option<String>,
    difficulty: Option<String>,
    /// Part of the scene id.
    id: Option<String>,
}

/// The most scenes `/api/scenes` lists (the first ones; `total` says how many matched).
const LISTED_SCENES: usize = 1000;

/// The scenes of a split and difficulty (both optional), whose id contains `id` if given: the
/// first [`LISTED_SCENES`], and how many matched.
pub(super) async fn scenes(
    State(viewer): State<Viewer>,
    Query(q): Query<SceneQuery>,
    headers: HeaderMap,
) -> Result<Json<Value>, Failure> {
    caller(&viewer, &headers)?;
    let bad = |e: String| Failure(StatusCode::BAD_REQUEST, e);
    let split = q.split.filter(|s| !s.is_empty()).map(|s| s.parse::<Split>()).transpose().map_err(bad)?;
    let difficulty =
        q.difficulty.filter(|s| !s.is_empty()).map(|s| s.parse::<Difficulty>()).transpose().map_err(bad)?;
    let id = q.id.map(|s| s.trim().to_owned()).filter(|s| !s.is_empty());
    let infos = viewer.episodes.store.infos();
    let matching = infos
        .iter()
        .filter(|s| split.is_none_or(|x| x == s.split))
        .filter(|s| difficulty.is_none_or(|x| x == s.difficulty))
        .filter(|s| id.as_deref().is_none_or(|x| s.id.contains(x)));
    let mut total = 0;
    let mut list = Vec::new();
    for s in matching {
        total += 1;
        if list.len() < LISTED_SCENES {
            list.push(json!({ "id": s.id, "room_type": s.room_type, "difficulty": s.difficulty.as_str(),
                              "split": s.split.as_str(), "objects": s.movable_objects }));
        }
    }
    Ok(Json(json!({ "scenes": list, "total": total })))
}

#[derive(Deserialize)]
pub(super) struct PlayRequest {
    scene: String,
}

/// A new episode of `scene` for the caller, labelled `human`.
pub(super) async fn play(
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
pub(super) struct StepBody {
    action: u8,
}

pub(super) async fn step(
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

pub(super) async fn close(
    State(viewer): State<Viewer>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Json<Value>, Failure> {
    let caller = caller(&viewer, &headers)?;
    let id = EpisodeId::from(id);
    let m = viewer.episodes.close(&caller, &id).await?;
    // A replay of it ends with it.
    viewer.replays().remove(&id);
    Ok(Json(json!({ "success": m.success, "osr": m.object_success_rate, "steps": m.steps })))
}

/// The record of a played episode's last run that ended, as one `esrp.results/v1` line.
pub(super) async fn record(
    State(viewer): State<Viewer>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, Failure> {
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
