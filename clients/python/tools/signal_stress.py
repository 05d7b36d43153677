"""Stress test of how `esrp eval` stops on a signal: runs the command many times, sends SIGTERM (or
SIGINT) to each run at a random moment — a third of the runs within `--max-delay` seconds of the
start (while Python imports, the command starts its server), the others within `--max-delay`
seconds of the run's first line (while it creates, steps and closes episodes), and while
finalizers run (the agent leaves garbage whose `__del__` takes time, the
place where a signal's exception used to be dropped) — and checks that every run exits with 143
(130) and the line `esrp eval: terminated` (`interrupted`) within a bound, having unwound (not
stopped by the watchdog), with nothing else on stderr (no traceback, no asyncio warning), and
leaves no server.

    python tools/signal_stress.py --runs 1000 --jobs 2

A run signalled before the command installed its handlers (while Python imports the package) dies
of the signal's default action, as any program would: nothing was started then. It is counted
apart ("before handlers"), not as a failure. Every other outcome but the one above is a failure,
printed with the run's stderr. Exits 1 if any run failed. `tests/test_signals.py` runs a short
variant in the test suite.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import IO

AGENT_MODULE = '''
import gc

import esrp


class Garbage:
    """Cyclic garbage whose finalizer runs Python code for a while: the collector runs it at any
    allocation of the agent, and a signal handler often runs inside it."""

    def __init__(self):
        self.me = self

    def __del__(self):
        total = 0
        for i in range(2000):
            total += i


class Littering:
    """Turns left and leaves finalizable garbage behind at every step."""

    def reset(self, observation, info):
        self.steps = 0

    def act(self, observation):
        self.steps += 1
        for _ in range(20):
            Garbage()
        if self.steps % 5 == 0:
            gc.collect()
        return esrp.Action.LEFT


def make(config):
    return Littering()
'''


NOISE = ("Traceback (most recent call last)", "Task was destroyed", "never retrieved", "was never awaited")
"""What a cleanly stopped run never prints: its stderr is the server's line and the command's."""


@dataclass
class Outcome:
    """One signalled run."""

    index: int
    delay: float
    after_start: bool  # the delay counted from the start (else from the run's first line)
    kind: str  # "ok", "before handlers", "finished early" or a failure's description
    seconds: float  # from the signal to the command's exit
    stderr: str


def _leftovers(marker: str) -> list[int]:
    """The processes whose environment holds `marker` (a run's command and the servers it started)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes()
        except OSError:
            continue
        if marker.encode() in environ:
            found.append(int(entry.name))
    return found


def signalled_run(
    index: int,
    *,
    folder: Path,
    delay: float,
    after_start: bool = True,
    signum: int = signal.SIGTERM,
    bound: float = 60.0,
    python: str = sys.executable,
) -> Outcome:
    """Starts `esrp eval` (the littering agent on the test split, its own server), sends `signum`
    `delay` seconds after its start (`after_start`) or after its first line on stderr (`esrp-server
    VERSION at ADDRESS`: the server is up), and checks how it ends."""
    marker = f"ESRP_SIGNAL_STRESS_RUN={uuid.uuid4().hex}"
    out = folder / f"run-{index}.jsonl"
    command = [python, "-m", "esrp.cli", "eval", "--agent", "littering_agent:make", "--split", "test"]
    command += ["--episodes-in-flight", "2", "--no-progress", "--out", str(out)]
    environment = dict(os.environ, PYTHONUNBUFFERED="1")
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(folder), environment.get("PYTHONPATH")]))
    name, value = marker.split("=")
    environment[name] = value
    with tempfile.TemporaryFile() as err:
        child = subprocess.Popen(command, env=environment, stdout=subprocess.DEVNULL, stderr=err, cwd=folder)
        if not after_start:
            deadline = time.monotonic() + bound
            while child.poll() is None and time.monotonic() < deadline and b"esrp-server" not in _read(err):
                time.sleep(0.01)
        time.sleep(delay)
        sent = time.monotonic()
        finished_before = child.poll() is not None
        if not finished_before:
            child.send_signal(signum)
        try:
            child.wait(timeout=bound)
            timed_out = False
        except subprocess.TimeoutExpired:
            timed_out = True
            child.kill()
            child.wait()
        seconds = time.monotonic() - sent
        err.seek(0)
        stderr = err.read().decode(errors="replace")
    # The server gets a moment to finish its own graceful exit.
    settle = time.monotonic() + 10
    while (left := [pid for pid in _leftovers(marker) if pid != child.pid]) and time.monotonic() < settle:
        time.sleep(0.05)
    for pid in left:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
    status = {signal.SIGTERM: 143, signal.SIGINT: 130}[signal.Signals(signum)]
    word = "terminated" if signum == signal.SIGTERM else "interrupted"
    if timed_out:
        kind = f"still running {bound:.0f} s after the signal"
    elif left:
        kind = f"left {len(left)} process(es) running: {left}"
    elif finished_before:
        kind = "finished early"
    elif child.returncode == -signum and "esrp-server" not in stderr:
        kind = "before handlers"
    elif child.returncode != status:
        kind = f"exit status {child.returncode}, not {status}"
    elif f"esrp eval: {word}" not in stderr:
        kind = f"no 'esrp eval: {word}' line"
    elif "had not stopped within the grace" in stderr:
        kind = "stopped by the watchdog, not by unwinding"
    elif any(noise in stderr for noise in NOISE):
        kind = "tracebacks or asyncio's warnings on stderr"
    else:
        kind = "ok"
    out.unlink(missing_ok=True)
    out.with_suffix(".md").unlink(missing_ok=True)
    return Outcome(index, delay, after_start, kind, seconds, stderr)


