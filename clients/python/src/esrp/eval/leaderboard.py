"""`esrp report --leaderboard DIR`: the challenge's ranking from a server's records.

A server started with `--records DIR` writes one `esrp.results/v1` file per token,
`DIR/<token-name>.jsonl`, whose records carry the server's own fields (docs/evaluation.md):
`token`, `started_at`, `dataset_hash`, `counted`, `reward_weights`, `observations` and, last,
`signature`; and, serving a challenge, the list of its scenes, `DIR/challenge-scenes.json`.

The records are checked first: with the records key (`--key FILE`, else `DIR/records.key`), a
record whose signature does not check is rejected, and so is one that `verify.refusals` refuses
(in another token's file, a second counted record of a scene, a split, difficulty, horizon or
dataset hash other than its scene's); the rejected are listed with their reasons, not ranked.
Without a key the leaderboard is made only when asked to (`unsigned`). It then keeps the records
of the `challenge` split marked `counted` (each token's one counted attempt per scene), at most one
per participant and scene (the first by `finished_at`), groups them by participant (the record's
`token`, else the file's stem) and scores each over EVERY scene of the challenge's list: a scene
it did not play counts as a failure (OSR 0, RDR 1). Participants are ranked by that SR, ties
broken by OSR (higher first), then RDR (lower first), then name.

It writes one self-contained HTML page (no script, no external resource) and prints the ranking as
text. The page's tables are marked for machines like `esrp report`'s: `table#leaderboard` with a
row per participant (`data-participant`, `data-rank`) and `table#references` with the paper's rows
(`data-paper`; references of another split, not ranked), each cell with a `data-key` (`played`,
`sr`, `sr-ci`, `osr`, `rdr`, `easy-sr`, `medium-sr`, `hard-sr`, `stage-1`..`stage-4`,
`observations`, `agents`, `first`, `last`, `versions`), and `table#rejected` with a row per
rejected record (`data-where`: `FILE:LINE`).
"""

from __future__ import annotations

import html
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path

from .. import __version__
from .manifest import MANIFEST, ChallengeScenes, load_manifest
from .report import _STYLE, _paper_shown
from .results import (
    DIFFICULTIES,
    PAPER,
    PAPER_DATASET,
    EpisodeRecord,
    ResultsError,
    Tally,
    fixed,
    wilson,
)
from .results import load_records as read_results_file
from .signing import KEY_FILE, load_key
from .verify import Numbered, refusals

__all__ = [
    "CHALLENGE_SPLIT",
    "Leaderboard",
    "LeaderboardError",
    "Participant",
    "Rejected",
    "Sourced",
    "check_records",
    "load_records",
    "read_key",
    "rank",
    "ranking_text",
    "select_counted",
    "write_leaderboard",
]

CHALLENGE_SPLIT = "challenge"
"""The split whose counted records the leaderboard ranks."""

_RFC3339 = re.compile(r"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d)(\.\d+)?(Z|[+-]\d\d:\d\d)", re.IGNORECASE)


class LeaderboardError(Exception):
    """A leaderboard cannot be made from this folder (exit status 2)."""


@dataclass(frozen=True)
class Sourced(Numbered):
    """A record, the file and line it was read from and the line's bytes (as `esrp verify` reads
    them), and who played it.
    """

    @property
    def participant(self) -> str:
        """Who played it: the record's `token` (a server record's), else the file's stem."""
        token = self.record.extra.get("token")
        return token if isinstance(token, str) and token else self.path.stem

    @property
    def counted(self) -> bool:
        """Whether the server counted it: the token's one attempt at a challenge scene."""
        return self.record.split == CHALLENGE_SPLIT and self.record.extra.get("counted") is True


def finished_key(source: Sourced) -> tuple[datetime, float]:
    """When `source`'s episode ended, for ordering (its `finished_at`, RFC 3339, any precision).
    Raises `LeaderboardError` naming the file and line when it is not RFC 3339.
    """
    text = source.record.finished_at
    match = _RFC3339.fullmatch(text)
    if match is None:
        raise LeaderboardError(
            f"{source.path}:{source.line}: finished_at {text!r} is not an RFC 3339 time "
            "(e.g. 2026-11-23T19:40:00Z)"
        )
    seconds, fraction, offset = match.groups()
    moment = datetime.strptime(seconds, "%Y-%m-%dT%H:%M:%S").replace(tzinfo=timezone.utc)
    if offset.upper() != "Z":
        sign = 1 if offset[0] == "+" else -1
        moment -= sign * timedelta(hours=int(offset[1:3]), minutes=int(offset[4:6]))
    return moment, float(fraction) if fraction else 0.0


