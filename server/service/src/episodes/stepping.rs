//! Stepping: Step and StepBatch (all or nothing) and the steps of a stream wave (each on its
//! own). Either way the steps are taken in order on their locked episodes and every view they
//! need goes to the render thread as one job; the renderer takes any number of views.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::Instant;

use esrp_core::Action;

use esrp_results::EpisodeRecord;

use super::entry::{EpisodeGuard, SharedEpisode};
use super::observe::Prepared;
use super::state::Episodes;
use super::{lifecycle, recording};
use crate::error::ServiceError;
use crate::metrics::{Metrics, Stages};
use crate::records::Written;
use crate::render::RenderTicket;
use crate::types::{Caller, EpisodeId, ResetCall, ResetResult, StepCall, StepResult};

/// Batches of at most this many steps are stepped on the async runtime itself.
const INLINE_STEPS: usize = 4;

/// A step queued for taking: where it is in its call (for messages), its episode (an index
/// into the call's locked episodes), its action and whether its answer carries the goal image.
struct QueuedStep {
    at: String,
    episode: usize,
    action: Action,
    include_goal: bool,
}

/// A step taken: its answer, its observation still without images, an upper bound of the
/// answer's encoded size, and the record of the run it ended, if the server records it.
struct TakenStep {
    result: StepResult,
    observation: Prepared,
    bytes: usize,
    record: Option<EpisodeRecord>,
    /// Its episode (an index into the call's locked episodes).
    episode: usize,
}

/// The one limit on a StepBatch's length (`--max-batch`): the adapters check it before they
/// read a batch's steps, and [`step_many`] again for any other caller.
pub(super) fn check_batch_len(episodes: &Episodes, steps: usize) -> Result<(), ServiceError> {
    let max = episodes.config.max_batch;
    if steps > max {
        return Err(ServiceError::BatchTooLarge { steps, max });
    }
    Ok(())
}

/// Takes the `queue` of steps in order on the locked `guards` (`ids` names them): each step
/// sees the state the previous one left, and one that cannot be taken answers its error
/// without moving. Its time counts in the `take` stage.
fn take_queued(
    episodes: &Episodes,
    guards: &mut [EpisodeGuard],
    ids: &[EpisodeId],
    queue: Vec<Result<QueuedStep, ServiceError>>,
) -> Vec<Result<TakenStep, ServiceError>> {
    let taking = Instant::now();
    let max_message_bytes = episodes.config.max_message_bytes;
    let taken = queue
        .into_iter()
        .map(|step| {
            let step = step?;
            let g = &mut guards[step.episode];
            let bytes = g.ensure_steppable(&step.at, &ids[step.episode], step.include_goal, max_message_bytes)?;
            let outcome = g.episode.step(step.action)?;
            if let Some(run) = g.run.as_mut() {
                run.actions.push(step.action.code());
                if run.counted
                    && let Some(recorder) = &episodes.recorder
                {
                    recorder.journal_step(&g.owner.name, &g.summary.id, step.action.code());
                }
            }
            let g = &mut **g;
            g.trail.step(&g.episode, step.action.code(), outcome.accepted);
            if let Some(watch) = &g.watch {
                watch.send_replace(u64::from(outcome.step_index));
            }
            let observation = g.observer.prepare(&g.episode, step.include_goal);
            let ended = outcome.terminated || outcome.truncated;
            let record = if ended { recording::finish(episodes, g, None) } else { None };
            let mut result = StepResult {
                observation: Default::default(),
                outcome,
                collided_with_name: outcome.collided_with.map(|o| g.episode.compiled().obstacle_name(o)),
                metrics: ended.then(|| g.episode.metrics()),
            };
            if g.paper_only {
                result.keep_paper_observation();
            }
            Ok(TakenStep { result, observation, bytes, record, episode: step.episode })
        })
        .collect();
    Stages::add(&episodes.metrics.stages.take, taking.elapsed());
    taken
}

/// Steps taken, their views being rendered and the records of the runs they ended being
/// written.
pub struct Stepped {
    taken: Vec<Result<TakenStep, ServiceError>>,
    render: RenderTicket,
    written: Vec<Written>,
    started: Instant,
}

