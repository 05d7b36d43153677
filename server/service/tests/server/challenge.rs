//! Roles, quotas, the hidden challenge split and the server's records, against the real binary:
//! an agent token is refused every privileged path of both APIs, a trainer the challenge's,
//! quotas hold under racing clients, and every run on the challenge is recorded once, whatever
//! ends it, across a `kill -9` and a restart, with the one counted attempt per scene enforced.

use std::path::Path;
use std::time::{Duration, Instant};

use esrp_server::proto;
use esrp_server::proto::esrp_client::EsrpClient;
use tonic::Code;
use tonic::transport::Channel;

use super::harness::Server;

const TOKENS: &str = r#"
[[token]]
name = "alice"
secret = "alice-secret"
role = "agent"
max_episodes = 2
max_streams = 1

[[token]]
name = "bob"
secret = "bob-secret"
role = "agent"

[[token]]
name = "tina"
secret = "tina-secret"
role = "trainer"

[[token]]
name = "root"
secret = "root-secret"
role = "admin"
"#;

const SEED: &str = "a-secret-seed-of-the-challenge";

pub(crate) type Authed = EsrpClient<tonic::service::interceptor::InterceptedService<Channel, Bearer>>;

/// Adds `authorization: Bearer SECRET` to every call.
#[derive(Clone)]
pub(crate) struct Bearer(&'static str);

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        request.metadata_mut().insert("authorization", format!("Bearer {}", self.0).parse().unwrap());
        Ok(request)
    }
}

pub(crate) async fn client(server: &Server, secret: &'static str) -> Authed {
    let channel = Channel::from_shared(server.address.clone()).unwrap().connect().await.unwrap();
    EsrpClient::with_interceptor(channel, Bearer(secret)).max_decoding_message_size(256 << 20)
}

