//! Episode lifetimes: streams take their episodes with them, idle episodes are reaped, and the
//! server holds a thousand live episodes at once.

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
        let responses = client.step_batch(proto::StepBatchRequest { steps }).await.unwrap().into_inner().responses;
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
