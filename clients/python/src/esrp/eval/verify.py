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
bar. Self-reported `esrp eval` / `esrp-eval` files and the server's own records verify alike. A
record that carries `reward_weights` (a server record's) replays with those weights.

With the records key (`key`, `esrp verify --key FILE`), server records are checked before they are
replayed (`refusals`): a record is refused, with its reason, when it is unsigned, altered (its
signature does not match its line), a duplicate (a signature seen before, or a second counted
record of one token on one scene), in the file of another token than its own, or when its split,
difficulty, horizon or dataset hash is not its scene's: from the challenge's scene list beside the
records (`challenge-scenes.json`) and, as it is replayed, from the server's summary of the scene
(the split always, the horizon on the hidden splits, where only an admin may set another). A
refused record is not replayed.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from .._async_client import AsyncClient
from .._common import unreachable
from .._errors import EsrpError, SceneNotFound, ServerUnavailable
from .._local import LocalServer
from .._signals import run_async
from .._values import EpisodeMetrics, Sensors, ServerInfo
from ._pool import run_workers
from .evaluation import Progress, ServerGone, server_gone
from .manifest import MANIFEST, ChallengeScenes, load_manifest
from .results import EpisodeRecord, ReadRecords, ResultsError, load_records, no_records
from .signing import BadSignature, UnsignedRecord, load_key, require, signature_of

__all__ = [
    "CHALLENGE_PREFIXES",
    "LABEL",
    "Mismatch",
    "Numbered",
    "VerifyError",
    "VerifyOutcome",
    "owner",
    "compare",
    "manifests_beside",
    "read_inputs",
    "refusals",
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
    """A record and where it was read: its file and line (1-based), and the line's bytes as read
    (without the newline; what a server record's signature covers).
    """

    path: Path
    line: int
    record: EpisodeRecord
    raw: bytes = b""

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
        records: How many records were checked (replayed, found unreplayable, or refused).
        mismatches: The records that do not match or were refused, in input order.
        signed: Whether the records' signatures were checked (a key was given).
        refused: How many of the mismatches were refused before any replay (their differences
            start with `refused: `).
    """

    records: int
    mismatches: list[Mismatch] = field(default_factory=list)
    signed: bool = False
    refused: int = 0

    def summary(self) -> str:
        """The closing line: `N records verified, all match` or `K of N records do not match`
        (with `, R refused` when records were refused).
        """
        if not self.mismatches:
            return f"{self.records} records verified, all match"
        refused = f" ({self.refused} refused)" if self.refused else ""
        return f"{len(self.mismatches)} of {self.records} records do not match{refused}"


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
        numbered += [
            Numbered(path, n, r, raw)
            for n, r, raw in zip(read.line_numbers, read.records, read.lines, strict=True)
        ]
    if not numbered:
        raise VerifyError(no_records(paths, reads))
    return numbered


REFUSED = "refused: "
"""How the first difference of a refused record begins."""

HIDDEN_SPLITS = ("challenge", "minival")
"""The splits whose episodes play their scene's own horizon (only an admin may set another)."""


def owner(path: Path, record: EpisodeRecord) -> str:
    """Whose record it is: its `token` (a server record's), else its file's stem."""
    token = record.extra.get("token")
    return token if isinstance(token, str) and token else path.stem


def manifests_beside(paths: Sequence[Path]) -> dict[Path, ChallengeScenes]:
    """The challenge's scene lists (`challenge-scenes.json`) in the folders of `paths`, by folder.
    Raises `ManifestError` (a `ResultsError`) for one that is there but cannot be read.
    """
    found: dict[Path, ChallengeScenes] = {}
    for folder in dict.fromkeys(p.parent for p in paths):
        if (folder / MANIFEST).is_file():
            found[folder] = load_manifest(folder / MANIFEST)
    return found


def _scene_facts(record: EpisodeRecord, manifest: ChallengeScenes | None) -> list[str]:
    """What is not its scene's in `record`, by the scene list `manifest` (nothing without one)."""
    if manifest is None:
        return []
    scene = manifest.by_id.get(record.scene_id)
    if scene is None:
        if record.split == "challenge" or record.scene_id.startswith("challenge/"):
            return [f"scene: {record.scene_id!r} is not one of the challenge's scenes ({manifest.path})"]
        return []
    wrong = []
    if record.split != "challenge":
        wrong.append(f"split: recorded {record.split!r}, the scene's is 'challenge'")
    if record.difficulty != scene.difficulty:
        wrong.append(f"difficulty: recorded {record.difficulty!r}, the scene's is {scene.difficulty!r}")
    if scene.horizon and record.horizon != scene.horizon:
        wrong.append(f"horizon: recorded {record.horizon}, the scene's is {scene.horizon}")
    digest = record.extra.get("dataset_hash")
    if digest is not None and digest != manifest.dataset_hash:
        wrong.append(f"dataset_hash: recorded {digest!r}, the challenge's is {manifest.dataset_hash!r}")
    return wrong


def refusals(
    inputs: Sequence[Numbered],
    key: bytes | None,
    manifests: Mapping[Path, ChallengeScenes] | None = None,
) -> dict[int, list[str]]:
    """The records of `inputs` to refuse, by index, each with its reasons (each starting
    `refused: `). With `key`, a record is refused when it is unsigned or its signature does not
    match its line (`esrp.eval.signing`), and a record whose signature matches when it is a
    duplicate (a signature seen on an earlier line). With or without it, a record is refused when
    its token is not its file's stem, when it is a second counted challenge record of its owner
    on its scene (the first in input order is kept: a token's file is in the order its episodes
    ended), or when its split, difficulty, horizon or dataset hash is not its scene's by the scene
    list of its folder (`manifests`, by folder).
    """
    found: dict[int, list[str]] = {}
    signatures: dict[str, Numbered] = {}
    counted: dict[tuple[str, str], Numbered] = {}
    manifests = manifests or {}
    for index, source in enumerate(inputs):
        record = source.record
        reasons: list[str] = []
        if key is not None:
            try:
                require(source.raw, key)
            except UnsignedRecord:
                if record.signature is not None:
                    found[index] = [
                        REFUSED + "unsigned: its signature is not the last member of its line as the "
                        "server writes it (the record was rewritten)"
                    ]
                else:
                    found[index] = [REFUSED + "unsigned: no signature member"]
                continue
            except BadSignature as error:
                found[index] = [REFUSED + str(error)]
                continue
            first = signatures.setdefault(signature_of(source.raw) or "", source)
            if first is not source:
                found[index] = [REFUSED + f"duplicate: the same signature as {first.where}"]
                continue
        token = record.extra.get("token")
        if isinstance(token, str) and token and source.path.stem != token:
            reasons.append(f"moved: a record of token {token!r} in {source.path.name}, not in {token}.jsonl")
        reasons += _scene_facts(record, manifests.get(source.path.parent))
        if not reasons and record.split == "challenge" and record.extra.get("counted") is True:
            first = counted.setdefault((owner(source.path, record), record.scene_id), source)
            if first is not source:
                reasons.append(
                    f"duplicate: a second counted record of {owner(source.path, record)!r} on "
                    f"{record.scene_id} (the first: {first.where})"
                )
        if reasons:
            found[index] = [REFUSED + reason for reason in reasons]
    return found


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


async def _replay(client: AsyncClient, record: EpisodeRecord, scene_checks: bool = False) -> list[str]:
    """Replays one record; returns what differs (nothing: it matches). Raises `ServerUnavailable`
    when the server does not answer; other errors of the server are differences. With
    `scene_checks`, a record whose split (or, on a hidden split, horizon) is not its scene's, by
    the server's summary of the scene, is refused.
    """
    try:
        episode = await client.create_episode(
            record.scene_id,
            horizon=record.horizon,
            reward=record.played_weights(),
            sensors=_SENSORS,
            agent=LABEL,
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
    refused: list[str] = []
    if scene_checks:
        split = episode.scene.split.value if episode.scene.split is not None else None
        if split is not None and split != record.split:
            refused.append(f"{REFUSED}split: recorded {record.split!r}, the scene's is {split!r}")
        horizon = episode.scene.horizon
        if split in HIDDEN_SPLITS and horizon > 0 and horizon != record.horizon:
            refused.append(f"{REFUSED}horizon: recorded {record.horizon}, the scene's is {horizon}")
    try:
        if refused:
            return refused
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
    key: bytes | None = None,
    manifests: Mapping[Path, ChallengeScenes] | None = None,
) -> VerifyOutcome:
    """Replays `inputs` on `client`'s server, `episodes_in_flight` at a time; returns what does not
    match, in input order. With `key`, the records are checked first (`refusals`, with the scene
    lists `manifests`) and as they are replayed (their scene's split and horizon, by the server),
    and those refused are not replayed. A server that dies (`local` exits) or stays unreachable
    stops the run with `ServerGone`.
    """
    info: ServerInfo = await client.server_info()
    print(f"esrp-server {info.version} at {client.address}: dataset {info.dataset}", file=sys.stderr)
    found: dict[int, list[str]] = refusals(inputs, key, manifests) if key is not None else {}
    refused = len(found)
    bar = Progress(len(inputs), len(found), progress, unit="record")
    queue = iter([(k, source) for k, source in enumerate(inputs) if k not in found])
    done = 0

    async def worker() -> None:
        nonlocal done, refused
        for index, source in queue:  # shared: each record is taken once, in order
            record = source.record
            if record.dataset != info.dataset:
                different = [
                    f"dataset: the record is of {record.dataset!r}, the server serves {info.dataset!r} "
                    "(start a server of that dataset)"
                ]
            else:
                try:
                    different = await _replay(client, record, scene_checks=key is not None)
                except ServerUnavailable as error:
                    gone = await server_gone(
                        client, local, done, what="replays", resume="re-run the same command"
                    )
                    if gone is not None:
                        raise ServerGone(gone) from error
                    different = [f"not replayed: {type(error).__name__}: {error.message}"]
            if different:
                found[index] = different
                refused += different[0].startswith(REFUSED)
            done += 1
            bar.advance(f"{len(found)} do not match" if found else "all match")

    try:
        await run_workers(max(1, min(episodes_in_flight, len(inputs) - len(found))), worker)
    finally:
        bar.close()
    mismatches = [Mismatch(inputs[index], tuple(found[index])) for index in sorted(found)]
    return VerifyOutcome(len(inputs), mismatches, signed=key is not None, refused=refused)


def run_verify(
    paths: Sequence[Path],
    *,
    server: str | None = None,
    token: str | None = None,
    server_args: Sequence[str] = (),
    episodes_in_flight: int = 8,
    progress: bool = True,
    key: Path | None = None,
) -> VerifyOutcome:
    """`esrp verify`: reads `paths` (`VerifyError` when they are not results), then `verify`s them
    on `server` (`host:port`), or on a `LocalServer` started for it (with `server_args`). With
    `key`, the file of the records key, the records' signatures are checked (`refusals`), with
    the scene lists found beside the records (`manifests_beside`); a key or scene list that
    cannot be read is a `VerifyError`.
    """
    if episodes_in_flight < 1:
        raise VerifyError("--episodes-in-flight must be at least 1")
    try:
        secret = load_key(key) if key is not None else None
        manifests = manifests_beside(paths) if key is not None else {}
    except ResultsError as error:
        raise VerifyError(str(error)) from None
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
                client,
                inputs,
                episodes_in_flight=episodes_in_flight,
                local=local,
                progress=progress,
                key=secret,
                manifests=manifests,
            )

    if server is not None:
        return run_async(main(server))
    with LocalServer(*server_args, unix_socket="auto") as local:
        return run_async(main(local.address, local))
