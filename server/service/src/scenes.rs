//! The served scenes: the built-in benchmark (generated lazily by index, kept in the machine's
//! scene cache on disk, and generated ahead in the background) or a dataset folder (read
//! lazily), and with `--challenge-seed` the hidden challenge and minival splits (generated
//! lazily from the secret seed by the built-in benchmark's rules, never kept on disk); each scene
//! compiled once and kept in a bounded cache.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::Path;
use std::sync::{Arc, Mutex};

use esrp_core::{CompiledScene, Difficulty, Scene, Split};
use esrp_dataset::cache::{Lookup, SceneCache};
use esrp_dataset::files::Dataset;
use esrp_dataset::pack::ScenePack;
use esrp_dataset::{BenchVersion, Benchmark};
use sha2::{Digest, Sha256};

use crate::error::ServiceError;
use crate::types::SceneInfo;

enum Source {
    BuiltIn(Benchmark),
    Folder(Dataset),
    /// The hidden splits: scene `i` of the store's hidden part is scene `i` of `bench`, a
    /// benchmark of the secret seed, renamed and put in the split its info names.
    Hidden(Benchmark),
}

/// Where a served scene comes from: the dataset (built-in or folder) or the hidden splits, and
/// its index there.
#[derive(Clone, Copy)]
enum Origin {
    Dataset(usize),
    Hidden(usize),
}

/// The hidden splits' scenes: `--challenge-scenes` then `--minival-scenes` scenes of a
/// benchmark of the secret seed, of `version`'s rules. Its scenes are a shuffled draw of the
/// whole benchmark's mix of room types and object counts, which is the test split's.
pub struct HiddenSplits {
    /// The secret.
    pub secret: String,
    /// The benchmark version whose rules generate them.
    pub version: BenchVersion,
    /// Challenge scenes.
    pub challenge: usize,
    /// Minival scenes.
    pub minival: usize,
}

impl HiddenSplits {
    /// The benchmark seed the secret stands for.
    pub fn seed(&self) -> u64 {
        let digest: [u8; 32] = Sha256::digest(format!("esrp-challenge-seed/v1\0{}", self.secret)).into();
        u64::from_le_bytes(digest[..8].try_into().unwrap_or_default())
    }
}

/// Compiled scenes by index, with their insertion order for eviction.
type Cache = (HashMap<usize, Arc<CompiledScene>>, VecDeque<usize>);

/// How many compiled scenes stay cached.
const CACHE_CAPACITY: usize = 2048;

/// The default benchmark's scenes, built into the server (`esrp-dataset pack`; a test checks
/// them against the generator): read in tens of microseconds where generating one takes tens of
/// milliseconds, so the built-in benchmark is as fast as a generated folder from its first use.
static BUILT_IN_PACK: &[u8] = include_bytes!("../packs/esrp-bench-v2.pack");

/// The built-in pack, if it holds every scene of `bench` as this generator makes them (the
/// default benchmark at the published seed).
pub fn built_in_pack(bench: &Benchmark) -> Option<ScenePack<'static>> {
    match ScenePack::parse(BUILT_IN_PACK) {
        Ok(pack) if pack.serves(bench) => Some(pack),
        Ok(_) => None,
        Err(e) => {
            tracing::warn!("the built-in scene pack cannot be read ({e}): scenes are generated");
            None
        }
    }
}

/// The served dataset.
pub struct SceneStore {
    source: Source,
    /// The built-in benchmark's scenes shipped in the binary, where they are the served ones.
    pack: Option<ScenePack<'static>>,
    /// The built-in benchmark's scenes on disk (`--scene-cache`).
    disk: Option<SceneCache>,
    hidden: Option<Source>,
    origins: Vec<Origin>,
    infos: Vec<SceneInfo>,
    hash: String,
    index_by_id: HashMap<String, usize>,
    cache: Mutex<Cache>,
    name: String,
    description: String,
}

