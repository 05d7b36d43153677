//! The episode layer's state, [`Episodes`]: the served scenes, the live episodes, the render
//! thread, the configuration and the metrics, with the helpers every job of the layer uses.
//! Its public methods are listed together in `episodes/mod.rs`.

use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::Instant;

use esrp_core::{CompiledScene, Scene, Split};

use super::entry::{EpisodeEntry, EpisodeGuard};
use crate::config::Config;
use crate::error::ServiceError;
use crate::metrics::Metrics;
use crate::records::{Attempts, Recorder};
use crate::registry::Registry;
use crate::render::RenderScheduler;
use crate::scenes::SceneStore;
use crate::types::{Caller, EpisodeId, SceneChoice, SensorConfig, SensorRequest};

/// The largest image side a client may ask for.
pub const MAX_RESOLUTION: u32 = 512;

/// The live episodes of a server and everything they share; what every handler of every
/// protocol calls (see `episodes/mod.rs` for its methods).
pub struct Episodes {
    /// The served scenes.
    pub store: SceneStore,
    /// Live episodes.
    pub(super) registry: Registry<EpisodeEntry>,
    /// The render thread.
    pub render: RenderScheduler,
    /// The configuration.
    pub config: Config,
    /// The next stream's id.
    pub(super) next_stream: AtomicU64,
    /// One permit per plan allowed to run at once (PlanActions).
    pub(super) planners: Arc<tokio::sync::Semaphore>,
    /// Prometheus metrics.
    pub metrics: Arc<Metrics>,
    /// The records writer (`--records`).
    pub recorder: Option<Recorder>,
    /// The counted attempts at challenge scenes.
    pub(super) attempts: Attempts,
    /// The served dataset's hash, for records.
    pub dataset_hash: String,
    /// Open streams (StepStream, dm_env_rpc connections) by token, for `max_streams`.
    pub(super) streams: std::sync::Mutex<std::collections::HashMap<Arc<str>, usize>>,
}

impl Episodes {
    /// Validates the sensors a client asked for.
    pub(super) fn sensors(&self, request: SensorRequest) -> Result<SensorConfig, ServiceError> {
        let resolution = request.resolution.unwrap_or(esrp_render::DEFAULT_RESOLUTION);
        let max = self.max_resolution();
        if !(16..=max).contains(&resolution) {
            return Err(ServiceError::InvalidResolution { resolution, max });
        }
        Ok(SensorConfig {
            depth: request.depth,
            segmentation: request.segmentation,
            current_top_down: request.current_top_down,
            resolution,
        })
    }

    /// Resolves a scene choice into a compiled scene (on a blocking thread: a scene may be
    /// generated or parsed).
    pub(super) async fn resolve_scene(
        self: &Arc<Self>,
        choice: SceneChoice,
    ) -> Result<Arc<CompiledScene>, ServiceError> {
        let this = self.clone();
        let job = move || -> Result<Arc<CompiledScene>, ServiceError> {
            let index = match choice {
                SceneChoice::SceneJson(json) => {
                    let scene = Scene::from_json(&json)?;
                    super::access::inline_split(scene.split)?;
                    super::access::inline_id(&scene.id, this.store.index_of(&scene.id).is_ok())?;
                    let id = scene.id.clone();
                    let compiled = esrp_core::guarded(|| CompiledScene::new(scene, esrp_core::Rules::default()))
                        .map_err(|message| {
                            ServiceError::InvalidArgument(format!(
                                "scene {}: the collision library cannot build it ({message}): check its sizes and positions",
                                crate::quote::quoted(&id)
                            ))
                        })??;
                    return Ok(Arc::new(compiled));
                }
                SceneChoice::SceneId(id) => this.store.index_of(&id)?,
                SceneChoice::FromSplit { split, seed } => {
                    let split = split.unwrap_or(Split::Test);
                    let candidates = this.store.indices_of_split(split);
                    if candidates.is_empty() {
                        return Err(ServiceError::EmptySplit(split));
                    }
                    candidates[(seed % candidates.len() as u64) as usize]
                }
            };
            this.store.compiled(index)
        };
        tokio::task::spawn_blocking(job).await.map_err(|e| ServiceError::Internal(e.to_string()))?
    }

    /// Resolves a reset's new scene, if it names one (see [`Episodes::resolve_scene`]).
    pub(super) async fn resolve_new_scene(
        self: &Arc<Self>,
        choice: Option<SceneChoice>,
    ) -> Result<Option<Arc<CompiledScene>>, ServiceError> {
        match choice {
            Some(choice) => self.resolve_scene(choice).await.map(Some),
            None => Ok(None),
        }
    }

    /// The episode `id` of `caller`, locked, marked used now.
    pub(super) async fn locked(&self, caller: &Caller, id: &EpisodeId) -> Result<EpisodeGuard, ServiceError> {
        let mut entry = self.registry.get(id, caller)?.lock_owned().await;
        entry.last_used = Instant::now();
        Ok(entry)
    }
}
