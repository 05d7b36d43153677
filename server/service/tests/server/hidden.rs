//! Hidden scenes serve a token other than an admin the paper's observation and nothing else,
//! on every call of both APIs and in the viewer's list: no reward, reward terms, placed count,
//! collision or fetch outcome, no metrics or goal frame before the end; every optional sensor, other
//! resolution and reward weight is refused. An organiser's `--challenge-observations full`
//! widens it; an admin sees everything.

use esrp_server::proto;
use tonic::Code;

use super::challenge::{Authed, DmConnection, boolean, client, create, int, refused, start, text};

/// Whether a step answer carries nothing beyond the paper's observation (and the step index,
/// the end flags and, once ended, the final metrics).
fn paper_only(answer: &proto::StepResponse) -> bool {
    let info = answer.info.clone().unwrap_or_default();
    let terms = info.reward_terms.unwrap_or_default();
    let observation = answer.observation.clone().unwrap_or_default();
    answer.reward == 0.0
        && terms == Default::default()
        && info.placed_count == 0
        && !info.accepted
        && info.collided_with.is_none()
        && info.no_op.is_empty()
        && info.fetched.is_none()
        && info.released.is_none()
        && observation.ego_rgb.is_some_and(|i| (i.width, i.height) == (128, 128))
        && observation.ego_depth.is_none()
        && observation.ego_segmentation.is_none()
        && observation.current_top_down.is_none()
        && (answer.terminated || answer.truncated || answer.metrics.is_none())
}

/// Steps `episode` with `actions` (fetches, releases, moves into walls, turns) one call each.
async fn step_all(client: &mut Authed, episode: &str, actions: &[i32]) -> Vec<proto::StepResponse> {
    let mut answers = Vec::new();
    for &action in actions {
        let request = proto::StepRequest { episode_id: episode.into(), action, include_goal: false };
        answers.push(client.step(request).await.expect("a step").into_inner());
    }
    answers
}

/// Forward into the wall, fetches and releases, turns: every kind of outcome a step can have.
const PROBES: [i32; 12] = [0, 0, 0, 0, 0, 0, 4, 5, 2, 4, 1, 3];

