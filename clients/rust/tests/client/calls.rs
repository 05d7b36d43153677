//! Every call of the typed API, and what it answers.

use std::time::Duration;

use esrp_client::{Action, Difficulty, EpisodeOptions, RandomActions, SceneFilter, Sensors, Split, Tls};
use tokio_stream::StreamExt;

use crate::harness::{client, live_episodes_settled_at, start, test_scenes};

#[tokio::test]
async fn server_dataset_and_scene_listing() {
    let server = start(&[]);
    let client = client(&server).await;
    client.wait_healthy(Duration::from_secs(10)).await.expect("healthy");
    let info = client.server_info().await.unwrap();
    assert_eq!(info.dataset, "esrp-bench-v2");
    assert!(info.limits.max_episodes > 0);
    // PlanActions' budgets, the flags' defaults.
    assert_eq!((info.limits.plan_budget_ms, info.limits.max_plan_ms), (10_000, 60_000));
    let dataset = client.describe_dataset().await.unwrap();
    assert_eq!(dataset.name, "esrp-bench-v2");
    let tests = dataset.by_split["test"] as usize;

    // Paging: small pages give the same scenes, in the same order, as one listing.
    let all = client.list_scenes(SceneFilter::split(Split::Test)).await.unwrap();
    assert_eq!(all.len(), tests);
    let paged: Vec<_> = client
        .scenes(SceneFilter { page_size: 7, ..SceneFilter::split(Split::Test) })
        .take(50)
        .collect::<Result<_, _>>()
        .await
        .unwrap();
    assert_eq!(paged[..], all[..50]);
    assert!(all.iter().all(|s| s.split == Some(Split::Test)));
    let hard = client.list_scenes(SceneFilter::split(Split::Test).difficulty(Difficulty::Hard)).await.unwrap();
    assert!(!hard.is_empty() && hard.iter().all(|s| s.difficulty == Some(Difficulty::Hard) && s.movable_objects >= 4));
}

#[tokio::test]
async fn server_info_says_the_plan_budgets_of_its_flags() {
    // A default budget above the cap is said as the cap, which is what a call gets.
    for (flags, said) in [
        (&["--plan-budget-ms", "2500", "--max-plan-ms", "90000"][..], (2_500, 90_000)),
        (&["--plan-budget-ms", "120000", "--max-plan-ms", "30000"][..], (30_000, 30_000)),
    ] {
        let server = start(flags);
        let client = client(&server).await;
        client.wait_healthy(Duration::from_secs(10)).await.expect("healthy");
        let limits = client.server_info().await.unwrap().limits;
        assert_eq!((limits.plan_budget_ms, limits.max_plan_ms), said, "{flags:?}");
    }
}

#[tokio::test]
async fn an_episode_from_create_to_close() {
    let server = start(&[]);
    let client = client(&server).await;
    let scene = test_scenes(&client, 1).await.remove(0);
    let sensors = Sensors { ego_depth: true, ego_segmentation: true, current_top_down: true, resolution: 64 };
    let options = EpisodeOptions::scene(&scene).sensors(sensors).privileged(true).horizon(300);
    let (mut episode, first) = client.create_episode(options).await.unwrap();
    assert_eq!(episode.scene().id, scene);
    assert_eq!(episode.id().len(), 32);
    assert_eq!((first.ego_rgb.width(), first.ego_rgb.height(), first.ego_rgb.channels()), (64, 64, 3));
    assert_eq!(first.ego_rgb.bytes().len(), 64 * 64 * 3);
    let goal_first = first.goal_rgb.clone().expect("the goal comes with the first observation");
    let depth = first.depth.as_ref().expect("depth is on");
    assert!(depth.values().all(|d| d > 0.0), "depth in metres, +inf where nothing is seen");
    assert!(depth.values().any(|d| d.is_finite()));
    assert_eq!(first.segmentation.as_ref().expect("labels are on").values().len(), 64 * 64);
    assert!(first.current_top_down.is_some());
    assert!(episode.spec().arrays.iter().any(|a| a.name == "ego_depth"));

    let step = episode.step(Action::TurnLeft).await.unwrap();
    assert!(step.info.accepted && step.info.step_index == 1 && !step.ended());
    assert!(step.observation.goal_rgb.is_none(), "the goal is sent only when asked");
    assert_ne!(step.observation.ego_rgb, first.ego_rgb, "turning changes the view");
    let with_goal = episode.step_with_goal(Action::TurnRight).await.unwrap();
    assert_eq!(with_goal.observation.goal_rgb.as_ref(), Some(&goal_first));
    assert_eq!(with_goal.observation.ego_rgb, first.ego_rgb, "a turn and its inverse restore the view");

    let goal = episode.goal().await.unwrap();
    assert_eq!(goal.image.bytes(), goal_first.bytes());
    assert!(goal.frame.expect("a test scene's goal has its frame").metres_per_pixel > 0.0);
    let (metrics, ended) = episode.metrics().await.unwrap();
    assert_eq!((metrics.steps, ended), (2, false));
    let state = episode.privileged_state().await.unwrap();
    assert_eq!(state.objects.len() as u32, episode.scene().movable_objects);
    let expert = state.expert_trajectory().unwrap();
    assert_eq!(expert.len() as u32, episode.scene().expert_length);

    let again = episode.reset().await.unwrap();
    assert_eq!(again, first, "a reset gives the first observation again, bit for bit");
    let mut last = None;
    for action in &expert {
        last = Some(episode.step(*action).await.unwrap());
    }
    let last = last.unwrap();
    assert!(last.terminated && last.ended());
    let m = last.metrics.expect("metrics at the end");
    assert!(m.success && m.stage == 4 && m.object_success_rate == 1.0);
    let closed = episode.close().await.unwrap();
    assert_eq!(closed, m);
    assert_eq!(client.server_info().await.unwrap().live_episodes, 0);
}

