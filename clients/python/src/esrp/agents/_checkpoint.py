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

__all__ = ["policy_checkpoint"]


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
