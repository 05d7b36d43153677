//! Replays the expert trajectory of one or more scene files and prints each episode's metrics
//! and the aggregate (SR, OSR, RDR).
//!
//! `cargo run -p esrp-core --release --example replay -- server/core/examples/scenes/bedroom.json`

use std::sync::Arc;

use esrp_core::{AggregateMetrics, CompiledScene, Episode, EpisodeConfig, Scene};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let paths: Vec<String> = std::env::args().skip(1).collect();
    if paths.is_empty() {
        return Err("usage: replay SCENE.json [SCENE.json ...]".into());
    }
    let mut aggregate = AggregateMetrics::new();
    for path in &paths {
        let text = std::fs::read_to_string(path).map_err(|e| format!("cannot read {path}: {e}"))?;
        let scene = Scene::from_json(&text).map_err(|e| format!("{path}: {e}"))?;
        let difficulty = scene.difficulty;
        let compiled = Arc::new(CompiledScene::new(scene, Default::default()).map_err(|e| format!("{path}: {e}"))?);
        let expert = compiled.scene().expert_trajectory.clone();
        let mut episode = Episode::new(compiled, EpisodeConfig::default())?;
        let started = std::time::Instant::now();
        for action in expert {
            if episode.is_over() {
                break;
            }
            episode.step(action)?;
        }
        let elapsed = started.elapsed();
        let m = episode.metrics();
        println!(
            "{path}: steps {} success {} OSR {:.3} RDR {:.4} stage {} reward {:.3} ({:.1} µs/step)",
            m.steps,
            m.success,
            m.object_success_rate,
            m.remaining_distance_ratio,
            m.stage as u8,
            m.total_reward,
            elapsed.as_secs_f64() * 1e6 / f64::from(m.steps.max(1)),
        );
        aggregate.add(difficulty, &m);
    }
    let all = aggregate.overall();
    println!(
        "overall: {} episode(s), SR {:.2} %, OSR {:.2} %, RDR {:.4}",
        all.episodes,
        100.0 * all.success_rate,
        100.0 * all.object_success_rate,
        all.remaining_distance_ratio
    );
    Ok(())
}
