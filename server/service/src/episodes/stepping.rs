//! Stepping: Step and StepBatch (all or nothing) and the steps of a stream wave (each on its
//! own). Either way the steps are taken in order on their locked episodes and every view they
//! need goes to the render thread as one job; the renderer takes any number of views.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::Instant;

use esrp_core::Action;
use esrp_render::ViewOutput;

use super::{EpisodeGuard, EpisodeId, SensorConfig, Shared, StepCall, StepResult, attach_images, observation};
use crate::error::ServiceError;
use crate::metrics::Metrics;
use crate::registry::SharedEpisode;
use crate::render::{FrameCache, RenderTicket, View};

/// Batches of at most this many steps are stepped on the async runtime itself.
const INLINE_STEPS: usize = 4;

/// A step to take: where it is in its call (for messages), its episode (an index into the
/// call's locked episodes), its action and whether its answer carries the goal image.
struct PlannedStep {
    at: String,
    episode: usize,
    action: Action,
    include_goal: bool,
}

/// A step taken: its answer without images, where they come from, and the sensors that say how
/// they fit in the answer.
struct TakenStep {
    result: StepResult,
    /// An upper bound of the answer's encoded size.
    bytes: usize,
    images: Images,
    sensors: SensorConfig,
}

/// Where a step's images come from.
enum Images {
    /// Views to render (copies go into the render job), and the episode's cache, to keep the
    /// images with these views once they are rendered.
    Render { views: Vec<View>, frames: FrameCache },
    /// The episode's last images: the step changed nothing they show.
    Reused(Vec<ViewOutput>),
}

/// Takes `plan` in order on the locked `guards` (`ids` names them): each step sees the state
/// the previous one left, and one that cannot be taken answers its error without moving.
fn take_planned(
    guards: &mut [EpisodeGuard],
    ids: &[EpisodeId],
    plan: Vec<Result<PlannedStep, ServiceError>>,
    max_message_bytes: usize,
) -> Vec<Result<TakenStep, ServiceError>> {
    plan.into_iter()
        .map(|step| {
            let step = step?;
            let g = &mut guards[step.episode];
            if g.episode.is_over() {
                return Err(ServiceError::EpisodeOver {
                    at: step.at,
                    episode: ids[step.episode].clone(),
                    steps: g.episode.steps(),
                });
            }
            let bytes = g.sensors.answer_bytes(step.include_goal);
            if bytes > max_message_bytes {
                return Err(ServiceError::StepAnswerTooLarge { bytes, max: max_message_bytes });
            }
            let outcome = g.episode.step(step.action)?;
            let views = super::observation_views(g);
            let images = match g.frames.lookup(&views) {
                Some(outputs) => Images::Reused(outputs),
                None => Images::Render { views, frames: g.frames.clone() },
            };
            let ended = outcome.terminated || outcome.truncated;
            let result = StepResult {
                observation: observation(g, step.include_goal),
                outcome,
                collided_with_name: outcome.collided_with.map(|o| g.episode.compiled().obstacle_name(o)),
                metrics: ended.then(|| g.episode.metrics()),
            };
            Ok(TakenStep { result, bytes, images, sensors: g.sensors })
        })
        .collect()
}

