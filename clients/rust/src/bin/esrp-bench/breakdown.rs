//! `--breakdown`: where the server's time went during a scenario, from its Prometheus metrics
//! (`esrp_stage_seconds_total{stage}` and `esrp_steps_total`, scraped before and after).
//!
//! For each stage it prints the microseconds per step (the stage's seconds over the steps
//! taken meanwhile) and how busy it kept the server (its seconds over the wall seconds: 0.95
//! is one thread busy 95 % of the time, 3.2 several threads at once). A stage near 1.0 that
//! runs on one thread is what caps the server.

use std::io::{Read, Write};
use std::time::Instant;

use anyhow::{Context, bail};

/// The stages, in the order a step goes through them (esrp-server's `metrics` module).
pub const STAGES: [&str; 7] =
    ["lock", "take", "render_queue", "render_encode", "render_device", "render_extract", "answer"];

/// One scrape of the server's metrics.
#[derive(Clone, Debug)]
pub struct Sample {
    at: Instant,
    steps: f64,
    stages: Vec<f64>,
    /// `esrp_render_atlases_created_total` (absent from servers older than it).
    atlases: Option<f64>,
}

/// Fetches `url` (`http://HOST:PORT/metrics`) and reads the steps and stage counters from it.
pub fn scrape(url: &str) -> anyhow::Result<Sample> {
    let host = url.trim_start_matches("http://").split('/').next().unwrap_or_default();
    let mut socket = std::net::TcpStream::connect(host).with_context(|| format!("the metrics endpoint {url}"))?;
    write!(socket, "GET /metrics HTTP/1.0\r\nHost: {host}\r\n\r\n")?;
    let mut text = String::new();
    socket.read_to_string(&mut text)?;
    if !(text.starts_with("HTTP/1.0 200") || text.starts_with("HTTP/1.1 200")) {
        bail!("{url} answered {}", text.lines().next().unwrap_or_default());
    }
    parse(&text)
}

/// The steps and stage counters of a metrics text.
pub fn parse(text: &str) -> anyhow::Result<Sample> {
    let value = |name: &str| -> Option<f64> {
        text.lines()
            .find_map(|line| line.strip_prefix(name).and_then(|rest| rest.strip_prefix(' ')))
            .and_then(|v| v.trim().parse().ok())
    };
    let steps = value("esrp_steps_total").context("the metrics have no esrp_steps_total")?;
    let stages = STAGES
        .iter()
        .map(|stage| {
            value(&format!("esrp_stage_seconds_total{{stage=\"{stage}\"}}"))
                .with_context(|| format!("the metrics have no stage {stage} (a server older than --breakdown?)"))
        })
        .collect::<anyhow::Result<_>>()?;
    Ok(Sample { at: Instant::now(), steps, stages, atlases: value("esrp_render_atlases_created_total") })
}

/// What happened between two samples.
#[derive(Clone, Debug)]
pub struct Breakdown {
    /// Steps the server took.
    pub steps: f64,
    /// Wall seconds.
    pub seconds: f64,
    /// Each stage's seconds.
    pub stages: Vec<f64>,
    /// Atlases the server's renderers made meanwhile (device allocations; none once its pool
    /// holds the batch sizes it needs), where the server counts them.
    pub atlases: Option<f64>,
}

impl Breakdown {
    /// From `before` to `after`.
    pub fn between(before: &Sample, after: &Sample) -> Self {
        Breakdown {
            steps: after.steps - before.steps,
            seconds: (after.at - before.at).as_secs_f64(),
            stages: after.stages.iter().zip(&before.stages).map(|(a, b)| a - b).collect(),
            atlases: after.atlases.zip(before.atlases).map(|(a, b)| a - b),
        }
    }

    /// The lines printed under a scenario's row.
    pub fn lines(&self) -> Vec<String> {
        let per_step = |s: f64| if self.steps > 0.0 { s / self.steps * 1e6 } else { f64::NAN };
        let mut lines = vec![format!(
            "  {:<18} {:>10} {:>8}   ({:.0} server steps in {:.1} s)",
            "stage", "µs/step", "busy", self.steps, self.seconds
        )];
        for (stage, seconds) in STAGES.iter().zip(&self.stages) {
            lines.push(format!("  {:<18} {:>10.1} {:>8.2}", stage, per_step(*seconds), seconds / self.seconds));
        }
        if let Some(atlases) = self.atlases {
            lines.push(format!("  atlases made: {atlases:.0}"));
        }
        lines
    }

    /// The `breakdown` entry of a scenario's JSON.
    pub fn to_json(&self) -> serde_json::Value {
        let stages: serde_json::Map<String, serde_json::Value> = STAGES
            .iter()
            .zip(&self.stages)
            .map(|(stage, seconds)| {
                let per_step = if self.steps > 0.0 { Some(seconds / self.steps * 1e6) } else { None };
                (stage.to_string(), serde_json::json!({ "us_per_step": per_step, "busy": seconds / self.seconds }))
            })
            .collect();
        serde_json::json!({ "steps": self.steps, "seconds": self.seconds, "stages": stages, "atlases_made": self.atlases })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = "# TYPE esrp_steps counter\nesrp_steps_total 100\n\
        esrp_stage_seconds_total{stage=\"lock\"} 0.001\nesrp_stage_seconds_total{stage=\"take\"} 0.002\n\
        esrp_stage_seconds_total{stage=\"render_queue\"} 0.5\nesrp_stage_seconds_total{stage=\"render_encode\"} 0.1\n\
        esrp_stage_seconds_total{stage=\"render_device\"} 0.3\nesrp_stage_seconds_total{stage=\"render_extract\"} 0.05\n\
        esrp_stage_seconds_total{stage=\"answer\"} 0.004\nesrp_render_atlases_created_total 3\n# EOF\n";

    #[test]
    fn a_breakdown_divides_each_stage_by_the_steps_and_the_wall_time() {
        let before = parse(TEXT).unwrap();
        let mut after = parse(&TEXT.replace("esrp_steps_total 100", "esrp_steps_total 300")).unwrap();
        after.stages[3] += 0.2; // render_encode: 0.2 s more over 200 steps
        after.at = before.at + std::time::Duration::from_secs(2);
        let b = Breakdown::between(&before, &after);
        assert_eq!(b.steps, 200.0);
        let encode = &b.to_json()["stages"]["render_encode"];
        assert!((encode["us_per_step"].as_f64().unwrap() - 1000.0).abs() < 1e-6, "{encode}");
        assert!((encode["busy"].as_f64().unwrap() - 0.1).abs() < 1e-9, "{encode}");
        assert_eq!(b.lines().len(), 1 + STAGES.len() + 1);
        assert_eq!(b.to_json()["atlases_made"], 0.0);
        let older = parse(&TEXT.replace("esrp_render_atlases_created_total 3\n", "")).unwrap();
        let b = Breakdown::between(&older, &after);
        assert!(b.atlases.is_none() && b.to_json()["atlases_made"].is_null());
        assert_eq!(b.lines().len(), 1 + STAGES.len(), "no atlas line for a server that does not count them");
    }

    #[test]
    fn a_server_without_stages_is_named() {
        let error = parse("esrp_steps_total 5\n").unwrap_err().to_string();
        assert!(error.contains("no stage lock"), "{error}");
    }
}
