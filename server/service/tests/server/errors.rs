//! Bad input, one test each: the right status code, a message that says what to change, and a
//! server that keeps serving.

use esrp_server::proto;
use esrp_server::proto::esrp_client::EsrpClient;
use tonic::Code;
use tonic::transport::Channel;

use super::harness::{Server, create_request, live_episodes, scene_ids, step_request};

/// Asserts `result` failed with `code` and a message containing `needle`, then that the server
/// still answers.
async fn assert_fails<T: std::fmt::Debug>(
    server: &mut Server,
    client: &mut EsrpClient<Channel>,
    result: Result<T, tonic::Status>,
    code: Code,
    needle: &str,
) {
    let status = result.expect_err("the call fails");
    assert_eq!(status.code(), code, "{status:?}");
    assert!(status.message().contains(needle), "message {:?} should mention {needle:?}", status.message());
    assert!(server.is_running(), "the server survives");
    let info = client.server_info(proto::ServerInfoRequest {}).await.expect("the server keeps serving");
    assert_eq!(info.into_inner().dataset, "esrp-bench-v2");
}

async fn first_episode(client: &mut EsrpClient<Channel>, privileged: bool) -> String {
    let scene = scene_ids(client, proto::Split::Test, 1).await.remove(0);
    client.create_episode(create_request(&scene, privileged)).await.unwrap().into_inner().episode_id
}

#[tokio::test]
async fn unknown_episode_is_not_found() {
    let mut server = Server::start(&[]);
    let mut client = server.client().await;
    let r = client.step(step_request("0123456789abcdef0123456789abcdef", 0)).await;
    assert_fails(&mut server, &mut client, r, Code::NotFound, "0123456789abcdef0123456789abcdef").await;
    let r = client.get_metrics(proto::GetMetricsRequest { episode_id: String::new() }).await;
    assert_fails(&mut server, &mut client, r, Code::NotFound, "no episode").await;
}

#[tokio::test]
async fn unknown_scene_is_not_found() {
    let mut server = Server::start(&[]);
    let mut client = server.client().await;
    let r = client.create_episode(create_request("esrp-bench-v2/99999", false)).await;
    assert_fails(&mut server, &mut client, r, Code::NotFound, "ListScenes").await;
    let r = client.create_episode(create_request("kitchen", false)).await;
    assert_fails(&mut server, &mut client, r, Code::NotFound, "kitchen").await;
    assert_eq!(live_episodes(&mut client).await, 0, "a failed create leaves nothing behind");
}

#[tokio::test]
async fn bad_action_code_is_invalid_argument() {
    let mut server = Server::start(&[]);
    let mut client = server.client().await;
    let episode = first_episode(&mut client, false).await;
    for code in [6, -1, i32::MAX] {
        let r = client.step(step_request(&episode, code)).await;
        assert_fails(&mut server, &mut client, r, Code::InvalidArgument, "action").await;
    }
    // The episode did not move: its first valid step is step 1.
    let ok = client.step(step_request(&episode, 2)).await.unwrap().into_inner();
    assert_eq!(ok.info.unwrap().step_index, 1);
}

#[tokio::test]
async fn stepping_after_the_end_is_failed_precondition() {
    let mut server = Server::start(&[]);
    let mut client = server.client().await;
    let scene = scene_ids(&mut client, proto::Split::Test, 1).await.remove(0);
    let mut request = create_request(&scene, false);
    request.horizon = 2;
    let episode = client.create_episode(request).await.unwrap().into_inner().episode_id;
    let first = client.step(step_request(&episode, 2)).await.unwrap().into_inner();
    assert!(!first.truncated);
    let second = client.step(step_request(&episode, 3)).await.unwrap().into_inner();
    assert!(second.truncated, "the horizon of 2 steps truncates the episode");
    assert!(second.metrics.is_some());
    let r = client.step(step_request(&episode, 2)).await;
    assert_fails(&mut server, &mut client, r, Code::FailedPrecondition, "step: episode").await;
    // A StepBatch names its step by its place in the request, however few it holds.
    let one = proto::StepBatchRequest { steps: vec![step_request(&episode, 2)], resets: Vec::new() };
    let r = client.step_batch(one).await;
    assert_fails(&mut server, &mut client, r, Code::FailedPrecondition, "steps[0]: episode").await;
    let one = proto::StepBatchRequest { steps: vec![step_request(&episode, 9)], resets: Vec::new() };
    let r = client.step_batch(one).await;
    assert_fails(&mut server, &mut client, r, Code::InvalidArgument, "steps[0].action: unknown action code 9").await;
    // Reset makes it steppable again.
    client.reset(proto::ResetRequest { episode_id: episode.clone(), scene: None }).await.unwrap();
    client.step(step_request(&episode, 2)).await.unwrap();
}

