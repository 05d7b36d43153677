//! Aggregation of per-episode metrics over many episodes (SPEC §5): SR, OSR, RDR and the share
//! of each stage, overall and per difficulty.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::episode::{EpisodeMetrics, Stage};
use crate::scene::Difficulty;

/// Means over a set of episodes.
#[derive(Clone, Copy, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct MetricsSummary {
    /// Number of episodes.
    pub episodes: usize,
    /// Success rate: mean of `S_i`.
    pub success_rate: f64,
    /// Mean object success rate.
    pub object_success_rate: f64,
    /// Mean remaining distance ratio.
    pub remaining_distance_ratio: f64,
    /// Share of episodes that ended in each stage 1–4 (index 0 is stage 1).
    pub stage_shares: [f64; 4],
}

/// Running sums, to which episodes are added one at a time.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AggregateMetrics {
    overall: Sums,
    by_difficulty: BTreeMap<Difficulty, Sums>,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
struct Sums {
    episodes: usize,
    successes: usize,
    object_success_rate: f64,
    remaining_distance_ratio: f64,
    stages: [usize; 4],
}

impl Sums {
    fn add(&mut self, m: &EpisodeMetrics) {
        self.episodes += 1;
        self.successes += usize::from(m.success);
        self.object_success_rate += m.object_success_rate;
        self.remaining_distance_ratio += m.remaining_distance_ratio;
        self.stages[m.stage as usize - Stage::NeverReached as usize] += 1;
    }

    fn summary(&self) -> MetricsSummary {
        if self.episodes == 0 {
            return MetricsSummary::default();
        }
        let n = self.episodes as f64;
        MetricsSummary {
            episodes: self.episodes,
            success_rate: self.successes as f64 / n,
            object_success_rate: self.object_success_rate / n,
            remaining_distance_ratio: self.remaining_distance_ratio / n,
            stage_shares: self.stages.map(|s| s as f64 / n),
        }
    }
}

impl AggregateMetrics {
    /// An empty aggregate.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds one finished episode of the given difficulty.
    pub fn add(&mut self, difficulty: Difficulty, metrics: &EpisodeMetrics) {
        self.overall.add(metrics);
        self.by_difficulty.entry(difficulty).or_default().add(metrics);
    }

    /// Means over every episode added.
    pub fn overall(&self) -> MetricsSummary {
        self.overall.summary()
    }

    /// Means over the episodes of one difficulty (zeros if there were none).
    pub fn for_difficulty(&self, difficulty: Difficulty) -> MetricsSummary {
        self.by_difficulty.get(&difficulty).map(Sums::summary).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episode(success: bool, osr: f64, rdr: f64, stage: Stage) -> EpisodeMetrics {
        EpisodeMetrics {
            success,
            object_success_rate: osr,
            remaining_distance_ratio: rdr,
            stage,
            placed: 0,
            movable_objects: 1,
            steps: 10,
            distance_start: 1.0,
            distance_now: rdr,
            total_reward: 0.0,
        }
    }

    #[test]
    fn means_overall_and_by_difficulty() {
        let mut agg = AggregateMetrics::new();
        agg.add(Difficulty::Easy, &episode(true, 1.0, 0.0, Stage::Succeeded));
        agg.add(Difficulty::Easy, &episode(false, 0.0, 1.0, Stage::NeverReached));
        agg.add(Difficulty::Hard, &episode(false, 0.5, 0.5, Stage::Fetched));
        let all = agg.overall();
        assert_eq!(all.episodes, 3);
        assert!((all.success_rate - 1.0 / 3.0).abs() < 1e-12);
        assert!((all.object_success_rate - 0.5).abs() < 1e-12);
        assert!((all.remaining_distance_ratio - 0.5).abs() < 1e-12);
        assert_eq!(all.stage_shares, [1.0 / 3.0, 0.0, 1.0 / 3.0, 1.0 / 3.0]);
        let easy = agg.for_difficulty(Difficulty::Easy);
        assert_eq!(easy.episodes, 2);
        assert!((easy.success_rate - 0.5).abs() < 1e-12);
        assert_eq!(agg.for_difficulty(Difficulty::Medium), MetricsSummary::default());
    }
}
