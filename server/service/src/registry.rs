//! The episode registry: a plain map from unguessable id to entry, each entry behind its own
//! lock, with a limit on their number (the server's, and each token's `max_episodes`), the
//! token that created each entry (only it, or an admin, may name it), the stream that owns an
//! entry, and reapers for idle and for unclaimed entries. What an entry holds is the episode
//! layer's business (`episodes::entry`): the registry knows it only as `E`.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::error::ServiceError;
use crate::types::{Caller, EpisodeId};

/// A shared, individually locked entry.
pub type Locked<E> = Arc<tokio::sync::Mutex<E>>;

/// A live episode in the registry.
struct Slot<E> {
    /// The stream that created it, if any (it closes with that stream).
    stream: Option<u64>,
    /// The token that created it.
    owner: Arc<Caller>,
    /// When it was inserted (its create answer leaves right after).
    created: Instant,
    /// Whether a call has named it since (or a stream owns it): its client has its id. An
    /// unclaimed episode is closed by [`Registry::reap_unclaimed`].
    claimed: bool,
    episode: Locked<E>,
}

/// The map and each token's count of live episodes, changed together.
struct Map<E> {
    slots: HashMap<EpisodeId, Slot<E>>,
    by_owner: HashMap<Arc<str>, usize>,
}

impl<E> Map<E> {
    fn len(&self) -> usize {
        self.slots.len()
    }

    /// Removes the slots `keep` refuses; returns them.
    fn remove_where(&mut self, mut keep: impl FnMut(&Slot<E>) -> bool) -> Vec<(EpisodeId, Slot<E>)> {
        let gone: Vec<EpisodeId> = self.slots.iter().filter(|(_, s)| !keep(s)).map(|(id, _)| id.clone()).collect();
        gone.into_iter().filter_map(|id| self.remove(&id).map(|slot| (id, slot))).collect()
    }

    fn remove(&mut self, id: &EpisodeId) -> Option<Slot<E>> {
        let slot = self.slots.remove(id)?;
        if let Some(count) = self.by_owner.get_mut(&slot.owner.name) {
            *count -= 1;
            if *count == 0 {
                self.by_owner.remove(&slot.owner.name);
            }
        }
        Some(slot)
    }
}

/// An episode taken out of the registry: its id, its entry and the token that created it.
pub type Removed<E> = (EpisodeId, Locked<E>, Arc<Caller>);

/// Live episodes.
pub struct Registry<E> {
    // A std mutex: held only for map operations, never across an await.
    episodes: Mutex<Map<E>>,
    max_episodes: usize,
}

impl<E> Registry<E> {
    /// An empty registry holding at most `max_episodes`.
    pub fn new(max_episodes: usize) -> Self {
        Self { episodes: Mutex::new(Map { slots: HashMap::new(), by_owner: HashMap::new() }), max_episodes }
    }