impl SceneStore {
    /// The built-in benchmark `version` of `seed`.
    pub fn built_in(version: BenchVersion, seed: u64) -> Self {
        let bench = Benchmark::new(version, seed);
        let infos: Vec<SceneInfo> = (0..bench.len())
            .map(|i| {
                let id = bench.scene_id(i);
                let count = bench.object_count(i);
                SceneInfo {
                    split: bench.split(i),
                    id,
                    room_type: bench.room_type(i).to_owned(),
                    difficulty: Difficulty::for_object_count(count).unwrap_or(Difficulty::Hard),
                    movable_objects: count,
                    horizon: 0,
                    expert_length: 0,
                }
            })
            .collect();
        let name = bench.name();
        let hash = format!("{name}\0{seed}");
        let pack = built_in_pack(&bench);
        let mut store =
            Self::new(Source::BuiltIn(bench), infos, name, format!("built-in {version} (seed {seed})"), hash);
        store.pack = pack;
        store
    }

    /// A dataset folder.
    pub fn folder(dir: &Path) -> Result<Self, esrp_dataset::files::FilesError> {
        let dataset = Dataset::open(dir)?;
        let infos = dataset
            .manifest()
            .scenes
            .iter()
            .map(|e| SceneInfo {
                id: e.id.clone(),
                room_type: e.room_type.clone(),
                difficulty: e.difficulty,
                split: e.split,
                movable_objects: e.movable_objects,
                horizon: 0,
                expert_length: e.expert_length,
            })
            .collect();
        let name = dataset.manifest().name.clone();
        // The manifest lists the scenes (ids, files, summaries), not their contents: a scene file
        // changed under the same manifest keeps the hash (scenes load lazily, and hashing every
        // file would read the whole dataset at start). A replay against another copy of the
        // dataset (`esrp verify`) tells such a change apart.
        let manifest = serde_json::to_string(dataset.manifest()).unwrap_or_default();
        let hash = format!("{name}\0{manifest}");
        Ok(Self::new(Source::Folder(dataset), infos, name, dir.display().to_string(), hash))
    }

    fn new(source: Source, infos: Vec<SceneInfo>, name: String, description: String, hash: String) -> Self {
        let index_by_id = infos.iter().enumerate().map(|(i, s)| (s.id.clone(), i)).collect();
        let origins = (0..infos.len()).map(Origin::Dataset).collect();
        Self {
            source,
            pack: None,
            disk: None,
            hidden: None,
            origins,
            infos,
            hash,
            index_by_id,
            cache: Mutex::new((HashMap::new(), VecDeque::new())),
            name,
            description,
        }
    }

    /// Keeps the built-in benchmark's scenes in the scene cache under `root` (nothing for a
    /// dataset folder, which is on disk already).
    /// On an error the store keeps no scene on disk.
    pub fn keep_on_disk(&mut self, root: &Path) -> Result<(), esrp_dataset::files::FilesError> {
        if let Source::BuiltIn(bench) = &self.source {
            self.disk = Some(SceneCache::open(root, bench)?);
        }
        Ok(())
    }

    /// The scene cache's folder, if scenes are kept on disk.
    pub fn disk_cache(&self) -> Option<&Path> {
        self.disk.as_ref().map(SceneCache::dir)
    }

    /// Starts generating the built-in benchmark's scenes that the scene cache lacks, test split
    /// first, on a thread at the lowest CPU priority (Linux's `SCHED_IDLE`: it runs only on
    /// cores nothing else wants). Requests never wait for it: a scene asked for first is
    /// generated by its request. `None` without a scene cache, and where the built-in pack holds
    /// every scene already.
    pub fn generate_ahead(&self) -> Option<std::thread::JoinHandle<()>> {
        if self.pack.is_some() {
            return None; // every scene is in the pack already
        }
        let (Source::BuiltIn(bench), Some(cache)) = (&self.source, &self.disk) else { return None };
        let (bench, cache) = (bench.clone(), cache.clone());
        // Each server starts at its own place in each split, so that servers sharing a cold
        // cache mostly generate different scenes.
        let mut order = Vec::with_capacity(self.infos.len());
        for split in [Split::Test, Split::Train] {
            let mut indices = self.indices_of_split(split);
            if !indices.is_empty() {
                let at = std::process::id() as usize % indices.len();
                indices.rotate_left(at);
            }
            order.extend(indices);
        }
        std::thread::Builder::new()
            .name("esrp-generate".into())
            .spawn(move || {
                lowest_priority();
                let started = std::time::Instant::now();
                let mut made = 0usize;
                for index in order {
                    if cache.contains(index) {
                        continue;
                    }
                    match bench.generate(index) {
                        Ok(generated) => {
                            if let Err(e) = cache.put(index, &generated.scene) {
                                tracing::warn!("generating ahead stopped: cannot write the scene cache: {e}");
                                return;
                            }
                            made += 1;
                        }
                        Err(e) => tracing::warn!(index, "generating ahead: {e}"),
                    }
                }
                tracing::info!(
                    made,
                    seconds = started.elapsed().as_secs_f64(),
                    dir = %cache.dir().display(),
                    "every scene of the built-in benchmark is in the scene cache"
                );
            })
            .ok()
    }

