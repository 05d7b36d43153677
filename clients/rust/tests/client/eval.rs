//! `esrp-eval` end to end: the binary against a real server, its records, its resumption and
//! its refusals.

use std::path::Path;
use std::process::{Command, Output};

use esrp_client::results::{EpisodeRecord, read_records};
use esrp_client::{Action, EpisodeOptions};

use crate::harness::{client, start};

fn eval(server: &str, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_esrp-eval"))
        .args(["--server", server])
        .args(args)
        .output()
        .expect("esrp-eval runs")
}

fn ok(output: Output) -> String {
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(output.status.success(), "esrp-eval failed:\n{stdout}\n{}", String::from_utf8_lossy(&output.stderr));
    stdout
}

fn records(path: &Path) -> Vec<EpisodeRecord> {
    let read = read_records(path).expect("the results read back");
    assert!(!read.torn_tail);
    read.records
}

/// The records without what differs between runs (times, order).
fn comparable(mut records: Vec<EpisodeRecord>) -> Vec<EpisodeRecord> {
    for r in &mut records {
        r.wall_seconds = 0.0;
        r.finished_at.clear();
    }
    records.sort_by(|a, b| a.scene_id.cmp(&b.scene_id));
    records
}

#[tokio::test]
async fn the_expert_succeeds_and_its_actions_replay() {
    let server = start(&[]);
    let dir = tempfile::tempdir().expect("a temp dir");
    let out = dir.path().join("expert.jsonl");
    let stdout = ok(eval(&server.address, &["--agent", "expert", "--limit", "3", "--out", out.to_str().unwrap()]));
    assert!(stdout.contains("SR 100.00 %"), "{stdout}");
    let records = records(&out);
    assert_eq!(records.len(), 3);
    for r in &records {
        assert!(r.success && r.end == "success" && r.stage == 4 && r.osr == 1.0, "{r:?}");
        assert_eq!(r.actions.len(), r.steps as usize);
        assert_eq!((r.split.as_str(), r.agent.as_str(), r.seed), ("test", "expert", None));
        assert!(r.horizon >= 200 && r.steps <= r.horizon);
    }
    // The recorded actions replay to the same end.
    let client = client(&server).await;
    let r = &records[0];
    let (mut episode, _) = client.create_episode(EpisodeOptions::scene(&r.scene_id)).await.expect("created");
    let mut last = None;
    for &code in &r.actions {
        last = Some(episode.step(Action::try_from(i64::from(code)).expect("a code")).await.expect("a step"));
    }
    let metrics = last.and_then(|s| s.metrics).expect("the replay ends the episode");
    assert_eq!((metrics.success, metrics.steps, metrics.total_reward), (r.success, r.steps, r.total_reward));
    let summary = std::fs::read_to_string(out.with_extension("md")).expect("the summary");
    assert!(summary.contains("| **expert** (this run) | 100.00 / 100.00 / 0.0000 |"), "{summary}");
    assert!(summary.contains("| ESRP-PLAN (paper) | 30.20 / 36.59 / 0.6916 |"), "{summary}");
}

#[tokio::test]
async fn an_interrupted_run_resumes_to_the_same_results() {
    let server = start(&[]);
    let dir = tempfile::tempdir().expect("a temp dir");
    let whole = dir.path().join("whole.jsonl");
    let parts = dir.path().join("parts.jsonl");
    let base = ["--agent", "random", "--seed", "5", "--difficulty", "easy", "--episodes-in-flight", "3"];
    ok(eval(&server.address, &[&base[..], &["--limit", "4", "--out", whole.to_str().unwrap()]].concat()));
    // Two episodes, then a line cut short by a kill, then the rest.
    ok(eval(&server.address, &[&base[..], &["--limit", "2", "--out", parts.to_str().unwrap()]].concat()));
    let mut text = std::fs::read(&parts).expect("the first part");
    text.extend_from_slice(br#"{"schema":"esrp.results/v1","scene_id":"esrp-bench"#);
    std::fs::write(&parts, text).expect("a torn line");
    let output = eval(&server.address, &[&base[..], &["--limit", "4", "--out", parts.to_str().unwrap()]].concat());
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    ok(output);
    assert!(stderr.contains("dropping a last line") && stderr.contains("2 of 4 scenes already done"), "{stderr}");
    let (whole, parts) = (records(&whole), records(&parts));
    assert_eq!(comparable(parts), comparable(whole.clone()));
    for r in &whole {
        let expected_seed = 5 ^ r
            .scene_id
            .bytes()
            .fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3));
        assert_eq!(r.seed, Some(expected_seed));
        assert_eq!(r.difficulty, "easy");
    }
}