pub(crate) fn start(dir: &Path, extra: &[&str]) -> Server {
    let tokens = dir.join("tokens.toml");
    std::fs::write(&tokens, TOKENS).unwrap();
    let records = dir.join("records");
    let mut args = vec![
        "--tokens",
        tokens.to_str().unwrap(),
        "--challenge-seed",
        SEED,
        "--challenge-scenes",
        "3",
        "--minival-scenes",
        "1",
        "--records",
        records.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    Server::start(&args)
}

/// A create of `scene`: with small images, but the paper's 128 px on a hidden scene (the only
/// size those serve a token other than an admin).
pub(crate) fn create(scene: &str, privileged: bool) -> proto::CreateEpisodeRequest {
    let hidden = scene.starts_with("challenge/") || scene.starts_with("minival/");
    proto::CreateEpisodeRequest {
        scene: Some(proto::create_episode_request::Scene::SceneId(scene.to_owned())),
        privileged,
        sensors: (!hidden).then(|| proto::Sensors { resolution: 16, ..Default::default() }),
        agent: "tester v1".into(),
        ..Default::default()
    }
}

pub(crate) fn refused<T: std::fmt::Debug>(result: Result<T, tonic::Status>, code: Code, needle: &str) {
    let status = result.expect_err("refused");
    assert_eq!(status.code(), code, "{status:?}");
    assert!(status.message().contains(needle), "{:?} does not contain {needle:?}", status.message());
}

async fn create_id(client: &mut Authed, request: proto::CreateEpisodeRequest) -> String {
    client.create_episode(request).await.expect("created").into_inner().episode_id
}

/// Steps `episode` with turns until it ends; returns the steps taken.
pub(crate) async fn play_out(client: &mut Authed, episode: &str) -> u32 {
    let mut steps = 0;
    loop {
        let request =
            proto::StepRequest { episode_id: episode.into(), action: 2 + (steps % 2) as i32, include_goal: false };
        let answer = client.step(request).await.expect("a step").into_inner();
        steps += 1;
        if answer.terminated || answer.truncated {
            return steps;
        }
    }
}

pub(crate) fn records(dir: &Path, token: &str) -> Vec<esrp_client::results::EpisodeRecord> {
    let path = dir.join("records").join(format!("{token}.jsonl"));
    if !path.exists() {
        return Vec::new();
    }
    let read = esrp_client::results::read_records(&path).expect("the server's records read back");
    assert!(!read.torn_tail);
    read.records
}

/// Each role (agent, admin) against the guarded calls, on esrp.v1 and dm_env_rpc, on one server: a
/// list read top to bottom, kept whole so that a call left out shows.
#[tokio::test]
async fn each_role_gets_only_what_it_may_on_both_apis() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), &[]);
    let mut alice = client(&server, "alice-secret").await;
    let mut tina = client(&server, "tina-secret").await;
    let mut root = client(&server, "root-secret").await;

    let info = alice.server_info(proto::ServerInfoRequest {}).await.unwrap().into_inner();
    assert_eq!((info.caller.as_str(), info.role.as_str(), info.challenge), ("alice", "agent", true));
    assert_eq!(info.recording, "challenge");

    // The hidden splits are listed by id, room, difficulty and objects only.
    let listed = alice
        .list_scenes(proto::ListScenesRequest { split: proto::Split::Challenge as i32, ..Default::default() })
        .await
        .unwrap()
        .into_inner()
        .scenes;
    let ids: Vec<&str> = listed.iter().map(|s| s.id.as_str()).collect();
    assert_eq!(ids, ["challenge/00000", "challenge/00001", "challenge/00002"]);
    assert!(listed.iter().all(|s| s.horizon == 0 && s.expert_length == 0 && s.movable_objects > 0));

    // An agent: no privileged episode anywhere, no privileged state, no plan.
    refused(alice.create_episode(create("esrp-bench-v2/00003", true)).await, Code::PermissionDenied, "role agent");
    let mine = create_id(&mut alice, create("esrp-bench-v2/00003", false)).await;
    let id = || proto::GetPrivilegedStateRequest { episode_id: mine.clone() };
    refused(alice.get_privileged_state(id()).await, Code::PermissionDenied, "may not call GetPrivilegedState");
    let plan = proto::PlanActionsRequest { episode_id: mine.clone(), ..Default::default() };
    refused(alice.plan_actions(plan).await, Code::PermissionDenied, "may not call PlanActions");

    // The same create on a stream answers the same refusal, in-band.
    let (requests, receiver) = tokio::sync::mpsc::channel(4);
    let mut answers =
        alice.step_stream(tokio_stream::wrappers::ReceiverStream::new(receiver)).await.unwrap().into_inner();
    let privileged = proto::StreamRequest {
        request_id: 7,
        request: Some(proto::stream_request::Request::Create(create("esrp-bench-v2/00003", true))),
    };
    requests.send(privileged).await.unwrap();
    match answers.message().await.unwrap().unwrap().response {
        Some(proto::stream_response::Response::Error(e)) => {
            assert_eq!(e.code, Code::PermissionDenied as i32, "{e:?}");
            assert!(e.message.contains("role agent"), "{e:?}");
        }
        other => panic!("a privileged create on an agent's stream is refused: {other:?}"),
    }
    drop((requests, answers));

    // A trainer: privileged episodes and plans, never on a hidden scene.
    let theirs = create_id(&mut tina, create("esrp-bench-v2/00003", true)).await;
    let state = tina.get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: theirs.clone() }).await;
    let scene_json = state.expect("a trainer reads its privileged episode").into_inner().scene_json;
    let plan = proto::PlanActionsRequest { episode_id: theirs.clone(), max_actions: 1, ..Default::default() };
    assert!(tina.plan_actions(plan).await.is_ok());
    for hidden in ["challenge/00000", "minival/00000"] {
        refused(tina.create_episode(create(hidden, true)).await, Code::PermissionDenied, "cannot be privileged");
        refused(root.create_episode(create(hidden, true)).await, Code::PermissionDenied, "cannot be privileged");
    }
    let into_hidden = proto::ResetRequest {
        episode_id: theirs.clone(),
        scene: Some(proto::reset_request::Scene::SceneId("challenge/00001".into())),
    };
    refused(tina.reset(into_hidden).await, Code::PermissionDenied, "cannot be privileged");
    // An inline scene cannot pass for a hidden one.
    let mut disguised: serde_json::Value = serde_json::from_str(&scene_json).unwrap();
    disguised["split"] = "challenge".into();
    let disguised = disguised.to_string();
    let inline = proto::CreateEpisodeRequest {
        scene: Some(proto::create_episode_request::Scene::SceneJson(disguised)),
        ..Default::default()
    };
    refused(tina.create_episode(inline).await, Code::InvalidArgument, "cannot claim the split challenge");
    // Nor take a served scene's id, nor one in the server's namespaces: records name scenes by id.
    let served: serde_json::Value = serde_json::from_str(&scene_json).unwrap();
    let served_id = served["id"].as_str().unwrap().to_owned();
    for id in [served_id.as_str(), "challenge/00001", "minival/00000", "esrp-bench-v2/00007"] {
        let mut renamed = served.clone();
        renamed["id"] = id.into();
        let inline = proto::CreateEpisodeRequest {
            scene: Some(proto::create_episode_request::Scene::SceneJson(renamed.to_string())),
            ..Default::default()
        };
        refused(tina.create_episode(inline).await, Code::InvalidArgument, "give it an id of its own");
    }
    let mut own = served.clone();
    own["id"] = "tina/my-room".into();
    let inline = proto::CreateEpisodeRequest {
        scene: Some(proto::create_episode_request::Scene::SceneJson(own.to_string())),
        ..Default::default()
    };
    assert!(tina.create_episode(inline).await.is_ok(), "an inline scene with an id of its own is served");
    // Hidden scenes play their own horizon.
    let longer = proto::CreateEpisodeRequest { horizon: 5000, ..create("minival/00000", false) };
    refused(alice.create_episode(longer).await, Code::PermissionDenied, "may not set the horizon");

    // Episodes are their creator's (or an admin's).
    let other = proto::GetMetricsRequest { episode_id: theirs.clone() };
    refused(alice.get_metrics(other).await, Code::PermissionDenied, "belongs to another token");
    let close = proto::CloseEpisodeRequest { episode_id: theirs.clone() };
    refused(alice.close_episode(close.clone()).await, Code::PermissionDenied, "belongs to another token");
    let state = root.get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: theirs.clone() }).await;
    assert!(state.is_ok(), "an admin reads any privileged episode");
    assert!(root.close_episode(close).await.is_ok(), "an admin closes any episode");

    // dm_env_rpc: the same caller, the same rules (its worlds are never privileged).
    use esrp_server::dm_env::wire::dm_env_rpc::v1 as dm;
    let world = |split: &str| dm::CreateWorldRequest { settings: [("split".to_owned(), text(split))].into() };
    // Each token keeps one connection: alice's quota is one stream at a time.
    let mut bob_connection = DmConnection::open(&server, "bob-secret").await;
    let mut alice_connection = DmConnection::open(&server, "alice-secret").await;
    let bob_world = bob_connection.call(dm::environment_request::Payload::CreateWorld(world("minival"))).await;
    let bob_world = match bob_world {
        Ok(dm::environment_response::Payload::CreateWorld(r)) => r.world_name,
        other => panic!("bob creates a world: {other:?}"),
    };
    let join = dm::JoinWorldRequest { world_name: bob_world.clone(), settings: Default::default() };
    let joined = alice_connection.call(dm::environment_request::Payload::JoinWorld(join.clone())).await;
    let status = joined.expect_err("alice may not join bob's world");
    assert_eq!(status.code, Code::PermissionDenied as i32, "{status:?}");
    assert!(status.message.contains("belongs to another token"), "{status:?}");
    // Nor reset it: refused as a world of bob's, its episode never named to alice.
    let reset = dm::ResetWorldRequest { world_name: bob_world.clone(), settings: Default::default() };
    let status = alice_connection.call(dm::environment_request::Payload::ResetWorld(reset)).await;
    let status = status.expect_err("alice may not reset bob's world");
    assert_eq!(status.code, Code::PermissionDenied as i32, "{status:?}");
    assert!(status.message.contains(&format!("world \"{bob_world}\" belongs to another token")), "{status:?}");
    // Nor destroy it: refused before anything is removed, so bob's world is still there.
    let destroy = dm::DestroyWorldRequest { world_name: bob_world };
    let destroyed = alice_connection.call(dm::environment_request::Payload::DestroyWorld(destroy)).await;
    let status = destroyed.expect_err("alice may not destroy bob's world");
    assert_eq!(status.code, Code::PermissionDenied as i32, "{status:?}");
    assert!(status.message.contains("belongs to another token"), "{status:?}");
    let mut root_connection = DmConnection::open(&server, "root-secret").await;
    let joined = root_connection.call(dm::environment_request::Payload::JoinWorld(join)).await;
    assert!(matches!(joined, Ok(dm::environment_response::Payload::JoinWorld(_))), "bob's world is intact: {joined:?}");
}

