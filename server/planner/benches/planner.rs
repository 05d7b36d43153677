//! `cargo bench -p esrp-planner --bench planner`: planning from the start of three fixed test
//! scenes of esrp-bench-v1 (easy, medium, hard) with the default options.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use esrp_core::{CompiledScene, Episode, EpisodeConfig, Rules};
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED};
use esrp_planner::{PlanOptions, plan};

/// Test-split scenes: one of each difficulty.
const SCENES: [(&str, usize); 3] = [("easy_00047", 47), ("medium_00117", 117), ("hard_00168", 168)];

fn episode(index: usize) -> Episode {
    let scene = Benchmark::new(BenchVersion::V1, DEFAULT_SEED).generate(index).expect("the scene generates").scene;
    let compiled = CompiledScene::new(scene, Rules::default()).expect("a valid scene");
    Episode::new(Arc::new(compiled), EpisodeConfig::default()).expect("a valid configuration")
}

fn planner(c: &mut Criterion) {
    let mut group = c.benchmark_group("plan");
    group.sample_size(10);
    for (name, index) in SCENES {
        let start = episode(index);
        group.bench_function(name, |b| {
            b.iter(|| plan(black_box(&start), &PlanOptions::default()).map(|p| p.actions.len()))
        });
    }
    group.finish();
}

criterion_group!(benches, planner);
criterion_main!(benches);
