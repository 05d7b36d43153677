//! Whole episodes through StepBatch and StepStream, and determinism under concurrency.

use std::collections::HashMap;

use esrp_dataset::dice::Dice;
use esrp_server::proto;
use esrp_server::proto::stream_request::Request as Rq;
use esrp_server::proto::stream_response::Response as Rs;
use tokio_stream::StreamExt;

use super::harness::{Server, create_request, digest, expert_actions, random_action, scene_ids, step_request};

/// The experts of a sample of built-in test scenes, stepped together through StepBatch in
/// lockstep, all succeed: SR = 1.
#[tokio::test]
async fn experts_of_test_scenes_succeed_through_step_batch() {
    let server = Server::start(&[]);
    let mut client = server.client().await;
    let scenes = scene_ids(&mut client, proto::Split::Test, 6).await;
    assert_eq!(scenes.len(), 6);
    let mut episodes = Vec::new();
    for scene in &scenes {
        let created = client.create_episode(create_request(scene, true)).await.unwrap().into_inner();
        let actions = expert_actions(&mut client, &created.episode_id).await;
        assert!(!actions.is_empty(), "{scene} has an expert trajectory");
        episodes.push((created.episode_id, actions));
    }
    let longest = episodes.iter().map(|e| e.1.len()).max().unwrap();
    let mut finals: HashMap<String, proto::StepResponse> = HashMap::new();
    for t in 0..longest {
        let batch: Vec<proto::StepRequest> =
            episodes.iter().filter(|e| t < e.1.len()).map(|(id, actions)| step_request(id, actions[t])).collect();
        let ids: Vec<String> = batch.iter().map(|s| s.episode_id.clone()).collect();
        let responses = client
            .step_batch(proto::StepBatchRequest { steps: batch, resets: Vec::new() })
            .await
            .unwrap()
            .into_inner()
            .responses;
        assert_eq!(responses.len(), ids.len(), "one response per step, in order");
        for (id, response) in ids.into_iter().zip(responses) {
            assert_eq!(response.info.as_ref().unwrap().step_index as usize, t + 1);
            finals.insert(id, response);
        }
    }
    let mut successes = 0;
    for (id, _) in &episodes {
        let last = &finals[id];
        assert!(last.terminated, "episode {id} ends with its expert");
        let metrics = last.metrics.as_ref().expect("the last response carries metrics");
        assert_eq!(metrics.object_success_rate, 1.0);
        assert_eq!(metrics.stage, 4);
        successes += u32::from(metrics.success);
    }
    assert_eq!(successes as usize, episodes.len(), "SR = 1 over the sample");
}

