//! `cargo bench -p esrp-server --bench trail`: what an unwatched episode pays for the web
//! viewer: the trail (`Trail::step`: a position a step, the carried object's, the last actions)
//! beside the simulator's own step, on a random walk over an esrp-bench-v2 scene. The viewer's
//! goal is that an unwatched episode loses at most 1 % of its steps/s; a server step also
//! renders and answers, so the share of the simulator step alone is an upper bound.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use esrp_core::{Action, CompiledScene, Episode, EpisodeConfig, Rules};
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED};
use esrp_server::episodes::Trail;

fn bench_trail(c: &mut Criterion) {
    let scene = Benchmark::new(BenchVersion::V2, DEFAULT_SEED).generate(3).expect("benchmark scenes generate").scene;
    let compiled = Arc::new(CompiledScene::new(scene, Rules::default()).expect("benchmark scenes compile"));
    let config = EpisodeConfig { horizon: Some(100_000), ..Default::default() };
    let start = Episode::new(compiled, config).expect("a running episode");
    let mut seed = 0x2545_F491_4F6C_DD1Du64;
    let walk: Vec<Action> = (0..4096)
        .map(|_| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            Action::from_code((seed % 6) as i64).expect("0..6 are actions")
        })
        .collect();
    let mut group = c.benchmark_group("unwatched");
    let (mut episode, mut next) = (start.clone(), 0);
    group.bench_function("step", |b| {
        b.iter(|| {
            if episode.is_over() {
                episode = start.clone();
            }
            next = (next + 1) % walk.len();
            black_box(episode.step(walk[next]).expect("running"))
        })
    });
    let (mut episode, mut next) = (start.clone(), 0);
    let mut trail = Trail::start(&episode);
    group.bench_function("step+trail", |b| {
        b.iter(|| {
            if episode.is_over() {
                episode = start.clone();
                trail = Trail::start(&episode);
            }
            next = (next + 1) % walk.len();
            let outcome = episode.step(walk[next]).expect("running");
            trail.step(&episode, walk[next].code(), !outcome.collided());
            black_box(outcome)
        })
    });
    group.finish();
}

criterion_group!(benches, bench_trail);
criterion_main!(benches);
