//! The pipelined stream driver answers exactly as unary calls do.

use esrp_client::{Action, Answer, ClientError, EpisodeOptions, RandomActions};

use crate::harness::{client, start, test_scenes};

/// Random plans of `steps` actions for `n` episodes, each with its own seed.
fn plans(n: usize, steps: usize) -> Vec<Vec<Action>> {
    (0..n).map(|i| RandomActions::new(100 + i as u64).take(steps).collect()).collect()
}

#[tokio::test]
async fn stream_driver_equals_unary_steps() {
    let server = start(&[]);
    let client = client(&server).await;
    for episodes in [1usize, 16] {
        let scenes = test_scenes(&client, episodes).await;
        let plans = plans(episodes, 24);
        // The reference: the same actions, one unary Step at a time.
        let mut expected = Vec::new();
        for (scene, plan) in scenes.iter().zip(&plans) {
            let (mut episode, _) = client.create_episode(EpisodeOptions::scene(scene).horizon(1000)).await.unwrap();
            let mut results = Vec::new();
            for action in plan {
                results.push(episode.step(*action).await.unwrap());
            }
            expected.push(results);
            episode.close().await.unwrap();
        }
        for window in [1usize, 4, 16] {
            let mut handles = Vec::new();
            for scene in &scenes {
                handles.push(client.create_episode(EpisodeOptions::scene(scene).horizon(1000)).await.unwrap().0);
            }
            let mut stream = client.episode_stream(window).await.unwrap();
            let run: Vec<(&str, &[Action])> = handles.iter().zip(&plans).map(|(h, p)| (h.id(), &p[..])).collect();
            let answers = stream.run(&run).await.unwrap();
            for (got, want) in answers.into_iter().zip(&expected) {
                let got: Vec<_> = got.into_iter().map(|r| r.unwrap()).collect();
                assert_eq!(&got, want, "{episodes} episodes, window {window}");
            }
            assert_eq!(stream.outstanding(), 0);
            for handle in handles {
                handle.close().await.unwrap();
            }
        }
    }
    assert_eq!(client.server_info().await.unwrap().live_episodes, 0);
}

#[tokio::test]
async fn stream_requests_and_in_band_errors() {
    let server = start(&[]);
    let client = client(&server).await;
    let scene = test_scenes(&client, 1).await.remove(0);
    let mut stream = client.episode_stream(2).await.unwrap();
    stream.create(&EpisodeOptions::scene(&scene).horizon(2)).unwrap();
    let created = stream.next().await.unwrap().unwrap();
    let Ok(Answer::Created { observation, scene: summary }) = created.result else { panic!("{created:?}") };
    assert_eq!(summary.id, scene);
    assert!(observation.goal_rgb.is_some());
    let id = created.episode_id;
    for _ in 0..3 {
        stream.step(&id, Action::TurnLeft).await.unwrap();
    }
    stream.reset(&id).unwrap();
    stream.close(&id).unwrap();
    stream.step(&id, Action::TurnLeft).await.unwrap();
    let mut answers = Vec::new();
    while let Some(answer) = stream.next().await.unwrap() {
        answers.push(answer);
    }
    assert_eq!(answers.iter().map(|a| a.request_id).collect::<Vec<_>>(), (2..=7).collect::<Vec<u64>>());
    assert!(matches!(&answers[0].result, Ok(Answer::Step(r)) if !r.ended()));
    assert!(matches!(&answers[1].result, Ok(Answer::Step(r)) if r.truncated));
    assert!(matches!(&answers[2].result, Err(ClientError::EpisodeEnded(_))), "{:?}", answers[2].result);
    assert!(matches!(&answers[3].result, Ok(Answer::Reset(_))));
    assert!(matches!(&answers[4].result, Ok(Answer::Closed(m)) if m.steps == 0));
    assert!(matches!(&answers[5].result, Err(ClientError::NotFound(_))), "{:?}", answers[5].result);
    assert!(client.episode_stream(0).await.is_err(), "a window of 0 is refused");
}
