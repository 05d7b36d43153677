"""SIGTERM and SIGINT stop the `esrp` commands every time (esrp._signals): a short run of the
stress test of `tools/signal_stress.py`, a command that swallows the signal's exception (the
watchdog ends it), `esrp bench` and `esrp demos export`, and the block's own rules in-process."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import child_pids, load_tool

from esrp import _signals


def test_signalled_runs_all_stop_with_their_status() -> None:
    stress = load_tool("signal_stress")
    outcomes = stress.stress(12, jobs=2, max_delay=3.0, seed=7)
    kinds = Counter(outcome.kind for outcome in outcomes)
    failures = [o for o in outcomes if o.kind not in ("ok", "before handlers")]
    assert not failures, "\n\n".join(
        f"run {o.index} ({o.delay:.2f} s): {o.kind}\n{o.stderr[-2000:]}" for o in failures
    )
    # Those signalled once the server is up all stop as they should (none "before handlers").
    assert all(o.kind == "ok" for o in outcomes if not o.after_start), kinds
    assert kinds["ok"] >= 4, kinds


def test_sigint_stops_the_command_too() -> None:
    stress = load_tool("signal_stress")
    outcomes = stress.stress(4, jobs=2, max_delay=3.0, seed=3, signum=signal.SIGINT)
    failures = [o for o in outcomes if o.kind not in ("ok", "before handlers")]
    assert not failures, "\n\n".join(f"run {o.index}: {o.kind}\n{o.stderr[-2000:]}" for o in failures)


SWALLOWING_AGENT = """
import time

import esrp


class Swallowing:
    '''Catches everything, the signal's exception included, and goes on.'''

    def reset(self, observation, info):
        pass

    def act(self, observation):
        while True:
            try:
                time.sleep(0.01)
            except BaseException:
                pass


def make(config):
    return Swallowing()
"""


def _start(command: list[str], cwd: Path, until: str | None) -> tuple[subprocess.Popen[bytes], Path]:
    """Starts `command` with stderr in a file; returns once the file holds `until` (None: once the
    command has started its server), within 120 s."""
    err_path = cwd / "stderr.txt"
    environment = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(cwd))
    with open(err_path, "wb") as err:
        child = subprocess.Popen(command, env=environment, cwd=cwd, stdout=subprocess.DEVNULL, stderr=err)
    deadline = time.monotonic() + 120
    try:
        while (until not in err_path.read_text(errors="replace")) if until else not child_pids(child.pid):
            assert child.poll() is None, err_path.read_text()
            assert time.monotonic() < deadline, err_path.read_text()
            time.sleep(0.05)
    except BaseException:
        child.kill()  # its server stops when its stdin pipe closes
        child.wait()
        raise
    return child, err_path


def _assert_stopped(
    child: subprocess.Popen[bytes], servers: list[int], err: Path, status: int, line: str
) -> None:
    child.wait(timeout=60)
    text = err.read_text(errors="replace")
    assert child.returncode == status, text
    assert line in text, text
    deadline = time.monotonic() + 10
    while any(Path(f"/proc/{pid}").exists() for pid in servers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(Path(f"/proc/{pid}").exists() for pid in servers), "a server outlived the command"


def test_a_command_that_swallows_the_signal_is_stopped_by_the_watchdog(tmp_path: Path) -> None:
    (tmp_path / "swallowing.py").write_text(SWALLOWING_AGENT)
    command = [sys.executable, "-m", "esrp.cli", "eval", "--agent", "swallowing:make", "--split", "test"]
    command += ["--no-progress", "--out", str(tmp_path / "out.jsonl")]
    child, err = _start(command, tmp_path, until="esrp-server")
    time.sleep(1.0)  # the agent is in its loop
    servers = child_pids(child.pid)
    assert servers
    sent = time.monotonic()
    child.send_signal(signal.SIGTERM)
    _assert_stopped(child, servers, err, 143, "esrp eval: terminated (it had not stopped within the grace")
    assert time.monotonic() - sent < 30


def test_sigterm_stops_esrp_bench_and_its_server(tmp_path: Path) -> None:
    command = [
        sys.executable,
        "-m",
        "esrp.bench",
        "--scenarios",
        "client-1",
        "--seconds",
        "30",
        "--repeat",
        "1",
    ]
    command += ["--warmup-rounds", "0"]
    child, err = _start(command, tmp_path, until="client-1")
    servers = child_pids(child.pid)
    assert servers
    child.send_signal(signal.SIGTERM)
    _assert_stopped(child, servers, err, 143, "esrp.bench: terminated")


def test_sigterm_stops_demos_export_and_keeps_what_it_wrote(tmp_path: Path) -> None:
    pytest.importorskip("zarr")
    store = tmp_path / "demos.zarr"
    command = [sys.executable, "-m", "esrp.cli", "demos", "export", "--split", "train", "--out", str(store)]
    child, err = _start(command, tmp_path, until=None)
    time.sleep(3.0)
    servers = child_pids(child.pid)
    assert servers
    child.send_signal(signal.SIGTERM)
    _assert_stopped(child, servers, err, 143, "esrp demos: terminated")


def _signalled_in_block(body: Callable[[], None]) -> _signals.Terminated:
    """Runs `body` in a `stop_on_signals` block; the `Terminated` it raised."""
    try:
        with _signals.stop_on_signals("test", grace=30):
            body()
    except _signals.Terminated as terminated:
        return terminated
    raise AssertionError("no Terminated was raised")


def test_the_block_raises_terminated_and_puts_the_handlers_back() -> None:
    before = signal.getsignal(signal.SIGTERM)

    def body() -> None:
        signal.raise_signal(signal.SIGTERM)
        time.sleep(5)  # the handler raises before this ends
        raise AssertionError("the signal did not stop the block")

    assert _signalled_in_block(body).code == 143
    # A signal came: the block's handler stays, and ignores what follows.
    signal.raise_signal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, before)
    with _signals.stop_on_signals("test"):
        assert signal.getsignal(signal.SIGTERM) is not before
    assert signal.getsignal(signal.SIGTERM) is before


def test_a_signal_in_a_deferred_section_is_raised_at_its_end() -> None:
    reached = []

    def body() -> None:
        with _signals.deferred():
            signal.raise_signal(signal.SIGTERM)
            time.sleep(0.05)
            reached.append("end of section")
        reached.append("after it")

    _signalled_in_block(body)
    assert reached == ["end of section"]
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


CHANNEL_SIGNALLED = """
import asyncio
import os
import signal
import sys
import threading

