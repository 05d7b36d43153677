//! `--listen-unix`: gRPC on a Unix domain socket beside TCP. The same calls answer the same way
//! over both; the token check applies; an old socket file is replaced only when nothing answers
//! on it; the file goes with the server.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use esrp_dataset::dice::Dice;
use esrp_server::proto;
use esrp_server::proto::esrp_client::EsrpClient;
use tonic::transport::{Channel, Endpoint};

use super::harness::{Server, create_request, digest, random_action, scene_ids, step_request};

/// A socket path in `dir`.
fn socket_in(dir: &tempfile::TempDir) -> PathBuf {
    dir.path().join("esrp.sock")
}

/// A client over the socket of `url` (`unix:PATH`).
async fn unix_client(url: &str) -> EsrpClient<Channel> {
    let channel = Endpoint::from_shared(url.to_owned()).expect("a unix: URL").connect().await.expect("connects");
    EsrpClient::new(channel).max_decoding_message_size(256 << 20)
}

/// `esrp-server ARGS` run to its end (it must fail to start): its exit status and stderr.
fn failed_start(args: &[&str]) -> (std::process::ExitStatus, String) {
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_esrp-server"))
        .args(["--listen", "127.0.0.1:0"])
        .args(args)
        .env("NODEVICE_SELECT", "1")
        .env("ESRP_NO_GENERATE_AHEAD", "true")
        .stdin(std::process::Stdio::null())
        .output()
        .expect("the server binary runs");
    (output.status, String::from_utf8_lossy(&output.stderr).into_owned())
}

/// The same scene and actions give the same answers over TCP and over the socket, in one server.
#[tokio::test]
async fn the_socket_answers_as_tcp_does() {
    let dir = tempfile::tempdir().unwrap();
    let path = socket_in(&dir);
    let server = Server::start(&["--listen-unix", path.to_str().unwrap()]);
    let url = server.unix.clone().expect("the server printed its socket");
    assert_eq!(url, format!("unix:{}", path.display()));
    assert_eq!(server.url(), url, "a local server's URL is its socket");
    let mut tcp = server.client().await;
    let mut unix = unix_client(&url).await;
    let scene = scene_ids(&mut tcp, proto::Split::Test, 1).await.remove(0);
    let mut ids = Vec::new();
    for client in [&mut tcp, &mut unix] {
        let created = client.create_episode(create_request(&scene, false)).await.expect("creates").into_inner();
        ids.push(created.episode_id);
    }
    let mut dice = Dice::new(5, 0, 0);
    for _ in 0..12 {
        let action = random_action(&mut dice);
        let over_tcp = tcp.step(step_request(&ids[0], action)).await.expect("steps over TCP").into_inner();
        let over_unix = unix.step(step_request(&ids[1], action)).await.expect("steps over the socket").into_inner();
        assert_eq!(digest(&over_tcp), digest(&over_unix), "action {action}");
    }
    // One server behind both: the episode made over TCP is there over the socket too.
    let info = unix.server_info(proto::ServerInfoRequest {}).await.expect("ServerInfo").into_inner();
    assert_eq!(info.live_episodes, 2);
}

/// The token check applies on the socket as on TCP.
#[tokio::test]
async fn the_socket_checks_tokens() {
    let dir = tempfile::tempdir().unwrap();
    let path = socket_in(&dir);
    let server = Server::start(&["--listen-unix", path.to_str().unwrap(), "--token", "s3cret"]);
    let mut unix = unix_client(server.unix.as_deref().unwrap()).await;
    let refused = unix.server_info(proto::ServerInfoRequest {}).await.expect_err("no token");
    assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{refused:?}");
    let client = esrp_client::Client::connect(server.url().to_owned()).token("s3cret").await.expect("connects");
    assert_eq!(client.server_info().await.expect("with the token").live_episodes, 0);
}

/// Waits (at most 30 s) for the server to end after SIGTERM.
fn terminate(server: &mut Server) -> std::process::ExitStatus {
    let killed = std::process::Command::new("kill").args(["-TERM", &server.pid().to_string()]).status().unwrap();
    assert!(killed.success());
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Some(status) = server.try_wait() {
            return status;
        }
        assert!(Instant::now() < deadline, "the server did not stop within 30 s of SIGTERM");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// A socket file nothing answers on (a killed server's) is replaced; one a live server answers on
/// is refused, as is any other file, which is left as it was; a stopped server removes its file.
#[test]
fn old_socket_files_are_replaced_live_ones_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = socket_in(&dir);
    let arg = path.to_str().unwrap();
    // A socket file that nothing listens on any more.
    drop(std::os::unix::net::UnixListener::bind(&path).unwrap());
    assert!(path.exists());
    let mut first = Server::start(&["--listen-unix", arg]);
    assert!(std::os::unix::net::UnixStream::connect(&path).is_ok(), "the new server answers on the old path");

    let (status, stderr) = failed_start(&["--listen-unix", arg]);
    assert!(!status.success());
    assert!(stderr.contains("another server is listening on this socket"), "{stderr}");
    assert!(std::os::unix::net::UnixStream::connect(&path).is_ok(), "the live server's socket is untouched");

    assert!(terminate(&mut first).success());
    assert!(!path.exists(), "a server stopped by SIGTERM removes its socket file");

    let file = dir.path().join("notes.txt");
    std::fs::write(&file, "keep me").unwrap();
    let (status, stderr) = failed_start(&["--listen-unix", file.to_str().unwrap()]);
    assert!(!status.success());
    assert!(stderr.contains("exists and is not a socket"), "{stderr}");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "keep me");
}

/// Paths a socket cannot have, and TLS (the socket serves plain HTTP/2), are refused with a
/// message that says what to change.
#[test]
fn bad_socket_settings_are_refused_clearly() {
    let long = format!("/tmp/{}.sock", "x".repeat(120));
    let (status, stderr) = failed_start(&["--listen-unix", &long]);
    assert!(!status.success());
    assert!(stderr.contains("must be shorter than 108 bytes"), "{stderr}");
    assert!(!Path::new(&long).exists());

    let (status, stderr) = failed_start(&["--listen-unix", "/no/such/folder/esrp.sock"]);
    assert!(!status.success());
    assert!(stderr.contains("/no/such/folder/esrp.sock") && stderr.contains("cannot listen"), "{stderr}");

    let (status, stderr) = failed_start(&["--listen-unix", "/tmp/x.sock", "--tls-cert", "c.pem", "--tls-key", "k.pem"]);
    assert!(!status.success());
    assert!(stderr.contains("--listen-unix") && stderr.contains("--tls-cert"), "{stderr}");
}
