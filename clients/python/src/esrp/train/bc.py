"""`esrp train bc`: trains ESRP-BC (`esrp.agents.bc`) on an `esrp.demos/v1` store.

Samples are windows of the store: for step t of an episode, the ego views and grasp flags of steps
t-n+1..t (the episode's first repeated before its start) and the goal image, and the expert's
actions t..t+h-1 (its last repeated past its end), as Diffusion Policy pads. Each epoch visits every
step once in a seeded random order; a batch reads only the chunks its windows touch.

A run folder holds `config.json` (the settings), `log.csv` (one line per epoch: epoch, optimizer
steps, mean loss, noise MSE and cross-entropy, learning rate, seconds) and `ckpt.pt` (model,
optimizer, epoch, random states: `--resume` goes on from it; `esrp eval --agent bc --checkpoint`
plays it).
"""

from __future__ import annotations

import csv
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from .. import _malloc_setup
from ..agents.bc import BcConfig, DiffusionPolicy, bc_loss, schedulers
from ..agents.encoders import resolve_device
from ._config import read_table
from ._training import load_resumable, save_checkpoint

__all__ = ["DemoWindows", "load_config", "train"]


def load_config(path: Path) -> BcConfig:
    """The `[bc]` table of a TOML file (or the top level of a JSON file) as a `BcConfig`."""
    table = read_table(path, "bc")
    try:
        return BcConfig.from_mapping(table)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: {error}") from None


