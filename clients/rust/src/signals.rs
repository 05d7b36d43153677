//! How the tools (`esrp-eval`, `esrp-bench`, `esrp-demo`) stop on SIGTERM and SIGINT
//! ([`exit_on_signals`]) and on an error ([`exit_status`]).

use std::io;
#[cfg(feature = "tools")]
use std::process::ExitCode;

/// The exit status of a tool's run: success, or its error printed as one line, `NAME: what
/// failed: why` (its causes joined by `: `, each said once; never a backtrace, whatever
/// `RUST_BACKTRACE` says), and status 1.
#[cfg(feature = "tools")]
pub fn exit_status(name: &str, result: anyhow::Result<()>) -> ExitCode {
    let Err(error) = result else { return ExitCode::SUCCESS };
    let mut line = String::new();
    for cause in error.chain() {
        let text = cause.to_string();
        // A cause an error's own message already gives (`{source}` in it) is said once.
        if !line.contains(&text) {
            if !line.is_empty() {
                line.push_str(": ");
            }
            line.push_str(&text);
        }
    }
    eprintln!("{name}: {}", line.replace('\n', " "));
    ExitCode::FAILURE
}

/// From now on, the first SIGTERM or SIGINT ends this process at once: it prints `NAME:
/// terminated` (or `NAME: interrupted`) and exits with status 143 (130). Destructors do not run,
/// and need not: what the tools write (results records, one `write` each) is already with the
/// system, and a [`crate::LocalServer`] stops by itself when its stdin pipe closes with this
/// process. Watched on a thread of its own with a runtime of its own (so it may be called inside
/// another runtime), and acted on wherever the tool is; returns once the handlers are installed.
pub fn exit_on_signals(name: &'static str) -> io::Result<()> {
    let (installed, outcome) = std::sync::mpsc::channel::<io::Result<()>>();
    std::thread::Builder::new().name("esrp-signals".into()).spawn(move || {
        let runtime = match tokio::runtime::Builder::new_current_thread().enable_io().build() {
            Ok(runtime) => runtime,
            Err(error) => {
                let _ = installed.send(Err(error));
                return;
            }
        };
        let (word, status) = runtime.block_on(async move {
            #[cfg(unix)]
            {
                use tokio::signal::unix::{SignalKind, signal};
                let handlers = signal(SignalKind::terminate()).and_then(|t| Ok((t, signal(SignalKind::interrupt())?)));
                let (mut terminate, mut interrupt) = match handlers {
                    Ok(handlers) => handlers,
                    Err(error) => {
                        let _ = installed.send(Err(error));
                        return std::future::pending().await;
                    }
                };
                let _ = installed.send(Ok(()));
                tokio::select! {
                    _ = terminate.recv() => ("terminated", 143),
                    _ = interrupt.recv() => ("interrupted", 130),
                }
            }
            #[cfg(not(unix))]
            {
                let _ = installed.send(Ok(()));
                let _ = tokio::signal::ctrl_c().await;
                ("interrupted", 130)
            }
        });
        eprintln!("{name}: {word}");
        std::process::exit(status);
    })?;
    outcome.recv().map_err(|_| io::Error::other("the signal thread ended before installing its handlers"))?
}
