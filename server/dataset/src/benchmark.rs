//! The built-in benchmarks `esrp-bench-v1` and `esrp-bench-v2`: 5,495 scene pairs defined by a
//! seed. Each scene is generated alone from its index, so the server can build any scene lazily
//! and it is identical to the same scene in a full generation.
//!
//! A scene's room type and object count come from fixed, shuffled lists with the benchmark's
//! exact counts (see [`ROOM_TYPES`] and [`OBJECT_COUNT_MIX`]); its geometry comes from a ChaCha
//! stream keyed by `(seed, index, attempt)`. An attempt that is rejected (by layout, planner or
//! replay) is retried with the next attempt number; the reasons are reported.
//!
//! The two versions share everything but the agent's start (SPEC §7): the same rooms, objects,
//! target and initial layouts, and the same train/test split of each index. In esrp-bench-v1 the
//! agent starts where the generator released its last object, within reach of it; in
//! esrp-bench-v2 the generator then drives away to a start pose drawn by [`crate::start`], and the
//! expert trajectory begins with the drive back. esrp-bench-v1 stays unchanged, byte for byte,
//! for results published on it; esrp-bench-v2 is the default.

use std::collections::BTreeMap;
use std::fmt;
use std::str::FromStr;

use esrp_core::{Scene, Split};

use crate::backward::{ConstructionParams, Rejection, construct, construct_run};
use crate::dice::Dice;
use crate::layout::{LayoutFailure, ROOM_TYPES, target_layout};
use crate::start::{StartReport, StartRule, start_away};

/// The name of esrp-bench-v1: the agent starts at the generator's last release.
pub const BENCH_V1: &str = "esrp-bench-v1";
/// The name of esrp-bench-v2: the agent starts away from the objects (SPEC §7).
pub const BENCH_V2: &str = "esrp-bench-v2";

/// A version of the built-in benchmark. The default is the newest, [`BenchVersion::V2`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum BenchVersion {
    /// `esrp-bench-v1`: the agent starts at the generator's last release pose, within reach of
    /// the object it put down; every expert trajectory begins with `fetch`.
    V1,
    /// `esrp-bench-v2`: the same scenes with the agent started away from every object.
    #[default]
    V2,
}

/// A benchmark name that is not one of [`BenchVersion::NAMES`].
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown benchmark {0:?}: use esrp-bench-v2 (the default) or esrp-bench-v1")]
pub struct UnknownBenchmark(pub String);

impl BenchVersion {
    /// Every version, oldest first.
    pub const ALL: [BenchVersion; 2] = [BenchVersion::V1, BenchVersion::V2];
    /// Their names, in the order of [`BenchVersion::ALL`].
    pub const NAMES: [&'static str; 2] = [BENCH_V1, BENCH_V2];

    /// The benchmark's name, e.g. `esrp-bench-v2`.
    pub const fn name(self) -> &'static str {
        match self {
            BenchVersion::V1 => BENCH_V1,
            BenchVersion::V2 => BENCH_V2,
        }
    }

    /// The version whose scenes (of any seed) have ids like `id`, e.g. `esrp-bench-v1/00042` or
    /// `esrp-bench-v2-s7/00003`.
    pub fn of_scene_id(id: &str) -> Option<Self> {
        let (prefix, _) = id.split_once('/')?;
        Self::ALL
            .into_iter()
            .find(|v| prefix == v.name() || prefix.strip_prefix(v.name()).and_then(|r| r.strip_prefix("-s")).is_some())
    }
}

impl fmt::Display for BenchVersion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for BenchVersion {
    type Err = UnknownBenchmark;
    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Self::ALL.into_iter().find(|v| v.name() == name).ok_or_else(|| UnknownBenchmark(name.to_owned()))
    }
}

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
    /// How the start pose was drawn (esrp-bench-v2; `None` for esrp-bench-v1).
    pub start: Option<StartReport>,
}

/// The benchmark of one version and seed.
#[derive(Clone, Debug)]
pub struct Benchmark {
    version: BenchVersion,
    seed: u64,
    room_types: Vec<&'static str>,
    object_counts: Vec<u8>,
    params: ConstructionParams,
    start_rule: StartRule,
}

