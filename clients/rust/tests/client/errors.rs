//! Each `ClientError` variant, from a real bad request to a real server.

use esrp_client::{Action, Client, ClientError, EpisodeOptions, LocalServer};

use crate::harness::{client, start, test_scenes};

#[tokio::test]
async fn each_error_kind_from_a_real_request() {
    let server = start(&["--max-episodes", "2"]);
    let client = client(&server).await;
    let scene = test_scenes(&client, 1).await.remove(0);

    let error = client.create_episode(EpisodeOptions::scene("no-such-scene")).await.unwrap_err();
    assert!(matches!(&error, ClientError::NotFound(m) if m.contains("no-such-scene")), "{error}");
    assert_eq!(error.code(), tonic::Code::NotFound);

    let error = client.create_episode(EpisodeOptions::scene_json("{\"format\": 3}")).await.unwrap_err();
    assert!(matches!(error, ClientError::InvalidArgument(_)), "{error}");

    let (mut short, _) = client.create_episode(EpisodeOptions::scene(&scene).horizon(1)).await.unwrap();
    assert!(short.step(Action::TurnLeft).await.unwrap().truncated);
    let error = short.step(Action::TurnLeft).await.unwrap_err();
    assert!(matches!(&error, ClientError::EpisodeEnded(m) if m.contains("Reset")), "{error}");

    let (unprivileged, _) = client.create_episode(EpisodeOptions::scene(&scene)).await.unwrap();
    let error = unprivileged.privileged_state().await.unwrap_err();
    assert!(matches!(error, ClientError::PermissionDenied(_)), "{error}");

    // Two live episodes: the limit.
    let error = client.create_episode(EpisodeOptions::scene(&scene)).await.unwrap_err();
    assert!(matches!(&error, ClientError::ResourceExhausted(m) if m.contains('2')), "{error}");

    let id = short.id().to_owned();
    short.close().await.unwrap();
    let mut gone = esrp_client::Episode::attach(&client, id, Default::default());
    let error = gone.step(Action::TurnLeft).await.unwrap_err();
    assert!(matches!(error, ClientError::NotFound(_)), "{error}");
    gone.detach();
    unprivileged.close().await.unwrap();
}

#[tokio::test]
async fn connection_errors() {
    let protected = start(&["--token", "right"]);
    let wrong = Client::connect(&protected.address).token("wrong").await.unwrap();
    let error = wrong.server_info().await.unwrap_err();
    assert!(matches!(error, ClientError::Unauthenticated(_)), "{error}");

    let error = Client::connect("not a url").await.unwrap_err();
    assert!(matches!(error, ClientError::Config(_)), "{error}");
    let error = Client::connect(&protected.address).token("line\nbreak").await.unwrap_err();
    assert!(matches!(error, ClientError::Config(_)), "{error}");

    // A port nobody listens on: refused at once when connecting, UNAVAILABLE on a lazy call.
    let closed = {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        format!("http://{}", listener.local_addr().unwrap())
    };
    let error = Client::connect(&closed).await.unwrap_err();
    assert!(matches!(error, ClientError::Transport(_)), "{error}");
    let lazy = Client::connect(&closed).connect_lazy().unwrap();
    let error = lazy.server_info().await.unwrap_err();
    assert!(matches!(error, ClientError::Unavailable(_)), "{error}");
}

