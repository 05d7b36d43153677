"""What the learning-curve tools (bc_curve.py, dagger_curve.py, ppo_curve.py) draw alike: success
rates with their 95 % Wilson intervals, and the figure written to its PNG."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from esrp.eval.results import wilson

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def success_errorbar(
    axis: Axes, points: Sequence[tuple[float, int, int]], label: str, marker: str = "o"
) -> None:
    """Draws success rates in % at `points` (x, successes, episodes), each with its 95 % Wilson
    interval as error bars."""
    sr = [100 * successes / episodes for _, successes, episodes in points]
    intervals = [wilson(successes, episodes) for _, successes, episodes in points]
    low = [v - 100 * lo for v, (lo, _) in zip(sr, intervals, strict=True)]
    high = [100 * hi - v for v, (_, hi) in zip(sr, intervals, strict=True)]
    axis.errorbar([x for x, _, _ in points], sr, yerr=[low, high], marker=marker, capsize=4, label=label)


def save(figure: Figure, out: Path) -> None:
    """Lays `figure` out and writes it to the PNG `out` (its folder made if missing)."""
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=110)