    fn map(&self) -> std::sync::MutexGuard<'_, Map<E>> {
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
        self.map().len() == 0
    }

    /// The number of live episodes `caller`'s token created.
    pub fn owned_by(&self, caller: &Caller) -> usize {
        self.map().by_owner.get(&caller.name).copied().unwrap_or(0)
    }

    /// Refuses a create when the server or `caller` holds its maximum of live episodes.
    pub fn check_room(&self, caller: &Caller) -> Result<(), ServiceError> {
        Self::room_in(&self.map(), self.max_episodes, caller)
    }

    fn room_in(map: &Map<E>, max_episodes: usize, caller: &Caller) -> Result<(), ServiceError> {
        if map.len() >= max_episodes {
            return Err(ServiceError::TooManyEpisodes { max: max_episodes });
        }
        if let Some(limit) = caller.max_episodes
            && map.by_owner.get(&caller.name).copied().unwrap_or(0) >= limit
        {
            return Err(ServiceError::Quota {
                caller: caller.describe(),
                what: "live episodes",
                quota: "max_episodes",
                limit,
            });
        }
        Ok(())
    }

    /// The limit.
    pub fn max_episodes(&self) -> usize {
        self.max_episodes
    }

    /// Adds an episode of `owner` under a fresh random 128-bit id, owned by `stream` if it was
    /// created on one (then it is claimed: the stream holds it); unclaimed otherwise. The
    /// limits are checked under the same lock as the insertion: racing creates cannot pass them.
    pub fn insert(&self, entry: E, stream: Option<u64>, owner: &Arc<Caller>) -> Result<EpisodeId, ServiceError> {
        let mut map = self.map();
        Self::room_in(&map, self.max_episodes, owner)?;
        let id = EpisodeId::random();
        let slot = Slot {
            stream,
            owner: owner.clone(),
            created: Instant::now(),
            claimed: stream.is_some(),
            episode: Arc::new(tokio::sync::Mutex::new(entry)),
        };
        map.slots.insert(id.clone(), slot);
        *map.by_owner.entry(owner.name.clone()).or_default() += 1;
        Ok(id)
    }

    /// The episode `id` for `caller` (its creator, or an admin), which this claims: every call
    /// that names an episode gets it here.
    pub fn get(&self, id: &EpisodeId, caller: &Caller) -> Result<Locked<E>, ServiceError> {
        let mut map = self.map();
        let slot = map.slots.get_mut(id).ok_or_else(|| ServiceError::UnknownEpisode(id.clone()))?;
        if !caller.is_admin() && slot.owner.name != caller.name {
            return Err(ServiceError::NotYours { episode: id.clone(), caller: caller.describe() });
        }
        slot.claimed = true;
        Ok(slot.episode.clone())
    }

    /// The episode `id` for `caller` (its creator, or an admin), without claiming it: a viewer
    /// looking at an episode is not its client.
    pub fn peek(&self, id: &EpisodeId, caller: &Caller) -> Result<Locked<E>, ServiceError> {
        let map = self.map();
        let slot = map.slots.get(id).ok_or_else(|| ServiceError::UnknownEpisode(id.clone()))?;
        if !caller.is_admin() && slot.owner.name != caller.name {
            return Err(ServiceError::NotYours { episode: id.clone(), caller: caller.describe() });
        }
        Ok(slot.episode.clone())
    }

    /// The episode `id` for a watcher `caller` (its creator, or an admin): as [`Registry::peek`],
    /// but its creator watching it claims it, as a call naming it would: a watcher sees its views
    /// (its first ego view and goal image), so its client has seen the scene.
    pub fn watch(&self, id: &EpisodeId, caller: &Caller) -> Result<Locked<E>, ServiceError> {
        let mut map = self.map();
        let slot = map.slots.get_mut(id).ok_or_else(|| ServiceError::UnknownEpisode(id.clone()))?;
        if slot.owner.name == caller.name {
            slot.claimed = true;
        } else if !caller.is_admin() {
            return Err(ServiceError::NotYours { episode: id.clone(), caller: caller.describe() });
        }
        Ok(slot.episode.clone())
    }

    /// The episode `id`, whoever created it, without claiming it (the server's own use).
    pub fn peek_any(&self, id: &EpisodeId) -> Option<Locked<E>> {
        self.map().slots.get(id).map(|slot| slot.episode.clone())
    }

    /// The live episodes `caller` may name (its own; all for an admin).
    pub fn visible_to(&self, caller: &Caller) -> Vec<(EpisodeId, Locked<E>)> {
        self.map()
            .slots
            .iter()
            .filter(|(_, slot)| caller.is_admin() || slot.owner.name == caller.name)
            .map(|(id, slot)| (id.clone(), slot.episode.clone()))
            .collect()
    }

    /// Whether the episode `id` is live.
    pub fn contains(&self, id: &EpisodeId) -> bool {
        self.map().slots.contains_key(id)
    }

    /// Claims the episode `id` for its creator (a dm_env_rpc world holds it), if it is live.
    pub fn claim(&self, id: &EpisodeId) {
        if let Some(slot) = self.map().slots.get_mut(id) {
            slot.claimed = true;
        }
    }

    /// Removes the episode `id` for `caller` (its creator, or an admin).
    pub fn remove(&self, id: &EpisodeId, caller: &Caller) -> Result<Locked<E>, ServiceError> {
        let mut map = self.map();
        let slot = map.slots.get(id).ok_or_else(|| ServiceError::UnknownEpisode(id.clone()))?;
        if !caller.is_admin() && slot.owner.name != caller.name {
            return Err(ServiceError::NotYours { episode: id.clone(), caller: caller.describe() });
        }
        map.remove(id).map(|slot| slot.episode).ok_or_else(|| ServiceError::UnknownEpisode(id.clone()))
    }

    /// Removes the episode `id` if no call has named it yet (its client cannot have used it);
    /// returns it. Checked and removed under the lock every call that names an episode takes
    /// ([`Registry::get`] claims it there), so an episode is either used or removed, never both.
    pub fn take_unclaimed(&self, id: &EpisodeId) -> Option<Locked<E>> {
        let mut map = self.map();
        if map.slots.get(id)?.claimed {
            return None;
        }
        map.remove(id).map(|slot| slot.episode)
    }

    /// Removes every episode created on stream `stream`; returns them.
    pub fn remove_stream(&self, stream: u64) -> Vec<Removed<E>> {
        Self::removed(self.map().remove_where(|slot| slot.stream != Some(stream)))
    }

    /// Removes every episode (at shutdown); returns them.
    pub fn remove_all(&self) -> Vec<Removed<E>> {
        Self::removed(self.map().remove_where(|_| false))
    }

    fn removed(slots: Vec<(EpisodeId, Slot<E>)>) -> Vec<Removed<E>> {
        slots.into_iter().map(|(id, slot)| (id, slot.episode, slot.owner)).collect()
    }

    /// Removes the episodes not owned by a stream whose entry `idle` says is idle; returns
    /// them. An episode that is locked right now is in use, hence not idle; episodes of an
    /// open stream live as long as the stream.
    pub fn reap(&self, idle: impl Fn(&E) -> bool) -> Vec<Removed<E>> {
        Self::removed(
            self.map().remove_where(|slot| {
                slot.stream.is_some() || slot.episode.try_lock().map(|e| !idle(&e)).unwrap_or(true)
            }),
        )
    }

    /// Removes the episodes that no call has named within `timeout` of their creation (their
    /// client never learnt their id: a create abandoned after its answer left); returns them.
    pub fn reap_unclaimed(&self, timeout: Duration) -> Vec<Removed<E>> {
        Self::removed(self.map().remove_where(|slot| slot.claimed || slot.created.elapsed() <= timeout))
    }
}
