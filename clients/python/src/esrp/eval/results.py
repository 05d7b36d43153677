"""The results schema `esrp.results/v1` shared by every evaluation tool (the Rust `esrp-eval`, the
Python `esrp eval`), as `docs/evaluation.md` describes it: one `EpisodeRecord` per line of a JSON
Lines file; `read_records` reads a file back (dropping a last line that an interruption cut short),
and `Summary` computes SR / OSR / RDR overall and per difficulty and writes the Markdown summary with
the paper's rows beside it — the same text as the Rust tool's (`clients/rust/src/results.rs`).
"""

from __future__ import annotations

import gzip
import json
import math
import os
import sys
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from .._values import RewardWeights

__all__ = [
    "DIFFICULTIES",
    "OBSERVATIONS",
    "PAPER",
    "PAPER_DATASET",
    "PAPER_TEST_SCENES",
    "PRIVILEGED_AGENTS",
    "RECORD_START",
    "REWARD_TERMS",
    "SCHEMA",
    "EpisodeRecord",
    "PaperRow",
    "ReadRecords",
    "ResultsError",
    "Summary",
    "Tally",
    "append_record",
    "fnv1a64",
    "load_records",
    "may_be_cut_record",
    "no_records",
    "read_records",
    "scene_seed",
    "truncate_to",
    "wilson",
]

SCHEMA = "esrp.results/v1"
"""The schema tag of every record."""

DIFFICULTIES = ("easy", "medium", "hard")
"""The difficulty names, in the order tables list them."""

REWARD_TERMS = ("success", "place", "unplace", "potential", "holding", "living")
"""The members of a server record's `reward_weights`, in the order SPEC §6 lists them (and
`to_json` writes them; the server writes them sorted by name)."""

OBSERVATIONS = ("paper", "full")
"""The values of a server record's `observations`: the paper's observation only, or everything."""

_U64 = (1 << 64) - 1
_U32 = (1 << 32) - 1


def fnv1a64(text: str) -> int:
    """FNV-1a, 64 bits, over `text`'s UTF-8 bytes (docs/evaluation.md, "Seeds")."""
    value = 0xCBF29CE484222325
    for byte in text.encode():
        value = ((value ^ byte) * 0x100000001B3) & _U64
    return value


def scene_seed(base_seed: int, scene_id: str) -> int:
    """The per-scene seed of a seeded agent: `base_seed XOR fnv1a64(scene_id)` (64 bits)."""
    return (base_seed & _U64) ^ fnv1a64(scene_id)


class ResultsError(Exception):
    """A results file could not be read: a line (not the last) is not an `esrp.results/v1` record."""


