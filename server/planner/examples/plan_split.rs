//! `cargo run --release -p esrp-planner --example plan_split -- [--benchmark esrp-bench-v1]
//! [--limit N] [--difficulty hard] [--scenes ID,..] [--threads 2] [--verbose]`
//!
//! Generates the benchmark's test split (esrp-bench-v2 unless `--benchmark` says, the default
//! seed), plans every scene
//! from its start with the default options, replays each plan on a fresh episode, and prints
//! SR / OSR / RDR overall and per difficulty, plan length against the expert's, planning time
//! (median, p99, max) and the failures with their scene ids. A failed plan is scored by
//! replaying the actions planned before the failure (`PlanError::partial`).

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, mpsc};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use esrp_core::{AggregateMetrics, CompiledScene, Difficulty, Episode, EpisodeConfig, EpisodeMetrics, Split};
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED};
use esrp_planner::{PlanFailure, PlanOptions, plan};

#[derive(Parser, Debug)]
#[command(about = "Plan the benchmark's test split and report SR / OSR / RDR and planning time")]
struct Args {
    /// The built-in benchmark: esrp-bench-v2 or esrp-bench-v1.
    #[arg(long, default_value_t = BenchVersion::default(), value_parser = parse_version)]
    benchmark: BenchVersion,
    /// Plan at most this many scenes (in index order).
    #[arg(long)]
    limit: Option<usize>,
    /// Only scenes of this difficulty.
    #[arg(long, value_parser = parse_difficulty)]
    difficulty: Option<Difficulty>,
    /// Only these scenes (ids like esrp-bench-v2/00042, or indices), comma-separated; any split.
    #[arg(long, value_delimiter = ',')]
    scenes: Vec<String>,
    /// Worker threads (each generates and plans its own scenes).
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Print one line per scene.
    #[arg(long)]
    verbose: bool,
    /// PlanOptions::heuristic_weight (default: the library's).
    #[arg(long)]
    heuristic_weight: Option<f64>,
    /// PlanOptions::iou_weight.
    #[arg(long)]
    iou_weight: Option<f64>,
    /// PlanOptions::duplicate_cell, metres (0: exact duplicates only).
    #[arg(long)]
    duplicate_cell: Option<f64>,
    /// PlanOptions::max_search_nodes.
    #[arg(long)]
    max_search_nodes: Option<u64>,
    /// PlanOptions::polish_nodes.
    #[arg(long)]
    polish_nodes: Option<u64>,
    /// PlanOptions::max_nodes.
    #[arg(long)]
    max_nodes: Option<u64>,
}

impl Args {
    fn options(&self) -> PlanOptions {
        let d = PlanOptions::default();
        PlanOptions {
            heuristic_weight: self.heuristic_weight.unwrap_or(d.heuristic_weight),
            iou_weight: self.iou_weight.unwrap_or(d.iou_weight),
            duplicate_cell: self.duplicate_cell.unwrap_or(d.duplicate_cell),
            max_search_nodes: self.max_search_nodes.unwrap_or(d.max_search_nodes),
            max_nodes: self.max_nodes.unwrap_or(d.max_nodes),
            polish_nodes: self.polish_nodes.unwrap_or(d.polish_nodes),
            ..d
        }
    }
}

fn parse_version(name: &str) -> Result<BenchVersion, String> {
    name.parse().map_err(|e: esrp_dataset::UnknownBenchmark| e.to_string())
}

fn parse_difficulty(text: &str) -> Result<Difficulty, String> {
    match text {
        "easy" => Ok(Difficulty::Easy),
        "medium" => Ok(Difficulty::Medium),
        "hard" => Ok(Difficulty::Hard),
        other => Err(format!("unknown difficulty {other:?}: use easy, medium or hard")),
    }
}