import esrp
from esrp import _signals

start = threading.Thread.start


def signalled_start(self):
    # The first grpc.aio channel starts grpcio's poller thread from inside its Cython constructor:
    # the signal lands there, and its handler runs at the next bytecode.
    threading.Thread.start = start
    os.kill(os.getpid(), signal.SIGTERM)
    start(self)


async def main():
    threading.Thread.start = signalled_start
    client = esrp.AsyncClient("127.0.0.1:9")
    print("made", flush=True)
    await client.close()


sys.exit(_signals.run_command("esrp test", lambda: asyncio.run(main()), handle_signals=True))
"""


def test_a_signal_while_a_channel_is_made_is_raised_once_it_is_whole(tmp_path: Path) -> None:
    # grpcio dies of SIGSEGV when an exception is raised inside its channel's constructor; the
    # command holds the signal until the channel exists, then stops as on any other signal.
    script = tmp_path / "signalled_channel.py"
    script.write_text(CHANNEL_SIGNALLED)
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 143, (done.returncode, done.stderr[-2000:])
    assert "esrp test: terminated" in done.stderr
    assert "made" not in done.stdout  # raised where the channel's section ended, in the constructor


def test_a_signal_in_the_event_loop_cancels_its_main_task_and_is_raised_after(
    recwarn: pytest.WarningsRecorder,
) -> None:
    reached = []

    async def side() -> None:
        await asyncio.sleep(30)

    async def main() -> None:
        helper = asyncio.ensure_future(side())
        try:
            await asyncio.sleep(0)
            signal.raise_signal(signal.SIGTERM)  # the handler runs here, inside the loop
            for _ in range(1000):  # no exception cuts this short: the task is cancelled at its next await
                pass
            reached.append("signalled")
            await asyncio.sleep(30)
            reached.append("not cancelled")
        finally:
            await asyncio.sleep(0)  # the clean-up may await
            helper.cancel()
            reached.append("cleaned up")

    started = time.monotonic()
    assert _signalled_in_block(lambda: _signals.run_async(main())).code == 143
    assert reached == ["signalled", "cleaned up"]
    assert time.monotonic() - started < 5
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    assert not [w for w in recwarn if "never awaited" in str(w.message)]
    # Outside a block it is asyncio.run.

    async def answer() -> int:
        return 42

    assert _signals.run_async(answer()) == 42


def test_an_exception_dropped_in_a_finalizer_is_raised_again() -> None:
    class Finalized:
        def __del__(self) -> None:
            signal.raise_signal(signal.SIGTERM)  # the handler raises here, inside __del__
            for _ in range(1000):
                pass

    def body() -> None:
        Finalized()  # dropped at once: its finalizer runs, the exception is reported and dropped
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            time.sleep(0.001)
        raise AssertionError("the dropped signal was not raised again")

    _signalled_in_block(body)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def test_a_signal_stops_the_children_started_in_the_block_only() -> None:
    """A server started before the command's block (a test session's, a notebook's) is not the
    command's: the CI run whose in-process signal tests stopped the session's server failed every
    later test that used it."""
    before = subprocess.Popen(["sleep", "60"])
    inside: list[subprocess.Popen[bytes]] = []
    try:
        _signals.track(before)

        def body() -> None:
            inside.append(subprocess.Popen(["sleep", "60"]))
            _signals.track(inside[0])
            signal.raise_signal(signal.SIGTERM)
            time.sleep(5)

        _signalled_in_block(body)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        assert inside[0].wait(5) == -signal.SIGTERM
        assert before.poll() is None, "the block stopped a child started before it"
    finally:
        for process in (before, *inside):
            process.kill()
            process.wait()
