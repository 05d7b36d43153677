"""ESRP-BC against ESRP-BC + DAgger, iteration by iteration, from an `esrp train bc --dagger` run:
the held-out success rate (with its 95 % Wilson interval) after each iteration (iteration 0 is the
BC policy the run started from), and, where given, the test-split success rate of evaluated
iterations; beside it, how often the policy already chose the planner's label in each
iteration's roll-outs, and the DAgger states collected.

    python clients/python/tools/dagger_curve.py runs/bc-dagger-v2-easy \\
        --test 0=docs/results/bc-v2.jsonl.gz --test 3=docs/results/bc-dagger-v2.jsonl.gz \\
        --out docs/images/bc-dagger-v2-easy.png

Reads `RUN/dagger.csv` (`--log` names another file); `--test ITERATION=RESULTS` takes an
esrp.results/v1 file (JSON Lines, gzip or not) of that iteration's policy.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from _curves import save, success_errorbar

from esrp.eval.results import read_records


def successes(path: Path) -> tuple[int, int]:
    """The successes and the episodes of esrp.results/v1 file `path` (gzip-compressed or not)."""
    records = read_records(path).records
    return sum(r.success for r in records), len(records)


def test_point(text: str) -> tuple[int, Path]:
    """`ITERATION=RESULTS` of `--test`."""
    iteration, separator, path = text.partition("=")
    if not separator or not iteration.isdigit() or not path:
        raise argparse.ArgumentTypeError(f"--test wants ITERATION=RESULTS, not {text!r}")
    return int(iteration), Path(path)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run", type=Path, help="the run folder of esrp train bc --dagger")
    parser.add_argument("--log", type=Path, help="the iterations' log (default RUN/dagger.csv)")
    parser.add_argument(
        "--test",
        type=test_point,
        action="append",
        default=[],
        metavar="ITERATION=RESULTS",
        help="test-split results of an iteration's policy (repeatable)",
    )
    parser.add_argument("--title", default=None, help="the figure's title (default: the run's name)")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args()
    log_path = args.log or args.run / "dagger.csv"
    if not log_path.is_file():
        print(f"dagger_curve: no {log_path}: not an esrp train bc --dagger run", file=sys.stderr)
        return 2
    with open(log_path, newline="") as file:
        lines = list(csv.DictReader(file))
    if not lines:
        print(f"dagger_curve: {log_path} has no iteration yet", file=sys.stderr)
        return 2
    tests: list[tuple[int, int, int]] = []
    for iteration, path in args.test:
        if not path.is_file():
            print(f"dagger_curve: no {path}", file=sys.stderr)
            return 2
        tests.append((iteration, *successes(path)))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    figure, (sr_axis, agreement_axis) = plt.subplots(1, 2, figsize=(11, 4))
    at = [int(r["iteration"]) for r in lines]

    held_out = [
        (int(r["iteration"]), round(float(r["sr"]) * int(r["eval_episodes"])), int(r["eval_episodes"]))
        for r in lines
    ]
    success_errorbar(sr_axis, held_out, f"held-out train scenes ({lines[-1]['eval_episodes']})", "o")
    if tests:
        success_errorbar(sr_axis, sorted(tests), f"test split ({tests[0][2]} scenes)", "s")
    sr_axis.set_xlabel("DAgger iteration (0: the BC policy)")
    sr_axis.set_ylabel("success rate, % (95 % Wilson interval)")
    sr_axis.set_ylim(bottom=0)
    sr_axis.legend(loc="best")
    sr_axis.grid(alpha=0.3)

    rolled = [r for r in lines if r["agreement"]]
    if rolled:
        agreement_axis.plot(
            [int(r["iteration"]) for r in rolled],
            [100 * float(r["agreement"]) for r in rolled],
            marker="o",
            color="tab:green",
            label="policy's action = planner's label",
        )
    agreement_axis.set_xlabel("DAgger iteration")
    agreement_axis.set_ylabel("agreement in the roll-outs, %")
    agreement_axis.set_ylim(0, 100)
    agreement_axis.grid(alpha=0.3)
    states = agreement_axis.twinx()
    states.bar(
        at,
        [int(r["steps"]) if int(r["iteration"]) else 0 for r in lines],
        width=0.5,
        alpha=0.25,
        color="tab:gray",
        label="DAgger states labelled",
    )
    states.set_ylabel("states labelled by the planner")
    agreement_axis.set_zorder(states.get_zorder() + 1)  # the line over the bars
    agreement_axis.patch.set_visible(False)
    handles = agreement_axis.get_legend_handles_labels()
    more = states.get_legend_handles_labels()
    agreement_axis.legend(handles[0] + more[0], handles[1] + more[1], loc="upper left")
    for axis in (sr_axis, agreement_axis):
        axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    figure.suptitle(args.title or args.run.name)
    save(figure, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
