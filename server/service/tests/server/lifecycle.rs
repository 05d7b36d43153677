//! Episode and process lifetimes: streams take their episodes with them, idle episodes are
//! reaped, the server holds a thousand live episodes at once, and SIGTERM/SIGINT (and SIGHUP)
//! end it with status 0 whatever it is doing.

use std::time::{Duration, Instant};

use esrp_server::proto;
use esrp_server::proto::stream_request::Request as Rq;
use esrp_server::proto::stream_response::Response as Rs;
use tokio_stream::StreamExt;

use super::harness::{Server, create_request, live_episodes, scene_ids, step_request};

/// Polls until the server reports `want` live episodes, for at most ten seconds.
async fn wait_for_live(client: &mut proto::esrp_client::EsrpClient<tonic::transport::Channel>, want: u32) -> u32 {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let live = live_episodes(client).await;
        if live == want || Instant::now() > deadline {
            return live;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test]
async fn a_client_that_disconnects_mid_stream_leaves_no_episode() {
    let mut server = Server::start(&[]);
    let mut client = server.client().await;
    let scene = scene_ids(&mut client, proto::Split::Test, 1).await.remove(0);
    // One episode made by a unary call outlives the stream.
    client.create_episode(create_request(&scene, false)).await.unwrap();
    {
        let mut streaming = server.client().await;
        let (tx, rx) = tokio::sync::mpsc::channel::<proto::StreamRequest>(64);
        let mut inbound =
            streaming.step_stream(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
        let mut ids = Vec::new();
        for i in 0..3 {
            tx.send(proto::StreamRequest { request_id: i, request: Some(Rq::Create(create_request(&scene, false))) })
                .await
                .unwrap();
            match inbound.next().await.unwrap().unwrap().response {
                Some(Rs::Created(c)) => ids.push(c.episode_id),
                other => panic!("expected Created, got {other:?}"),
            }
        }
        // Steps in flight when the client vanishes.
        for (i, id) in ids.iter().enumerate() {
            tx.send(proto::StreamRequest { request_id: 10 + i as u64, request: Some(Rq::Step(step_request(id, 2))) })
                .await
                .unwrap();
        }
        assert_eq!(live_episodes(&mut client).await, 4);
        // Drop the stream and its connection without closing anything.
    }
    assert_eq!(wait_for_live(&mut client, 1).await, 1, "the stream's three episodes are closed with it");
    assert!(server.is_running());
}

#[tokio::test]
async fn idle_episodes_are_reaped() {
    let server = Server::start(&["--idle-timeout-seconds", "1"]);
    let mut client = server.client().await;
    let scene = scene_ids(&mut client, proto::Split::Test, 1).await.remove(0);
    let episode = client.create_episode(create_request(&scene, false)).await.unwrap().into_inner().episode_id;
    assert_eq!(wait_for_live(&mut client, 0).await, 0, "an untouched episode is closed after the idle timeout");
    let status = client.step(step_request(&episode, 0)).await.expect_err("a reaped episode is gone");
    assert_eq!(status.code(), tonic::Code::NotFound);
}

/// A thousand live episodes at once, each stepped; the thousand-and-first is refused with
/// RESOURCE_EXHAUSTED until one closes.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_thousand_live_episodes() {
    const N: usize = 1000;
    let mut server = Server::start(&["--max-episodes", "1000"]);
    let mut client = server.client().await;
    let scenes = scene_ids(&mut client, proto::Split::Test, 10).await;
    let mut tasks = Vec::new();
    for t in 0..8 {
        let mut client = server.client().await;
        let scenes = scenes.clone();
        tasks.push(tokio::spawn(async move {
            let mut ids = Vec::new();
            for i in (t..N).step_by(8) {
                let created = client.create_episode(create_request(&scenes[i % scenes.len()], false)).await.unwrap();
                ids.push(created.into_inner().episode_id);
            }
            ids
        }));
    }
    let mut ids = Vec::new();
    for task in tasks {
        ids.extend(task.await.unwrap());
    }
    assert_eq!(ids.len(), N);
    assert_eq!(live_episodes(&mut client).await, N as u32);
    for chunk in ids.chunks(250) {
        let steps = chunk.iter().map(|id| step_request(id, 2)).collect();
        let responses = client
            .step_batch(proto::StepBatchRequest { steps, resets: Vec::new() })
            .await
            .unwrap()
            .into_inner()
            .responses;
        assert_eq!(responses.len(), chunk.len());
        assert!(
            responses
                .iter()
                .all(|r| r.observation.as_ref().unwrap().ego_rgb.as_ref().unwrap().data.len() == 128 * 128 * 3)
        );
    }
    let refused = client.create_episode(create_request(&scenes[0], false)).await.expect_err("the limit holds");
    assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
    assert!(refused.message().contains("--max-episodes"), "{refused:?}");
    client.close_episode(proto::CloseEpisodeRequest { episode_id: ids[0].clone() }).await.unwrap();
    client.create_episode(create_request(&scenes[0], false)).await.expect("room for one more after a close");
    if let Some(rss) = server.resident_bytes() {
        eprintln!("server resident memory with {N} live episodes: {:.1} MiB", rss as f64 / (1 << 20) as f64);
    }
    assert!(server.is_running());
}

/// What a client does between the server's start and its SIGTERM.
#[derive(Clone, Copy, Debug)]
enum Work {
    /// Nothing: the signal comes right after the "listening" line (the renderer may still be
    /// starting).
    Nothing,
    /// One ListScenes call, no episode.
    ListScenes,
    /// Creates an episode and takes five steps; the episode is still live at the signal.
    FiveSteps,
    /// Creates episodes and sends steps whose answers are not awaited: steps are in flight.
    StepsInFlight,
}

const WORK: [Work; 4] = [Work::Nothing, Work::ListScenes, Work::FiveSteps, Work::StepsInFlight];

/// A server process started for one SIGTERM cycle, with its stdout and stderr drained.
struct Signalled {
    child: std::process::Child,
    /// The server's stdin (`--stop-on-stdin-close`: it stops when this is dropped).
    stdin: Option<std::process::ChildStdin>,
    address: String,
    stderr: std::thread::JoinHandle<String>,
}

impl Signalled {
    fn start(backend: &str) -> Signalled {
        Signalled::start_with(&["--render-backend", backend])
    }

    /// A server started with `args`, SIGHUP at its default.
    fn start_with(args: &[&str]) -> Signalled {
        Signalled::start_with_hangup(args, Hangup::Default)
    }

    /// A server started with `args` and SIGHUP as `hangup` says, whatever this process's own
    /// disposition (a test run under `nohup` passes SIGHUP on ignored).
    fn start_with_hangup(args: &[&str], hangup: Hangup) -> Signalled {
        use std::io::{BufRead, BufReader, Read};
        use std::process::Stdio;
        let mut command = esrp_client::LocalServer::command(Some(env!("CARGO_BIN_EXE_esrp-server").into()), args)
            .expect("the server command");
        set_hangup(&mut command, hangup);
        command
            .env("NODEVICE_SELECT", "1")
            .env("ESRP_LOG", "warn")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let mut child = command.spawn().expect("the server binary starts");
        let stdin = child.stdin.take();
        let mut stdout = BufReader::new(child.stdout.take().expect("piped stdout"));
        // The server's own lines start with `esrp-server `: log lines before them are passed over.
        let mut line = String::new();
        while !line.starts_with("esrp-server ") {
            line.clear();
            assert!(stdout.read_line(&mut line).expect("the server's output") > 0, "the server printed no address");
        }
        let address = line.trim().strip_prefix("esrp-server listening on ").unwrap_or_else(|| panic!("{line:?}"));
        let address = format!("http://{address}");
        // Keep both pipes drained (and open) until the process ends.
        std::thread::spawn(move || std::io::copy(&mut stdout, &mut std::io::sink()));
        let mut stderr = child.stderr.take().expect("piped stderr");
        let stderr = std::thread::spawn(move || {
            let mut text = String::new();
            let _ = stderr.read_to_string(&mut text);
            text
        });
        Signalled { child, stdin, address, stderr }
    }

    /// Sends SIGTERM and waits (at most 30 s) for the process to end; its status and stderr.
    fn terminate(self) -> (std::process::ExitStatus, String) {
        self.signal("-TERM")
    }

    /// Sends `signal` (`kill`'s spelling: `-TERM`, `-HUP`).
    fn send(&self, signal: &str) {
        let killed = std::process::Command::new("kill")
            .args([signal, &self.child.id().to_string()])
            .status()
            .expect("kill(1) runs");
        assert!(killed.success(), "kill {signal} failed");
    }

    /// Sends `signal` (`kill`'s spelling: `-TERM`, `-HUP`) and waits (at most 30 s) for the
    /// process to end; its status and stderr.
    fn signal(mut self, signal: &str) -> (std::process::ExitStatus, String) {
        self.send(signal);
        let deadline = Instant::now() + Duration::from_secs(30);
        let status = loop {
            if let Some(status) = self.child.try_wait().expect("waitpid") {
                break status;
            }
            if Instant::now() > deadline {
                let _ = self.child.kill();
                let status = self.child.wait().expect("waitpid");
                let stderr = self.stderr.join().unwrap_or_default();
                panic!("the server did not exit within 30 s of {signal} ({status}); stderr:\n{stderr}");
            }
            std::thread::sleep(Duration::from_millis(10));
        };
        (status, self.stderr.join().unwrap_or_default())
    }
}

/// How a server's parent leaves SIGHUP to it: at its default (a terminal's or SSH session's
/// child), or ignored (started under `nohup`).
#[derive(Clone, Copy, Debug)]
enum Hangup {
    Default,
    Ignored,
}

/// Makes `command`'s process start with SIGHUP as `hangup` says.
#[allow(unsafe_code)]
fn set_hangup(command: &mut std::process::Command, hangup: Hangup) {
    use std::os::unix::process::CommandExt;
    let disposition = match hangup {
        Hangup::Default => libc::SIG_DFL,
        Hangup::Ignored => libc::SIG_IGN,
    };
    // SAFETY: between fork and exec the child runs only signal(2), which is async-signal-safe
    // and sets nothing but its own disposition of SIGHUP.
    unsafe {
        command.pre_exec(move || {
            if libc::signal(libc::SIGHUP, disposition) == libc::SIG_ERR {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

async fn do_work(address: &str, work: Work) {
    if let Work::Nothing = work {
        return;
    }
    let mut client = proto::esrp_client::EsrpClient::connect(address.to_owned()).await.expect("the client connects");
    let scene = scene_ids(&mut client, proto::Split::Test, 1).await.remove(0);
    match work {
        Work::Nothing | Work::ListScenes => {}
        Work::FiveSteps => {
            let id = client.create_episode(create_request(&scene, false)).await.unwrap().into_inner().episode_id;
            for action in [2, 2, 1, 2, 3] {
                client.step(step_request(&id, action)).await.expect("a step");
            }
        }
        Work::StepsInFlight => {
            for _ in 0..3 {
                let id = client.create_episode(create_request(&scene, false)).await.unwrap().into_inner().episode_id;
                for _ in 0..4 {
                    let mut client = client.clone();
                    let request = step_request(&id, 2);
                    // Not awaited: the answer (or the error of a closing server) is dropped.
                    tokio::spawn(async move { client.step(request).await });
                }
            }
            // Let the steps reach the server.
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

/// Runs `cycles` start → work → SIGTERM cycles on `backend` (rotating through [`WORK`]) and
/// returns a description of each one that did not exit with status 0.
async fn sigterm_cycles(backend: &str, cycles: usize) -> Vec<String> {
    sigterm_cycles_with(&["--render-backend", backend], cycles).await
}

/// [`sigterm_cycles`] of a server started with `args`.
async fn sigterm_cycles_with(args: &[&str], cycles: usize) -> Vec<String> {
    let mut failures = Vec::new();
    for cycle in 0..cycles {
        let work = WORK[cycle % WORK.len()];
        let server = Signalled::start_with(args);
        do_work(&server.address, work).await;
        let (status, stderr) = tokio::task::spawn_blocking(move || server.terminate()).await.unwrap();
        if !status.success() {
            let tail: String = stderr.lines().rev().take(5).collect::<Vec<_>>().join(" | ");
            failures.push(format!("cycle {cycle} ({work:?}): {status}; stderr ends: {tail}"));
        }
    }
    failures
}

/// Cycles per backend: `ESRP_SIGTERM_CYCLES` (the release record used 100), else 15.
fn cycles() -> usize {
    std::env::var("ESRP_SIGTERM_CYCLES").ok().and_then(|v| v.parse().ok()).unwrap_or(15)
}

/// The graceful shutdown of docs/server.md: SIGTERM ends the server with status 0 every time, on both
/// backends, with no client, after ListScenes alone, with live episodes and with steps in
/// flight. Before the fix, OpenGL (llvmpipe) died with SIGSEGV/SIGABRT in about one run in ten:
/// the render thread dropped the GL device while the main thread ran the process's exit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_exits_with_status_zero_every_time() {
    let cycles = cycles();
    let mut failures = Vec::new();
    for backend in ["gl", "vulkan"] {
        let started = Instant::now();
        let failed = sigterm_cycles(backend, cycles).await;
        eprintln!(
            "{backend}: {} of {cycles} SIGTERM cycles exited 0 ({:.1} s)",
            cycles - failed.len(),
            started.elapsed().as_secs_f64()
        );
        failures.extend(failed.into_iter().map(|f| format!("{backend}: {f}")));
    }
    assert!(failures.is_empty(), "SIGTERM did not end the server with status 0:\n{}", failures.join("\n"));
}

/// The same with batches in flight (`--render-pipeline 2`): the render threads hand their
/// batches to readback threads, which finish and answer them before the renderer goes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_with_batches_in_flight_exits_with_status_zero() {
    let cycles = cycles().div_ceil(3);
    let mut failures = Vec::new();
    for backend in ["gl", "vulkan"] {
        let args = ["--render-backend", backend, "--render-pipeline", "2"];
        failures.extend(sigterm_cycles_with(&args, cycles).await.into_iter().map(|f| format!("{backend}: {f}")));
    }
    assert!(failures.is_empty(), "SIGTERM did not end the server with status 0:\n{}", failures.join("\n"));
}

/// A client that keeps a stream open, idle, does not hold the server up: SIGTERM ends it with
/// status 0 once the shutdown grace is over (without the bound it waited for the client for
/// ever; this test then fails after 30 s), and the client's stream ends with an error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_open_stream_does_not_hold_up_shutdown() {
    let server = Signalled::start_with(&["--shutdown-grace-ms", "500"]);
    let mut client = proto::esrp_client::EsrpClient::connect(server.address.clone()).await.expect("connects");
    let scene = scene_ids(&mut client, proto::Split::Test, 1).await.remove(0);
    let (tx, rx) = tokio::sync::mpsc::channel::<proto::StreamRequest>(4);
    let mut inbound = client.step_stream(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
    tx.send(proto::StreamRequest { request_id: 1, request: Some(Rq::Create(create_request(&scene, false))) })
        .await
        .unwrap();
    assert!(matches!(inbound.next().await.unwrap().unwrap().response, Some(Rs::Created(_))));
    // The stream stays open (`tx` lives) and idle through the signal.
    let signalled = Instant::now();
    let (status, stderr) = tokio::task::spawn_blocking(move || server.terminate()).await.unwrap();
    let took = signalled.elapsed();
    assert!(status.success(), "SIGTERM with an open stream: {status}; stderr:\n{stderr}");
    assert!(took < Duration::from_secs(10), "the server took {took:?} to exit with a 0.5 s grace");
    let end = tokio::time::timeout(Duration::from_secs(5), inbound.next()).await.expect("the stream ends");
    assert!(!matches!(end, Some(Ok(_))), "no answer after the server stopped: {end:?}");
    drop(tx);
}

/// With `--stop-on-stdin-close` (which `LocalServer` passes), the end of stdin is a graceful
/// shutdown: a tool that dies without stopping its server (SIGKILL) takes the server with it.
#[tokio::test]
async fn the_server_stops_when_its_stdin_closes() {
    let mut server = Signalled::start_with(&["--shutdown-grace-ms", "500"]);
    let mut client = proto::esrp_client::EsrpClient::connect(server.address.clone()).await.expect("connects");
    assert!(!scene_ids(&mut client, proto::Split::Test, 1).await.is_empty(), "it serves with stdin open");
    let closed = Instant::now();
    drop(server.stdin.take());
    let (status, stderr) = tokio::task::spawn_blocking(move || {
        let deadline = Instant::now() + Duration::from_secs(20);
        while server.child.try_wait().expect("waitpid").is_none() {
            if Instant::now() > deadline {
                let _ = server.child.kill();
                break;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        (server.child.wait().expect("waitpid"), server.stderr.join().unwrap_or_default())
    })
    .await
    .unwrap();
    assert!(status.success(), "stdin closed: {status}; stderr:\n{stderr}");
    assert!(closed.elapsed() < Duration::from_secs(10), "the server took {:?} to stop", closed.elapsed());
}

/// A SIGTERM or SIGINT sent as soon as the "listening" line is read is a graceful exit
/// (status 0), not death by the signal: the handlers are installed before the line is printed.
#[tokio::test]
async fn a_signal_right_after_listening_is_a_graceful_exit() {
    for signal in ["-TERM", "-INT", "-TERM"] {
        let mut server = Signalled::start("gl");
        let sent = std::process::Command::new("kill")
            .args([signal, &server.child.id().to_string()])
            .status()
            .expect("kill(1) runs");
        assert!(sent.success());
        let status = tokio::task::spawn_blocking(move || {
            let status = server.child.wait().expect("waitpid");
            (status, server.stderr.join().unwrap_or_default())
        })
        .await
        .unwrap();
        assert!(status.0.success(), "kill {signal} right after listening: {}; stderr:\n{}", status.0, status.1);
    }
}

/// SIGHUP (the terminal or SSH session that started the server went away) is a graceful shutdown
/// too: status 0, the open episode recorded, the Unix socket file removed. It used to end the
/// process at once (status 129), losing the record and leaving the socket file behind.
#[tokio::test]
async fn sighup_is_a_graceful_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let (socket, records) = (dir.path().join("esrp.sock"), dir.path().join("records"));
    let server = Signalled::start_with(&[
        "--listen-unix",
        socket.to_str().unwrap(),
        "--records",
        records.to_str().unwrap(),
        "--record",
        "all",
    ]);
    do_work(&server.address, Work::FiveSteps).await;
    let (status, stderr) = tokio::task::spawn_blocking(move || server.signal("-HUP")).await.unwrap();
    assert!(status.success(), "SIGHUP: {status}; stderr:\n{stderr}");
    assert!(!socket.exists(), "the socket file is removed");
    let read = esrp_client::results::read_records(&records.join("anonymous.jsonl")).expect("the record is written");
    assert_eq!(read.records.len(), 1, "{:?}", read.records);
    assert_eq!(read.records[0].steps, 5, "{:?}", read.records[0]);
}

/// A server started ignoring SIGHUP (`nohup esrp-server ...`) keeps it ignored, as whoever started
/// it asked: it serves on after one, and stops on SIGTERM.
#[tokio::test]
async fn sighup_stays_ignored_where_the_server_was_started_ignoring_it() {
    let server = Signalled::start_with_hangup(&[], Hangup::Ignored);
    server.send("-HUP");
    do_work(&server.address, Work::FiveSteps).await;
    let (status, stderr) = tokio::task::spawn_blocking(move || server.terminate()).await.unwrap();
    assert!(status.success(), "SIGTERM after an ignored SIGHUP: {status}; stderr:\n{stderr}");
}

/// A CreateEpisode whose client gives up (its deadline expires) before the answer is sent
/// leaves no episode behind: the client never learns the id, so nothing could close it.
#[tokio::test]
async fn an_abandoned_create_leaves_no_episode() {
    let server = Server::start(&[]);
    // A small receive window: the answer (about 4.3 MB) travels for a while, in steps the
    // client reads, so that many deadlines expire while it travels; once the server has
    // written all of it, only the last 64 KiB are in flight.
    let channel = tonic::transport::Endpoint::from_shared(server.address.clone())
        .unwrap()
        .initial_stream_window_size(65_535)
        .initial_connection_window_size(65_535)
        .connect()
        .await
        .expect("the client connects");
    let mut client = proto::esrp_client::EsrpClient::new(channel).max_decoding_message_size(256 << 20);
    let scene = scene_ids(&mut client, proto::Split::Test, 1).await.remove(0);
    let request = || proto::CreateEpisodeRequest {
        sensors: Some(proto::Sensors {
            ego_depth: true,
            ego_segmentation: true,
            current_top_down: true,
            resolution: 512,
        }),
        ..create_request(&scene, false)
    };
    // How long one create takes here, at best (the scene is compiled and uploaded by then).
    let mut took = Duration::MAX;
    for _ in 0..4 {
        let started = Instant::now();
        let created = client.create_episode(request()).await.expect("a create").into_inner();
        took = took.min(started.elapsed());
        client.close_episode(proto::CloseEpisodeRequest { episode_id: created.episode_id }).await.unwrap();
    }
    // Deadlines spread around that time, so that some expire while the server renders, some
    // while the answer travels, some after it arrived.
    let (mut abandoned, mut answered) = (0, 0);
    for i in 0..60u32 {
        let mut call = tonic::Request::new(request());
        call.set_timeout(took * (20 + 4 * i) / 100);
        match client.create_episode(call).await {
            Ok(created) => {
                answered += 1;
                let episode_id = created.into_inner().episode_id;
                client
                    .close_episode(proto::CloseEpisodeRequest { episode_id })
                    .await
                    .expect("an episode whose id was answered is live");
            }
            Err(status) => {
                assert!(matches!(status.code(), tonic::Code::DeadlineExceeded | tonic::Code::Cancelled), "{status:?}");
                abandoned += 1;
            }
        }
    }
    eprintln!("{abandoned} creates abandoned, {answered} answered");
    assert!(abandoned > 0, "some deadlines expired");
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(live_episodes(&mut client).await, 0, "no abandoned create left its episode");
}