@dataclass
class EpisodeRecord:
    """One finished episode: a line of a results file. Fields as docs/evaluation.md lists them,
    in the same order (the order they are written in), then `extra`: the fields of the line that
    this version does not know, kept as they were read.
    """

    schema: str
    scene_id: str
    dataset: str
    split: str
    room_type: str
    difficulty: str
    objects: int
    agent: str
    agent_config: dict[str, Any]
    seed: int | None
    success: bool
    osr: float
    rdr: float
    stage: int
    placed: int
    steps: int
    horizon: int
    end: str
    total_reward: float
    actions: list[int]
    wall_seconds: float
    agent_stats: dict[str, Any]
    server_version: str
    client: str
    finished_at: str
    extra: dict[str, Any] = field(default_factory=dict)
    """Fields the schema's table does not list, by name, as read: e.g. a server record's `token`,
    `started_at`, `dataset_hash` and `counted` (docs/evaluation.md). Written back after the others."""
    reward_weights: dict[str, float] | None = None
    """A server record's: the six reward weights the episode played with (`REWARD_TERMS`); None
    in other tools' records."""
    observations: str | None = None
    """A server record's: what the episode served its client, `"paper"` (the paper's observation
    only) or `"full"`; None in other tools' records."""
    signature: str | None = None
    """A server record's: the HMAC-SHA256 of its line (`esrp.eval.signing`), 64 hex digits, the
    last member of the line; None in other tools' records. A record written again by `to_json`
    keeps it, but it signs the server's line, not the rewritten one."""

    def played_weights(self) -> RewardWeights | None:
        """The reward weights the episode played with, to replay it with (a server record's
        `reward_weights`); None for records without them (the server's defaults).
        """
        return None if self.reward_weights is None else RewardWeights(**self.reward_weights)

    def to_json(self) -> str:
        """The record as one line of compact JSON (no newline), UTF-8 text as is: the schema's
        fields in order, then the `extra` ones, with `reward_weights` and `observations` after
        `counted` (after the `extra` ones when there is no `counted`), and `signature` last. The
        members of `agent_config` and `agent_stats` are written sorted by name, in nested objects
        too (as the Rust tools write them), whatever order the agent gave them in.
        """
        data = {name: getattr(self, name) for name in _FIELD_TYPES}
        # The free-form objects with their members sorted by name at every depth, as the Rust
        # tools (serde_json's maps) write them: the same stats are the same bytes in either tool.
        data["agent_config"] = _sorted_members(self.agent_config)
        data["agent_stats"] = _sorted_members(self.agent_stats)
        server = {name: getattr(self, name) for name in _SERVER_FIELDS if getattr(self, name) is not None}
        for name, value in self.extra.items():
            if name in _FIELD_TYPES or name in _SERVER_FIELDS or name == "signature":
                continue
            data[name] = value
            if name == "counted":
                data.update(server)
        data.update(server)  # no-op when written after `counted`: the order of a dict is its first
        if self.signature is not None:
            data["signature"] = self.signature
        return json.dumps(data, separators=(",", ":"), ensure_ascii=False, allow_nan=False)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EpisodeRecord:
        """A record of a parsed JSON object; fields the schema does not list go to `extra`, unread.
        Raises `ValueError` naming the first missing or mistyped field, or a schema other than
        `esrp.results/v1`.
        """
        if not isinstance(data, Mapping):
            raise ValueError(f"a JSON {type(data).__name__}, not an object")
        if data.get("schema") != SCHEMA:
            raise ValueError(f"schema is {data.get('schema')!r}, not {SCHEMA!r}")
        values: dict[str, Any] = {}
        for name, kinds in _FIELD_TYPES.items():
            if name not in data:
                raise ValueError(f"missing field {name!r}")
            value = data[name]
            if not _is(value, kinds):
                raise ValueError(f"field {name!r} is {value!r}, not {' or '.join(k.__name__ for k in kinds)}")
            values[name] = float(value) if float in kinds and not isinstance(value, bool) else value
            limit = _INT_LIMITS.get(name)
            if limit is not None and value is not None and not 0 <= value <= limit:
                raise ValueError(f"field {name!r} is {value!r}, not an integer 0..{limit}")
        if not all(isinstance(a, int) and not isinstance(a, bool) and 0 <= a <= 5 for a in values["actions"]):
            raise ValueError("field 'actions' holds something other than action codes 0..5")
        weights = data.get("reward_weights")
        if weights is not None:
            if (
                not isinstance(weights, Mapping)
                or set(weights) != set(REWARD_TERMS)
                or not all(_is(weights[term], (float, int)) for term in REWARD_TERMS)
            ):
                raise ValueError(
                    f"field 'reward_weights' is {weights!r}, not an object of the numbers "
                    + ", ".join(REWARD_TERMS)
                )
            weights = {term: float(weights[term]) for term in REWARD_TERMS}
        observations = data.get("observations")
        if observations is not None and observations not in OBSERVATIONS:
            raise ValueError(f"field 'observations' is {observations!r}, not 'paper' or 'full'")
        signature = data.get("signature")
        if signature is not None and not isinstance(signature, str):
            raise ValueError(f"field 'signature' is {signature!r}, not a string")
        known = {*_FIELD_TYPES, *_SERVER_FIELDS, "signature"}
        extra = {name: value for name, value in data.items() if name not in known}
        return cls(
            **values, extra=extra, reward_weights=weights, observations=observations, signature=signature
        )


def _sorted_members(value: Any) -> Any:  # noqa: ANN401 - free-form JSON
    """`value` with the members of every object in it sorted by name (lists keep their order)."""
    if isinstance(value, Mapping):
        return {key: _sorted_members(value[key]) for key in sorted(value)}
    if isinstance(value, (list, tuple)):
        return [_sorted_members(v) for v in value]
    return value


