//! `esrp-server`: parses the configuration, sets up logging and serves until SIGINT/SIGTERM/SIGHUP;
//! `esrp-server health-check` asks a running server whether it is serving.

// Proving `esrp_server::run`'s future Send walks deep into wgpu's types (as in the library).
#![recursion_limit = "256"]

mod health_check;

use clap::{CommandFactory, Parser, Subcommand};
use esrp_server::Config;
use esrp_server::config::LogFormat;

/// The command line: the server's flags, or a subcommand.
#[derive(Debug, Parser)]
#[command(
    name = "esrp-server",
    version,
    about = "The ESRP environment server (gRPC)",
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(flatten)]
    config: Config,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Ask a running server's grpc.health.v1 service whether it is serving: exit 0 if it is,
    /// 1 with a one-line reason otherwise (container HEALTHCHECK, Kubernetes exec probes). It
    /// reads the server's ESRP_* variables for its defaults (the address from ESRP_LISTEN, TLS
    /// from ESRP_TLS_CERT).
    HealthCheck(health_check::HealthCheckArgs),
}

/// SIGINT, SIGTERM and SIGHUP, listened for from the moment this is made: a signal that arrives
/// before anything awaits [`Signals::wait`] (while the renderer starts, say) is kept, not lost,
/// and does not kill the process. With `--stop-on-stdin-close`, the end of standard input too.
struct Signals {
    #[cfg(unix)]
    interrupt: tokio::signal::unix::Signal,
    #[cfg(unix)]
    terminate: tokio::signal::unix::Signal,
    /// SIGHUP (the terminal or SSH session the server was started from went away), unless the
    /// server was started ignoring it (`nohup`): left to its default, it ended the process at
    /// once, its open episodes unrecorded and its Unix socket file left behind.
    #[cfg(unix)]
    hangup: Option<tokio::signal::unix::Signal>,
    stdin_closed: Option<tokio::sync::oneshot::Receiver<()>>,
}

impl Signals {
    /// Installs the handlers (call before announcing the address: once a client or a script can
    /// see the server, its signals must mean a graceful shutdown).
    fn install(stop_on_stdin_close: bool) -> anyhow::Result<Self> {
        let stdin_closed = if stop_on_stdin_close { Some(watch_stdin()?) } else { None };
        #[cfg(unix)]
        {
            use tokio::signal::unix::{SignalKind, signal};
            let error = |e: std::io::Error| anyhow::anyhow!("cannot install the SIGINT/SIGTERM handlers: {e}");
            let hangup = if hangup_ignored() {
                None
            } else {
                let error = |e: std::io::Error| anyhow::anyhow!("cannot install the SIGHUP handler: {e}");
                Some(signal(SignalKind::hangup()).map_err(error)?)
            };
            Ok(Self {
                interrupt: signal(SignalKind::interrupt()).map_err(error)?,
                terminate: signal(SignalKind::terminate()).map_err(error)?,
                hangup,
                stdin_closed,
            })
        }
        #[cfg(not(unix))]
        Ok(Self { stdin_closed })
    }

    /// Completes on the first SIGINT, SIGTERM or SIGHUP (Ctrl-C elsewhere), or the end of stdin
    /// when watched.
    async fn wait(self) {
        let stdin_closed = async move {
            match self.stdin_closed {
                Some(closed) => {
                    let _ = closed.await;
                    tracing::info!("standard input closed (--stop-on-stdin-close)");
                }
                None => std::future::pending().await,
            }
        };
        #[cfg(unix)]
        {
            let (mut interrupt, mut terminate) = (self.interrupt, self.terminate);
            let hangup = async move {
                match self.hangup {
                    Some(mut hangup) => {
                        hangup.recv().await;
                        tracing::info!("SIGHUP: the terminal or session that started the server went away");
                    }
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                _ = interrupt.recv() => {},
                _ = terminate.recv() => {},
                () = hangup => {},
                () = stdin_closed => {},
            }
        }
        #[cfg(not(unix))]
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {},
            () = stdin_closed => {},
        }
        tracing::info!("shutting down");
    }
}

/// Whether SIGHUP is ignored, as `nohup` (or a parent that set it so) leaves it: then it stays
/// ignored, as the one who started the server asked.
#[cfg(unix)]
#[allow(unsafe_code)]
fn hangup_ignored() -> bool {
    // SAFETY: sigaction with a null new action only reads the current disposition into `old`,
    // a zeroed plain C struct that it fills.
    unsafe {
        let mut old: libc::sigaction = std::mem::zeroed();
        libc::sigaction(libc::SIGHUP, std::ptr::null(), &mut old) == 0 && old.sa_sigaction == libc::SIG_IGN
    }
}

/// Reads standard input to its end on a thread of its own (not the runtime's: a blocking read
/// there would hold up the runtime's shutdown while the parent keeps the pipe open); the receiver
/// completes at the end, or at a read error.
fn watch_stdin() -> anyhow::Result<tokio::sync::oneshot::Receiver<()>> {
    let (closed, receiver) = tokio::sync::oneshot::channel();
    std::thread::Builder::new()
        .name("esrp-stdin".into())
        .spawn(move || {
            let mut sink = std::io::sink();
            let _ = std::io::copy(&mut std::io::stdin().lock(), &mut sink);
            let _ = closed.send(());
        })
        .map_err(|e| anyhow::anyhow!("cannot start the thread that watches stdin: {e}"))?;
    Ok(receiver)
}

