"""The server's scaling curves from `scripts/gpu-bench.sh` runs: steps/s against episodes (one
StepBatch of all of them) and against render threads (256 episodes), one line per run.

    python tools/scaling_plot.py --run "2-core VM, llvmpipe=/tmp/gb-gl" [--run LABEL=DIR ...] \
        --out docs/images/scaling.png

Each DIR is a gpu-bench output folder: its `episodes-N.json` and `threads-N.json`, or where a
point's JSON is absent (only the summary came back from a machine), the same figure from the
folder's `summary.md` (`scripts/gpu_bench_summary.py`'s tables "Episodes" and "Render threads").
A run without some of them (a step its budget skipped) draws what it has. Needs matplotlib.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path
from typing import Any

EPISODES = (1, 4, 16, 64, 256, 1024)
THREADS = (1, 2, 4, 8)


@functools.cache
def summary_rates(folder: Path) -> dict[tuple[str, str], float]:
    """The steps/s in `folder/summary.md`'s tables, keyed as the JSON files name them:
    (`episodes-N.json` or `threads-N.json`, scenario). Empty when there is no summary. Read once
    per folder."""
    path = folder / "summary.md"
    if not path.exists():
        return {}
    prefixes = {"## Episodes": "episodes", "## Render threads": "threads"}
    rates: dict[tuple[str, str], float] = {}
    prefix: str | None = None
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("## "):
            prefix = next((name for head, name in prefixes.items() if line.startswith(head)), None)
            continue
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        # | N | scenario | episodes | steps/s | ...: the header and the rule are not numbers.
        if prefix is None or len(cells) < 4 or not cells[0].isdigit():
            continue
        try:
            rates[(f"{prefix}-{cells[0]}.json", cells[1])] = float(cells[3].replace(",", ""))
        except ValueError:
            continue  # "–": no figure
    return rates


def rate(folder: Path, name: str, scenario: str) -> float | None:
    """The steps/s of `scenario` in `folder/name` (else in the folder's summary.md), or None when
    neither has it."""
    path = folder / name
    if not path.exists():
        return summary_rates(folder).get((name, scenario))
    report: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    for result in report.get("results", []):
        if result.get("scenario") == scenario and result.get("steps_per_second") is not None:
            return float(result["steps_per_second"])
    return None


def parse_run(text: str) -> tuple[str, Path]:
    label, separator, folder = text.rpartition("=")
    if not separator or not label:
        raise argparse.ArgumentTypeError(f"{text!r}: give LABEL=DIR")
    path = Path(folder)
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{folder}: not a folder")
    return label, path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=parse_run, action="append", required=True, metavar="LABEL=DIR")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args(argv)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("scaling_plot.py needs matplotlib (pip install matplotlib)", file=sys.stderr)
        return 2
    figure, (by_episodes, by_threads) = plt.subplots(1, 2, figsize=(11, 4))
    drawn = False
    for label, folder in args.run:
        points = [(e, rate(folder, f"episodes-{e}.json", "batch-64")) for e in EPISODES]
        xs = [e for e, r in points if r is not None]
        if xs:
            by_episodes.plot(xs, [r for _, r in points if r is not None], marker="o", label=label)
            drawn = True
        for scenario, style in (("batch-64", "-"), ("stream-mux-64", "--")):
            points = [(t, rate(folder, f"threads-{t}.json", scenario)) for t in THREADS]
            xs = [t for t, r in points if r is not None]
            if xs:
                ys = [r for _, r in points if r is not None]
                by_threads.plot(xs, ys, style, marker="o", label=f"{label}: {scenario}")
                drawn = True
    if not drawn:
        print("no gpu-bench results in the runs given", file=sys.stderr)
        return 1
    by_episodes.set(xscale="log", xlabel="episodes (one StepBatch of all)", ylabel="steps/s")
    by_episodes.set_title("Episodes")
    by_threads.set(xscale="log", xlabel="render threads", ylabel="steps/s")
    by_threads.set_title("Render threads (256 episodes)")
    by_threads.set_xticks(THREADS, [str(t) for t in THREADS])
    by_threads.minorticks_off()
    for axes in (by_episodes, by_threads):
        axes.grid(True, alpha=0.3)
        axes.set_ylim(bottom=0)
        axes.legend(fontsize=8)
    figure.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.out, dpi=110)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
