//! `--breakdown`: where the server's time went during a scenario, from its Prometheus metrics
//! (`esrp_stage_seconds_total{stage}` and `esrp_steps_total`, scraped before and after).
//!
//! For each stage it prints the microseconds per step (the stage's seconds over the steps
//! taken meanwhile) and how busy it kept the server (its seconds over the wall seconds: 0.95
//! is one thread busy 95 % of the time, 3.2 several threads at once). A stage near 1.0 that
//! runs on one thread is what caps the server. Where the server times its render devices
//! (`esrp_render_timestamps`), a last line says how much of `render_device` the devices spent
//! drawing, by their own clocks: the rest of it is submission, synchronisation and the copy back.
//! Where the server reports its CPU time (`esrp_process_cpu_seconds_total` and, by threads,
//! `esrp_thread_cpu_seconds_total`: Linux), the lines after say how many core-microseconds each
//! group of its threads used per step and how many cores it kept busy: a render thread busy far
//! beyond its stages' time is spinning while it waits, and a server whose threads together near
//! the machine's cores is what the cores cap.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::time::Instant;

use anyhow::{Context, bail};

/// The stages, in the order a step goes through them (esrp-server's `metrics` module).
pub const STAGES: [&str; 8] =
    ["lock", "take", "render_queue", "render_encode", "render_submit", "render_device", "render_extract", "answer"];

/// One scrape of the server's metrics.
#[derive(Clone, Debug)]
pub struct Sample {
    at: Instant,
    steps: f64,
    /// Each stage's counter; `None` for a stage the server does not count (one older than it).
    stages: Vec<Option<f64>>,
    /// `esrp_render_atlases_created_total` (absent from servers older than it).
    atlases: Option<f64>,
    /// `esrp_render_gpu_seconds_total`, where the server times its devices.
    gpu: Option<f64>,
    /// `esrp_process_cpu_seconds_total`, where the server reports it.
    cpu: Option<f64>,
    /// `esrp_thread_cpu_seconds_total`, by its `threads` label.
    threads: BTreeMap<String, f64>,
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
    let stages: Vec<Option<f64>> =
        STAGES.iter().map(|stage| value(&format!("esrp_stage_seconds_total{{stage=\"{stage}\"}}"))).collect();
    if stages.iter().all(Option::is_none) {
        bail!("the metrics have no esrp_stage_seconds_total (a server older than --breakdown?)");
    }
    let timed = value("esrp_render_timestamps").is_some_and(|v| v > 0.0);
    let gpu = value("esrp_render_gpu_seconds_total").filter(|_| timed);
    let threads = text
        .lines()
        .filter_map(|line| {
            let rest = line.strip_prefix("esrp_thread_cpu_seconds_total{threads=\"")?;
            let (name, rest) = rest.split_once("\"}")?;
            Some((name.to_owned(), rest.trim().parse().ok()?))
        })
        .collect();
    Ok(Sample {
        at: Instant::now(),
        steps,
        stages,
        atlases: value("esrp_render_atlases_created_total"),
        gpu,
        cpu: value("esrp_process_cpu_seconds_total"),
        threads,
    })
}

/// What happened between two samples.
#[derive(Clone, Debug)]
pub struct Breakdown {
    /// Steps the server took.
    pub steps: f64,
    /// Wall seconds.
    pub seconds: f64,
    /// Each stage's seconds (`None`: not counted by the server).
    pub stages: Vec<Option<f64>>,
    /// Atlases the server's renderers made meanwhile (device allocations; none once its pool
    /// holds the batch sizes it needs), where the server counts them.
    pub atlases: Option<f64>,
    /// Seconds the server's render devices spent drawing, by their clocks, where it times them.
    pub gpu: Option<f64>,
    /// CPU seconds the server's process used, where it reports them.
    pub cpu: Option<f64>,
    /// CPU seconds of each group of the server's threads that used any, the busiest first.
    pub threads: Vec<(String, f64)>,
}

