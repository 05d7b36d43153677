//! [`LocalServer`]: an `esrp-server` child process on a free local port, for tools, tests and
//! notebooks that want a server without a second terminal.

use std::ffi::{OsStr, OsString};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

use crate::client::{Client, ConnectBuilder};
use crate::error::{ClientError, Result};

/// The server binary's file name on this platform.
fn binary_name() -> String {
    format!("esrp-server{}", std::env::consts::EXE_SUFFIX)
}

/// Where [`LocalServer`] looks for `esrp-server`, in order: `ESRP_SERVER_BIN`; beside the
/// running executable (and its parent folder, for test binaries in `target/*/deps`); `PATH`;
/// this workspace's `target/release` and `target/debug` (or `CARGO_TARGET_DIR`'s).
pub fn find_server_binary() -> Result<PathBuf> {
    if let Some(path) = std::env::var_os("ESRP_SERVER_BIN") {
        let path = PathBuf::from(path);
        return if path.is_file() {
            Ok(path)
        } else {
            Err(ClientError::LocalServer(format!("ESRP_SERVER_BIN={} is not a file", path.display())))
        };
    }
    let mut candidates = Vec::new();
    if let Ok(exe) = std::env::current_exe() {
        for dir in exe.ancestors().skip(1).take(2) {
            candidates.push(dir.join(binary_name()));
        }
    }
    if let Some(path) = std::env::var_os("PATH") {
        candidates.extend(std::env::split_paths(&path).map(|dir| dir.join(binary_name())));
    }
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target"));
    candidates.extend(["release", "debug"].map(|profile| target.join(profile).join(binary_name())));
    candidates.into_iter().find(|c| c.is_file()).ok_or_else(|| {
        ClientError::LocalServer(format!(
            "cannot find {}: build it with `cargo build --release -p esrp-server`, put it on PATH, or set ESRP_SERVER_BIN",
            binary_name()
        ))
    })
}

/// An `esrp-server` child process on a free local port, killed on drop. It is started with
/// `--stop-on-stdin-close` and a pipe on its stdin held here, so it also stops when this
/// process ends without dropping it (a signal's default action, `std::process::exit`, SIGKILL).
#[derive(Debug)]
pub struct LocalServer {
    child: Child,
    /// The server's stdin: the server stops when it is closed (by drop or by this process's end).
    _stdin: Option<ChildStdin>,
    /// The server's stdout, kept open: a closed pipe would make its later prints fail.
    _stdout: BufReader<ChildStdout>,
    /// `http://127.0.0.1:PORT`.
    pub address: String,
    /// `unix:PATH`, the server's Unix domain socket, when started with `--listen-unix` (see
    /// [`LocalServer::url`]).
    pub unix: Option<String>,
    /// `http://127.0.0.1:PORT/metrics`, when started with `--metrics-listen`.
    pub metrics: Option<String>,
    /// `http://127.0.0.1:PORT/`, the web viewer, when started with `--http-listen`.
    pub viewer: Option<String>,
}

impl Drop for LocalServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        // A killed server leaves its socket file behind.
        if let Some(path) = self.unix.as_deref().and_then(|url| url.strip_prefix("unix:")) {
            let _ = std::fs::remove_file(path);
        }
    }
}

/// The longest path a socket may have here and on macOS (`sockaddr_un`: 104 bytes there, 108 on
/// Linux, with the final zero).
const SOCKET_PATH_BYTES: usize = 104;

/// `args` with `--listen-unix` and a fresh [`socket_path`] added, so that the started server's
/// [`LocalServer::url`] is its Unix domain socket (less kernel work per step than loopback TCP
/// for the clients of this machine); unchanged where they already name a socket or ask for TLS
/// (the socket serves plain HTTP/2 only), or where the temporary folder is too deep for a
/// socket's path (the server is then reached over TCP).
pub fn with_socket<S: AsRef<OsStr>>(args: &[S]) -> Vec<OsString> {
    let named = |flag| names_flag(args.iter().map(AsRef::as_ref), flag);
    let mut out: Vec<OsString> = args.iter().map(|a| a.as_ref().to_owned()).collect();
    let path = socket_path();
    if !named("--listen-unix") && !named("--tls-cert") && path.as_os_str().len() < SOCKET_PATH_BYTES {
        out.extend(["--listen-unix".into(), path.into_os_string()]);
    }
    out
}