pub(crate) fn text(value: &str) -> esrp_server::dm_env::wire::dm_env_rpc::v1::Tensor {
    use esrp_server::dm_env::wire::dm_env_rpc::v1::tensor::{Payload, StringArray};
    esrp_server::dm_env::wire::dm_env_rpc::v1::Tensor {
        payload: Some(Payload::Strings(StringArray { array: vec![value.to_owned()] })),
        shape: vec![],
    }
}

pub(crate) fn boolean(value: bool) -> esrp_server::dm_env::wire::dm_env_rpc::v1::Tensor {
    use esrp_server::dm_env::wire::dm_env_rpc::v1::tensor::{BoolArray, Payload};
    esrp_server::dm_env::wire::dm_env_rpc::v1::Tensor {
        payload: Some(Payload::Bools(BoolArray { array: vec![value] })),
        shape: vec![],
    }
}

pub(crate) fn int(value: i64) -> esrp_server::dm_env::wire::dm_env_rpc::v1::Tensor {
    use esrp_server::dm_env::wire::dm_env_rpc::v1::tensor::{Int64Array, Payload};
    esrp_server::dm_env::wire::dm_env_rpc::v1::Tensor {
        payload: Some(Payload::Int64s(Int64Array { array: vec![value] })),
        shape: vec![],
    }
}