    /// Adds the hidden splits: `challenge/00000`… then `minival/00000`…, listed by id, room
    /// type, difficulty and object count only.
    pub fn with_hidden(mut self, hidden: &HiddenSplits) -> Result<Self, String> {
        let bench = Benchmark::new(hidden.version, hidden.seed());
        let splits = std::iter::repeat_n(Split::Challenge, hidden.challenge)
            .chain(std::iter::repeat_n(Split::Minival, hidden.minival));
        for (i, split) in splits.enumerate().take(bench.len()) {
            let number = if split == Split::Challenge { i } else { i - hidden.challenge };
            let count = bench.object_count(i);
            let info = SceneInfo {
                id: format!("{}/{number:05}", split.as_str()),
                room_type: bench.room_type(i).to_owned(),
                difficulty: Difficulty::for_object_count(count).unwrap_or(Difficulty::Hard),
                split,
                movable_objects: count,
                horizon: 0,
                expert_length: 0,
            };
            if self.index_by_id.insert(info.id.clone(), self.infos.len()).is_some() {
                return Err(format!(
                    "the served dataset has a scene {:?}, an id of the hidden splits: rename it or drop --challenge-seed",
                    info.id
                ));
            }
            self.infos.push(info);
            self.origins.push(Origin::Hidden(i));
        }
        self.hash = format!("{}\0{}\0{}\0{}", self.hash, hidden.secret, hidden.challenge, hidden.minival);
        self.hidden = Some(Source::Hidden(bench));
        Ok(self)
    }