@dataclass
class Participant:
    """One participant's counted records, scored over every scene of the challenge (`scenes`).

    Attributes:
        name: The participant (its token's name).
        scenes: The challenge's scene list: every scene counts, played or not.
        records: The counted records, one per scene played.
    """

    name: str
    scenes: ChallengeScenes
    records: list[Sourced] = field(default_factory=list)

    def _difficulty(self, source: Sourced) -> str:
        scene = self.scenes.by_id.get(source.record.scene_id)
        return scene.difficulty if scene is not None else source.record.difficulty

    def played(self, difficulty: str | None = None) -> Tally:
        """The tally of the scenes played (of one difficulty): the counted records alone."""
        return Tally.of(
            s.record for s in self.records if difficulty is None or self._difficulty(s) == difficulty
        )

    def over_all_scenes(self, difficulty: str | None = None) -> Tally:
        """The tally over every scene of the challenge (of one difficulty): each scene not played
        is one more episode, a failure with OSR 0 and RDR 1 (no stage).
        """
        tally = self.played(difficulty)
        unplayed = max(0, self.scenes.count(difficulty) - tally.episodes)
        tally.episodes += unplayed
        tally.rdr_sum += unplayed
        return tally

    @property
    def overall(self) -> Tally:
        """The tally over every scene of the challenge (`over_all_scenes`)."""
        return self.over_all_scenes()

    def by_difficulty(self, difficulty: str) -> Tally:
        """The tally over every scene of one difficulty (`over_all_scenes`)."""
        return self.over_all_scenes(difficulty)

    @property
    def observations(self) -> list[str]:
        """What its counted episodes served (`"paper"`, `"full"`), in the order first seen; empty
        for records that do not say.
        """
        return list(dict.fromkeys(s.record.observations for s in self.records if s.record.observations))

    @property
    def agents(self) -> list[str]:
        """The agent labels of the records, in the order first used."""
        return list(dict.fromkeys(s.record.agent for s in self.records))

    @property
    def first(self) -> str:
        """The `finished_at` of the earliest counted episode."""
        return min(self.records, key=finished_key).record.finished_at

    @property
    def last(self) -> str:
        """The `finished_at` of the latest counted episode."""
        return max(self.records, key=finished_key).record.finished_at

    @property
    def versions(self) -> list[str]:
        """The server versions and datasets it played on: `0.2.0 on esrp-bench-v2 (hash ...)`."""
        return list(dict.fromkeys(_version(s.record) for s in self.records))

    def ranking_key(self) -> tuple[float, float, float, str]:
        """SR over all scenes (higher first), OSR (higher first), RDR (lower first), then the name."""
        t = self.overall
        return (-t.sr, -t.osr, t.rdr, self.name)


def _version(record: EpisodeRecord) -> str:
    digest = record.extra.get("dataset_hash")
    dataset = f"{record.dataset} (hash {digest})" if isinstance(digest, str) and digest else record.dataset
    return f"esrp-server {record.server_version} on {dataset}"


def load_records(folder: str | os.PathLike[str]) -> list[Sourced]:
    """Every record of every `*.jsonl` file of `folder` (by name), with its file and line. Raises
    `LeaderboardError` when the folder is missing, holds no such file, or holds one that is not
    `esrp.results/v1`.
    """
    directory = Path(folder)
    if not directory.is_dir():
        raise LeaderboardError(f"no folder {directory} (the server's --records folder)")
    files = sorted(directory.glob("*.jsonl"))
    if not files:
        raise LeaderboardError(f"{directory} holds no *.jsonl records")
    sourced: list[Sourced] = []
    for path in files:
        try:
            read = read_results_file(path, "esrp report")
        except ResultsError as error:
            raise LeaderboardError(str(error)) from None
        sourced += [
            Sourced(path, n, r, raw)
            for n, r, raw in zip(read.line_numbers, read.records, read.lines, strict=True)
        ]
    return sourced


def read_scenes(folder: str | os.PathLike[str]) -> ChallengeScenes:
    """The challenge's scene list of a records folder, `DIR/challenge-scenes.json`. Raises
    `LeaderboardError` when it is missing or cannot be read.
    """
    path = Path(folder) / MANIFEST
    if not path.is_file():
        raise LeaderboardError(
            f"no {path}: the challenge's scene list, which the leaderboard scores every participant "
            "over (the server writes it at its start when started with --challenge-seed and --records)"
        )
    try:
        return load_manifest(path)
    except ResultsError as error:
        raise LeaderboardError(str(error)) from None


