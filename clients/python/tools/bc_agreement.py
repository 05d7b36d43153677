"""How well an ESRP-BC policy predicts a demonstration store's labels, teacher-forced: at states
sampled from the store, the policy's chunk (denoised afresh from its views, as an agent's first
request there would be) against the store's targets, the very windows its training learns (the
demonstrator's next actions, or a DAgger store's planner chunk from that state).

    python clients/python/tools/bc_agreement.py docs/results/checkpoints/bc-v2-easy-plan-e70.pt \\
        clients/python/demos/v2-easy-64-plan.zarr --states 256

Prints, with 95 % Wilson intervals: how often the chunk's first action is the label, and how
often its first `n_execute` actions all are (positions without a label count as agreeing), over
all the states and apart for those where the agent is empty-handed and holding an object. A
policy that fits its own training store poorly cannot be imitating it; one that agrees on the
demonstrations but not on DAgger states has not learned the states it visits.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from esrp.agents.bc import denoise_actions, load_policy, schedulers
from esrp.eval.results import wilson
from esrp.train.bc import DemoWindows


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoint", type=Path, help="an ESRP-BC checkpoint (for playing or resumable)")
    parser.add_argument("store", type=Path, help="an esrp.demos/v1 store at the policy's resolution")
    parser.add_argument("--states", type=int, default=256, help="states sampled (default 256)")
    parser.add_argument("--seed", type=int, default=0, help="the sample's and the noise's seed")
    parser.add_argument("--batch", type=int, default=64, help="states denoised at once (default 64)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args()
    if args.states < 1 or args.batch < 1:
        parser.error("--states and --batch must be at least 1")
    torch.set_num_threads(args.threads)
    try:
        model = load_policy(args.checkpoint)
        windows = DemoWindows([args.store], model.config.n_obs, model.config.horizon)
    except (OSError, ValueError) as error:
        print(f"bc_agreement: {error}", file=sys.stderr)
        return 2
    config = model.config
    _, scheduler = schedulers(config)
    count = min(args.states, len(windows))
    steps = np.sort(np.random.default_rng(args.seed).choice(len(windows), size=count, replace=False))
    generator = torch.Generator().manual_seed(args.seed)
    first, chunk, holding = (np.zeros(count, dtype=bool) for _ in range(3))
    with torch.no_grad():
        for start in range(0, count, args.batch):
            batch = windows.batch(steps[start : start + args.batch])
            cond = model.condition_indexed(
                batch["frames"], batch["frame_index"], batch["goals"], batch["goal_index"], batch["grasping"]
            )
            sampled = denoise_actions(model, scheduler, cond, generator).numpy()
            targets, mask = batch["actions"].numpy(), batch["mask"].numpy()
            done = slice(start, start + len(sampled))
            first[done] = sampled[:, 0] == targets[:, 0]
            chunk[done] = ((sampled == targets) | ~mask)[:, : config.n_execute].all(axis=1)
            holding[done] = batch["grasping"][:, -1].numpy()
    parts = (("all", np.ones(count, dtype=bool)), ("empty-handed", ~holding), ("holding", holding))
    for part, where in parts:
        states = int(where.sum())
        for name, hits in (("first action", first), (f"first {config.n_execute} actions", chunk)):
            agreeing = int(hits[where].sum())
            low, high = wilson(agreeing, states)
            interval = f"{100 * low:.1f}-{100 * high:.1f}"
            rate = 100 * agreeing / states if states else 0.0
            print(f"{part:>12} {name:>18}: {rate:5.1f} % agree ({interval}), {states} states")
    return 0


if __name__ == "__main__":
    sys.exit(main())