/// FNV-1a, 64 bits: a fixed, portable hash for splitting by id.
fn fnv1a(text: &str) -> u64 {
    text.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

/// The split of a scene id: `test` for one id in ten (by a fixed hash), `train` otherwise.
pub fn split_for_id(id: &str) -> Split {
    if fnv1a(id).is_multiple_of(10) { Split::Test } else { Split::Train }
}

/// The id of scene `index` of `version` and `seed`.
fn id_of(version: BenchVersion, seed: u64, index: usize) -> String {
    if seed == DEFAULT_SEED {
        format!("{}/{index:05}", version.name())
    } else {
        format!("{}-s{seed}/{index:05}", version.name())
    }
}

impl Benchmark {
    /// The benchmark `version` generated from `seed` ([`DEFAULT_SEED`] is the published one).
    pub fn new(version: BenchVersion, seed: u64) -> Self {
        let mut room_types: Vec<&'static str> =
            ROOM_TYPES.iter().flat_map(|&(name, n)| std::iter::repeat_n(name, n)).collect();
        let mut object_counts: Vec<u8> =
            OBJECT_COUNT_MIX.iter().flat_map(|&(objects, n)| std::iter::repeat_n(objects as u8, n)).collect();
        Dice::new(seed, u64::MAX, 0).shuffle(&mut room_types);
        Dice::new(seed, u64::MAX, 1).shuffle(&mut object_counts);
        Self {
            version,
            seed,
            room_types,
            object_counts,
            params: ConstructionParams::default(),
            start_rule: StartRule::default(),
        }
    }

    /// The version.
    pub fn version(&self) -> BenchVersion {
        self.version
    }

    /// The seed.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The benchmark's name: `esrp-bench-v2` for the default seed, `esrp-bench-v2-s7` for
    /// seed 7 (likewise for v1).
    pub fn name(&self) -> String {
        let id = self.scene_id(0);
        id[..id.len() - 6].to_owned()
    }

    /// The rule its start poses follow (esrp-bench-v2).
    pub fn start_rule(&self) -> &StartRule {
        &self.start_rule
    }

    /// Number of scenes.
    pub fn len(&self) -> usize {
        self.room_types.len()
    }

    /// Always false: the benchmark has scenes.
    pub fn is_empty(&self) -> bool {
        self.room_types.is_empty()
    }

    /// The id of scene `index`: `esrp-bench-v2/00042` for the default seed,
    /// `esrp-bench-v2-s7/00042` for seed 7 (likewise for v1).
    pub fn scene_id(&self, index: usize) -> String {
        id_of(self.version, self.seed, index)
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

    /// The split of scene `index`: every version keeps esrp-bench-v1's, which hashes the v1 id
    /// ([`split_for_id`]).
    pub fn split(&self, index: usize) -> Split {
        split_for_id(&id_of(BenchVersion::V1, self.seed, index))
    }

    /// Generates scene `index` (`index < len()`), retrying rejected attempts.
    pub fn generate(&self, index: usize) -> Result<Generated, GenerationFailed> {
        let mut rejections = BTreeMap::new();
        let mut last = Rejection::TooFewMovable;
        for attempt in 0..MAX_ATTEMPTS {
            let mut dice = Dice::new(self.seed, index as u64, attempt);
            // After every 8 rejected attempts, make the room a little roomier.
            let ease = (attempt / 8) as f64;
            let result = target_layout(&mut dice, self.room_type(index), self.object_count(index), ease)
                .map_err(|LayoutFailure::TooFewMovable| Rejection::TooFewMovable)
                .and_then(|mut target| {
                    target.id = self.scene_id(index);
                    target.split = self.split(index);
                    match self.version {
                        BenchVersion::V1 => construct(target, &mut dice, &self.params).map(|scene| (scene, None)),
                        // The same construction as v1 (same dice, same rejections), then the
                        // drive away on the rest of the attempt's stream.
                        BenchVersion::V2 => construct_run(target, &mut dice, &self.params)
                            .and_then(|run| start_away(run, &mut dice, &self.start_rule))
                            .map(|(scene, report)| (scene, Some(report))),
                    }
                });
            match result {
                Ok((scene, start)) => {
                    return Ok(Generated { scene, rejections, start });
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
        let bench = Benchmark::new(BenchVersion::V1, DEFAULT_SEED);
        assert_eq!(bench.len(), BENCH_SCENES);
        assert_eq!(bench.name(), "esrp-bench-v1");
        assert_eq!(bench.scene_id(42), "esrp-bench-v1/00042");
        assert_eq!(bench.index_of("esrp-bench-v1/00042"), Some(42));
        assert_eq!(bench.index_of("esrp-bench-v1/99999"), None);
        assert_eq!(bench.index_of("esrp-bench-v2/00042"), None);
        let seven = Benchmark::new(BenchVersion::V1, 7);
        assert_eq!(seven.scene_id(3), "esrp-bench-v1-s7/00003");
        assert_eq!(seven.index_of("esrp-bench-v1-s7/00003"), Some(3));
        assert_eq!(seven.name(), "esrp-bench-v1-s7");
        let tests = (0..BENCH_SCENES).filter(|&i| split_for_id(&bench.scene_id(i)) == Split::Test).count();
        assert!((450..650).contains(&tests), "{tests} test scenes");
        // v2: its own ids, v1's split of every index.
        let v2 = Benchmark::new(BenchVersion::default(), DEFAULT_SEED);
        assert_eq!(v2.version(), BenchVersion::V2);
        assert_eq!(v2.scene_id(42), "esrp-bench-v2/00042");
        assert_eq!(v2.index_of("esrp-bench-v2/00042"), Some(42));
        assert_eq!(Benchmark::new(BenchVersion::V2, 7).scene_id(3), "esrp-bench-v2-s7/00003");
        for i in 0..BENCH_SCENES {
            assert_eq!(v2.split(i), split_for_id(&bench.scene_id(i)), "scene {i}");
            assert_eq!(bench.split(i), v2.split(i));
        }
    }

    #[test]
    fn versions_by_name_and_scene_id() {
        assert_eq!("esrp-bench-v1".parse::<BenchVersion>(), Ok(BenchVersion::V1));
        assert_eq!("esrp-bench-v2".parse::<BenchVersion>(), Ok(BenchVersion::V2));
        assert!("esrp-bench-v3".parse::<BenchVersion>().unwrap_err().to_string().contains("esrp-bench-v1"));
        assert_eq!(BenchVersion::of_scene_id("esrp-bench-v1/00042"), Some(BenchVersion::V1));
        assert_eq!(BenchVersion::of_scene_id("esrp-bench-v2-s7/00003"), Some(BenchVersion::V2));
        assert_eq!(BenchVersion::of_scene_id("esrp-bench-v2x/00003"), None);
        assert_eq!(BenchVersion::of_scene_id("3dfront/abc"), None);
        assert_eq!(BenchVersion::default().name(), BENCH_V2);
    }
}