pub(crate) type DmAnswer = Result<
    esrp_server::dm_env::wire::dm_env_rpc::v1::environment_response::Payload,
    esrp_server::dm_env::wire::google::rpc::Status,
>;

/// One dm_env_rpc connection of a token: requests are answered in order on one stream, and its
/// worlds live as long as it does.
pub(crate) struct DmConnection {
    requests: tokio::sync::mpsc::Sender<esrp_server::dm_env::wire::dm_env_rpc::v1::EnvironmentRequest>,
    responses: tonic::Streaming<esrp_server::dm_env::wire::dm_env_rpc::v1::EnvironmentResponse>,
}

impl DmConnection {
    /// Opens the connection. A stream the token closed just before gives its place back only once
    /// the server has seen it close, so a refusal for the stream quota is retried for a while.
    pub(crate) async fn open(server: &Server, secret: &str) -> Self {
        use esrp_server::dm_env::wire::dm_env_rpc::v1 as dm;
        let mut client = dm::environment_client::EnvironmentClient::connect(server.address.clone()).await.unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let (requests, receiver) = tokio::sync::mpsc::channel(4);
            let mut call = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(receiver));
            call.metadata_mut().insert("authorization", format!("Bearer {secret}").parse().unwrap());
            match client.process(call).await {
                Ok(responses) => return Self { requests, responses: responses.into_inner() },
                Err(status) if status.code() == Code::ResourceExhausted && Instant::now() < deadline => {
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
                Err(status) => panic!("a dm_env_rpc connection opens: {status:?}"),
            }
        }
    }

    /// Sends one request and returns its answer (an error payload as `Err`).
    pub(crate) async fn call(
        &mut self,
        request: esrp_server::dm_env::wire::dm_env_rpc::v1::environment_request::Payload,
    ) -> DmAnswer {
        use esrp_server::dm_env::wire::dm_env_rpc::v1 as dm;
        self.requests.send(dm::EnvironmentRequest { payload: Some(request) }).await.unwrap();
        match self.responses.message().await.unwrap().unwrap().payload.unwrap() {
            dm::environment_response::Payload::Error(status) => Err(status),
            other => Ok(other),
        }
    }
}

