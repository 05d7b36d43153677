"""The `checkpoint` option of the learned agents (`esrp eval --agent bc|ppo --checkpoint`): where a
trained policy is, checked before its agent loads it. Here, beside the agents, so that an agent
loads a checkpoint without importing the training code (`esrp.train` imports `esrp.agents`, never
the reverse).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

__all__ = ["policy_checkpoint", "read_checkpoint"]


def read_checkpoint(
    path: str | Path, kind: str, what: str, map_location: torch.device | str = "cpu"
) -> dict[str, Any]:
    """The checkpoint at `path` (`torch.load`), checked to be of `kind` (`esrp-bc`, `esrp-ppo`)
    with its `config` and `model`. Raises `ValueError` naming the file when it cannot be read, is
    not a checkpoint (empty, cut short, another file) or is another kind (`what`: its name in the
    message, e.g. `ESRP-PPO`).
    """
    try:
        state = torch.load(Path(path), map_location=map_location, weights_only=False)
    except OSError as error:
        raise ValueError(f"cannot read {path}: {error.strerror or error}") from None
    except Exception as error:  # the unpickler's and the zip reader's errors, of many kinds
        raise ValueError(f"{path} is not a readable checkpoint ({type(error).__name__}: {error})") from None
    if (
        not isinstance(state, dict)
        or state.get("kind") != kind
        or not isinstance(state.get("config"), dict)
        or "model" not in state
    ):
        raise ValueError(f"{path} is not an {what} checkpoint")
    return state


def policy_checkpoint(config: Mapping[str, Any], agent: str) -> str:
    """The `checkpoint` of an agent's config (`esrp eval --agent bc|ppo --checkpoint`), checked to
    exist; sets torch's thread count to the config's `threads` (default 1: one per evaluation).
    """
    checkpoint = config.get("checkpoint")
    if not checkpoint:
        raise ValueError(f"--agent {agent} needs --checkpoint RUN/ckpt.pt (made by esrp train {agent})")
    if not Path(str(checkpoint)).is_file():
        raise ValueError(f"no checkpoint at {checkpoint}")
    threads = int(config.get("threads", 1))
    if threads > 0:
        torch.set_num_threads(threads)
    return str(checkpoint)
