"""Adapters from ESRP's envs to the libraries researchers train with.

Each is a module of its own that imports its library (install the matching extra):

- `esrp.integrations.sb3` (`esrp[sb3]`): a Stable-Baselines3 `VecEnv` over the native vector env,
  one StepBatch round trip per step for every sub-env.
- `esrp.integrations.torchrl` (`esrp[torchrl]`): TorchRL envs over the single and the vector env.
- `esrp.integrations.minari` (`esrp[minari]`) and `esrp.integrations.lerobot` (`esrp[lerobot]`):
  `esrp demos export --format minari|lerobot`, demonstrations and recorded episodes as a Minari or
  a LeRobot dataset, replayed and checked by `_replay`, which both share.

The adapters use the public client and envs only (`esrp.Client`, `esrp.envs`); nothing in the
package imports them but the command that runs them.
"""