impl Stepped {
    /// `n` steps that all failed with an internal `error` (nothing moved).
    fn failed(n: usize, error: &ServiceError) -> Self {
        // Not "internal error: internal error: …".
        let message = match error {
            ServiceError::Internal(m) => m.clone(),
            other => other.to_string(),
        };
        Stepped {
            taken: (0..n).map(|_| Err(ServiceError::Internal(message.clone()))).collect(),
            render: RenderTicket::nothing(),
            written: Vec::new(),
            started: Instant::now(),
        }
    }

    /// An upper bound of the encoded size of the answers.
    pub fn answer_bytes(&self) -> usize {
        self.taken.iter().map(|t| t.as_ref().map_or(256, |t| t.bytes)).sum()
    }

    /// Waits for the rendering (and for the records of the runs the steps ended to be on
    /// disk) and answers every step, in order.
    pub async fn finish(self, metrics: &Metrics) -> Vec<Result<StepResult, ServiceError>> {
        let Stepped { taken, render, written, started } = self;
        let rendered = render.wait().await;
        for w in written {
            w.wait().await;
        }
        metrics.observe_steps(taken.iter().filter(|t| t.is_ok()).count(), started.elapsed());
        match rendered {
            Ok(outputs) => {
                let answering = Instant::now();
                let mut outputs = outputs.into_iter();
                let answers = taken
                    .into_iter()
                    .map(|t| {
                        let TakenStep { mut result, observation, .. } = t?;
                        result.observation = observation.finish(&mut outputs);
                        Ok(result)
                    })
                    .collect();
                Stages::add(&metrics.stages.answer, answering.elapsed());
                answers
            }
            // The steps were taken: they answer the failure (and must not be retaken).
            Err(e) => {
                let message = match e {
                    ServiceError::Render(m) => m,
                    other => other.to_string(),
                };
                taken.into_iter().map(|t| t.and_then(|_| Err(ServiceError::Render(message.clone())))).collect()
            }
        }
    }
}

/// Step and StepBatch, all or nothing (see `Episodes::step_many`); `batch` names each step
/// `steps[i]` in messages, as a StepBatch's request does (however few it holds), else `step`.
pub(super) async fn step_many(
    episodes: &Arc<Episodes>,
    caller: &Caller,
    steps: Vec<StepCall>,
    batch: bool,
) -> Result<Vec<StepResult>, ServiceError> {
    let stepped = start_many(episodes, caller, steps, 0, batch).await?;
    stepped.finish(&episodes.metrics).await.into_iter().collect()
}

/// An upper bound of the encoded size of a reset's answer beside its observation (the scene's
/// summary), bytes.
const RESET_SUMMARY_BYTES: usize = 256;

/// A StepBatch with resets (see `Episodes::step_batch`).
pub(super) async fn step_batch(
    episodes: &Arc<Episodes>,
    caller: &Arc<Caller>,
    steps: Vec<StepCall>,
    resets: Vec<ResetCall>,
) -> Result<(Vec<StepResult>, Vec<ResetResult>), ServiceError> {
    if resets.is_empty() {
        return Ok((step_many(episodes, caller, steps, true).await?, Vec::new()));
    }
    check_batch_len(episodes, steps.len() + resets.len())?;
    // Each episode once in the whole batch; the reset ones known and the caller's.
    let stepped: HashSet<&EpisodeId> = steps.iter().map(|s| &s.episode).collect();
    let mut seen = HashSet::new();
    let mut reset_bytes = 0;
    for (i, r) in resets.iter().enumerate() {
        if stepped.contains(&r.episode) || !seen.insert(&r.episode) {
            return Err(ServiceError::DuplicateStep { at: format!("resets[{i}]"), episode: r.episode.clone() });
        }
        let entry = episodes.locked(caller, &r.episode).await?;
        reset_bytes += entry.observer.sensors.answer_bytes(true) + RESET_SUMMARY_BYTES;
    }
    let max_message_bytes = episodes.config.max_message_bytes;
    if steps.is_empty() && reset_bytes > max_message_bytes {
        let steps = resets.len();
        return Err(ServiceError::BatchAnswerTooLarge { steps, bytes: reset_bytes, max: max_message_bytes });
    }
    // The new scenes are read before anything moves: a bad one fails the call.
    let mut targets = Vec::with_capacity(resets.len());
    for r in resets {
        targets.push((r.episode, episodes.resolve_new_scene(r.scene).await?));
    }
    // The steps, validated whole with the resets' answers counted in the message's size; their
    // views render while the resets are taken.
    let taken =
        if steps.is_empty() { None } else { Some(start_many(episodes, caller, steps, reset_bytes, true).await?) };
    let mut reset = Vec::with_capacity(targets.len());
    let mut failed = None;
    for (episode, scene) in targets {
        match lifecycle::reset_to(episodes, caller, &episode, scene).await {
            Ok(r) => reset.push(r),
            Err(e) => {
                failed = Some(e);
                break;
            }
        }
    }
    // The steps were taken: their rendering and records finish whatever became of the resets.
    let results = match taken {
        Some(taken) => taken.finish(&episodes.metrics).await.into_iter().collect::<Result<Vec<_>, _>>()?,
        None => Vec::new(),
    };
    match failed {
        Some(e) => Err(e),
        None => Ok((results, reset)),
    }
}