def read_key(
    folder: str | os.PathLike[str], key: str | os.PathLike[str] | None, *, unsigned: bool = False
) -> tuple[bytes | None, Path | None]:
    """The records key and its file: `key`, else `DIR/records.key`; `(None, None)` when neither
    exists and `unsigned` allows it. Raises `LeaderboardError` when the key cannot be read, or
    none exists and `unsigned` is false.
    """
    path = Path(key) if key is not None else Path(folder) / KEY_FILE
    if key is None and not path.is_file():
        if unsigned:
            return None, None
        raise LeaderboardError(
            f"no records key: {path} does not exist and no --key FILE was given, so the records' "
            "signatures cannot be checked (give the server's --records-key file with --key, or "
            "--unsigned to rank the records unchecked)"
        )
    try:
        return load_key(path), path
    except ResultsError as error:
        raise LeaderboardError(str(error)) from None


@dataclass(frozen=True)
class Rejected:
    """A record the leaderboard does not read, and why (`refused: ...`, as `esrp verify` says)."""

    source: Sourced
    reasons: tuple[str, ...]


def check_records(
    records: Sequence[Sourced], key: bytes | None, scenes: ChallengeScenes
) -> tuple[list[Sourced], list[Rejected]]:
    """`records` split into those that pass `verify.refusals` (with `key`: their signatures
    check) and those rejected, with the reasons, in input order.
    """
    found = refusals(records, key, {s.path.parent: scenes for s in records})
    kept = [s for k, s in enumerate(records) if k not in found]
    rejected = [Rejected(records[k], tuple(found[k])) for k in sorted(found)]
    return kept, rejected


def select_counted(records: Iterable[Sourced]) -> list[Sourced]:
    """The counted challenge records, at most one per participant and scene: the first to finish."""
    first: dict[tuple[str, str], Sourced] = {}
    for source in sorted((s for s in records if s.counted), key=finished_key):
        first.setdefault((source.participant, source.record.scene_id), source)
    return list(first.values())


def rank(records: Iterable[Sourced], scenes: ChallengeScenes) -> list[Participant]:
    """The participants of `select_counted(records)` (those of scenes in `scenes`), scored over
    every scene of `scenes`, best first (`Participant.ranking_key`).
    """
    participants: dict[str, Participant] = {}
    for source in select_counted(records):
        if source.record.scene_id not in scenes.by_id:
            continue
        name = source.participant
        participants.setdefault(name, Participant(name, scenes)).records.append(source)
    return sorted(participants.values(), key=Participant.ranking_key)


def _pct(value: float) -> str:
    return fixed(100 * value, 2)


def _interval(t: Tally) -> str:
    low, high = wilson(t.successes, t.episodes)
    return f"{_pct(low)}–{_pct(high)}"


def ranking_text(participants: Sequence[Participant], scenes: int) -> str:
    """The ranking as lines for a terminal: rank, participant, SR over all scenes with its 95 %
    interval, OSR, RDR (an unplayed scene a failure) and the scenes played (of all `scenes`).
    """
    width = max(len("participant"), *(len(p.name) for p in participants))
    lines = [
        f"{'rank':>4}  {'participant':<{width}}  {'SR %':>6}  {'95 % CI':<13}  {'OSR %':>6}  RDR     "
        "scenes played"
    ]
    for k, p in enumerate(participants, start=1):
        t = p.overall
        lines.append(
            f"{k:>4}  {p.name:<{width}}  {_pct(t.sr):>6}  {_interval(t):<13}  {_pct(t.osr):>6}  "
            f"{fixed(t.rdr, 4)}  {p.played().episodes} of {scenes}"
        )
    return "".join(line + "\n" for line in lines)


def _cells(p: Participant) -> list[tuple[str, str]]:
    t = p.overall
    cells = [
        ("played", f"{p.played().episodes} of {p.scenes.count()}"),
        ("sr", _pct(t.sr)),
        ("sr-ci", _interval(t)),
        ("osr", _pct(t.osr)),
        ("rdr", fixed(t.rdr, 4)),
    ]
    for d in DIFFICULTIES:
        total = p.scenes.count(d)
        played = p.played(d).episodes
        cells.append((f"{d}-sr", f"{_pct(p.by_difficulty(d).sr)} ({played} of {total})" if total else "–"))
    cells += [(f"stage-{s}", _pct(t.stage_share(s))) for s in range(1, 5)]
    cells += [
        ("observations", ", ".join(p.observations) or "–"),
        ("agents", ", ".join(p.agents)),
        ("first", p.first),
        ("last", p.last),
        ("versions", "; ".join(p.versions)),
    ]
    return cells