#[tokio::test]
async fn quotas_hold_under_racing_clients() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), &[]);
    let alice = client(&server, "alice-secret").await;
    let racers = (0..8).map(|_| {
        let mut alice = alice.clone();
        tokio::spawn(async move { alice.create_episode(create("esrp-bench-v2/00003", false)).await })
    });
    let mut created = Vec::new();
    for racer in racers {
        match racer.await.unwrap() {
            Ok(answer) => created.push(answer.into_inner().episode_id),
            Err(status) => {
                assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
                assert!(
                    status.message().contains("already has 2 live episodes open, its quota (max_episodes"),
                    "{status:?}"
                );
            }
        }
    }
    assert_eq!(created.len(), 2, "exactly max_episodes creates win the race");
    // Another token's quota is its own.
    let mut bob = client(&server, "bob-secret").await;
    create_id(&mut bob, create("esrp-bench-v2/00003", false)).await;
    // A close frees a place.
    let mut alice = alice.clone();
    alice.close_episode(proto::CloseEpisodeRequest { episode_id: created[0].clone() }).await.unwrap();
    create_id(&mut alice, create("esrp-bench-v2/00003", false)).await;

    // max_streams = 1: a second stream (or dm_env_rpc connection) is refused while one is open.
    let (keep, receiver) = tokio::sync::mpsc::channel::<proto::StreamRequest>(1);
    let first = alice.step_stream(tokio_stream::wrappers::ReceiverStream::new(receiver)).await;
    let first = first.expect("the first stream opens");
    let second = alice.step_stream(tokio_stream::iter(Vec::<proto::StreamRequest>::new())).await;
    refused(second, Code::ResourceExhausted, "already has 1 streams open, its quota (max_streams");
    drop((keep, first));
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (again, receiver) = tokio::sync::mpsc::channel::<proto::StreamRequest>(1);
        match alice.step_stream(tokio_stream::wrappers::ReceiverStream::new(receiver)).await {
            Ok(_) => break,
            Err(status) if status.code() == Code::ResourceExhausted && Instant::now() < deadline => {
                drop(again);
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Err(status) => panic!("the stream's place comes back when it closes: {status:?}"),
        }
    }
}