#[tokio::test]
async fn oversize_batch_is_resource_exhausted() {
    let mut server = Server::start(&["--max-batch", "4"]);
    let mut client = server.client().await;
    let mut steps = Vec::new();
    for _ in 0..5 {
        steps.push(step_request(&first_episode(&mut client, false).await, 0));
    }
    let r = client.step_batch(proto::StepBatchRequest { steps: steps.clone(), resets: Vec::new() }).await;
    assert_fails(&mut server, &mut client, r, Code::ResourceExhausted, "--max-batch").await;
    // A batch naming one episode twice is refused before anything moves.
    let twice = vec![steps[0].clone(), steps[1].clone(), steps[0].clone()];
    let r = client.step_batch(proto::StepBatchRequest { steps: twice, resets: Vec::new() }).await;
    assert_fails(&mut server, &mut client, r, Code::InvalidArgument, "twice").await;
    let ok = client
        .step_batch(proto::StepBatchRequest { steps: steps[..4].to_vec(), resets: Vec::new() })
        .await
        .unwrap()
        .into_inner();
    assert!(ok.responses.iter().all(|r| r.info.as_ref().unwrap().step_index == 1), "nothing moved before");
}

#[tokio::test]
async fn malformed_inline_scene_is_invalid_argument() {
    let mut server = Server::start(&[]);
    let mut client = server.client().await;
    let inline = |json: String| proto::CreateEpisodeRequest {
        scene: Some(proto::create_episode_request::Scene::SceneJson(json)),
        ..Default::default()
    };
    let r = client.create_episode(inline("{ not json".into())).await;
    assert_fails(&mut server, &mut client, r, Code::InvalidArgument, "invalid scene").await;
    // Well-formed JSON, but an unknown schema version: the message names it.
    let scene =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../core/examples/scenes/bedroom.json")).unwrap();
    let bad = scene.replacen("esrp.scene/v1", "esrp.scene/v9", 1);
    let r = client.create_episode(inline(bad)).await;
    assert_fails(&mut server, &mut client, r, Code::InvalidArgument, "esrp.scene/v9").await;
    // A number past any room (a fixed box of half extent 1e308 once passed, and parry's EPA
    // panicked a few steps later): refused at the create, the field named.
    let mut huge: serde_json::Value = serde_json::from_str(&scene).unwrap();
    huge["fixed_objects"][0]["shape"]["parts"][0]["half_extents"][1] = serde_json::json!(1e308);
    let r = client.create_episode(inline(huge.to_string())).await;
    assert_fails(&mut server, &mut client, r, Code::InvalidArgument, "fixed_objects[0].shape.parts[0].half_extents")
        .await;
    // The example scene itself is accepted inline.
    client.create_episode(inline(scene)).await.expect("a valid inline scene is served");
}

#[tokio::test]
async fn wrong_or_missing_token_is_unauthenticated() {
    let mut server = Server::start(&["--token", "s3cret"]);
    let channel = Channel::from_shared(server.address.clone()).unwrap().connect().await.unwrap();
    let with_token = |token: &'static str| {
        move |mut request: tonic::Request<()>| {
            request.metadata_mut().insert("authorization", format!("Bearer {token}").parse().unwrap());
            Ok(request)
        }
    };
    let mut bare = EsrpClient::new(channel.clone());
    let status = bare.server_info(proto::ServerInfoRequest {}).await.expect_err("no token, no answer");
    assert_eq!(status.code(), Code::Unauthenticated);
    assert!(status.message().contains("--token"), "{status:?}");
    let mut wrong = EsrpClient::with_interceptor(channel.clone(), with_token("guess"));
    let status = wrong.server_info(proto::ServerInfoRequest {}).await.expect_err("a wrong token, no answer");
    assert_eq!(status.code(), Code::Unauthenticated);
    assert!(server.is_running());
    let mut right = EsrpClient::with_interceptor(channel, with_token("s3cret"));
    let info = right.server_info(proto::ServerInfoRequest {}).await.expect("the right token is served").into_inner();
    assert_eq!(info.dataset, "esrp-bench-v2");
}

#[tokio::test]
async fn privileged_call_on_a_normal_episode_is_permission_denied() {
    let mut server = Server::start(&[]);
    let mut client = server.client().await;
    let episode = first_episode(&mut client, false).await;
    let r = client.get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: episode.clone() }).await;
    assert_fails(&mut server, &mut client, r, Code::PermissionDenied, "privileged = true").await;
    let privileged = first_episode(&mut client, true).await;
    let state = client
        .get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: privileged })
        .await
        .expect("a privileged episode answers")
        .into_inner();
    assert!(!state.objects.is_empty());
}

