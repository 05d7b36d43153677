"""How fast the environment of an `esrp train ppo` config runs alone: its vector env (the config's
scenes, episodes in parallel, resolution, horizon and reward: `esrp.train.ppo.make_env`) stepped
with uniform random actions and no network, against which a training run's steps per second (its
`log.csv`) says how much of the time the learner takes.

    python clients/python/tools/ppo_env_speed.py clients/python/configs/ppo-v2-easy-cpu.toml \
        --seconds 60 --server-arg=--dataset --server-arg=V2_FOLDER

Prints steps per second over `--seconds` after `--warmup` seconds (the first resets, and scenes a
built-in server builds on first use, are left out).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import esrp
from esrp import _malloc_setup
from esrp.train.ppo import load_config, make_env


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", type=Path, help="a TOML file with a [ppo] table")
    parser.add_argument("--seconds", type=float, default=30.0, help="measured seconds (default 30)")
    parser.add_argument("--warmup", type=float, default=5.0, help="unmeasured seconds first (default 5)")
    parser.add_argument("--server", help="a running esrp-server (default: one is started)")
    parser.add_argument(
        "--server-arg", action="append", default=[], help="an argument of the server started here"
    )
    args = parser.parse_args(argv)
    config = load_config(args.config)
    _malloc_setup.apply()  # as the training loop does

    def measure(address: str) -> float:
        with esrp.Client(address, timeout=120) as client:
            env = make_env(config, client)
            try:
                env.reset(seed=config.seed)
                rng = np.random.default_rng(config.seed)
                started = time.perf_counter()
                while time.perf_counter() - started < args.warmup:
                    env.step(rng.integers(0, 6, config.num_envs))
                steps = 0
                started = time.perf_counter()
                while time.perf_counter() - started < args.seconds:
                    env.step(rng.integers(0, 6, config.num_envs))
                    steps += config.num_envs
                return steps / (time.perf_counter() - started)
            finally:
                env.close()

    if args.server:
        rate = measure(args.server)
    else:
        with esrp.LocalServer(*args.server_arg) as server:
            rate = measure(server.address)
    print(f"{rate:.1f} steps/s: {config.num_envs} envs at {config.resolution} px, random actions, no network")
    return 0


if __name__ == "__main__":
    sys.exit(main())