/// One stream creates an episode, pipelines the whole expert trajectory without waiting for
/// answers, gets every answer in order, and closes the episode.
#[tokio::test]
async fn a_full_episode_runs_through_a_pipelined_stream() {
    let server = Server::start(&[]);
    let mut client = server.client().await;
    let scene = scene_ids(&mut client, proto::Split::Test, 2).await.pop().unwrap();
    // The expert trajectory, read from a privileged probe episode.
    let probe = client.create_episode(create_request(&scene, true)).await.unwrap().into_inner();
    let actions = expert_actions(&mut client, &probe.episode_id).await;

    let (tx, rx) = tokio::sync::mpsc::channel::<proto::StreamRequest>(4096);
    let mut inbound = client.step_stream(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
    tx.send(proto::StreamRequest { request_id: 1, request: Some(Rq::Create(create_request(&scene, false))) })
        .await
        .unwrap();
    let episode_id = match inbound.next().await.unwrap().unwrap().response {
        Some(Rs::Created(created)) => created.episode_id,
        other => panic!("expected Created, got {other:?}"),
    };
    for (i, &action) in actions.iter().enumerate() {
        tx.send(proto::StreamRequest {
            request_id: 100 + i as u64,
            request: Some(Rq::Step(step_request(&episode_id, action))),
        })
        .await
        .unwrap();
    }
    let mut last = None;
    for i in 0..actions.len() {
        let response = inbound.next().await.unwrap().unwrap();
        assert_eq!(response.request_id, 100 + i as u64, "answers come in request order");
        match response.response {
            Some(Rs::Step(step)) => last = Some(step),
            other => panic!("expected Step, got {other:?}"),
        }
    }
    let last = last.unwrap();
    assert!(last.terminated);
    assert!(last.metrics.unwrap().success);
    // The probe ran nothing; the stream's episode is the one that succeeded.
    tx.send(proto::StreamRequest {
        request_id: 7,
        request: Some(Rq::Close(proto::CloseEpisodeRequest { episode_id })),
    })
    .await
    .unwrap();
    match inbound.next().await.unwrap().unwrap().response {
        Some(Rs::Closed(closed)) => assert!(closed.metrics.unwrap().success),
        other => panic!("expected Closed, got {other:?}"),
    }
    // A bad request on the stream is answered in-band and the stream goes on.
    tx.send(proto::StreamRequest { request_id: 8, request: Some(Rq::Step(step_request("0123", 0))) }).await.unwrap();
    match inbound.next().await.unwrap().unwrap().response {
        Some(Rs::Error(error)) => assert_eq!(error.code, tonic::Code::NotFound as i32),
        other => panic!("expected an in-band error, got {other:?}"),
    }
    tx.send(proto::StreamRequest { request_id: 9, request: Some(Rq::Create(create_request(&scene, false))) })
        .await
        .unwrap();
    assert!(matches!(inbound.next().await.unwrap().unwrap().response, Some(Rs::Created(_))));
}

/// What a request of the pipelining test did: a step's digest, a reset's observation
/// digest, or an error code.
#[derive(Debug, PartialEq, Eq)]
enum Answer {
    Step(u64),
    Reset(u64),
    Error(i32),
}

/// Requests sent all at once on one stream (several steps of one episode, steps of a second
/// episode between them, a bad action, steps past the end, a reset, more steps) get the same
/// answers, in order, as the same requests made one by one with unary calls.
#[tokio::test]
async fn pipelined_stream_answers_match_unary_calls() {
    let server = Server::start(&[]);
    let mut client = server.client().await;
    let scene = scene_ids(&mut client, proto::Split::Test, 1).await.pop().unwrap();
    let create = || proto::CreateEpisodeRequest { horizon: 10, ..create_request(&scene, false) };
    // (episode 0 or 1, None for a reset or Some(action)).
    let mut dice = Dice::new(17, 0, 0);
    let mut plan: Vec<(usize, Option<i32>)> = Vec::new();
    for i in 0..14 {
        plan.push((0, Some(if i == 4 { 9 } else { random_action(&mut dice) })));
        if i % 3 == 0 {
            plan.push((1, Some(random_action(&mut dice))));
        }
    }
    plan.push((0, None));
    plan.extend((0..6).map(|_| (0, Some(random_action(&mut dice)))));

    let answer_of = |result: Result<Answer, tonic::Status>| result.unwrap_or_else(|s| Answer::Error(s.code() as i32));
    let mut expected = Vec::new();
    let unary: Vec<String> = [
        client.create_episode(create()).await.unwrap().into_inner().episode_id,
        client.create_episode(create()).await.unwrap().into_inner().episode_id,
    ]
    .into();
    for &(e, action) in &plan {
        let id = unary[e].clone();
        expected.push(answer_of(match action {
            Some(a) => client.step(step_request(&id, a)).await.map(|r| Answer::Step(digest(&r.into_inner()))),
            None => client.reset(proto::ResetRequest { episode_id: id, scene: None }).await.map(|r| {
                Answer::Reset(digest(&proto::StepResponse {
                    observation: r.into_inner().observation,
                    ..Default::default()
                }))
            }),
        }));
    }
    assert!(expected.contains(&Answer::Error(tonic::Code::InvalidArgument as i32)));
    assert!(expected.contains(&Answer::Error(tonic::Code::FailedPrecondition as i32)));

    let streamed: Vec<String> = [
        client.create_episode(create()).await.unwrap().into_inner().episode_id,
        client.create_episode(create()).await.unwrap().into_inner().episode_id,
    ]
    .into();
    let (tx, rx) = tokio::sync::mpsc::channel::<proto::StreamRequest>(plan.len());
    for (i, &(e, action)) in plan.iter().enumerate() {
        let id = streamed[e].clone();
        let request = match action {
            Some(a) => Rq::Step(step_request(&id, a)),
            None => Rq::Reset(proto::ResetRequest { episode_id: id, scene: None }),
        };
        tx.send(proto::StreamRequest { request_id: i as u64, request: Some(request) }).await.unwrap();
    }
    drop(tx);
    let mut inbound = client.step_stream(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
    let mut answers = Vec::new();
    while let Some(response) = inbound.next().await {
        let response = response.unwrap();
        assert_eq!(response.request_id, answers.len() as u64, "answers come in request order");
        answers.push(match response.response {
            Some(Rs::Step(r)) => Answer::Step(digest(&r)),
            Some(Rs::Reset(r)) => {
                Answer::Reset(digest(&proto::StepResponse { observation: r.observation, ..Default::default() }))
            }
            Some(Rs::Error(error)) => Answer::Error(error.code),
            other => panic!("unexpected answer {other:?}"),
        });
    }
    assert_eq!(answers, expected);
}

/// With a message limit of a few answers (which is also a stream's budget of answers waiting
/// to be sent), a client that sends 120 steps at once still gets every answer, in order: the
/// server waits for the client to read rather than holding everything.
#[tokio::test]
async fn a_stream_waits_within_its_answer_budget() {
    let server = Server::start(&["--max-message-bytes", "200000"]);
    let mut client = server.client().await;
    let scene = scene_ids(&mut client, proto::Split::Test, 1).await.pop().unwrap();
    let id = client.create_episode(create_request(&scene, false)).await.unwrap().into_inner().episode_id;
    let mut dice = Dice::new(3, 0, 0);
    let (tx, rx) = tokio::sync::mpsc::channel::<proto::StreamRequest>(120);
    for i in 0..120u64 {
        let request = Rq::Step(step_request(&id, random_action(&mut dice)));
        tx.send(proto::StreamRequest { request_id: i, request: Some(request) }).await.unwrap();
    }
    drop(tx);
    let mut inbound = client.step_stream(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
    let mut n = 0u64;
    let read_all = async {
        while let Some(response) = inbound.next().await {
            let response = response.unwrap();
            assert_eq!(response.request_id, n);
            match response.response {
                Some(Rs::Step(step)) => assert_eq!(u64::from(step.info.unwrap().step_index), n + 1),
                other => panic!("expected Step, got {other:?}"),
            }
            n += 1;
        }
    };
    tokio::time::timeout(std::time::Duration::from_secs(120), read_all).await.expect("the stream stalled");
    assert_eq!(n, 120);
}

const EPISODES: usize = 256;
const TASKS: usize = 32;
const STEPS: usize = 12;
const SCENES: usize = 8;

/// What one episode produced: the digest of its first observation and of every step response,
/// and its final metrics.
type Trace = (Vec<u64>, proto::EpisodeMetrics);

async fn run_episode(
    client: &mut proto::esrp_client::EsrpClient<tonic::transport::Channel>,
    scene: &str,
    seed: u64,
) -> Trace {
    let created = client.create_episode(create_request(scene, false)).await.unwrap().into_inner();
    let mut digests = vec![digest(&proto::StepResponse { observation: created.observation, ..Default::default() })];
    let mut dice = Dice::new(seed, 0, 0);
    for _ in 0..STEPS {
        let response =
            client.step(step_request(&created.episode_id, random_action(&mut dice))).await.unwrap().into_inner();
        digests.push(digest(&response));
        if response.terminated || response.truncated {
            break;
        }
    }
    let closed =
        client.close_episode(proto::CloseEpisodeRequest { episode_id: created.episode_id }).await.unwrap().into_inner();
    (digests, closed.metrics.unwrap())
}

/// 256 episodes stepped from 32 concurrent tasks (each interleaving its own 8) give the same
/// observations, rewards, infos and metrics as the same episodes run one at a time.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_episodes_match_sequential_runs() {
    concurrent_matches_sequential(&[]).await;
}

/// The same with four render threads, whose batches overlap: what an episode sees does not
/// depend on which thread drew it, nor on what it was drawn with.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn several_render_threads_keep_every_episode_as_it_runs_alone() {
    concurrent_matches_sequential(&["--render-threads", "4"]).await;
}

/// And with two render devices, each with its own copy of the scenes.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn several_render_devices_keep_every_episode_as_it_runs_alone() {
    concurrent_matches_sequential(&["--render-devices", "2", "--render-threads", "3"]).await;
}

