//! A counted attempt at a challenge scene is spent once its episode is used, whatever its
//! client does with the create's answer afterwards: a raw HTTP/2 client holds the answer with
//! flow control, reads the episode id from its first bytes, plays the episode on another
//! connection, then resets the create. Only a create whose episode was never used gives its
//! attempt back.

use std::time::Duration;

use bytes::Bytes;
use esrp_server::proto;
use prost::Message;
use tonic::Code;

use super::challenge::{Authed, client, create, play_out, records, refused, start};
use super::harness::Server;

/// A CreateEpisode sent on a raw HTTP/2 connection whose stream window is 64 bytes: the
/// server can send the answer's first 64 bytes and no more, and the client never opens the
/// window further.
struct HeldCreate {
    /// The create's request stream, to reset.
    send: h2::SendStream<Bytes>,
    /// The answer's body, never read further.
    _body: h2::RecvStream,
    /// The connection: the create lives while it does.
    _connection: tokio::task::JoinHandle<()>,
    /// The episode id read from the answer's first bytes.
    episode_id: String,
}

/// A raw CreateEpisode sent whole on a new HTTP/2 connection whose streams start with
/// `window` bytes of flow-control window: the answer's future, the request's stream (to reset)
/// and the connection's task.
struct RawCreate {
    response: h2::client::ResponseFuture,
    send: h2::SendStream<Bytes>,
    connection: tokio::task::JoinHandle<()>,
}

async fn send_create(server: &Server, secret: &str, request: proto::CreateEpisodeRequest, window: u32) -> RawCreate {
    let authority = server.address.trim_start_matches("http://").to_owned();
    let tcp = tokio::net::TcpStream::connect(&authority).await.expect("the server listens");
    let (send_request, connection) = h2::client::Builder::new()
        .initial_window_size(window)
        .initial_connection_window_size(window.max(65_535))
        .handshake::<_, Bytes>(tcp)
        .await
        .expect("HTTP/2");
    let connection = tokio::spawn(async move {
        let _ = connection.await;
    });
    let mut send_request = send_request.ready().await.expect("the connection is ready");
    let call = http::Request::builder()
        .method("POST")
        .uri(format!("http://{authority}/esrp.v1.Esrp/CreateEpisode"))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .header("authorization", format!("Bearer {secret}"))
        .body(())
        .unwrap();
    let (response, mut send) = send_request.send_request(call, false).expect("the create is sent");
    let message = request.encode_to_vec();
    let mut framed = vec![0u8];
    framed.extend_from_slice(&(message.len() as u32).to_be_bytes());
    framed.extend_from_slice(&message);
    send.send_data(Bytes::from(framed), true).expect("the request's body is sent");
    RawCreate { response, send, connection }
}

/// A create of `scene` by `client` once its attempt has come back (within 10 s); its episode id.
/// Panics with `lost` if the attempt stays spent.
async fn create_when_given_back(client: &mut Authed, scene: &str, lost: &str) -> String {
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        match client.create_episode(create(scene, false)).await {
            Ok(created) => return created.into_inner().episode_id,
            Err(status) if status.code() == Code::FailedPrecondition && std::time::Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Err(status) => panic!("{lost}: {status:?}"),
        }
    }
}

/// The answer carries the paper's 128 px images (about 100 kB) after the id and the spec: the
/// server takes it as delivered once the client's window lets the images leave, and a 64-byte
/// window holds back more than the id.
async fn held_create(server: &Server, secret: &str, scene: &str) -> HeldCreate {
    let request = proto::CreateEpisodeRequest { sensors: None, ..create(scene, false) };
    let RawCreate { response, send, connection } = send_create(server, secret, request, 64).await;
    let response = tokio::time::timeout(Duration::from_secs(60), response).await.expect("headers come").unwrap();
    assert_eq!(response.status(), 200);
    let mut body = response.into_body();
    // gRPC frame (5 bytes), then field 1 (tag 0x0a, length 32) and the id's 32 hex digits.
    let mut head = Vec::new();
    while head.len() < 39 {
        let chunk = tokio::time::timeout(Duration::from_secs(60), body.data()).await.expect("data comes");
        head.extend_from_slice(&chunk.expect("the answer has begun").expect("a data frame"));
    }
    assert!(head.len() <= 64, "the window holds the answer back: {} bytes arrived", head.len());
    assert_eq!(head[5..7], [0x0a, 32], "the answer begins with the episode id");
    let episode_id = String::from_utf8(head[7..39].to_vec()).unwrap();
    // The body is kept, not read: its window stays shut.
    HeldCreate { send, _body: body, _connection: connection, episode_id }
}

