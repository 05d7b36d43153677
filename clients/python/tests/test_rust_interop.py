"""The Python and Rust evaluation tools share one schema (docs/evaluation.md): Python reads the Rust
`esrp-eval`'s files and computes the same summary; the Rust tool resumes a file Python wrote and
summarises it to the same numbers.

The Rust binary comes from `ESRP_EVAL_BIN`, else the checkout's `target/{release,debug}` (or
`CARGO_TARGET_DIR`'s); `scripts/python-tests.sh` builds it, so CI always runs these tests.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

import esrp
from esrp.cli import main
from esrp.eval.replay import replay_record
from esrp.eval.results import Summary, read_records

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