#[tokio::test]
async fn the_planner_agent_places_everything() {
    let server = start(&[]);
    let dir = tempfile::tempdir().expect("a temp dir");
    let out = dir.path().join("plan.jsonl");
    ok(eval(
        &server.address,
        &["--agent", "plan", "--difficulty", "easy", "--limit", "2", "--out", out.to_str().unwrap()],
    ));
    for r in records(&out) {
        assert!(r.success, "{r:?}");
        assert_eq!(r.agent_stats["plan_calls"], 1);
        assert!(r.agent_stats["nodes_expanded"].as_u64().unwrap_or(0) > 0);
        assert!(r.agent_stats["failure"].is_null());
    }
}

#[tokio::test]
async fn bad_requests_are_refused_with_a_reason() {
    let server = start(&[]);
    let dir = tempfile::tempdir().expect("a temp dir");
    let out = dir.path().join("r.jsonl");
    let output = eval(&server.address, &["--agent", "random", "--scenes", "no/such", "--out", out.to_str().unwrap()]);
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("scene \"no/such\" is not among the test scenes"));

    ok(eval(&server.address, &["--agent", "expert", "--limit", "1", "--out", out.to_str().unwrap()]));
    let output = eval(&server.address, &["--agent", "random", "--limit", "1", "--out", out.to_str().unwrap()]);
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("holds results of agent \"expert\"") && stderr.contains("--fresh"), "{stderr}");

    // The same agent with other settings is another run.
    let plan = dir.path().join("plan.jsonl");
    ok(eval(&server.address, &["--agent", "plan", "--limit", "1", "--out", plan.to_str().unwrap()]));
    let output = eval(
        &server.address,
        &["--agent", "plan", "--limit", "2", "--plan-budget-ms", "5000", "--out", plan.to_str().unwrap()],
    );
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("with other settings") && stderr.contains("\"budget_ms\":5000"), "{stderr}");
}

/// `--scenes` naming a scene twice, or an empty id, is refused before anything runs (exit 2), as
/// `esrp eval` refuses it: each scene is played, and resumed, once.
#[test]
fn scenes_named_twice_or_empty_are_refused_up_front() {
    let dir = tempfile::tempdir().expect("a temp dir");
    let out = dir.path().join("r.jsonl");
    for (scenes, said) in [
        ("a/1,b/2,a/1,b/2,c/3", "--scenes lists a/1, b/2 more than once"),
        ("a/1,,b/2", "--scenes names an empty scene id"),
    ] {
        let output = eval("127.0.0.1:1", &["--agent", "random", "--scenes", scenes, "--out", out.to_str().unwrap()]);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(2), "{scenes}: {stderr}");
        assert!(stderr.contains(said), "{scenes}: {stderr}");
        assert!(!out.exists());
    }
}

/// A planning budget PlanActions cannot carry is refused before anything runs: 0 was sent as
/// 1 ms (every episode then failed with deadline_exceeded), and one over 32 bits was cut down.
#[test]
fn a_plan_budget_out_of_range_is_refused_up_front() {
    let dir = tempfile::tempdir().expect("a temp dir");
    let out = dir.path().join("plan.jsonl");
    for budget in ["0", "4294967296"] {
        let output =
            eval("127.0.0.1:1", &["--agent", "plan", "--plan-budget-ms", budget, "--out", out.to_str().unwrap()]);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(2), "{budget}: {stderr}");
        assert!(stderr.contains(&format!("invalid value '{budget}' for '--plan-budget-ms")), "{stderr}");
        assert!(!out.exists());
    }
}

