"""The quickstart notebook (examples/quickstart.ipynb) runs top to bottom in a real Jupyter kernel
against the server binary this suite uses: no cell raises, and what it shows holds (the planner's
plan solves the scene, the server stops)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat", reason="the test extra's notebook packages are not installed")
nbclient = pytest.importorskip("nbclient", reason="the test extra's notebook packages are not installed")

NOTEBOOK = Path(__file__).resolve().parents[1] / "examples" / "quickstart.ipynb"


def test_the_quickstart_notebook_runs(tmp_path: Path) -> None:
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    # The kernel inherits this process's environment: ESRP_SERVER_BIN names the server it starts.
    client = nbclient.NotebookClient(
        notebook, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()  # raises CellExecutionError, with the cell and its traceback, if a cell fails
    printed = "".join(
        output.get("text", "")
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.outputs
        if output.output_type == "stream" and output.name == "stdout"
    )
    assert "esrp-bench-v2" in printed
    # What its text says of the benchmark is what the server lists: the scenes of each split, and
    # the movable objects of each difficulty.
    listed = re.findall(
        r"^(\w+): (\d+) scenes; movable objects by difficulty: easy (\S+), medium (\S+), hard (\S+)$",
        printed,
        re.MULTILINE,
    )
    assert [split for split, *_ in listed] == ["train", "test"]
    text = "".join("".join(cell.source) for cell in notebook.cells if cell.cell_type == "markdown")
    total = sum(int(count) for _, count, *_ in listed)
    assert f"{total:,} scene pairs (a start and a goal layout) in two splits, train and test" in text
    for _, _, easy, medium, hard in listed:
        assert f"(Easy: {easy} movable object, Medium: {medium}, Hard: {hard})" in text
    assert "success: True" in printed
    assert "server stopped" in printed
    images = [
        output
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.outputs
        if "image/png" in output.get("data", {})
    ]
    assert len(images) == 2  # the first views, and the view when the plan solved the scene