/// And with three batches in flight per render thread (two threads), read back by their
/// readback threads while the next ones are submitted.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn batches_in_flight_keep_every_episode_as_it_runs_alone() {
    concurrent_matches_sequential(&["--render-pipeline", "3", "--render-threads", "2"]).await;
}

async fn concurrent_matches_sequential(args: &[&str]) {
    let server = Server::start(args);
    let mut client = server.client().await;
    let scenes = scene_ids(&mut client, proto::Split::Train, SCENES).await;
    assert_eq!(scenes.len(), SCENES);

    // Concurrent: each task creates its episodes, then steps them round-robin.
    let mut tasks = Vec::new();
    for task in 0..TASKS {
        let mut client = server.client().await;
        let scenes = scenes.clone();
        tasks.push(tokio::spawn(async move {
            let mine: Vec<usize> = (task..EPISODES).step_by(TASKS).collect();
            let mut live = Vec::new();
            for &e in &mine {
                let created =
                    client.create_episode(create_request(&scenes[e % SCENES], false)).await.unwrap().into_inner();
                let first = digest(&proto::StepResponse { observation: created.observation, ..Default::default() });
                live.push((e, created.episode_id, Dice::new(e as u64, 0, 0), vec![first], false));
            }
            for _ in 0..STEPS {
                for (_, id, dice, digests, done) in live.iter_mut() {
                    if *done {
                        continue;
                    }
                    let response = client.step(step_request(id, random_action(dice))).await.unwrap().into_inner();
                    digests.push(digest(&response));
                    *done = response.terminated || response.truncated;
                }
            }
            let mut traces = Vec::new();
            for (e, id, _, digests, _) in live {
                let closed =
                    client.close_episode(proto::CloseEpisodeRequest { episode_id: id }).await.unwrap().into_inner();
                traces.push((e, (digests, closed.metrics.unwrap())));
            }
            traces
        }));
    }
    let mut concurrent: HashMap<usize, Trace> = HashMap::new();
    for task in tasks {
        concurrent.extend(task.await.unwrap());
    }
    assert_eq!(concurrent.len(), EPISODES);

    // Sequential: one episode at a time.
    for e in 0..EPISODES {
        let alone = run_episode(&mut client, &scenes[e % SCENES], e as u64).await;
        assert_eq!(concurrent[&e], alone, "episode {e} differs when run concurrently");
    }
}