/// One scene's outcome.
struct Row {
    id: String,
    difficulty: Difficulty,
    expert_steps: usize,
    generation: Duration,
    planning: Duration,
    nodes: u64,
    relocated: u32,
    /// Plan length, or the failure.
    outcome: Result<usize, PlanFailure>,
    metrics: EpisodeMetrics,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let bench = Arc::new(Benchmark::new(args.benchmark, DEFAULT_SEED));
    let mut indices: Vec<usize> = if args.scenes.is_empty() {
        (0..bench.len()).filter(|&i| bench.split(i) == Split::Test).collect()
    } else {
        args.scenes
            .iter()
            .map(|s| {
                s.parse::<usize>()
                    .ok()
                    .filter(|&i| i < bench.len())
                    .or_else(|| bench.index_of(s.trim()))
                    .with_context(|| format!("no scene {s:?} in {}", bench.name()))
            })
            .collect::<anyhow::Result<_>>()?
    };
    if let Some(difficulty) = args.difficulty {
        indices.retain(|&i| Difficulty::for_object_count(bench.object_count(i)) == Some(difficulty));
    }
    if let Some(limit) = args.limit {
        indices.truncate(limit);
    }
    if indices.is_empty() {
        bail!("no scenes selected");
    }
    if args.threads == 0 {
        bail!("--threads must be at least 1");
    }
    eprintln!("planning {} scenes on {} threads", indices.len(), args.threads);
    let started = Instant::now();
    let options = Arc::new(args.options());
    println!("options: {options:?}");
    let indices = Arc::new(indices);
    let next = Arc::new(AtomicUsize::new(0));
    let (sender, receiver) = mpsc::channel();
    let workers: Vec<_> = (0..args.threads)
        .map(|_| {
            let (bench, indices, next, sender) = (bench.clone(), indices.clone(), next.clone(), sender.clone());
            let options = options.clone();
            std::thread::spawn(move || {
                loop {
                    let k = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&index) = indices.get(k) else { break };
                    if sender.send(run_scene(&bench, index, &options)).is_err() {
                        break;
                    }
                }
            })
        })
        .collect();
    drop(sender);
    let mut rows = Vec::new();
    for row in receiver {
        let row = row?;
        if args.verbose || row.outcome.is_err() {
            print_row(&row);
        }
        rows.push(row);
        if rows.len() % 50 == 0 {
            eprintln!("{} / {} scenes, {:.0} s", rows.len(), indices.len(), started.elapsed().as_secs_f64());
        }
    }
    for worker in workers {
        worker.join().map_err(|_| anyhow::anyhow!("a worker thread panicked"))?;
    }
    rows.sort_by(|a, b| a.id.cmp(&b.id));
    report(&rows, started.elapsed());
    Ok(())
}

fn run_scene(bench: &Benchmark, index: usize, options: &PlanOptions) -> anyhow::Result<Row> {
    let generation_started = Instant::now();
    let scene = bench.generate(index).with_context(|| format!("generating scene {index}"))?.scene;
    let generation = generation_started.elapsed();
    let id = scene.id.clone();
    let difficulty = scene.difficulty;
    let expert_steps = scene.expert_trajectory.len();
    let compiled = CompiledScene::shared(scene).with_context(|| format!("compiling {id}"))?;
    let mut episode = Episode::new(compiled, EpisodeConfig::default())?;
    let (actions, outcome, stats) = match plan(&episode, options) {
        Ok(found) => {
            let steps = found.actions.len();
            (found.actions, Ok(steps), found.stats)
        }
        Err(error) => (error.partial, Err(error.reason), error.stats),
    };
    for action in actions {
        if episode.is_over() {
            break;
        }
        episode.step(action)?;
    }
    Ok(Row {
        id,
        difficulty,
        expert_steps,
        generation,
        planning: stats.elapsed,
        nodes: stats.nodes_expanded,
        relocated: stats.objects_relocated,
        outcome,
        metrics: episode.metrics(),
    })
}

fn print_row(row: &Row) {
    let outcome = match &row.outcome {
        Ok(steps) => format!("ok {steps} steps (expert {})", row.expert_steps),
        Err(failure) => format!("FAILED: {failure}"),
    };
    println!(
        "{} {:6} {:7.3} s {:8} nodes {} relocated  OSR {:.2} RDR {:.3}  {outcome}",
        row.id,
        row.difficulty.as_str(),
        row.planning.as_secs_f64(),
        row.nodes,
        row.relocated,
        row.metrics.object_success_rate,
        row.metrics.remaining_distance_ratio,
    );
}