def _read(file: IO[bytes]) -> bytes:
    """What was written to `file` so far (from its start; the position is kept)."""
    position = file.tell()
    file.seek(0)
    data = file.read()
    file.seek(position)
    return data


def stress(
    runs: int,
    *,
    jobs: int = 2,
    max_delay: float = 3.0,
    seed: int = 0,
    signum: int = signal.SIGTERM,
    bound: float = 60.0,
    log: bool = False,
) -> list[Outcome]:
    """`runs` signalled runs, `jobs` at a time, each signalled after a delay drawn uniformly from
    [0, max_delay) seconds (from the start for a third of them, else from the first line); returns
    their outcomes in order."""
    rng = random.Random(seed)
    delays = [rng.uniform(0.0, max_delay) for _ in range(runs)]
    from_start = [rng.random() < 1 / 3 for _ in range(runs)]
    with tempfile.TemporaryDirectory(prefix="esrp-signal-stress-") as name:
        folder = Path(name)
        (folder / "littering_agent.py").write_text(AGENT_MODULE)
        outcomes: list[Outcome] = []
        started = time.monotonic()

        def one(index: int) -> Outcome:
            outcome = signalled_run(
                index,
                folder=folder,
                delay=delays[index],
                after_start=from_start[index],
                signum=signum,
                bound=bound,
            )
            if log:
                outcomes.append(outcome)
                failed = sum(o.kind not in ("ok", "before handlers", "finished early") for o in outcomes)
                print(
                    f"[{len(outcomes)}/{runs}, {time.monotonic() - started:.0f} s] run {index}: "
                    f"signal {outcome.delay:.2f} s after {'start' if outcome.after_start else 'first line'}, "
                    f"{outcome.kind}, exit after {outcome.seconds:.2f} s"
                    f" ({failed} failed so far)",
                    flush=True,
                )
                if outcome.kind not in ("ok", "before handlers", "finished early"):
                    print(outcome.stderr[-4000:], flush=True)
            return outcome

        with ThreadPoolExecutor(jobs) as pool:
            return list(pool.map(one, range(runs)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument("--jobs", type=int, default=2, help="runs at a time")
    parser.add_argument(
        "--max-delay",
        type=float,
        default=3.0,
        help="signal within [0, this) s of the start or of the first line",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--signal", choices=["TERM", "INT"], default="TERM")
    parser.add_argument("--bound", type=float, default=60.0, help="seconds a run may take to exit")
    args = parser.parse_args()
    started = time.monotonic()
    signum = signal.SIGTERM if args.signal == "TERM" else signal.SIGINT
    outcomes = stress(
        args.runs,
        jobs=args.jobs,
        max_delay=args.max_delay,
        seed=args.seed,
        signum=signum,
        bound=args.bound,
        log=True,
    )
    counts = Counter(o.kind for o in outcomes)
    signalled = sum(n for kind, n in counts.items() if kind != "finished early")
    failed = sum(n for kind, n in counts.items() if kind not in ("ok", "before handlers", "finished early"))
    slowest = max((o.seconds for o in outcomes if o.kind == "ok"), default=0.0)
    print(
        f"{args.runs} runs in {time.monotonic() - started:.0f} s: {signalled} signalled (SIG{args.signal}), "
        f"{counts['ok']} stopped as they should, {counts['before handlers']} before handlers, "
        f"{counts['finished early']} finished before the signal, {failed} failed; "
        f"slowest exit {slowest:.2f} s"
    )
    for kind, n in counts.most_common():
        print(f"  {n:5d}  {kind}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
