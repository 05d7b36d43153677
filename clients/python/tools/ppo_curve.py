"""Learning curve of an `esrp train ppo` run beside the random agent, on the run's own scenes.

    python clients/python/tools/ppo_curve.py runs/ppo-easy1 --out docs/images/ppo-easy1.png \
        --json docs/results/ppo-easy1.json

Plays `--episodes` episodes with uniform random actions and as many with the run's final policy
(actions drawn from it, as in training; `--greedy` takes its most likely action) on the run's own
vector env (`esrp.train.ppo.make_env`: its scenes, horizon, reward, resolution), on a server started
here (or `--server`); then plots the return of every training episode (and its moving average) and
the success rate against environment steps, with the random agent's and the final policy's means
as lines. Prints (and with `--json` writes) the numbers.

A run trained in phases (a curriculum: `--stop-at`, then `--resume` on other scenes) is drawn with
`--phases 0:"v1 easy",400000:"v2 easy"` (a line where each phase begins); `--no-play` draws the
training curve alone (for a run whose figures come from `esrp eval` on the test split), and
`--reference "v2 easy test=0.05"` adds a success rate measured elsewhere as a line.

    python clients/python/tools/ppo_curve.py runs/ppo-v2-easy --out docs/images/ppo-v2-easy.png \
        --no-play --phases '0:v1 easy,409600:v2 easy' --reference 'v2 Easy test split=0.05'
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from _curves import save

import esrp
from esrp.agents.ppo import PpoConfig, PpoNet, load_network
from esrp.train.ppo import make_env

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def play(
    config: PpoConfig, client: esrp.Client, episodes: int, network: PpoNet | None, greedy: bool, seed: int
) -> dict[str, Any]:
    """Mean return, success rate and length over `episodes` episodes (random actions without a
    network), `config.num_envs` at a time.
    """
    env = make_env(config, client)
    rng = np.random.default_rng(seed)
    generator = torch.Generator().manual_seed(seed)
    returns: list[float] = []
    successes: list[bool] = []
    lengths: list[int] = []
    try:
        observations, _ = env.reset(seed=seed)
        n = config.num_envs
        running = np.zeros(n)
        length = np.zeros(n, dtype=np.int64)
        starts = torch.ones(n)
        state = network.initial_state(n) if network is not None else None
        while len(returns) < episodes:
            if network is None or state is None:
                actions = rng.integers(0, 6, n)
            else:
                with torch.no_grad():
                    logits, _, state = network(
                        network.preprocess(torch.from_numpy(observations["ego_rgb"])),
                        network.preprocess(torch.from_numpy(observations["goal_rgb"])),
                        torch.from_numpy(observations["grasping"]),
                        state,
                        starts,
                    )
                if greedy:
                    actions = logits.argmax(dim=-1).numpy()
                else:
                    actions = torch.multinomial(torch.softmax(logits, -1), 1, generator=generator)[
                        :, 0
                    ].numpy()
            observations, reward, terminated, truncated, infos = env.step(actions)
            running += reward
            length += 1
            done = terminated | truncated
            for i in np.flatnonzero(done).tolist():
                if len(returns) < episodes:
                    returns.append(float(running[i]))
                    lengths.append(int(length[i]))
                    successes.append(bool(infos["final_info"]["metrics"]["success"][i]))
                running[i], length[i] = 0.0, 0
            starts = torch.from_numpy(done.astype(np.float32))
    finally:
        env.close()
    return {
        "episodes": episodes,
        "return_mean": float(np.mean(returns)),
        "return_std": float(np.std(returns)),
        "success_rate": float(np.mean(successes)),
        "length_mean": float(np.mean(lengths)),
    }


def draw_curves(
    config: PpoConfig,
    steps: np.ndarray[Any, Any],
    returns: np.ndarray[Any, Any],
    success: np.ndarray[Any, Any],
    window: int,
    random: dict[str, Any] | None,
    final: dict[str, Any] | None,
    references: list[tuple[str, float]],
    phases: list[tuple[int, str]],
) -> Figure:
    """The figure: the training episodes' returns (top) and success rate (bottom) against
    environment steps, each with its moving average over `window` episodes, the random agent's and
    the final policy's levels where they were played, the `references` and the `phases`."""
    kernel = np.ones(window) / window
    average = np.convolve(returns, kernel, mode="valid")
    success_average = np.convolve(success, kernel, mode="valid")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    top.scatter(steps, returns, s=3, alpha=0.25, color="tab:blue", label="training episode")
    top.plot(steps[window - 1 :], average, color="tab:blue", label=f"moving average ({window} episodes)")
    if random is not None and final is not None:
        top.axhline(random["return_mean"], color="tab:red", linestyle="--", label="random agent")
        top.axhline(final["return_mean"], color="tab:green", linestyle=":", label="final policy")
    top.set_ylabel("episode return (dense reward)")
    scene = config.scene or f"{config.split} {config.difficulty or ''}".strip()
    top.set_title(f"ESRP-PPO on {scene}: {config.num_envs} envs, {steps[-1]:,} steps")
    bottom.plot(steps[window - 1 :], success_average, color="tab:blue", label="training (moving average)")
    if random is not None and final is not None:
        bottom.axhline(random["success_rate"], color="tab:red", linestyle="--", label="random agent")
        bottom.axhline(final["success_rate"], color="tab:green", linestyle=":", label="final policy")
    for (label, sr), color in zip(references, ("tab:purple", "tab:orange", "tab:brown"), strict=False):
        bottom.axhline(sr, color=color, linestyle="-.", label=label)
    for axes in (top, bottom):
        for at, label in phases:
            axes.axvline(at, color="grey", linewidth=0.8)
            if axes is top:
                axes.annotate(
                    label,
                    (at, 1.0),
                    xycoords=("data", "axes fraction"),
                    xytext=(3, -12),
                    textcoords="offset points",
                    fontsize=8,
                    color="dimgrey",
                )
    top.legend(loc="upper right", fontsize=8)
    bottom.set_ylim(-0.03, 1.03)
    bottom.set_xlabel("environment steps")
    bottom.set_ylabel("success rate")
    bottom.legend(loc="lower right", fontsize=8)
    return figure


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="the run folder of esrp train ppo")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    parser.add_argument("--episodes", type=int, default=64, help="episodes per agent (default 64)")
    parser.add_argument("--greedy", action="store_true", help="the policy's most likely actions")
    parser.add_argument("--window", type=int, default=50, help="episodes in the moving average")
    parser.add_argument("--server", help="a running esrp-server (default: one is started)")
    parser.add_argument("--seed", type=int, default=12345)
    parser.add_argument("--no-play", dest="play", action="store_false", help="the training curve alone")
    parser.add_argument("--phases", default="", help="STEPS:LABEL,... where each phase of the run begins")
    parser.add_argument(
        "--reference", action="append", default=[], help="LABEL=SR: a success rate measured elsewhere"
    )
    args = parser.parse_args(argv)
    try:
        phases = [
            (int(steps), label) for steps, label in (p.split(":", 1) for p in args.phases.split(",") if p)
        ]
        references = [(label, float(sr)) for label, sr in (r.rsplit("=", 1) for r in args.reference)]
    except ValueError:
        parser.error("--phases takes STEPS:LABEL,... and --reference LABEL=SR")

    # matplotlib here, before anything is read or played: without it the tool fails at once.
    import matplotlib

    matplotlib.use("Agg")

    torch.set_num_threads(2)
    config = PpoConfig.from_mapping(json.loads((args.run / "config.json").read_text()))
    with open(args.run / "episodes.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    if not rows:
        print(f"{args.run}/episodes.csv holds no episode", file=sys.stderr)
        return 2
    steps = np.array([int(r["steps"]) for r in rows])
    returns = np.array([float(r["return"]) for r in rows])
    success = np.array([int(r["success"]) for r in rows], dtype=float)

    # The final policy, read before a server starts (a bad checkpoint fails at once); not with --no-play.
    network = load_network(args.run / "ckpt.pt") if args.play else None

    def evaluate(address: str) -> tuple[dict[str, Any], dict[str, Any]]:
        with esrp.Client(address, timeout=120) as client:
            random = play(config, client, args.episodes, None, False, args.seed)
            final = play(config, client, args.episodes, network, args.greedy, args.seed)
        return random, final

    random: dict[str, Any] | None = None
    final: dict[str, Any] | None = None
    if args.play and args.server:
        random, final = evaluate(args.server)
    elif args.play:
        with esrp.LocalServer() as server:
            random, final = evaluate(server.address)

    figure = draw_curves(
        config,
        steps,
        returns,
        success,
        max(1, min(args.window, len(rows))),
        random,
        final,
        references,
        phases,
    )
    save(figure, args.out)
    summary = {
        "run": str(args.run),
        "scene": config.scene,
        "training_steps": int(steps[-1]),
        "training_episodes": len(rows),
        "random": random,
        "final_policy": None if final is None else {**final, "greedy": args.greedy},
    }
    text = json.dumps(summary, indent=2)
    print(text)
    if args.json:
        args.json.write_text(text + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
