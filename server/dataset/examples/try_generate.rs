fn main() {
    let bench = esrp_dataset::Benchmark::new(0);
    let n: usize = std::env::args().nth(1).and_then(|a| a.parse().ok()).unwrap_or(40);
    let mut totals = std::collections::BTreeMap::new();
    let start = std::time::Instant::now();
    let mut times = Vec::new();
    for i in 0..n {
        let t = std::time::Instant::now();
        match bench.generate(i) {
            Ok(g) => {
                for (k, v) in g.rejections {
                    *totals.entry(k).or_insert(0) += v;
                }
                let s = &g.scene;
                times.push(t.elapsed().as_secs_f64() * 1e3);
                println!(
                    "{} {} {:?} objs {} fixed {} expert {} {:.1} ms",
                    s.id,
                    s.room_type,
                    s.difficulty,
                    s.movable_objects.len(),
                    s.fixed_objects.len(),
                    s.expert_trajectory.len(),
                    t.elapsed().as_secs_f64() * 1e3
                );
            }
            Err(e) => println!("{i}: FAILED {e}"),
        }
    }
    times.sort_by(f64::total_cmp);
    println!(
        "total {:.2} s, median {:.1} ms, rejections {totals:?}",
        start.elapsed().as_secs_f64(),
        times.get(times.len() / 2).copied().unwrap_or(0.0)
    );
}
