//! The results schema `esrp.results/v1` shared by every evaluation tool (Rust `esrp-eval`,
//! Python `esrp eval`) and the server's records, as `docs/evaluation.md` describes it: the
//! record type and its files come from esrp-results (re-exported here); [`Summary`] computes
//! SR / OSR / RDR overall and per difficulty and writes the Markdown summary with the paper's
//! rows beside it.

use std::collections::BTreeMap;
use std::fmt::Write as _;

pub use esrp_results::{EpisodeRecord, ReadRecords, ResultsError, SCHEMA, append_record, read_records, truncate_to};

use crate::types::Difficulty;

/// SR / OSR / RDR and stage counts over a set of records.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Tally {
    /// Episodes.
    pub episodes: u32,
    /// Successful episodes.
    pub successes: u32,
    /// Sum of OSR.
    pub osr_sum: f64,
    /// Sum of RDR.
    pub rdr_sum: f64,
    /// Episodes per stage 1..=4 (index 0 is stage 1).
    pub stages: [u32; 4],
    /// Sum of steps.
    pub steps: u64,
    /// Episodes the agent ended before success or the horizon.
    pub ended_by_agent: u32,
}

impl Tally {
    /// Adds a record.
    pub fn add(&mut self, r: &EpisodeRecord) {
        self.episodes += 1;
        self.successes += u32::from(r.success);
        self.osr_sum += r.osr;
        self.rdr_sum += r.rdr;
        if (1..=4).contains(&r.stage) {
            self.stages[r.stage as usize - 1] += 1;
        }
        self.steps += u64::from(r.steps);
        self.ended_by_agent += u32::from(r.end == "agent");
    }

    fn mean(&self, sum: f64) -> f64 {
        if self.episodes == 0 { f64::NAN } else { sum / f64::from(self.episodes) }
    }

    /// Success rate, 0..=1 (NaN without episodes).
    pub fn sr(&self) -> f64 {
        self.mean(f64::from(self.successes))
    }

    /// Object success rate, 0..=1.
    pub fn osr(&self) -> f64 {
        self.mean(self.osr_sum)
    }

    /// Remaining distance ratio.
    pub fn rdr(&self) -> f64 {
        self.mean(self.rdr_sum)
    }

    /// Share of episodes in stage `stage` (1..=4).
    pub fn stage_share(&self, stage: usize) -> f64 {
        self.mean(f64::from(self.stages[stage - 1]))
    }
}

/// The summary of one agent's records: overall and per difficulty.
#[derive(Clone, Debug, Default)]
pub struct Summary {
    /// The agent's name (of the first record).
    pub agent: String,
    /// Every record.
    pub overall: Tally,
    /// Per difficulty name (`easy`, `medium`, `hard`).
    pub by_difficulty: BTreeMap<String, Tally>,
}

/// A row of the paper's results (SPEC §8), percentages and RDR.
struct PaperRow {
    name: &'static str,
    overall: [f64; 3],
    by_difficulty: [[f64; 3]; 3],
    stages: Option<[f64; 4]>,
}

/// The paper's Tables I–III (SPEC §8): SR % / OSR % / RDR overall, per difficulty (Easy,
/// Medium, Hard), and the stage shares where it gives them.
const PAPER: [PaperRow; 4] = [
    PaperRow {
        name: "ESRP-PPO (paper)",
        overall: [20.18, 20.35, 0.9845],
        by_difficulty: [[33.33, 33.33, 0.9040], [0.54, 0.54, 1.0645], [0.00, 0.00, 1.0048]],
        stages: Some([13.21, 5.76, 60.85, 20.18]),
    },
    PaperRow {
        name: "ESRP-BC (paper)",
        overall: [19.09, 20.31, 1.0170],
        by_difficulty: [[29.44, 29.44, 0.9631], [0.91, 4.20, 1.1157], [0.00, 4.44, 1.0704]],
        stages: Some([11.33, 6.73, 62.85, 19.09]),
    },
    PaperRow {
        name: "ESRP-VLM (paper)",
        overall: [17.64, 18.97, 0.9830],
        by_difficulty: [[27.64, 27.64, 0.9523], [0.00, 3.99, 1.0372], [0.00, 0.00, 1.0378]],
        stages: Some([11.64, 4.18, 66.55, 17.64]),
    },
    PaperRow {
        name: "ESRP-PLAN (paper)",
        overall: [30.20, 36.59, 0.6916],
        by_difficulty: [[35.73, 35.73, 0.7101], [22.40, 39.71, 0.6425], [0.00, 22.00, 0.8165]],
        stages: None,
    },
];

const DIFFICULTIES: [Difficulty; 3] = [Difficulty::Easy, Difficulty::Medium, Difficulty::Hard];

impl Summary {
    /// The summary of `records`.
    pub fn of(records: &[EpisodeRecord]) -> Self {
        let mut summary =
            Summary { agent: records.first().map(|r| r.agent.clone()).unwrap_or_default(), ..Default::default() };
        for r in records {
            summary.overall.add(r);
            summary.by_difficulty.entry(r.difficulty.clone()).or_default().add(r);
        }
        summary
    }

