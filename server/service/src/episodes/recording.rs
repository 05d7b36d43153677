//! The runs the server records or counts (`--records`, the challenge's one counted attempt per
//! scene and token): starting a run, logging its actions (in `stepping`), and ending it into an
//! `esrp.results/v1` record, whatever ends it: its last step, a close, a reset, a reaper, the end
//! of its stream, or the server's shutdown. An episode whose create answer never left, and that
//! no call has named, is not a run: its attempt is given back. Once a call has named it, it is.

use std::time::{Instant, SystemTime};

use esrp_core::Split;
use esrp_results::{EpisodeRecord, SCHEMA};

use super::entry::{EpisodeEntry, RunLog};
use super::state::Episodes;
use crate::error::ServiceError;
use crate::records::{RecordMode, Written, rfc3339};
use crate::registry::Removed;
use crate::types::Caller;

/// Starts a run of `caller` on scene `scene` of `split`: takes the counted attempt (a
/// challenge scene, a caller that is not an admin) or refuses a second one; the run is logged
/// if it is counted or recorded, or if it `keep`s its record (then it is recorded whatever
/// `--record` says, where the server keeps records).
pub(super) fn begin(
    episodes: &Episodes,
    caller: &Caller,
    split: Split,
    scene: &str,
    keep: bool,
) -> Result<Option<RunLog>, ServiceError> {
    let counted = split == Split::Challenge && !caller.is_admin();
    let recorded =
        episodes.recorder.as_ref().is_some_and(|r| keep || r.mode() == RecordMode::All || split == Split::Challenge);
    if counted {
        episodes.attempts.take(caller, scene)?;
    }
    Ok((counted || recorded || keep).then(|| RunLog {
        actions: Vec::new(),
        started: SystemTime::now(),
        clock: Instant::now(),
        counted,
        recorded,
        keep,
        finished: false,
    }))
}

/// Ends the entry's run, if it is logged and not ended yet: marks its counted attempt ended and
/// returns its record if the server records it. `closed_by` says what closed an episode that
/// had not ended (`client`, `idle`, `unclaimed`, `stream`, `reset`, `shutdown`).
pub(super) fn finish(episodes: &Episodes, entry: &mut EpisodeEntry, closed_by: Option<&str>) -> Option<EpisodeRecord> {
    let run = entry.run.as_mut().filter(|r| !r.finished)?;
    run.finished = true;
    let finished_at = rfc3339(SystemTime::now());
    if run.counted {
        episodes.attempts.ended(&entry.owner.name, &entry.summary.id, &finished_at);
    }
    if !run.recorded && !run.keep {
        return None;
    }
    let keep = run.keep;
    let played = Played {
        episode: &entry.episode,
        summary: &entry.summary,
        agent: &entry.agent,
        token: &entry.owner.name,
        paper_only: entry.paper_only,
        privileged: entry.privileged,
    };
    let record = record_of(episodes, &played, run, closed_by, finished_at);
    if keep {
        entry.last_record = Some(record.clone());
    }
    Some(record)
}

/// What a record tells of a run besides its log.
struct Played<'a> {
    episode: &'a esrp_core::Episode,
    summary: &'a crate::types::SceneInfo,
    agent: &'a str,
    token: &'a str,
    paper_only: bool,
    /// The episode could read the simulator's state (its record says so).
    privileged: bool,
}

