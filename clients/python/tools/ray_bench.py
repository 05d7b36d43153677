"""Episodes per minute of `esrp eval`: the local harness against `esrp eval --ray` with 1 and 2
spawned servers, for the expert and the random agents, side by side in one run.

    python clients/python/tools/ray_bench.py [--expert-scenes N] [--random-scenes N] [--rounds R]

Each configuration runs `esrp eval` in a fresh process (a local Ray is started for the --ray ones,
and its start is not counted: the time is the one `esrp eval` prints for its episodes) over the
first N test scenes, with 8 episodes in flight per server; rounds alternate the configurations.
Needs esrp[ray] and an esrp-server (ESRP_SERVER_BIN or PATH). Prints a table; `--json` writes it.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CONFIGS = {
    "local, 1 server": [],
    "ray, 1 server": ["--ray", "--spawn-servers", "1"],
    "ray, 2 servers": ["--ray", "--spawn-servers", "2"],
}


def run(agent: str, scenes: int, extra: list[str], folder: Path) -> float:
    """Episodes per minute of one `esrp eval` run (from the duration it prints)."""
    out = folder / f"{agent}-{time.monotonic_ns()}.jsonl"
    command = [sys.executable, "-m", "esrp.cli", "eval", "--agent", agent, "--split", "test"]
    command += ["--limit", str(scenes), "--out", str(out), "--no-progress", "--episodes-in-flight", "8"]
    command += extra
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
    found = re.search(rf"{agent} on (\d+) scenes of \S+ \((\d+) s\)", done.stdout)
    if found is None:
        raise SystemExit(f"no duration in the output:\n{done.stdout}")
    episodes, seconds = int(found.group(1)), max(int(found.group(2)), 1)
    return 60.0 * episodes / seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--expert-scenes", type=int, default=544)
    parser.add_argument("--random-scenes", type=int, default=120)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}", flush=True)
    results: dict[str, dict[str, list[float]]] = {}
    with tempfile.TemporaryDirectory() as scratch:
        for agent, scenes in (("expert", args.expert_scenes), ("random", args.random_scenes)):
            for round_ in range(args.rounds):
                for name, extra in CONFIGS.items():
                    rate = run(agent, scenes, extra, Path(scratch))
                    results.setdefault(agent, {}).setdefault(name, []).append(rate)
                    print(f"{agent:6s} round {round_ + 1}  {name:16s} {rate:8.0f} episodes/min", flush=True)
    print(f"load average after {os.getloadavg()[0]:.2f}")
    print("\nagent   configuration      episodes/min (median)  vs local")
    for agent, by_config in results.items():
        local = statistics.median(by_config["local, 1 server"])
        for name, rates in by_config.items():
            median = statistics.median(rates)
            print(f"{agent:6s}  {name:16s} {median:12.0f}           {median / local:6.2f}x")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
