//! The episode registry: live episodes by unguessable id, each behind its own lock, with a
//! limit on their number and a reaper for idle ones.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use esrp_core::Episode;
use esrp_render::{SceneHandle, TopDownFrame};

use crate::episodes::{EpisodeId, SensorConfig};
use crate::error::ServiceError;
use crate::scenes::SceneInfo;

/// One live episode and what the service keeps beside it.
pub struct EpisodeEntry {
    /// The simulator state.
    pub episode: Episode,
    /// The scene's geometry on the renderer.
    pub scene: Arc<SceneHandle>,
    /// The scene's summary.
    pub summary: SceneInfo,
    /// Optional sensors.
    pub sensors: SensorConfig,
    /// Whether GetPrivilegedState is allowed.
    pub privileged: bool,
    /// The goal image (RGB at the sensors' resolution), rendered once.
    pub goal: Bytes,
    /// Its pixel ↔ floor mapping.
    pub frame: TopDownFrame,
    /// Last time a call used it.
    pub last_used: Instant,
    /// The planner's last answer (PlanActions), reused while the episode follows it.
    pub plan: Option<crate::episodes::planning::CachedPlan>,
    /// The last observation's images, answered again by steps that change nothing they show.
    pub frames: crate::render::FrameCache,
}

/// A shared, individually locked episode.
pub type SharedEpisode = Arc<tokio::sync::Mutex<EpisodeEntry>>;

/// Live episodes.
pub struct Registry {
    // A std mutex: held only for map operations, never across an await.
    // Each episode with the stream that created it (closed with that stream).
    episodes: Mutex<HashMap<EpisodeId, (Option<u64>, SharedEpisode)>>,
    max_episodes: usize,
}

impl Registry {
    /// An empty registry holding at most `max_episodes`.
    pub fn new(max_episodes: usize) -> Self {
        Self { episodes: Mutex::new(HashMap::new()), max_episodes }
    }

    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<EpisodeId, (Option<u64>, SharedEpisode)>> {
        // A panic while holding this lock cannot leave the map inconsistent (every operation is
        // a single insert or remove), so a poisoned lock is still safe to use.
        self.episodes.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// Number of live episodes.
    pub fn len(&self) -> usize {
        self.map().len()
    }

    /// Whether no episode is live.
    pub fn is_empty(&self) -> bool {
        self.map().is_empty()
    }

    /// The limit.
    pub fn max_episodes(&self) -> usize {
        self.max_episodes
    }

    /// Adds an episode under a fresh random 128-bit id, owned by `stream` if it was created on
    /// one.
    pub fn insert(&self, entry: EpisodeEntry, stream: Option<u64>) -> Result<EpisodeId, ServiceError> {
        let mut map = self.map();
        if map.len() >= self.max_episodes {
            return Err(ServiceError::TooManyEpisodes { max: self.max_episodes });
        }
        let id = EpisodeId::random();
        map.insert(id.clone(), (stream, Arc::new(tokio::sync::Mutex::new(entry))));
        Ok(id)
    }

    /// The episode `id`.
    pub fn get(&self, id: &EpisodeId) -> Result<SharedEpisode, ServiceError> {
        self.map().get(id).map(|(_, e)| e.clone()).ok_or_else(|| ServiceError::UnknownEpisode(id.clone()))
    }

    /// Removes the episode `id`.
    pub fn remove(&self, id: &EpisodeId) -> Result<SharedEpisode, ServiceError> {
        self.map().remove(id).map(|(_, e)| e).ok_or_else(|| ServiceError::UnknownEpisode(id.clone()))
    }

    /// Removes every episode created on stream `stream`; returns how many.
    pub fn remove_stream(&self, stream: u64) -> usize {
        let mut map = self.map();
        let before = map.len();
        map.retain(|_, (owner, _)| *owner != Some(stream));
        before - map.len()
    }

    /// Removes episodes idle for longer than `idle`; returns how many.
    pub fn reap(&self, idle: Duration) -> usize {
        let mut map = self.map();
        let before = map.len();
        // An episode that is locked right now is in use, hence not idle.
        // Episodes of an open stream live as long as the stream.
        map.retain(|_, (stream, e)| {
            stream.is_some() || e.try_lock().map(|e| e.last_used.elapsed() <= idle).unwrap_or(true)
        });
        before - map.len()
    }
}
