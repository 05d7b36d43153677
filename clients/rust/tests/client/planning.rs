//! PlanActions end to end: the server's planner from the current state of a real episode, its
//! cache, its budget, and its errors.

use std::time::Duration;

use esrp_client::{Action, Client, ClientError, Difficulty, EpisodeOptions, RandomActions, SceneFilter, Split};
use tokio_stream::StreamExt;

use crate::harness::{client, start};

/// The first `n` test scenes of `difficulty`.
async fn scenes_of(client: &Client, difficulty: Difficulty, n: usize) -> Vec<String> {
    let filter = SceneFilter::split(Split::Test).difficulty(difficulty);
    client.scenes(filter).take(n).map(|s| s.expect("a scene").id).collect().await
}

/// Steps `actions` one by one; returns whether the last one ended the episode in success, and
/// checks that no motion was refused.
async fn follow(episode: &mut esrp_client::Episode, actions: &[Action]) -> bool {
    let mut success = false;
    for (i, &action) in actions.iter().enumerate() {
        let r = episode.step(action).await.expect("a planned step is taken");
        assert!(
            r.info.accepted || matches!(action, Action::Fetch | Action::Release),
            "step {i} ({action:?}) of the plan collided: {:?}",
            r.info
        );
        if r.ended() {
            assert_eq!(i + 1, actions.len(), "the episode ended before the plan did");
            success = r.terminated;
        }
    }
    success
}

#[tokio::test]
async fn plans_from_the_start_and_from_any_state_reach_success() {
    let server = start(&[]);
    let client = client(&server).await;
    let mut scenes = scenes_of(&client, Difficulty::Easy, 2).await;
    scenes.extend(scenes_of(&client, Difficulty::Medium, 1).await);
    for (k, scene) in scenes.iter().enumerate() {
        let (mut episode, _) =
            client.create_episode(EpisodeOptions::scene(scene).privileged(true)).await.expect("created");
        // From a state the agent wandered into (it may hold something): a few random steps.
        let mut random = RandomActions::new(k as u64 + 11);
        for _ in 0..(6 * k) {
            if episode.step(random.next_action()).await.expect("a step").ended() {
                break;
            }
        }
        let (metrics, ended) = episode.metrics().await.expect("metrics");
        if ended {
            continue;
        }
        let plan = episode.plan_actions(0, None).await.expect("PlanActions answers");
        assert!(plan.reaches_success, "{scene}: {:?} {}", plan.failure, plan.failure_message);
        assert_eq!(plan.failure, None);
        assert_eq!(plan.plan_length as usize, plan.actions.len());
        assert!(!plan.cached);
        assert!(plan.stats.nodes_expanded > 0 && plan.stats.searches > 0, "{:?}", plan.stats);
        assert!(plan.actions.len() as u32 + metrics.steps <= episode.scene().horizon, "the plan fits the horizon");
        assert!(follow(&mut episode, &plan.actions).await, "{scene}: the plan did not end in success");
        let (metrics, ended) = episode.metrics().await.expect("metrics");
        assert!(ended && metrics.success && metrics.remaining_distance_ratio < 1.0, "{metrics:?}");
    }
}

#[tokio::test]
async fn the_plan_is_cached_while_the_episode_follows_it() {
    let server = start(&["--metrics-listen", "127.0.0.1:0"]);
    let client = client(&server).await;
    let scene = scenes_of(&client, Difficulty::Medium, 1).await.remove(0);
    let (mut episode, _) =
        client.create_episode(EpisodeOptions::scene(&scene).privileged(true)).await.expect("created");
    let first = episode.plan_actions(5, None).await.expect("a plan");
    assert!(first.reaches_success && !first.cached);
    assert_eq!(first.actions.len(), 5.min(first.plan_length as usize));
    let length = first.plan_length;
    follow(&mut episode, &first.actions).await;

    // Where the plan leads: answered from the cache, the rest of the same plan.
    let rest = episode.plan_actions(0, None).await.expect("the rest");
    assert!(rest.cached, "the episode followed the plan");
    assert_eq!(rest.plan_length, length - first.actions.len() as u32);
    assert_eq!(rest.stats, first.stats, "the stats of the planning that made the plan");

    // Off the plan (a turn and back is another state: the step counter moved): planned anew,
    // and the new plan still succeeds.
    let off = rest.actions[0];
    let detour = if off == Action::TurnLeft {
        [Action::TurnRight, Action::TurnLeft]
    } else {
        [Action::TurnLeft, Action::TurnRight]
    };
    follow(&mut episode, &detour).await;
    let fresh = episode.plan_actions(0, None).await.expect("a new plan");
    assert!(!fresh.cached && fresh.reaches_success);
    assert!(follow(&mut episode, &fresh.actions).await);

    // Reset goes back to where the first plan started: planned again (the cache holds the last
    // plan only), to the same plan (the planner is deterministic), then cached.
    let whole: Vec<Action> = first.actions.iter().chain(&rest.actions).copied().collect();
    episode.reset().await.expect("reset");
    let again = episode.plan_actions(0, None).await.expect("a plan");
    assert!(!again.cached);
    assert_eq!(again.actions, whole);
    let cached = episode.plan_actions(3, None).await.expect("a plan");
    assert!(cached.cached && cached.plan_length == length && cached.actions[..] == whole[..3]);

    let text = server_scrape(&server);
    assert!(text.contains("esrp_plans_total{outcome=\"cached\"} 2"), "{text}");
    assert!(text.contains("esrp_plans_total{outcome=\"planned\"} 3"), "{text}");
}