#[tokio::test]
async fn step_batch_matches_single_steps() {
    let server = start(&[]);
    let client = client(&server).await;
    let scenes = test_scenes(&client, 4).await;
    let mut batched = Vec::new();
    let mut single = Vec::new();
    for scene in &scenes {
        batched.push(client.create_episode(EpisodeOptions::scene(scene)).await.unwrap().0);
        single.push(client.create_episode(EpisodeOptions::scene(scene)).await.unwrap().0);
    }
    let mut actions = RandomActions::new(3);
    for _ in 0..20 {
        let wave: Vec<Action> = (0..scenes.len()).map(|_| actions.next_action()).collect();
        let steps: Vec<_> = batched.iter().zip(&wave).map(|(e, a)| (e, *a)).collect();
        let answers = client.step_batch(&steps).await.unwrap();
        for ((episode, action), answer) in single.iter_mut().zip(&wave).zip(answers) {
            assert_eq!(episode.step(*action).await.unwrap(), answer);
        }
    }
}

#[tokio::test]
async fn dropped_episodes_are_closed() {
    let server = start(&[]);
    let client = client(&server).await;
    let scenes = test_scenes(&client, 3).await;
    for scene in &scenes {
        let (mut episode, _) = client.create_episode(EpisodeOptions::scene(scene)).await.unwrap();
        episode.step(Action::MoveForward).await.unwrap();
    }
    let kept = client.create_episode(EpisodeOptions::scene(&scenes[0])).await.unwrap().0;
    let id = kept.detach();
    // Closing on drop is a task on the runtime: give it a moment.
    assert_eq!(
        live_episodes_settled_at(&client, 1).await,
        1,
        "dropped handles close their episodes; a detached one lives"
    );
    let attached = esrp_client::Episode::attach(&client, id, Default::default());
    attached.close().await.unwrap();
    assert_eq!(client.server_info().await.unwrap().live_episodes, 0);
}

#[tokio::test]
async fn token_and_tls() {
    let dir = tempfile::tempdir().unwrap();
    let (cert, cert_path, key_path) = crate::harness::localhost_certificate(dir.path());
    let server = start(&["--tls-cert", &cert_path, "--tls-key", &key_path, "--token", "s3cret"]);
    let port = server.address.rsplit(':').next().unwrap();
    let url = format!("https://localhost:{port}");
    let tls = Tls::ca_pem(&cert).domain_name("localhost");
    let client = esrp_client::Client::connect(&url).tls(tls.clone()).token("s3cret").await.unwrap();
    let scene = test_scenes(&client, 1).await.remove(0);
    let (mut episode, _) = client.create_episode(EpisodeOptions::scene(scene)).await.unwrap();
    assert!(episode.step(Action::TurnLeft).await.unwrap().info.accepted);
    episode.close().await.unwrap();

    let without_token = esrp_client::Client::connect(&url).tls(tls).await.unwrap();
    let error = without_token.server_info().await.unwrap_err();
    assert!(matches!(error, esrp_client::ClientError::Unauthenticated(_)), "{error}");
}

#[tokio::test]
async fn abandoned_creates_leave_no_episode() {
    let server = start(&[]);
    let client = client(&server).await;
    let scene = test_scenes(&client, 1).await.remove(0);
    let sensors = Sensors { ego_depth: true, ego_segmentation: true, current_top_down: true, resolution: 256 };
    let options = EpisodeOptions::scene(&scene).sensors(sensors);
    let started = std::time::Instant::now();
    client.create_episode(options.clone()).await.unwrap().0.close().await.unwrap();
    let create = started.elapsed();
    // Deadlines from a fifth to twice a create's time: some calls are given up while the server
    // renders, some while the answer travels or after it arrived, some complete.
    let mut kept = Vec::new();
    for i in 0..30u32 {
        let deadline = create.mul_f64(0.2 + f64::from(i) * 0.06);
        if let Ok(created) = tokio::time::timeout(deadline, client.create_episode(options.clone())).await {
            kept.push(created.unwrap().0);
        }
    }
    for episode in kept {
        episode.close().await.expect("an answered create's episode exists");
    }
    assert_eq!(live_episodes_settled_at(&client, 0).await, 0, "every abandoned create's episode is closed");
}

/// What a user moves into tasks is `Send` (and what it shares, `Sync`), and so are the futures
/// of the calls (`tokio::spawn` takes only those): checked when this compiles.
#[test]
fn handles_and_the_futures_of_their_calls_are_send() {
    use esrp_client::{Client, ClientError, Episode, EpisodeStream, LocalServer};
    fn shared<T: Send + Sync + 'static>() {}
    fn moved<T: Send + 'static>() {}
    fn send<T: Send>(_: T) {}
    shared::<Client>();
    shared::<Episode>();
    shared::<ClientError>();
    shared::<LocalServer>();
    moved::<EpisodeStream>();
    let _calls = |client: Client, mut episode: Episode, mut stream: EpisodeStream| {
        send(client.create_episode(EpisodeOptions::seeded(Split::Test, 0)));
        send(client.list_scenes(SceneFilter::default()));
        send(client.scenes(SceneFilter::default()));
        send(client.episode_stream(4));
        send(episode.step(Action::TurnLeft));
        send(episode.reset());
        send(episode.plan_actions(0, None));
        send(stream.step("e", Action::TurnLeft));
        send(stream.next());
        send(stream.run(&[]));
        send(episode.close());
    };
}