_HEADER = [
    "rank",
    "participant",
    "scenes played",
    "SR % (all scenes)",
    "SR 95 % CI",
    "OSR %",
    "RDR",
    "Easy SR % (played of scenes)",
    "Medium SR % (played of scenes)",
    "Hard SR % (played of scenes)",
    "stage 1 %",
    "stage 2 %",
    "stage 3 %",
    "stage 4 %",
    "observations",
    "agents",
    "first",
    "last",
    "server and dataset",
]

_LEADERBOARD_STYLE = """
body { max-width: 1500px; }
td[data-key=sr-ci], td[data-key=played] { white-space: nowrap; }
td[data-key=agents], td[data-key=versions], td[data-key=first], td[data-key=last],
#rejected td { text-align: left; font-size: 0.85em; }
"""


@dataclass
class Leaderboard:
    """A leaderboard made: the ranking, the scenes it is over, what was rejected, and the page.

    Attributes:
        participants: The ranking, best first.
        scenes: The challenge's scene list.
        rejected: The records not read, with their reasons, in file order.
        records: How many records the folder holds.
        key: The key file the signatures were checked with; None: they were not (`unsigned`).
        page: The page written.
    """

    participants: list[Participant]
    scenes: ChallengeScenes
    rejected: list[Rejected]
    records: int
    key: Path | None
    page: Path


def _observations_note(board: Leaderboard) -> str:
    allowed = ", ".join(f"{split}: {what}" for split, what in board.scenes.observations.items())
    text = f"Observations allowed (the challenge&#8217;s scene list): {html.escape(allowed or '–')}."
    challenge = board.scenes.observations.get(CHALLENGE_SPLIT)
    other: dict[str, dict[str, int]] = {}
    for p in board.participants:
        for s in p.records:
            served = s.record.observations
            if served is not None and served != challenge:
                counts = other.setdefault(p.name, {})
                counts[served] = counts.get(served, 0) + 1
    if other:
        parts = [
            f"{name}: " + ", ".join(f"{what} ({n} records)" for what, n in counts.items())
            for name, counts in other.items()
        ]
        text += " Counted records that served otherwise: " + html.escape("; ".join(parts)) + "."
    return text


def _signatures_note(board: Leaderboard) -> str:
    e = html.escape
    rejected = f"{len(board.rejected)} of {board.records} records rejected (below)"
    if board.key is None:
        return (
            f"Signatures NOT checked (--unsigned: no records key): the records were read as they are; "
            f"{rejected}."
        )
    return f"Signatures checked with the records key {e(str(board.key))}: {rejected}."