impl Breakdown {
    /// From `before` to `after`.
    pub fn between(before: &Sample, after: &Sample) -> Self {
        Breakdown {
            steps: after.steps - before.steps,
            seconds: (after.at - before.at).as_secs_f64(),
            stages: after.stages.iter().zip(&before.stages).map(|(a, b)| Some(a.as_ref()? - b.as_ref()?)).collect(),
            atlases: after.atlases.zip(before.atlases).map(|(a, b)| a - b),
            gpu: after.gpu.zip(before.gpu).map(|(a, b)| a - b),
            cpu: after.cpu.zip(before.cpu).map(|(a, b)| a - b),
            threads: {
                // A group absent before had used nothing yet (its threads started meanwhile).
                let mut threads: Vec<(String, f64)> = after
                    .threads
                    .iter()
                    .map(|(name, a)| (name.clone(), a - before.threads.get(name).copied().unwrap_or(0.0)))
                    .filter(|&(_, used)| used > 0.0)
                    .collect();
                threads.sort_by(|a, b| b.1.total_cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
                threads
            },
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
            lines.push(match seconds {
                Some(s) => format!("  {:<18} {:>10.1} {:>8.2}", stage, per_step(*s), s / self.seconds),
                None => format!("  {stage:<18} {:>10} {:>8}   (not counted by this server)", "-", "-"),
            });
        }
        if let Some(gpu) = self.gpu {
            lines.push(format!(
                "  {:<18} {:>10.1} {:>8.2}   (the device drawing, by its clock: part of render_device)",
                "gpu_drawing",
                per_step(gpu),
                gpu / self.seconds
            ));
        }
        if let Some(atlases) = self.atlases {
            lines.push(format!("  atlases made: {atlases:.0}"));
        }
        if let Some(cpu) = self.cpu {
            lines.push(format!("  {:<18} {:>10} {:>8}", "server CPU", "core-µs", "cores"));
            for (threads, seconds) in &self.threads {
                lines.push(format!("  {:<18} {:>10.1} {:>8.2}", threads, per_step(*seconds), seconds / self.seconds));
            }
            lines.push(format!("  {:<18} {:>10.1} {:>8.2}", "(all threads)", per_step(cpu), cpu / self.seconds));
        }
        lines
    }

    /// The `breakdown` entry of a scenario's JSON.
    pub fn to_json(&self) -> serde_json::Value {
        let stages: serde_json::Map<String, serde_json::Value> = STAGES
            .iter()
            .zip(&self.stages)
            .map(|(stage, seconds)| (stage.to_string(), self.figures(*seconds)))
            .collect();
        serde_json::json!({
            "steps": self.steps,
            "seconds": self.seconds,
            "stages": stages,
            "gpu_drawing": self.gpu.map(|gpu| self.figures(Some(gpu))),
            "atlases_made": self.atlases,
            "cpu": self.cpu.map(|cpu| serde_json::json!({
                "process": self.figures(Some(cpu)),
                "threads": self.threads.iter().map(|(name, s)| (name.clone(), self.figures(Some(*s))))
                    .collect::<serde_json::Map<String, serde_json::Value>>(),
            })),
        })
    }

    /// A stage's microseconds per step and busy share, as JSON (nulls for a stage not counted).
    fn figures(&self, seconds: Option<f64>) -> serde_json::Value {
        let per_step = seconds.filter(|_| self.steps > 0.0).map(|s| s / self.steps * 1e6);
        serde_json::json!({ "us_per_step": per_step, "busy": seconds.map(|s| s / self.seconds) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A server's metrics before `render_submit` and the device's timestamps.
    const TEXT: &str = "# TYPE esrp_steps counter\nesrp_steps_total 100\n\
        esrp_stage_seconds_total{stage=\"lock\"} 0.001\nesrp_stage_seconds_total{stage=\"take\"} 0.002\n\
        esrp_stage_seconds_total{stage=\"render_queue\"} 0.5\nesrp_stage_seconds_total{stage=\"render_encode\"} 0.1\n\
        esrp_stage_seconds_total{stage=\"render_device\"} 0.3\nesrp_stage_seconds_total{stage=\"render_extract\"} 0.05\n\
        esrp_stage_seconds_total{stage=\"answer\"} 0.004\nesrp_render_atlases_created_total 3\n# EOF\n";

    /// `TEXT` with `render_submit`, the timestamps' gauge at `timed` and `gpu` seconds drawn.
    fn newer(timed: u8, gpu: f64) -> String {
        TEXT.replace(
            "esrp_render_atlases_created_total 3\n",
            &format!(
                "esrp_render_atlases_created_total 3\nesrp_stage_seconds_total{{stage=\"render_submit\"}} 0.02\n\
                 esrp_render_timestamps {timed}\nesrp_render_gpu_seconds_total {gpu}\n"
            ),
        )
    }

    #[test]
    fn a_breakdown_divides_each_stage_by_the_steps_and_the_wall_time() {
        let before = parse(&newer(1, 0.5)).unwrap();
        let mut after = parse(&newer(1, 0.9).replace("esrp_steps_total 100", "esrp_steps_total 300")).unwrap();
        after.stages[3] = after.stages[3].map(|s| s + 0.2); // render_encode: 0.2 s more over 200 steps
        after.at = before.at + std::time::Duration::from_secs(2);
        let b = Breakdown::between(&before, &after);
        assert_eq!(b.steps, 200.0);
        let json = b.to_json();
        let encode = &json["stages"]["render_encode"];
        assert!((encode["us_per_step"].as_f64().unwrap() - 1000.0).abs() < 1e-6, "{encode}");
        assert!((encode["busy"].as_f64().unwrap() - 0.1).abs() < 1e-9, "{encode}");
        let gpu = &json["gpu_drawing"];
        assert!((gpu["us_per_step"].as_f64().unwrap() - 2000.0).abs() < 1e-6, "{gpu}");
        assert!((gpu["busy"].as_f64().unwrap() - 0.2).abs() < 1e-9, "{gpu}");
        assert_eq!(json["stages"]["render_submit"]["us_per_step"], 0.0);
        let lines = b.lines();
        assert_eq!(lines.len(), 1 + STAGES.len() + 2, "{lines:#?}");
        assert!(lines[STAGES.len() + 1].contains("gpu_drawing") && lines[STAGES.len() + 1].contains("2000.0"));
        assert_eq!(json["atlases_made"], 0.0);
    }

    #[test]
    fn an_older_server_misses_a_stage_the_timestamps_and_the_atlases() {
        let before = parse(&TEXT.replace("esrp_render_atlases_created_total 3\n", "")).unwrap();
        let mut after = parse(&TEXT.replace("esrp_steps_total 100", "esrp_steps_total 300")).unwrap();
        after.at = before.at + std::time::Duration::from_secs(2);
        let b = Breakdown::between(&before, &after);
        let json = b.to_json();
        assert!(b.atlases.is_none() && json["atlases_made"].is_null());
        assert!(json["stages"]["render_submit"]["us_per_step"].is_null(), "{json}");
        assert!(json["gpu_drawing"].is_null());
        let lines = b.lines();
        assert_eq!(lines.len(), 1 + STAGES.len(), "no atlas or gpu line: {lines:#?}");
        assert!(
            lines[5].starts_with("  render_submit") && lines[5].contains("not counted by this server"),
            "{lines:#?}"
        );
    }

    #[test]
    fn the_servers_cpu_is_divided_by_thread_groups_the_busiest_first() {
        let with_cpu = |process: f64, render: f64, runtime: Option<f64>, steps: u32| {
            let mut text = newer(0, 0.0).replace("esrp_steps_total 100", &format!("esrp_steps_total {steps}"));
            text.push_str(&format!(
                "esrp_process_cpu_seconds_total {process}\n\
                 esrp_thread_cpu_seconds_total{{threads=\"esrp-render\"}} {render}\n\
                 esrp_thread_cpu_seconds_total{{threads=\"idle one\"}} 0.5\n"
            ));
            if let Some(runtime) = runtime {
                text.push_str(&format!("esrp_thread_cpu_seconds_total{{threads=\"esrp-runtime\"}} {runtime}\n"));
            }
            parse(&text).unwrap()
        };
        // esrp-runtime's threads started after the first scrape.
        let before = with_cpu(10.0, 4.0, None, 1000);
        let mut after = with_cpu(13.0, 5.0, Some(1.5), 2000);
        after.at = before.at + std::time::Duration::from_secs(2);
        let b = Breakdown::between(&before, &after);
        assert_eq!(b.threads, vec![("esrp-runtime".to_owned(), 1.5), ("esrp-render".to_owned(), 1.0)]);
        let json = b.to_json();
        let process = &json["cpu"]["process"];
        assert!((process["us_per_step"].as_f64().unwrap() - 3000.0).abs() < 1e-6, "{json}");
        assert!((process["busy"].as_f64().unwrap() - 1.5).abs() < 1e-9, "{json}");
        let render = &json["cpu"]["threads"]["esrp-render"];
        assert!((render["us_per_step"].as_f64().unwrap() - 1000.0).abs() < 1e-6, "{json}");
        assert!(json["cpu"]["threads"].get("idle one").is_none(), "a group that used nothing: {json}");
        let lines = b.lines();
        let at = lines.iter().position(|l| l.contains("server CPU")).unwrap_or_else(|| panic!("{lines:#?}"));
        assert!(lines[at + 1].trim_start().starts_with("esrp-runtime") && lines[at + 1].contains("1500.0"));
        assert!(lines[at + 2].trim_start().starts_with("esrp-render"), "{lines:#?}");
        assert!(lines[at + 3].contains("(all threads)") && lines[at + 3].contains("1.50"), "{lines:#?}");
        // A server that does not report its CPU: no such lines, and null in the JSON.
        let old = parse(TEXT).unwrap();
        let b = Breakdown::between(&old, &old);
        assert!(b.to_json()["cpu"].is_null() && !b.lines().iter().any(|l| l.contains("server CPU")));
    }

    #[test]
    fn a_device_not_timed_has_no_gpu_line() {
        let sample = parse(&newer(0, 0.0)).unwrap();
        let b = Breakdown::between(&sample, &sample);
        assert!(b.gpu.is_none() && b.to_json()["gpu_drawing"].is_null());
    }

    #[test]
    fn a_server_without_stages_is_named() {
        let error = parse("esrp_steps_total 5\n").unwrap_err().to_string();
        assert!(error.contains("no esrp_stage_seconds_total"), "{error}");
    }
}