/// A CreateEpisode on a raw HTTP/2 connection, reset by its client `after` it was sent: the
/// server drops the call wherever it is (claiming the attempt, building the episode), before
/// any answer.
async fn abandoned_create(server: &Server, secret: &str, scene: &str, after: Duration) {
    // Large images with every sensor: the build renders long enough for the reset to land in it.
    let sensors = proto::Sensors { resolution: 512, ego_depth: true, ego_segmentation: true, current_top_down: true };
    let request = proto::CreateEpisodeRequest { sensors: Some(sensors), ..create(scene, false) };
    let RawCreate { mut send, connection, .. } = send_create(server, secret, request, 65_535).await;
    tokio::time::sleep(after).await;
    send.send_reset(h2::Reason::CANCEL);
    tokio::time::sleep(Duration::from_millis(20)).await;
    connection.abort();
}

/// A create dropped while the server claims its attempt or builds its episode (its client gave
/// up before any answer) leaves no episode, and gives the attempt back: the scene can be played.
#[tokio::test]
async fn a_create_abandoned_before_its_answer_gives_its_attempt_back() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), &["--challenge-observations", "full"]);
    let mut bob = client(&server, "bob-secret").await;
    for (index, after) in [2u64, 5, 10].into_iter().enumerate() {
        let scene = format!("challenge/{index:05}");
        abandoned_create(&server, "bob-secret", &scene, Duration::from_millis(after)).await;
        let lost = format!("{scene}, reset {after} ms after its create: the attempt is lost");
        let episode_id = create_when_given_back(&mut bob, &scene, &lost).await;
        bob.close_episode(proto::CloseEpisodeRequest { episode_id }).await.unwrap();
    }
}

/// Each moment a create's answer may be reset at: before its episode was used, after a step,
/// after the horizon. Once used, the attempt stays spent and exactly one record is written.
#[tokio::test]
async fn a_create_reset_after_its_episode_was_used_keeps_the_attempt_spent() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), &[]);
    let mut bob = client(&server, "bob-secret").await;

    // Never used: the reset gives the attempt back, and nothing is recorded.
    let held = held_create(&server, "bob-secret", "challenge/00000").await;
    let HeldCreate { mut send, .. } = held;
    send.send_reset(h2::Reason::CANCEL);
    let again = create_when_given_back(&mut bob, "challenge/00000", "an unused create's attempt comes back").await;
    assert!(records(dir.path(), "bob").is_empty(), "an unused create is not a run");
    bob.close_episode(proto::CloseEpisodeRequest { episode_id: again }).await.unwrap();
    assert_eq!(records(dir.path(), "bob").len(), 1, "the answered create, closed, is recorded");

    // Used (one step), then reset: the attempt stays spent; the run is recorded once.
    let held = held_create(&server, "bob-secret", "challenge/00001").await;
    let step = proto::StepRequest { episode_id: held.episode_id.clone(), action: 2, include_goal: false };
    bob.step(step).await.expect("the held create's episode steps");
    let HeldCreate { mut send, episode_id, .. } = held;
    send.send_reset(h2::Reason::CANCEL);
    tokio::time::sleep(Duration::from_millis(300)).await;
    refused(bob.create_episode(create("challenge/00001", false)).await, Code::FailedPrecondition, "already played");
    let goal = bob.get_goal(proto::GetGoalRequest { episode_id: episode_id.clone() }).await;
    assert!(goal.is_ok(), "the used episode lives on after its create was reset: {goal:?}");
    bob.close_episode(proto::CloseEpisodeRequest { episode_id }).await.unwrap();
    let written: Vec<_> = records(dir.path(), "bob").into_iter().filter(|r| r.scene_id == "challenge/00001").collect();
    assert_eq!(written.len(), 1, "one record of the used attempt");
    assert_eq!((written[0].actions.as_slice(), written[0].counted), (&[2u8][..], Some(true)));

    // Played to its horizon, then reset: still one record, the attempt still spent.
    let held = held_create(&server, "bob-secret", "challenge/00002").await;
    let steps = play_out(&mut bob, &held.episode_id).await;
    let HeldCreate { mut send, episode_id, .. } = held;
    send.send_reset(h2::Reason::CANCEL);
    tokio::time::sleep(Duration::from_millis(300)).await;
    refused(bob.create_episode(create("challenge/00002", false)).await, Code::FailedPrecondition, "already played");
    // Closing the ended episode records nothing more: its last step wrote its record.
    bob.close_episode(proto::CloseEpisodeRequest { episode_id }).await.expect("the ended episode lives on");
    let written: Vec<_> = records(dir.path(), "bob").into_iter().filter(|r| r.scene_id == "challenge/00002").collect();
    assert_eq!(written.len(), 1, "one record of the attempt played to its horizon");
    assert_eq!((written[0].steps, written[0].end.as_str()), (steps, "horizon"));
}