/// Mesa's CPU renderers (llvmpipe, lavapipe) rasterise with a pool of `LP_NUM_THREADS`
/// threads (one per core by default). On a few cores, handing every small view to that pool
/// costs more than it saves: rasterising in the submitting thread (the render thread for
/// llvmpipe through OpenGL, lavapipe's queue thread for Vulkan) measured 1.3-1.7x the steps/s
/// on 2 cores. So unless the user chose, machines with at most 4 cores do that.
#[allow(unsafe_code)]
fn default_lavapipe_threads() {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if std::env::var_os("LP_NUM_THREADS").is_none() && cores <= 4 {
        // SAFETY: called in `main` right after parsing the command line, before any other
        // thread exists (the async runtime is built after), so nothing reads the environment
        // concurrently.
        unsafe { std::env::set_var("LP_NUM_THREADS", "0") };
    }
}

/// Runs the server (or its health check); an error that ends it is one line, `esrp-server: what
/// failed: why`, and status 1 (never a backtrace, whatever `RUST_BACKTRACE` says).
fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("esrp-server: {}", health_check::one_line(&error));
            std::process::ExitCode::FAILURE
        }
    }
}

fn run() -> anyhow::Result<()> {
    let args: Vec<std::ffi::OsString> = std::env::args_os().collect();
    let Cli { config, command } = Cli::try_parse_from(&args)
        .unwrap_or_else(|error| esrp_server::config::tell_the_variable(error, &Cli::command(), &args).exit());
    if let Some(Command::HealthCheck(args)) = command {
        match health_check::run(&args, &config) {
            Ok(answer) => {
                println!("{answer}");
                return Ok(());
            }
            Err(error) => {
                // One line, for `docker inspect` and probe events.
                eprintln!("esrp-server health-check: {}", health_check::one_line(&error));
                std::process::exit(1);
            }
        }
    }
    default_lavapipe_threads();
    // One name for the async workers and the blocking pool (planning): `esrp_thread_cpu_seconds_total`
    // counts their CPU as `esrp-runtime`.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(config.worker_threads())
        .thread_name("esrp-runtime")
        .enable_all()
        .build()?;
    let result = runtime.block_on(serve(config));
    // Dropping the runtime waits for its blocking tasks and drops every task, and with them the
    // episodes, scenes and renderer they hold: all of that is released here, before `main`
    // returns, never while the process runs its exit handlers.
    drop(runtime);
    result
}

async fn serve(config: Config) -> anyhow::Result<()> {
    let filter = tracing_subscriber::EnvFilter::try_from_env("ESRP_LOG").unwrap_or_else(|_| "info".into());
    match config.log_format {
        LogFormat::Text => {
            // Colours only for a person at a terminal: not in a file or a pipe, nor with NO_COLOR.
            use std::io::IsTerminal;
            let colour = std::io::stdout().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
            tracing_subscriber::fmt().with_ansi(colour).with_env_filter(filter).init()
        }
        LogFormat::Json => tracing_subscriber::fmt().json().with_env_filter(filter).init(),
    }
    let signals = Signals::install(config.stop_on_stdin_close)?;
    let listener = tokio::net::TcpListener::bind(config.listen)
        .await
        .map_err(|e| anyhow::anyhow!("cannot listen on {}: {e}", config.listen))?;
    // Tests and scripts read the bound address (useful with port 0) from this line, the first on
    // stdout: it is printed before anything that may log (the renderer's driver does).
    println!("esrp-server listening on {}", listener.local_addr()?);
    // With --listen-unix, the socket's line comes next (`unix:PATH`, what local clients connect to).
    let unix = match &config.listen_unix {
        Some(path) => {
            let socket = esrp_server::listen::UnixSocket::bind(path)?;
            let shown = std::path::absolute(path).unwrap_or_else(|_| path.clone());
            println!("esrp-server listening on unix:{}", shown.display());
            Some(socket)
        }
        None => None,
    };
    let metrics_listener = match config.metrics_listen {
        Some(address) => {
            let listener = tokio::net::TcpListener::bind(address)
                .await
                .map_err(|e| anyhow::anyhow!("cannot listen on {address} for --metrics-listen: {e}"))?;
            println!("esrp-server metrics on http://{}/metrics", listener.local_addr()?);
            Some(listener)
        }
        None => None,
    };
    let viewer_listener = match config.http_listen {
        Some(address) => {
            if config.token.is_none() && config.tokens.is_none() && !address.ip().is_loopback() {
                anyhow::bail!(
                    "--http-listen {address}: without --token or --tokens the viewer serves only a loopback address \
                     (e.g. 127.0.0.1:8080); give tokens to serve it on {}",
                    address.ip()
                );
            }
            let listener = tokio::net::TcpListener::bind(address)
                .await
                .map_err(|e| anyhow::anyhow!("cannot listen on {address} for --http-listen: {e}"))?;
            println!("esrp-server viewer on http://{}/", listener.local_addr()?);
            Some(listener)
        }
        None => None,
    };
    let listeners = esrp_server::Listeners { grpc: listener, metrics: metrics_listener, viewer: viewer_listener, unix };
    Ok(esrp_server::run(listeners, config, signals.wait()).await?)
}
