"""`esrp report --leaderboard DIR`: the challenge's ranking from a server's records.

A server started with `--records DIR` writes one `esrp.results/v1` file per token,
`DIR/<token-name>.jsonl`, whose records carry the server's own fields (docs/evaluation.md):
`token`, `started_at`, `dataset_hash` and `counted`. The leaderboard keeps the records of the
`challenge` split marked `counted` (each token's one counted attempt per scene), at most one per
participant and scene (the first by `finished_at`, should a file hold two), groups them by
participant (the record's `token`, else the file's stem) and ranks the participants by SR, ties
broken by OSR (higher first), then RDR (lower first), then name.

It writes one self-contained HTML page (no script, no external resource) and prints the ranking as
text. The page's tables are marked for machines like `esrp report`'s: `table#leaderboard` with a
row per participant (`data-participant`, `data-rank`) and `table#references` with the paper's rows
(`data-paper`; references of another split, not ranked), each cell with a `data-key` (`episodes`,
`sr`, `sr-ci`, `osr`, `rdr`, `easy-sr`, `medium-sr`, `hard-sr`, `stage-1`..`stage-4`, `agents`,
`first`, `last`, `versions`).
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

__all__ = [
    "CHALLENGE_SPLIT",
    "LeaderboardError",
    "Participant",
    "Sourced",
    "load_records",
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
class Sourced:
    """A record and the file it was read from."""

    path: Path
    line: int
    record: EpisodeRecord

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
    """One participant's counted records and what the leaderboard shows of them."""

    name: str
    records: list[Sourced] = field(default_factory=list)

    @property
    def overall(self) -> Tally:
        """The tally of the counted records."""
        return Tally.of(s.record for s in self.records)

    def by_difficulty(self, difficulty: str) -> Tally:
        """The tally of the counted records of one difficulty."""
        return Tally.of(s.record for s in self.records if s.record.difficulty == difficulty)

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
        """SR (higher first), OSR (higher first), RDR (lower first), then the name."""
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
        sourced += [Sourced(path, n, r) for n, r in zip(read.line_numbers, read.records, strict=True)]
    return sourced


def select_counted(records: Iterable[Sourced]) -> list[Sourced]:
    """The counted challenge records, at most one per participant and scene: the first to finish."""
    first: dict[tuple[str, str], Sourced] = {}
    for source in sorted((s for s in records if s.counted), key=finished_key):
        first.setdefault((source.participant, source.record.scene_id), source)
    return list(first.values())


def rank(records: Iterable[Sourced]) -> list[Participant]:
    """The participants of `select_counted(records)`, best first (`Participant.ranking_key`)."""
    participants: dict[str, Participant] = {}
    for source in select_counted(records):
        participants.setdefault(source.participant, Participant(source.participant)).records.append(source)
    return sorted(participants.values(), key=Participant.ranking_key)


def _pct(value: float) -> str:
    return fixed(100 * value, 2)


def _interval(t: Tally) -> str:
    low, high = wilson(t.successes, t.episodes)
    return f"{_pct(low)}–{_pct(high)}"


def ranking_text(participants: Sequence[Participant], scenes: int) -> str:
    """The ranking as lines for a terminal: rank, participant, SR with its 95 % interval, OSR, RDR
    and the episodes counted (of the `scenes` anyone played).
    """
    width = max(len("participant"), *(len(p.name) for p in participants))
    lines = [
        f"{'rank':>4}  {'participant':<{width}}  {'SR %':>6}  {'95 % CI':<13}  {'OSR %':>6}  RDR     episodes"
    ]
    for k, p in enumerate(participants, start=1):
        t = p.overall
        lines.append(
            f"{k:>4}  {p.name:<{width}}  {_pct(t.sr):>6}  {_interval(t):<13}  {_pct(t.osr):>6}  "
            f"{fixed(t.rdr, 4)}  {t.episodes} of {scenes}"
        )
    return "".join(line + "\n" for line in lines)


def _cells(p: Participant, scenes: int) -> list[tuple[str, str]]:
    t = p.overall
    cells = [
        ("episodes", f"{t.episodes} of {scenes}"),
        ("sr", _pct(t.sr)),
        ("sr-ci", _interval(t)),
        ("osr", _pct(t.osr)),
        ("rdr", fixed(t.rdr, 4)),
    ]
    for d in DIFFICULTIES:
        tally = p.by_difficulty(d)
        cells.append((f"{d}-sr", f"{_pct(tally.sr)} ({tally.episodes})" if tally.episodes else "–"))
    cells += [(f"stage-{s}", _pct(t.stage_share(s))) for s in range(1, 5)]
    cells += [
        ("agents", ", ".join(p.agents)),
        ("first", p.first),
        ("last", p.last),
        ("versions", "; ".join(p.versions)),
    ]
    return cells


_HEADER = [
    "rank",
    "participant",
    "episodes",
    "SR %",
    "SR 95 % CI",
    "OSR %",
    "RDR",
    "Easy SR % (n)",
    "Medium SR % (n)",
    "Hard SR % (n)",
    "stage 1 %",
    "stage 2 %",
    "stage 3 %",
    "stage 4 %",
    "agents",
    "first",
    "last",
    "server and dataset",
]

_LEADERBOARD_STYLE = """
body { max-width: 1500px; }
td[data-key=sr-ci], td[data-key=episodes] { white-space: nowrap; }
td[data-key=agents], td[data-key=versions], td[data-key=first], td[data-key=last] {
  text-align: left; font-size: 0.85em; }
"""


def _page(title: str, participants: Sequence[Participant], scenes: int, folder: Path) -> str:
    e = html.escape
    versions = list(dict.fromkeys(v for p in participants for v in p.versions))
    rows = []
    for k, p in enumerate(participants, start=1):
        cells = "".join(f'<td data-key="{e(key)}">{e(text)}</td>' for key, text in _cells(p, scenes))
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
    page = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{e(title)}</title><style>{_STYLE}{_LEADERBOARD_STYLE}</style></head><body>",
        f"<h1>{e(title)}</h1>",
        f'<p class="note" id="basis">Each participant&#8217;s counted attempts on the {CHALLENGE_SPLIT} '
        f"split ({scenes} scenes played in all), one per scene, from the server&#8217;s records in "
        f"{e(str(folder))}. Ranked by SR, ties broken by OSR (higher first), then RDR (lower first). "
        "SR 95 % CI: the Wilson score interval over the participant&#8217;s episodes. SR and OSR in %, "
        "RDR as a ratio (lower is better).</p>",
        f'<p class="note" id="versions">Served by: {e("; ".join(versions))}.</p>',
        '<table id="leaderboard">',
        "<thead><tr>" + "".join(f"<th>{e(h)}</th>" for h in _HEADER) + "</tr></thead>",
        "<tbody>",
        *rows,
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
) -> tuple[list[Participant], int, Path]:
    """Ranks the counted challenge records of `folder` (`rank`) and writes the page to `out`;
    returns the ranking, the number of challenge scenes anyone played, and the page's path. Raises
    `LeaderboardError` when the folder holds no counted challenge record.
    """
    directory = Path(folder)
    records = load_records(directory)
    participants = rank(records)
    if not participants:
        raise LeaderboardError(
            f"{directory} holds no counted challenge records (split {CHALLENGE_SPLIT!r}, counted true) "
            f"among its {len(records)} records"
        )
    scenes = len({s.record.scene_id for p in participants for s in p.records})
    path = Path(out)
    if path.parent != Path():
        path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(_page(title, participants, scenes, directory), encoding="utf-8")
    return participants, scenes, path
