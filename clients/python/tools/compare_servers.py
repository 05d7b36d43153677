"""Whether two esrp-server binaries answer the same episodes bit for bit.

Starts each binary on the built-in benchmark, plays the same episodes on both (the same scenes,
the same seeded random actions, with every optional sensor on) and compares every answer: each
observation's pixels, depth and segmentation byte for byte, and the rewards, reward terms,
flags, step info and final metrics. Prints a digest per server and the first difference, if
any. Meant for refactors and speed work that must not change what an agent sees
(`docs/performance.md` records such comparisons).

Usage:
    python tools/compare_servers.py OLD_BINARY NEW_BINARY [--episodes 24] [--steps 120] [--seed 7]
        [--server-arg=--render-backend=vulkan ...]

Exit status 0 when every answer is identical, 1 at the first difference, 2 on bad input.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

import esrp

SENSORS = esrp.Sensors(depth=True, segmentation=True, current_top_down=True)


def observation_parts(observation: esrp.Observation) -> Iterator[tuple[str, bytes]]:
    """The observation's arrays as named byte strings (absent ones skipped)."""
    arrays: dict[str, Any] = {
        "ego_rgb": observation.ego_rgb,
        "goal_rgb": observation.goal_rgb,
        "depth": observation.depth,
        "segmentation": observation.segmentation,
        "current_top_down": observation.current_top_down,
    }
    for name, array in arrays.items():
        if array is not None:
            yield name, np.ascontiguousarray(array).tobytes()
    yield "grasping", bytes([observation.grasping])


def episode_answers(client: esrp.Client, scene: str, actions: list[int]) -> Iterator[tuple[str, bytes]]:
    """Every answer of one episode of `scene` driven by `actions`, as named byte strings."""
    with client.create_episode(scene, sensors=SENSORS) as episode:
        if episode.observation is not None:  # a created episode carries its first observation
            for name, data in observation_parts(episode.observation):
                yield f"create.{name}", data
        for i, action in enumerate(actions):
            result = episode.step(action, include_goal=i % 17 == 0)
            for name, data in observation_parts(result.observation):
                yield f"step {i}.{name}", data
            rest = (result.reward, result.terminated, result.truncated, result.info, result.metrics)
            yield f"step {i}.answer", repr(rest).encode()
            if result.ended:
                break


def play(
    binary: Path, server_args: list[str], scenes: list[str], plans: list[list[int]]
) -> Iterator[tuple[str, bytes]]:
    """Every answer of every episode on a server started from `binary` with `server_args`."""
    with esrp.LocalServer(*server_args, binary=binary) as server, server.client() as client:
        for scene, actions in zip(scenes, plans, strict=True):
            for name, data in episode_answers(client, scene, actions):
                yield f"{scene} {name}", data


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("old", type=Path, help="the first esrp-server binary")
    parser.add_argument("new", type=Path, help="the second esrp-server binary")
    parser.add_argument("--episodes", type=int, default=24, help="episodes to play (default 24)")
    parser.add_argument("--steps", type=int, default=120, help="random actions per episode (default 120)")
    parser.add_argument("--seed", type=int, default=7, help="seed of the scenes and actions (default 7)")
    parser.add_argument(
        "--server-arg",
        action="append",
        default=[],
        help="a flag for both servers, e.g. --server-arg=--render-backend=vulkan (repeatable)",
    )
    args = parser.parse_args(argv)
    for binary in (args.old, args.new):
        if not binary.is_file():
            parser.error(f"{binary} is not a file")
    if args.episodes < 1 or args.steps < 1:
        parser.error("--episodes and --steps must be at least 1")

    with esrp.LocalServer(*args.server_arg, binary=args.old) as server, server.client() as client:
        test_scenes = [s.id for s in client.scenes(split="test")]
    rng = np.random.default_rng(args.seed)
    scenes = [test_scenes[i] for i in rng.choice(len(test_scenes), size=args.episodes, replace=False)]
    plans = [rng.integers(0, 6, size=args.steps).tolist() for _ in scenes]

    digests = [hashlib.sha256(), hashlib.sha256()]
    answers = 0
    old_answers, new_answers = (
        play(args.old, args.server_arg, scenes, plans),
        play(args.new, args.server_arg, scenes, plans),
    )
    for (name_a, data_a), (name_b, data_b) in zip(old_answers, new_answers, strict=False):
        if name_a != name_b or data_a != data_b:
            print(f"first difference: {name_a} ({len(data_a)} bytes) against {name_b} ({len(data_b)} bytes)")
            return 1
        digests[0].update(data_a)
        digests[1].update(data_b)
        answers += 1
    # Both generators are exhausted only if neither server answered more than the other.
    if next(old_answers, None) is not None or next(new_answers, None) is not None:
        print(f"first difference: after {answers} answer parts, one server's episodes went on")
        return 1
    print(f"{args.old}: {digests[0].hexdigest()}")
    print(f"{args.new}: {digests[1].hexdigest()}")
    print(
        f"identical: {answers} answer parts of {len(scenes)} episodes "
        f"({args.steps} random actions each, every sensor)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
