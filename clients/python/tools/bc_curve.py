"""Learning curve of an `esrp train bc` run: the training loss (and its two terms) against epochs
beside the held-out success rate (with its 95 % Wilson interval) of the checkpoints evaluated; of an
`esrp train ppo-bc` run: its cross-entropy and the accuracy of its most likely action.

    python clients/python/tools/bc_curve.py runs/bc-v2-easy --out docs/images/bc-v2-easy.png

Reads `RUN/log.csv` (one line per epoch) and `RUN/eval.csv` (one line per held-out evaluation, as
`esrp train bc` writes with `eval_every`); `--log` and `--eval` name other files. A run without
held-out evaluations gets the loss panel alone.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from _curves import save, success_errorbar


def rows(path: Path) -> list[dict[str, str]]:
    """The lines of CSV file `path` as dicts."""
    with open(path, newline="") as file:
        return list(csv.DictReader(file))


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run", type=Path, help="the run folder of esrp train bc")
    parser.add_argument("--log", type=Path, help="the per-epoch losses (default RUN/log.csv)")
    parser.add_argument("--eval", type=Path, help="the held-out evaluations (default RUN/eval.csv)")
    parser.add_argument("--title", default=None, help="the figure's title (default: the run's name)")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args()
    log_path = args.log or args.run / "log.csv"
    eval_path = args.eval or args.run / "eval.csv"
    if not log_path.is_file():
        print(f"bc_curve: no {log_path}: not an esrp train bc or ppo-bc run", file=sys.stderr)
        return 2
    losses = rows(log_path)
    evaluations = rows(eval_path) if eval_path.is_file() else []

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    panels = 2 if evaluations else 1
    figure, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 4), squeeze=False)
    epochs = [int(r["epoch"]) for r in losses]
    loss_axis = axes[0][0]
    if "accuracy" in losses[0]:  # esrp train ppo-bc: one cross-entropy, and the accuracy beside it
        loss_axis.plot(epochs, [float(r["loss"]) for r in losses], marker="o", label="cross-entropy")
        accuracy_axis = loss_axis.twinx()
        accuracy = [100 * float(r["accuracy"]) for r in losses]
        accuracy_axis.plot(epochs, accuracy, marker="s", color="tab:green", label="accuracy")
        accuracy_axis.set_ylabel("accuracy of the most likely action, %")
        # One legend, where neither curve is (they cross the middle of the left half).
        handles = loss_axis.get_legend_handles_labels()[0] + accuracy_axis.get_legend_handles_labels()[0]
        accuracy_axis.legend(handles=handles, loc="center right")
    else:
        for key, label in (("loss", "loss (MSE + λ·CE)"), ("mse", "noise MSE"), ("ce", "cross-entropy")):
            loss_axis.plot(epochs, [float(r[key]) for r in losses], marker="o", label=label)
    loss_axis.set_xlabel("epoch")
    loss_axis.set_ylabel("training loss (epoch mean)")
    if "accuracy" not in losses[0]:
        loss_axis.legend(loc="upper right")
    loss_axis.grid(alpha=0.3)
    if evaluations:
        sr_axis = axes[0][1]
        points = [
            (int(r["epoch"]), round(float(r["sr"]) * int(r["episodes"])), int(r["episodes"]))
            for r in evaluations
        ]
        success_errorbar(sr_axis, points, f"held-out SR ({evaluations[-1]['episodes']} scenes)")
        sr_axis.set_xlabel("epoch")
        sr_axis.set_ylabel("success rate, % (95 % Wilson interval)")
        sr_axis.set_ylim(bottom=0)
        sr_axis.legend(loc="upper left")
        sr_axis.grid(alpha=0.3)
    for axis in axes[0]:
        axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    figure.suptitle(args.title or args.run.name)
    save(figure, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
