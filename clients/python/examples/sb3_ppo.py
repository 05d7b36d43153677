"""Train Stable-Baselines3's PPO on ESRP's easy train scenes through the native vector env
(`esrp.integrations.sb3`), then play the policy on a few easy test scenes.

    pip install "esrp[gym,sb3,server]"
    python examples/sb3_ppo.py --timesteps 20000 --envs 8

Starts a local esrp-server (the `esrp-server` wheel, or `--server ADDRESS` for a running one),
trains for `--timesteps` steps with SB3's `MultiInputPolicy` (a NatureCNN per view, the grasp
flag one-hot), saves the model to `--save` and prints the test episodes' success rate. A few
thousand steps only show the loop working; the paper's PPO trained for 6 M steps (SPEC §8).
Arguments it cannot run with are refused before anything starts (status 2); a server that cannot
be reached, or is lost mid-run, ends it with a line naming the error (status 1).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from stable_baselines3 import PPO

import esrp
from esrp.integrations.sb3 import make_vec_env


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--timesteps", type=int, default=20_000, help="training steps (default 20000)")
    parser.add_argument("--envs", type=int, default=8, help="episodes in parallel (default 8)")
    parser.add_argument("--resolution", type=int, default=64, help="view side, 36 px or more (default 64)")
    parser.add_argument("--n-steps", type=int, default=128, help="PPO's steps per env per rollout")
    parser.add_argument("--test-episodes", type=int, default=8, help="easy test episodes played after")
    parser.add_argument("--save", type=Path, default=Path("sb3-ppo-esrp.zip"), help="where the model goes")
    parser.add_argument("--server", help="a running esrp-server (default: one is started here)")
    args = parser.parse_args(argv)
    # What SB3 would otherwise fail on deep inside, with a traceback.
    if args.resolution < 36:
        parser.error(f"--resolution must be 36 or more (SB3's NatureCNN), not {args.resolution}")
    for name in ("envs", "test_episodes", "n_steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1, not {getattr(args, name)}")
    rollout = args.n_steps * args.envs
    if rollout < 2:
        parser.error(f"--n-steps x --envs must be 2 or more (PPO's minibatch), not {rollout}")
    if args.timesteps < 0:
        parser.error(f"--timesteps must be 0 or more, not {args.timesteps}")
    try:
        return _train_and_play(args)
    except esrp.EsrpError as error:
        print(f"{parser.prog}: {type(error).__name__}: {error}", file=sys.stderr)
        return 1


def _train_and_play(args: argparse.Namespace) -> int:
    with esrp.LocalServer() if args.server is None else _Running(args.server) as server:
        sensors = esrp.Sensors(resolution=args.resolution)
        env = make_vec_env(args.envs, server.address, split="train", difficulty="easy", sensors=sensors)
        try:
            model = PPO(
                "MultiInputPolicy",
                env,
                n_steps=args.n_steps,
                batch_size=min(256, args.n_steps * args.envs),
                ent_coef=0.01,
                device="cpu",
                seed=0,
                verbose=1,
            )
            model.learn(total_timesteps=args.timesteps, progress_bar=False)
            model.save(args.save)
            print(f"saved {args.save}")
        finally:
            env.close()

        test = make_vec_env(
            args.test_episodes,
            server.address,
            monitor=False,
            split="test",
            difficulty="easy",
            sensors=sensors,
        )
        try:
            test.seed(0)
            observations = test.reset()
            assert isinstance(observations, dict)  # ESRP's observations are dicts of arrays
            done = np.zeros(args.test_episodes, dtype=bool)
            successes = np.zeros(args.test_episodes, dtype=bool)
            while not done.all():
                actions, _ = model.predict(observations, deterministic=False)
                observations, _, dones, infos = test.step(actions)
                assert isinstance(observations, dict)
                for i in np.flatnonzero(dones & ~done):
                    successes[i] = infos[i]["is_success"]
                done |= dones
            print(f"easy test episodes: {successes.sum()}/{args.test_episodes} solved")
        finally:
            test.close()
    return 0


class _Running:
    """A server that runs already, used as `LocalServer` is (its address)."""

    def __init__(self, address: str) -> None:
        self.address = address

    def __enter__(self) -> _Running:
        return self

    def __exit__(self, *_: object) -> None:
        pass


if __name__ == "__main__":
    sys.exit(main())
