"""`esrp report`: tables and plots of `esrp.results/v1` files, as Markdown and as one self-contained
HTML page (plots and replay stills inlined as PNG data URLs; no script, no external resource).

For every run (a file, or each agent of a file that holds several) it lays out the paper's tables
with the paper's rows (SPEC §8) beside them: Table I (SR / OSR / RDR overall), Table II (the same
per difficulty, the SR with its 95 % Wilson interval) and Table III (failure stages); then plots
(SR and OSR by difficulty, stage shares, the RDR distribution, the share of episodes solved within
k steps) and, for chosen episodes, a replay still (the final frame of `esrp.eval.replay`). Privileged
agents (plan, expert) are marked as such, and runs over different scenes, runs that hold a scene
more than once (every record counts), or runs over less than the full test split the paper's rows
were measured on, are warned about. Needs the `report` extra
(matplotlib, Pillow); stills need a server.

The HTML marks its numbers for machines: each table has an `id` (`table-overall`,
`table-difficulty`, `table-stages`), each row a `data-run` (the run's label; the paper's rows
`data-paper`), each cell a `data-key` (`episodes`, `sr`, `sr-ci`, `osr`, `rdr`, `easy-sr`..., `stage-1`...).
"""

from __future__ import annotations

import base64
import html
import io
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import __version__
from .._client import Client
from .._common import unreachable
from .._errors import ServerUnavailable
from .._local import LocalServer
from .results import (
    DIFFICULTIES,
    PAPER,
    PAPER_DATASET,
    PAPER_TEST_SCENES,
    PRIVILEGED_AGENTS,
    EpisodeRecord,
    ReadRecords,
    ResultsError,
    Tally,
    fixed,
    load_records,
    no_records,
    wilson,
)

__all__ = ["ReportError", "Run", "coverage_warnings", "load_runs", "repeated_scenes", "write_report"]

_DIFFICULTY_TITLES = {"easy": "Easy", "medium": "Medium", "hard": "Hard"}
_STAGE_TITLES = ("1 never in reach", "2 never fetched", "3 fetched, no success", "4 success")


class ReportError(Exception):
    """A report cannot be made from these inputs."""


@dataclass
class Run:
    """One agent's records from one results file."""

    label: str
    path: Path
    agent: str
    records: list[EpisodeRecord]

    @property
    def privileged(self) -> bool:
        """Whether the agent reads the privileged state (plan, expert, or an agent whose records say
        `"privileged": true`, as `esrp eval --privileged` marks them): a reference.
        """
        return self.agent in PRIVILEGED_AGENTS or any(r.extra.get("privileged") is True for r in self.records)

    @property
    def shown(self) -> str:
        """The label as tables and plots show it: privileged agents marked as such."""
        return f"{self.label} (privileged)" if self.privileged else self.label

    @property
    def overall(self) -> Tally:
        """The tally of every record."""
        return Tally.of(self.records)

    def by_difficulty(self, difficulty: str) -> Tally:
        """The tally of the records of one difficulty."""
        return Tally.of(r for r in self.records if r.difficulty == difficulty)


def load_runs(paths: Sequence[str | os.PathLike[str]]) -> list[Run]:
    """The runs of results files: one per (file, agent), labelled by the agent's name, with the
    file's name added where two runs share an agent. A file without records (a run whose episodes
    all failed) is said on stderr and left out; no file with records raises `ReportError`.
    """
    runs: list[Run] = []
    reads: list[ReadRecords] = []
    for raw in paths:
        path = Path(raw)
        try:
            reads.append(load_records(path, "esrp report"))
        except ResultsError as error:
            raise ReportError(str(error)) from None
        agents: dict[str, list[EpisodeRecord]] = {}
        for record in reads[-1].records:
            agents.setdefault(record.agent, []).append(record)
        runs.extend(Run(agent, path, agent, group) for agent, group in agents.items())
    if not runs:
        raise ReportError(no_records(paths, reads))
    for raw, read in zip(paths, reads, strict=True):
        if not read.records:
            # Nothing of it in the tables: said, rather than left out unnoticed.
            print(f"esrp report: warning: {raw} holds no records (left out)", file=sys.stderr)
    counts: dict[str, int] = {}
    for run in runs:
        counts[run.agent] = counts.get(run.agent, 0) + 1
    for run in runs:
        if counts[run.agent] > 1:
            run.label = f"{run.agent} ({run.path.stem})"
    return runs