/// Whether `args` give `flag` (`--flag VALUE` or `--flag=VALUE`).
fn names_flag<'a>(mut args: impl Iterator<Item = &'a OsStr>, flag: &str) -> bool {
    args.any(|a| {
        let a = a.as_encoded_bytes();
        a == flag.as_bytes() || a.strip_prefix(flag.as_bytes()).is_some_and(|rest| rest.starts_with(b"="))
    })
}

/// A fresh path for a local server's Unix domain socket (`--listen-unix`), in the temporary
/// folder: `esrp-server-PID-N.sock`.
pub fn socket_path() -> PathBuf {
    static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    std::env::temp_dir().join(format!("esrp-server-{}-{n:x}.sock", std::process::id()))
}

/// The server at `address` if given, else a local one started now with `binary` and `args`
/// (see [`LocalServer::start`]; its [`LocalServer::url`]), running as long as the returned
/// [`LocalServer`] lives.
pub fn reach_or_start<S: AsRef<OsStr>>(
    address: Option<&str>,
    binary: Option<PathBuf>,
    args: &[S],
) -> Result<(String, Option<LocalServer>)> {
    match address {
        Some(address) => Ok((address.to_owned(), None)),
        None => {
            let local = LocalServer::start(binary, args)?;
            Ok((local.url().to_owned(), Some(local)))
        }
    }
}

impl LocalServer {
    /// Starts `binary` (default: [`find_server_binary`]) with `--listen 127.0.0.1:0` and
    /// `args`, and waits until it listens.
    pub fn start<S: AsRef<OsStr>>(binary: Option<PathBuf>, args: &[S]) -> Result<Self> {
        Self::spawn(Self::command(binary, args)?)
    }

    /// The command [`LocalServer::start`] runs, for callers that adjust it (environment,
    /// stderr) before [`LocalServer::spawn`]: `esrp-server --listen 127.0.0.1:0
    /// --stop-on-stdin-close ARGS`, with `ESRP_LOG` at `warn` unless set (and no
    /// `ESRP_LISTEN_UNIX` from this process's environment: see [`with_socket`]).
    pub fn command<S: AsRef<OsStr>>(binary: Option<PathBuf>, args: &[S]) -> Result<Command> {
        let binary = match binary {
            Some(b) => b,
            None => find_server_binary()?,
        };
        let mut command = Command::new(binary);
        command
            .args(["--listen", "127.0.0.1:0", "--stop-on-stdin-close"])
            .args(args)
            .env("ESRP_LOG", std::env::var("ESRP_LOG").unwrap_or_else(|_| "warn".into()))
            // A socket comes from the arguments only (`with_socket`): one inherited from this
            // process's environment would print a line `spawn` does not expect.
            .env_remove("ESRP_LISTEN_UNIX");
        Ok(command)
    }

    /// Spawns a server `command` with its stdin and stdout piped and waits until it listens; with
    /// `--listen-unix`, `--metrics-listen` or `--http-listen` among its arguments, reads the
    /// socket's, the metrics' or the viewer's address too. A process that ends or prints
    /// something else first, or prints no listening line within [`START_TIMEOUT`], is killed and
    /// reaped, and the error says so.
    pub fn spawn(command: Command) -> Result<Self> {
        Self::spawn_within(command, START_TIMEOUT)
    }

