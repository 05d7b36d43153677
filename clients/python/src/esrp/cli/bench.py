"""`esrp bench` (also `python -m esrp.bench`): end-to-end throughput and latency of the Python
client, beside the Rust client's (`esrp-bench`) and MiniWorld's on the same machine in the same run.

Scenarios (each runs `--seconds` after `--warmup` seconds that are not counted; actions are random
with fixed seeds; every client waits for a step's answer before it sends that episode's next
action, as an agent that looks at every observation does; episodes that end are reset):

- `client-1`: one episode, `Episode.step` (unary Step).
  client-1, env-1 and vec-64 run once per `--transport` (`Client`'s: `auto`, the default, is the
  native transport where the `esrp-native` package is installed; `native,grpcio` measures both
  side by side, the second as `env-1@grpcio`, ...).
- `env-1`: one `RearrangeEnv` (`esrp/Rearrange-v1`), `env.step` closed loop, on the scene that
  client-1 and esrp-bench's unary-1 play.
- `stream-64`: 64 episodes on one `EpisodeStream`, each sending its next step when its answer comes.
- `vec-64`: one `RearrangeVectorEnv` of 64 envs, `envs.step` closed loop (NEXT_STEP autoreset),
  sub-env i on the i-th of the 64 scenes that esrp-bench's batch-64 plays, each restarted in place
  when it ends as batch-64's are (`scene_per_env=True`).
- `rust`: the Rust client `esrp-bench` against the same server, for the matching scenarios
  (`unary-1` for client-1 and env-1, `stream-mux-64` for stream-64, `batch-64` for vec-64, whose
  calls are the same: one StepBatch of 64 at a time). Found as `ESRP_BENCH_BIN`, on `PATH`, or in
  the checkout's `target/release` (or `CARGO_TARGET_DIR`'s); skipped with a message otherwise.
- `miniworld`: MiniWorld's `MiniWorld-PickupObjects-v0` at 128x128, in process (the `bench`
  extra: `pip install 'esrp[bench]'`; headless, it renders through EGL, see the README); skipped
  with a message when it is not installed or cannot open an OpenGL context.

Steps/s counts the steps taken in the measured window; latency is per `step` call (for vec-64,
per wave of 64). With `--repeat K` the scenarios run K rounds one after the other and the table
shows the medians (ratios to Rust: the median of each round's ratio). Before them, `--warmup-rounds`
(1) rounds run the same scenarios unmeasured: a server generates and compiles each scene of the
built-in benchmark on its first use (a vec-64 round on a fresh server measured a third of a warm
one's steps/s), and the measured rounds then visit the same scenes, from the same seeds.

`--servers K` spreads vec-64's 64 sub-envs over K servers (`RearrangeVectorEnv`'s `servers`):
started here, or the comma-separated addresses of `--server`; its row is then
`vec-64/K-servers`, and the other scenarios play on the first server. One server's device queue
caps a vector env on a GPU machine; this measures what spreading raises it to.

`--processes N` runs the chosen scenarios in N processes at once against one server (started
here unless `--server` names one), so that one Python process is not what caps the figure on a
many-core machine: each runs every round itself, and the table sums their steps/s per scenario
(the latencies: the median of their medians, the worst of their p99s). Not with `rust` or
`miniworld`, which measure other programs.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.metadata
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import __version__, _grpc_setup, _malloc_setup
from .._signals import run_command

if TYPE_CHECKING:
    import gymnasium

    from .._client import Client
    from .._native import Transport

__all__ = ["SCENARIOS", "Measurement", "main", "run"]

SCENARIOS = ("client-1", "env-1", "stream-64", "vec-64", "rust", "miniworld")
"""Every scenario, in the order they run."""

DEFAULT_SCENARIOS = SCENARIOS
"""What `esrp bench` runs without `--scenarios`."""

_RUST_SCENARIOS = {
    "client-1": "unary-1",
    "env-1": "unary-1",
    "stream-64": "stream-mux-64",
    "vec-64": "batch-64",
}
"""The Rust scenario each Python one is compared with."""

_RUST_BINARY = "esrp-bench.exe" if os.name == "nt" else "esrp-bench"
_EPISODES = 64
_MINIWORLD_ENV = "MiniWorld-PickupObjects-v0"


@dataclass
class Measurement:
    """One scenario's result in one round.

    Attributes:
        scenario: Its name (`env-1`, `rust:unary-1`, ...).
        episodes: Episodes (or envs) stepped together.
        steps: Steps taken in the measured window.
        seconds: Length of the measured window.
        latencies: Seconds per `step` call (per wave for vec-64), measured steps only.
        cpu_seconds: CPU time of this process (all its threads) over the measured steps, for the
            scenarios that run in it (0 for the Rust client's).
        skipped: Why it did not run, if it did not.
        note: Anything else worth printing.
    """

    scenario: str
    episodes: int = 0
    steps: int = 0
    seconds: float = 0.0
    latencies: list[float] = field(default_factory=list, repr=False)
    cpu_seconds: float = 0.0
    skipped: str | None = None
    note: str = ""

    @property
    def steps_per_second(self) -> float:
        """Steps per second over the measured window (0 when skipped)."""
        return self.steps / self.seconds if self.seconds > 0 else 0.0

    @property
    def cpu_per_step(self) -> float | None:
        """This process's CPU seconds per measured step (None when not measured)."""
        return self.cpu_seconds / self.steps if self.cpu_seconds > 0 and self.steps else None

    def percentile(self, p: float) -> float | None:
        """The `p` (0..1) quantile of the step latency in seconds, as esrp-bench picks it."""
        if not self.latencies:
            return None
        ordered = sorted(self.latencies)
        return ordered[round((len(ordered) - 1) * p)]


class _Window:
    """The clock of one scenario: a warm-up, then `seconds` measured."""

    def __init__(self, warmup: float, seconds: float) -> None:
        self.measure_from = time.perf_counter() + warmup
        self.until = self.measure_from + seconds
        self.seconds = seconds


def _closed_loop(name: str, episodes: int, window: _Window, step: Callable[[], int]) -> Measurement:
    """Calls `step` (which takes `steps` steps and returns how many) until the window ends;
    counts the calls that started after the warm-up and ended before the window did.
    """
    result = Measurement(name, episodes=episodes, seconds=window.seconds)
    cpu_from: float | None = None
    while True:
        start = time.perf_counter()
        if start >= window.until:
            return result
        if cpu_from is None and start >= window.measure_from:
            cpu_from = time.process_time()
        steps = step()
        end = time.perf_counter()
        if start >= window.measure_from and end <= window.until:
            result.steps += steps
            result.latencies.append(end - start)
            assert cpu_from is not None
            result.cpu_seconds = time.process_time() - cpu_from


def _test_scenes(client: Client, count: int) -> list[str]:
    """`count` test scenes, round robin over the split (as esrp-bench takes them)."""
    scenes = [scene.id for scene in client.scenes("test", page_size=min(count, 1000))][:count]
    return [scenes[i % len(scenes)] for i in range(count)]


@dataclass(frozen=True)
class _Target:
    """The server a Python scenario connects to, and how."""

    address: str
    token: str | None
    transport: Transport = "auto"
    spread: tuple[str, ...] = ()
    """The servers vec-64 spreads its sub-envs over (none: `address` alone)."""

    def client(self, address: str | None = None) -> Client:
        from .._client import Client

        return Client(address or self.address, token=self.token, transport=self.transport)


def bench_client_1(
    target: _Target, window_of: Callable[[], _Window], label: str | None = None
) -> Measurement:
    """`client-1`: unary steps of one episode."""
    with target.client() as client:
        rng = np.random.default_rng(1)
        with client.create_episode(_test_scenes(client, 1)[0]) as episode:

            def step() -> int:
                result = episode.step(int(rng.integers(6)))
                if result.ended:
                    episode.reset()
                return 1

            return _closed_loop(label or "client-1", 1, window_of(), step)


def _env_stepper(env: gymnasium.Env[Any, Any], actions: list[int]) -> Callable[[], int]:
    """A closed loop's step for a Gymnasium env.

    Each call takes one step: the next of `actions` (2**16 of them, repeated), resetting when an
    episode ends.
    """
    taken = 0

    def step() -> int:
        nonlocal taken
        _, _, terminated, truncated, _ = env.step(actions[taken & 0xFFFF])
        taken += 1
        if terminated or truncated:
            env.reset()
        return 1

    return step


def bench_env_1(target: _Target, window_of: Callable[[], _Window], label: str | None = None) -> Measurement:
    """`env-1`: one Gymnasium env, closed loop, on the scene unary-1 plays."""
    from ..envs import RearrangeEnv

    client = target.client()
    env = RearrangeEnv(client=client, scene=_test_scenes(client, 1)[0])
    try:
        env.reset(seed=0)
        step = _env_stepper(env, np.random.default_rng(2).integers(0, 6, size=1 << 16).tolist())
        return _closed_loop(label or "env-1", 1, window_of(), step)
    finally:
        env.close()
        client.close()


def bench_vec_64(target: _Target, window_of: Callable[[], _Window], label: str | None = None) -> Measurement:
    """`vec-64`: the native vector env of 64 envs, closed loop, on the 64 scenes batch-64 plays
    (spread over `target.spread`'s servers where it names several).
    """
    from ..envs import RearrangeVectorEnv

    clients = [target.client(address) for address in target.spread or (target.address,)]
    envs = RearrangeVectorEnv(
        _EPISODES, client=clients, scene=_test_scenes(clients[0], _EPISODES), scene_per_env=True
    )
    try:
        envs.reset(seed=0)
        rng = np.random.default_rng(4)

        def step() -> int:
            envs.step(rng.integers(0, 6, size=_EPISODES))
            return _EPISODES

        return _closed_loop(label or "vec-64", _EPISODES, window_of(), step)
    finally:
        envs.close()
        for client in clients:
            client.close()


def bench_stream_64(target: _Target, window_of: Callable[[], _Window]) -> Measurement:
    """`stream-64`: 64 episodes on one stream; each answer sends that episode's next step (a reset
    first when it ended), as esrp-bench's `stream-mux-64`.
    """
    with (
        target.client() as client,
        client.episode_stream(window=1) as stream,
    ):
        for scene in _test_scenes(client, _EPISODES):
            stream.create(scene)
        episodes = [answer.created().episode_id for answer in stream]
        rng = np.random.default_rng(3)
        actions = rng.integers(0, 6, size=1 << 16).tolist()
        taken = 0
        window = window_of()
        result = Measurement("stream-64", episodes=_EPISODES, seconds=window.seconds)
        # What each request in flight is, in request order: (sent at, episode, is a step).
        in_flight: list[tuple[float, int, bool]] = []
        for index, episode in enumerate(episodes):
            in_flight.append((time.perf_counter(), index, True))
            stream.step(episode, actions[taken & 0xFFFF])
            taken += 1
        head = 0
        cpu_from: float | None = None
        while (answer := stream.next()) is not None:
            now = time.perf_counter()
            if cpu_from is None and now >= window.measure_from:
                cpu_from = time.process_time()
            elif cpu_from is not None and now <= window.until:
                result.cpu_seconds = time.process_time() - cpu_from
            sent, index, is_step = in_flight[head]
            head += 1
            if not is_step:
                answer.unwrap()
            else:
                ended = answer.step_result().ended
                if sent >= window.measure_from and now <= window.until:
                    result.steps += 1
                    result.latencies.append(now - sent)
                if now < window.until:
                    if ended:
                        in_flight.append((time.perf_counter(), index, False))
                        stream.reset(episodes[index])
                    in_flight.append((time.perf_counter(), index, True))
                    stream.step(episodes[index], actions[taken & 0xFFFF])
                    taken += 1
            if head > 4096:
                del in_flight[:head]
                head = 0
        return result


def find_rust_bench() -> Path | None:
    """The Rust `esrp-bench`: `ESRP_BENCH_BIN`, `PATH`, then the checkout's `target/release`
    (or `CARGO_TARGET_DIR`'s), else None.
    """
    variable = os.environ.get("ESRP_BENCH_BIN")
    if variable:
        return Path(variable) if Path(variable).is_file() else None
    on_path = shutil.which(_RUST_BINARY)
    if on_path:
        return Path(on_path)
    from .._local import _checkout_targets

    for target in _checkout_targets():
        candidate = target / "release" / _RUST_BINARY
        if candidate.is_file():
            return candidate
    return None


def bench_rust(address: str, token: str | None, seconds: float, names: Sequence[str]) -> list[Measurement]:
    """Runs the Rust `esrp-bench` against `address` for the scenarios `names`; one Measurement
    each (named `rust:NAME`), or one skipped Measurement when the binary is missing or fails.
    """
    binary = find_rust_bench()
    if binary is None:
        return [
            Measurement(
                "rust",
                skipped="esrp-bench not found: build it (`cargo build --release -p esrp-client`), "
                "put it on PATH, or set ESRP_BENCH_BIN",
            )
        ]
    with tempfile.TemporaryDirectory() as folder:
        report = Path(folder) / "rust.json"
        command = [
            str(binary),
            "--server",
            address if "://" in address or address.startswith("unix:") else f"http://{address}",
            "--seconds",
            f"{seconds}",
            "--scenarios",
            ",".join(names),
            "--json",
            str(report),
        ]
        environment = dict(os.environ)
        if token is not None:
            environment["ESRP_TOKEN"] = token
        done = subprocess.run(command, capture_output=True, text=True, env=environment, check=False)
        if done.returncode != 0 or not report.is_file():
            tail = (done.stderr or done.stdout).strip().splitlines()[-3:]
            return [Measurement("rust", skipped=f"{binary} failed ({done.returncode}): {' / '.join(tail)}")]
        rows = json.loads(report.read_text())["results"]
    results = []
    for row in rows:
        measurement = Measurement(
            f"rust:{row['scenario']}", episodes=row["episodes"], steps=row["steps"], seconds=row["seconds"]
        )
        # esrp-bench reports quantiles, not samples: a two-point list whose p50 and p99 are them.
        if row.get("p50_ms") is not None:
            measurement.latencies = [row["p50_ms"] / 1e3, row["p99_ms"] / 1e3]
        results.append(measurement)
    return results


def miniworld_unavailable() -> str | None:
    """Why MiniWorld cannot run here (None when it can be imported). Without an X display, pyglet
    is told to render headless (EGL; Mesa's llvmpipe on a machine without a GPU) unless
    `PYGLET_HEADLESS` says otherwise.
    """
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("PYGLET_HEADLESS", "true")
    try:
        importlib.import_module("miniworld")  # registers the MiniWorld envs with Gymnasium
    except Exception as error:  # noqa: BLE001 - any import failure (no package, no OpenGL) skips it
        return (
            f"MiniWorld is not available ({type(error).__name__}: {error}); install it with "
            "`pip install 'esrp[bench]'` (headless: see the README)"
        )
    return None


def bench_miniworld(window_of: Callable[[], _Window]) -> Measurement:
    """`miniworld`: one MiniWorld-PickupObjects-v0 env at 128x128, in process, closed loop."""
    reason = miniworld_unavailable()
    if reason is not None:
        return Measurement("miniworld", skipped=reason)
    import gymnasium

    try:
        env = gymnasium.make(_MINIWORLD_ENV, obs_width=128, obs_height=128)
        env.reset(seed=0)
    except Exception as error:  # noqa: BLE001 - no OpenGL context: skip with the reason
        return Measurement("miniworld", skipped=f"MiniWorld could not start: {type(error).__name__}: {error}")
    try:
        choices = int(getattr(env.action_space, "n", 3))
        step = _env_stepper(env, np.random.default_rng(5).integers(0, choices, size=1 << 16).tolist())
        result = _closed_loop("miniworld", 1, window_of(), step)
        result.note = f"{_MINIWORLD_ENV}, 128x128, in process"
        return result
    finally:
        env.close()


def machine() -> dict[str, Any]:
    """What the numbers were measured on: CPU model, cores, load average, versions."""
    model = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        usable = os.cpu_count() or 0
    versions = {"esrp": __version__, "python": platform.python_version()}
    # From the installed metadata: importing pyglet (through miniworld) before its headless option
    # is set would pin it to X11.
    for package in ("grpcio", "protobuf", "numpy", "gymnasium", "miniworld", "esrp-native"):
        with contextlib.suppress(importlib.metadata.PackageNotFoundError):
            versions[package] = importlib.metadata.version(package)
    return {
        "cpu": model,
        "cores": os.cpu_count() or 0,
        "usable_cores": usable,
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else [],
        "platform": platform.platform(),
        "versions": versions,
        "grpc_experiments": os.environ.get("GRPC_EXPERIMENTS", ""),
    }


def run(
    address: str,
    *,
    scenarios: Sequence[str] = DEFAULT_SCENARIOS,
    seconds: float = 5.0,
    warmup: float = 1.0,
    token: str | None = None,
    round_index: int = 0,
    log: Callable[[str], None] = lambda line: None,
    transports: Sequence[Transport] = ("auto",),
    spread: Sequence[str] = (),
) -> list[Measurement]:
    """One round of `scenarios` against the server at `address`; their Measurements in order.
    client-1, env-1 and vec-64 run once per transport (`Client`'s `transport`): under their own
    name with the first, as `env-1@grpcio` (...) with the others. stream-64 runs once (streams
    always go through grpcio). With `spread` (several addresses), vec-64 spreads its sub-envs over
    those servers, as `vec-64/K-servers`.
    """

    def window_of() -> _Window:
        return _Window(warmup, seconds)

    results: list[Measurement] = []
    python_names = [name for name in scenarios if name in _RUST_SCENARIOS]
    for name in scenarios:
        log(f"round {round_index + 1}: {name}")
        if name in _BY_TRANSPORT:
            spreads = name == "vec-64" and len(spread) > 1
            for index, transport in enumerate(transports):
                label = f"{name}/{len(spread)}-servers" if spreads else name
                label += "" if index == 0 else f"@{transport}"
                target = _Target(address, token, transport, tuple(spread) if spreads else ())
                results.append(_BY_TRANSPORT[name](target, window_of, label))
        elif name == "stream-64":
            results.append(bench_stream_64(_Target(address, token), window_of))
        elif name == "rust":
            wanted = list(dict.fromkeys(_RUST_SCENARIOS[n] for n in python_names)) or ["unary-1"]
            results.extend(bench_rust(address, token, seconds, wanted))
        elif name == "miniworld":
            results.append(bench_miniworld(window_of))
        else:
            raise ValueError(f"unknown scenario {name!r}: use {', '.join(SCENARIOS)}")
    return results


_BY_TRANSPORT: dict[str, Callable[[_Target, Callable[[], _Window], str], Measurement]] = {
    "client-1": bench_client_1,
    "env-1": bench_env_1,
    "vec-64": bench_vec_64,
}
"""The scenarios that run once per transport."""


@dataclass
class _Row:
    """A table row: one scenario over every round."""

    scenario: str
    episodes: int
    rates: list[float]
    p50: list[float]
    p99: list[float]
    cpu: list[float]
    ratios: list[float]
    skipped: str | None
    note: str


def _rows(rounds: Sequence[Sequence[Measurement]]) -> list[_Row]:
    names = list(dict.fromkeys(m.scenario for results in rounds for m in results))
    rows = []
    for name in names:
        found = [m for results in rounds for m in results if m.scenario == name]
        ran = [m for m in found if m.skipped is None]
        ratios = []
        for results in rounds:
            mine = next((m for m in results if m.scenario == name and m.skipped is None), None)
            twin = _RUST_SCENARIOS.get(name.split("@")[0])
            rust = next((m for m in results if m.scenario == f"rust:{twin}" and m.skipped is None), None)
            if mine is not None and rust is not None and rust.steps_per_second > 0:
                ratios.append(mine.steps_per_second / rust.steps_per_second)
        rows.append(
            _Row(
                scenario=name,
                episodes=max((m.episodes for m in found), default=0),
                rates=[m.steps_per_second for m in ran],
                p50=[p for m in ran if (p := m.percentile(0.5)) is not None],
                p99=[p for m in ran if (p := m.percentile(0.99)) is not None],
                cpu=[c for m in ran if (c := m.cpu_per_step) is not None],
                ratios=ratios,
                skipped=found[0].skipped if not ran else None,
                note=next((m.note for m in ran if m.note), ""),
            )
        )
    return rows


def _median(values: Sequence[float]) -> float | None:
    return statistics.median(values) if values else None


def _scaled(value: float | None, factor: float) -> float | None:
    return None if value is None else value * factor


def format_table(rounds: Sequence[Sequence[Measurement]]) -> str:
    """The results as a text table: medians over the rounds."""
    header = (
        f"{'scenario':<20} {'envs':>5} {'steps/s':>9} {'p50 ms':>8} {'p99 ms':>8} {'vs Rust':>8} "
        f"{'cpu us/step':>11}  note"
    )
    lines = [header]
    for row in _rows(rounds):
        if row.skipped is not None:
            lines.append(f"{row.scenario:<20} {'':>5} {'skipped':>9}  {row.skipped}")
            continue
        rate, p50, p99, ratio, cpu = (_median(v) for v in (row.rates, row.p50, row.p99, row.ratios, row.cpu))
        spread = ""
        if len(row.rates) > 1:
            spread = f"rounds {min(row.rates):,.0f}-{max(row.rates):,.0f}"
        note = "; ".join(
            part for part in (row.note if row.scenario.startswith("rust:") else "", spread) if part
        )
        lines.append(
            f"{row.scenario:<20} {row.episodes:>5} {rate or 0:>9,.0f} "
            f"{'' if p50 is None else f'{p50 * 1e3:.2f}':>8} {'' if p99 is None else f'{p99 * 1e3:.2f}':>8} "
            f"{'' if ratio is None else f'{ratio:.2f}x':>8} "
            f"{'' if cpu is None else f'{cpu * 1e6:.0f}':>11}  {note}"
        )
    return "\n".join(lines)


def _json_report(rounds: Sequence[Sequence[Measurement]], info: dict[str, Any]) -> dict[str, Any]:
    rows = []
    for row in _rows(rounds):
        rows.append(
            {
                "scenario": row.scenario,
                "episodes": row.episodes,
                "skipped": row.skipped,
                "steps_per_second": _median(row.rates),
                "p50_ms": _scaled(_median(row.p50), 1e3),
                "p99_ms": _scaled(_median(row.p99), 1e3),
                "ratio_to_rust": _median(row.ratios),
                "client_cpu_us_per_step": _scaled(_median(row.cpu), 1e6),
                "rounds_steps_per_second": row.rates,
                "note": row.note,
            }
        )
    per_round = [
        [{k: v for k, v in asdict(m).items() if k != "latencies"} for m in results] for results in rounds
    ]
    return {**info, "results": rows, "rounds": per_round}


@contextlib.contextmanager
def _servers(addresses: list[str] | None, count: int, unix_socket: bool) -> Iterator[list[str]]:
    """The servers' addresses: `addresses`, or `count` servers started here (stopped after)."""
    if addresses is not None:
        yield addresses
        return
    from .._local import start_servers

    started = start_servers(count, unix_socket=unix_socket)
    try:
        yield [server.address for server in started]
    finally:
        for server in started:
            server.stop()


def _parse_args(argv: Sequence[str] | None, prog: str) -> argparse.Namespace:
    # The `esrp` command's parser: an error is one line, `PROG: error: ... (see PROG --help)`.
    from ._args import Parser

    parser = Parser(
        prog=prog,
        description="Throughput and latency of the esrp Python client, beside the Rust client and MiniWorld.",
    )
    parser.add_argument(
        "--server",
        help="a running server, host:port or unix:PATH, or several, comma-separated, for --servers "
        "(default: start esrp-server on a free port)",
    )
    parser.add_argument(
        "--servers",
        type=int,
        help="spread vec-64's sub-envs over this many servers: started here, or those of --server "
        "(default 1, or --server's count)",
    )
    parser.add_argument(
        "--socket",
        action="store_true",
        help="the server started here also serves a Unix domain socket (--listen-unix) and the "
        "clients connect through it, as an env that starts its own server does (default: loopback TCP)",
    )
    parser.add_argument("--token", default=os.environ.get("ESRP_TOKEN"), help="bearer token (env ESRP_TOKEN)")
    parser.add_argument(
        "--seconds", type=float, default=5.0, help="measured seconds per scenario (default 5)"
    )
    parser.add_argument("--warmup", type=float, default=1.0, help="warm-up seconds per scenario (default 1)")
    parser.add_argument(
        "--scenarios",
        default=",".join(DEFAULT_SCENARIOS),
        help=f"comma-separated, of {', '.join(SCENARIOS)} (default: all)",
    )
    parser.add_argument(
        "--repeat", type=int, default=1, help="rounds of every scenario; the table shows medians"
    )
    parser.add_argument(
        "--warmup-rounds",
        type=int,
        default=1,
        help="unmeasured rounds first, so that the server has generated the scenes (default 1)",
    )
    parser.add_argument(
        "--transport",
        default="auto",
        help="comma-separated transports of client-1, env-1 and vec-64: auto (native where esrp-native "
        "is installed), native, grpcio; the first one's rows have the plain names (default auto)",
    )
    parser.add_argument("--json", type=Path, help="also write the results to this JSON file")
    parser.add_argument(
        "--processes",
        type=int,
        default=1,
        help="run the scenarios in this many processes at once against one server; the table sums "
        "them (default 1)",
    )
    args = parser.parse_args(argv)
    args.transports = [name.strip() for name in args.transport.split(",") if name.strip()]
    from .. import _native

    for transport in args.transports:
        try:
            _native.resolve(transport, secure=False)
        except ValueError as error:
            parser.error(f"--transport: {error}")
    if not args.transports or len(set(args.transports)) != len(args.transports):
        parser.error("--transport: give one or more different transports")
    args.scenarios = [name.strip() for name in args.scenarios.split(",") if name.strip()]
    unknown = [name for name in args.scenarios if name not in SCENARIOS]
    if unknown:
        parser.error(f"unknown scenario(s) {', '.join(unknown)}: use {', '.join(SCENARIOS)}")
    if args.socket and args.server is not None:
        parser.error("--socket is for the server started here: name a server's socket as --server unix:PATH")
    args.addresses = None
    if args.server is not None:
        args.addresses = [address.strip() for address in args.server.split(",") if address.strip()]
        if not args.addresses:
            parser.error("--server: give an address")
        if args.servers is not None and args.servers != len(args.addresses):
            parser.error(f"--servers {args.servers} but --server names {len(args.addresses)}")
    args.servers = args.servers if args.servers is not None else len(args.addresses or [None])
    if not 1 <= args.servers <= _EPISODES:
        parser.error(f"--servers must be between 1 and {_EPISODES} (vec-64's sub-envs)")
    if args.servers > 1 and "vec-64" not in args.scenarios:
        parser.error("--servers spreads vec-64 over several servers: run vec-64")
    if not 1 <= args.processes <= 256:
        parser.error("--processes must be between 1 and 256")
    if args.processes > 1 and {"rust", "miniworld"} & set(args.scenarios):
        parser.error("--processes runs the Python scenarios only: leave rust and miniworld out")
    if args.repeat < 1 or args.seconds <= 0 or args.warmup < 0 or args.warmup_rounds < 0:
        parser.error(
            "--repeat must be at least 1, --seconds positive, --warmup and --warmup-rounds not negative"
        )
    return args


def main(argv: Sequence[str] | None = None, prog: str = "python -m esrp.bench") -> int:
    """The command line: runs the rounds, prints the machine and the table, writes the JSON.
    `prog` names the command in its usage and errors (`esrp bench` when the `esrp` command runs it).

    First it applies the process tunings the measurements assume (`esrp._grpc_setup`, before
    anything here imports grpc, and `esrp._malloc_setup`); this module imports grpc only then.
    """
    _grpc_setup.apply()
    _malloc_setup.apply()
    handle_signals = argv is None and threading.current_thread() is threading.main_thread()
    return run_command(prog, lambda: _checked(argv, prog), handle_signals=handle_signals)


def _checked(argv: Sequence[str] | None, prog: str) -> int:
    from .._errors import EsrpError

    args = _parse_args(argv, prog)
    try:
        return _main(args)
    except EsrpError as error:
        print(f"{prog}: {type(error).__name__}: {error}", file=sys.stderr)
        return 1


def _in_processes(args: argparse.Namespace, addresses: Sequence[str]) -> list[dict[str, Any]]:
    """Runs this command with `args` in `args.processes` child processes at once against the
    servers at `addresses`; returns each child's JSON report.
    """
    flags = [
        *("--server", ",".join(addresses), "--scenarios", ",".join(args.scenarios)),
        *("--seconds", str(args.seconds), "--warmup", str(args.warmup), "--repeat", str(args.repeat)),
        *("--warmup-rounds", str(args.warmup_rounds), "--transport", ",".join(args.transports)),
    ]
    environment = dict(os.environ)
    if args.token is not None:
        environment["ESRP_TOKEN"] = args.token
    with tempfile.TemporaryDirectory(prefix="esrp-bench-") as folder:
        paths = [Path(folder) / f"{i}.json" for i in range(args.processes)]
        children = [
            subprocess.Popen(
                [sys.executable, "-m", "esrp.bench", *flags, "--json", str(path)],
                stdout=subprocess.DEVNULL,
                env=environment,
            )
            for path in paths
        ]
        codes = [child.wait() for child in children]
        if any(codes):
            raise RuntimeError(f"a benchmark process failed (exit statuses {codes})")
        return [json.loads(path.read_text(encoding="utf-8")) for path in paths]


def _summed(reports: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per scenario of several processes' reports: their steps/s summed, the median of
    their median latencies and the worst of their p99s.
    """
    rows = []
    for first in reports[0]["results"]:
        same = [r for report in reports for r in report["results"] if r["scenario"] == first["scenario"]]
        rates = [r["steps_per_second"] for r in same if r["steps_per_second"] is not None]
        p50 = [r["p50_ms"] for r in same if r["p50_ms"] is not None]
        p99 = [r["p99_ms"] for r in same if r["p99_ms"] is not None]
        rows.append(
            {
                "scenario": first["scenario"],
                "episodes": sum(r["episodes"] for r in same),
                "steps_per_second": sum(rates) if rates else None,
                "p50_ms": statistics.median(p50) if p50 else None,
                "p99_ms": max(p99) if p99 else None,
                "processes_steps_per_second": rates,
            }
        )
    return rows


def _main_processes(args: argparse.Namespace) -> int:
    """`--processes N`: the children's reports, summed, printed and written."""
    with _servers(args.addresses, args.servers, args.socket) as addresses:
        print(f"server {', '.join(addresses)}: {args.processes} processes at once", flush=True)
        reports = _in_processes(args, addresses)
    rows = _summed(reports)
    print(f"{'scenario':<22}{'episodes':>9}{'steps/s':>11}{'p50 ms':>9}{'p99 ms':>9}")
    for row in rows:
        rate = "" if row["steps_per_second"] is None else f"{row['steps_per_second']:.0f}"
        p50 = "" if row["p50_ms"] is None else f"{row['p50_ms']:.2f}"
        p99 = "" if row["p99_ms"] is None else f"{row['p99_ms']:.2f}"
        print(f"{row['scenario']:<22}{row['episodes']:>9}{rate:>11}{p50:>9}{p99:>9}")
    if args.json is not None:
        report = {"date": time.strftime("%Y-%m-%d"), "processes": args.processes, "results": rows}
        args.json.write_text(json.dumps({**report, "children": reports}, indent=2))
    return 0


def _main(args: argparse.Namespace) -> int:
    from .._client import Client

    if args.processes > 1:
        return _main_processes(args)

    before = machine()
    print(
        f"machine: {before['cpu']}, {before['cores']} cores ({before['usable_cores']} usable), "
        f"load average {' '.join(f'{x:.2f}' for x in before['load_average'])}; "
        f"Python {before['versions']['python']}, esrp {__version__}"
        + (f"; GRPC_EXPERIMENTS={before['grpc_experiments']}" if before["grpc_experiments"] else ""),
        flush=True,
    )
    rounds: list[list[Measurement]] = []
    with _servers(args.addresses, args.servers, args.socket) as addresses:
        address = addresses[0]
        with Client(address, token=args.token) as client:
            info = client.server_info()
        transports = {}
        for transport in args.transports:
            with Client(address, token=args.token, transport=transport) as client:
                transports[transport] = client.transport
        if len(addresses) > 1:
            print(f"vec-64 over {len(addresses)} servers: {', '.join(addresses)}", flush=True)
        print(
            f"server {address}: esrp-server {info.version}, renderer {info.renderer_adapter} "
            f"({info.renderer_backend}, {info.renderer_rasterizer} rasterizer), dataset {info.dataset}; "
            "transport "
            + ", ".join(f"{t} = {resolved}" if t == "auto" else t for t, resolved in transports.items()),
            flush=True,
        )
        # The warm-up rounds first, unmeasured, then the measured ones: the same scenarios.
        for index in range(-args.warmup_rounds, args.repeat):
            warm = index < 0
            label = "  warm-up {} (not counted)" if warm else "  {}"

            def log(line: str, label: str = label) -> None:
                print(label.format(line), file=sys.stderr, flush=True)

            results = run(
                address,
                scenarios=args.scenarios,
                seconds=args.seconds,
                warmup=args.warmup,
                token=args.token,
                round_index=index + args.warmup_rounds if warm else index,
                log=log,
                transports=args.transports,
                spread=addresses,
            )
            if not warm:
                rounds.append(results)
    after = machine()
    print(format_table(rounds))
    print(f"load average after: {' '.join(f'{x:.2f}' for x in after['load_average'])}")
    if args.json is not None:
        report = _json_report(
            rounds,
            {
                "date": time.strftime("%Y-%m-%d"),
                "server": address,
                "servers": addresses,
                "server_version": info.version,
                "renderer": info.renderer_adapter,
                "backend": info.renderer_backend,
                "rasterizer": info.renderer_rasterizer,
                "seconds": args.seconds,
                "warmup": args.warmup,
                "repeat": args.repeat,
                "warmup_rounds": args.warmup_rounds,
                "transports": transports,
                "machine": before,
                "load_average_after": after["load_average"],
            },
        )
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
