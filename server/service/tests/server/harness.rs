//! Starts the real `esrp-server` binary on an ephemeral port and connects a client.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

use esrp_server::proto::esrp_client::EsrpClient;
use tonic::transport::Channel;

/// A running server process, killed on drop.
pub struct Server {
    child: Child,
    /// `http://127.0.0.1:PORT`.
    pub address: String,
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
        let mut line = String::new();
        BufReader::new(stdout).read_line(&mut line).expect("the server prints its address");
        let address = line.trim().rsplit(' ').next().expect("an address").to_owned();
        Server { child, address: format!("http://{address}") }
    }

    /// A connected client.
    pub async fn client(&self) -> EsrpClient<Channel> {
        EsrpClient::connect(self.address.clone()).await.expect("the client connects").max_decoding_message_size(256 << 20)
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