    /// A few lines for a terminal: SR / OSR / RDR overall and per difficulty (one line saying so
    /// when there are no episodes, as the Python summary's).
    pub fn text(&self) -> String {
        if self.overall.episodes == 0 {
            return "no episodes recorded: no SR, OSR or RDR to give\n".to_owned();
        }
        let mut out = String::new();
        let line = |out: &mut String, name: &str, t: &Tally| {
            let _ = writeln!(
                out,
                "{name:<8} SR {:>6.2} %  OSR {:>6.2} %  RDR {:.4}  stages 1/2/3/4 {:.1}/{:.1}/{:.1}/{:.1} %  ({} episodes, {} ended by the agent)",
                100.0 * t.sr(),
                100.0 * t.osr(),
                t.rdr(),
                100.0 * t.stage_share(1),
                100.0 * t.stage_share(2),
                100.0 * t.stage_share(3),
                100.0 * t.stage_share(4),
                t.episodes,
                t.ended_by_agent,
            );
        };
        line(&mut out, "overall", &self.overall);
        for d in DIFFICULTIES {
            if let Some(t) = self.by_difficulty.get(d.name()) {
                line(&mut out, d.name(), t);
            }
        }
        out
    }

    /// The Markdown summary: the agent's SR / OSR / RDR overall and per difficulty with the
    /// paper's rows (SPEC §8) beside it, then stage shares and step counts.
    pub fn markdown(&self, title: &str) -> String {
        let mut md = String::new();
        let _ = writeln!(md, "# {title}\n");
        if self.overall.episodes == 0 {
            let _ = writeln!(
                md,
                "No episodes recorded for **{}**: there is no SR, OSR or RDR to give (every episode failed with an error, or none was played).",
                self.agent
            );
            return md;
        }
        let _ = writeln!(
            md,
            "SR and OSR in %, RDR as a ratio (lower is better). {} episodes. The paper's rows are its Tables I–III (SPEC §8).\n",
            self.overall.episodes
        );
        let _ = writeln!(md, "| agent | overall SR / OSR / RDR | Easy | Medium | Hard |");
        let _ = writeln!(md, "|---|---|---|---|---|");
        let cell = |t: Option<&Tally>| match t {
            Some(t) if t.episodes > 0 => {
                format!("{:.2} / {:.2} / {:.4}", 100.0 * t.sr(), 100.0 * t.osr(), t.rdr())
            }
            _ => "–".to_owned(),
        };
        let _ = write!(md, "| **{}** (this run) | {} |", self.agent, cell(Some(&self.overall)));
        for d in DIFFICULTIES {
            let _ = write!(md, " {} |", cell(self.by_difficulty.get(d.name())));
        }
        md.push('\n');
        for row in &PAPER {
            let [sr, osr, rdr] = row.overall;
            let _ = write!(md, "| {} | {sr:.2} / {osr:.2} / {rdr:.4} |", row.name);
            for [sr, osr, rdr] in row.by_difficulty {
                let _ = write!(md, " {sr:.2} / {osr:.2} / {rdr:.4} |");
            }
            md.push('\n');
        }
        let _ = writeln!(md, "\n## Failure stages (% of episodes in stage 1 / 2 / 3 / 4)\n");
        let _ = writeln!(md, "| agent | 1 never in reach | 2 never fetched | 3 fetched, no success | 4 success |");
        let _ = writeln!(md, "|---|---|---|---|---|");
        let t = &self.overall;
        let _ = writeln!(
            md,
            "| **{}** (this run) | {:.2} | {:.2} | {:.2} | {:.2} |",
            self.agent,
            100.0 * t.stage_share(1),
            100.0 * t.stage_share(2),
            100.0 * t.stage_share(3),
            100.0 * t.stage_share(4)
        );
        for row in PAPER.iter().filter(|r| r.stages.is_some()) {
            if let Some([a, b, c, d]) = row.stages {
                let _ = writeln!(md, "| {} | {a:.2} | {b:.2} | {c:.2} | {d:.2} |", row.name);
            }
        }
        let _ = writeln!(md, "\n## Episodes\n");
        let _ = writeln!(md, "| difficulty | episodes | successes | mean steps | ended by the agent |");
        let _ = writeln!(md, "|---|---|---|---|---|");
        let rows = DIFFICULTIES
            .iter()
            .filter_map(|d| self.by_difficulty.get(d.name()).map(|t| (d.name(), t)))
            .chain(std::iter::once(("all", &self.overall)));
        for (name, t) in rows {
            let mean_steps = if t.episodes == 0 { 0.0 } else { t.steps as f64 / f64::from(t.episodes) };
            let _ =
                writeln!(md, "| {name} | {} | {} | {mean_steps:.1} | {} |", t.episodes, t.successes, t.ended_by_agent);
        }
        md
    }
}

#[cfg(test)]
mod tests {
    use esrp_results::testing::record;

    use super::*;

    #[test]
    fn summary_means_by_difficulty() {
        let records = [
            record("a", "easy", true, 1.0, 0.0, 4),
            record("b", "easy", false, 0.0, 1.0, 3),
            record("c", "hard", false, 0.5, 0.5, 1),
        ];
        let s = Summary::of(&records);
        assert_eq!(s.overall.episodes, 3);
        assert!((s.overall.sr() - 1.0 / 3.0).abs() < 1e-12);
        assert!((s.overall.osr() - 0.5).abs() < 1e-12);
        assert_eq!(s.by_difficulty["easy"].successes, 1);
        assert!((s.by_difficulty["hard"].rdr() - 0.5).abs() < 1e-12);
        assert_eq!(s.overall.stages, [1, 0, 1, 1]);
        let md = s.markdown("random");
        assert!(md.contains("| **random** (this run) | 33.33 / 50.00 / 0.5000 | 50.00 / 50.00 / 0.5000 | – | 0.00 / 50.00 / 0.5000 |"), "{md}");
        assert!(md.contains("| ESRP-PLAN (paper) | 30.20 / 36.59 / 0.6916 |"));
    }
}
