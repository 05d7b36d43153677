//! Starts the real `esrp-server` binary on an ephemeral port and connects a client.

use esrp_client::LocalServer;
use esrp_server::proto;
use esrp_server::proto::esrp_client::EsrpClient;
use tonic::transport::Channel;

/// A running server process (the test build of the binary), killed on drop.
pub struct Server(LocalServer);

impl std::ops::Deref for Server {
    type Target = LocalServer;

    fn deref(&self) -> &LocalServer {
        &self.0
    }
}

impl std::ops::DerefMut for Server {
    fn deref_mut(&mut self) -> &mut LocalServer {
        &mut self.0
    }
}

impl Server {
    /// Starts `esrp-server --listen 127.0.0.1:0` with extra `args`, generating no scene ahead
    /// (a test of its own does; elsewhere it would only take the cores other tests use).
    pub fn start(args: &[&str]) -> Server {
        Self::start_with_env(args, &[("ESRP_NO_GENERATE_AHEAD", "true")])
    }

    /// Starts `esrp-server --listen 127.0.0.1:0` with extra `args` and environment `env`.
    pub fn start_with_env(args: &[&str], env: &[(&str, &str)]) -> Server {
        let mut command =
            LocalServer::command(Some(env!("CARGO_BIN_EXE_esrp-server").into()), args).expect("the server command");
        command.env("NODEVICE_SELECT", "1").env("ESRP_LOG", "warn").stderr(std::process::Stdio::inherit());
        command.envs(env.iter().copied());
        Server(LocalServer::spawn(command).expect("the server binary starts and listens"))
    }

    /// Fetches the Prometheus text from the metrics endpoint (plain HTTP/1.0 over a socket).
    pub fn scrape(&self) -> String {
        use std::io::{Read, Write};
        let url = self.metrics.as_deref().expect("started with --metrics-listen");
        let host = url.trim_start_matches("http://").trim_end_matches("/metrics");
        let mut socket = std::net::TcpStream::connect(host).expect("the metrics endpoint accepts");
        write!(socket, "GET /metrics HTTP/1.0\r\nHost: {host}\r\n\r\n").unwrap();
        let mut response = String::new();
        socket.read_to_string(&mut response).unwrap();
        assert!(response.starts_with("HTTP/1.0 200") || response.starts_with("HTTP/1.1 200"), "{response}");
        response
    }

    /// One HTTP/1.0 request to the web viewer (`--http-listen`), with `Authorization: Bearer
    /// SECRET` if given; returns the status code and the body.
    pub async fn viewer_request(&self, method: &str, path: &str, secret: Option<&str>, body: &str) -> (u16, String) {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let url = self.viewer.as_deref().expect("started with --http-listen");
        let host = url.trim_start_matches("http://").trim_end_matches('/');
        let mut socket = tokio::net::TcpStream::connect(host).await.expect("the viewer accepts");
        let authorization = secret.map(|s| format!("Authorization: Bearer {s}\r\n")).unwrap_or_default();
        let request = format!(
            "{method} {path} HTTP/1.0\r\nHost: {host}\r\n{authorization}Content-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        );
        socket.write_all(request.as_bytes()).await.unwrap();
        let mut response = String::new();
        socket.read_to_string(&mut response).await.unwrap();
        let status = response.split(' ').nth(1).and_then(|s| s.parse().ok()).expect("a status line");
        let body = response.split_once("\r\n\r\n").map(|(_, b)| b.to_owned()).unwrap_or_default();
        (status, body)
    }

    /// A connected client.
    pub async fn client(&self) -> EsrpClient<Channel> {
        EsrpClient::connect(self.address.clone())
            .await
            .expect("the client connects")
            .max_decoding_message_size(256 << 20)
    }

    /// A plaintext client that may fail to connect (an error on the first call instead).
    pub async fn client_unchecked(&self) -> EsrpClient<Channel> {
        EsrpClient::new(Channel::from_shared(self.address.clone()).expect("a URL").connect_lazy())
    }
}

/// A create request for a scene of the served dataset.
pub fn create_request(scene_id: &str, privileged: bool) -> proto::CreateEpisodeRequest {
    proto::CreateEpisodeRequest {
        scene: Some(proto::create_episode_request::Scene::SceneId(scene_id.to_owned())),
        privileged,
        ..Default::default()
    }
}

/// A step request without the goal image.
pub fn step_request(episode_id: &str, action: i32) -> proto::StepRequest {
    proto::StepRequest { episode_id: episode_id.to_owned(), action, include_goal: false }
}

/// The ids of the first `n` scenes of `split` in the served dataset.
pub async fn scene_ids(client: &mut EsrpClient<Channel>, split: proto::Split, n: usize) -> Vec<String> {
    let page = client
        .list_scenes(proto::ListScenesRequest { split: split as i32, page_size: n as u32, ..Default::default() })
        .await
        .expect("ListScenes answers")
        .into_inner();
    page.scenes.into_iter().map(|s| s.id).take(n).collect()
}

/// The expert action codes of a privileged episode's scene.
pub async fn expert_actions(client: &mut EsrpClient<Channel>, episode_id: &str) -> Vec<i32> {
    let state = client
        .get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: episode_id.to_owned() })
        .await
        .expect("GetPrivilegedState answers a privileged episode")
        .into_inner();
    let scene = esrp_core::Scene::from_json(&state.scene_json).expect("the server sends valid scene JSON");
    scene.expert_trajectory.iter().map(|a| i32::from(a.code())).collect()
}

/// The number of live episodes the server reports.
pub async fn live_episodes(client: &mut EsrpClient<Channel>) -> u32 {
    client.server_info(proto::ServerInfoRequest {}).await.expect("ServerInfo answers").into_inner().live_episodes
}

/// A random action code, 0..6, from the project's portable seeded random source.
pub fn random_action(dice: &mut esrp_dataset::dice::Dice) -> i32 {
    dice.below(6) as i32
}

/// A digest of everything a step response says (observation bytes included), for comparing
/// runs: FNV-1a over the encoded message.
pub fn digest(response: &proto::StepResponse) -> u64 {
    use prost::Message;
    let bytes = response.encode_to_vec();
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}
