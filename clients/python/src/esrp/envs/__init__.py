"""The Gymnasium environment `esrp/Rearrange-v1` and its native vector env (needs the `gym` extra).

`RearrangeEnv` (`envs.single`) owns one server episode and steps it with unary calls.
`RearrangeVectorEnv` (`envs.vector`) owns N episodes on one StepStream and advances them all with one
pipelined round trip per step (steps and autoresets together): no subprocesses, no per-env threads.
Both follow Gymnasium 1.x exactly: `reset(seed=s)` seeds the env's `np_random`, which picks the scene
from the filtered scene list, so the same seed plays the same scene; the vector env seeds sub-env i
with `s + i`, exactly as `SyncVectorEnv` over N `RearrangeEnv`s would, and gives bit-identical
observations.

Observations are dicts: `ego_rgb` and `goal_rgb` (R, R, 3) uint8, `grasping` 0/1 (Discrete(2)), and
`depth` (R, R) float32, `segmentation` (R, R) uint32 and `current_top_down` (R, R, 3) uint8 for the
sensors that are on. Actions are `Discrete(6)` with the codes of `esrp.Action`. Infos: the scene's
id, difficulty, room type, object count and horizon on resets; `is_success` on the step that ends an
episode.

Importing this package registers `esrp/Rearrange-v1` with gymnasium (`esrp._registration`). The
envs use the package's public client only (`esrp.Client`); they read no esrp.v1 message.
"""

from __future__ import annotations

from .._registration import register_envs
from ._shared import observation_space
from .single import RearrangeEnv
from .vector import RearrangeVectorEnv

__all__ = ["RearrangeEnv", "RearrangeVectorEnv", "observation_space"]

register_envs()