_FIELD_TYPES: dict[str, tuple[type, ...]] = {
    "schema": (str,),
    "scene_id": (str,),
    "dataset": (str,),
    "split": (str,),
    "room_type": (str,),
    "difficulty": (str,),
    "objects": (int,),
    "agent": (str,),
    "agent_config": (dict,),
    "seed": (int, type(None)),
    "success": (bool,),
    "osr": (float, int),
    "rdr": (float, int),
    "stage": (int,),
    "placed": (int,),
    "steps": (int,),
    "horizon": (int,),
    "end": (str,),
    "total_reward": (float, int),
    "actions": (list,),
    "wall_seconds": (float, int),
    "agent_stats": (dict,),
    "server_version": (str,),
    "client": (str,),
    "finished_at": (str,),
}


_INT_LIMITS = {"objects": _U32, "stage": _U32, "placed": _U32, "steps": _U32, "horizon": _U32, "seed": _U64}
"""The integer fields' ranges, as every tool reads them (the Rust tools' `u32` and `u64`)."""


_SERVER_FIELDS = ("reward_weights", "observations")
"""The typed fields of a server record written after `counted` (then `signature`, last)."""


def _is(value: object, kinds: tuple[type, ...]) -> bool:
    if isinstance(value, bool):
        return bool in kinds
    return isinstance(value, kinds)


@dataclass
class ReadRecords:
    """A results file read back.

    Attributes:
        records: The records, in file order.
        line_numbers: The line (1-based) each record was read from.
        lines: The bytes of each record's line as read, without its newline (what a server
            record's signature covers: `esrp.eval.signing`).
        complete_bytes: Byte length of the complete lines read: a last line cut short by an
            interruption starts there, and `truncate_to` removes it.
        torn_tail: Whether a last line was cut short (incomplete or unreadable).
        torn_line: The number (1-based) of that last line; 0 when there is none.
        torn_reason: Why it was dropped: `no newline` (a record whose write stopped right before
            its newline), or why it is not a record (JSON or schema error); empty when none.
        torn_whole: Whether that line is not what an interrupted append leaves: it ends with its
            newline (the last byte an append writes), or it does not begin as every tool's record
            line begins (`{"schema":"esrp.results/v1"`, spaces aside; a one-line JSON file of
            something else often lacks its newline). Such a line is not a torn write but a line of
            something else: `esrp eval` refuses to cut it off, and `load_records` (the commands'
            input) refuses it.
    """

    records: list[EpisodeRecord] = field(default_factory=list)
    line_numbers: list[int] = field(default_factory=list)
    lines: list[bytes] = field(default_factory=list)
    complete_bytes: int = 0
    torn_tail: bool = False
    torn_line: int = 0
    torn_reason: str = ""
    torn_whole: bool = False
    compressed: bool = False
    """Whether the file is gzip-compressed (`.jsonl.gz`, as docs/results keeps them): it was read
    decompressed, and its lines and byte counts are the decompressed ones."""

    def torn_note(self, path: str | os.PathLike[str]) -> str:
        """The dropped last line of file `path`, in words (empty when none was dropped):
        `r.jsonl:7: its last line is cut short (no newline)`, or `... is not an esrp.results/v1
        record (...)`.
        """
        if not self.torn_tail:
            return ""
        if self.torn_reason == "no newline":
            return f"{path}:{self.torn_line}: its last line is cut short (no newline)"
        return f"{path}:{self.torn_line}: its last line is not an {SCHEMA} record ({self.torn_reason})"


RECORD_START = b'{"schema":"esrp.results/v1"'
"""How every tool's record line begins (the Rust tools', Python's and the server's)."""


def may_be_cut_record(line: bytes) -> bool:
    """Whether `line`, a last line without its newline, may be a record whose append was cut short:
    it begins as a record line does (`RECORD_START`, spaces aside), or is a beginning of that.
    """
    squeezed = line.translate(None, b" \t\r\n")
    return squeezed.startswith(RECORD_START) or RECORD_START.startswith(squeezed)


def _not_json(name: str) -> float:
    """`NaN`, `Infinity` and `-Infinity`: Python's json reads them, JSON (and the Rust tools) do not."""
    raise ValueError(f"{name} is not a JSON number")


GZIP_MAGIC = b"\x1f\x8b"
"""The first two bytes of a gzip file."""


