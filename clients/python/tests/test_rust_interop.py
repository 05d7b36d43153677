"""The Python and Rust evaluation tools share one schema (docs/evaluation.md): Python reads the Rust
`esrp-eval`'s files and computes the same summary; the Rust tool resumes a file Python wrote and
summarises it to the same numbers.

The Rust binary comes from `ESRP_EVAL_BIN`, else the checkout's `target/{release,debug}` (or
`CARGO_TARGET_DIR`'s); `scripts/python-tests.sh` builds it, so CI always runs these tests.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any

import pytest

import esrp
from esrp.cli import main
from esrp.eval.replay import replay_record
from esrp.eval.results import ResultsError, Summary, read_records

REPOSITORY = Path(__file__).resolve().parents[3]


def rust_eval_binary() -> Path | None:
    variable = os.environ.get("ESRP_EVAL_BIN")
    if variable:
        return Path(variable)
    targets = [Path(os.environ["CARGO_TARGET_DIR"])] if os.environ.get("CARGO_TARGET_DIR") else []
    targets.append(REPOSITORY / "target")
    for target in targets:
        for profile in ("release", "debug"):
            candidate = target / profile / "esrp-eval"
            if candidate.is_file():
                return candidate
    return None


@pytest.fixture(scope="module")
def rust_eval() -> Path:
    binary = rust_eval_binary()
    if binary is None:
        pytest.skip(
            "no Rust esrp-eval: set ESRP_EVAL_BIN or `cargo build -p esrp-client --bin esrp-eval` "
            "(scripts/python-tests.sh builds it)"
        )
    assert binary.is_file(), f"ESRP_EVAL_BIN={binary} is not a file"
    return binary


def tables(markdown: str) -> str:
    """A summary without its closing line (which names the tool and the time)."""
    return markdown.split("\nWritten by ")[0]


def run_rust(binary: Path, server: esrp.LocalServer, *args: str) -> None:
    command = [str(binary), *args, "--server", f"http://{server.address}"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr


def test_python_reads_the_rust_tools_files(
    rust_eval: Path, server: esrp.LocalServer, client: esrp.Client, tmp_path: Path, easy_scenes: list[str]
) -> None:
    scenes = ",".join([*easy_scenes[:2], next(client.scenes("test", "medium")).id])
    for agent in ("random", "expert"):
        out = tmp_path / f"rust-{agent}.jsonl"
        run_rust(rust_eval, server, "--agent", agent, "--scenes", scenes, "--seed", "9", "--out", str(out))
        read = read_records(out)
        assert not read.torn_tail
        records = read.records
        assert sorted(r.scene_id for r in records) == sorted(scenes.split(","))
        assert all(r.client.startswith("esrp-eval ") and r.agent == agent for r in records)
        python_summary = Summary.of(records).markdown(f"{agent} on esrp-bench-v2 (test split)")
        assert tables(python_summary) == tables(out.with_suffix(".md").read_text())
        # The Rust tool's records replay on the server with the Python client.
        replay_record(client, records[0], every_frame=False)


def test_the_rust_tool_resumes_and_summarises_a_python_file(
    rust_eval: Path, server: esrp.LocalServer, tmp_path: Path, easy_scenes: list[str]
) -> None:
    scenes = ",".join(easy_scenes[:3])
    out = tmp_path / "python-plan.jsonl"
    assert (
        main(["eval", "--agent", "plan", "--scenes", scenes, "--out", str(out), "--server", server.address])
        == 0
    )
    written = out.read_bytes()
    python_summary = out.with_suffix(".md").read_text()
    rust_summary = tmp_path / "rust-summary.md"
    # Every scene is in the file already: the Rust tool reads it, plays nothing, and summarises it.
    run_rust(
        rust_eval,
        server,
        "--agent",
        "plan",
        "--scenes",
        scenes,
        "--out",
        str(out),
        "--summary",
        str(rust_summary),
    )
    assert out.read_bytes() == written
    assert tables(rust_summary.read_text()) == tables(python_summary)


def test_both_tools_write_the_members_of_agent_stats_in_one_order(
    rust_eval: Path, server: esrp.LocalServer, tmp_path: Path, easy_scenes: list[str]
) -> None:
    """esrp-eval writes the plan agent's stats sorted by name (serde_json's maps); esrp eval wrote
    them in the order it built them (plan_calls, nodes_expanded...), so the same stats were other
    bytes in the two tools' files. Both write them sorted now, and the agent's config alike."""
    scene = easy_scenes[0]
    rust, python = tmp_path / "rust-plan.jsonl", tmp_path / "python-plan.jsonl"
    run_rust(rust_eval, server, "--agent", "plan", "--scenes", scene, "--out", str(rust))
    args = ["eval", "--agent", "plan", "--scenes", scene, "--out", str(python), "--server", server.address]
    assert main(args) == 0

    def members(path: Path, name: str) -> list[str]:
        line: dict[str, Any] = json.loads(path.read_text().splitlines()[0])
        return list(line[name])

    assert members(rust, "agent_stats") == sorted(members(rust, "agent_stats"))
    assert members(python, "agent_stats") == members(rust, "agent_stats")
    assert members(python, "agent_config") == members(rust, "agent_config")
    config = '"agent_config":{"budget_ms":'
    assert config in rust.read_text()
    assert config in python.read_text()


def rust_refuses(binary: Path, server: esrp.LocalServer, *args: str) -> str:
    """Runs the Rust tool, which must refuse (exit status 1); returns its last line on stderr."""
    command = [str(binary), *args, "--server", f"http://{server.address}"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 1, done.stderr
    return done.stderr.strip().splitlines()[-1]


def test_neither_tool_resumes_a_file_of_another_run(
    rust_eval: Path,
    server: esrp.LocalServer,
    tmp_path: Path,
    easy_scenes: list[str],
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Each tool resumed the other's random file, whose actions come from another generator for the
    same seed, and esrp-eval a file of another --seed, or of privileged episodes (Python's mark,
    which it did not read): one file of two runs, which neither tool reproduces."""
    one, two = easy_scenes[:2]
    again = "write to another --out, or pass --fresh to start it over"
    rust = tmp_path / "rust-random.jsonl"
    run_rust(rust_eval, server, "--agent", "random", "--scenes", one, "--seed", "9", "--out", str(rust))
    python = tmp_path / "python-random.jsonl"
    common = [
        "eval",
        "--agent",
        "random",
        "--seed",
        "9",
        "--scenes",
        f"{one},{two}",
        "--server",
        server.address,
    ]
    assert main([*common, "--out", str(python), "--scenes", one]) == 0
    privileged = tmp_path / "python-privileged.jsonl"
    assert main([*common, "--out", str(privileged), "--scenes", one, "--privileged"]) == 0
    files = {path: path.read_bytes() for path in (rust, python, privileged)}
    capsys.readouterr()

    assert main([*common, "--out", str(rust)]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"esrp eval: {rust} holds results of agent 'random' written by esrp-eval 0.1.0, whose random "
        f"numbers differ from esrp eval (Python)'s for the same seed: {again}"
    )
    rust_args = ["--agent", "random", "--scenes", f"{one},{two}", "--seed", "9", "--out"]
    assert rust_refuses(rust_eval, server, *rust_args, str(python)) == (
        f'esrp-eval: {python} holds results of agent "random" written by esrp eval (Python) 0.1.0, whose '
        f"random numbers differ from esrp-eval's for the same seed: {again}"
    )
    assert rust_refuses(rust_eval, server, *rust_args, str(privileged)) == (
        f'esrp-eval: {privileged} holds results of agent "random" played privileged (esrp eval (Python) '
        f"0.1.0), unlike this run: {again}"
    )
    other_seed = ["--agent", "random", "--scenes", f"{one},{two}", "--seed", "10", "--out", str(rust)]
    assert rust_refuses(rust_eval, server, *other_seed) == (
        f'esrp-eval: {rust} holds results of agent "random" played with --seed 9, not 10: {again}'
    )
    assert {path: path.read_bytes() for path in files} == files
    # The same run resumes, as before.
    run_rust(rust_eval, server, *rust_args, str(rust))
    assert len(read_records(rust).records) == 2


