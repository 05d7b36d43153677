//! The served scenes: the built-in benchmark (generated lazily by index) or a dataset folder
//! (read lazily), each compiled once and kept in a bounded cache with its uploaded geometry.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::Path;
use std::sync::{Arc, Mutex};

use esrp_core::{CompiledScene, Difficulty, Scene, Split};
use esrp_dataset::files::Dataset;
use esrp_dataset::{BenchVersion, Benchmark};

use crate::error::ServiceError;
use crate::types::SceneInfo;

enum Source {
    BuiltIn(Benchmark),
    Folder(Dataset),
}

/// Compiled scenes by index, with their insertion order for eviction.
type Cache = (HashMap<usize, Arc<CompiledScene>>, VecDeque<usize>);

/// How many compiled scenes stay cached.
const CACHE_CAPACITY: usize = 2048;

/// The served dataset.
pub struct SceneStore {
    source: Source,
    infos: Vec<SceneInfo>,
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
        Self::new(Source::BuiltIn(bench), infos, name, format!("built-in {version} (seed {seed})"))
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
        Ok(Self::new(Source::Folder(dataset), infos, name, dir.display().to_string()))
    }

    fn new(source: Source, infos: Vec<SceneInfo>, name: String, description: String) -> Self {
        let index_by_id = infos.iter().enumerate().map(|(i, s)| (s.id.clone(), i)).collect();
        Self { source, infos, index_by_id, cache: Mutex::new((HashMap::new(), VecDeque::new())), name, description }
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
        match &self.source {
            Source::BuiltIn(bench) => {
                bench.generate(index).map(|g| g.scene).map_err(|e| ServiceError::Internal(e.to_string()))
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