    /// A hash of what is served (the dataset's name and seed or manifest, and the hidden
    /// splits' secret and sizes): 16 hex digits, the same on every server serving the same
    /// scenes. Records carry it.
    pub fn dataset_hash(&self) -> String {
        let digest: [u8; 32] = Sha256::digest(format!("esrp-dataset-hash/v1\0{}", self.hash)).into();
        digest[..8].iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Whether the hidden splits are served.
    pub fn has_hidden(&self) -> bool {
        self.hidden.is_some()
    }

    /// Dataset name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Where the scenes come from.
    pub fn description(&self) -> &str {
        &self.description
    }

    /// Every scene's summary, in dataset order.
    pub fn infos(&self) -> &[SceneInfo] {
        &self.infos
    }

    /// The index of a scene id.
    pub fn index_of(&self, id: &str) -> Result<usize, ServiceError> {
        self.index_by_id.get(id).copied().ok_or_else(|| ServiceError::UnknownScene(id.to_owned()))
    }

    /// Counts by split, difficulty and room type.
    pub fn counts(&self) -> [BTreeMap<String, u32>; 3] {
        let mut counts: [BTreeMap<String, u32>; 3] = Default::default();
        for s in &self.infos {
            *counts[0].entry(s.split.as_str().to_owned()).or_default() += 1;
            *counts[1].entry(s.difficulty.as_str().to_owned()).or_default() += 1;
            *counts[2].entry(s.room_type.clone()).or_default() += 1;
        }
        counts
    }

    /// The scene at `index`, compiled; built (generated or read) on first use. Blocking: call it
    /// from a blocking thread.
    pub fn compiled(&self, index: usize) -> Result<Arc<CompiledScene>, ServiceError> {
        if let Some(scene) = self.cache.lock().ok().and_then(|c| c.0.get(&index).cloned()) {
            return Ok(scene);
        }
        let scene = self.build(index)?;
        let compiled = Arc::new(CompiledScene::new(scene, esrp_core::Rules::default())?);
        if let Ok(mut cache) = self.cache.lock() {
            let (map, order) = &mut *cache;
            if map.insert(index, compiled.clone()).is_none() {
                order.push_back(index);
            }
            while order.len() > CACHE_CAPACITY {
                if let Some(old) = order.pop_front() {
                    map.remove(&old);
                }
            }
        }
        Ok(compiled)
    }

    fn build(&self, index: usize) -> Result<Scene, ServiceError> {
        let info = self.infos.get(index).ok_or_else(|| ServiceError::UnknownScene(format!("#{index}")))?;
        let (source, at) = match self.origins[index] {
            Origin::Dataset(at) => (&self.source, at),
            Origin::Hidden(at) => {
                (self.hidden.as_ref().ok_or_else(|| ServiceError::Internal("no hidden splits".into()))?, at)
            }
        };
        match source {
            Source::BuiltIn(bench) => {
                if let Some(pack) = &self.pack {
                    match pack.scene(at) {
                        Ok(scene) => return Ok(scene),
                        Err(e) => tracing::warn!("built-in scene pack: {e}; generating the scene"),
                    }
                }
                if let Some(cache) = &self.disk {
                    match cache.get(at) {
                        Lookup::Hit(scene) => return Ok(*scene),
                        Lookup::Miss => {}
                        Lookup::Corrupt(why) => tracing::warn!("scene cache: {why}; generating the scene again"),
                    }
                }
                let scene = bench.generate(at).map(|g| g.scene).map_err(|e| ServiceError::Internal(e.to_string()))?;
                if let Some(cache) = &self.disk
                    && let Err(e) = cache.put(at, &scene)
                {
                    tracing::warn!("scene cache: cannot keep {}: {e}", info.id);
                }
                Ok(scene)
            }
            Source::Hidden(bench) => {
                let mut scene = bench.generate(at).map_err(|e| ServiceError::Internal(e.to_string()))?.scene;
                scene.id = info.id.clone();
                scene.split = info.split;
                Ok(scene)
            }
            Source::Folder(dataset) => dataset
                .scene_by_id(&info.id)
                .ok_or_else(|| ServiceError::UnknownScene(info.id.clone()))?
                .map_err(|e| ServiceError::Internal(e.to_string())),
        }
    }

    /// The indices of the scenes of `split`, in order.
    pub fn indices_of_split(&self, split: Split) -> Vec<usize> {
        (0..self.infos.len()).filter(|&i| self.infos[i].split == split).collect()
    }
}

/// Puts the calling thread on Linux's `SCHED_IDLE` policy: it runs only when a core has nothing
/// else to run. Elsewhere, or if refused, the thread keeps its priority.
#[allow(unsafe_code)] // Audited: one libc call on plain data, see the SAFETY note.
fn lowest_priority() {
    #[cfg(target_os = "linux")]
    {
        let param = libc::sched_param { sched_priority: 0 };
        // SAFETY: sched_setscheduler reads `param` and changes only the calling thread's policy
        // (pid 0); it has no other effect on memory.
        let refused = unsafe { libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) } != 0;
        if refused {
            tracing::debug!("generating ahead at normal priority: SCHED_IDLE was refused");
        }
    }
}

#[cfg(test)]
mod tests {
    use esrp_dataset::pack::scene_json;

    use super::*;

    /// The pack built into the server holds the generator's scenes, byte for byte: a sample spread
    /// over the whole benchmark here (`esrp-dataset pack --check --out
    /// server/service/packs/esrp-bench-v2.pack` compares all of them, in a few minutes).
    #[test]
    fn the_built_in_pack_is_the_generators_output() {
        let bench = Benchmark::new(BenchVersion::V2, esrp_dataset::DEFAULT_SEED);
        let pack = built_in_pack(&bench).expect("the built-in pack serves esrp-bench-v2 at the published seed");
        let step = bench.len() / 60;
        for index in (0..bench.len()).step_by(step).chain([bench.len() - 1]) {
            let generated = scene_json(&bench.generate(index).expect("the scene generates").scene);
            assert!(
                pack.json(index).expect("the pack holds it") == generated,
                "scene {index} differs from the generator's"
            );
        }
        // Another seed or version is not the pack's: those scenes are generated.
        assert!(built_in_pack(&Benchmark::new(BenchVersion::V2, 7)).is_none());
        assert!(built_in_pack(&Benchmark::new(BenchVersion::V1, esrp_dataset::DEFAULT_SEED)).is_none());
        // The store serves the pack's scenes.
        let store = SceneStore::built_in(BenchVersion::V2, esrp_dataset::DEFAULT_SEED);
        assert!(store.pack.is_some());
        assert!(store.generate_ahead().is_none(), "nothing to generate ahead");
        assert_eq!(scene_json(&store.build(5).unwrap()), pack.json(5).unwrap());
    }
}