def read_records(path: str | os.PathLike[str]) -> ReadRecords:
    """Reads a results file, decompressed first when it is gzip-compressed (`compressed` says so).
    A last line that does not parse (an interrupted write), or that lacks its newline, is reported
    in `torn_tail`, not an error (`torn_whole` says whether it cannot be an interrupted write); any
    other bad line raises `ResultsError`, as does a gzip file that does not decompress. Blank lines
    are skipped.
    """
    out = ReadRecords()
    with open(path, "rb") as file:
        data = file.read()
    if data.startswith(GZIP_MAGIC):
        try:
            data = gzip.decompress(data)
        except (OSError, EOFError, zlib.error) as error:
            raise ResultsError(f"{path}: a gzip file that does not decompress: {error}") from None
        out.compressed = True
    # Lines as `readlines()` gives them: split at newlines only, each keeping its own.
    *ended, tail = data.split(b"\n")
    lines = [line + b"\n" for line in ended] + ([tail] if tail else [])
    for number, raw in enumerate(lines, start=1):
        complete = raw.endswith(b"\n")
        text = raw.strip()
        if not text:
            if complete:
                out.complete_bytes += len(raw)
            continue
        try:
            record = EpisodeRecord.from_dict(json.loads(text.decode(), parse_constant=_not_json))
        except (ValueError, TypeError) as error:
            if number == len(lines):  # only the last line may be torn
                whole = complete or not may_be_cut_record(raw)
                out.torn_tail, out.torn_line, out.torn_whole = True, number, whole
                out.torn_reason = str(error) or type(error).__name__
                break
            raise ResultsError(f"{path}:{number}: not an {SCHEMA} record: {error}") from None
        if complete:
            out.records.append(record)
            out.line_numbers.append(number)
            out.lines.append(raw[:-1])
            out.complete_bytes += len(raw)
        else:
            # A record without its newline: the write was interrupted right before it.
            out.torn_tail, out.torn_line, out.torn_reason = True, number, "no newline"
    return out


def load_records(path: str | os.PathLike[str], command: str) -> ReadRecords:
    """`read_records(path)` for a command's input: a file that cannot be read raises `ResultsError`
    in one line (`cannot read r.jsonl: No such file or directory`), as does a whole last line (one
    that ends with its newline, which an interrupted write never leaves) that is not a record, like
    any other line; a last line cut short, which was dropped, is said on stderr (`esrp report:
    r.jsonl:7: its last line is cut short (no newline), skipped`; `command` names the command).
    """
    try:
        read = read_records(path)
    except OSError as error:
        raise ResultsError(f"cannot read {path}: {error.strerror or error}") from None
    if read.torn_whole:
        raise ResultsError(f"{path}:{read.torn_line}: not an {SCHEMA} record: {read.torn_reason}")
    if read.torn_tail:
        print(f"{command}: {read.torn_note(path)}, skipped", file=sys.stderr)
    return read


def no_records(paths: Sequence[str | os.PathLike[str]], reads: Sequence[ReadRecords]) -> str:
    """The message for input files that hold no record: `the results files hold no records`, with
    each dropped last line (`torn_note`), which is often the reason (a file of something else).
    """
    notes = [read.torn_note(path) for path, read in zip(paths, reads, strict=True) if read.torn_tail]
    return "the results files hold no records" + (f" ({'; '.join(notes)})" if notes else "")


def read_many(paths: Iterable[str | os.PathLike[str]]) -> list[tuple[Path, list[EpisodeRecord]]]:
    """The records of several results files (each with a torn last line dropped), by file."""
    return [(Path(p), read_records(p).records) for p in paths]


def truncate_to(path: str | os.PathLike[str], size: int) -> None:
    """Cuts a results file to its first `size` bytes (dropping a torn last line)."""
    with open(path, "r+b") as file:
        file.truncate(size)


def append_record(file: IO[bytes], record: EpisodeRecord) -> None:
    """Appends one record as a line and flushes it (to the OS: an interruption loses at most the
    line being written, which the next read drops).
    """
    file.write(record.to_json().encode() + b"\n")
    file.flush()


