"""Stable-Baselines3's rollout collection over ESRP, side by side in one run: SB3's PPO
(`MultiInputPolicy`, on the CPU) collecting `--rollouts` rollouts of `--n-steps` steps per env from
`--envs` episodes, through

- `adapter`: `esrp.integrations.sb3.make_vec_env` (one StepBatch per step of every env);
- `dummy`: SB3's own `make_vec_env("esrp/Rearrange-v1", vec_env_cls=DummyVecEnv)` (one unary call
  per env per step, in turn);
- `subproc`: the same with `SubprocVecEnv` (one process per env, with `--subproc`; slow to start).

Each collects from the same server (started here unless `--server` names one) on easy train scenes
at `--resolution`; a first rollout, left out, warms the scenes and the policy. `--repeat K` runs
the configurations K times, interleaved, and prints every round and the medians (steps per second
of collection, the policy's forward passes included: what `learn()` waits for besides its updates).

    python clients/python/tools/sb3_speed.py --envs 16 --resolution 64 --repeat 3
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import torch
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env as sb3_make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

import esrp
from esrp.integrations.sb3 import make_vec_env


def collect(env: VecEnv, n_steps: int, rollouts: int) -> float:
    """Steps per second of `rollouts` rollout collections by SB3's PPO on `env` (after one
    unmeasured rollout)."""
    model = PPO("MultiInputPolicy", env, n_steps=n_steps, batch_size=n_steps, device="cpu", seed=0)
    _, callback = model._setup_learn(total_timesteps=10**9, callback=None)
    callback.on_training_start(locals(), globals())
    wrapped = model.get_env()  # as `learn()` steps it: with SB3's image transposition
    assert wrapped is not None
    model.collect_rollouts(wrapped, callback, model.rollout_buffer, n_rollout_steps=n_steps)
    started = time.perf_counter()
    for _ in range(rollouts):
        model.collect_rollouts(wrapped, callback, model.rollout_buffer, n_rollout_steps=n_steps)
    return rollouts * n_steps * env.num_envs / (time.perf_counter() - started)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", type=int, default=16, help="episodes in parallel (default 16)")
    parser.add_argument("--resolution", type=int, default=64, help="view side in pixels (default 64)")
    parser.add_argument("--n-steps", type=int, default=64, help="steps per env per rollout (default 64)")
    parser.add_argument("--rollouts", type=int, default=3, help="measured rollouts (default 3)")
    parser.add_argument("--repeat", type=int, default=1, help="rounds of all configurations")
    parser.add_argument("--subproc", action="store_true", help="also measure SubprocVecEnv")
    parser.add_argument("--server", help="a running esrp-server (default: one is started)")
    parser.add_argument("--server-arg", action="append", default=[], help="an argument of the server")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # the policy's share of the CPU the same in every configuration

    def run(address: str) -> dict[str, list[float]]:
        options: dict[str, Any] = {
            "address": address,
            "split": "train",
            "difficulty": "easy",
            "sensors": esrp.Sensors(resolution=args.resolution),
        }
        makers: dict[str, Callable[[], VecEnv]] = {
            "adapter": lambda: make_vec_env(args.envs, **options),
            "dummy": lambda: sb3_make_vec_env(
                esrp.ENV_ID, n_envs=args.envs, seed=0, env_kwargs=options, vec_env_cls=DummyVecEnv
            ),
        }
        if args.subproc:
            makers["subproc"] = lambda: sb3_make_vec_env(
                esrp.ENV_ID, n_envs=args.envs, seed=0, env_kwargs=options, vec_env_cls=SubprocVecEnv
            )
        rates: dict[str, list[float]] = {name: [] for name in makers}
        for round_ in range(args.repeat):
            for name, make in makers.items():
                env = make()
                try:
                    rates[name].append(collect(env, args.n_steps, args.rollouts))
                finally:
                    env.close()
                print(f"round {round_ + 1}  {name:8s} {rates[name][-1]:8.1f} steps/s", flush=True)
        return rates

    if args.server:
        rates = run(args.server)
    else:
        with esrp.LocalServer(*args.server_arg) as server:
            rates = run(server.address)
    adapter = statistics.median(rates["adapter"])
    print(f"\nmedians over {args.repeat} round(s): {args.envs} envs at {args.resolution} px,", end=" ")
    print(f"n_steps {args.n_steps}")
    for name, values in rates.items():
        median = statistics.median(values)
        print(f"  {name:8s} {median:8.1f} steps/s  ({median / adapter:.2f}x the adapter)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
