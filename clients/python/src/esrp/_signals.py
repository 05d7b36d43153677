"""How the `esrp` commands stop on SIGTERM and SIGINT, every time (`stop_on_signals`).

A Python signal handler runs between two bytecodes of the main thread, wherever that thread is,
and an exception it raises unwinds the command from there: the `with` blocks close the episodes,
the files and the server the command started. Raised inside a finalizer (`__del__`), a weakref or
GC callback, the interpreter reports the exception ("Exception ignored in ...") and drops it; code
that catches every exception drops it too. So that no signal is lost:

- the first SIGTERM raises `Terminated` (a `SystemExit` with status 143, which asyncio passes on as
  it does `SystemExit`) and the first SIGINT `KeyboardInterrupt` (status 130);
- when the interpreter drops that exception as unraisable, the same signal is sent again a moment
  later, so that the handler raises it again at another bytecode;
- a watchdog thread waits `grace` seconds from the first signal; if the command has not returned by
  then, it stops the child processes the command tracks (the servers `LocalServer` started inside
  the block), prints the command's one-line message and exits with the signal's status at once.
  Records already appended stay: they are flushed to the OS as each is written.

Only the children started inside the block are the command's: a server started before it (a test
session's, a notebook's) belongs to whoever started it, and a signal that stops the block leaves it
running.

Later signals while the command unwinds are not raised again: that would cut its clean-up short
(stopping the server); the watchdog bounds how long the clean-up may take. A signal that arrives
inside `deferred()` (starting or stopping a child, which must not be cut in two) is raised when
that section ends. Leaving the block after a signal stops any tracked child still running.

A command's event loop runs in `run_async`: there a signal cancels the loop's main task (which
unwinds through its `async with` blocks) instead of raising inside asyncio's own code, and its
exception is raised once the loop has closed.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, TypeVar

__all__ = [
    "STATUS",
    "Terminated",
    "deferred",
    "reclaim",
    "run_async",
    "run_command",
    "stop_on_signals",
    "track",
    "untrack",
]

STATUS = {signal.SIGTERM: 143, signal.SIGINT: 130}
"""The exit status of a command stopped by each signal (128 + its number)."""

_T = TypeVar("_T")

_WORD = {signal.SIGTERM: "terminated", signal.SIGINT: "interrupted"}
"""What a command stopped by each signal says: `COMMAND: terminated`."""

_REDELIVERY_DELAY = 0.01
"""Seconds between a dropped signal exception and the signal sent again: the unraisable hook has
returned by then, so the handler does not raise inside the hook (whose own exceptions are dropped)."""


class Terminated(SystemExit):
    """SIGTERM arrived: raised in the main thread by the handler of `stop_on_signals`."""

    def __init__(self) -> None:
        super().__init__(STATUS[signal.SIGTERM])


class _State:
    """What the handlers of one `stop_on_signals` block share."""

    def __init__(self, command: str, grace: float) -> None:
        self.command = command
        self.grace = grace
        self.signum: int | None = None  # the first signal
        self.redeliver = False  # the first signal's exception was dropped: raise it again
        self.in_hook = False  # the unraisable hook runs: an exception raised now would be dropped
        self.wakeup = threading.Event()  # asks the watchdog thread to send the signal again
        self.done = threading.Event()  # the command returned or raised out of the block
        self.defer = 0  # depth of the main thread's `deferred()` sections
        self.held = False  # a signal's exception waits for the end of a deferred section
        self.on_hold: Callable[[], None] | None = None  # called when a signal is held (`run_async`)
        # The children started inside the block (any thread), stopped when a signal stops it.
        self.children: set[subprocess.Popen[Any]] = set()
        self.children_lock = threading.Lock()

    def exception(self) -> BaseException:
        return Terminated() if self.signum == signal.SIGTERM else KeyboardInterrupt()

    def handle(self, signum: int, frame: object) -> None:
        if self.done.is_set():
            return
        if self.signum is None:
            self.signum = signum
            threading.Thread(target=self._watch, name="esrp-signal-watchdog", daemon=True).start()
        elif not self.redeliver:
            return  # a later signal while the command unwinds
        if self.in_hook:
            self.wakeup.set()  # inside the hook its own exception would be dropped: later
            return
        self.redeliver = False
        if self.defer:
            self.held = True
            if self.on_hold is not None:
                self.on_hold()
            return
        raise self.exception()

    def dropped(self, unraisable: Any) -> bool:  # noqa: ANN401 - sys.UnraisableHookArgs
        """Whether `unraisable` is this block's signal exception; if so, the signal is sent again
        (by the watchdog thread, `_REDELIVERY_DELAY` later: this hook returns first).
        """
        self.in_hook = True
        try:
            exception = unraisable.exc_value
            ours = isinstance(exception, Terminated) or (
                isinstance(exception, KeyboardInterrupt) and self.signum == signal.SIGINT
            )
            if not ours or self.signum is None or self.done.is_set():
                return False
            self.redeliver = True
            self.wakeup.set()
            return True
        finally:
            self.in_hook = False

    def _watch(self) -> None:
        """The first signal's thread: sends the signal again when asked (`wakeup`), and stops the
        process if the block has not been left `grace` seconds after the signal.
        """
        assert self.signum is not None
        deadline = time.monotonic() + self.grace
        while not self.done.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                _stop_now(self, self.signum)
                return
            if self.wakeup.wait(left):
                self.wakeup.clear()
                time.sleep(_REDELIVERY_DELAY)
                if not self.done.is_set():
                    os.kill(os.getpid(), self.signum)


_active: _State | None = None
"""The state of the `stop_on_signals` block the process is in, if any."""


def track(process: subprocess.Popen[Any]) -> None:
    """Makes `process` one of the children stopped when the command is stopped by a signal: inside a
    `stop_on_signals` block (from any thread); outside one it stays its starter's to stop.
    """
    state = _active
    if state is not None:
        with state.children_lock:
            state.children.add(process)


def untrack(process: subprocess.Popen[Any]) -> None:
    """Forgets `process` (it was stopped and waited for)."""
    state = _active
    if state is not None:
        with state.children_lock:
            state.children.discard(process)


def _stop_children(state: _State, timeout: float = 3.0) -> int:
    """Stops every child the block `state` tracks that still runs (SIGTERM, then SIGKILL after
    `timeout` seconds) and waits for it; returns how many were running.
    """
    with state.children_lock:
        processes = list(state.children)
        state.children.clear()
    running = [process for process in processes if process.poll() is None]
    for process in running:
        with contextlib.suppress(OSError):
            process.terminate()
    for process in running:
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError):
                process.kill()
            process.wait()
    return len(running)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """A section that a signal must not cut in two (a child started but not yet tracked, or
    signalled but not yet waited for): inside it, in the main thread of a `stop_on_signals` block,
    the signal's exception is held and raised when the section ends. Elsewhere it does nothing.
    """
    state = _active
    if state is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    state.defer += 1
    try:
        yield
    finally:
        state.defer -= 1
        if not state.defer and state.held and not state.done.is_set():
            state.held = False
            raise state.exception()


def run_async(main: Coroutine[Any, Any, _T]) -> _T:
    """`asyncio.run(main)` for a command. Inside a `stop_on_signals` block (its main thread), a
    signal cancels `main`'s task instead of raising at whatever bytecode the event loop is in: the
    loop's own code does not survive that (callbacks cut in two, tasks destroyed while pending, a
    page of "Task exception was never retrieved" after the command's last line). `main` unwinds
    through its `async with` blocks as on any cancellation, the loop closes as usual, and the
    signal's exception is raised after it; so is a signal that comes before `main` starts or after
    it ends. Elsewhere it is `asyncio.run`.
    """
    state = _active
    if state is None or threading.current_thread() is not threading.main_thread():
        return asyncio.run(main)
    task: asyncio.Task[Any] | None = None

    def cancel() -> None:
        if task is not None and not task.done():
            task.cancel()
            task.get_loop().call_soon_threadsafe(_nothing)  # wakes a loop that waits for events

    async def guarded() -> _T:
        nonlocal task
        task = asyncio.current_task()
        if state.held:  # the signal came while the loop started
            main.close()
            raise asyncio.CancelledError
        return await main

    previous, state.on_hold = state.on_hold, cancel
    try:
        with deferred():
            try:
                return asyncio.run(guarded())
            except asyncio.CancelledError:
                if not state.held:
                    raise
                state.held = False
                raise state.exception() from None
    finally:
        state.on_hold = previous


def _nothing() -> None:
    pass


def reclaim() -> None:
    """Puts the handlers of the `stop_on_signals` block the process is in back, after a library
    replaced them (`ray.init` installs a SIGTERM handler of its own, which exits with status 15).
    """
    state = _active
    if state is not None and threading.current_thread() is threading.main_thread():
        for signum in STATUS:
            signal.signal(signum, state.handle)


def _stop_now(state: _State, signum: int) -> None:
    """The watchdog's end: stops the block's children, prints the command's line and exits with the
    signal's status at once.
    """
    stopped = _stop_children(state)
    servers = f"; stopped the {stopped} server(s) it started" if stopped else ""
    word = _WORD[signal.Signals(signum)]
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    with contextlib.suppress(Exception):
        print(
            f"{state.command}: {word} (it had not stopped within the grace after the signal{servers})",
            file=sys.stderr,
            flush=True,
        )
    os._exit(STATUS[signal.Signals(signum)])


@contextlib.contextmanager
def stop_on_signals(command: str, *, grace: float = 10.0) -> Iterator[None]:
    """Inside the block, SIGTERM raises `Terminated` and SIGINT `KeyboardInterrupt` in the main
    thread, never lost (see the module's text); after `grace` seconds without leaving the block, the
    process stops the children it tracks and exits with status 143 (SIGTERM) or 130 (SIGINT),
    printing `COMMAND: terminated (...)`. Only in the main thread and not nested; elsewhere the
    block does nothing. The unraisable hook in force before is put back on leaving, and so are the
    signal handlers unless a signal came.
    """
    global _active
    if threading.current_thread() is not threading.main_thread() or _active is not None:
        yield
        return
    state = _active = _State(command, grace)
    previous_hook = sys.unraisablehook

    def hook(unraisable: Any) -> None:  # noqa: ANN401 - sys.UnraisableHookArgs
        if not state.dropped(unraisable):
            previous_hook(unraisable)

    def at_exit() -> None:
        # Where C code calls back into Python and meets a `SystemExit`, the interpreter exits at
        # once (`PyErr_Print`), with the status (143) but without unwinding this block: say what
        # happened, and stop the children, here.
        if state.signum is not None:
            _stop_children(state)
            print(f"{command}: {_WORD[signal.Signals(state.signum)]}", file=sys.stderr, flush=True)

    previous = {signum: signal.signal(signum, state.handle) for signum in STATUS}
    sys.unraisablehook = hook
    atexit.register(at_exit)
    try:
        yield
    finally:
        atexit.unregister(at_exit)
        state.done.set()
        _active = None
        sys.unraisablehook = previous_hook
        state.wakeup.set()  # the watchdog thread sees `done` and ends
        if state.signum is None:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
        else:
            # Left as they are (they ignore every signal now): a signal sent again that is still on
            # its way must not kill the process with the default action while it exits.
            _stop_children(state)


def run_command(name: str, body: Callable[[], int], *, handle_signals: bool) -> int:
    """Runs a command's `body` and returns its exit status; a SIGINT that reaches here prints
    `NAME: interrupted` and gives 130, a SIGTERM `NAME: terminated` and 143. With `handle_signals`
    (the command's own process, not a call from Python code) inside `stop_on_signals(name)`;
    otherwise SIGTERM keeps the handler the process has.
    """
    try:
        with stop_on_signals(name) if handle_signals else contextlib.nullcontext():
            return body()
    except KeyboardInterrupt:
        print(f"{name}: {_WORD[signal.SIGINT]}", file=sys.stderr)
        return STATUS[signal.SIGINT]
    except Terminated:
        print(f"{name}: {_WORD[signal.SIGTERM]}", file=sys.stderr)
        return STATUS[signal.SIGTERM]
