"""`esrp verify`: replays every record of `esrp.results/v1` files on a server and checks that the
replay reproduces the record exactly.

The simulator is deterministic, so a record's `actions` stepped from its scene's start, with its
`horizon`, give back its metrics bit for bit (docs/evaluation.md, "Replaying"). For each record a
new episode of `scene_id` is created (not privileged, so challenge scenes replay too, on a server
that serves them) and the actions are stepped; the replay must then agree with the record on
`success`, `osr`, `rdr`, `stage`, `placed`, `steps` and `total_reward` (compared exactly: both
are the server's doubles), and on `end`: a record that ended in `success` or at the `horizon` must
end so at its last action, one the `agent` ended must still be running after its last action, and
no replay may end before its last action. A record of another dataset than the server's, or of a
scene the server does not serve, does not match either (with a message saying why).

The files are read whole before anything is replayed (bad input fails at once); the replays run
`episodes_in_flight` at a time on one `AsyncClient`, in file order, with `esrp eval`'s progress
bar. Self-reported `esrp eval` / `esrp-eval` files and the server's own records verify alike.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from .._async_client import AsyncClient
from .._common import unreachable
from .._errors import EsrpError, SceneNotFound, ServerUnavailable
from .._local import LocalServer
from .._values import EpisodeMetrics, Sensors, ServerInfo
from ._pool import run_workers
from .evaluation import Progress, ServerGone, server_gone
from .results import EpisodeRecord, ReadRecords, ResultsError, load_records, no_records

__all__ = [
    "CHALLENGE_PREFIXES",
    "LABEL",
    "Mismatch",
    "Numbered",
    "VerifyError",
    "VerifyOutcome",
    "compare",
    "read_inputs",
    "run_verify",
    "verify",
]

LABEL = "esrp verify"
"""The agent label of the replays' episodes (`CreateEpisodeRequest.agent`, in a server's records)."""

CHALLENGE_PREFIXES = ("challenge/", "minival/")
"""How the ids of the hidden splits' scenes begin."""

_CHALLENGE_ONLY = (
    "challenge scenes replay only on a server started with the challenge's --challenge-seed "
    "(and an admin token)"
)

# The replays draw nothing anyone looks at: the smallest images the server makes (the simulation
# does not depend on them).
_SENSORS = Sensors(resolution=16)


class VerifyError(Exception):
    """The verification cannot run: its input is not readable results (exit status 2)."""


@dataclass(frozen=True)
class Numbered:
    """A record and where it was read: its file and line (1-based)."""

    path: Path
    line: int
    record: EpisodeRecord

    @property
    def where(self) -> str:
        """`FILE:LINE`."""
        return f"{self.path}:{self.line}"


@dataclass(frozen=True)
class Mismatch:
    """A record whose replay does not reproduce it.

    Attributes:
        source: The record and where it is.
        differences: What differs, one entry per field (`osr: recorded 1.0, replayed 0.5`), or
            why the record could not be replayed.
    """

    source: Numbered
    differences: tuple[str, ...]

    def text(self) -> str:
        """One line: `FILE:LINE: SCENE: what differs; ...`."""
        return f"{self.source.where}: {self.source.record.scene_id}: " + "; ".join(self.differences)


@dataclass
class VerifyOutcome:
    """What a verification found.

    Attributes:
        records: How many records were replayed (or found unreplayable).
        mismatches: The records that do not match, in input order.
    """

    records: int
    mismatches: list[Mismatch] = field(default_factory=list)

    def summary(self) -> str:
        """The closing line: `N records verified, all match` or `K of N records do not match`."""
        if not self.mismatches:
            return f"{self.records} records verified, all match"
        return f"{len(self.mismatches)} of {self.records} records do not match"


def read_inputs(paths: Sequence[Path]) -> list[Numbered]:
    """Every record of `paths`, in order, with its file and line. Raises `VerifyError` for a file
    that cannot be read or holds a line that is not an `esrp.results/v1` record, and when the
    files hold no record at all. A last line cut short (a write in progress, or interrupted) is
    said on stderr and left out.
    """
    numbered: list[Numbered] = []
    reads: list[ReadRecords] = []
    for path in paths:
        try:
            read = load_records(path, "esrp verify")
        except ResultsError as error:
            raise VerifyError(str(error)) from None
        reads.append(read)
        numbered += [Numbered(path, n, r) for n, r in zip(read.line_numbers, read.records, strict=True)]
    if not numbered:
        raise VerifyError(no_records(paths, reads))
    return numbered


def _end_of(metrics: EpisodeMetrics) -> str:
    return "success" if metrics.success else "horizon"


def compare(record: EpisodeRecord, metrics: EpisodeMetrics, ended_after: int | None) -> list[str]:
    """What differs between `record` and its replay, which ended with `metrics` after
    `ended_after` of the record's actions (None: still running after the last one).
    """
    different: list[str] = []
    total = len(record.actions)
    if ended_after is not None and ended_after < total:
        different.append(
            f"the replay ended ({_end_of(metrics)}) after {ended_after} of the record's {total} actions"
        )
    replayed_end = "agent" if ended_after is None else _end_of(metrics)
    pairs: list[tuple[str, object, object]] = [
        ("success", record.success, metrics.success),
        ("osr", record.osr, metrics.object_success_rate),
        ("rdr", record.rdr, metrics.remaining_distance_ratio),
        ("stage", record.stage, metrics.stage),
        ("placed", record.placed, metrics.placed),
        ("steps", record.steps, metrics.steps),
        ("total_reward", record.total_reward, metrics.total_reward),
        ("end", record.end, replayed_end),
    ]
    for name, recorded, replayed in pairs:
        # Exact: the record holds the server's doubles, which JSON carries without loss.
        if recorded != replayed:
            different.append(f"{name}: recorded {recorded!r}, replayed {replayed!r}")
    return different