/// Every record the server writes is signed with its key (generated in the records folder), and
/// says what the episode served and the reward weights it played with; the folder lists the
/// challenge's scenes for the leaderboard.
#[tokio::test]
async fn records_are_signed_and_the_challenge_scenes_listed() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), &[]);
    let mut bob = client(&server, "bob-secret").await;
    let episode = bob.create_episode(create("challenge/00001", false)).await.expect("created").into_inner();
    bob.close_episode(proto::CloseEpisodeRequest { episode_id: episode.episode_id }).await.unwrap();
    let folder = dir.path().join("records");
    let key = esrp_server::records::RecordsKey::load_or_create(&folder, None).expect("the server's key");
    let text = std::fs::read_to_string(folder.join("bob.jsonl")).unwrap();
    let line = text.lines().next().expect("one record");
    assert!(key.verify(line.as_bytes()), "the server's record verifies: {line}");
    let forged = line.replace("\"counted\":true", "\"counted\":false");
    assert_ne!(forged, line);
    assert!(!key.verify(forged.as_bytes()), "a changed record does not");
    let record = &records(dir.path(), "bob")[0];
    assert_eq!(record.observations.as_deref(), Some("paper"));
    let weights = record.reward_weights.as_ref().expect("the reward weights are recorded");
    assert_eq!(weights.get("success").and_then(|v| v.as_f64()), Some(10.0));
    assert!(record.signature.as_ref().is_some_and(|s| s.len() == 64));

    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(folder.join("challenge-scenes.json")).unwrap()).unwrap();
    assert_eq!(manifest["schema"], "esrp.challenge-scenes/v1");
    assert_eq!(manifest["observations"]["challenge"], "paper");
    assert_eq!(manifest["dataset_hash"].as_str(), record.dataset_hash.as_deref());
    let scenes = manifest["scenes"].as_array().expect("scenes");
    assert_eq!(scenes.len(), 3, "every challenge scene (--challenge-scenes 3)");
    assert!(scenes.iter().all(|s| s["id"].as_str().is_some_and(|id| id.starts_with("challenge/"))));
    assert!(scenes.iter().all(|s| s["objects"].as_u64().is_some_and(|n| n > 0)));
}

/// Reads a protobuf varint at `*at` of `bytes`, moving `*at` past it.
fn varint(bytes: &[u8], at: &mut usize) -> u64 {
    let mut value = 0u64;
    for shift in (0..64).step_by(7) {
        let byte = bytes[*at];
        *at += 1;
        value |= u64::from(byte & 0x7f) << shift;
        if byte & 0x80 == 0 {
            break;
        }
    }
    value
}

/// The length-delimited field `field` of the message in `bytes[start..]`: its payload's start
/// and length. Every field before it must be length-delimited.
fn field_at(bytes: &[u8], start: usize, field: u64) -> (usize, usize) {
    let mut at = start;
    loop {
        let tag = varint(bytes, &mut at);
        assert_eq!(tag & 7, 2, "a length-delimited field");
        let len = varint(bytes, &mut at) as usize;
        if tag >> 3 == field {
            return (at, len);
        }
        at += len;
    }
}

/// A client that lets the create's answer in up to all but its last piece (the server hands an
/// answer to the transport in 16 kB pieces): it reads the whole first ego view and nearly all
/// the goal image of a challenge scene, then resets the create. It has seen the scene: the
/// attempt is spent, and recorded as closed there.
#[tokio::test]
async fn a_create_whose_images_were_let_in_keeps_its_attempt_spent() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), &[]);
    let mut bob = client(&server, "bob-secret").await;
    // The answer is about 98.5 kB (two 128 px images): six whole pieces, then a last one.
    let window = 6 * 16 * 1024;
    let request = proto::CreateEpisodeRequest { sensors: None, ..create("challenge/00000", false) };
    let RawCreate { response, mut send, connection } = send_create(&server, "bob-secret", request, window).await;
    let response = tokio::time::timeout(Duration::from_secs(60), response).await.expect("headers come").unwrap();
    let mut body = response.into_body();
    let mut got = Vec::new();
    while got.len() < window as usize {
        let chunk = tokio::time::timeout(Duration::from_secs(60), body.data()).await.expect("data comes");
        got.extend_from_slice(&chunk.expect("the answer goes on").expect("a data frame"));
    }
    // Its observation (field 3): the ego view whole, and all of the goal image but its end.
    let (observation, length) = field_at(&got, 5, 3);
    let (ego, ego_len) = field_at(&got, observation, 1);
    assert!(ego + ego_len < got.len(), "the ego view arrived whole");
    assert!(observation + length - got.len() < 1024, "all but the goal image's last bytes arrived");
    send.send_reset(h2::Reason::CANCEL);
    tokio::time::sleep(Duration::from_millis(300)).await;
    refused(bob.create_episode(create("challenge/00000", false)).await, Code::FailedPrecondition, "already played");
    // Its episode is closed as a run ended there, and recorded.
    let written = records(dir.path(), "bob");
    assert_eq!(written.len(), 1, "one record of the seen attempt");
    let closed_by = written[0].agent_stats.get("closed_by").and_then(|v| v.as_str());
    assert_eq!((written[0].counted, closed_by), (Some(true), Some("unanswered")));
    connection.abort();
}

