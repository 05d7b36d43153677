"""TorchRL over ESRP (needs the `torchrl` extra).

`make_env()` is TorchRL's `GymEnv("esrp/Rearrange-v1", ...)`: one episode, stepped with unary
calls. `make_env(num_envs=N)` wraps ESRP's native vector env instead, so the N episodes of the
env's batch (`batch_size=[N]`) advance in one StepBatch round trip per step, with no worker
processes:

    from torchrl.collectors import Collector
    from esrp.integrations.torchrl import make_env

    env = make_env(16, "127.0.0.1:50051", split="train", difficulty="easy")
    collector = Collector(env, policy=None, frames_per_batch=16 * 64, total_frames=-1)

The vector env runs in Gymnasium's `DISABLED` autoreset mode, the one TorchRL prefers: an episode
that ends stays ended until TorchRL resets it (`_reset` in the tensordict, sent as the env's
`reset_mask`), so `("next", ...)` always holds the step's own last observation. Observations are
TorchRL's: `ego_rgb` and `goal_rgb` uint8 (R, R, 3) tensors, `grasping`, and the sensors asked for;
the action a one-hot of 6 (or an index with `categorical_action_encoding=True`); and
`("next", "is_success")`, true on the step that ends a solved episode (`SuccessReader`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import EnvBase, GymEnv, GymWrapper
from torchrl.envs.gym_like import BaseInfoDictReader

from .._registration import ENV_ID, register_envs
from ..envs import RearrangeVectorEnv

__all__ = ["SuccessReader", "make_env"]


class SuccessReader(BaseInfoDictReader):
    """Reads ESRP's `is_success` into each step's tensordict (`("next", "is_success")`, a bool of
    shape `batch_size + (1,)`, as `done`'s): true on the step that ends a solved episode, false
    on every other step. Reads the single env's info (a bool, present on an episode's last step)
    and the vector env's (an array, masked by `_is_success`) alike.
    """

    def __init__(self, batch_size: torch.Size) -> None:
        self.batch_size = batch_size
        success = Unbounded(torch.Size((*batch_size, 1)), dtype=torch.bool)
        self._spec = Composite(is_success=success, shape=batch_size)

    def __call__(self, info_dict: dict[str, Any], tensordict: TensorDictBase) -> TensorDictBase:
        """Sets `is_success` in `tensordict` from the step's `info_dict`."""
        value = info_dict.get("is_success", False)
        mask = info_dict.get("_is_success")
        # A reset's info has no `is_success`: false for every episode of the batch.
        success = np.broadcast_to(np.asarray(value, dtype=np.bool_), self.batch_size)
        if mask is not None:
            success = success & np.asarray(mask, dtype=np.bool_)
        # A copy: the broadcast is a read-only view, which torch would share (and warn about).
        tensor = torch.from_numpy(np.array(success, dtype=np.bool_)).reshape(*self.batch_size, 1)
        tensordict.set("is_success", tensor.to(tensordict.device) if tensordict.device else tensor)
        return tensordict

    @property
    def info_spec(self) -> Composite:  # pyright: ignore[reportIncompatibleMethodOverride]  # TorchRL's own type
        """The spec of what the reader adds: `is_success`."""
        return self._spec


def make_env(
    num_envs: int | None = None,
    address: str | Sequence[str] | None = None,
    *,
    categorical_action_encoding: bool = False,
    device: str | None = None,
    **options: Any,  # noqa: ANN401
) -> EnvBase:
    """A TorchRL env of ESRP at `address` (`options`: the env's, e.g. `split`, `difficulty`,
    `scene`, `sensors`, `horizon`, `reward`): one episode (`GymEnv`) with `num_envs=None`, else a
    batch of `num_envs` episodes over the native vector env (`GymWrapper`, batch size
    `[num_envs]`; it may be spread over several servers: a list of addresses, or `servers=K`).
    `categorical_action_encoding`: actions as indices instead of one-hot vectors.
    """
    if "autoreset_mode" in options:
        raise ValueError("make_env sets autoreset_mode itself (DISABLED: TorchRL resets ended episodes)")
    env: GymWrapper
    if num_envs is None:
        register_envs()
        env = GymEnv(
            ENV_ID,
            address=address,
            categorical_action_encoding=categorical_action_encoding,
            device=device,
            **options,
        )
    else:
        venv = RearrangeVectorEnv(num_envs, address, autoreset_mode=AutoresetMode.DISABLED, **options)
        env = GymWrapper(venv, categorical_action_encoding=categorical_action_encoding, device=device)
    env.set_info_dict_reader(SuccessReader(env.batch_size))
    return env