#[tokio::test]
async fn a_batch_whose_answer_exceeds_the_message_limit_is_refused_before_anything_moves() {
    let mut server = Server::start(&["--max-message-bytes", "200000"]);
    let mut client = server.client().await;
    let mut steps = Vec::new();
    for _ in 0..3 {
        let mut step = step_request(&first_episode(&mut client, false).await, 2);
        step.include_goal = true; // 2 images of 49 KB each per step: ~295 KB in all
        steps.push(step);
    }
    let r = client.step_batch(proto::StepBatchRequest { steps: steps.clone(), resets: Vec::new() }).await;
    assert_fails(&mut server, &mut client, r, Code::ResourceExhausted, "--max-message-bytes").await;
    for step in &mut steps {
        step.include_goal = false;
    }
    let ok = client.step_batch(proto::StepBatchRequest { steps, resets: Vec::new() }).await.unwrap().into_inner();
    assert!(ok.responses.iter().all(|r| r.info.as_ref().unwrap().step_index == 1), "nothing moved before");
}

#[tokio::test]
async fn a_create_whose_answer_exceeds_the_message_limit_is_refused_before_it_is_built() {
    let mut server = Server::start(&["--max-message-bytes", "1000000"]);
    let mut client = server.client().await;
    let sensors = proto::Sensors { resolution: 512, ..Default::default() }; // 2 images of 786 KB
    let request =
        proto::CreateEpisodeRequest { sensors: Some(sensors), ..create_request("esrp-bench-v2/00007", false) };
    let r = client.create_episode(request).await;
    assert_fails(&mut server, &mut client, r, Code::ResourceExhausted, "this create would take about 1.6 MB").await;
    assert_eq!(live_episodes(&mut client).await, 0, "nothing was built");
}

#[tokio::test]
async fn an_unreadable_stream_request_ends_the_stream_with_its_status() {
    use esrp_server::proto::stream_request::Request as Rq;
    use tokio_stream::StreamExt;
    let mut server = Server::start(&["--max-message-bytes", "100000"]);
    let mut client = server.client().await;
    let (tx, rx) = tokio::sync::mpsc::channel::<proto::StreamRequest>(4);
    let mut inbound = client.step_stream(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
    let huge = proto::CreateEpisodeRequest {
        scene: Some(proto::create_episode_request::Scene::SceneJson("x".repeat(200_000))),
        ..Default::default()
    };
    tx.send(proto::StreamRequest { request_id: 1, request: Some(Rq::Create(huge)) }).await.unwrap();
    let status = match inbound.next().await {
        Some(Ok(response)) => panic!("no answer expected for an unreadable request: {response:?}"),
        Some(Err(status)) => status,
        None => panic!("the stream ended without saying why"),
    };
    assert_eq!(status.code(), Code::OutOfRange, "{status:?}");
    assert!(server.is_running());
    client.server_info(proto::ServerInfoRequest {}).await.expect("the server keeps serving");
}

/// A long client-given value is echoed bounded: its first characters and its length, so that
/// the message fits in response metadata (grpcio caps it at 16 KiB).
#[tokio::test]
async fn long_client_values_are_echoed_bounded() {
    let mut server = Server::start(&[]);
    let mut client = server.client().await;
    let long = "a".repeat(20_000);
    let short = |status: &tonic::Status, code: Code| {
        assert_eq!(status.code(), code, "{status:?}");
        let message = status.message();
        assert!(message.len() < 512, "a message of {} bytes: {}…", message.len(), &message[..200.min(message.len())]);
        message.to_owned()
    };
    let id = || long.clone();
    let answers = [
        client.step(step_request(&long, 0)).await.map(drop),
        client.get_metrics(proto::GetMetricsRequest { episode_id: id() }).await.map(drop),
        client.close_episode(proto::CloseEpisodeRequest { episode_id: id() }).await.map(drop),
        client.reset(proto::ResetRequest { episode_id: id(), ..Default::default() }).await.map(drop),
        client.get_goal(proto::GetGoalRequest { episode_id: id() }).await.map(drop),
        client.get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: id() }).await.map(drop),
        client
            .step_batch(proto::StepBatchRequest { steps: vec![step_request(&long, 0)], resets: Vec::new() })
            .await
            .map(drop),
    ];
    for answer in answers {
        let message = short(&answer.expect_err("an unknown episode"), Code::NotFound);
        assert!(message.contains("(20000 characters)"), "{message}");
    }
    let r = client.create_episode(create_request(&long, false)).await;
    short(&r.expect_err("an unknown scene"), Code::NotFound);
    let r = client.list_scenes(proto::ListScenesRequest { page_token: id(), ..Default::default() }).await;
    short(&r.expect_err("a page token this server never gave"), Code::InvalidArgument);
    // Invalid inline scene JSON whose parse error quotes a long key, or a long string.
    for json in [format!("{{\"{long}\": 1}}"), format!("{{\"schema\": \"{long}\"}}")] {
        let request = proto::CreateEpisodeRequest {
            scene: Some(proto::create_episode_request::Scene::SceneJson(json)),
            ..Default::default()
        };
        let r = client.create_episode(request).await;
        let status = r.expect_err("invalid scene JSON");
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        assert!(status.message().len() < 2048, "a message of {} bytes", status.message().len());
        assert!(status.message().contains("invalid scene"), "{}", status.message());
    }
    assert!(server.is_running(), "the server survives");
    assert_eq!(live_episodes(&mut client).await, 0);
}