fn server_scrape(server: &esrp_client::LocalServer) -> String {
    use std::io::{Read, Write};
    let url = server.metrics.as_deref().expect("started with --metrics-listen");
    let host = url.trim_start_matches("http://").trim_end_matches("/metrics");
    let mut socket = std::net::TcpStream::connect(host).expect("the metrics endpoint accepts");
    write!(socket, "GET /metrics HTTP/1.0\r\nHost: {host}\r\n\r\n").expect("a request");
    let mut response = String::new();
    socket.read_to_string(&mut response).expect("a response");
    response
}

#[tokio::test]
async fn plan_errors_keep_their_kind() {
    let server = start(&[]);
    let client = client(&server).await;
    let scene = scenes_of(&client, Difficulty::Hard, 1).await.remove(0);

    let (plain, _) = client.create_episode(EpisodeOptions::scene(&scene)).await.expect("created");
    let err = plain.plan_actions(0, None).await.unwrap_err();
    assert!(matches!(&err, ClientError::PermissionDenied(m) if m.contains("privileged = true")), "{err}");

    // A budget nothing can plan a Hard scene in.
    let (privileged, _) = client.create_episode(EpisodeOptions::scene(&scene).privileged(true)).await.expect("created");
    let err = privileged.plan_actions(0, Some(Duration::from_millis(1))).await.unwrap_err();
    assert!(matches!(&err, ClientError::DeadlineExceeded(m) if m.contains("budget of 1 ms")), "{err}");

    // An ended episode.
    let expert = privileged.privileged_state().await.expect("state").expert_trajectory().expect("expert");
    let mut privileged = privileged;
    follow(&mut privileged, &expert).await;
    let err = privileged.plan_actions(0, None).await.unwrap_err();
    assert!(matches!(&err, ClientError::EpisodeEnded(_)), "{err}");

    // A plan that cannot fit the horizon: a failure in the answer, not an error.
    let (short, _) =
        client.create_episode(EpisodeOptions::scene(&scene).privileged(true).horizon(3)).await.expect("created");
    let answer = short.plan_actions(0, None).await.expect("an answer");
    assert!(!answer.reaches_success);
    assert_eq!(answer.failure, Some(esrp_client::PlanFailure::TooLong), "{}", answer.failure_message);
    assert!(answer.failure_message.contains("before the horizon"), "{}", answer.failure_message);

    let ghost = esrp_client::Episode::attach(&client, "0".repeat(32), privileged.scene().clone());
    let err = ghost.plan_actions(0, None).await.unwrap_err();
    assert!(matches!(&err, ClientError::NotFound(_)), "{err}");
    ghost.detach();
}