/// The record of a run ended at `finished_at` (its actions taken out of `run`).
fn record_of(
    episodes: &Episodes,
    played: &Played<'_>,
    run: &mut RunLog,
    closed_by: Option<&str>,
    finished_at: String,
) -> EpisodeRecord {
    let Played { episode, summary, agent, token, paper_only, privileged } = *played;
    let m = episode.metrics();
    let over = episode.is_over();
    let end = if m.success {
        "success"
    } else if over {
        "horizon"
    } else {
        "agent"
    };
    let mut agent_stats = serde_json::Map::new();
    if let (false, Some(by)) = (over, closed_by) {
        agent_stats.insert("closed_by".into(), by.into());
    }
    EpisodeRecord {
        schema: SCHEMA.to_owned(),
        scene_id: summary.id.clone(),
        dataset: episodes.store.name().to_owned(),
        split: summary.split.as_str().to_owned(),
        room_type: summary.room_type.clone(),
        difficulty: summary.difficulty.as_str().to_owned(),
        objects: summary.movable_objects as u32,
        agent: agent.to_owned(),
        agent_config: serde_json::Map::new(),
        seed: None,
        success: m.success,
        osr: m.object_success_rate,
        rdr: m.remaining_distance_ratio,
        stage: m.stage as u32,
        placed: m.placed as u32,
        steps: m.steps,
        horizon: episode.horizon(),
        end: end.to_owned(),
        total_reward: m.total_reward,
        actions: std::mem::take(&mut run.actions),
        wall_seconds: run.clock.elapsed().as_secs_f64(),
        agent_stats,
        server_version: env!("CARGO_PKG_VERSION").to_owned(),
        client: concat!("esrp-server ", env!("CARGO_PKG_VERSION")).to_owned(),
        finished_at,
        privileged: privileged.then_some(true),
        token: Some(token.to_owned()),
        started_at: Some(rfc3339(run.started)),
        dataset_hash: Some(episodes.dataset_hash.clone()),
        counted: Some(run.counted),
        reward_weights: serde_json::to_value(episode.config().reward).ok().and_then(|v| v.as_object().cloned()),
        observations: Some(if paper_only { "paper" } else { "full" }.to_owned()),
        signature: None,
    }
}

/// Journals the claim of a counted run and waits until it is on disk (where the server keeps
/// records): from then on, no crash gives the attempt back. A claim that could not be written
/// refuses the run ([`ServiceError::NotRecordable`]; the caller gives the attempt back).
pub(super) async fn claim(
    episodes: &Episodes,
    caller: &Caller,
    scene: &str,
    agent: &str,
    config: esrp_core::EpisodeConfig,
    run: &RunLog,
) -> Result<(), ServiceError> {
    if let Some(recorder) = &episodes.recorder {
        let claim = crate::records::Claim {
            token: caller.name.to_string(),
            scene: scene.to_owned(),
            agent: agent.to_owned(),
            started_at: rfc3339(run.started),
            config,
        };
        recorder.claim(&claim).outcome().await.map_err(ServiceError::NotRecordable)?;
    }
    Ok(())
}

/// Gives `token`'s attempt at `scene` back (its episode was never used), in memory and in the
/// journal.
pub(super) fn give_back(episodes: &Episodes, token: &std::sync::Arc<str>, scene: &str) {
    episodes.attempts.give_back(token, scene);
    if let Some(recorder) = &episodes.recorder {
        recorder.journal_release(token, scene);
    }
}

/// Records the counted attempts a crash cut (claimed in the journal, with no record), before
/// the server serves anything: each is replayed from its scene's start through its journaled
/// actions, recorded as ended there (`closed_by: "restart"`), and counted. Returns how many.
pub(super) fn recover(episodes: &Episodes) -> Result<usize, ServiceError> {
    let Some(recorder) = &episodes.recorder else { return Ok(0) };
    let internal = |e: crate::records::RecordsError| ServiceError::Internal(e.to_string());
    let mut recovered = 0;
    for journaled in crate::records::read_journal(recorder.dir()).map_err(internal)? {
        let crate::records::Claim { token, scene, agent, started_at, config } = &journaled.claim;
        if episodes.attempts.is_ended(token, scene) {
            continue;
        }
        let compiled = episodes.store.compiled(episodes.store.index_of(scene)?)?;
        let mut episode = esrp_core::Episode::new(compiled, *config)?;
        for &code in &journaled.actions {
            if episode.is_over() {
                break;
            }
            let action = esrp_core::Action::from_code(i64::from(code))
                .map_err(|e| ServiceError::Internal(format!("the attempts journal of {scene}: {e}")))?;
            episode.step(action)?;
        }
        let summary = super::entry::summary_of(episode.compiled().scene());
        let started = humantime::parse_rfc3339(started_at).unwrap_or_else(|_| SystemTime::now());
        let mut run = RunLog {
            actions: journaled.actions.iter().copied().take(episode.steps() as usize).collect(),
            started,
            clock: Instant::now(),
            counted: true,
            recorded: true,
            keep: false,
            finished: true,
        };
        let paper_only = super::access::split_is_paper_only(summary.split, &episodes.config);
        // A counted attempt is never privileged (the challenge refuses privileged episodes to
        // every token but an admin's, whose attempts are not counted).
        let played = Played { episode: &episode, summary: &summary, agent, token, paper_only, privileged: false };
        let finished_at = rfc3339(SystemTime::now());
        let record = record_of(episodes, &played, &mut run, Some("restart"), finished_at.clone());
        recorder.write_now(&record).map_err(internal)?;
        episodes.attempts.ended(token, scene, &finished_at);
        recovered += 1;
    }
    Ok(recovered)
}