def repeated_scenes(run: Run) -> dict[str, int]:
    """The scenes `run` holds more than one record of, each with its number of records, in the
    order they first appear.
    """
    counts: dict[str, int] = {}
    for r in run.records:
        counts[r.scene_id] = counts.get(r.scene_id, 0) + 1
    return {scene: count for scene, count in counts.items() if count > 1}


def coverage_warnings(runs: Sequence[Run]) -> list[str]:
    """What makes the runs' numbers hard to compare with each other or with the paper's rows: runs
    over different scenes, runs that hold some scene more than once (their means count every
    record, so a repeated scene weighs more than the others), and runs that are not over the full
    test split of the paper's dataset (the paper's rows are full-test-split figures).
    """
    warnings: list[str] = []
    scenes = [{r.scene_id for r in run.records} for run in runs]
    if len(runs) > 1 and any(s != scenes[0] for s in scenes[1:]):
        common = set.intersection(*scenes)
        counts = ", ".join(f"{run.label} {len(s)}" for run, s in zip(runs, scenes, strict=True))
        warnings.append(
            f"the runs cover different scenes ({counts}; {len(common)} common to all): their rows compare "
            "different episodes"
        )
    for run in runs:
        # Every record counts, as in the tools' summaries (esrp eval, esrp-eval): said, so that a
        # ranking is not skewed by repeated episodes without a word.
        repeated = repeated_scenes(run)
        if repeated:
            scene, count = next(iter(repeated.items()))
            extra = sum(repeated.values()) - len(repeated)
            plural = "s" if len(repeated) > 1 else ""
            warnings.append(
                f"{run.label} holds {len(repeated)} scene{plural} more than once (e.g. {scene}, recorded "
                f"{count} times; {extra} records beyond one per scene): its rows count every record, so a "
                "repeated scene weighs more than the others"
            )
    for run, ids in zip(runs, scenes, strict=True):
        datasets = sorted({r.dataset for r in run.records})
        if datasets != [PAPER_DATASET]:
            warnings.append(
                f"{run.label} is of dataset {', '.join(datasets)}; the paper's rows are of {PAPER_DATASET}"
            )
            continue
        test = {r.scene_id for r in run.records if r.split == "test"}
        if len(test) != len(ids):
            warnings.append(
                f"{run.label} holds {len(ids) - len(test)} scenes outside the test split; the paper's rows "
                "are of the test split"
            )
        if len(test) < PAPER_TEST_SCENES:
            low, high = wilson(run.overall.successes, run.overall.episodes)
            warnings.append(
                f"{run.label} covers {len(test)} of the {PAPER_TEST_SCENES} test scenes; the paper's rows "
                f"are full-test-split figures (this run's SR: {_pct(run.overall.sr)} %, 95 % interval "
                f"{_pct(low)}–{_pct(high)} %)"
            )
    return warnings


# Tables: each a header and rows of (cells, marks); cells are text, marks say what they hold.


@dataclass
class _Row:
    name: str  # the row's data-run / data-paper
    cells: list[tuple[str, str]]  # (data-key, text)
    paper: bool
    shown: str = ""  # the row's header, where it differs from `name`

    @property
    def header(self) -> str:
        return self.shown or self.name


def _paper_shown(name: str) -> str:
    """A paper row's header: its ESRP-PLAN, like ours, reads the privileged state."""
    return name.replace("(paper)", "(paper, privileged)") if name.startswith("ESRP-PLAN") else name


def _sr_interval(t: Tally) -> str:
    low, high = wilson(t.successes, t.episodes)
    return f"{_pct(low)}–{_pct(high)}"


@dataclass
class _Table:
    table_id: str
    title: str
    note: str
    header: list[str]
    rows: list[_Row]


def _pct(value: float) -> str:
    return fixed(100 * value, 2)


