//! A full episode through unary calls: the expert of a built-in test scene succeeds.

use esrp_server::proto;

use super::harness::Server;

#[tokio::test]
async fn the_expert_succeeds_through_unary_steps() {
    let server = Server::start(&[]);
    let mut client = server.client().await;
    let info = client.server_info(proto::ServerInfoRequest {}).await.unwrap().into_inner();
    assert_eq!(info.dataset, "esrp-bench-v1");
    let created = client
        .create_episode(proto::CreateEpisodeRequest {
            scene: Some(proto::create_episode_request::Scene::SceneId("esrp-bench-v1/00003".into())),
            privileged: true,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let observation = created.observation.unwrap();
    assert_eq!(observation.ego_rgb.as_ref().unwrap().data.len(), 128 * 128 * 3);
    assert_eq!(observation.goal_rgb.as_ref().unwrap().data.len(), 128 * 128 * 3);
    let state = client
        .get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: created.episode_id.clone() })
        .await
        .unwrap()
        .into_inner();
    let scene = esrp_core::Scene::from_json(&state.scene_json).unwrap();
    let mut last = None;
    for action in &scene.expert_trajectory {
        let response = client
            .step(proto::StepRequest {
                episode_id: created.episode_id.clone(),
                action: i32::from(action.code()),
                include_goal: false,
            })
            .await
            .unwrap()
            .into_inner();
        last = Some(response);
    }
    let last = last.unwrap();
    assert!(last.terminated);
    assert!(last.metrics.unwrap().success);
}