/// A second run over a challenge's scenes is refused by the server (one counted attempt per scene
/// and token): `esrp-eval` says that those episodes would be refused again, not to rerun them.
#[tokio::test]
async fn challenge_scenes_already_played_are_not_offered_for_a_rerun() {
    let dir = tempfile::tempdir().expect("a temp dir");
    let tokens = dir.path().join("tokens.toml");
    std::fs::write(&tokens, "[[token]]\nname = \"team\"\nsecret = \"team-secret\"\nrole = \"agent\"\n").unwrap();
    let records = dir.path().join("records");
    let server = start(&[
        "--tokens",
        tokens.to_str().unwrap(),
        "--challenge-seed",
        "the-organisers-secret-seed",
        "--challenge-scenes",
        "2",
        "--records",
        records.to_str().unwrap(),
    ]);
    let out = dir.path().join("run.jsonl");
    let run = |more: &[&str]| {
        let args =
            ["--agent", "random", "--split", "challenge", "--token", "team-secret", "--out", out.to_str().unwrap()];
        eval(&server.address, &[&args[..], more].concat())
    };
    ok(run(&[]));
    let again = run(&["--fresh"]);
    assert!(!again.status.success());
    let stderr = String::from_utf8_lossy(&again.stderr);
    assert!(
        stderr.contains(
            "2 episodes were refused by the server and not recorded, as they would be again: challenge/00000, \
             challenge/00001"
        ),
        "{stderr}"
    );
    assert!(stderr.contains("already played") && !stderr.contains("rerun"), "{stderr}");
    // The summary's first line counts them too (it said `random on 0 scenes`, no more).
    let stdout = String::from_utf8_lossy(&again.stdout);
    assert!(stdout.contains("random on 0 scenes of esrp-bench-v2, 2 more failed (not recorded) ("), "{stdout}");
}

/// The processes whose parent is `pid` (Linux's /proc).
pub(crate) fn children(pid: u32) -> Vec<u32> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir("/proc").expect("/proc").flatten() {
        let Ok(child) = entry.file_name().to_string_lossy().parse::<u32>() else { continue };
        let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else { continue };
        // pid (comm) state ppid ...: comm may hold spaces, so split after its closing paren.
        let parent = stat.rsplit_once(')').and_then(|(_, rest)| rest.split_whitespace().nth(1)?.parse::<u32>().ok());
        if parent == Some(pid) {
            found.push(child);
        }
    }
    found
}

/// `esrp-eval ARGS --out DIR/random.jsonl` on a server it starts, once it has written two
/// records: the process (stderr piped) and the results file.
fn eval_with_two_records(dir: &Path, args: &[&str]) -> (std::process::Child, std::path::PathBuf) {
    use std::time::{Duration, Instant};
    let out = dir.join("random.jsonl");
    let mut child = Command::new(env!("CARGO_BIN_EXE_esrp-eval"))
        .args(args)
        .args(["--out", out.to_str().unwrap()])
        .env("NODEVICE_SELECT", "1")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("esrp-eval starts");
    let deadline = Instant::now() + Duration::from_secs(120);
    while std::fs::read(&out).map_or(0, |b| b.iter().filter(|&&c| c == b'\n').count()) < 2 {
        assert!(child.try_wait().unwrap().is_none(), "esrp-eval ended early");
        assert!(Instant::now() < deadline, "no records within 120 s");
        std::thread::sleep(Duration::from_millis(20));
    }
    (child, out)
}

/// Whether process `pid` runs (a zombie, exited but not yet reaped by its new parent, does not).
pub(crate) fn alive(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .is_ok_and(|stat| stat.rsplit_once(')').is_some_and(|(_, rest)| !rest.trim_start().starts_with('Z')))
}

/// SIGTERM (a job scheduler, `kill`) ends `esrp-eval` with status 143 and its one line, keeps
/// the records already written whole, and takes down the server it started; SIGKILL too leaves
/// no server (it stops when its stdin pipe closes).
#[test]
fn a_signal_ends_the_run_and_its_server() {
    use std::time::{Duration, Instant};
    for (signal, status) in [("-TERM", Some(143)), ("-KILL", None)] {
        let dir = tempfile::tempdir().expect("a temp dir");
        let (child, out) = eval_with_two_records(dir.path(), &["--agent", "random", "--split", "train"]);
        let servers = children(child.id());
        assert_eq!(servers.len(), 1, "one server started: {servers:?}");
        let sent = Command::new("kill").args([signal, &child.id().to_string()]).status().expect("kill(1) runs");
        assert!(sent.success());
        let output = child.wait_with_output().expect("waitpid");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), status, "{signal}: {}; stderr:\n{stderr}", output.status);
        if status.is_some() {
            assert!(stderr.contains("esrp-eval: terminated"), "{stderr}");
        }
        let deadline = Instant::now() + Duration::from_secs(15);
        while servers.iter().any(|&pid| alive(pid)) && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(50));
        }
        assert!(!servers.iter().any(|&pid| alive(pid)), "{signal}: the server lives on");
        // What was written is whole records.
        let read = read_records(&out).expect("the results read back");
        assert!(!read.torn_tail && read.records.len() >= 2);
    }
}

