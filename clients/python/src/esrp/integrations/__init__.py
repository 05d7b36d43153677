"""Adapters from ESRP's envs to the libraries researchers train with.

Each is a module of its own that imports its library (install the matching extra):

- `esrp.integrations.sb3` (`esrp[sb3]`): a Stable-Baselines3 `VecEnv` over the native vector env,
  one StepBatch round trip per step for every sub-env.
- `esrp.integrations.torchrl` (`esrp[torchrl]`): TorchRL envs over the single and the vector env.

The adapters use the public envs only (`esrp.envs`); nothing in the package imports them.
"""