/// The value at quantile `q` of sorted `values` (nearest rank).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

fn report(rows: &[Row], wall: Duration) {
    let mut aggregate = AggregateMetrics::new();
    for row in rows {
        aggregate.add(row.difficulty, &row.metrics);
    }
    println!("\n## {} scenes, wall {:.1} s", rows.len(), wall.as_secs_f64());
    println!("| split | scenes | SR % | OSR % | RDR |");
    println!("|---|---|---|---|---|");
    let groups = [
        ("overall", aggregate.overall()),
        ("easy", aggregate.for_difficulty(Difficulty::Easy)),
        ("medium", aggregate.for_difficulty(Difficulty::Medium)),
        ("hard", aggregate.for_difficulty(Difficulty::Hard)),
    ];
    for (name, summary) in groups {
        println!(
            "| {name} | {} | {:.2} | {:.2} | {:.4} |",
            summary.episodes,
            100.0 * summary.success_rate,
            100.0 * summary.object_success_rate,
            summary.remaining_distance_ratio
        );
    }
    let planned: Vec<(usize, usize)> =
        rows.iter().filter_map(|r| r.outcome.as_ref().ok().map(|&steps| (steps, r.expert_steps))).collect();
    if !planned.is_empty() {
        let mut ratios: Vec<f64> = planned.iter().map(|&(p, e)| p as f64 / e.max(1) as f64).collect();
        ratios.sort_by(f64::total_cmp);
        let plan_mean = planned.iter().map(|p| p.0 as f64).sum::<f64>() / planned.len() as f64;
        let expert_mean = planned.iter().map(|p| p.1 as f64).sum::<f64>() / planned.len() as f64;
        let shorter = planned.iter().filter(|p| p.0 <= p.1).count();
        println!(
            "\nplan length (successes): mean {plan_mean:.1} steps vs expert {expert_mean:.1}; plan/expert median {:.2}, \
             p90 {:.2}, max {:.2}; {shorter} of {} no longer than the expert",
            quantile(&ratios, 0.5),
            quantile(&ratios, 0.9),
            quantile(&ratios, 1.0),
            planned.len()
        );
    }
    let mut times: Vec<f64> = rows.iter().map(|r| r.planning.as_secs_f64()).collect();
    times.sort_by(f64::total_cmp);
    let planning_total: f64 = times.iter().sum();
    let generation_total: f64 = rows.iter().map(|r| r.generation.as_secs_f64()).sum();
    println!(
        "planning time per episode: median {:.3} s, p99 {:.3} s, max {:.3} s; total {:.1} s (generation {:.1} s) \
         over all threads",
        quantile(&times, 0.5),
        quantile(&times, 0.99),
        quantile(&times, 1.0),
        planning_total,
        generation_total
    );
    for difficulty in [Difficulty::Easy, Difficulty::Medium, Difficulty::Hard] {
        let mut times: Vec<f64> =
            rows.iter().filter(|r| r.difficulty == difficulty).map(|r| r.planning.as_secs_f64()).collect();
        times.sort_by(f64::total_cmp);
        println!(
            "  {:6}: median {:.3} s, p99 {:.3} s, max {:.3} s",
            difficulty.as_str(),
            quantile(&times, 0.5),
            quantile(&times, 0.99),
            quantile(&times, 1.0)
        );
    }
    let relocated = rows.iter().filter(|r| r.relocated > 0).count();
    println!("scenes that moved an object to a buffer pose: {relocated}");
    let mut failures: BTreeMap<String, Vec<&str>> = BTreeMap::new();
    for row in rows {
        if let Err(failure) = &row.outcome {
            failures.entry(failure_kind(failure).to_string()).or_default().push(&row.id);
        }
    }
    if failures.is_empty() {
        println!("failures: none");
    }
    for (kind, ids) in failures {
        let shown: Vec<&str> = ids.iter().take(12).copied().collect();
        println!("failures {kind}: {} — {}", ids.len(), shown.join(", "));
    }
}

fn failure_kind(failure: &PlanFailure) -> &'static str {
    failure.name()
}
