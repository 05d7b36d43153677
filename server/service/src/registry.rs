//! The episode registry: a plain map from unguessable id to entry, each entry behind its own
//! lock, with a limit on their number, the stream that owns an entry, and reapers for idle and
//! for unclaimed entries. What an entry holds is the episode layer's business
//! (`episodes::entry`): the registry knows it only as `E`.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::error::ServiceError;
use crate::types::EpisodeId;

/// A shared, individually locked entry.
pub type Locked<E> = Arc<tokio::sync::Mutex<E>>;

/// A live episode in the registry.
struct Slot<E> {
    /// The stream that created it, if any (it closes with that stream).
    stream: Option<u64>,
    /// When it was inserted (its create answer leaves right after).
    created: Instant,
    /// Whether a call has named it since (or a stream owns it): its client has its id. An
    /// unclaimed episode is closed by [`Registry::reap_unclaimed`].
    claimed: bool,
    episode: Locked<E>,
}

/// Live episodes.
pub struct Registry<E> {
    // A std mutex: held only for map operations, never across an await.
    episodes: Mutex<HashMap<EpisodeId, Slot<E>>>,
    max_episodes: usize,
}

impl<E> Registry<E> {
    /// An empty registry holding at most `max_episodes`.
    pub fn new(max_episodes: usize) -> Self {
        Self { episodes: Mutex::new(HashMap::new()), max_episodes }
    }

    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<EpisodeId, Slot<E>>> {
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
    /// one (then it is claimed: the stream holds it); unclaimed otherwise.
    pub fn insert(&self, entry: E, stream: Option<u64>) -> Result<EpisodeId, ServiceError> {
        let mut map = self.map();
        if map.len() >= self.max_episodes {
            return Err(ServiceError::TooManyEpisodes { max: self.max_episodes });
        }
        let id = EpisodeId::random();
        let slot = Slot {
            stream,
            created: Instant::now(),
            claimed: stream.is_some(),
            episode: Arc::new(tokio::sync::Mutex::new(entry)),
        };
        map.insert(id.clone(), slot);
        Ok(id)
    }

    /// The episode `id`, which this claims: every call that names an episode gets it here.
    pub fn get(&self, id: &EpisodeId) -> Result<Locked<E>, ServiceError> {
        let mut map = self.map();
        let slot = map.get_mut(id).ok_or_else(|| ServiceError::UnknownEpisode(id.clone()))?;
        slot.claimed = true;
        Ok(slot.episode.clone())
    }

    /// Claims the episode `id` for its creator (a dm_env_rpc world holds it), if it is live.
    pub fn claim(&self, id: &EpisodeId) {
        if let Some(slot) = self.map().get_mut(id) {
            slot.claimed = true;
        }
    }

    /// Removes the episode `id`.
    pub fn remove(&self, id: &EpisodeId) -> Result<Locked<E>, ServiceError> {
        self.map().remove(id).map(|slot| slot.episode).ok_or_else(|| ServiceError::UnknownEpisode(id.clone()))
    }

    /// Removes every episode created on stream `stream`; returns how many.
    pub fn remove_stream(&self, stream: u64) -> usize {
        let mut map = self.map();
        let before = map.len();
        map.retain(|_, slot| slot.stream != Some(stream));
        before - map.len()
    }

    /// Removes the episodes not owned by a stream whose entry `idle` says is idle; returns how
    /// many. An episode that is locked right now is in use, hence not idle; episodes of an open
    /// stream live as long as the stream.
    pub fn reap(&self, idle: impl Fn(&E) -> bool) -> usize {
        let mut map = self.map();
        let before = map.len();
        map.retain(|_, slot| slot.stream.is_some() || slot.episode.try_lock().map(|e| !idle(&e)).unwrap_or(true));
        before - map.len()
    }

    /// Removes the episodes that no call has named within `timeout` of their creation (their
    /// client never learnt their id: a create abandoned after its answer left); returns how
    /// many.
    pub fn reap_unclaimed(&self, timeout: Duration) -> usize {
        let mut map = self.map();
        let before = map.len();
        map.retain(|_, slot| slot.claimed || slot.created.elapsed() <= timeout);
        before - map.len()
    }
}