def _page(title: str, board: Leaderboard, folder: Path) -> str:
    e = html.escape
    participants = board.participants
    scenes = board.scenes.count()
    versions = list(dict.fromkeys(v for p in participants for v in p.versions))
    rows = []
    for k, p in enumerate(participants, start=1):
        cells = "".join(f'<td data-key="{e(key)}">{e(text)}</td>' for key, text in _cells(p))
        rows.append(
            f'<tr data-participant="{e(p.name)}" data-rank="{k}"><td data-key="rank">{k}</td>'
            f'<th scope="row">{e(p.name)}</th>{cells}</tr>'
        )
    references = []
    for paper in PAPER:
        sr, osr, rdr = paper.overall
        reference_cells = [("sr", f"{sr:.2f}"), ("osr", f"{osr:.2f}"), ("rdr", f"{rdr:.4f}")]
        reference_cells += [
            (f"{d}-sr", f"{v[0]:.2f}") for d, v in zip(DIFFICULTIES, paper.by_difficulty, strict=True)
        ]
        stages = paper.stages or (None, None, None, None)
        reference_cells += [
            (f"stage-{s}", "–" if v is None else f"{v:.2f}") for s, v in enumerate(stages, start=1)
        ]
        cells = "".join(f'<td data-key="{e(key)}">{e(text)}</td>' for key, text in reference_cells)
        references.append(
            f'<tr data-paper="{e(paper.name)}" class="paper">'
            f'<th scope="row">{e(_paper_shown(paper.name))}</th>{cells}</tr>'
        )
    reference_header = ["reference", "SR %", "OSR %", "RDR", "Easy SR %", "Medium SR %", "Hard SR %"]
    reference_header += [f"stage {s} %" for s in range(1, 5)]
    rejected = [
        f'<tr data-where="{e(r.source.where)}"><td>{e(r.source.where)}</td>'
        f"<td>{e(r.source.participant)}</td><td>{e(r.source.record.scene_id)}</td>"
        f"<td>{e('; '.join(r.reasons))}</td></tr>"
        for r in board.rejected
    ]
    by_difficulty = ", ".join(f"{board.scenes.count(d)} {d}" for d in DIFFICULTIES)
    page = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{e(title)}</title><style>{_STYLE}{_LEADERBOARD_STYLE}</style></head><body>",
        f"<h1>{e(title)}</h1>",
        f'<p class="note" id="basis">Each participant is scored over all {scenes} scenes of the '
        f"{CHALLENGE_SPLIT} split ({e(by_difficulty)}; {e(str(board.scenes.path))}): a scene it did "
        "not play counts as a failure (OSR 0, RDR 1). Its counted attempts, one per scene, are "
        f"read from the server&#8217;s records in {e(str(folder))}. Ranked by the SR over all scenes, "
        "ties broken by OSR (higher first), then RDR (lower first). SR 95 % CI: the Wilson score "
        "interval over all scenes. Stage shares are of all scenes (an unplayed scene has none). SR "
        "and OSR in %, RDR as a ratio (lower is better).</p>",
        f'<p class="note" id="observations">{_observations_note(board)}</p>',
        f'<p class="note" id="signatures">{_signatures_note(board)}</p>',
        f'<p class="note" id="versions">Served by: {e("; ".join(versions))}.</p>',
        '<table id="leaderboard">',
        "<thead><tr>" + "".join(f"<th>{e(h)}</th>" for h in _HEADER) + "</tr></thead>",
        "<tbody>",
        *rows,
        "</tbody></table>",
        "<h2>Rejected records (not ranked)</h2>",
        '<table id="rejected">',
        "<thead><tr><th>file:line</th><th>participant</th><th>scene</th><th>reason</th></tr></thead>",
        "<tbody>",
        *rejected,
        "</tbody></table>",
        "<h2>References (not ranked)</h2>",
        f'<p class="note">The paper&#8217;s rows (its Tables I–III, SPEC §8), measured on the test split '
        f"of {PAPER_DATASET}, not on the challenge&#8217;s scenes: for orientation only. ESRP-PLAN reads "
        "the simulator&#8217;s privileged state.</p>",
        '<table id="references">',
        "<thead><tr>" + "".join(f"<th>{e(h)}</th>" for h in reference_header) + "</tr></thead>",
        "<tbody>",
        *references,
        "</tbody></table>",
        f'<p class="note">Written by esrp report {e(__version__)}.</p></body></html>',
    ]
    return "\n".join(page) + "\n"


def write_leaderboard(
    folder: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    title: str = "ESRP challenge leaderboard",
    key: str | os.PathLike[str] | None = None,
    unsigned: bool = False,
) -> Leaderboard:
    """Ranks the counted challenge records of `folder` over every scene of its scene list
    (`read_scenes`, `rank`), after rejecting those whose signature does not check under the
    records key (`read_key`: `key`, else `DIR/records.key`; none at all only with `unsigned`) or
    that `verify.refusals` refuses, and writes the page to `out`. Raises `LeaderboardError` when
    the scene list or the key is missing, or the folder holds no counted challenge record that
    passes.
    """
    directory = Path(folder)
    records = load_records(directory)
    scenes = read_scenes(directory)
    secret, key_path = read_key(directory, key, unsigned=unsigned)
    kept, rejected = check_records(records, secret, scenes)
    participants = rank(kept, scenes)
    if not participants:
        refused = f", {len(rejected)} rejected" if rejected else ""
        raise LeaderboardError(
            f"{directory} holds no counted challenge records (split {CHALLENGE_SPLIT!r}, counted true) "
            f"among its {len(records)} records{refused}"
        )
    path = Path(out)
    if path.parent != Path():
        path.parent.mkdir(parents=True, exist_ok=True)
    board = Leaderboard(participants, scenes, rejected, len(records), key_path, path)
    path.write_text(_page(title, board, directory), encoding="utf-8")
    return board
