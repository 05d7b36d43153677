//! How the tools (`esrp-eval`, `esrp-bench`, `esrp-demo`) stop on SIGTERM and SIGINT
//! ([`exit_on_signals`]) and on an error (`exit_status`, with the `tools` feature).

use std::io;
use std::path::{Path, PathBuf};
#[cfg(feature = "tools")]
use std::process::ExitCode;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};

/// The exit status of a tool's run: success, or its error printed as one line, `NAME: what
/// failed: why` (its causes joined by `: `, each said once; never a backtrace, whatever
/// `RUST_BACKTRACE` says), and status 1.
///
/// While a stop by [`exit_on_signals`] is under way, this waits for it instead (the process
/// exits there, with the signal's status): a tool whose calls failed because its episodes were
/// being closed must not end the process first.
#[cfg(feature = "tools")]
pub fn exit_status(name: &str, result: anyhow::Result<()>) -> ExitCode {
    while STOPPING.load(Ordering::SeqCst) {
        std::thread::park();
    }
    let Err(error) = result else { return ExitCode::SUCCESS };
    eprintln!("{name}: {}", crate::error::one_line(error.as_ref()));
    ExitCode::FAILURE
}

/// How long a stopped tool waits for the server to close its live episodes before it exits.
pub const CLOSE_GRACE: std::time::Duration = std::time::Duration::from_secs(5);

/// Set once a stop has begun: the tool's own end then waits for it (see [`exit_status`]).
static STOPPING: AtomicBool = AtomicBool::new(false);

/// The paths of the live [`RemovedOnExit`] guards: a stop removes them before the process exits.
static MADE: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// What a stop says last ([`say_when_stopped`]).
type Note = Box<dyn Fn() -> Option<String> + Send>;

/// The line a stop says last, if the tool gave one ([`say_when_stopped`]).
static NOTE: Mutex<Option<Note>> = Mutex::new(None);

/// Has a stop by [`exit_on_signals`] or [`exit_when_stdin_closes`] say, after closing the
/// episodes and before the process exits, `NAME: ` and the line `note` makes then (none where it
/// returns `None`): e.g. what the tool's results file keeps and how to go on. Replaces an earlier
/// note.
pub fn say_when_stopped(note: impl Fn() -> Option<String> + Send + 'static) {
    *NOTE.lock().unwrap_or_else(std::sync::PoisonError::into_inner) = Some(Box::new(note));
}

/// A folder (or file) the tool made for its run and removes when the run is over: when the guard
/// is dropped (the run ended, or failed), or when a stop by [`exit_on_signals`] or
/// [`exit_when_stdin_closes`] ends the process, which runs no destructor. E.g. the folder where
/// `esrp-bench --processes` collects its client processes' results.
#[derive(Debug)]
pub struct RemovedOnExit(PathBuf);

impl RemovedOnExit {
    /// Removes `path` when the guard is dropped or the process is stopped (see the type).
    pub fn new(path: PathBuf) -> Self {
        MADE.lock().unwrap_or_else(std::sync::PoisonError::into_inner).push(path.clone());
        Self(path)
    }

    /// The path.
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for RemovedOnExit {
    fn drop(&mut self) {
        let mut made = MADE.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(i) = made.iter().position(|p| *p == self.0) {
            made.swap_remove(i);
        }
        drop(made);
        remove(&self.0);
    }
}

/// Removes a folder with what it holds, or a file; what is not there is no error.
fn remove(path: &Path) {
    let _ = std::fs::remove_dir_all(path).or_else(|_| std::fs::remove_file(path));
}

/// Removes what the live [`RemovedOnExit`] guards hold: a stop's last act before it exits.
fn remove_made() {
    let made = std::mem::take(&mut *MADE.lock().unwrap_or_else(std::sync::PoisonError::into_inner));
    for path in &made {
        remove(path);
    }
}

/// From now on, the first SIGTERM or SIGINT stops this process: it prints `NAME: terminated`
/// (or `NAME: interrupted`), closes on the server every episode it holds a live
/// [`crate::Episode`] handle to (within [`CLOSE_GRACE`]; a second signal skips the wait), and
/// exits with status 143 (130). So a job scheduler's SIGTERM leaves no episode on a shared
/// server behind (a `StepStream`'s episodes end with its connection anyway); those that could
/// not be closed are counted on stderr, and the server's idle timeout ends them. No other
/// destructor runs, and none need: what the tools write (results records, one `write` each) is
/// already with the system, a [`crate::LocalServer`] stops by itself when its stdin pipe
/// closes with this process, and what [`RemovedOnExit`] guards is removed. Watched on a thread of its own with a runtime of its own (so it may
/// be called inside another runtime), and acted on wherever the tool is; returns once the
/// handlers are installed.
pub fn exit_on_signals(name: &'static str) -> io::Result<()> {
    let (installed, outcome) = std::sync::mpsc::channel::<io::Result<()>>();
    std::thread::Builder::new().name("esrp-signals".into()).spawn(move || {
        let runtime = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
            Ok(runtime) => runtime,
            Err(error) => {
                let _ = installed.send(Err(error));
                return;
            }
        };
        let status = runtime.block_on(async move {
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
                let (word, status) = tokio::select! {
                    _ = terminate.recv() => ("terminated", 143),
                    _ = interrupt.recv() => ("interrupted", 130),
                };
                let again = async {
                    tokio::select! {
                        _ = terminate.recv() => {}
                        _ = interrupt.recv() => {}
                    }
                };
                // A stop already under way (standard input closed) is cut short by this signal.
                let _ = stop(name, word, again).await;
                status
            }
            #[cfg(not(unix))]
            {
                let _ = installed.send(Ok(()));
                let _ = tokio::signal::ctrl_c().await;
                let _ = stop(name, "interrupted", async {
                    let _ = tokio::signal::ctrl_c().await;
                })
                .await;
                130
            }
        });
        remove_made();
        std::process::exit(status);
    })?;
    outcome.recv().map_err(|_| io::Error::other("the signal thread ended before installing its handlers"))?
}

