//! Helpers for the bundled tools (`esrp-bench`, `esrp-demo`) and for embedding: connecting a
//! well-tuned channel and starting a local server process.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

use anyhow::{Context, bail};
use tonic::transport::Channel;

use crate::proto::esrp_client::EsrpClient;

/// Adds `authorization: Bearer TOKEN` to every call when a token is set.
#[derive(Clone, Debug, Default)]
pub struct Bearer(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request.metadata_mut().insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// A client of `esrp.v1` that sends the server's bearer token, if any.
pub type Client = EsrpClient<tonic::service::interceptor::InterceptedService<Channel, Bearer>>;

/// Connects to `address` (`http://host:port`) with settings suited to ESRP's traffic: no
/// Nagle delay (an agent waits for every answer) and HTTP/2 windows large enough for many
/// ~49 KB observations in flight. With `token`, every call carries `authorization: Bearer
/// TOKEN` (the server's `--token`).
pub async fn connect(address: &str, token: Option<&str>) -> anyhow::Result<Client> {
    let channel = Channel::from_shared(address.to_owned())
        .with_context(|| format!("{address:?} is not a URL like http://127.0.0.1:50051"))?
        .initial_connection_window_size(64 << 20)
        .initial_stream_window_size(16 << 20)
        .tcp_nodelay(true)
        .connect()
        .await
        .with_context(|| format!("cannot connect to {address}: is esrp-server running there?"))?;
    let bearer = match token {
        Some(token) => {
            Bearer(Some(format!("Bearer {token}").parse().context("the token must be printable ASCII without spaces")?))
        }
        None => Bearer(None),
    };
    Ok(EsrpClient::with_interceptor(channel, bearer)
        .max_decoding_message_size(256 << 20)
        .max_encoding_message_size(256 << 20))
}

/// An `esrp-server` child process on a free local port, killed on drop.
pub struct LocalServer {
    child: Child,
    /// `http://127.0.0.1:PORT`.
    pub address: String,
}

impl Drop for LocalServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl LocalServer {
    /// Starts `binary` (default: the `esrp-server` beside the running executable) with
    /// `--listen 127.0.0.1:0` and `args`, and waits until it listens.
    pub fn start(binary: Option<PathBuf>, args: &[String]) -> anyhow::Result<Self> {
        use std::io::{BufRead, BufReader};
        let binary = match binary {
            Some(b) => b,
            None => std::env::current_exe()?.with_file_name(format!("esrp-server{}", std::env::consts::EXE_SUFFIX)),
        };
        let mut child = Command::new(&binary)
            .args(["--listen", "127.0.0.1:0"])
            .args(args)
            .env("ESRP_LOG", std::env::var("ESRP_LOG").unwrap_or_else(|_| "warn".into()))
            .stdout(Stdio::piped())
            .spawn()
            .with_context(|| {
                format!("cannot start {} (build it with `cargo build --release -p esrp-server`)", binary.display())
            })?;
        let mut line = String::new();
        BufReader::new(child.stdout.take().context("no stdout")?).read_line(&mut line)?;
        let Some(address) = line.trim().strip_prefix("esrp-server listening on ") else {
            bail!("the server did not start: {line:?}");
        };
        Ok(Self { address: format!("http://{address}"), child })
    }

    /// The process's resident memory in bytes (Linux; `None` elsewhere).
    pub fn resident_bytes(&self) -> Option<u64> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).ok()?;
        let kib: u64 = status.lines().find(|l| l.starts_with("VmRSS:"))?.split_whitespace().nth(1)?.parse().ok()?;
        Some(kib * 1024)
    }
}