#[tokio::test]
async fn hidden_scenes_serve_the_paper_observation_only() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), &["--http-listen", "127.0.0.1:0"]);
    let mut bob = client(&server, "bob-secret").await;

    // Every optional sensor, other resolution and reward weight is refused, saying what is allowed.
    let sensors =
        |s: proto::Sensors| proto::CreateEpisodeRequest { sensors: Some(s), ..create("challenge/00000", false) };
    let refusals = [
        sensors(proto::Sensors { ego_depth: true, ..Default::default() }),
        sensors(proto::Sensors { ego_segmentation: true, ..Default::default() }),
        sensors(proto::Sensors { current_top_down: true, ..Default::default() }),
        sensors(proto::Sensors { resolution: 512, ..Default::default() }),
        sensors(proto::Sensors { resolution: 64, ..Default::default() }),
        proto::CreateEpisodeRequest {
            reward: Some(proto::RewardWeights { potential: Some(5.0), ..Default::default() }),
            ..create("challenge/00000", false)
        },
        proto::CreateEpisodeRequest { horizon: 1000, ..create("minival/00000", false) },
    ];
    for request in refusals {
        let status = bob.create_episode(request).await.expect_err("refused");
        assert_eq!(status.code(), Code::PermissionDenied, "{status:?}");
    }
    let status = bob.create_episode(sensors(proto::Sensors { ego_depth: true, ..Default::default() })).await;
    refused(status, Code::PermissionDenied, "paper's observation only: the ego and goal images at 128 px");
    // None of those took the attempt: the paper's create is served.
    let episode = bob.create_episode(create("challenge/00000", false)).await.expect("created").into_inner();
    let first = episode.observation.clone().unwrap();
    assert_eq!(first.ego_rgb.map(|i| i.width), Some(128));
    assert!(first.ego_depth.is_none() && first.current_top_down.is_none());
    let id = episode.episode_id;

    // Unary steps.
    for answer in step_all(&mut bob, &id, &PROBES).await {
        assert!(paper_only(&answer), "a step answer on a challenge scene says more than the paper's: {answer:?}");
    }
    // Metrics wait for the end, and so does the goal image's frame on the floor (the room's
    // size in metres); the image itself is served.
    let metrics = bob.get_metrics(proto::GetMetricsRequest { episode_id: id.clone() }).await;
    refused(metrics, Code::PermissionDenied, "only once it has ended");
    let goal = bob.get_goal(proto::GetGoalRequest { episode_id: id.clone() }).await.expect("the goal").into_inner();
    assert!(
        goal.goal_rgb.is_some_and(|i| i.width == 128) && goal.frame.is_none(),
        "mid-run goal: frame {:?}",
        goal.frame
    );
    // Batched steps.
    let batch = proto::StepBatchRequest {
        steps: vec![proto::StepRequest { episode_id: id.clone(), action: 0, include_goal: false }],
        resets: Vec::new(),
    };
    let answered = bob.step_batch(batch).await.expect("a batch").into_inner();
    assert!(answered.responses.iter().all(paper_only), "{:?}", answered.responses);
    // The viewer's list shows no placed count or success mid-run (nor the scene's layout).
    let listed = viewer_episodes(&server, "bob-secret").await;
    let mine = listed.iter().find(|e| e["id"] == id.as_str()).expect("the episode is listed");
    assert_eq!((mine["placed"].as_u64(), mine["success"].as_bool()), (Some(0), Some(false)), "{mine}");
    // Played out: the last answer carries the final metrics, and GetMetrics answers.
    let mut last = None;
    for step in 0.. {
        let request = proto::StepRequest { episode_id: id.clone(), action: 2 + step % 2, include_goal: false };
        let answer = bob.step(request).await.expect("a step").into_inner();
        assert!(paper_only(&answer), "{answer:?}");
        if answer.terminated || answer.truncated {
            last = Some(answer);
            break;
        }
    }
    assert!(last.and_then(|a| a.metrics).is_some(), "the ending step carries the final metrics");
    assert!(bob.get_metrics(proto::GetMetricsRequest { episode_id: id.clone() }).await.is_ok());
    let goal = bob.get_goal(proto::GetGoalRequest { episode_id: id }).await.expect("the goal").into_inner();
    assert!(goal.frame.is_some_and(|f| f.metres_per_pixel > 0.0), "an ended episode's goal has its frame");
    // An admin's episode of a hidden scene is not paper-only: its goal has its frame mid-run.
    let mut root = client(&server, "root-secret").await;
    let theirs = root.create_episode(create("challenge/00001", false)).await.expect("created").into_inner();
    let goal = root.get_goal(proto::GetGoalRequest { episode_id: theirs.episode_id }).await.unwrap().into_inner();
    assert!(goal.frame.is_some(), "an admin's goal has its frame");

    // A stream: the same answers, in-band.
    let minival = bob.create_episode(create("minival/00000", false)).await.expect("minival").into_inner().episode_id;
    let (requests, receiver) = tokio::sync::mpsc::channel(PROBES.len());
    for (n, &action) in PROBES.iter().enumerate() {
        let step = proto::StepRequest { episode_id: minival.clone(), action, include_goal: false };
        let request =
            proto::StreamRequest { request_id: n as u64, request: Some(proto::stream_request::Request::Step(step)) };
        requests.send(request).await.unwrap();
    }
    let mut answers =
        bob.step_stream(tokio_stream::wrappers::ReceiverStream::new(receiver)).await.unwrap().into_inner();
    for _ in PROBES {
        match answers.message().await.unwrap().unwrap().response {
            Some(proto::stream_response::Response::Step(answer)) => assert!(paper_only(&answer), "{answer:?}"),
            other => panic!("a step answer: {other:?}"),
        }
    }
    drop((requests, answers));

    // dm_env_rpc: the same rules for its worlds.
    use esrp_server::dm_env::wire::dm_env_rpc::v1 as dm;
    let mut connection = DmConnection::open(&server, "bob-secret").await;
    for (name, value) in [("resolution", int(64)), ("ego_depth", boolean(true)), ("current_top_down", boolean(true))] {
        let settings = [("split".to_owned(), text("minival")), (name.to_owned(), value)].into();
        let created =
            connection.call(dm::environment_request::Payload::CreateWorld(dm::CreateWorldRequest { settings })).await;
        let status = created.expect_err("refused");
        assert_eq!(status.code, Code::PermissionDenied as i32, "{name}: {status:?}");
        assert!(status.message.contains("paper's observation only"), "{status:?}");
    }
}

/// The viewer's `/api/episodes` for `secret`, as JSON.
async fn viewer_episodes(server: &super::harness::Server, secret: &str) -> Vec<serde_json::Value> {
    let (status, body) = server.viewer_request("GET", "/api/episodes", Some(secret), "").await;
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).expect("JSON")
}