/// A tool's `main`: runs its async `body` on a multi-threaded runtime ([`block_on`]) and makes
/// its result the process's exit status ([`exit_status`]).
#[cfg(feature = "tools")]
pub fn run_tool(name: &str, body: impl std::future::Future<Output = anyhow::Result<()>>) -> ExitCode {
    let result = match tokio::runtime::Runtime::new() {
        Ok(runtime) => block_on(&runtime, body),
        Err(error) => Err(anyhow::Error::new(error).context("starting the async runtime")),
    };
    exit_status(name, result)
}

/// Runs a tool's async `body` on `runtime` to its end. If a stop by [`exit_on_signals`] has begun
/// by then, the body's end waits on the runtime for the process to exit instead: the episodes'
/// closes go through the connections this runtime drives, so it must outlive them (a body whose
/// calls failed because its episodes were being closed would otherwise drop it under them).
pub fn block_on<F: std::future::Future>(runtime: &tokio::runtime::Runtime, body: F) -> F::Output {
    runtime.block_on(async {
        let output = body.await;
        if STOPPING.load(Ordering::SeqCst) {
            std::future::pending::<()>().await;
        }
        output
    })
}

/// From now on, this process stops as on SIGTERM (episodes closed, status 143) when its
/// standard input reaches its end: for a child process whose parent holds a pipe to it, so
/// that the child ends with its parent however the parent ends (the `--processes` of
/// `esrp-bench`). Returns once the watching thread runs.
pub fn exit_when_stdin_closes(name: &'static str) -> io::Result<()> {
    std::thread::Builder::new().name("esrp-stdin".into()).spawn(move || {
        let mut sink = [0u8; 256];
        let mut stdin = io::stdin().lock();
        while !matches!(io::Read::read(&mut stdin, &mut sink), Ok(0) | Err(_)) {}
        if let Ok(runtime) = tokio::runtime::Builder::new_current_thread().enable_all().build()
            && !runtime.block_on(stop(name, "stopped (its standard input closed)", std::future::pending()))
        {
            // A signal's stop is under way: it exits.
            loop {
                std::thread::park();
            }
        }
        remove_made();
        std::process::exit(143);
    })?;
    Ok(())
}

/// What a stop does before the process exits: says `NAME: WORD`, marks the stop begun, and
/// closes the live episodes until they are closed, [`CLOSE_GRACE`] has passed, or `again` (a
/// second signal) completes; says how many it could not close. Returns false at once, doing
/// nothing, when another stop had begun.
async fn stop(name: &str, word: &str, again: impl std::future::Future<Output = ()>) -> bool {
    if STOPPING.swap(true, Ordering::SeqCst) {
        return false;
    }
    eprintln!("{name}: {word}");
    let deadline = tokio::time::Instant::now() + CLOSE_GRACE;
    tokio::select! {
        not_closed = crate::episode::close_live(deadline) => {
            if not_closed > 0 {
                eprintln!(
                    "{name}: {not_closed} episode(s) could not be closed on the server within {} s; \
                     its idle timeout will end them",
                    CLOSE_GRACE.as_secs()
                );
            }
        }
        () = again => eprintln!("{name}: stopped without closing its episodes (a second signal)"),
    }
    let note = NOTE.lock().unwrap_or_else(std::sync::PoisonError::into_inner).take();
    if let Some(line) = note.and_then(|note| note()) {
        eprintln!("{name}: {line}");
    }
    true
}