def _tables(runs: Sequence[Run]) -> list[_Table]:
    """Tables I–III: each run's rows, then the paper's."""
    return [_overall_table(runs), _difficulty_table(runs), _stages_table(runs)]


def _overall_table(runs: Sequence[Run]) -> _Table:
    """Table I: SR (with its interval), OSR and RDR of each run and of the paper's agents."""
    overall = _Table(
        "table-overall",
        "Table I — overall",
        "SR and OSR in %, RDR as a ratio (lower is better); SR 95 % CI: the Wilson score interval "
        "of the SR over the run's episodes. Privileged agents read the simulator's state (SPEC §4): "
        "references, not ESRP agents proper.",
        ["run", "episodes", "SR", "SR 95 % CI", "OSR", "RDR"],
        [],
    )
    for run in runs:
        t = run.overall
        overall.rows.append(
            _Row(
                run.label,
                [
                    ("episodes", str(t.episodes)),
                    ("sr", _pct(t.sr)),
                    ("sr-ci", _sr_interval(t)),
                    ("osr", _pct(t.osr)),
                    ("rdr", fixed(t.rdr, 4)),
                ],
                False,
                run.shown,
            )
        )
    for paper in PAPER:
        sr, osr, rdr = paper.overall
        overall.rows.append(
            _Row(
                paper.name,
                [
                    ("episodes", "–"),
                    ("sr", f"{sr:.2f}"),
                    ("sr-ci", "–"),
                    ("osr", f"{osr:.2f}"),
                    ("rdr", f"{rdr:.4f}"),
                ],
                True,
                _paper_shown(paper.name),
            )
        )
    return overall


def _difficulty_table(runs: Sequence[Run]) -> _Table:
    """Table II: episodes, SR, OSR and RDR by difficulty, of each run and of the paper's agents."""
    header = ["run"]
    for d in DIFFICULTIES:
        header += [f"{_DIFFICULTY_TITLES[d]} {name}" for name in ("n", "SR", "OSR", "RDR")]
    by_difficulty = _Table(
        "table-difficulty",
        "Table II — by difficulty",
        "Easy: 1 object, Medium: 2–3, Hard: 4–6. SR and OSR in %.",
        header,
        [],
    )
    for run in runs:
        cells: list[tuple[str, str]] = []
        for d in DIFFICULTIES:
            t = run.by_difficulty(d)
            if t.episodes:
                cells += [
                    (f"{d}-episodes", str(t.episodes)),
                    (f"{d}-sr", _pct(t.sr)),
                    (f"{d}-osr", _pct(t.osr)),
                    (f"{d}-rdr", fixed(t.rdr, 4)),
                ]
            else:
                cells += [(f"{d}-episodes", "0"), (f"{d}-sr", "–"), (f"{d}-osr", "–"), (f"{d}-rdr", "–")]
        by_difficulty.rows.append(_Row(run.label, cells, False, run.shown))
    for paper in PAPER:
        cells = []
        for d, (sr, osr, rdr) in zip(DIFFICULTIES, paper.by_difficulty, strict=True):
            cells += [
                (f"{d}-episodes", "–"),
                (f"{d}-sr", f"{sr:.2f}"),
                (f"{d}-osr", f"{osr:.2f}"),
                (f"{d}-rdr", f"{rdr:.4f}"),
            ]
        by_difficulty.rows.append(_Row(paper.name, cells, True, _paper_shown(paper.name)))
    return by_difficulty


def _stages_table(runs: Sequence[Run]) -> _Table:
    """Table III: the share of episodes in each failure stage, of each run and of the paper's agents."""
    stages = _Table(
        "table-stages",
        "Table III — failure stages",
        "% of episodes in each stage (SPEC §5).",
        ["run", *_STAGE_TITLES],
        [],
    )
    for run in runs:
        t = run.overall
        stages.rows.append(
            _Row(run.label, [(f"stage-{s}", _pct(t.stage_share(s))) for s in range(1, 5)], False, run.shown)
        )
    for paper in PAPER:
        if paper.stages is not None:
            stages.rows.append(
                _Row(
                    paper.name,
                    [(f"stage-{s}", f"{v:.2f}") for s, v in enumerate(paper.stages, start=1)],
                    True,
                    _paper_shown(paper.name),
                )
            )
    return stages


