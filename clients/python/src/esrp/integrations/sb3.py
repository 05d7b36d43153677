"""Stable-Baselines3 over ESRP's native vector env (needs the `sb3` extra).

SB3 vectorises single envs itself (`DummyVecEnv`, `SubprocVecEnv`): one connection and one unary
call per env per step. `make_vec_env` instead gives SB3 a `VecEnv` over `RearrangeVectorEnv`, so a
step of all N episodes is one StepBatch round trip, in process:

    from stable_baselines3 import PPO
    from esrp.integrations.sb3 import make_vec_env

    env = make_vec_env(16, "127.0.0.1:50051", split="train", difficulty="easy")
    PPO("MultiInputPolicy", env, n_steps=128).learn(100_000)

It keeps SB3's conventions exactly, as `DummyVecEnv` over `gymnasium.make("esrp/Rearrange-v1")`
would (tested side by side): an episode that ends is reset in the same step, its last observation
in `infos[i]["terminal_observation"]` and `infos[i]["TimeLimit.truncated"]` set when the horizon
cut it; `is_success` (and the episode's `metrics`) in the info of the step that ends it; the
reset's info (scene id, difficulty...) in the `EsrpVecEnv`'s `reset_infos` (under
`make_vec_env`'s `VecMonitor`, `env.venv.reset_infos`: SB3's wrappers keep their own, empty);
`seed(s)` seeds sub-env i with `s + i` and `set_options(...)` sets the options of the next
`reset()`, as SB3's own vector envs do (per-env options may differ in `scene` alone).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import gymnasium
import numpy as np
import numpy.typing as npt
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv, VecMonitor
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvObs, VecEnvStepReturn

from ..envs import RearrangeVectorEnv
from ..envs.vector import _FINAL_KEYS, _RESET_KEYS

__all__ = ["EsrpVecEnv", "make_vec_env", "unbatch_infos"]


def unbatch_infos(infos: dict[str, Any], num_envs: int) -> list[dict[str, Any]]:
    """Gymnasium's vector infos (a dict of arrays, each with its `_key` mask; dicts nested the same
    way) as one dict per sub-env, holding the keys its masks set, values as Python scalars where
    the arrays hold numbers.
    """
    per_env: list[dict[str, Any]] = [{} for _ in range(num_envs)]
    for key, value in infos.items():
        if key.startswith("_"):
            continue
        mask = infos.get(f"_{key}")
        if mask is None:
            raise ValueError(f"vector info {key!r} has no mask `_{key}`")
        nested = unbatch_infos(value, num_envs) if isinstance(value, dict) else None
        for i in np.flatnonzero(mask):
            if nested is not None:
                per_env[i][key] = nested[i]
            else:
                item = value[i]
                per_env[i][key] = item.item() if isinstance(item, np.generic) else item
    return per_env


def merged_options(per_env: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The vector env's reset options for SB3's per-env ones: the same for all, except `scene`,
    which may differ (one id per sub-env, None or absent: the sub-env's own pick). Raises
    `ValueError` where another option differs.
    """
    others = [{key: value for key, value in options.items() if key != "scene"} for options in per_env]
    if any(other != others[0] for other in others):
        raise ValueError(
            "per-env reset options differ in more than `scene`, but ESRP's vector env takes one "
            f"options dict for all its sub-envs (a `scene` may differ: one id per sub-env): {list(per_env)!r}"
        )
    merged = dict(others[0]) if others else {}
    scenes = [options.get("scene") for options in per_env]
    if any(scene is not None for scene in scenes):
        merged["scene"] = scenes[0] if all(scene == scenes[0] for scene in scenes) else scenes
    return merged


