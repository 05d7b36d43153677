//! `esrp-bench` end to end: a scenario run in several processes against one real server, with
//! the server's time broken down by stage from its metrics.

use std::process::Command;

use crate::harness::start;

#[test]
fn scenarios_run_in_processes_with_the_servers_breakdown() {
    let server = start(&["--metrics-listen", "127.0.0.1:0", "--no-generate-ahead"]);
    let metrics = server.metrics.clone().expect("the metrics endpoint");
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("bench.json");
    let output = Command::new(env!("CARGO_BIN_EXE_esrp-bench"))
        .args(["--server", &server.address, "--metrics", &metrics, "--breakdown", "--processes", "2"])
        .args(["--scenarios", "batch-64,unary-1", "--episodes", "3", "--seconds", "1", "--json"])
        .arg(&json)
        .output()
        .expect("esrp-bench runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&output.stderr));
    assert!(stdout.contains("render_device") && stdout.contains("2 processes"), "{stdout}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let batch = &report["results"][0];
    assert_eq!(batch["scenario"], "batch-64");
    assert_eq!(batch["processes"], 2);
    assert_eq!(batch["episodes"], 6, "--episodes in each process");
    assert!(batch["steps"].as_u64().unwrap() > 0);
    let breakdown = &batch["breakdown"];
    assert!(breakdown["steps"].as_f64().unwrap() >= batch["steps"].as_f64().unwrap(), "{breakdown}");
    for stage in ["lock", "take", "render_queue", "render_encode", "render_device", "render_extract", "answer"] {
        let busy = breakdown["stages"][stage]["busy"].as_f64().unwrap();
        assert!((0.0..64.0).contains(&busy), "{stage}: {breakdown}");
    }
    assert!(breakdown["stages"]["render_device"]["us_per_step"].as_f64().unwrap() > 0.0);
    if cfg!(target_os = "linux") {
        // The server's CPU, by threads: its render thread drew every view, and the whole
        // process used at least what its threads did.
        let cpu = &breakdown["cpu"];
        let render = cpu["threads"]["esrp-render"]["us_per_step"].as_f64().unwrap_or_else(|| panic!("{cpu}"));
        let process = cpu["process"]["us_per_step"].as_f64().unwrap();
        let threads: f64 =
            cpu["threads"].as_object().unwrap().values().map(|t| t["us_per_step"].as_f64().unwrap()).sum();
        assert!(render > 0.0 && process > 0.0, "{cpu}");
        // Ticks of 10 ms: the threads' sum and the process's total may differ by a few.
        assert!(threads <= process * 1.2 + 1e3, "{cpu}");
        assert!(stdout.contains("server CPU") && stdout.contains("esrp-render"), "{stdout}");
    }
    if cfg!(all(target_os = "linux", target_env = "gnu")) {
        // The client's CPU, summed over its two processes.
        let seconds = batch["client_cpu_seconds"].as_f64().unwrap_or_else(|| panic!("{batch}"));
        assert!(seconds > 0.0 && seconds < 2.0 * 2.0 * 2.0, "two processes of at most 2 cores for 1 s: {batch}");
        assert!(batch["client_cpu_us_per_step"].as_f64().unwrap() > 0.0, "{batch}");
        assert!(report["results"][1]["client_cpu_seconds"].as_f64().unwrap() > 0.0);
        assert!(stdout.contains("client CPU:"), "{stdout}");
    }
    assert_eq!(report["results"][1]["episodes"], 2);
}

#[test]
fn a_breakdown_of_a_named_server_needs_its_metrics() {
    let server = start(&["--no-generate-ahead"]);
    let output = Command::new(env!("CARGO_BIN_EXE_esrp-bench"))
        .args(["--server", &server.address, "--breakdown", "--scenarios", "unary-1", "--seconds", "0.5"])
        .output()
        .expect("esrp-bench runs");
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("--metrics URL"), "{stderr}");
}

#[test]
fn several_servers_need_several_processes() {
    let output = Command::new(env!("CARGO_BIN_EXE_esrp-bench"))
        .args(["--server", "http://127.0.0.1:1,http://127.0.0.1:2", "--scenarios", "unary-1"])
        .output()
        .expect("esrp-bench runs");
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("several servers need --processes"), "{stderr}");
}

/// `--client-threads`: a scenario of many episodes runs on one thread (a current-thread runtime)
/// or on as many as asked; a count beyond 256 is refused.
#[test]
fn the_clients_runtime_threads_are_chosen() {
    let server = start(&["--no-generate-ahead"]);
    for threads in ["1", "3"] {
        let output = Command::new(env!("CARGO_BIN_EXE_esrp-bench"))
            .args(["--server", &server.address, "--client-threads", threads])
            .args(["--scenarios", "unary-64,stream-mux-64", "--episodes", "3", "--seconds", "0.5"])
            .output()
            .expect("esrp-bench runs");
        let stdout = String::from_utf8_lossy(&output.stdout);
        assert!(output.status.success(), "{threads}: {stdout}\n{}", String::from_utf8_lossy(&output.stderr));
        assert!(stdout.contains("unary-64") && stdout.contains("stream-mux-64"), "{stdout}");
    }
    let output = Command::new(env!("CARGO_BIN_EXE_esrp-bench"))
        .args(["--server", &server.address, "--client-threads", "257", "--scenarios", "unary-1"])
        .output()
        .expect("esrp-bench runs");
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("--client-threads"));
}

/// `--transport unix`: the started server serves a Unix domain socket too and the clients (here
/// two processes) connect through it; its file is gone when esrp-bench ends. A named server is
/// reached as its URL says, so the flag is refused with one.
#[test]
fn clients_reach_a_started_server_over_its_socket() {
    let binary = esrp_client::find_server_binary().expect("esrp-server is built (cargo build -p esrp-server)");
    let output = Command::new(env!("CARGO_BIN_EXE_esrp-bench"))
        .arg("--server-binary")
        .arg(binary)
        .arg("--server-args=--no-generate-ahead")
        .args(["--transport", "unix", "--processes", "2", "--scenarios", "stream-mux-64,unary-1"])
        .args(["--episodes", "3", "--seconds", "0.5"])
        .env("NODEVICE_SELECT", "1")
        .output()
        .expect("esrp-bench runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&output.stderr));
    let socket = stdout
        .split_whitespace()
        .find_map(|word| word.strip_prefix("unix:"))
        .unwrap_or_else(|| panic!("esrp-bench names the socket it drove: {stdout}"));
    let socket = socket.trim_end_matches(':');
    assert!(stdout.contains("stream-mux-64") && stdout.contains("2 processes"), "{stdout}");
    assert!(!std::path::Path::new(socket).exists(), "{socket} is left behind");

    let output = Command::new(env!("CARGO_BIN_EXE_esrp-bench"))
        .args(["--server", "http://127.0.0.1:1", "--transport", "unix", "--scenarios", "unary-1"])
        .output()
        .expect("esrp-bench runs");
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("--server unix:PATH"), "{stderr}");
}