async def _replay(client: AsyncClient, record: EpisodeRecord) -> list[str]:
    """Replays one record; returns what differs (nothing: it matches). Raises `ServerUnavailable`
    when the server does not answer; other errors of the server are differences.
    """
    try:
        episode = await client.create_episode(
            record.scene_id, horizon=record.horizon, sensors=_SENSORS, agent=LABEL
        )
    except ServerUnavailable:
        raise
    except EsrpError as error:
        if record.scene_id.startswith(CHALLENGE_PREFIXES):
            return [f"not replayed: {_CHALLENGE_ONLY} ({type(error).__name__}: {error.message})"]
        if isinstance(error, SceneNotFound):
            return [f"not replayed: the server does not serve scene {record.scene_id!r}"]
        return [f"not replayed: CreateEpisode failed: {type(error).__name__}: {error.message}"]
    metrics: EpisodeMetrics | None = None
    ended_after: int | None = None
    try:
        if record.actions:
            window = min(len(record.actions), 64)
            async with await client.episode_stream(window=window) as stream:
                results = (await stream.run({episode.id: record.actions}))[episode.id]
            for k, result in enumerate(results, start=1):
                if isinstance(result, ServerUnavailable):
                    raise result
                if isinstance(result, EsrpError):
                    return [f"not replayed: step {k} failed: {type(result).__name__}: {result.message}"]
                if result.ended:
                    metrics, ended_after = result.metrics, k
                    break
    finally:
        with contextlib.suppress(EsrpError):
            closed = await episode.close()
            metrics = metrics if metrics is not None else closed
    if metrics is None:
        return ["not replayed: the server answered no final metrics"]
    return compare(record, metrics, ended_after)


async def verify(
    client: AsyncClient,
    inputs: Sequence[Numbered],
    *,
    episodes_in_flight: int = 8,
    local: LocalServer | None = None,
    progress: bool = True,
) -> VerifyOutcome:
    """Replays `inputs` on `client`'s server, `episodes_in_flight` at a time; returns what does not
    match, in input order. A server that dies (`local` exits) or stays unreachable stops the run
    with `ServerGone`.
    """
    info: ServerInfo = await client.server_info()
    print(f"esrp-server {info.version} at {client.address}: dataset {info.dataset}", file=sys.stderr)
    found: dict[int, list[str]] = {}
    bar = Progress(len(inputs), 0, progress, unit="record")
    queue = iter(enumerate(inputs))
    done = 0

    async def worker() -> None:
        nonlocal done
        for index, source in queue:  # shared: each record is taken once, in order
            record = source.record
            if record.dataset != info.dataset:
                different = [
                    f"dataset: the record is of {record.dataset!r}, the server serves {info.dataset!r} "
                    "(start a server of that dataset)"
                ]
            else:
                try:
                    different = await _replay(client, record)
                except ServerUnavailable as error:
                    gone = await server_gone(
                        client, local, done, what="replays", resume="re-run the same command"
                    )
                    if gone is not None:
                        raise ServerGone(gone) from error
                    different = [f"not replayed: {type(error).__name__}: {error.message}"]
            if different:
                found[index] = different
            done += 1
            bar.advance(f"{len(found)} do not match" if found else "all match")

    try:
        await run_workers(min(episodes_in_flight, len(inputs)), worker)
    finally:
        bar.close()
    mismatches = [Mismatch(inputs[index], tuple(found[index])) for index in sorted(found)]
    return VerifyOutcome(len(inputs), mismatches)


def run_verify(
    paths: Sequence[Path],
    *,
    server: str | None = None,
    token: str | None = None,
    server_args: Sequence[str] = (),
    episodes_in_flight: int = 8,
    progress: bool = True,
) -> VerifyOutcome:
    """`esrp verify`: reads `paths` (`VerifyError` when they are not results), then `verify`s them
    on `server` (`host:port`), or on a `LocalServer` started for it (with `server_args`).
    """
    if episodes_in_flight < 1:
        raise VerifyError("--episodes-in-flight must be at least 1")
    inputs = read_inputs(paths)

    async def main(address: str, local: LocalServer | None = None) -> VerifyOutcome:
        async with AsyncClient(address, token=token, timeout=120) as client:
            if server is not None:
                try:
                    await client.server_info()  # fails at once when nothing answers there
                except ServerUnavailable as error:
                    raise VerifyError(unreachable(server, error)) from None
            await client.wait_healthy(30)
            return await verify(
                client, inputs, episodes_in_flight=episodes_in_flight, local=local, progress=progress
            )

    if server is not None:
        return asyncio.run(main(server))
    with LocalServer(*server_args) as local:
        return asyncio.run(main(local.address, local))
