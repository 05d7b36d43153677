"""The training speed of an ESRP-BC config: optimizer steps per second over a number of batches of
its demonstrations, and the epoch time that makes, without training a whole epoch.

    python tools/bc_speed.py --config configs/bc-v2-easy-cpu.toml [--batches 40] [--span N]

Each batch is read, moved to the device and trained on exactly as `esrp train bc` does (its
learning rate aside). It runs with whichever `esrp` is importable, so that an older checkout's
package (PYTHONPATH=OLD/clients/python/src) can be measured beside this one on the same store;
`--span` and the views encoded per batch need a package with span sampling. Prints one JSON line:
batches timed, seconds per batch, windows per second, the projected epoch in seconds, and the views
and goals each batch encodes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from esrp.agents.bc import DiffusionPolicy, bc_loss, schedulers
from esrp.train.bc import DemoWindows, load_config


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, required=True, help="a training config ([bc] table)")
    parser.add_argument("--batches", type=int, default=40, help="batches timed (default 40)")
    parser.add_argument("--warmup", type=int, default=3, help="batches run first, not timed (default 3)")
    parser.add_argument("--span", type=int, help="override the config's span (a package with spans)")
    args = parser.parse_args(argv)
    if args.batches < 1 or args.warmup < 0:
        parser.error("--batches must be at least 1 and --warmup 0 or more")
    config = load_config(args.config)
    if args.span is not None:
        if not hasattr(config, "span"):
            parser.error("--span: this package samples no spans")
        config = dataclasses.replace(config, span=args.span)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    windows = DemoWindows(
        config.demos, config.n_obs, config.horizon, in_memory=config.in_memory, progress=True
    )
    model = DiffusionPolicy(config)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    scheduler, _ = schedulers(config)
    spans = hasattr(windows, "epoch_order")
    order = (
        windows.epoch_order(config.seed, config.span)
        if spans
        else np.random.default_rng(config.seed).permutation(len(windows))
    )
    needed = (args.warmup + args.batches) * config.batch_size
    if needed > len(order):
        parser.error(
            f"{args.warmup + args.batches} batches of {config.batch_size} exceed the store's "
            f"{len(order)} steps"
        )
    encoded: list[tuple[int, int]] = []
    started = 0.0
    for i in range(args.warmup + args.batches):
        if i == args.warmup:
            started = time.perf_counter()
        batch = windows.batch(np.sort(order[i * config.batch_size : (i + 1) * config.batch_size]))
        if spans:
            encoded.append((len(batch["frames"]), len(batch["goals"])))
        loss, _, _ = bc_loss(model, scheduler, batch)
        optimizer.zero_grad()
        loss.backward()  # type: ignore[no-untyped-call]
        optimizer.step()
    seconds = (time.perf_counter() - started) / args.batches
    batches_per_epoch = -(-len(windows) // config.batch_size)
    views, goals = (
        np.mean(encoded, axis=0).tolist()
        if encoded
        else (config.n_obs * config.batch_size, config.batch_size)
    )
    print(
        json.dumps(
            {
                "config": str(args.config),
                "span": getattr(config, "span", None),
                "batches": args.batches,
                "batch_size": config.batch_size,
                "seconds_per_batch": round(seconds, 4),
                "windows_per_second": round(config.batch_size / seconds, 1),
                "epoch_seconds": round(seconds * batches_per_epoch, 1),
                "views_encoded_per_batch": round(views, 1),
                "goals_encoded_per_batch": round(goals, 1),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
