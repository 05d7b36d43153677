//! A full episode through unary calls: the expert of a built-in test scene succeeds.

use esrp_server::proto;

use super::harness::{Server, create_request, expert_actions, step_request};

#[tokio::test]
async fn the_expert_succeeds_through_unary_steps() {
    let server = Server::start(&[]);
    let mut client = server.client().await;
    let info = client.server_info(proto::ServerInfoRequest {}).await.unwrap().into_inner();
    assert_eq!(info.dataset, "esrp-bench-v2");
    let created = client
        .create_episode(proto::CreateEpisodeRequest {
            scene: Some(proto::create_episode_request::Scene::SceneId("esrp-bench-v2/00003".into())),
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

/// An episode of esrp-bench-v2/00003 created on `server` and stepped with `actions`: the client
/// and the episode's id.
async fn stepped(
    server: &Server,
    actions: &[i32],
) -> (proto::esrp_client::EsrpClient<tonic::transport::Channel>, String) {
    let mut client = server.client().await;
    let id = client.create_episode(create_request("esrp-bench-v2/00003", false)).await.unwrap().into_inner().episode_id;
    for &action in actions {
        client.step(step_request(&id, action)).await.unwrap();
    }
    (client, id)
}

/// The value of metric `name` (its full name with labels) in a metrics text.
fn metric(text: &str, name: &str) -> f64 {
    let line = text.lines().find(|l| l.strip_prefix(name).is_some_and(|rest| rest.starts_with(' ')));
    line.unwrap_or_else(|| panic!("{name} in {text}")).rsplit(' ').next().unwrap().parse().unwrap()
}

/// The Prometheus endpoint counts steps, episodes and render batches.
#[tokio::test]
async fn metrics_count_steps_episodes_and_render_batches() {
    let server = Server::start(&["--metrics-listen", "127.0.0.1:0"]);
    let (mut client, episode_id) = stepped(&server, &[2, 2, 3]).await;
    let text = server.scrape();
    let value = |name: &str| metric(&text, name);
    assert_eq!(value("esrp_steps_total"), 3.0);
    assert_eq!(value("esrp_episodes_created_total"), 1.0);
    assert_eq!(value("esrp_live_episodes"), 1.0);
    assert_eq!(value("esrp_step_latency_seconds_count"), 3.0);
    // Create renders goal + first view, each step one view.
    assert!(value("esrp_render_batch_views_sum") >= 5.0, "{text}");
    // Where the steps' time went, by stage: each stage the steps went through took some.
    let stages =
        ["lock", "take", "render_queue", "render_encode", "render_submit", "render_device", "render_extract", "answer"];
    for stage in stages {
        let seconds = value(&format!("esrp_stage_seconds_total{{stage=\"{stage}\"}}"));
        assert!(seconds > 0.0 && seconds < 60.0, "{stage}: {seconds}");
    }
    // A CPU renderer's drawing is not timed by default (--render-timestamps auto).
    assert_eq!(value("esrp_render_timestamps"), 0.0, "{text}");
    assert_eq!(value("esrp_render_gpu_seconds_total"), 0.0, "{text}");
    assert_eq!(value("esrp_render_threads"), 1.0, "auto: one thread on the software renderer");
    assert_eq!(value("esrp_render_pipeline"), 1.0, "auto: one batch in flight per thread");
    // Batches of one and two views (the create's, then each step's) share one pooled atlas.
    assert_eq!(value("esrp_render_atlases_created_total"), 1.0, "{text}");
    client.close_episode(proto::CloseEpisodeRequest { episode_id }).await.unwrap();
    let text = server.scrape();
    assert!(text.contains("esrp_episodes_closed_total{reason=\"client\"} 1"), "{text}");
    assert!(text.contains("esrp_live_episodes 0"), "{text}");
}

/// --render-timestamps on times the device's drawing (the software renderers have timestamp
/// queries): the gauge says so, and the drawing is a part of the batches' time on the render
/// thread.
#[tokio::test]
async fn render_timestamps_time_the_device_s_drawing() {
    let server = Server::start(&["--metrics-listen", "127.0.0.1:0", "--render-timestamps", "on"]);
    stepped(&server, &[2, 3, 0]).await;
    let text = server.scrape();
    let value = |name: &str| metric(&text, name);
    assert_eq!(value("esrp_render_timestamps"), 1.0, "{text}");
    let drawing = value("esrp_render_gpu_seconds_total");
    let thread: f64 = ["render_encode", "render_submit", "render_device"]
        .iter()
        .map(|stage| value(&format!("esrp_stage_seconds_total{{stage=\"{stage}\"}}")))
        .sum();
    assert!(drawing > 0.0 && drawing <= thread, "drew {drawing} s of {thread} s");
}

/// With --tls-cert/--tls-key the server speaks TLS only: a client that trusts the certificate is
/// served, a plaintext client is not.
#[tokio::test]
async fn tls_serves_clients_that_trust_the_certificate() {
    use tonic::transport::{Certificate, Channel, ClientTlsConfig};
    let rcgen::CertifiedKey { cert, signing_key } =
        rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (cert_path, key_path) = (dir.path().join("cert.pem"), dir.path().join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, signing_key.serialize_pem()).unwrap();
    let server = Server::start(&["--tls-cert", cert_path.to_str().unwrap(), "--tls-key", key_path.to_str().unwrap()]);
    let port = server.address.rsplit(':').next().unwrap();
    let tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(cert.pem())).domain_name("localhost");
    let channel = Channel::from_shared(format!("https://localhost:{port}"))
        .unwrap()
        .tls_config(tls)
        .unwrap()
        .connect()
        .await
        .unwrap();
    let info = proto::esrp_client::EsrpClient::new(channel)
        .server_info(proto::ServerInfoRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(info.dataset, "esrp-bench-v2");
    let mut plain = server.client_unchecked().await;
    assert!(plain.server_info(proto::ServerInfoRequest {}).await.is_err(), "plaintext is refused");
}

/// esrp-bench-v2 is served by default and esrp-bench-v1 on request, with the same split of each
/// index; a v1 episode starts within reach of an object, a v2 episode of the same index away
/// from them all (stage 1 if the agent does nothing).
#[tokio::test]
async fn both_benchmarks_are_served() {
    let v2 = Server::start(&[]);
    let v1 = Server::start(&["--benchmark", "esrp-bench-v1"]);
    let (mut c2, mut c1) = (v2.client().await, v1.client().await);
    assert_eq!(c1.server_info(proto::ServerInfoRequest {}).await.unwrap().into_inner().dataset, "esrp-bench-v1");
    let test_ids = |ids: Vec<String>| ids.into_iter().map(|id| id[14..].to_owned()).collect::<Vec<_>>();
    let ids1 = super::harness::scene_ids(&mut c1, proto::Split::Test, 20).await;
    let ids2 = super::harness::scene_ids(&mut c2, proto::Split::Test, 20).await;
    assert!(ids1[0].starts_with("esrp-bench-v1/") && ids2[0].starts_with("esrp-bench-v2/"), "{ids1:?} {ids2:?}");
    assert_eq!(test_ids(ids1), test_ids(ids2.clone()));
    let episode_id =
        c2.create_episode(super::harness::create_request(&ids2[0], false)).await.unwrap().into_inner().episode_id;
    let metrics =
        c2.close_episode(proto::CloseEpisodeRequest { episode_id }).await.unwrap().into_inner().metrics.unwrap();
    assert_eq!(metrics.stage, 1, "{metrics:?}");
    let episode_id = c1
        .create_episode(super::harness::create_request(&ids2[0].replace("-v2/", "-v1/"), false))
        .await
        .unwrap()
        .into_inner()
        .episode_id;
    let metrics =
        c1.close_episode(proto::CloseEpisodeRequest { episode_id }).await.unwrap().into_inner().metrics.unwrap();
    assert_eq!(metrics.stage, 2, "{metrics:?}");
    let bad = esrp_client::LocalServer::command(Some(env!("CARGO_BIN_EXE_esrp-server").into()), &["--benchmark", "v3"])
        .unwrap()
        .output()
        .unwrap();
    assert!(!bad.status.success() && String::from_utf8_lossy(&bad.stderr).contains("esrp-bench-v2"));
}

/// A server that cannot start says why in one line on stderr (no backtrace, whatever
/// `RUST_BACKTRACE` says; a cause said once) and exits with status 1.
#[test]
fn a_server_that_cannot_start_says_why_in_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing");
    for (flag, said) in [("--tokens", "token file"), ("--dataset", "cannot serve the dataset folder")] {
        let line = super::startup::refused_at_start(&[flag, missing.to_str().unwrap()], &[]);
        assert!(line.starts_with(&format!("esrp-server: {said}")), "{flag}: {line}");
        assert_eq!(line.matches("No such file or directory").count(), 1, "a cause said once: {line}");
    }
}

/// A value refused from an environment variable (`ESRP_*`) is said to come from it: clap's message
/// names only the flag. One given on the command line, which wins over the variable, is not.
#[test]
fn a_refused_value_from_the_environment_names_its_variable() {
    let start = |args: &[&str], variable: (&str, &str)| {
        let output = esrp_client::LocalServer::command(Some(env!("CARGO_BIN_EXE_esrp-server").into()), args)
            .unwrap()
            .env(variable.0, variable.1)
            .output()
            .unwrap();
        assert_eq!(output.status.code(), Some(2));
        String::from_utf8_lossy(&output.stderr).into_owned()
    };
    let tip = "tip: this value comes from the environment variable";
    for (variable, value) in
        [("ESRP_MAX_EPISODES", "0"), ("ESRP_RENDER_RASTERIZER", "ray"), ("ESRP_RENDER_BACKEND", "metal")]
    {
        let stderr = start(&[], (variable, value));
        let flag = format!("--{}", variable.trim_start_matches("ESRP_").to_lowercase().replace('_', "-"));
        assert!(stderr.contains(&format!("invalid value '{value}' for '{flag}")), "{stderr}");
        assert!(stderr.contains(&format!("{tip} {variable}\n")), "{stderr}");
    }
    let stderr = start(&["--max-episodes", "0"], ("ESRP_MAX_EPISODES", "0"));
    assert!(stderr.contains("invalid value '0' for '--max-episodes") && !stderr.contains(tip), "{stderr}");
    let stderr = start(&["--max-episodes=0"], ("ESRP_MAX_EPISODES", "5"));
    assert!(!stderr.contains(tip), "{stderr}");
}

/// A switch's environment variable takes the usual spellings of on and off (1/0, yes/no, on/off,
/// true/false): `ESRP_STOP_ON_STDIN_CLOSE=0` leaves the server running when its stdin ends, `=1`
/// stops it. A spelling of neither is refused.
#[test]
fn a_switch_s_variable_takes_the_usual_spellings() {
    use std::io::BufRead;
    use std::process::{Command, Stdio};
    for (value, stops) in [("1", true), ("yes", true), ("on", true), ("0", false), ("no", false), ("off", false)] {
        let mut child = Command::new(env!("CARGO_BIN_EXE_esrp-server"))
            .args(["--listen", "127.0.0.1:0", "--no-generate-ahead"])
            .env("ESRP_STOP_ON_STDIN_CLOSE", value)
            .env("NODEVICE_SELECT", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        assert!(line.starts_with("esrp-server listening on"), "{value}: {line}");
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(if stops { 20 } else { 2 });
        let mut exited = None;
        while exited.is_none() && std::time::Instant::now() < deadline {
            exited = child.try_wait().unwrap();
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        if exited.is_none() {
            let _ = child.kill();
        }
        let _ = child.wait();
        assert_eq!(exited.is_some(), stops, "ESRP_STOP_ON_STDIN_CLOSE={value}: {exited:?}");
    }
    let output =
        Command::new(env!("CARGO_BIN_EXE_esrp-server")).env("ESRP_STOP_ON_STDIN_CLOSE", "maybe").output().unwrap();
    assert_eq!(output.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&output.stderr).contains("invalid value 'maybe' for '--stop-on-stdin-close'"));
}

/// A server drawing with the compute rasteriser (`--render-rasterizer compute`) says so in its
/// ServerInfo and answers the same observations as one drawing with the graphics pipeline, but
/// for a few edge pixels, along a scene's expert run.
#[tokio::test]
async fn the_compute_rasterizer_draws_what_the_pipeline_draws() {
    let pipeline = Server::start(&["--render-backend", "vulkan"]);
    let compute = Server::start(&["--render-backend", "vulkan", "--render-rasterizer", "compute"]);
    let mut observations = Vec::new();
    for (server, rasterizer) in [(&pipeline, "pipeline"), (&compute, "compute")] {
        let mut client = server.client().await;
        let info = client.server_info(proto::ServerInfoRequest {}).await.unwrap().into_inner();
        assert_eq!(info.renderer_rasterizer, rasterizer);
        let created = client.create_episode(create_request("esrp-bench-v2/00011", true)).await.unwrap().into_inner();
        let observation = created.observation.unwrap();
        let mut images = vec![observation.ego_rgb.unwrap().data, observation.goal_rgb.unwrap().data];
        for action in expert_actions(&mut client, &created.episode_id).await.into_iter().take(40) {
            let answer = client.step(step_request(&created.episode_id, action)).await.unwrap().into_inner();
            images.push(answer.observation.unwrap().ego_rgb.unwrap().data);
        }
        observations.push(images);
    }
    for (i, (a, b)) in observations[0].iter().zip(&observations[1]).enumerate() {
        assert_eq!(a.len(), b.len());
        let differ = a.chunks_exact(3).zip(b.chunks_exact(3)).filter(|(p, q)| p != q).count();
        assert!(differ * 200 < a.len() / 3, "image {i}: {differ} pixels differ");
    }
}
