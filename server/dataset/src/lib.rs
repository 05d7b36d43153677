//! **esrp-dataset**: ESRP-Bench — procedural scene pairs that reproduce the structure and
//! statistics of the paper's benchmark, the backward construction of initial layouts with the
//! esrp-core simulator, expert trajectories, dataset files and statistics, and an importer for
//! users who have 3D-FRONT.
//!
//! # Module map
//!
//! - [`catalogue`]: low-poly furniture models built from parts, with real sizes.
//! - [`layout`]: room plans and furnishing rules per room type; the choice of movable pieces.
//! - [`backward`]: the rule-based agent that moves objects away from their targets, the expert
//!   trajectory and the replay check.
//! - [`benchmark`]: `esrp-bench-v2` (the default) and `esrp-bench-v1`, 5,495 scenes defined by a
//!   seed, any one generated alone.
//! - [`start`]: esrp-bench-v2's start pose away from the objects, drawn among the poses the
//!   generator can reach after its last release, and the check of that rule.
//! - [`front`]: the 3D-FRONT importer: houses and 3D-FUTURE models to scene pairs.
//! - [`cache`]: a built-in benchmark's generated scenes kept on disk, once per machine.
//! - [`pack`]: a built-in benchmark's generated scenes in one file, each compressed on its own (the server ships them).
//! - [`files`]: the on-disk format (`manifest.json` and `scenes/*.json`), written atomically.
//! - [`stats`]: dataset statistics as JSON and PNG plots.
//! - [`dice`]: the portable seeded random source.
//!
//! # Invariants
//!
//! - **Same seed, same bytes.** Generation uses ChaCha streams keyed by `(seed, index,
//!   attempt)` and makes no decision on platform-dependent math, so the same seed gives
//!   byte-identical files on every machine, and a scene generated alone is identical to the same
//!   scene in a full run.
//! - **Only replayed scenes ship.** Every scene is validated by esrp-core and its expert
//!   trajectory replayed to success before it is returned or written.
//! - **One simulator.** Backward construction steps the same `esrp_core::Episode` as the server.

#![warn(missing_docs)]

pub mod backward;
pub mod benchmark;
pub mod cache;
pub mod catalogue;
pub mod dice;
pub mod files;
pub mod front;
pub mod layout;
pub mod pack;
pub mod start;
pub mod stats;

pub use backward::{
    Construction, ConstructionParams, Rejection, construct, construct_run, horizon_for, validate_by_replay,
};
pub use benchmark::{
    BENCH_SCENES, BENCH_V1, BENCH_V2, BenchVersion, Benchmark, DEFAULT_SEED, Generated, GenerationFailed,
    UnknownBenchmark, split_for_id,
};
pub use start::{StartReport, StartRule, StartViolation, check_start};