class DemoWindows:
    """The training windows of one or more `esrp.demos/v1` stores (expert demonstrations and DAgger
    exports aggregated), read a batch at a time.
    """

    def __init__(self, paths: str | Path | Sequence[str | Path], n_obs: int, horizon: int) -> None:
        import zarr

        listed = [paths] if isinstance(paths, str | Path) else list(paths)
        if not listed:
            raise ValueError("no demonstration store given")
        self.stores: list[Any] = []
        ends_list: list[np.ndarray] = []
        actions, grasping = [], []
        resolution = None
        offset = 0
        for path in listed:
            store = cast(Any, zarr.open_group(str(path), mode="r"))
            if store.attrs.get("format") != "esrp.demos/v1":
                raise ValueError(f"{path} is not an esrp.demos/v1 store (esrp demos export makes one)")
            if resolution is not None and store.attrs.get("resolution") != resolution:
                raise ValueError(
                    f"{path} holds {store.attrs.get('resolution')} px views, the others {resolution} px"
                )
            resolution = store.attrs.get("resolution")
            ends = np.asarray(store["meta/episode_ends"][:], dtype=np.int64)
            if len(ends) == 0:
                raise ValueError(f"{path} holds no episode")
            self.stores.append(store)
            ends_list.append(ends + offset)
            # Actions and flags are small: read once (only the whole episodes).
            actions.append(np.asarray(store["data/action"][: ends[-1]], dtype=np.int64))
            grasping.append(np.asarray(store["data/grasping"][: ends[-1]], dtype=bool))
            offset += int(ends[-1])
        ends = np.concatenate(ends_list)
        self.resolution = int(resolution or 128)
        """The views' side in pixels (every store's)."""
        self.n_obs, self.horizon = n_obs, horizon
        starts = np.concatenate([[0], ends[:-1]])
        self.episode = np.repeat(np.arange(len(ends)), ends - starts)
        self.start, self.end = starts[self.episode], ends[self.episode]
        self.actions = np.concatenate(actions)
        self.grasping = np.concatenate(grasping)
        # Where each store's steps and episodes begin in the joined numbering.
        self.step_offsets = np.cumsum([0, *(len(a) for a in actions)])
        self.episode_offsets = np.cumsum([0, *(len(e) for e in ends_list)])

    def __len__(self) -> int:
        return len(self.episode)

    def _read(self, name: str, indices: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """Rows `indices` (sorted, in the joined numbering) of array `name` of every store."""
        parts = []
        for i, store in enumerate(self.stores):
            mine = indices[(indices >= offsets[i]) & (indices < offsets[i + 1])] - offsets[i]
            if len(mine):
                parts.append(np.asarray(store[name].get_orthogonal_selection((mine,))))
        return np.concatenate(parts)

    def batch(self, steps: np.ndarray) -> dict[str, torch.Tensor]:
        """The windows of `steps` (indices into the stores' joined steps) as tensors."""
        offsets = np.arange(-self.n_obs + 1, 1)
        frames = np.maximum(steps[:, None] + offsets[None], self.start[steps][:, None])
        future = np.minimum(steps[:, None] + np.arange(self.horizon)[None], self.end[steps][:, None] - 1)
        unique, inverse = np.unique(frames, return_inverse=True)
        ego = self._read("data/ego_rgb", unique, self.step_offsets)[inverse.reshape(frames.shape)]
        episodes, inverse_goal = np.unique(self.episode[steps], return_inverse=True)
        goal = self._read("meta/goal_rgb", episodes, self.episode_offsets)[inverse_goal]
        return {
            "ego": torch.from_numpy(ego),
            "goal": torch.from_numpy(goal),
            "grasping": torch.from_numpy(self.grasping[frames]),
            "actions": torch.from_numpy(self.actions[future]),
        }


def train(config: BcConfig, out: Path, *, resume: bool = False, progress: bool = True) -> Path:
    """Trains for `config.epochs` epochs (from the checkpoint in `out` with `resume`); returns the
    checkpoint's path.
    """
    _malloc_setup.apply()  # large buffers freed and made at every step stay mapped (esrp._malloc_setup)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    out.mkdir(parents=True, exist_ok=True)
    checkpoint = out / "ckpt.pt"
    if not resume and checkpoint.exists():
        raise ValueError(f"{out} already holds a run: pass --resume to go on with it, or another --out")
    device = resolve_device(config.device)
    torch.manual_seed(config.seed)
    windows = DemoWindows(config.demos, config.n_obs, config.horizon)
    if windows.resolution != config.resolution:
        raise ValueError(
            f"the demonstrations hold {windows.resolution} px views and the config says resolution = "
            f"{config.resolution}: set resolution = {windows.resolution} in [bc]"
        )
    model = DiffusionPolicy(config).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    epoch, steps = 0, 0
    if resume and checkpoint.exists():
        # More epochs (or another checkpoint interval, thread count or device) may be asked of a
        # resumed run.
        free = {"epochs", "checkpoint_every", "threads", "device"}
        state = load_resumable(checkpoint, "esrp-bc", config.to_dict(), free, device)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        epoch, steps = int(state["epoch"]), int(state["steps"])
        print(f"resuming {checkpoint} after epoch {epoch}", file=sys.stderr)
    (out / "config.json").write_text(json.dumps(config.to_dict(), indent=2) + "\n", encoding="utf-8")
    noise_scheduler, _ = schedulers(config)
    log_path = out / "log.csv"
    new_log = not log_path.exists() or epoch == 0
    if new_log:
        with open(log_path, "w", newline="") as file:
            csv.writer(file).writerow(["epoch", "steps", "loss", "mse", "ce", "lr", "seconds"])
    started = time.monotonic()
    model.train()
    while epoch < config.epochs:
        order = np.random.default_rng(config.seed + epoch).permutation(len(windows))
        sums = np.zeros(3)
        batches = 0
        for first in range(0, len(order), config.batch_size):
            batch = {
                key: value.to(device)
                for key, value in windows.batch(np.sort(order[first : first + config.batch_size])).items()
            }
            loss, mse, ce = bc_loss(model, noise_scheduler, batch)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"epoch {epoch + 1}: the loss is {loss.item()}")
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            optimizer.step()
            sums += (loss.item(), mse.item(), ce.item())
            batches += 1
            steps += 1
        epoch += 1
        mean = sums / max(batches, 1)
        with open(log_path, "a", newline="") as file:
            row = [epoch, steps, *(f"{v:.6f}" for v in mean), config.lr, f"{time.monotonic() - started:.1f}"]
            csv.writer(file).writerow(row)
        if progress:
            print(
                f"epoch {epoch}/{config.epochs}  loss {mean[0]:.4f} (mse {mean[1]:.4f}, ce {mean[2]:.4f})",
                file=sys.stderr,
            )
        if epoch % config.checkpoint_every == 0 or epoch == config.epochs:
            save_checkpoint(checkpoint, "esrp-bc", model, optimizer, epoch=epoch, steps=steps)
    if not checkpoint.exists():
        save_checkpoint(checkpoint, "esrp-bc", model, optimizer, epoch=epoch, steps=steps)
    return checkpoint