/// Steps taken, their views being rendered.
pub struct Stepped {
    taken: Vec<Result<TakenStep, ServiceError>>,
    render: RenderTicket,
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
            started: Instant::now(),
        }
    }

    /// An upper bound of the encoded size of the answers.
    pub fn answer_bytes(&self) -> usize {
        self.taken.iter().map(|t| t.as_ref().map_or(256, |t| t.bytes)).sum()
    }

    /// Waits for the rendering and answers every step, in order.
    pub async fn finish(self, metrics: &Metrics) -> Vec<Result<StepResult, ServiceError>> {
        let Stepped { taken, render, started } = self;
        let rendered = render.wait().await;
        metrics.observe_steps(taken.iter().filter(|t| t.is_ok()).count(), started.elapsed());
        match rendered {
            Ok(outputs) => {
                let mut outputs = outputs.into_iter();
                taken
                    .into_iter()
                    .map(|t| {
                        let mut t = t?;
                        let mine: Vec<ViewOutput> = match t.images {
                            Images::Render { views, frames } => {
                                let mine: Vec<ViewOutput> = outputs.by_ref().take(views.len()).collect();
                                frames.store(views, &mine);
                                mine
                            }
                            Images::Reused(mine) => mine,
                        };
                        attach_images(&mut t.result.observation, &t.sensors, mine);
                        Ok(t.result)
                    })
                    .collect()
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

impl Shared {
    /// Step and StepBatch, all or nothing: validates the whole batch (one step per episode, no
    /// ended episode, an answer that fits in a message) before any episode moves, then steps
    /// every episode and renders every view in one job.
    pub async fn step_many(self: &Arc<Self>, steps: Vec<StepCall>) -> Result<Vec<StepResult>, ServiceError> {
        if steps.len() > self.config.max_batch {
            return Err(ServiceError::BatchTooLarge { steps: steps.len(), max: self.config.max_batch });
        }
        // "steps[3]" in a batch, "step" alone.
        let batch = steps.len() > 1;
        let at = |i: usize| if batch { format!("steps[{i}]") } else { "step".to_owned() };
        let mut seen = HashSet::new();
        let mut episodes = Vec::with_capacity(steps.len());
        let mut plan = Vec::with_capacity(steps.len());
        for (i, s) in steps.iter().enumerate() {
            if !seen.insert(&s.episode) {
                return Err(ServiceError::DuplicateStep { at: at(i), episode: s.episode.clone() });
            }
            episodes.push((s.episode.clone(), self.registry.get(&s.episode)?));
            plan.push(Ok(PlannedStep { at: at(i), episode: i, action: s.action, include_goal: s.include_goal }));
        }
        let max_message_bytes = self.config.max_message_bytes;
        let check = |guards: &[EpisodeGuard], plan: &[Result<PlannedStep, ServiceError>]| {
            if let Some(i) = plan.iter().position(Result::is_err) {
                return Err(ServiceError::UnknownEpisode(steps[i].episode.clone()));
            }
            let mut bytes = 0usize;
            for (i, g) in guards.iter().enumerate() {
                if g.episode.is_over() {
                    return Err(ServiceError::EpisodeOver {
                        at: at(i),
                        episode: steps[i].episode.clone(),
                        steps: g.episode.steps(),
                    });
                }
                bytes += g.sensors.answer_bytes(steps[i].include_goal);
            }
            // Refuse, before anything moves, a batch whose answer could not be sent.
            if bytes > max_message_bytes {
                return Err(ServiceError::BatchAnswerTooLarge { steps: steps.len(), bytes, max: max_message_bytes });
            }
            Ok(())
        };
        let stepped = self.take_steps(episodes, plan, check).await?;
        stepped.finish(&self.metrics).await.into_iter().collect()
    }

    /// Takes the steps of a stream wave, each answered on its own: an episode may be stepped
    /// several times (in order, each step seeing the state the previous one left), a bad step
    /// answers its error without disturbing the others, and every view of the wave is
    /// rendered as one job. Returns once the steps are taken; the answers come from
    /// [`Stepped::finish`]. The caller bounds the number of steps (`--max-batch`).
    pub async fn step_each(self: &Arc<Self>, steps: Vec<StepCall>) -> Stepped {
        let count = steps.len();
        let mut episodes: Vec<(EpisodeId, SharedEpisode)> = Vec::new();
        let mut index: HashMap<EpisodeId, usize> = HashMap::new();
        let mut plan = Vec::with_capacity(count);
        for s in steps {
            let episode = match index.get(&s.episode) {
                Some(&e) => Ok(e),
                None => self.registry.get(&s.episode).map(|shared| {
                    episodes.push((s.episode.clone(), shared));
                    index.insert(s.episode.clone(), episodes.len() - 1);
                    episodes.len() - 1
                }),
            };
            plan.push(episode.map(|episode| PlannedStep {
                at: "step".to_owned(),
                episode,
                action: s.action,
                include_goal: s.include_goal,
            }));
        }
        match self.take_steps(episodes, plan, |_, _| Ok(())).await {
            Ok(stepped) => stepped,
            Err(e) => Stepped::failed(count, &e),
        }
    }

    /// Locks `episodes` (in id order, so that concurrent calls cannot deadlock), turns the
    /// steps of any closed while this call waited into NOT_FOUND, runs `check` on the locked
    /// episodes and the plan (its error fails the whole call before anything moves), takes the
    /// planned steps in order (a few inline, more on a blocking thread), hands all their views
    /// to the render thread as one job and unlocks the episodes: the views are snapshots, so
    /// the episodes may take their next steps while these render.
    async fn take_steps(
        self: &Arc<Self>,
        episodes: Vec<(EpisodeId, SharedEpisode)>,
        mut plan: Vec<Result<PlannedStep, ServiceError>>,
        check: impl FnOnce(&[EpisodeGuard], &[Result<PlannedStep, ServiceError>]) -> Result<(), ServiceError>,
    ) -> Result<Stepped, ServiceError> {
        let started = Instant::now();
        let mut order: Vec<usize> = (0..episodes.len()).collect();
        order.sort_by(|&a, &b| episodes[a].0.cmp(&episodes[b].0));
        let mut slots: Vec<Option<EpisodeGuard>> = (0..episodes.len()).map(|_| None).collect();
        for &e in &order {
            slots[e] = Some(episodes[e].1.clone().lock_owned().await);
        }
        let mut guards: Vec<EpisodeGuard> = slots.into_iter().flatten().collect();
        // Closed (or reaped) while this call waited for its lock.
        for (e, (id, _)) in episodes.iter().enumerate() {
            if self.registry.get(id).is_err() {
                for step in plan.iter_mut().filter(|s| s.as_ref().is_ok_and(|s| s.episode == e)) {
                    *step = Err(ServiceError::UnknownEpisode(id.clone()));
                }
            }
        }
        check(&guards, &plan)?;
        let ids: Vec<EpisodeId> = episodes.into_iter().map(|(id, _)| id).collect();
        let max_message_bytes = self.config.max_message_bytes;
        // A step costs microseconds (a rejected turn, the worst case, well under 0.1 ms): a few
        // run inline, which spares a thread hand-off per step; more go to a blocking thread so
        // that the runtime never stalls.
        let taken = if plan.len() <= INLINE_STEPS {
            take_planned(&mut guards, &ids, plan, max_message_bytes)
        } else {
            let (guards_back, taken) = tokio::task::spawn_blocking(move || {
                let taken = take_planned(&mut guards, &ids, plan, max_message_bytes);
                (guards, taken)
            })
            .await
            .map_err(|e| ServiceError::Internal(e.to_string()))?;
            guards = guards_back;
            taken
        };
        let mut views = Vec::new();
        let mut reused = 0;
        for t in taken.iter().filter_map(|t| t.as_ref().ok()) {
            match &t.images {
                Images::Render { views: mine, .. } => views.extend(mine.iter().cloned()),
                Images::Reused(outputs) => reused += outputs.len(),
            }
        }
        self.metrics.reused_views.inc_by(reused as u64);
        let render = self.render.submit(views);
        let now = Instant::now();
        for g in &mut guards {
            g.last_used = now;
        }
        Ok(Stepped { taken, render, started })
    }
}