/// One story told in order, across a kill and a restart of the server: each step depends on the
/// records and attempts the steps before it left, so it stays one test.
#[tokio::test]
async fn every_challenge_run_is_recorded_once_across_a_kill_and_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = start(dir.path(), &["--idle-timeout-seconds", "1"]);
    let mut bob = client(&server, "bob-secret").await;
    let mut root = client(&server, "root-secret").await;

    // Played to its end: recorded by the step that ended it, before its answer.
    let ended = create_id(&mut bob, create("challenge/00000", false)).await;
    let steps = play_out(&mut bob, &ended).await;
    let written = records(dir.path(), "bob");
    assert_eq!(written.len(), 1, "the record is on disk when the last step's answer arrives");
    let first = &written[0];
    assert_eq!((first.scene_id.as_str(), first.split.as_str(), first.steps), ("challenge/00000", "challenge", steps));
    assert_eq!((first.token.as_deref(), first.agent.as_str(), first.counted), (Some("bob"), "tester v1", Some(true)));
    assert_eq!((first.end.as_str(), first.actions.len()), ("horizon", steps as usize));
    assert_eq!(first.horizon, steps);
    assert!(first.dataset_hash.as_ref().is_some_and(|h| h.len() == 16));
    assert!(first.agent_stats.is_empty());

    // A second attempt at a counted scene is refused, and so is a reset of it.
    refused(bob.create_episode(create("challenge/00000", false)).await, Code::FailedPrecondition, "already played");
    let reset = proto::ResetRequest { episode_id: ended.clone(), scene: None };
    refused(bob.reset(reset).await, Code::FailedPrecondition, "already played");

    // Closed by its client after two steps.
    let closed = create_id(&mut bob, create("challenge/00001", false)).await;
    for action in [2, 2] {
        bob.step(proto::StepRequest { episode_id: closed.clone(), action, include_goal: false }).await.unwrap();
    }
    bob.close_episode(proto::CloseEpisodeRequest { episode_id: closed }).await.unwrap();
    let written = records(dir.path(), "bob");
    assert_eq!(written.len(), 2);
    assert_eq!((written[1].end.as_str(), written[1].actions.as_slice()), ("agent", &[2u8, 2][..]));
    assert_eq!(written[1].agent_stats.get("closed_by").and_then(|v| v.as_str()), Some("client"));

    // Created on a stream that then ends: recorded as closed by the stream's end.
    let mut tina = client(&server, "tina-secret").await;
    let (requests, receiver) = tokio::sync::mpsc::channel(4);
    let mut answers =
        tina.step_stream(tokio_stream::wrappers::ReceiverStream::new(receiver)).await.unwrap().into_inner();
    let on_stream = proto::StreamRequest {
        request_id: 1,
        request: Some(proto::stream_request::Request::Create(create("challenge/00000", false))),
    };
    requests.send(on_stream).await.unwrap();
    let created = answers.message().await.unwrap().unwrap();
    assert!(matches!(created.response, Some(proto::stream_response::Response::Created(_))), "{created:?}");
    drop(requests);
    while answers.message().await.ok().flatten().is_some() {}
    let deadline = Instant::now() + Duration::from_secs(10);
    while records(dir.path(), "tina").is_empty() {
        assert!(Instant::now() < deadline, "the stream's episode is recorded when the stream ends");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let streamed = &records(dir.path(), "tina")[0];
    assert_eq!(streamed.agent_stats.get("closed_by").and_then(|v| v.as_str()), Some("stream"));

    // Left idle: the reaper closes it, and it is recorded as closed there.
    let idle = create_id(&mut bob, create("challenge/00002", false)).await;
    bob.step(proto::StepRequest { episode_id: idle, action: 3, include_goal: false }).await.unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    while records(dir.path(), "bob").len() < 3 {
        assert!(Instant::now() < deadline, "the idle episode is reaped and recorded");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let reaped = &records(dir.path(), "bob")[2];
    assert_eq!(reaped.agent_stats.get("closed_by").and_then(|v| v.as_str()), Some("idle"));

    // An admin is not counted (it may replay any scene: `esrp verify`), and only challenge runs
    // are recorded by default.
    create_id(&mut root, create("challenge/00000", false)).await;
    create_id(&mut root, create("challenge/00000", false)).await;
    create_id(&mut bob, create("minival/00000", false)).await;
    create_id(&mut bob, create("minival/00000", false)).await;

    // kill -9 while alice's run is going: the earlier records stay whole; hers was claimed in
    // the journal before her episode existed, and its step journaled within milliseconds.
    let mut alice = client(&server, "alice-secret").await;
    let running = create_id(&mut alice, create("challenge/00001", false)).await;
    alice.step(proto::StepRequest { episode_id: running, action: 2, include_goal: false }).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let killed = std::process::Command::new("kill").args(["-9", &server.pid().to_string()]).status().unwrap();
    assert!(killed.success());
    server.wait().unwrap();
    assert_eq!(records(dir.path(), "bob").len(), 3);
    assert!(records(dir.path(), "alice").is_empty());
    // A torn line, as a crash mid-write would leave, is cut at the restart.
    let bob_file = dir.path().join("records/bob.jsonl");
    let mut bytes = std::fs::read(&bob_file).unwrap();
    bytes.extend_from_slice(b"{\"schema\":\"esrp.results/v1\",\"scene_id\":\"chal");
    std::fs::write(&bob_file, bytes).unwrap();

    let server = start(dir.path(), &[]);
    let mut bob = client(&server, "bob-secret").await;
    let mut alice = client(&server, "alice-secret").await;
    // The server answers once its records are read back.
    bob.server_info(proto::ServerInfoRequest {}).await.unwrap();
    assert_eq!(records(dir.path(), "bob").len(), 3, "the torn line is gone and nothing is duplicated");
    for scene in ["challenge/00000", "challenge/00001", "challenge/00002"] {
        refused(bob.create_episode(create(scene, false)).await, Code::FailedPrecondition, "already played");
    }
    // Alice's cut attempt counts, recorded as ended at its last journaled step.
    refused(alice.create_episode(create("challenge/00001", false)).await, Code::FailedPrecondition, "already played");
    let cut = records(dir.path(), "alice");
    assert_eq!(cut.len(), 1, "{cut:?}");
    assert_eq!(
        (cut[0].scene_id.as_str(), cut[0].actions.as_slice(), cut[0].counted),
        ("challenge/00001", &[2u8][..], Some(true))
    );
    assert_eq!((cut[0].steps, cut[0].end.as_str()), (1, "agent"));
    assert_eq!(cut[0].agent_stats.get("closed_by").and_then(|v| v.as_str()), Some("restart"));
    let again = create_id(&mut alice, create("challenge/00002", false)).await;

    // Cut by the shutdown: recorded as closed there.
    let mut server = server;
    let stopped = std::process::Command::new("kill").args(["-TERM", &server.pid().to_string()]).status().unwrap();
    assert!(stopped.success());
    assert!(server.wait().unwrap().success());
    let cut = records(dir.path(), "alice");
    assert_eq!(cut.len(), 2, "{cut:?}");
    assert_eq!((cut[1].scene_id.as_str(), cut[1].steps), ("challenge/00002", 0));
    assert_eq!(cut[1].agent_stats.get("closed_by").and_then(|v| v.as_str()), Some("shutdown"));
    drop(again);
}