@dataclass
class Tally:
    """SR / OSR / RDR and stage counts over a set of records."""

    episodes: int = 0
    successes: int = 0
    osr_sum: float = 0.0
    rdr_sum: float = 0.0
    stages: list[int] = field(default_factory=lambda: [0, 0, 0, 0])
    """Episodes per stage 1..4 (index 0 is stage 1)."""
    steps: int = 0
    ended_by_agent: int = 0

    def add(self, record: EpisodeRecord) -> None:
        """Adds a record."""
        self.episodes += 1
        self.successes += int(record.success)
        self.osr_sum += record.osr
        self.rdr_sum += record.rdr
        if 1 <= record.stage <= 4:
            self.stages[record.stage - 1] += 1
        self.steps += record.steps
        self.ended_by_agent += int(record.end == "agent")

    @classmethod
    def of(cls, records: Iterable[EpisodeRecord]) -> Tally:
        """The tally of `records`."""
        tally = cls()
        for record in records:
            tally.add(record)
        return tally

    def _mean(self, total: float) -> float:
        return math.nan if self.episodes == 0 else total / self.episodes

    @property
    def sr(self) -> float:
        """Success rate, 0..1 (NaN without episodes)."""
        return self._mean(self.successes)

    @property
    def osr(self) -> float:
        """Object success rate, 0..1."""
        return self._mean(self.osr_sum)

    @property
    def rdr(self) -> float:
        """Remaining distance ratio (lower is better)."""
        return self._mean(self.rdr_sum)

    def stage_share(self, stage: int) -> float:
        """Share of episodes in stage `stage` (1..4), 0..1."""
        return self._mean(self.stages[stage - 1])

    @property
    def mean_steps(self) -> float:
        """Mean steps per episode (0 without episodes)."""
        return 0.0 if self.episodes == 0 else self.steps / self.episodes


@dataclass(frozen=True)
class PaperRow:
    """A row of the paper's results (SPEC §8): SR % / OSR % / RDR overall and per difficulty
    (easy, medium, hard), and the stage shares % (1..4) where the paper gives them.
    """

    name: str
    overall: tuple[float, float, float]
    by_difficulty: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
    stages: tuple[float, float, float, float] | None


PAPER: tuple[PaperRow, ...] = (
    PaperRow(
        "ESRP-PPO (paper)",
        (20.18, 20.35, 0.9845),
        ((33.33, 33.33, 0.9040), (0.54, 0.54, 1.0645), (0.00, 0.00, 1.0048)),
        (13.21, 5.76, 60.85, 20.18),
    ),
    PaperRow(
        "ESRP-BC (paper)",
        (19.09, 20.31, 1.0170),
        ((29.44, 29.44, 0.9631), (0.91, 4.20, 1.1157), (0.00, 4.44, 1.0704)),
        (11.33, 6.73, 62.85, 19.09),
    ),
    PaperRow(
        "ESRP-VLM (paper)",
        (17.64, 18.97, 0.9830),
        ((27.64, 27.64, 0.9523), (0.00, 3.99, 1.0372), (0.00, 0.00, 1.0378)),
        (11.64, 4.18, 66.55, 17.64),
    ),
    PaperRow(
        "ESRP-PLAN (paper)",
        (30.20, 36.59, 0.6916),
        ((35.73, 35.73, 0.7101), (22.40, 39.71, 0.6425), (0.00, 22.00, 0.8165)),
        None,
    ),
)
"""The paper's Tables I–III (SPEC §8)."""


PAPER_DATASET = "esrp-bench-v1"
"""The dataset of the paper's rows."""

PAPER_TEST_SCENES = 544
"""The scenes of esrp-bench-v1's test split, over which the paper's rows were measured."""

PRIVILEGED_AGENTS = ("plan", "expert")
"""The agents that read the simulator's privileged state (SPEC §4): references, not ESRP agents
proper. The paper's ESRP-PLAN is privileged too."""


def wilson(successes: int, trials: int, z: float = 1.959964) -> tuple[float, float]:
    """The Wilson score interval of a success rate, 0..1 (95 % with the default `z`); `(0, 1)`
    without trials.
    """
    if trials == 0:
        return 0.0, 1.0
    p = successes / trials
    z2 = z * z
    centre = (p + z2 / (2 * trials)) / (1 + z2 / trials)
    half = z / (1 + z2 / trials) * math.sqrt(p * (1 - p) / trials + z2 / (4 * trials * trials))
    # Exact at the ends (rounding would leave 0.9999999999999999 for all successes).
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == trials else min(1.0, centre + half)
    return low, high


def fixed(value: float, digits: int) -> str:
    """`value` with `digits` decimals, as Rust's `{:.N}` writes it (`NaN`, `inf` included)."""
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{value:.{digits}f}"