/// A plan whose client goes away stops: with one planner thread, a long plan abandoned by its
/// caller is counted as cancelled (without the cancel it would run to its 60 s budget).
#[tokio::test]
async fn an_abandoned_plan_stops_its_planner() {
    let server = start(&["--planner-threads", "1", "--metrics-listen", "127.0.0.1:0"]);
    let client = client(&server).await;
    // The slowest test scene to plan (the planner's whole node budget, tens of seconds in a
    // release build).
    let (episode, _) =
        client.create_episode(EpisodeOptions::scene("esrp-bench-v2/04304").privileged(true)).await.expect("created");
    let mut request = tonic::Request::new(esrp_client::proto::PlanActionsRequest {
        episode_id: episode.id().to_owned(),
        max_actions: 0,
        budget_ms: 60_000,
    });
    request.set_timeout(Duration::from_millis(300));
    let err = client.raw().plan_actions(request).await.expect_err("given up after 300 ms");
    assert!(matches!(err.code(), tonic::Code::DeadlineExceeded | tonic::Code::Cancelled), "{err}");
    let mut text = String::new();
    for _ in 0..300 {
        text = server_scrape(&server);
        if text.contains("esrp_plans_total{outcome=\"cancelled\"} 1") {
            return;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("the abandoned plan was not cancelled:\n{text}");
}

/// A call that waits its whole budget while every planner thread plans for other calls says so
/// (it planned nothing), rather than that the planner found no plan, and counts as `busy`.
#[tokio::test]
async fn a_call_that_waits_its_whole_budget_for_a_planner_thread_says_so() {
    let server = start(&["--planner-threads", "1", "--metrics-listen", "127.0.0.1:0"]);
    let client = client(&server).await;
    let scene = scenes_of(&client, Difficulty::Easy, 1).await.remove(0);
    let (waiting, _) = client.create_episode(EpisodeOptions::scene(&scene).privileged(true)).await.expect("created");
    // The slowest test scene to plan holds the one planner thread.
    let (slow, _) =
        client.create_episode(EpisodeOptions::scene("esrp-bench-v2/04304").privileged(true)).await.expect("created");
    let holder = tokio::spawn(async move { slow.plan_actions(0, Some(Duration::from_secs(30))).await.map(drop) });
    tokio::time::sleep(Duration::from_secs(1)).await;
    let err = waiting.plan_actions(0, Some(Duration::from_millis(1500))).await.unwrap_err();
    assert!(
        matches!(&err, ClientError::DeadlineExceeded(m)
            if m.contains("no planner thread came free within the budget of 1500 ms: all 1 (--planner-threads)")),
        "{err}"
    );
    holder.abort();
    let text = server_scrape(&server);
    assert!(text.contains("esrp_plans_total{outcome=\"busy\"} 1"), "{text}");
}

/// A plan that finishes after its episode was reset onto another scene is not kept for that
/// scene, even where the two start states are the same (the state fingerprint does not cover the
/// scene): here the second scene is the first with a horizon of 3 steps, where no plan fits.
#[tokio::test]
async fn a_plan_for_a_scene_the_episode_has_left_is_not_cached_for_the_next() {
    use esrp_client::proto;
    let server = start(&["--planner-threads", "1"]);
    let client = client(&server).await;
    let scene = scenes_of(&client, Difficulty::Easy, 1).await.remove(0);
    let (listed, _) = client.create_episode(EpisodeOptions::scene(&scene).privileged(true)).await.expect("created");
    let mut json: serde_json::Value =
        serde_json::from_str(&listed.privileged_state().await.expect("state").0.scene_json).expect("scene JSON");
    json["id"] = "inline/roomy".into();
    let roomy = json.to_string();
    json["id"] = "inline/short".into();
    json["horizon"] = 3.into();
    let short = json.to_string();
    let (episode, _) =
        client.create_episode(EpisodeOptions::scene_json(roomy).privileged(true)).await.expect("created");

    // The one planner thread is busy, so the call on `episode` waits, its start state taken.
    let (slow, _) =
        client.create_episode(EpisodeOptions::scene("esrp-bench-v2/04304").privileged(true)).await.expect("created");
    let holder = tokio::spawn(async move { slow.plan_actions(0, Some(Duration::from_secs(30))).await.map(drop) });
    tokio::time::sleep(Duration::from_secs(1)).await;
    let request = proto::PlanActionsRequest { episode_id: episode.id().to_owned(), max_actions: 0, budget_ms: 60_000 };
    let mut raw = client.raw();
    let pending = tokio::spawn(async move { raw.plan_actions(request).await.map(tonic::Response::into_inner) });
    tokio::time::sleep(Duration::from_secs(1)).await;
    let reset = proto::ResetRequest {
        episode_id: episode.id().to_owned(),
        scene: Some(proto::reset_request::Scene::SceneJson(short)),
    };
    client.raw().reset(reset).await.expect("reset onto the short scene");
    holder.abort(); // its planner stops, and the waiting call plans the roomy scene's start
    let planned = pending.await.expect("the call ends").expect("an answer");
    assert!(planned.reaches_success && !planned.cached, "planned from the roomy scene's start: {planned:?}");

    let answer = episode.plan_actions(0, None).await.expect("an answer");
    assert!(!answer.cached, "the roomy scene's plan was answered for the short one: {answer:?}");
    assert_eq!(answer.failure, Some(esrp_client::PlanFailure::TooLong), "{}", answer.failure_message);
}