/// The first frame the web viewer sends `secret`'s watcher of episode `episode`, as JSON.
async fn watched_frame(server: &Server, secret: &str, episode: &str) -> serde_json::Value {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let url = server.viewer.as_deref().expect("started with --http-listen");
    let host = url.trim_start_matches("http://").trim_end_matches('/');
    let mut socket = tokio::net::TcpStream::connect(host).await.expect("the viewer accepts");
    let request =
        format!("GET /api/episodes/{episode}/watch HTTP/1.0\r\nHost: {host}\r\nAuthorization: Bearer {secret}\r\n\r\n");
    socket.write_all(request.as_bytes()).await.unwrap();
    let mut text = String::new();
    let mut buffer = [0u8; 65536];
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    loop {
        if let Some((_, after)) = text.split_once("event: frame\ndata: ")
            && let Some((data, _)) = after.split_once('\n')
        {
            return serde_json::from_str(data).expect("a frame is JSON");
        }
        assert!(std::time::Instant::now() < deadline, "no frame came: {text}");
        let n = tokio::time::timeout(Duration::from_secs(60), socket.read(&mut buffer)).await.unwrap().unwrap();
        assert!(n > 0, "the watch ended without a frame: {text}");
        text.push_str(&String::from_utf8_lossy(&buffer[..n]));
    }
}

/// A client that never lets the create's answer in, but watches its episode in the web viewer
/// (the list shows its id): the watch shows the scene's ego view and goal image, so the
/// attempt is spent when the create is then reset.
#[tokio::test]
async fn a_create_watched_in_the_viewer_keeps_its_attempt_spent() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), &["--http-listen", "127.0.0.1:0"]);
    let mut bob = client(&server, "bob-secret").await;
    let request = proto::CreateEpisodeRequest { sensors: None, ..create("challenge/00001", false) };
    let RawCreate { mut send, connection, .. } = send_create(&server, "bob-secret", request, 0).await;
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    let episode = loop {
        let (status, body) = server.viewer_request("GET", "/api/episodes", Some("bob-secret"), "").await;
        assert_eq!(status, 200, "{body}");
        let list: Vec<serde_json::Value> = serde_json::from_str(&body).expect("JSON");
        if let Some(id) = list.first().and_then(|e| e["id"].as_str()) {
            break id.to_owned();
        }
        assert!(std::time::Instant::now() < deadline, "the held create's episode is listed");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let frame = watched_frame(&server, "bob-secret", &episode).await;
    for image in ["ego", "goal"] {
        assert!(frame[image].as_str().is_some_and(|u| u.starts_with("data:image/png")), "{image}: {frame}");
    }
    send.send_reset(h2::Reason::CANCEL);
    tokio::time::sleep(Duration::from_millis(300)).await;
    refused(bob.create_episode(create("challenge/00001", false)).await, Code::FailedPrecondition, "already played");
    connection.abort();
}

#[tokio::test]
async fn an_attempt_whose_claim_cannot_be_journaled_is_refused_and_not_counted() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), &[]);
    let mut bob = client(&server, "bob-secret").await;
    // The records folder goes away under the running server (a volume unmounted, say): the
    // attempts journal cannot be opened, so no claim can be made durable.
    bob.server_info(proto::ServerInfoRequest {}).await.expect("served: the records folder is open");
    let (folder, away) = (dir.path().join("records"), dir.path().join("away"));
    std::fs::rename(&folder, &away).unwrap();
    refused(bob.create_episode(create("challenge/00002", false)).await, Code::Unavailable, "cannot be recorded");
    // Back in place, the same scene is played: the refused create counted no attempt.
    std::fs::rename(&away, &folder).unwrap();
    let episode = bob.create_episode(create("challenge/00002", false)).await.expect("the attempt is not spent");
    let episode_id = episode.into_inner().episode_id;
    play_out(&mut bob, &episode_id).await;
    let journal = std::fs::read_to_string(folder.join("attempts.journal")).unwrap();
    assert_eq!(journal.matches("{\"claim\":").count(), 1, "one claim, the played one's: {journal}");
    assert_eq!(records(dir.path(), "bob").len(), 1);
}
