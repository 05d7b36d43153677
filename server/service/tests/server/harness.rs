//! Starts the real `esrp-server` binary on an ephemeral port and connects a client.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

use esrp_server::proto;
use esrp_server::proto::esrp_client::EsrpClient;
use tonic::transport::Channel;

/// A running server process, killed on drop.
pub struct Server {
    child: Child,
    /// `http://127.0.0.1:PORT`.
    pub address: String,
    /// `http://127.0.0.1:PORT/metrics`, when started with `--metrics-listen`.
    pub metrics: Option<String>,
}

impl Server {
    /// Starts `esrp-server --listen 127.0.0.1:0` with extra `args`.
    pub fn start(args: &[&str]) -> Server {
        let mut child = Command::new(env!("CARGO_BIN_EXE_esrp-server"))
            .args(["--listen", "127.0.0.1:0"])
            .args(args)
            .env("NODEVICE_SELECT", "1")
            .env("ESRP_LOG", "warn")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("the server binary starts");
        let stdout = child.stdout.take().expect("stdout is piped");
        let mut stdout = BufReader::new(stdout);
        let mut line = String::new();
        stdout.read_line(&mut line).expect("the server prints its address");
        let address = line.trim().rsplit(' ').next().expect("an address").to_owned();
        let metrics = args.contains(&"--metrics-listen").then(|| {
            let mut line = String::new();
            stdout.read_line(&mut line).expect("the server prints its metrics address");
            line.trim().rsplit(' ').next().expect("a metrics URL").to_owned()
        });
        Server { child, address: format!("http://{address}"), metrics }
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

    /// Whether the process is still running.
    pub fn is_running(&mut self) -> bool {
        self.child.try_wait().map(|s| s.is_none()).unwrap_or(false)
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
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

/// SplitMix64: a tiny deterministic generator for random action sequences.
pub struct SplitMix(pub u64);

impl SplitMix {
    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A random action code, 0..6.
    pub fn action(&mut self) -> i32 {
        (self.next_u64() % 6) as i32
    }
}

/// A digest of everything a step response says (observation bytes included), for comparing
/// runs: FNV-1a over the encoded message.
pub fn digest(response: &proto::StepResponse) -> u64 {
    use prost::Message;
    let bytes = response.encode_to_vec();
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

impl Server {
    /// The server process's resident memory in bytes (Linux; `None` elsewhere).
    pub fn resident_bytes(&self) -> Option<u64> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).ok()?;
        let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
        let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some(kib * 1024)
    }
}