def _markdown_table(table: _Table) -> str:
    lines = [f"## {table.title}\n", f"{table.note}\n", "| " + " | ".join(table.header) + " |"]
    lines.append("|" + "---|" * len(table.header))
    for row in table.rows:
        name = row.header if row.paper else f"**{row.header}**"
        lines.append("| " + " | ".join([name, *(text for _, text in row.cells)]) + " |")
    return "\n".join(lines) + "\n"


def _html_table(table: _Table) -> str:
    e = html.escape
    head = "".join(f"<th>{e(h)}</th>" for h in table.header)
    body = []
    for row in table.rows:
        mark = f'data-paper="{e(row.name)}" class="paper"' if row.paper else f'data-run="{e(row.name)}"'
        cells = "".join(f'<td data-key="{e(key)}">{e(text)}</td>' for key, text in row.cells)
        body.append(f'<tr {mark}><th scope="row">{e(row.header)}</th>{cells}</tr>')
    return (
        f'<h2>{e(table.title)}</h2>\n<p class="note">{e(table.note)}</p>\n'
        f'<table id="{e(table.table_id)}">\n<thead><tr>{head}</tr></thead>\n<tbody>\n'
        + "\n".join(body)
        + "\n</tbody>\n</table>\n"
    )


# Plots.


def _figure(width: float = 7.0, height: float = 3.6) -> Any:  # noqa: ANN401 - a matplotlib Figure
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise ReportError("esrp report needs matplotlib: pip install 'esrp[report]'") from None
    return Figure(figsize=(width, height), dpi=100, layout="constrained")


def _png(figure: Any) -> bytes:  # noqa: ANN401
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", metadata={"Software": None})
    return buffer.getvalue()


def _colour(k: int) -> str:
    palette = ("#4e79a7", "#f28e2b", "#59a14f", "#e15759", "#76b7b2", "#edc948", "#b07aa1", "#9c755f")
    return palette[k % len(palette)]


def _plot_by_difficulty(runs: Sequence[Run]) -> bytes:
    figure = _figure(7.0, 3.9)
    sr_axes, osr_axes = figure.subplots(1, 2, sharey=True)
    groups = [*DIFFICULTIES, "overall"]
    width = 0.8 / len(runs)
    for k, run in enumerate(runs):
        tallies = [run.by_difficulty(d) for d in DIFFICULTIES] + [run.overall]
        xs = [g + (k - (len(runs) - 1) / 2) * width for g in range(len(groups))]
        sr = [100 * t.sr if t.episodes else 0.0 for t in tallies]
        osr = [100 * t.osr if t.episodes else 0.0 for t in tallies]
        # The SR's 95 % Wilson interval as an error bar (none where there are no episodes).
        intervals = [
            wilson(t.successes, t.episodes) if t.episodes else (v / 100, v / 100)
            for t, v in zip(tallies, sr, strict=True)
        ]
        below = [max(0.0, v - 100 * low) for v, (low, _) in zip(sr, intervals, strict=True)]
        above = [max(0.0, 100 * high - v) for v, (_, high) in zip(sr, intervals, strict=True)]
        sr_axes.bar(
            xs,
            sr,
            width,
            label=run.shown,
            color=_colour(k),
            yerr=[below, above],
            error_kw={"elinewidth": 0.8, "capsize": 2, "ecolor": "#333333"},
        )
        osr_axes.bar(xs, osr, width, color=_colour(k))
    for axes, name in ((sr_axes, "SR % (95 % Wilson interval)"), (osr_axes, "OSR %")):
        axes.set_xticks(range(len(groups)), [g.capitalize() for g in groups])
        axes.set_title(name)
        axes.set_ylim(0, 105)
        axes.grid(axis="y", alpha=0.3)
    # Below the plots, not over the bars.
    figure.legend(fontsize="small", loc="outside lower center", ncols=min(len(runs), 4))
    return _png(figure)