    /// [`LocalServer::spawn`], waiting at most `timeout` for the server's lines.
    pub fn spawn_within(mut command: Command, timeout: std::time::Duration) -> Result<Self> {
        let with_unix = names_flag(command.get_args(), "--listen-unix")
            || command
                .get_envs()
                .any(|(name, value)| name == "ESRP_LISTEN_UNIX" && value.is_some_and(|v| !v.is_empty()));
        let with_metrics = names_flag(command.get_args(), "--metrics-listen");
        let with_viewer = names_flag(command.get_args(), "--http-listen");
        // The lines to read, in the order the server prints them.
        let mut wanted = vec!["esrp-server listening on "];
        wanted.extend(with_unix.then_some("esrp-server listening on "));
        wanted.extend(with_metrics.then_some("esrp-server metrics on "));
        wanted.extend(with_viewer.then_some("esrp-server viewer on "));
        let program = Path::new(command.get_program()).display().to_string();
        let mut child = command.stdin(Stdio::piped()).stdout(Stdio::piped()).spawn().map_err(|e| {
            ClientError::LocalServer(format!(
                "cannot start {program}: {e} (build it with `cargo build --release -p esrp-server`)"
            ))
        })?;
        let Some(stdout) = child.stdout.take() else {
            stop(&mut child);
            return Err(ClientError::LocalServer("no stdout".into()));
        };
        // The lines are read on a thread of their own, so that a server that prints nothing
        // cannot hold this one past `timeout`; killing it ends the thread's read.
        let (sender, lines) = std::sync::mpsc::channel();
        let reader_program = program.clone();
        std::thread::spawn(move || {
            let mut stdout = BufReader::new(stdout);
            let values: Result<Vec<String>> =
                wanted.iter().map(|prefix| read_value(&mut stdout, prefix, &reader_program)).collect();
            let _ = sender.send((values, stdout));
        });
        let (values, stdout) = match lines.recv_timeout(timeout) {
            Ok((Ok(values), stdout)) => (values, stdout),
            Ok((Err(error), _)) => {
                stop(&mut child);
                return Err(error);
            }
            Err(_) => {
                stop(&mut child);
                return Err(ClientError::LocalServer(format!(
                    "{program} printed no listening line within {:?}: stopped it",
                    timeout
                )));
            }
        };
        let mut values = values.into_iter();
        let address = format!("http://{}", values.next().unwrap_or_default());
        let unix = if with_unix { values.next() } else { None };
        let metrics = if with_metrics { values.next() } else { None };
        let viewer = if with_viewer { values.next() } else { None };
        Ok(Self { _stdin: child.stdin.take(), child, _stdout: stdout, address, unix, metrics, viewer })
    }

    /// What a client on this machine connects to: the Unix domain socket (`unix:PATH`) when
    /// there is one, else the TCP `address`.
    pub fn url(&self) -> &str {
        self.unix.as_deref().unwrap_or(&self.address)
    }

    /// Connection settings for this server, at its [`LocalServer::url`] (add a token or TLS,
    /// then `.await`).
    pub fn connect(&self) -> ConnectBuilder {
        Client::connect(self.url().to_owned())
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Whether the process is still running.
    pub fn is_running(&mut self) -> bool {
        self.child.try_wait().map(|s| s.is_none()).unwrap_or(false)
    }

    /// The process's exit status if it has exited, `None` while it runs.
    pub fn try_wait(&mut self) -> Option<std::process::ExitStatus> {
        self.child.try_wait().ok().flatten()
    }

    /// The process's resident memory in bytes (Linux; `None` elsewhere).
    pub fn resident_bytes(&self) -> Option<u64> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).ok()?;
        let kib: u64 = status.lines().find(|l| l.starts_with("VmRSS:"))?.split_whitespace().nth(1)?.parse().ok()?;
        Some(kib * 1024)
    }

    /// Waits for the process to exit (after a signal sent with [`LocalServer::pid`]) and
    /// returns its status.
    pub fn wait(&mut self) -> Result<std::process::ExitStatus> {
        self.child.wait().map_err(|e| ClientError::LocalServer(format!("cannot wait for the server: {e}")))
    }
}

