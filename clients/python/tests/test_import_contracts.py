"""The import contracts (`[tool.importlinter]` in pyproject.toml) hold on the package, and each one
fails on a violation put in on purpose: a copy of the source with one planted import, checked by
import-linter itself."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("importlinter")

PACKAGE = Path(__file__).resolve().parents[1]

# (the contract's name, the module that gets the planted import, the import)
PLANTED = [
    (
        "envs, eval, integrations use the public client",
        "esrp/envs/single.py",
        "import esrp._convert",
    ),
    (
        "envs, eval, integrations use the public client",
        "esrp/integrations/sb3.py",
        "import esrp.v1.esrp_pb2",
    ),
    ("the client core imports nothing from esrp.envs", "esrp/_values.py", "import esrp.eval.results"),
    ("the client core imports nothing from esrp.envs", "esrp/_client.py", "import esrp.integrations.sb3"),
    (
        "esrp.train may import esrp.agents, never the reverse",
        "esrp/agents/encoders.py",
        "import esrp.train._config",
    ),
]


def lint_imports(source: Path) -> subprocess.CompletedProcess[str]:
    """import-linter over the package found in `source`, with the project's contracts."""
    code = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    env = {**os.environ, "PYTHONPATH": str(source)}
    return subprocess.run(
        [sys.executable, "-c", code, "--config", str(PACKAGE / "pyproject.toml"), "--no-cache"],
        cwd=source,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_the_contracts_hold() -> None:
    result = lint_imports(PACKAGE / "src")
    assert result.returncode == 0, result.stdout + result.stderr
    contracts = len({name for name, _, _ in PLANTED})
    assert f"Contracts: {contracts} kept, 0 broken." in result.stdout, result.stdout


@pytest.mark.parametrize(("contract", "module", "planted"), PLANTED)
def test_each_contract_fails_on_a_planted_import(
    tmp_path: Path, contract: str, module: str, planted: str
) -> None:
    shutil.copytree(PACKAGE / "src" / "esrp", tmp_path / "esrp")
    path = tmp_path / module
    path.write_text(path.read_text() + f"\n{planted}  # planted by the test\n")
    result = lint_imports(tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    broken = [line for line in result.stdout.splitlines() if line.endswith(" BROKEN")]
    assert len(broken) == 1, result.stdout
    assert broken[0].startswith(contract), result.stdout