def _plot_stages(runs: Sequence[Run]) -> bytes:
    rows: list[tuple[str, list[float]]] = [
        (run.shown, [100 * run.overall.stage_share(s) for s in range(1, 5)]) for run in runs
    ]
    rows += [(_paper_shown(p.name), list(p.stages)) for p in PAPER if p.stages is not None]
    figure = _figure(7.0, 0.45 * len(rows) + 1.6)
    axes = figure.subplots()
    colours = ("#bab0ac", "#f28e2b", "#e15759", "#59a14f")
    for k, (_, shares) in enumerate(rows):
        left = 0.0
        for s, share in enumerate(shares):
            axes.barh(k, share, left=left, color=colours[s], label=_STAGE_TITLES[s] if k == 0 else None)
            left += share
    axes.set_yticks(range(len(rows)), [name for name, _ in rows])
    axes.invert_yaxis()
    axes.set_xlim(0, 100)
    axes.set_xlabel("% of episodes")
    axes.set_title("Failure stages")
    # Outside the axes, in space the layout makes for it (a legend anchored below them is cut off).
    figure.legend(fontsize="small", ncols=4, loc="outside lower center")
    return _png(figure)


def _plot_rdr(runs: Sequence[Run]) -> bytes:
    figure = _figure(7.0, 3.9)
    axes = figure.subplots()
    values = [[r.rdr for r in run.records] for run in runs]
    top = max((max(v) for v in values if v), default=1.0)
    bins = [i * max(top, 1.0) / 20 for i in range(21)]
    for k, (run, rdr) in enumerate(zip(runs, values, strict=True)):
        axes.hist(rdr, bins=bins, alpha=0.6, label=run.shown, color=_colour(k))
    axes.axvline(1.0, color="black", linewidth=0.8, linestyle="--")
    axes.set_xlabel("RDR (remaining / initial distance; 1 = no progress)")
    axes.set_ylabel("episodes")
    axes.set_title("RDR distribution")
    figure.legend(fontsize="small", loc="outside lower center", ncols=min(len(runs), 4))
    return _png(figure)


def _plot_solved_by_steps(runs: Sequence[Run]) -> bytes:
    """The share of each run's episodes solved within k steps, for every k up to the horizon: how
    fast an agent succeeds, and what a shorter horizon would have cost it (each curve ends at the
    run's SR).
    """
    figure = _figure(7.0, 3.9)
    axes = figure.subplots()
    horizons = sorted({r.horizon for run in runs for r in run.records})
    top = max([*horizons, *(r.steps for run in runs for r in run.records), 1])
    for k, run in enumerate(runs):
        solved = sorted(r.steps for r in run.records if r.success)
        total = len(run.records)
        xs = [0, *solved, top]
        ys = [0.0, *(100 * (i + 1) / total for i in range(len(solved))), 100 * len(solved) / total]
        axes.step(xs, ys, where="post", color=_colour(k), label=f"{run.shown} (SR {_pct(run.overall.sr)} %)")
    for horizon in horizons:
        axes.axvline(horizon, color="black", linewidth=0.8, linestyle="--")
    shown = ", ".join(str(h) for h in horizons[:4]) + (" ..." if len(horizons) > 4 else "")
    axes.set_xlim(0, top * 1.02)
    axes.set_ylim(0, 105)
    axes.set_xlabel(f"steps (dashed: the horizon, {shown})")
    axes.set_ylabel("% of episodes solved")
    axes.set_title("Episodes solved within k steps")
    axes.grid(alpha=0.3)
    figure.legend(fontsize="small", loc="outside lower center", ncols=min(len(runs), 3))
    return _png(figure)


# Replay stills.


def _choose(runs: Sequence[Run], count: int, scenes: Sequence[str]) -> list[tuple[Run, EpisodeRecord]]:
    """The episodes to draw: per run, the named scenes it holds, then its first `count` records in
    scene order that are not among them.
    """
    chosen: list[tuple[Run, EpisodeRecord]] = []
    for run in runs:
        by_scene = {r.scene_id: r for r in run.records}
        picked = [by_scene[s] for s in scenes if s in by_scene]
        rest = [r for r in sorted(run.records, key=lambda r: r.scene_id) if r.scene_id not in scenes]
        picked += rest[: max(count, 0)]
        chosen.extend((run, r) for r in picked)
    return chosen


