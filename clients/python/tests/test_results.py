"""The results schema: records, reading with a torn last line, seeds, and the summary's text (the
Rust tool's, checked against the same expectations as clients/rust/src/results.rs)."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import pytest

from esrp.eval.results import (
    SCHEMA,
    EpisodeRecord,
    ResultsError,
    Summary,
    append_record,
    fnv1a64,
    read_records,
    scene_seed,
    truncate_to,
)


def record(scene: str, difficulty: str, success: bool, osr: float, rdr: float, stage: int) -> EpisodeRecord:
    return EpisodeRecord(
        schema=SCHEMA,
        scene_id=scene,
        dataset="d",
        split="test",
        room_type="Bedroom",
        difficulty=difficulty,
        objects=1,
        agent="random",
        agent_config={},
        seed=3,
        success=success,
        osr=osr,
        rdr=rdr,
        stage=stage,
        placed=int(success),
        steps=10,
        horizon=200,
        end="success" if success else "horizon",
        total_reward=1.5,
        actions=[0] * 10,
        wall_seconds=0.1,
        agent_stats={},
        server_version="0.1.0",
        client="test",
        finished_at="2026-11-23T00:00:00Z",
    )


def test_fnv1a64_and_scene_seeds() -> None:
    assert fnv1a64("") == 0xCBF29CE484222325
    assert fnv1a64("a") == 0xAF63DC4C8601EC8C
    assert fnv1a64("foobar") == 0x85944171F73967E8
    assert scene_seed(0, "a") == fnv1a64("a")
    assert scene_seed(7, "a") == 7 ^ fnv1a64("a")
    assert scene_seed(-1, "a") == ((1 << 64) - 1) ^ fnv1a64("a")


def test_summary_means_by_difficulty() -> None:
    records = [
        record("a", "easy", True, 1.0, 0.0, 4),
        record("b", "easy", False, 0.0, 1.0, 3),
        record("c", "hard", False, 0.5, 0.5, 1),
    ]
    summary = Summary.of(records)
    assert summary.overall.episodes == 3
    assert summary.overall.sr == pytest.approx(1 / 3)
    assert summary.overall.osr == pytest.approx(0.5)
    assert summary.by_difficulty["easy"].successes == 1
    assert summary.by_difficulty["hard"].rdr == pytest.approx(0.5)
    assert summary.overall.stages == [1, 0, 1, 1]
    md = summary.markdown("random")
    row = "| **random** (this run) | 33.33 / 50.00 / 0.5000 | 50.00 / 50.00 / 0.5000 | – |"
    assert row + " 0.00 / 50.00 / 0.5000 |" in md
    assert "| ESRP-PLAN (paper) | 30.20 / 36.59 / 0.6916 |" in md
    assert "| **random** (this run) | 33.33 | 0.00 | 33.33 | 33.33 |" in md
    assert "| all | 3 | 1 | 10.0 | 0 |" in md
    assert summary.text().startswith("overall  SR  33.33 %  OSR  50.00 %  RDR 0.5000")


def test_a_summary_of_no_records_says_so() -> None:
    """A run whose episodes all failed wrote `**** (this run)` and `SR NaN %`."""
    summary = Summary.of([], "my_agents:make")
    assert summary.agent == "my_agents:make"
    assert summary.text() == "no episodes recorded: no SR, OSR or RDR to give\n"
    md = summary.markdown("my_agents:make on esrp-bench-v1 (test split)")
    assert "No episodes recorded for **my_agents:make**" in md
    assert "NaN" not in md
    assert "****" not in md
    assert "**?**" in Summary.of([]).markdown("x")  # no name at all


def test_round_trip_and_a_torn_last_line(tmp_path: Path) -> None:
    path = tmp_path / "r.jsonl"
    with open(path, "wb") as file:
        append_record(file, record("a", "easy", True, 1.0, 0.0, 4))
        append_record(file, record("b", "easy", True, 1.0, 0.0, 4))
    whole = path.stat().st_size
    with open(path, "ab") as file:
        file.write(b'{"schema":"esrp.results/v1","scene_id":"c"')
    read = read_records(path)
    assert [r.scene_id for r in read.records] == ["a", "b"]
    assert read.torn_tail
    assert read.complete_bytes == whole
    truncate_to(path, read.complete_bytes)
    again = read_records(path)
    assert (len(again.records), again.torn_tail) == (2, False)
    assert again.records[1] == record("b", "easy", True, 1.0, 0.0, 4)
    # Field order and types as docs/evaluation.md lists them.
    line = json.loads(path.read_text().splitlines()[0])
    assert list(line)[:3] == ["schema", "scene_id", "dataset"]
    assert list(line)[-1] == "finished_at"


def test_agent_stats_and_configs_are_written_with_their_members_sorted(tmp_path: Path) -> None:
    """The Rust tools (serde_json's maps) write every object's members sorted by name; the Python
    writer kept `agent_stats` and `agent_config` in the order the agent gave them, so the same
    stats were other bytes in the two tools' files. Both are written sorted now, at every depth
    (objects in lists too); lists keep their order, and the record itself is left as it was."""
    stats = {"zeta": 1, "alpha": {"b": [{"y": 1, "x": 2}, 3], "a": None}, "mid": (2, 1)}
    config = {"turns": 3, "budget_ms": 50}
    mine = record("a", "easy", True, 1.0, 0.0, 4)
    mine.agent_stats, mine.agent_config = stats, config
    line = mine.to_json()
    assert '"agent_config":{"budget_ms":50,"turns":3},' in line
    assert '"agent_stats":{"alpha":{"a":null,"b":[{"x":2,"y":1},3]},"mid":[2,1],"zeta":1},' in line
    # What serde_json writes: the members sorted, compact.
    compact = json.dumps(stats, sort_keys=True, separators=(",", ":"))
    assert f'"agent_stats":{compact},' in line
    assert list(mine.agent_stats) == ["zeta", "alpha", "mid"]  # the record is not changed
    path = tmp_path / "r.jsonl"
    with open(path, "wb") as file:
        append_record(file, mine)
    again = read_records(path).records[0]
    assert again.agent_stats == {**stats, "mid": [2, 1]}
    assert again.agent_config == config
    assert again.to_json() == line


def test_a_gzip_file_reads_as_its_plain_twin(tmp_path: Path) -> None:
    """docs/results keeps its records as .jsonl.gz: the readers take them as they are."""
    plain = tmp_path / "r.jsonl"
    with open(plain, "wb") as file:
        for name in ("a", "b"):
            append_record(file, record(name, "easy", True, 1.0, 0.0, 4))
        file.write(b'{"schema":"esrp.results/v1","scene_id":"c"')  # cut short
    packed = tmp_path / "r.jsonl.gz"
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    one, other = read_records(plain), read_records(packed)
    assert (one.compressed, other.compressed) == (False, True)
    assert other.records == one.records
    assert other.lines == one.lines  # what a signature covers: the decompressed line's bytes
    assert (other.line_numbers, other.complete_bytes) == (one.line_numbers, one.complete_bytes)
    assert (other.torn_tail, other.torn_line, other.torn_whole) == (True, 3, False)
    # A file of several gzip members (cat a.gz b.gz) is read whole, as gunzip reads it.
    packed.write_bytes(gzip.compress(b"\n") + gzip.compress(plain.read_bytes()))
    assert read_records(packed).records == one.records
    broken = tmp_path / "broken.jsonl.gz"
    broken.write_bytes(gzip.compress(plain.read_bytes())[:-12])
    with pytest.raises(ResultsError, match=r"broken.jsonl.gz: a gzip file that does not decompress: "):
        read_records(broken)


def test_a_complete_record_without_its_newline_is_torn(tmp_path: Path) -> None:
    path = tmp_path / "r.jsonl"
    path.write_text(record("a", "easy", True, 1.0, 0.0, 4).to_json())
    read = read_records(path)
    assert read.records == []
    assert read.torn_tail
    assert read.complete_bytes == 0


def test_bad_lines_and_unknown_fields(tmp_path: Path) -> None:
    path = tmp_path / "r.jsonl"
    good = record("a", "easy", True, 1.0, 0.0, 4).to_json()
    path.write_text("not json\n" + good + "\n")
    with pytest.raises(ResultsError, match=":1: not an esrp.results/v1 record"):
        read_records(path)
    wrong = json.loads(good) | {"schema": "esrp.results/v2"}
    path.write_text(json.dumps(wrong) + "\n" + good + "\n")
    with pytest.raises(ResultsError, match="schema"):
        read_records(path)
    missing = json.loads(good)
    del missing["rdr"]
    path.write_text(json.dumps(missing) + "\n" + good + "\n")
    with pytest.raises(ResultsError, match="rdr"):
        read_records(path)
    # Readers ignore fields they do not know; integers are numbers too.
    extra = json.loads(good) | {"later_field": [1, 2], "osr": 1}
    path.write_text(json.dumps(extra) + "\n")
    (only,) = read_records(path).records
    assert only.osr == 1.0


# Values every reader refuses, the Rust tools' too (test_rust_interop.py): (field, its value as
# the line writes it, what the error says). Python's json read the first ones (NaN, Infinity),
# and the Python reader the out-of-range integers, which the Rust reader refuses.
NOT_RECORDS = [
    ("rdr", "NaN", "NaN is not a JSON number"),
    ("agent_stats", '{"loss":-Infinity}', "-Infinity is not a JSON number"),
    ("steps", "-10", "field 'steps' is -10, not an integer 0..4294967295"),
    ("objects", "4294967296", "field 'objects' is 4294967296"),
    ("seed", "18446744073709551616", "field 'seed' is 18446744073709551616"),
    ("seed", "-1", "field 'seed' is -1, not an integer 0..18446744073709551615"),
    ("actions", "[0,6]", "action codes 0..5"),
]


def with_value(line: str, name: str, raw: str) -> str:
    """`line` (a record's JSON) with field `name` set to `raw`, as written (`NaN` included)."""
    data = json.loads(line)
    data[name] = "@VALUE@"
    return json.dumps(data, separators=(",", ":")).replace('"@VALUE@"', raw)


def test_numbers_json_has_not_and_integers_out_of_range_are_refused(tmp_path: Path) -> None:
    good = record("a", "easy", False, 0.0, 0.0, 1).to_json()
    path = tmp_path / "r.jsonl"
    for name, raw, why in NOT_RECORDS:
        path.write_text(with_value(good, name, raw) + "\n" + good + "\n")
        with pytest.raises(ResultsError, match=":1: not an esrp.results/v1 record: ") as error:
            read_records(path)
        assert why in str(error.value), (raw, str(error.value))
    # The largest values are records.
    path.write_text(with_value(with_value(good, "seed", str(2**64 - 1)), "steps", str(2**32 - 1)) + "\n")
    (only,) = read_records(path).records
    assert (only.seed, only.steps) == (2**64 - 1, 2**32 - 1)


def test_lines_that_are_not_objects_and_what_a_dropped_last_line_was(tmp_path: Path) -> None:
    """A line of JSON that is not an object (`[1]`, `3`) is a bad line like any other (it raised
    AttributeError); a dropped last line says why it was dropped and whether it was whole."""
    path = tmp_path / "r.jsonl"
    good = record("a", "easy", True, 1.0, 0.0, 4).to_json()
    for other in ("[1]", "3", "null"):
        path.write_text(other + "\n" + good + "\n")
        with pytest.raises(ResultsError, match=":1: not an esrp.results/v1 record: a JSON"):
            read_records(path)
    path.write_text(good + "\n[1]\n")
    read = read_records(path)
    assert (len(read.records), read.torn_tail, read.torn_line, read.torn_whole) == (1, True, 2, True)
    assert read.torn_note("r.jsonl") == (
        "r.jsonl:2: its last line is not an esrp.results/v1 record (a JSON list, not an object)"
    )
    path.write_text(good + "\n" + good)
    read = read_records(path)
    assert (read.torn_line, read.torn_whole) == (2, False)
    assert read.torn_note("r.jsonl") == "r.jsonl:2: its last line is cut short (no newline)"
    path.write_text(good + "\n")
    assert read_records(path).torn_note("r.jsonl") == ""


def test_a_server_record_keeps_its_own_fields(tmp_path: Path) -> None:
    """A server's record (docs/evaluation.md: `token`, `started_at`, `dataset_hash`, `counted`)
    reads as any record; its extra fields are kept and written back after the schema's."""
    server_fields = {
        "token": "team-a",
        "started_at": "2026-11-23T19:39:58Z",
        "dataset_hash": "0123456789abcdef",
        "counted": True,
    }
    line = json.loads(record("challenge/00012", "easy", True, 1.0, 0.0, 4).to_json())
    line |= {"split": "challenge", "agent": "unnamed", "seed": None, "client": "esrp-server 0.2.0"}
    path = tmp_path / "team-a.jsonl"
    path.write_text(json.dumps(line | server_fields) + "\n")
    (read,) = read_records(path).records
    assert (read.scene_id, read.split, read.seed) == ("challenge/00012", "challenge", None)
    assert read.extra == server_fields
    written = json.loads(read.to_json())
    assert written == line | server_fields
    assert list(written)[-5:] == ["finished_at", "token", "started_at", "dataset_hash", "counted"]
    assert record("a", "easy", True, 1.0, 0.0, 4).extra == {}
