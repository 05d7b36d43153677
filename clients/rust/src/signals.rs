//! How the tools (`esrp-eval`, `esrp-bench`, `esrp-demo`) stop on SIGTERM and SIGINT:
//! [`exit_on_signals`].

use std::io;

/// From now on, the first SIGTERM or SIGINT ends this process at once: it prints `NAME:
/// terminated` (or `NAME: interrupted`) and exits with status 143 (130). Destructors do not run,
/// and need not: what the tools write (results records, one `write` each) is already with the
/// system, and a [`crate::LocalServer`] stops by itself when its stdin pipe closes with this
/// process. Watched on a thread of its own, so a signal is acted on wherever the tool is.
pub fn exit_on_signals(name: &'static str) -> io::Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread().enable_io().build()?;
    #[cfg(unix)]
    let (mut terminate, mut interrupt) = runtime.block_on(async {
        use tokio::signal::unix::{SignalKind, signal};
        io::Result::Ok((signal(SignalKind::terminate())?, signal(SignalKind::interrupt())?))
    })?;
    std::thread::Builder::new().name("esrp-signals".into()).spawn(move || {
        #[cfg(unix)]
        let (word, status) = runtime.block_on(async {
            tokio::select! {
                _ = terminate.recv() => ("terminated", 143),
                _ = interrupt.recv() => ("interrupted", 130),
            }
        });
        #[cfg(not(unix))]
        let (word, status) = runtime.block_on(async {
            let _ = tokio::signal::ctrl_c().await;
            ("interrupted", 130)
        });
        eprintln!("{name}: {word}");
        std::process::exit(status);
    })?;
    Ok(())
}
