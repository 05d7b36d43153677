"""Training tools, for people who train the learning baselines (the `train` extra: torch, diffusers,
zarr): `demos` (`esrp demos export`: expert or DAgger trajectories into an `esrp.demos/v1` zarr
store), `bc` (`esrp train bc`: ESRP-BC on those stores), `heldout` (its held-out evaluations and
the server a training run uses), `dagger` (`esrp train bc --dagger`: the DAgger loop), `ppo` (`esrp
train ppo`: ESRP-PPO, a CleanRL-style loop on the native vector env), `_config` (reading the
TOML/JSON configs of `configs/`) and `_training` (checkpoints written atomically, resumption; the
agents read theirs without it: `esrp.agents._checkpoint`).

Importing this package imports none of them (nor torch).
"""
