//! Helpers for the bundled tools (`esrp-bench`, `esrp-demo`) and for embedding: connecting a
//! well-tuned channel and starting a local server process.

use std::ffi::OsStr;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, Stdio};

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
    /// The server's stdout, kept open: a closed pipe would make its later prints fail.
    _stdout: BufReader<ChildStdout>,
    /// `http://127.0.0.1:PORT`.
    pub address: String,
    /// `http://127.0.0.1:PORT/metrics`, when started with `--metrics-listen`.
    pub metrics: Option<String>,
}

impl Drop for LocalServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The server at `address` if given, else a local one started now with `binary` and `args`
/// (see [`LocalServer::start`]), running as long as the returned [`LocalServer`] lives.
pub fn reach_or_start(
    address: Option<&str>,
    binary: Option<PathBuf>,
    args: &[String],
) -> anyhow::Result<(String, Option<LocalServer>)> {
    match address {
        Some(address) => Ok((address.to_owned(), None)),
        None => {
            let local = LocalServer::start(binary, args)?;
            Ok((local.address.clone(), Some(local)))
        }
    }
}

impl LocalServer {
    /// Starts `binary` (default: the `esrp-server` beside the running executable) with
    /// `--listen 127.0.0.1:0` and `args`, and waits until it listens.
    pub fn start(binary: Option<PathBuf>, args: &[String]) -> anyhow::Result<Self> {
        Self::spawn(Self::command(binary, args)?)
    }

    /// The command [`LocalServer::start`] runs, for callers that adjust it (environment,
    /// stderr) before [`LocalServer::spawn`]: `esrp-server --listen 127.0.0.1:0 ARGS`, with
    /// `ESRP_LOG` at `warn` unless set.
    pub fn command<S: AsRef<OsStr>>(binary: Option<PathBuf>, args: &[S]) -> anyhow::Result<Command> {
        let binary = match binary {
            Some(b) => b,
            None => std::env::current_exe()?.with_file_name(format!("esrp-server{}", std::env::consts::EXE_SUFFIX)),
        };
        let mut command = Command::new(binary);
        command
            .args(["--listen", "127.0.0.1:0"])
            .args(args)
            .env("ESRP_LOG", std::env::var("ESRP_LOG").unwrap_or_else(|_| "warn".into()));
        Ok(command)
    }

    /// Spawns a server `command` with its stdout piped and waits until it listens; with
    /// `--metrics-listen` among its arguments, reads the metrics address too.
    pub fn spawn(mut command: Command) -> anyhow::Result<Self> {
        let with_metrics = command.get_args().any(|a| a == "--metrics-listen");
        let mut child = command.stdout(Stdio::piped()).spawn().with_context(|| {
            format!(
                "cannot start {} (build it with `cargo build --release -p esrp-server`)",
                Path::new(command.get_program()).display()
            )
        })?;
        let mut stdout = BufReader::new(child.stdout.take().context("no stdout")?);
        let mut line = String::new();
        stdout.read_line(&mut line)?;
        let Some(address) = line.trim().strip_prefix("esrp-server listening on ") else {
            bail!("the server did not start: {line:?}");
        };
        let address = format!("http://{address}");
        let metrics = if with_metrics {
            let mut line = String::new();
            stdout.read_line(&mut line)?;
            let Some(url) = line.trim().strip_prefix("esrp-server metrics on ") else {
                bail!("the server did not print its metrics address: {line:?}");
            };
            Some(url.to_owned())
        } else {
            None
        };
        Ok(Self { child, _stdout: stdout, address, metrics })
    }

    /// Whether the process is still running.
    pub fn is_running(&mut self) -> bool {
        self.child.try_wait().map(|s| s.is_none()).unwrap_or(false)
    }

    /// The process's resident memory in bytes (Linux; `None` elsewhere).
    pub fn resident_bytes(&self) -> Option<u64> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).ok()?;
        let kib: u64 = status.lines().find(|l| l.starts_with("VmRSS:"))?.split_whitespace().nth(1)?.parse().ok()?;
        Some(kib * 1024)
    }
}