def _stills(
    chosen: Sequence[tuple[Run, EpisodeRecord]],
    server: str | None,
    token: str | None,
    server_args: Sequence[str],
) -> list[tuple[Run, EpisodeRecord, bytes | str]]:
    """The final frame of each chosen episode as PNG bytes (or the reason it could not be made)."""
    from .replay import ReplayError, replay_record

    def draw(client: Client) -> list[tuple[Run, EpisodeRecord, bytes | str]]:
        out: list[tuple[Run, EpisodeRecord, bytes | str]] = []
        for run, record in chosen:
            try:
                replay = replay_record(client, record, every_frame=False)
            except ReplayError as error:
                print(f"esrp report: {error}", file=sys.stderr)
                out.append((run, record, str(error)))
                continue
            buffer = io.BytesIO()
            _pil_png(replay.frames[-1], buffer)
            out.append((run, record, buffer.getvalue()))
        return out

    if not chosen:
        return []
    if server is not None:
        with Client(server, token=token, timeout=120) as client:
            try:
                client.server_info()  # fails at once when nothing answers there
            except ServerUnavailable as error:
                raise ReportError(unreachable(server, error)) from None
            return draw(client)
    with LocalServer(*server_args, unix_socket="auto") as local, local.client(timeout=120) as client:
        return draw(client)


def _pil_png(frame: Any, buffer: io.BytesIO) -> None:  # noqa: ANN401 - a numpy frame
    from PIL import Image

    Image.fromarray(frame).save(buffer, format="PNG")


# The report.