/// A batch larger than one render call may hold (65 views of 512×512 is over 16 Mpixels) is
/// rendered in parts, not refused after its steps were taken.
#[tokio::test]
async fn a_batch_beyond_one_render_call_is_rendered_in_parts() {
    let server = Server::start(&[]);
    let mut client = server.client().await;
    let scene = scene_ids(&mut client, proto::Split::Test, 1).await.remove(0);
    let mut steps = Vec::new();
    for _ in 0..65 {
        let mut request = create_request(&scene, false);
        request.sensors = Some(proto::Sensors { resolution: 512, ..Default::default() });
        let created = client.create_episode(request).await.unwrap().into_inner();
        steps.push(step_request(&created.episode_id, 2));
    }
    let responses =
        client.step_batch(proto::StepBatchRequest { steps, resets: Vec::new() }).await.unwrap().into_inner().responses;
    assert_eq!(responses.len(), 65);
    let first = responses[0].observation.as_ref().unwrap().ego_rgb.as_ref().unwrap();
    assert_eq!((first.height, first.width, first.data.len()), (512, 512, 512 * 512 * 3));
    // Same scene, same action: every episode sees the same thing.
    assert!(responses.iter().all(|r| r.observation.as_ref().unwrap().ego_rgb.as_ref().unwrap().data == first.data));
}

/// A step that changes nothing its views show (a rejected motion, a fetch with nothing in
/// reach) answers the episode's last images instead of rendering them again, and they are
/// exactly what rendering gives: a second episode that takes only the first one's accepted
/// actions reaches the same states and renders each of them, with every sensor on.
#[tokio::test]
async fn steps_that_change_nothing_answer_the_last_images() {
    // The flag's `=` form: LocalServer reads the metrics' address either way.
    let server = Server::start(&["--metrics-listen=127.0.0.1:0"]);
    let mut client = server.client().await;
    let sensors = proto::Sensors { ego_depth: true, ego_segmentation: true, current_top_down: true, resolution: 64 };
    let create =
        || proto::CreateEpisodeRequest { sensors: Some(sensors), ..create_request("esrp-bench-v2/00003", false) };
    let first = client.create_episode(create()).await.unwrap().into_inner();
    let mut previous = first.observation.unwrap();
    previous.goal_rgb = None;
    let mut dice = Dice::new(11, 0, 0);
    let mut accepted = Vec::new();
    let mut rejected = 0;
    for _ in 0..120 {
        let action = random_action(&mut dice);
        let response = client.step(step_request(&first.episode_id, action)).await.unwrap().into_inner();
        let observation = response.observation.clone().unwrap();
        if response.info.as_ref().unwrap().accepted {
            accepted.push((action, observation.clone()));
        } else {
            rejected += 1;
            assert_eq!(observation, previous, "a rejected step shows what the step before it showed");
        }
        previous = observation;
        if response.terminated || response.truncated {
            break;
        }
    }
    assert!(rejected >= 10 && accepted.len() >= 10, "{rejected} rejected, {} accepted", accepted.len());
    let text = server.scrape();
    let reused = text
        .lines()
        .find_map(|l| l.strip_prefix("esrp_render_views_reused_total "))
        .unwrap_or_else(|| panic!("the reuse counter in {text}"));
    // Two views per observation: the ego view (with depth and labels) and the top-down one.
    // Some accepted steps change nothing visible either.
    assert!(reused.parse::<u64>().unwrap() >= 2 * rejected, "{reused} views reused, {rejected} steps rejected");

    let second = client.create_episode(create()).await.unwrap().into_inner();
    for (i, (action, expected)) in accepted.iter().enumerate() {
        let response = client.step(step_request(&second.episode_id, *action)).await.unwrap().into_inner();
        assert!(response.info.unwrap().accepted, "accepted action {i} is accepted again");
        assert_eq!(&response.observation.unwrap(), expected, "accepted action {i}");
    }
}