def test_both_tools_refuse_the_same_lines_and_cut_off_only_a_record_cut_short(
    rust_eval: Path, server: esrp.LocalServer, tmp_path: Path, easy_scenes: list[str]
) -> None:
    """What one reader took for a record the other refused (NaN, a negative count, an action code
    6); a one-line JSON file without its newline, given as --out, was cut off by both tools as if
    an interruption had torn it, and so lost. Each is now refused by both, naming FILE:LINE, and the
    file is left as it is; a record cut short is still dropped and the run resumed."""
    from test_results import NOT_RECORDS, with_value

    scene = easy_scenes[0]
    good = tmp_path / "good.jsonl"
    run_rust(rust_eval, server, "--agent", "random", "--scenes", scene, "--seed", "9", "--out", str(good))
    line = good.read_text()
    args = ["--agent", "random", "--scenes", scene, "--seed", "9", "--out"]
    for k, (name, raw, _) in enumerate(NOT_RECORDS):
        bad = tmp_path / f"bad{k}.jsonl"
        bad.write_text(with_value(line, name, raw) + "\n" + line)
        with pytest.raises(ResultsError, match=f"^{bad}:1: "):
            read_records(bad)
        assert rust_refuses(rust_eval, server, *args, str(bad)).startswith(
            f"esrp-eval: {bad}:1: not an esrp.results/v1 record: "
        ), raw
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"learning_rate": 0.001, "epochs": 100}))
    written = config.read_bytes()
    assert rust_refuses(rust_eval, server, *args, str(config)).startswith(
        f"esrp-eval: {config}:1: not an esrp.results/v1 record: "
    )
    assert config.read_bytes() == written
    cut = tmp_path / "cut.jsonl"
    cut.write_text(line[: len(line) // 2])
    run_rust(rust_eval, server, *args, str(cut))
    assert [r.scene_id for r in read_records(cut).records] == [scene]