def _data_url(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th[scope=row], thead th:first-child { text-align: left; }
tr.paper { color: #666; background: #f6f6f6; }
.note { color: #555; font-size: 0.9em; }
figure { display: inline-block; margin: 0.5em; vertical-align: top; }
figcaption { font-size: 0.85em; color: #444; }
img { max-width: 100%; border: 1px solid #ddd; }
.warnings { background: #fff6e0; border: 1px solid #e8c36a; padding: 0.2em 1em; }
"""


def write_report(
    results: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    *,
    title: str = "ESRP evaluation report",
    replays: int = 0,
    replay_scenes: Sequence[str] = (),
    server: str | None = None,
    token: str | None = None,
    server_args: Sequence[str] = (),
) -> list[Path]:
    """Writes `report.md` (with its plots and stills as PNG files beside it) and `report.html` (one
    self-contained page) into `out`; returns their paths. Stills (`replays` per run, and the
    `replay_scenes`) replay their records on `server`, or on a `LocalServer` started for them.
    """
    runs = load_runs(results)
    folder = Path(out)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    tables = _tables(runs)
    plots = [
        ("sr_osr_by_difficulty", "SR and OSR by difficulty", _plot_by_difficulty(runs)),
        ("stages", "Failure stages (the paper's rows below the runs)", _plot_stages(runs)),
        ("rdr", "RDR distribution", _plot_rdr(runs)),
        (
            "solved_by_steps",
            "Episodes solved within k steps (each curve ends at the run's SR; dashed: the horizon)",
            _plot_solved_by_steps(runs),
        ),
    ]
    stills = _stills(_choose(runs, replays, replay_scenes), server, token, server_args)

    warnings = coverage_warnings(runs)
    for warning in warnings:
        print(f"esrp report: warning: {warning}", file=sys.stderr)
    sources = ", ".join(f"`{run.path.name}` ({run.label}, {_episodes(run)})" for run in runs)
    report = _Report(title, sources, warnings, tables, plots, stills)
    markdown_path = _write_markdown(folder, report)
    html_path = _write_html(folder, report)
    return [markdown_path, html_path]


def _episodes(run: Run) -> str:
    """`N episodes`, and `of K scenes` where the run repeats some (the tables count every record)."""
    scenes = len({r.scene_id for r in run.records})
    repeated = f" of {scenes} scenes (some repeated)" if scenes != len(run.records) else ""
    return f"{len(run.records)} episodes{repeated}"


@dataclass(frozen=True)
class _Report:
    """What both pages of a report show.

    Its title, the runs it reads (`sources`), the warnings about their coverage, Tables I–III, the
    plots (name, caption, PNG) and the replay stills (PNG, or why there is none).
    """

    title: str
    sources: str
    warnings: list[str]
    tables: list[_Table]
    plots: list[tuple[str, str, bytes]]
    stills: list[tuple[Run, EpisodeRecord, bytes | str]]


def _write_markdown(folder: Path, report: _Report) -> Path:
    """Writes `report.md` into `folder`, and its plots and stills as PNG files in `images/`."""
    title, sources, warnings = report.title, report.sources, report.warnings
    tables, plots, stills = report.tables, report.plots, report.stills
    md = [f"# {title}\n", f"Runs: {sources}. The paper's rows are its Tables I–III (SPEC §8).\n"]
    if warnings:
        md.append("**Read with care:**\n\n" + "".join(f"- {w}\n" for w in warnings))
    md += [_markdown_table(t) for t in tables]
    md.append("## Plots\n")
    for name, caption, png in plots:
        (folder / "images" / f"{name}.png").write_bytes(png)
        md.append(f"![{caption}](images/{name}.png)\n")
    if stills:
        md.append("## Replays (final frames: ego | goal | now, agent path red, carried objects blue)\n")
    for k, (run, record, still) in enumerate(stills):
        caption = _still_caption(run, record)
        if isinstance(still, bytes):
            name = f"replay_{k}.png"
            (folder / "images" / name).write_bytes(still)
            md.append(f"![{caption}](images/{name})\n")
        else:
            md.append(f"{caption}: no still ({still})\n")
    md.append(f"Written by esrp report {__version__}.\n")
    markdown_path = folder / "report.md"
    markdown_path.write_text("\n".join(md), encoding="utf-8")
    return markdown_path


def _write_html(folder: Path, report: _Report) -> Path:
    """Writes `report.html` into `folder`: one page, its plots and stills inlined as data URLs."""
    title, sources, warnings = report.title, report.sources, report.warnings
    tables, plots, stills = report.tables, report.plots, report.stills
    e = html.escape
    page = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{e(title)}</title><style>{_STYLE}</style></head><body>",
        f"<h1>{e(title)}</h1>",
        f'<p class="note">Runs: {e(sources.replace("`", ""))}. '
        "The paper&#8217;s rows (grey) are its Tables I–III (SPEC §8).</p>",
    ]
    if warnings:
        page.append(
            '<div class="warnings"><p><strong>Read with care:</strong></p><ul>'
            + "".join(f"<li>{e(w)}</li>" for w in warnings)
            + "</ul></div>"
        )
    page += [_html_table(t) for t in tables]
    page.append("<h2>Plots</h2>")
    for name, caption, png in plots:
        page.append(
            f'<figure id="plot-{name}"><img class="plot" alt="{e(caption)}" src="{_data_url(png)}">'
            f"<figcaption>{e(caption)}</figcaption></figure>"
        )
    if stills:
        page.append("<h2>Replays</h2>")
        page.append(
            '<p class="note">Final frames: ego view | goal | current top-down, with the agent&#8217;s '
            "path in red and carried objects&#8217; paths in blue.</p>"
        )
    for run, record, still in stills:
        caption = _still_caption(run, record)
        if isinstance(still, bytes):
            page.append(
                f'<figure class="replay" data-scene="{e(record.scene_id)}">'
                f'<img class="replay" alt="{e(caption)}" src="{_data_url(still)}">'
                f"<figcaption>{e(caption)}</figcaption></figure>"
            )
        else:
            page.append(f'<p class="replay-error">{e(caption)}: no still ({e(still)})</p>')
    page.append(f'<p class="note">Written by esrp report {e(__version__)}.</p></body></html>')
    html_path = folder / "report.html"
    html_path.write_text("\n".join(page) + "\n", encoding="utf-8")
    return html_path


def _still_caption(run: Run, record: EpisodeRecord) -> str:
    """A replay still's caption: the run, the scene, how the episode ended, its steps and OSR."""
    return f"{run.label}: {record.scene_id} ({record.end}, {record.steps} steps, OSR {_pct(record.osr)} %)"