/// Queues `records` for their files; each [`Written`] completes once its record is on disk.
pub(super) fn write(episodes: &Episodes, records: Vec<EpisodeRecord>) -> Vec<Written> {
    match &episodes.recorder {
        Some(recorder) => records
            .iter()
            .map(|r| {
                episodes.metrics.count_record(r.token.as_deref().unwrap_or("anonymous"));
                recorder.write(r)
            })
            .collect(),
        None => Vec::new(),
    }
}

/// Ends the runs of episodes the server closed (`closed_by` says why) and waits until their
/// records are on disk.
pub(super) async fn close_removed(episodes: &Episodes, removed: Vec<Removed<EpisodeEntry>>, closed_by: &str) {
    let mut records = Vec::new();
    for (_, entry, _) in removed {
        let mut entry = entry.lock().await;
        records.extend(finish(episodes, &mut entry, Some(closed_by)));
    }
    for written in write(episodes, records) {
        written.wait().await;
    }
}

/// Reading the records back (the web viewer's replay by scene).
impl Episodes {
    /// The server's records `caller` may read, of scene `scene` if given: its own token's file,
    /// every file for an admin. Fails where the server keeps no records (`--records`).
    pub async fn stored_records(
        &self,
        caller: &Caller,
        scene: Option<String>,
    ) -> Result<Vec<crate::records::StoredRecord>, ServiceError> {
        let token = (!caller.is_admin()).then(|| caller.name.to_string());
        self.read_stored(token, scene).await
    }

    /// Record `index` of token `token`'s file, if `caller` may read it (its own; any for an admin).
    pub async fn stored_record(
        &self,
        caller: &Caller,
        token: &str,
        index: usize,
    ) -> Result<EpisodeRecord, ServiceError> {
        if !caller.is_admin() && *caller.name != *token {
            return Err(ServiceError::Denied(format!(
                "{} may read only its own records, not token {}'s",
                caller.describe(),
                crate::quote::quoted(token)
            )));
        }
        // Only the named token's file is read.
        let found = self.read_stored(Some(token.to_owned()), None).await?;
        found
            .into_iter()
            .find(|r| r.token == token && r.index == index)
            .map(|r| r.record)
            .ok_or_else(|| ServiceError::UnknownRecord { token: token.to_owned(), index })
    }

    /// The records of `token`'s file (every file's with `None`), of scene `scene` if given, read
    /// on a blocking thread.
    async fn read_stored(
        &self,
        token: Option<String>,
        scene: Option<String>,
    ) -> Result<Vec<crate::records::StoredRecord>, ServiceError> {
        let dir = self.records_dir()?;
        tokio::task::spawn_blocking(move || crate::records::stored_records(&dir, token.as_deref(), scene.as_deref()))
            .await
            .map_err(|e| ServiceError::Internal(format!("reading the records stopped: {e}")))?
            .map_err(|e| ServiceError::Internal(e.to_string()))
    }

    fn records_dir(&self) -> Result<std::path::PathBuf, ServiceError> {
        self.recorder.as_ref().map(|r| r.dir().to_path_buf()).ok_or(ServiceError::NoRecords)
    }
}
