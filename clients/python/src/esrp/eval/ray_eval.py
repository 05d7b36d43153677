"""`esrp eval --ray`: one evaluation distributed over a Ray cluster, writing the same results file
as a local run.

One Ray actor per server connection. An actor either starts an `esrp-server` next to itself
(`spawn_servers`: a `LocalServer` in the actor's process, on the actor's node) or is pinned to one
given server (`servers`: episodes are stateful, so an actor never changes server). The actor builds
its gRPC channel and its agents inside its own process (never before a fork), from the same
`EvalSettings` as a local run, so every agent `esrp eval` knows (random, expert, plan, vlm,
MODULE:CALLABLE with its config) runs the same way there.

The driver fixes the scenes up front (dataset order, the local run's filters, minus what the results
file already holds), hands each actor at most `episodes_per_actor` episodes at a time (backpressure:
a scene is handed out only when a slot frees, in order, so no bias toward short episodes) and is the
only writer of the results file: a record is appended when its episode's task returns, once.

Faults use Ray's own machinery. When an actor's server dies (a spawned server that exited, or a
pinned one that answers UNAVAILABLE), the actor ends its own process; Ray restarts it
(`max_restarts`; a spawned server is started afresh) and re-runs its unfinished episodes there from
their start (`max_task_retries`): episodes are deterministic, so the result is what it would have
been. An actor out of restarts is dropped and its episodes go to the others. A run interrupted as a
whole resumes from its results file like a local one.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from .. import _signals
from .._async_client import AsyncClient
from .._errors import EsrpError, ServerUnavailable
from .._local import LocalServer
from .._values import SceneSummary, ServerInfo
from .evaluation import (
    EvalError,
    EvalOutcome,
    EvalSettings,
    FailureLog,
    Progress,
    agent_factory,
    finish,
    free_on_resume,
    open_results,
    pick_scenes,
    play_episode,
    stops_the_run,
)
from .results import EpisodeRecord, append_record

__all__ = ["EvalActor", "RaySettings", "run_ray_eval"]


@dataclass
class RaySettings:
    """How `esrp eval --ray` uses the cluster; the fields are its flags.

    Attributes:
        address: The Ray cluster: None starts a local one for the run; `auto` joins the one this
            machine belongs to; or `ray://HOST:PORT` / `HOST:PORT`.
        servers: Pinned servers (`host:port`), one actor each; empty: actors spawn their own.
        spawn_servers: Actors that start an esrp-server next to themselves; 0: one per CPU of the
            cluster (each actor reserves `cpus_per_actor`).
        cpus_per_actor: CPUs an actor (and its spawned server) reserves.
        episodes_per_actor: Episodes in flight on each actor (each actor's server).
        max_restarts: Restarts of an actor whose server died (Ray's `max_restarts`).
        token: The servers' bearer token (given to spawned servers too).
        server_args: More flags of spawned servers.
    """

    address: str | None = None
    servers: Sequence[str] = ()
    spawn_servers: int = 0
    cpus_per_actor: float = 1.0
    episodes_per_actor: int = 8
    max_restarts: int = 3
    token: str | None = None
    server_args: Sequence[str] = ()


class EvalActor:
    """Plays episodes on one server: its own (`address` None: started here) or a pinned one.

    Made a Ray actor by `run_ray_eval` (`ray.remote(...)(EvalActor)`): an asyncio actor, so the
    episodes the driver hands it run concurrently on one client.
    """

    def __init__(
        self, settings: EvalSettings, address: str | None, token: str | None, server_args: Sequence[str]
    ) -> None:
        self.settings = settings
        self.token = token
        self.server: LocalServer | None = None
        if address is None:
            server_flags = [*server_args, *(["--token", token] if token else [])]
            self.server = LocalServer(*server_flags, unix_socket="auto").start()
            address = self.server.address
        self.address = address
        self.factory = agent_factory(settings)
        self._client: AsyncClient | None = None
        self._info: ServerInfo | None = None

    async def _connect(self) -> tuple[AsyncClient, ServerInfo]:
        if self._client is None or self._info is None:
            client = AsyncClient(self.address, token=self.token, timeout=120)
            await client.wait_healthy(30)
            self._info = await client.server_info()
            self._client = client
        return self._client, self._info

    async def describe(self) -> tuple[ServerInfo, list[SceneSummary]]:
        """The server's info and the scenes the settings choose (fixed up front by the driver)."""
        client, info = await self._connect()
        return info, await pick_scenes(client, self.settings)

    async def play(self, scene: SceneSummary) -> EpisodeRecord:
        """Plays `scene` and returns its record. When the server is gone, ends this actor's
        process: Ray restarts the actor and runs the episode again from its start.
        """
        client, info = await self._connect()
        try:
            return await play_episode(client, info, scene, self.settings, self.factory)
        except EsrpError as error:
            if self._server_gone(error):
                self._end(f"{scene.id}: the server at {self.address} is gone ({error})")
            raise

    def _server_gone(self, error: EsrpError) -> bool:
        """Whether `error` means this actor's server is gone (not an error of the episode)."""
        if self.server is None:
            return isinstance(error, ServerUnavailable)
        process = self.server.process
        if process is None or process.poll() is not None:
            return True
        if not isinstance(error, ServerUnavailable):
            return False
        # A killed process closes its sockets before it can be reaped: give it a moment.
        try:
            process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            return False
        return True

    def server_pid(self) -> int | None:
        """The spawned server's process id (None for a pinned server)."""
        return None if self.server is None else self.server.pid

    def _end(self, why: str) -> None:
        print(f"esrp eval --ray: {why}; restarting this actor", file=sys.stderr, flush=True)
        if self.server is not None:
            with contextlib.suppress(Exception):
                self.server.stop()
        # Not an exception (that would fail one task): the process ends, and Ray's restart and
        # task retries take over.
        os._exit(1)


def _actor_died(error: BaseException) -> bool:
    import ray.exceptions

    return isinstance(error, ray.exceptions.RayActorError | ray.exceptions.ActorUnavailableError)


def run_ray_eval(settings: EvalSettings, cluster: RaySettings) -> EvalOutcome:
    """Runs `settings` over a Ray cluster (see the module's docstring); returns what happened."""
    try:
        import ray
    except ImportError:
        raise EvalError("--ray needs Ray: pip install 'esrp[ray]'") from None
    if settings.episodes_in_flight < 1 or cluster.episodes_per_actor < 1:
        raise EvalError("episodes in flight must be at least 1")
    agent_factory(settings)  # a bad agent spec fails here, before any actor starts
    if not sys.stderr.isatty():
        # Ray colours the prefix of the workers' lines it prints here (`(EvalActor pid=...)`)
        # whatever stderr is: not into a file or a pipe.
        os.environ.setdefault("RAY_COLOR_PREFIX", "0")
    started_ray = False
    if not ray.is_initialized():
        options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": True}
        # `ray.init()` with no address joins the newest cluster started on this machine (or
        # $RAY_ADDRESS's) when there is one; "local" always starts a cluster of the run's own.
        try:
            ray.init(address=cluster.address or "local", **options)
        except ConnectionError as error:
            # Ray's own message names its `ray.init` arguments (`--address`), not esrp eval's.
            raise EvalError(
                f"--ray {cluster.address}: no Ray cluster could be reached there ({error}): start one "
                "(`ray start --head` for `auto`), name its address, or pass --ray local for one of the "
                "run's own"
            ) from None
        started_ray = True
        _signals.reclaim()  # ray.init replaced the command's SIGTERM handler with one of its own
    try:
        return _drive(ray, settings, cluster)
    finally:
        if started_ray:
            ray.shutdown()


def _drive(ray: Any, settings: EvalSettings, cluster: RaySettings) -> EvalOutcome:  # noqa: ANN401
    actor_class = ray.remote(
        num_cpus=cluster.cpus_per_actor,
        max_restarts=cluster.max_restarts,
        max_task_retries=-1,
    )(EvalActor)
    if cluster.servers:
        addresses: list[str | None] = list(cluster.servers)
    else:
        cpus = float(ray.cluster_resources().get("CPU", 1))
        count = cluster.spawn_servers or max(int(cpus // cluster.cpus_per_actor), 1)
        addresses = [None] * count
    server_args = list(cluster.server_args)
    actors = [actor_class.remote(settings, address, cluster.token, server_args) for address in addresses]
    where = "pinned to " + ", ".join(cluster.servers) if cluster.servers else "each with its own esrp-server"
    print(f"esrp eval --ray: {len(actors)} actors, {where}", file=sys.stderr)
    info, scenes = _first_answer(ray, [actor.describe.remote() for actor in actors])
    print(
        f"esrp-server {info.version}: dataset {info.dataset}, renderer {info.renderer_adapter}",
        file=sys.stderr,
    )

    out = settings.out
    resumed = open_results(settings, scenes, free_on_resume(settings))
    records, done, earlier, tally = resumed.records, resumed.done, resumed.earlier, resumed.tally
    pending = deque(resumed.todo)
    progress = Progress(len(scenes), earlier, settings.progress)
    failures = FailureLog(out, progress)
    written = 0
    started = time.monotonic()
    live = set(range(len(actors)))
    in_flight: dict[Any, tuple[int, SceneSummary]] = {}
    load = [0] * len(actors)

    def hand_out() -> None:
        for index in sorted(live, key=lambda i: load[i]):
            while pending and load[index] < cluster.episodes_per_actor:
                scene = pending.popleft()
                in_flight[actors[index].play.remote(scene)] = (index, scene)
                load[index] += 1

    try:
        with open(out, "ab") as file:
            hand_out()
            while in_flight:
                ready, _ = ray.wait(list(in_flight), num_returns=1)
                ref = ready[0]
                index, scene = in_flight.pop(ref)
                load[index] -= 1
                try:
                    record: EpisodeRecord = ray.get(ref)
                except Exception as error:  # noqa: BLE001 - sorted below: an actor gone, or the episode's own error.
                    cause = getattr(error, "cause", None) or error
                    if _actor_died(error):
                        if index in live:
                            live.discard(index)
                            gone = type(error).__name__
                            progress.note(f"an actor is gone for good ({gone}); {len(live)} actors left")
                        if not live:
                            raise EvalError(
                                f"every actor died; {len(pending) + len(in_flight) + 1} episodes not run "
                                "(rerun to resume)"
                            ) from error
                        pending.appendleft(scene)  # played again from its start elsewhere
                    else:
                        stopped = stops_the_run(scene.id, cause, written)
                        if stopped is not None:
                            raise stopped from error
                        # A task's error carries the worker's traceback in its text.
                        failures.add(scene.id, cause, trace=str(error))
                        progress.advance(tally)
                    hand_out()
                    continue
                if record.scene_id not in done:  # each episode once, whatever Ray retried
                    done.add(record.scene_id)
                    append_record(file, record)
                    written += 1
                    records.append(record)
                    tally.add(record)
                    progress.advance(tally)
                hand_out()
    finally:
        progress.close()
        for actor in actors:
            with contextlib.suppress(Exception):
                ray.kill(actor, no_restart=True)

    return finish(settings, info, records, written, failures, time.monotonic() - started)


def _first_answer(ray: Any, refs: list[Any]) -> tuple[ServerInfo, list[SceneSummary]]:  # noqa: ANN401
    """The first actor's answer to `describe` that comes back (all agree: the same dataset)."""
    errors: list[str] = []
    waiting = list(refs)
    while waiting:
        ready, waiting = ray.wait(waiting, num_returns=1)
        try:
            answer: tuple[ServerInfo, list[SceneSummary]] = ray.get(ready[0])
        except EvalError:
            raise
        except Exception as error:  # noqa: BLE001 - another actor may still answer.
            cause = getattr(error, "cause", None)
            if isinstance(cause, EvalError):
                raise cause from None
            errors.append(f"{type(error).__name__}: {error}")
            continue
        return answer
    raise EvalError("no actor could reach its server: " + "; ".join(errors[:3]))