/// Validates `steps` whole (with `more_bytes` of other answers in the same message), takes
/// them and hands their views to the render thread (see `Episodes::step_many`); messages name a
/// step `steps[i]` in a `batch`, else `step`.
async fn start_many(
    episodes: &Arc<Episodes>,
    caller: &Caller,
    steps: Vec<StepCall>,
    more_bytes: usize,
    batch: bool,
) -> Result<Stepped, ServiceError> {
    check_batch_len(episodes, steps.len())?;
    let at = |i: usize| if batch { format!("steps[{i}]") } else { "step".to_owned() };
    let mut seen = HashSet::new();
    let mut locked = Vec::with_capacity(steps.len());
    let mut queue = Vec::with_capacity(steps.len());
    for (i, s) in steps.iter().enumerate() {
        if !seen.insert(&s.episode) {
            return Err(ServiceError::DuplicateStep { at: at(i), episode: s.episode.clone() });
        }
        locked.push((s.episode.clone(), episodes.registry.get(&s.episode, caller)?));
        queue.push(Ok(QueuedStep { at: at(i), episode: i, action: s.action, include_goal: s.include_goal }));
    }
    let max_message_bytes = episodes.config.max_message_bytes;
    let check = |guards: &[EpisodeGuard], queue: &[Result<QueuedStep, ServiceError>]| {
        if let Some(i) = queue.iter().position(Result::is_err) {
            return Err(ServiceError::UnknownEpisode(steps[i].episode.clone()));
        }
        let mut bytes = more_bytes;
        for (i, g) in guards.iter().enumerate() {
            g.ensure_running(&at(i), &steps[i].episode)?;
            bytes += g.observer.sensors.answer_bytes(steps[i].include_goal);
        }
        // Refuse, before anything moves, a batch whose answer could not be sent.
        if bytes > max_message_bytes {
            return Err(ServiceError::BatchAnswerTooLarge { steps: steps.len(), bytes, max: max_message_bytes });
        }
        Ok(())
    };
    take_steps(episodes, locked, queue, check).await
}

/// The steps of a stream wave, each answered on its own (see `Episodes::step_each`).
pub(super) async fn step_each(episodes: &Arc<Episodes>, caller: &Caller, steps: Vec<StepCall>) -> Stepped {
    let count = steps.len();
    let mut locked: Vec<(EpisodeId, SharedEpisode)> = Vec::new();
    let mut index: HashMap<EpisodeId, usize> = HashMap::new();
    let mut queue = Vec::with_capacity(count);
    for s in steps {
        let episode = match index.get(&s.episode) {
            Some(&e) => Ok(e),
            None => episodes.registry.get(&s.episode, caller).map(|shared| {
                locked.push((s.episode.clone(), shared));
                index.insert(s.episode.clone(), locked.len() - 1);
                locked.len() - 1
            }),
        };
        queue.push(episode.map(|episode| QueuedStep {
            at: "step".to_owned(),
            episode,
            action: s.action,
            include_goal: s.include_goal,
        }));
    }
    match take_steps(episodes, locked, queue, |_, _| Ok(())).await {
        Ok(stepped) => stepped,
        Err(e) => Stepped::failed(count, &e),
    }
}

