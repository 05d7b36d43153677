//! The built-in benchmark `esrp-bench-v1`: 5,495 scene pairs defined by a seed. Each scene is
//! generated alone from its index, so the server can build any scene lazily and it is identical
//! to the same scene in a full generation.
//!
//! A scene's room type and object count come from fixed, shuffled lists with the benchmark's
//! exact counts (see [`ROOM_TYPES`] and [`OBJECT_COUNT_MIX`]); its geometry comes from a ChaCha
//! stream keyed by `(seed, index, attempt)`. An attempt that is rejected (by layout, planner or
//! replay) is retried with the next attempt number; the reasons are reported.

use std::collections::BTreeMap;

use esrp_core::{Scene, Split};

use crate::backward::{ConstructionParams, Rejection, construct};
use crate::dice::Dice;
use crate::layout::{LayoutFailure, ROOM_TYPES, target_layout};

/// The benchmark's name.
pub const BENCH_NAME: &str = "esrp-bench-v1";
/// Number of scene pairs in the benchmark.
pub const BENCH_SCENES: usize = 5495;
/// The seed of the published benchmark.
pub const DEFAULT_SEED: u64 = 0;
/// Scenes per number of movable objects: Easy 3,780 (1 object), Medium 1,480 (2–3), Hard 235
/// (4–6); 8,205 objects in all, as near the paper's 8,213 as whole scenes allow.
pub const OBJECT_COUNT_MIX: [(usize, usize); 6] = [(1, 3780), (2, 1100), (3, 380), (4, 130), (5, 65), (6, 40)];
/// Attempts per scene before generation of that index is declared failed.
pub const MAX_ATTEMPTS: u64 = 64;

/// A scene that could not be generated in [`MAX_ATTEMPTS`] attempts.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("scene {index} could not be generated in {attempts} attempts (last: {last})")]
pub struct GenerationFailed {
    /// The scene index.
    pub index: usize,
    /// Attempts made.
    pub attempts: u64,
    /// The last rejection.
    pub last: Rejection,
}

/// A generated scene with the rejections met on the way.
#[derive(Clone, Debug)]
pub struct Generated {
    /// The scene.
    pub scene: Scene,
    /// Rejected attempts before it, by reason.
    pub rejections: BTreeMap<&'static str, usize>,
}

/// The benchmark for one seed.
#[derive(Clone, Debug)]
pub struct Benchmark {
    seed: u64,
    room_types: Vec<&'static str>,
    object_counts: Vec<u8>,
    params: ConstructionParams,
}

/// FNV-1a, 64 bits: a fixed, portable hash for splitting by id.
fn fnv1a(text: &str) -> u64 {
    text.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

/// The split of a scene id: `test` for one id in ten (by a fixed hash), `train` otherwise.
pub fn split_for_id(id: &str) -> Split {
    if fnv1a(id).is_multiple_of(10) { Split::Test } else { Split::Train }
}

impl Benchmark {
    /// The benchmark generated from `seed` ([`DEFAULT_SEED`] is `esrp-bench-v1` itself).
    pub fn new(seed: u64) -> Self {
        let mut room_types: Vec<&'static str> =
            ROOM_TYPES.iter().flat_map(|&(name, n)| std::iter::repeat_n(name, n)).collect();
        let mut object_counts: Vec<u8> =
            OBJECT_COUNT_MIX.iter().flat_map(|&(objects, n)| std::iter::repeat_n(objects as u8, n)).collect();
        Dice::new(seed, u64::MAX, 0).shuffle(&mut room_types);
        Dice::new(seed, u64::MAX, 1).shuffle(&mut object_counts);
        Self { seed, room_types, object_counts, params: ConstructionParams::default() }
    }

    /// The seed.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// Number of scenes.
    pub fn len(&self) -> usize {
        self.room_types.len()
    }

    /// Always false: the benchmark has scenes.
    pub fn is_empty(&self) -> bool {
        self.room_types.is_empty()
    }

    /// The id of scene `index`: `esrp-bench-v1/00042` for the default seed,
    /// `esrp-bench-v1-s7/00042` for seed 7.
    pub fn scene_id(&self, index: usize) -> String {
        if self.seed == DEFAULT_SEED {
            format!("{BENCH_NAME}/{index:05}")
        } else {
            format!("{BENCH_NAME}-s{}/{index:05}", self.seed)
        }
    }

    /// The index of a scene id of this benchmark, if it is one.
    pub fn index_of(&self, id: &str) -> Option<usize> {
        let prefix = self.scene_id(0);
        let prefix = &prefix[..prefix.len() - 5];
        let index: usize = id.strip_prefix(prefix)?.parse().ok()?;
        (index < self.len()).then_some(index)
    }

    /// Room type of scene `index`.
    pub fn room_type(&self, index: usize) -> &'static str {
        self.room_types[index]
    }

    /// Number of movable objects of scene `index`.
    pub fn object_count(&self, index: usize) -> usize {
        usize::from(self.object_counts[index])
    }

    /// Generates scene `index` (`index < len()`), retrying rejected attempts.
    pub fn generate(&self, index: usize) -> Result<Generated, GenerationFailed> {
        let mut rejections = BTreeMap::new();
        let mut last = Rejection::TooFewMovable;
        for attempt in 0..MAX_ATTEMPTS {
            let mut dice = Dice::new(self.seed, index as u64, attempt);
            let result = target_layout(&mut dice, self.room_type(index), self.object_count(index))
                .map_err(|LayoutFailure::TooFewMovable| Rejection::TooFewMovable)
                .and_then(|mut target| {
                    target.id = self.scene_id(index);
                    target.split = split_for_id(&target.id);
                    construct(target, &mut dice, &self.params)
                });
            match result {
                Ok(scene) => {
                    return Ok(Generated { scene, rejections });
                }
                Err(rejection) => {
                    *rejections.entry(rejection.reason()).or_insert(0) += 1;
                    last = rejection;
                }
            }
        }
        Err(GenerationFailed { index, attempts: MAX_ATTEMPTS, last })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_and_ids() {
        let total: usize = OBJECT_COUNT_MIX.iter().map(|(_, n)| n).sum();
        assert_eq!(total, BENCH_SCENES);
        let bench = Benchmark::new(DEFAULT_SEED);
        assert_eq!(bench.len(), BENCH_SCENES);
        assert_eq!(bench.scene_id(42), "esrp-bench-v1/00042");
        assert_eq!(bench.index_of("esrp-bench-v1/00042"), Some(42));
        assert_eq!(bench.index_of("esrp-bench-v1/99999"), None);
        assert_eq!(Benchmark::new(7).scene_id(3), "esrp-bench-v1-s7/00003");
        assert_eq!(Benchmark::new(7).index_of("esrp-bench-v1-s7/00003"), Some(3));
        let tests = (0..BENCH_SCENES).filter(|&i| split_for_id(&bench.scene_id(i)) == Split::Test).count();
        assert!((450..650).contains(&tests), "{tests} test scenes");
    }
}
