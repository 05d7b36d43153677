"""The vector env when its sub-envs restart often: `RearrangeVectorEnv(--envs)` on the easy test
scenes with a short `--horizon` (every sub-env ends and autoresets every `--horizon` steps),
random actions from a fixed seed, `--seconds` of steps after 20 unmeasured ones, against a fresh
esrp-server. Prints one JSON line: steps per second and the client's CPU time per step.

Run it with the package and the server to compare, each side in its own process, alternating:

    PYTHONPATH=OLD_OR_NEW/clients/python/src python clients/python/tools/autoreset_speed.py \\
        --binary OLD_OR_NEW/esrp-server --horizon 8 --seconds 5 --mode next_step
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from gymnasium.vector import AutoresetMode

import esrp
from esrp.cli._args import positive, positive_float
from esrp.envs import RearrangeVectorEnv


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--binary", type=Path, help="the esrp-server (default: as LocalServer finds it)")
    parser.add_argument("--envs", type=positive, default=64)
    parser.add_argument("--horizon", type=positive, default=8)
    parser.add_argument("--seconds", type=positive_float, default=5.0)
    parser.add_argument("--mode", choices=("next_step", "same_step"), default="next_step")
    args = parser.parse_args()
    mode = AutoresetMode[args.mode.upper()]
    with esrp.LocalServer(binary=args.binary) as server:
        envs = RearrangeVectorEnv(
            args.envs,
            address=server.address,
            split="test",
            difficulty="easy",
            horizon=args.horizon,
            autoreset_mode=mode,
        )
        try:
            envs.reset(seed=0)
            rng = np.random.default_rng(0)
            for _ in range(20):
                envs.step(rng.integers(0, 6, args.envs))
            steps, started, cpu = 0, time.perf_counter(), time.process_time()
            while time.perf_counter() - started < args.seconds:
                envs.step(rng.integers(0, 6, args.envs))
                steps += args.envs
            wall, used = time.perf_counter() - started, time.process_time() - cpu
        finally:
            envs.close()
    result = {
        "horizon": args.horizon,
        "mode": args.mode,
        "steps_per_s": round(steps / wall),
        "client_cpu_us_per_step": round(used / steps * 1e6, 1),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    try:
        main()
    except esrp.EsrpError as error:  # no server, or one that failed: one line, exit status 1
        sys.exit(f"autoreset_speed.py: {error}")