/// How long [`LocalServer::spawn`] waits for the server's listening lines. A server prints them
/// once its sockets are bound, before its dataset and renderer are checked: in well under a
/// second, unless something is badly wrong.
pub const START_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(60);

/// Kills `child` (if it still runs) and reaps it.
fn stop(child: &mut Child) {
    let _ = child.kill();
    let _ = child.wait();
}

/// The rest of the first line of `stdout` that starts with `prefix`. The server's own lines
/// start with `esrp-server `; log lines its start wrote to stdout before them (a driver's
/// complaint while the renderer is made) are passed over. Another `esrp-server ` line first, or
/// the output's end, is an error: the server did not start.
fn read_value(stdout: &mut BufReader<ChildStdout>, prefix: &str, program: &str) -> Result<String> {
    loop {
        let mut line = String::new();
        let read = stdout
            .read_line(&mut line)
            .map_err(|e| ClientError::LocalServer(format!("cannot read {program}'s output: {e}")))?;
        if let Some(value) = line.trim().strip_prefix(prefix) {
            return Ok(value.to_owned());
        }
        if read == 0 || line.starts_with("esrp-server ") {
            return Err(ClientError::LocalServer(format!(
                "{program} did not start (it printed {line:?}; its stderr says why)"
            )));
        }
    }
}

/// How long [`first_contact`] waits for a local server that failed to serve to exit.
const EXIT_GRACE: std::time::Duration = std::time::Duration::from_secs(3);

/// Connects with `connect` and asks the server's [`crate::ServerInfo`]: a tool's first
/// contact with its server. When that fails and `local` (the server the tool started) has
/// exited, or exits within a few seconds, the error says so, rather than the connection's
/// refusal: a server prints its listening line once bound, before its configuration (a dataset,
/// a renderer) is checked, and says on its stderr why it cannot serve.
pub async fn first_contact(
    connect: ConnectBuilder,
    local: Option<&mut LocalServer>,
) -> Result<(Client, crate::types::ServerInfo)> {
    let contact = async {
        let client = connect.await?;
        let info = client.server_info().await?;
        Ok((client, info))
    };
    let error = match contact.await {
        Ok(contact) => return Ok(contact),
        Err(error) => error,
    };
    let Some(local) = local else { return Err(error) };
    let deadline = tokio::time::Instant::now() + EXIT_GRACE;
    loop {
        if let Some(status) = local.try_wait() {
            return Err(ClientError::LocalServer(format!(
                "esrp-server {} before it served (its stderr, above, says why)",
                describe_exit(status)
            )));
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(error);
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
}

/// `exited with status 1`, `exited with signal 9`.
pub fn describe_exit(status: std::process::ExitStatus) -> String {
    #[cfg(unix)]
    {
        use std::os::unix::process::ExitStatusExt;
        if let Some(signal) = status.signal() {
            return format!("exited with signal {signal}");
        }
    }
    status.code().map_or_else(|| format!("exited ({status})"), |code| format!("exited with status {code}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn with_socket_adds_a_fresh_socket_unless_one_is_named_or_tls_asked() {
        let added = with_socket(&["--max-episodes", "8"]);
        assert_eq!(added.len(), 4);
        assert_eq!(added[2], "--listen-unix");
        let path = PathBuf::from(&added[3]);
        assert!(path.starts_with(std::env::temp_dir()) && path.extension() == Some(OsStr::new("sock")), "{path:?}");
        assert_ne!(with_socket::<&str>(&[])[1], added[3], "each call a fresh path");
        for named in [
            &["--listen-unix", "/tmp/a.sock"][..],
            &["--listen-unix=/tmp/a.sock"],
            &["--tls-cert", "c.pem", "--tls-key", "k.pem"],
            &["--tls-cert=c.pem"],
        ] {
            assert_eq!(with_socket(named), named.iter().map(OsString::from).collect::<Vec<_>>(), "{named:?}");
        }
        // A flag that only starts like it is not it.
        assert_eq!(with_socket(&["--listen-unixish"]).len(), 3);
    }
}