/// A StepBatch's resets: taken with its steps in one call (the same scene or another, as Reset
/// takes them), counted against `--max-batch` with them, and checked with them before anything
/// moves.
#[tokio::test]
async fn step_batch_resets_with_its_steps() {
    let mut server = Server::start(&["--max-batch", "4"]);
    let mut client = server.client().await;
    let scenes = scene_ids(&mut client, proto::Split::Test, 4).await;
    let mut ids = Vec::new();
    let mut firsts = Vec::new();
    for scene in &scenes[..3] {
        let created = client.create_episode(create_request(scene, false)).await.unwrap().into_inner();
        ids.push(created.episode_id);
        firsts.push(created.observation.unwrap());
    }
    let fresh = client.create_episode(create_request(&scenes[3], false)).await.unwrap().into_inner();
    let reset = |id: &str, scene: Option<&str>| proto::ResetRequest {
        episode_id: id.to_owned(),
        scene: scene.map(|s| proto::reset_request::Scene::SceneId(s.to_owned())),
    };
    let steps: Vec<proto::StepRequest> = ids.iter().map(|id| step_request(id, 2)).collect();
    let batch = proto::StepBatchRequest { steps: steps.clone(), resets: Vec::new() };
    client.step_batch(batch).await.unwrap();

    // Refused before anything moves: each episode once in all, a scene that does not exist, an
    // episode that does not exist, more than --max-batch steps and resets together.
    let batch = |steps: &[proto::StepRequest], resets: Vec<proto::ResetRequest>| proto::StepBatchRequest {
        steps: steps.to_vec(),
        resets,
    };
    let r = client.step_batch(batch(&steps[..2], vec![reset(&ids[1], None)])).await;
    assert_fails(&mut server, &mut client, r, Code::InvalidArgument, "resets[0]: episode").await;
    let r = client.step_batch(batch(&steps[..1], vec![reset(&ids[1], None), reset(&ids[1], None)])).await;
    assert_fails(&mut server, &mut client, r, Code::InvalidArgument, "resets[1]").await;
    let r = client.step_batch(batch(&steps[..1], vec![reset(&ids[1], Some("esrp-bench-v2/none"))])).await;
    assert_fails(&mut server, &mut client, r, Code::NotFound, "esrp-bench-v2/none").await;
    let r = client.step_batch(batch(&steps[..1], vec![reset("00000000000000000000000000000000", None)])).await;
    assert_fails(&mut server, &mut client, r, Code::NotFound, "no episode").await;
    let r = client.step_batch(batch(&steps, vec![reset(&fresh.episode_id, None), reset(&ids[0], None)])).await;
    assert_fails(&mut server, &mut client, r, Code::ResourceExhausted, "5 steps and resets").await;

    // Episode 0 steps, 1 restarts on its scene and 2 on the fourth scene, in one call.
    let answer = client
        .step_batch(batch(&steps[..1], vec![reset(&ids[1], None), reset(&ids[2], Some(&scenes[3]))]))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.responses.len(), 1);
    assert_eq!(answer.responses[0].info.as_ref().unwrap().step_index, 2, "its second step: nothing moved before");
    assert_eq!(answer.resets.len(), 2, "one answer per reset, in order");
    assert_eq!(answer.resets[0].observation.as_ref(), Some(&firsts[1]), "the scene's first observation again");
    assert_eq!(answer.resets[0].scene.as_ref().unwrap().id, scenes[1]);
    assert_eq!(answer.resets[1].observation, fresh.observation, "as a new episode on the fourth scene");
    assert_eq!(answer.resets[1].scene.as_ref().unwrap().id, scenes[3]);
    // Only resets; then each episode goes on from where the batch left it.
    let only = client.step_batch(batch(&[], vec![reset(&ids[0], None)])).await.unwrap().into_inner();
    assert_eq!((only.responses.len(), only.resets[0].observation.as_ref()), (0, Some(&firsts[0])));
    let next = client.step_batch(batch(&steps, Vec::new())).await.unwrap().into_inner().responses;
    let indices: Vec<u32> = next.iter().map(|r| r.info.as_ref().unwrap().step_index).collect();
    assert_eq!(indices, [1, 1, 1]);
}