def triple(tally: Tally | None) -> str:
    """`SR / OSR / RDR` of a tally as the summary's cells write them (`–` without episodes)."""
    if tally is None or tally.episodes == 0:
        return "–"
    return f"{fixed(100 * tally.sr, 2)} / {fixed(100 * tally.osr, 2)} / {fixed(tally.rdr, 4)}"


@dataclass
class Summary:
    """The summary of one agent's records: overall and per difficulty."""

    agent: str
    overall: Tally
    by_difficulty: dict[str, Tally]

    @classmethod
    def of(cls, records: Sequence[EpisodeRecord], agent: str | None = None) -> Summary:
        """The summary of `records`; the agent's name is `agent`, else the first record's."""
        by_difficulty: dict[str, Tally] = {}
        for record in records:
            by_difficulty.setdefault(record.difficulty, Tally()).add(record)
        name = agent if agent is not None else records[0].agent if records else "?"
        return cls(name, Tally.of(records), by_difficulty)

    def text(self) -> str:
        """A few lines for a terminal: SR / OSR / RDR overall and per difficulty (one line saying so
        when there are no episodes).
        """
        if self.overall.episodes == 0:
            return "no episodes recorded: no SR, OSR or RDR to give\n"
        lines = []
        for name, tally in [("overall", self.overall)] + [
            (d, self.by_difficulty[d]) for d in DIFFICULTIES if d in self.by_difficulty
        ]:
            shares = "/".join(fixed(100 * tally.stage_share(s), 1) for s in range(1, 5))
            lines.append(
                f"{name:<8} SR {fixed(100 * tally.sr, 2):>6} %  OSR {fixed(100 * tally.osr, 2):>6} %  "
                f"RDR {fixed(tally.rdr, 4)}  stages 1/2/3/4 {shares} %  "
                f"({tally.episodes} episodes, {tally.ended_by_agent} ended by the agent)"
            )
        return "".join(line + "\n" for line in lines)

    def markdown(self, title: str) -> str:
        """The Markdown summary: SR / OSR / RDR overall and per difficulty with the paper's rows
        (SPEC §8) beside them, then stage shares and step counts — the Rust tool's text.
        """
        t = self.overall
        if t.episodes == 0:
            return (
                f"# {title}\n\nNo episodes recorded for **{self.agent}**: there is no SR, OSR or RDR "
                "to give (every episode failed with an error, or none was played).\n"
            )
        md = [
            f"# {title}\n\n",
            f"SR and OSR in %, RDR as a ratio (lower is better). {t.episodes} episodes. "
            "The paper's rows are its Tables I–III (SPEC §8).\n\n",
            "| agent | overall SR / OSR / RDR | Easy | Medium | Hard |\n",
            "|---|---|---|---|---|\n",
        ]
        row = f"| **{self.agent}** (this run) | {triple(t)} |"
        row += "".join(f" {triple(self.by_difficulty.get(d))} |" for d in DIFFICULTIES)
        md.append(row + "\n")
        for paper in PAPER:
            sr, osr, rdr = paper.overall
            cells = "".join(f" {a:.2f} / {b:.2f} / {c:.4f} |" for a, b, c in paper.by_difficulty)
            md.append(f"| {paper.name} | {sr:.2f} / {osr:.2f} / {rdr:.4f} |{cells}\n")
        md.append("\n## Failure stages (% of episodes in stage 1 / 2 / 3 / 4)\n\n")
        md.append("| agent | 1 never in reach | 2 never fetched | 3 fetched, no success | 4 success |\n")
        md.append("|---|---|---|---|---|\n")
        shares = " | ".join(fixed(100 * t.stage_share(s), 2) for s in range(1, 5))
        md.append(f"| **{self.agent}** (this run) | {shares} |\n")
        for paper in PAPER:
            if paper.stages is not None:
                md.append(f"| {paper.name} | {' | '.join(f'{s:.2f}' for s in paper.stages)} |\n")
        md.append("\n## Episodes\n\n")
        md.append("| difficulty | episodes | successes | mean steps | ended by the agent |\n")
        md.append("|---|---|---|---|---|\n")
        rows = [(d, self.by_difficulty[d]) for d in DIFFICULTIES if d in self.by_difficulty]
        for name, tally in [*rows, ("all", t)]:
            md.append(
                f"| {name} | {tally.episodes} | {tally.successes} | {tally.mean_steps:.1f} | "
                f"{tally.ended_by_agent} |\n"
            )
        return "".join(md)