/// A server that dies under a client's calls is UNAVAILABLE to every later call, unary or on an
/// open stream (tonic says UNKNOWN "transport error" for a broken connection; the other gRPC
/// clients, and ours, say UNAVAILABLE), so that callers can tell a lost server by its kind.
#[tokio::test]
async fn a_server_that_dies_is_unavailable() {
    let server = start(&[]);
    let client = client(&server).await;
    let scene = test_scenes(&client, 1).await.remove(0);
    let (mut episode, _) = client.create_episode(EpisodeOptions::scene(&scene)).await.unwrap();
    let mut stream = client.episode_stream(4).await.unwrap();
    let (id, _) = {
        stream.create(&EpisodeOptions::scene(&scene)).unwrap();
        let answer = stream.next().await.unwrap().unwrap();
        (answer.episode_id.clone(), answer)
    };
    // Calls in flight when it is killed.
    let mut in_flight = tokio::task::JoinSet::new();
    for _ in 0..4 {
        let client = client.clone();
        let scene = scene.clone();
        in_flight.spawn(async move {
            loop {
                if let Err(error) = client.create_episode(EpisodeOptions::scene(&scene)).await {
                    return error;
                }
            }
        });
    }
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    drop(server); // killed
    while let Some(error) = in_flight.join_next().await {
        let error = error.unwrap();
        assert!(matches!(&error, ClientError::Unavailable(m) if !m.is_empty()), "in flight: {error:?}");
    }
    let error = episode.step(Action::TurnLeft).await.unwrap_err();
    assert!(matches!(error, ClientError::Unavailable(_)), "unary: {error:?}");
    let sent = stream.step(&id, Action::TurnLeft).await;
    let error = match sent {
        Err(error) => error,
        Ok(_) => stream.next().await.unwrap_err(),
    };
    assert!(matches!(error, ClientError::Unavailable(_)), "stream: {error:?}");
    episode.detach();
}

/// An empty scene id is the protocol's "no scene", which the server would answer with some
/// scene of the test split: the client refuses it before anything is sent.
#[tokio::test]
async fn an_empty_scene_id_is_refused_not_replaced() {
    let server = start(&[]);
    let client = client(&server).await;
    let empty = |result: Result<(), ClientError>| {
        let error = result.expect_err("an empty scene id is refused");
        assert!(matches!(&error, ClientError::InvalidArgument(m) if m.contains("scene id is empty")), "{error}");
    };
    empty(client.create_episode(EpisodeOptions::scene("")).await.map(drop));
    let mut stream = client.episode_stream(1).await.unwrap();
    empty(stream.create(&EpisodeOptions::scene("")).map(drop));
    assert_eq!(stream.outstanding(), 0, "nothing was sent");
    let scene = test_scenes(&client, 1).await.remove(0);
    let (mut episode, _) = client.create_episode(EpisodeOptions::scene(&scene)).await.unwrap();
    empty(episode.reset_to_scene("").await.map(drop));
    assert_eq!(client.server_info().await.unwrap().live_episodes, 1, "no episode but the one asked for");
    episode.close().await.unwrap();
}

/// The processes whose command line is exactly `args` (Linux's /proc).
fn processes_running(args: &[&str]) -> usize {
    let wanted: Vec<u8> = args.iter().flat_map(|a| a.bytes().chain([0])).collect();
    std::fs::read_dir("/proc")
        .expect("/proc")
        .flatten()
        .filter(|entry| std::fs::read(entry.path().join("cmdline")).is_ok_and(|cmdline| cmdline == wanted))
        .count()
}

/// A program that prints no listening line in time, or ends without one, is no server: the
/// error says so, and the process is not left behind (killed, reaped).
#[test]
fn a_server_that_does_not_listen_is_stopped_and_said_so() {
    let silent = ["sleep", "101.25"];
    let mut command = std::process::Command::new(silent[0]);
    command.arg(silent[1]);
    let started = std::time::Instant::now();
    let error = LocalServer::spawn_within(command, std::time::Duration::from_millis(500)).unwrap_err().to_string();
    assert!(error.contains("printed no listening line within 500ms: stopped it"), "{error}");
    assert!(started.elapsed() < std::time::Duration::from_secs(5));
    assert_eq!(processes_running(&silent), 0, "the silent process was killed");

    let mut command = std::process::Command::new("sh");
    command.args(["-c", "echo 'esrp-server cannot listen'; exec sleep 102.5"]);
    let error = LocalServer::spawn(command).unwrap_err().to_string();
    assert!(error.contains("did not start (it printed \"esrp-server cannot listen\\n\""), "{error}");
    assert_eq!(processes_running(&["sleep", "102.5"]), 0, "a server that said it did not start is stopped");
}
