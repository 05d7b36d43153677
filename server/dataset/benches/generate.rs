//! `cargo bench -p esrp-dataset --bench generate`: the cost of generating one scene of the
//! built-in benchmarks by its index (layout, backward construction, validation and replay,
//! rejected attempts included; for esrp-bench-v2 also the search for the start pose and the drive
//! away), over a fixed spread of indices.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED};

fn bench_generate(c: &mut Criterion) {
    let mut group = c.benchmark_group("generate");
    group.sample_size(60);
    for version in BenchVersion::ALL {
        let bench = Benchmark::new(version, DEFAULT_SEED);
        // Cycle through 60 consecutive scenes: the mix of room types and object counts that a
        // full generation sees.
        let mut index = 0;
        group.bench_function(format!("{version}/scene-by-index"), |b| {
            b.iter(|| {
                index = (index + 1) % 60;
                black_box(bench.generate(index).expect("benchmark scenes generate"))
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench_generate);
criterion_main!(benches);
