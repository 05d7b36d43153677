"""What the challenge's guards cost, measured side by side on one server.

- A create (and its close) on a challenge scene by an agent token, whose counted attempt is
  journaled and synced before the episode exists, beside the same create by an admin (not
  counted: no claim), scene by scene, interleaved.
- A step on a challenge scene served with the paper's observation only (the agent's episode),
  beside a step of the same scene served in full (the admin's), interleaved.

Prints the median and 90th percentile of each, in milliseconds.

    .venv/bin/python clients/python/tools/challenge_costs.py --server-binary target/release/esrp-server \\
        --scenes 100 --steps 400

Needs the `esrp` package (`pip install ./clients/python`) in the Python that runs it.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import esrp

TOKENS = """
[[token]]
name = "agent"
secret = "agent-secret"
role = "agent"

[[token]]
name = "root"
secret = "root-secret"
role = "admin"
"""


def summary(name: str, seconds: list[float]) -> str:
    """`name: median … ms, p90 … ms (n …)`."""
    ms = sorted(s * 1000 for s in seconds)
    p90 = ms[min(len(ms) - 1, int(0.9 * len(ms)))]
    return f"{name:<44} median {statistics.median(ms):7.2f} ms   p90 {p90:7.2f} ms   (n {len(ms)})"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--server-binary", required=True, help="the esrp-server to measure")
    parser.add_argument("--scenes", type=int, default=100, help="challenge scenes, one create each per token")
    parser.add_argument("--steps", type=int, default=400, help="steps of each kind")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        tokens = Path(folder) / "tokens.toml"
        tokens.write_text(TOKENS)
        flags = ["--tokens", str(tokens), "--challenge-seed", "a-secret-seed-for-measuring"]
        flags += ["--challenge-scenes", str(args.scenes), "--records", str(Path(folder) / "records")]
        with esrp.LocalServer(*flags, binary=args.server_binary) as server:
            agent = esrp.Client(server.address, token="agent-secret")
            root = esrp.Client(server.address, token="root-secret")
            scenes = [f"challenge/{i:05}" for i in range(args.scenes)]
            for scene in scenes:  # built and uploaded once, before anything is timed
                root.create_episode(scene, agent="warm-up").close()
            claimed: list[float] = []
            unclaimed: list[float] = []
            for n, scene in enumerate(scenes):
                pair = [(agent, claimed), (root, unclaimed)]
                for client, into in pair if n % 2 else pair[::-1]:
                    started = time.perf_counter()
                    client.create_episode(scene, agent="costs").close()
                    into.append(time.perf_counter() - started)
            print(summary("create+close, counted (journaled claim)", claimed))
            print(summary("create+close, admin (no claim)", unclaimed))
            paper: list[float] = []
            full: list[float] = []
            # minival: played again and again; the agent's episode serves the paper's observation.
            episodes = (
                (agent.create_episode("minival/00000"), paper),
                (root.create_episode("minival/00000"), full),
            )
            for i in range(args.steps):
                for episode, into in episodes:
                    started = time.perf_counter()
                    answer = episode.step(2 + i % 2)
                    into.append(time.perf_counter() - started)
                    if answer.terminated or answer.truncated:
                        episode.reset()
            print(summary("step, paper's observation (agent, minival)", paper))
            print(summary("step, full answer (admin, minival)", full))


if __name__ == "__main__":
    main()