class EsrpVecEnv(VecEnv):
    """An SB3 `VecEnv` over a `RearrangeVectorEnv` (made here in SAME_STEP autoreset mode, the one
    SB3's semantics need; see the module's doc). Attribute calls (`get_attr`, `env_method`) reach
    the vector env itself, as there are no per-env objects: each returns the same value for every
    index asked. Indices are taken as `DummyVecEnv` takes them (None: every sub-env; an int or a
    sequence of them; negative ones count from the end); one out of range raises `IndexError`.
    """

    def __init__(self, venv: RearrangeVectorEnv) -> None:
        if venv.autoreset_mode != AutoresetMode.SAME_STEP:
            raise ValueError(
                "EsrpVecEnv needs a RearrangeVectorEnv with autoreset_mode=SAME_STEP (SB3 resets an "
                f"ended episode in the step that ends it), got {venv.autoreset_mode}"
            )
        self.venv = venv
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self._actions: npt.NDArray[Any] | None = None

    def reset(self) -> VecEnvObs:
        """Resets every sub-env with the seeds of `seed()` and the options of `set_options()`
        (one dict for all, or one per sub-env), both for this reset only; the infos go to
        `reset_infos`. Options that ESRP's vector env cannot take (a list of another length than
        `num_envs`; dicts that differ in more than `scene`) raise `ValueError` and stay set.
        """
        if len(self._options) != self.num_envs:
            raise ValueError(
                f"set_options() was given {len(self._options)} options dicts for {self.num_envs} "
                "sub-envs: give one dict (for every sub-env) or a list of one per sub-env"
            )
        options = merged_options(self._options)
        seeds = None if all(seed is None for seed in self._seeds) else list(self._seeds)
        observations, infos = self.venv.reset(seed=seeds, options=dict(options) or None)
        self.reset_infos = unbatch_infos(infos, self.num_envs)
        # Seeds and options hold for one reset, as in SB3's own vector envs.
        self._reset_seeds()
        self._reset_options()
        return dict(observations)

    def step_async(self, actions: np.ndarray) -> None:
        """Takes the actions of the next `step_wait()` (one per sub-env)."""
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        """Steps every sub-env in one round trip and resets those that end (see the module)."""
        if self._actions is None:
            raise RuntimeError("step_wait() called without step_async()")
        actions, self._actions = self._actions, None
        observations, rewards, terminated, truncated, infos = self.venv.step(actions)
        n = self.num_envs
        finals = infos.get("_final_obs", np.zeros(n, dtype=np.bool_))
        step_infos = {key: value for key, value in infos.items() if key.lstrip("_") not in _AUTORESET_KEYS}
        per_env = unbatch_infos(step_infos, n)
        if np.any(finals):
            last_infos = unbatch_infos(infos["final_info"], n)
            reset_infos = unbatch_infos(
                {key: value for key, value in infos.items() if key.lstrip("_") in _RESET_KEYS}, n
            )
            for i in np.flatnonzero(finals).tolist():
                per_env[i] = last_infos[i]
                per_env[i]["terminal_observation"] = infos["final_obs"][i]
                self.reset_infos[i] = reset_infos[i]
        for i in range(n):
            per_env[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        dones = np.logical_or(terminated, truncated)
        return dict(observations), rewards.astype(np.float32), dones, per_env

    def close(self) -> None:
        """Closes the vector env (its episodes on the server)."""
        self.venv.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """The vector env's attribute `attr_name`, once per index asked."""
        value = getattr(self.venv, attr_name)
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:  # noqa: ANN401
        """Refused (`AttributeError`): the sub-envs are set when the env is made."""
        raise AttributeError(
            f"cannot set {attr_name!r} on the sub-envs of an ESRP vector env: its sub-envs are "
            "episodes of one env, configured when it is made (make_vec_env's options)"
        )

    def env_method(
        self,
        method_name: str,
        *method_args: Any,  # noqa: ANN401
        indices: VecEnvIndices = None,
        **method_kwargs: Any,  # noqa: ANN401
    ) -> list[Any]:
        """Calls the vector env's method `method_name` once (not at all for no index); its result,
        once per index asked.
        """
        targets = self._get_indices(indices)
        if not targets:
            return []
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result for _ in targets]

    def env_is_wrapped(
        self, wrapper_class: type[gymnasium.Wrapper[Any, Any, Any, Any]], indices: VecEnvIndices = None
    ) -> list[bool]:
        """False for every index: no Gymnasium wrapper wraps a sub-env."""
        # The sub-envs are episodes of the vector env: no Gymnasium wrapper wraps any of them.
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """Each sub-env's frame with `render_mode="rgb_array"`, as the single env's `render()`
        gives it: the egocentric view, the goal image and (with that sensor) the current top-down
        side by side, (R, 2R or 3R, 3) uint8; else Nones.
        """
        frames = self.venv.render()
        if frames is None:
            return [None] * self.num_envs
        return list(frames)

    def _get_indices(self, indices: VecEnvIndices) -> list[int]:
        """The sub-envs `indices` names, as `DummyVecEnv` reads them, each checked."""
        every = range(self.num_envs)
        if indices is None:
            return list(every)
        asked: Iterable[int] = [indices] if isinstance(indices, int | np.integer) else indices
        checked = []
        for index in asked:
            if not -self.num_envs <= index < self.num_envs:
                raise IndexError(
                    f"sub-env index {index} is out of range: the env has {self.num_envs} sub-envs "
                    f"(0 to {self.num_envs - 1}, or negative from the end)"
                )
            checked.append(every[index])
        return checked


_AUTORESET_KEYS = frozenset(_FINAL_KEYS)
"""The keys a SAME_STEP step adds for the sub-envs it reset: their last observation and info, and
the reset's info (`_RESET_KEYS`)."""


def make_vec_env(
    num_envs: int,
    address: str | Sequence[str] | None = None,
    *,
    monitor: bool = True,
    **options: Any,  # noqa: ANN401
) -> VecEnv:
    """An SB3 `VecEnv` of `num_envs` ESRP episodes over one `RearrangeVectorEnv` at `address`
    (`options`: the vector env's, e.g. `split`, `difficulty`, `scene`, `sensors`, `reward`,
    `client`; a list of addresses, or `servers=K`, spreads the episodes over several servers).
    With `monitor` (the default) it is wrapped in SB3's `VecMonitor`, so episodes' returns, lengths
    and `is_success` reach SB3's logs (`rollout/ep_rew_mean`, `rollout/success_rate`).
    """
    if "autoreset_mode" in options:
        raise ValueError("make_vec_env sets autoreset_mode itself (SAME_STEP, SB3's semantics)")
    venv = RearrangeVectorEnv(num_envs, address, autoreset_mode=AutoresetMode.SAME_STEP, **options)
    env: VecEnv = EsrpVecEnv(venv)
    if monitor:
        env = VecMonitor(env)
    return env