/// A local server that dies under a run stops the run at once with one message (not one failure
/// per remaining scene), keeping the records written.
#[test]
fn a_dead_local_server_stops_the_run() {
    let dir = tempfile::tempdir().expect("a temp dir");
    let (child, out) =
        eval_with_two_records(dir.path(), &["--agent", "random", "--split", "test", "--episodes-in-flight", "2"]);
    let servers = children(child.id());
    assert_eq!(servers.len(), 1);
    let killed = Command::new("kill").args(["-KILL", &servers[0].to_string()]).status().expect("kill(1) runs");
    assert!(killed.success());
    let output = child.wait_with_output().expect("waitpid");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(stderr.contains("the local esrp-server exited with signal 9 after"), "{stderr}");
    assert!(stderr.contains("re-run the same command to resume"), "{stderr}");
    assert!(stderr.matches("unavailable").count() <= 2, "one message, not one per scene:\n{stderr}");
    let read = read_records(&out).expect("the results read back");
    assert!(!read.torn_tail && read.records.len() >= 2);
}

/// `--tls-ca` and `--tls-domain` reach a server serving TLS with a certificate of its own CA;
/// without them its certificate is not trusted (the system's authorities did not sign it), and
/// with a plain `--server` they are refused before anything runs.
#[test]
fn the_tools_reach_a_tls_server_with_its_ca() {
    let dir = tempfile::tempdir().unwrap();
    let (_, cert_path, key_path) = crate::harness::localhost_certificate(dir.path());
    let server = start(&["--tls-cert", &cert_path, "--tls-key", &key_path]);
    let port = server.address.rsplit(':').next().unwrap();
    let (by_name, by_address) = (format!("https://localhost:{port}"), format!("https://127.0.0.1:{port}"));
    let out = dir.path().join("random.jsonl");
    let run = ["--agent", "random", "--split", "test", "--limit", "1", "--out", out.to_str().unwrap()];
    let ca = ["--tls-ca", cert_path.as_str()];
    ok(eval(&by_name, &[&run[..], &ca].concat()));
    std::fs::remove_file(&out).unwrap();
    ok(eval(&by_address, &[&run[..], &ca, &["--tls-domain", "localhost"]].concat()));
    let demo = Command::new(env!("CARGO_BIN_EXE_esrp-demo"))
        .args(["--server", &by_name, "--scenes", "1"])
        .args(ca)
        .output()
        .expect("esrp-demo runs");
    assert!(demo.status.success(), "{}", String::from_utf8_lossy(&demo.stderr));

    let untrusted = eval(&by_name, &run);
    let stderr = String::from_utf8_lossy(&untrusted.stderr);
    assert!(!untrusted.status.success() && stderr.lines().count() == 1, "{stderr}");
    assert!(stderr.contains("certificate") || stderr.contains("UnknownIssuer"), "{stderr}");
    let plain = eval("http://127.0.0.1:1", &[&run[..], &ca].concat());
    let stderr = String::from_utf8_lossy(&plain.stderr);
    assert!(stderr.contains("are for a server named by an https:// --server URL"), "{stderr}");
    let missing = eval(&by_name, &[&run[..], &["--tls-ca", "/nonexistent/ca.pem"]].concat());
    let stderr = String::from_utf8_lossy(&missing.stderr);
    assert!(stderr.contains("cannot read the CA certificate /nonexistent/ca.pem"), "{stderr}");
}

/// A local server that cannot serve (a dataset that is not there) is said to have exited, with
/// its own reason on stderr, rather than as a refused connection.
#[test]
fn a_local_server_that_cannot_serve_is_said_to_have_exited() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("r.jsonl");
    let output = Command::new(env!("CARGO_BIN_EXE_esrp-eval"))
        .args(["--agent", "random", "--split", "test", "--out", out.to_str().unwrap()])
        .arg("--server-arg=--dataset=/nonexistent/dataset")
        .env("NODEVICE_SELECT", "1")
        .output()
        .expect("esrp-eval runs");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("esrp-server: cannot serve the dataset folder: /nonexistent/dataset"), "{stderr}");
    assert!(stderr.contains("esrp-eval: local server: esrp-server exited with status 1 before it served"), "{stderr}");
}
