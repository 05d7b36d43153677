//! The tools stopped by a signal (a job scheduler's SIGTERM, a Ctrl-C) on a server they do not
//! own: they close their episodes there before they exit, and `esrp-bench`'s client processes
//! end with it.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::harness::{client, live_episodes_settled_at, start};

/// A tool's run: the process, and the file its stderr goes to (a file, not a pipe: its client
/// processes inherit it, and a pipe would keep the reader waiting as long as any of them lives).
struct Run {
    child: Child,
    stderr: tempfile::NamedTempFile,
}

/// Starts `program ARGS` and waits until the server holds at least `live` episodes.
async fn started_with_live_episodes(server: &esrp_client::LocalServer, program: &str, args: &[&str], live: u32) -> Run {
    let stderr = tempfile::NamedTempFile::new().expect("a temp file");
    let child = Command::new(program)
        .args(["--server", &server.address])
        .args(args)
        .env("NODEVICE_SELECT", "1")
        .stdout(Stdio::null())
        .stderr(stderr.reopen().expect("the temp file opens"))
        .spawn()
        .expect("the tool starts");
    let client = client(server).await;
    let deadline = Instant::now() + Duration::from_secs(120);
    while client.server_info().await.expect("ServerInfo answers").live_episodes < live {
        assert!(Instant::now() < deadline, "{program}: {live} episodes not live within 120 s");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    Run { child, stderr }
}

/// Sends `signal` (`-TERM`, `-INT`) to the run's process; its exit status and stderr.
fn stopped(mut run: Run, signal: &str) -> (Option<i32>, String) {
    let sent = Command::new("kill").args([signal, &run.child.id().to_string()]).status().expect("kill(1) runs");
    assert!(sent.success());
    let status = run.child.wait().expect("waitpid");
    (status.code(), std::fs::read_to_string(run.stderr.path()).expect("its stderr reads back"))
}

/// The server's idle timeout (600 s by default) is far off: only the tools' closes can bring
/// its live episodes back to none within the few seconds polled.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stopped_tool_closes_its_episodes_on_the_server() {
    let server = start(&["--no-generate-ahead"]);
    let dir = tempfile::tempdir().expect("a temp dir");
    let out = dir.path().join("random.jsonl");
    // The tool and its arguments; the episodes to wait for; the signal, the status and the line.
    let runs = [
        (env!("CARGO_BIN_EXE_esrp-demo"), vec!["--scenes", "60"], 30, "-TERM", 143, "esrp-demo: terminated"),
        (env!("CARGO_BIN_EXE_esrp-demo"), vec!["--scenes", "60"], 45, "-INT", 130, "esrp-demo: interrupted"),
        (
            env!("CARGO_BIN_EXE_esrp-eval"),
            vec!["--agent", "random", "--split", "test", "--episodes-in-flight", "16", "--out", out.to_str().unwrap()],
            16,
            "-TERM",
            143,
            "esrp-eval: terminated",
        ),
    ];
    let watcher = client(&server).await;
    for (program, args, live, signal, status, said) in runs {
        let run = started_with_live_episodes(&server, program, &args, live).await;
        let (code, stderr) = stopped(run, signal);
        assert_eq!(code, Some(status), "{program} {signal}: {stderr}");
        assert!(stderr.contains(said) && !stderr.contains("could not be closed"), "{stderr}");
        assert_eq!(live_episodes_settled_at(&watcher, 0).await, 0, "{program} {signal} left episodes: {stderr}");
        if program.ends_with("esrp-eval") {
            // Its last line: what its results file keeps, and how to go on.
            let kept = std::fs::read_to_string(&out).map_or(0, |text| text.lines().count());
            let episodes = if kept == 1 { "1 episode".to_owned() } else { format!("{kept} episodes") };
            let last = format!("esrp-eval: {} keeps {episodes}: run the same command again to resume", out.display());
            assert_eq!(stderr.lines().last(), Some(last.as_str()), "{stderr}");
        }
    }
}

/// SIGTERM to `esrp-bench --processes 2`: the parent stops, its children (which would have run
/// out their `--seconds`) stop with it, none of their episodes is left, and neither is the
/// folder where the children were to leave their results.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stopped_bench_takes_its_client_processes_along() {
    let server = start(&["--no-generate-ahead"]);
    let args = ["--scenarios", "unary-64", "--processes", "2", "--episodes", "8", "--seconds", "600"];
    let run = started_with_live_episodes(&server, env!("CARGO_BIN_EXE_esrp-bench"), &args, 16).await;
    let children = crate::eval::children(run.child.id());
    assert_eq!(children.len(), 2, "two client processes: {children:?}");
    let results = std::env::temp_dir().join(format!("esrp-bench-{}-unary-64", run.child.id()));
    assert!(results.is_dir(), "{} holds the children's results while they run", results.display());
    let (code, stderr) = stopped(run, "-TERM");
    assert!(!results.exists(), "{} is left behind: {stderr}", results.display());
    assert_eq!(code, Some(143), "{stderr}");
    let deadline = Instant::now() + Duration::from_secs(15);
    while children.iter().any(|&pid| crate::eval::alive(pid)) {
        if Instant::now() > deadline {
            for pid in &children {
                let _ = Command::new("kill").arg(pid.to_string()).status();
            }
            panic!("the client processes lived on: {stderr}");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(live_episodes_settled_at(&client(&server).await, 0).await, 0, "{stderr}");
}