/// Locks `locked` (in id order, so that concurrent calls cannot deadlock), turns the steps of
/// any closed while this call waited into NOT_FOUND, runs `check` on the locked episodes and
/// the queue (its error fails the whole call before anything moves), takes the queued steps
/// in order (a few inline, more on a blocking thread), hands all their views to the render
/// thread as one job and unlocks the episodes: the views are snapshots, so the episodes may
/// take their next steps while these render.
async fn take_steps(
    episodes: &Arc<Episodes>,
    locked: Vec<(EpisodeId, SharedEpisode)>,
    mut queue: Vec<Result<QueuedStep, ServiceError>>,
    check: impl FnOnce(&[EpisodeGuard], &[Result<QueuedStep, ServiceError>]) -> Result<(), ServiceError>,
) -> Result<Stepped, ServiceError> {
    let started = Instant::now();
    let mut order: Vec<usize> = (0..locked.len()).collect();
    order.sort_by(|&a, &b| locked[a].0.cmp(&locked[b].0));
    let mut slots: Vec<Option<EpisodeGuard>> = (0..locked.len()).map(|_| None).collect();
    for &e in &order {
        slots[e] = Some(locked[e].1.clone().lock_owned().await);
    }
    let mut guards: Vec<EpisodeGuard> = slots.into_iter().flatten().collect();
    Stages::add(&episodes.metrics.stages.lock, started.elapsed());
    // Closed (or reaped) while this call waited for its lock.
    for (e, (id, _)) in locked.iter().enumerate() {
        if !episodes.registry.contains(id) {
            for step in queue.iter_mut().filter(|s| s.as_ref().is_ok_and(|s| s.episode == e)) {
                *step = Err(ServiceError::UnknownEpisode(id.clone()));
            }
        }
    }
    check(&guards, &queue)?;
    let ids: Vec<EpisodeId> = locked.into_iter().map(|(id, _)| id).collect();
    // A step costs microseconds (a rejected turn, the worst case, well under 0.1 ms): a few
    // run inline, which spares a thread hand-off per step; more go to a blocking thread so
    // that the runtime never stalls.
    let taken = if queue.len() <= INLINE_STEPS {
        take_queued(episodes, &mut guards, &ids, queue)
    } else {
        let this = episodes.clone();
        let (guards_back, taken) = tokio::task::spawn_blocking(move || {
            let taken = take_queued(&this, &mut guards, &ids, queue);
            (guards, taken)
        })
        .await
        .map_err(|e| ServiceError::Internal(e.to_string()))?;
        guards = guards_back;
        taken
    };
    let mut views = Vec::new();
    let mut reused = 0;
    let mut records = Vec::new();
    let mut taken = taken;
    for t in taken.iter_mut().filter_map(|t| t.as_mut().ok()) {
        views.extend(t.observation.views().iter().cloned());
        reused += t.observation.reused();
        records.extend(t.record.take());
    }
    episodes.metrics.reused_views.inc_by(reused as u64);
    let render = episodes.render.submit(views);
    let written = recording::write(episodes, records);
    let now = Instant::now();
    for g in &mut guards {
        g.last_used = now;
    }
    // Steps by token: one label lookup per token of the call, not per step.
    let mut by_token: Vec<(&Arc<str>, usize)> = Vec::new();
    for t in taken.iter().flatten() {
        let owner = &guards[t.episode].owner.name;
        match by_token.iter_mut().find(|(name, _)| *name == owner) {
            Some((_, n)) => *n += 1,
            None => by_token.push((owner, 1)),
        }
    }
    for (token, n) in by_token {
        episodes.metrics.count_steps_by(token, n);
    }
    Ok(Stepped { taken, render, written, started })
}
