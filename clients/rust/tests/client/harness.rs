//! Starts the real server binary for a test.

use esrp_client::{Client, LocalServer};

/// Starts `esrp-server` with `args` (stderr shown, logs at warn).
pub fn start(args: &[&str]) -> LocalServer {
    let mut command = LocalServer::command(None, args).expect("esrp-server is built (cargo build -p esrp-server)");
    command.env("NODEVICE_SELECT", "1").stderr(std::process::Stdio::inherit());
    LocalServer::spawn(command).expect("the server starts and listens")
}

/// A plain client of `server`.
pub async fn client(server: &LocalServer) -> Client {
    server.connect().await.expect("the client connects")
}

/// The ids of the first `n` test scenes.
pub async fn test_scenes(client: &Client, n: usize) -> Vec<String> {
    use tokio_stream::StreamExt;
    let filter = esrp_client::SceneFilter::split(esrp_client::Split::Test);
    client.scenes(filter).take(n).map(|s| s.expect("a scene").id).collect().await
}

/// The server's live episode count once it reaches `expected`, or after 5 s of polling (closes
/// on drop and after abandoned calls happen in background tasks).
pub async fn live_episodes_settled_at(client: &Client, expected: u32) -> u32 {
    let mut live = u32::MAX;
    for _ in 0..100 {
        live = client.server_info().await.expect("ServerInfo answers").live_episodes;
        if live == expected {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    live
}

/// A self-signed certificate for `localhost` and its key, written as `cert.pem` and `key.pem` in
/// `dir`: the certificate's PEM and the two paths (as `--tls-cert` and `--tls-key` take them).
pub fn localhost_certificate(dir: &std::path::Path) -> (String, String, String) {
    let rcgen::CertifiedKey { cert, signing_key } =
        rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).expect("a certificate");
    let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).expect("the certificate is written");
    std::fs::write(&key_path, signing_key.serialize_pem()).expect("the key is written");
    (cert.pem(), cert_path.display().to_string(), key_path.display().to_string())
}
