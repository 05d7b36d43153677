"""`esrp train bc`: trains ESRP-BC (`esrp.agents.bc`) on an `esrp.demos/v1` store.

Samples are windows of the store: for step t of an episode, the ego views and grasp flags of steps
t-n+1..t (the episode's first repeated before its start) and the goal image, and the expert's
actions t..t+h-1 (its last repeated past its end), as Diffusion Policy pads. Each epoch visits every
step once in a seeded random order; a batch reads only the chunks its windows touch, or, with
`in_memory`, the views read into memory once at the start (the same batches).

A run folder holds `config.json` (the settings), `log.csv` (one line per epoch: epoch, optimizer
steps, mean loss, noise MSE and cross-entropy, learning rate, seconds) and `ckpt.pt` (model,
optimizer, epoch, random states: `--resume` goes on from it; `esrp eval --agent bc --checkpoint`
plays it). With `eval_every` (or `final_eval`), the held-out evaluations (`esrp.train.heldout`)
write `eval.csv` (one line each: epoch, optimizer steps, SR, OSR, RDR, episodes recorded and
failed, seconds) and their results files `eval/epoch-NNNN.jsonl`; the checkpoint is written before
each, so an evaluation an interruption cut short is finished first when the run resumes.
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
from ._training import resume_from, run_folder, save_checkpoint
from .heldout import EVAL_FIELDS, TrainServer, evaluate_checkpoint, heldout_scenes, read_eval_log

__all__ = ["FINE_TUNE_FREE", "LOG_FIELDS", "RESUME_FREE", "DemoWindows", "load_config", "train"]

LOG_FIELDS = ("epoch", "steps", "loss", "mse", "ce", "lr", "seconds")
"""The columns of a run's `log.csv`: one line per epoch."""

RESUME_FREE = frozenset(
    {"epochs", "checkpoint_every", "threads", "device", "in_memory"}
    | {name for name in BcConfig.__dataclass_fields__ if name.startswith("eval_")}
)
"""Settings a resumed run may change: more epochs, the checkpoint interval, threads, device, where
the batches are read from, and the held-out evaluation (none changes what is trained)."""

FINE_TUNE_FREE = RESUME_FREE | {"demos", "seed"}
"""Settings in which a run that starts from another run's weights (`train(init=...)`) may differ
from it: the model and the optimizer must be the same."""

_LOAD_BLOCK = 4096
"""Steps read at a time when a store's views are read into memory."""


def load_config(path: Path) -> BcConfig:
    """The `[bc]` table of a TOML file (or the top level of a JSON file) as a `BcConfig`."""
    table = read_table(path, "bc")
    try:
        return BcConfig.from_mapping(table)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: {error}") from None


class DemoWindows:
    """The training windows of one or more `esrp.demos/v1` stores (expert demonstrations and DAgger
    exports aggregated), read a batch at a time: from the stores' chunks, or with `in_memory` from
    copies of their views read into memory here (printing a line per store with `progress`).
    """

    def __init__(
        self,
        paths: str | Path | Sequence[str | Path],
        n_obs: int,
        horizon: int,
        *,
        in_memory: bool = False,
        progress: bool = False,
    ) -> None:
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
        self.n_obs, self.horizon = n_obs, horizon
        starts = np.concatenate([[0], ends[:-1]])
        self.episode = np.repeat(np.arange(len(ends)), ends - starts)
        self.start, self.end = starts[self.episode], ends[self.episode]
        self.actions = np.concatenate(actions)
        self.grasping = np.concatenate(grasping)
        # Where each store's steps and episodes begin in the joined numbering.
        self.step_offsets = np.cumsum([0, *(len(a) for a in actions)])
        self.episode_offsets = np.cumsum([0, *(len(e) for e in ends_list)])
        self.paths = [str(path) for path in listed]
        self.resolution = int(self.stores[0]["data/ego_rgb"].shape[1])
        """The views' side in pixels."""
        self.memory: dict[str, np.ndarray] = {}
        if in_memory:
            self._read_into_memory(progress)

    def __len__(self) -> int:
        return len(self.episode)

    def _read_into_memory(self, progress: bool) -> None:
        """Reads every store's ego views and goal images (its whole episodes) into `memory`, in the
        joined numbering.
        """
        side = self.resolution
        steps, episodes = int(self.step_offsets[-1]), int(self.episode_offsets[-1])
        mib = (steps + episodes) * side * side * 3 / 2**20
        if progress:
            print(
                f"reading {len(self.stores)} demonstration stores into memory: {steps} steps, "
                f"{episodes} episodes, {mib:.0f} MiB",
                file=sys.stderr,
            )
        ego = np.empty((steps, side, side, 3), dtype=np.uint8)
        goal = np.empty((episodes, side, side, 3), dtype=np.uint8)
        for i, store in enumerate(self.stores):
            started = time.monotonic()
            first, last = int(self.step_offsets[i]), int(self.step_offsets[i + 1])
            views = store["data/ego_rgb"]
            for start in range(first, last, _LOAD_BLOCK):
                end = min(start + _LOAD_BLOCK, last)
                ego[start:end] = views[start - first : end - first]
            begin, count = (
                int(self.episode_offsets[i]),
                int(self.episode_offsets[i + 1] - self.episode_offsets[i]),
            )
            goal[begin : begin + count] = store["meta/goal_rgb"][:count]
            if progress:
                print(
                    f"  {self.paths[i]}: {last - first} steps in {time.monotonic() - started:.1f} s",
                    file=sys.stderr,
                )
        self.memory = {"data/ego_rgb": ego, "meta/goal_rgb": goal}

    def _read(self, name: str, indices: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """Rows `indices` (sorted, in the joined numbering) of array `name` of every store."""
        held = self.memory.get(name)
        if held is not None:
            return np.asarray(held[indices])
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


def _trim_log(path: Path, fields: Sequence[str], epoch: int) -> None:
    """Makes `path` a CSV log of the epochs up to `epoch`: started over (its header only) when the
    run starts, else its lines after `epoch` (written before an interruption, past the checkpoint
    the run resumes from) dropped.
    """
    rows: list[list[str]] = []
    if epoch > 0 and path.exists():
        with open(path, newline="") as file:
            rows = [row for row in list(csv.reader(file))[1:] if row and int(row[0]) <= epoch]
    with open(path, "w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(fields)
        writer.writerows(rows)


def train(
    config: BcConfig,
    out: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    server: TrainServer | None = None,
    init: Path | None = None,
    final_eval: bool = False,
) -> Path:
    """Trains for `config.epochs` epochs (from the checkpoint in `out` with `resume`); returns the
    checkpoint's path.

    Args:
        config: The settings.
        out: The run folder.
        resume: Go on from `out/ckpt.pt` if it exists (else start).
        progress: Print a line per epoch (and the evaluations' progress) on stderr.
        server: The server of the held-out evaluations; None: one is started here when the run
            evaluates, and stopped at its end.
        init: Start from the model and optimizer of this checkpoint (of a model with the same
            settings, `FINE_TUNE_FREE` aside) instead of fresh weights; ignored when resuming.
        final_eval: Evaluate after the last epoch even with `eval_every` 0.

    Raises `ValueError` for bad settings or files, `EvalError` when an evaluation cannot run (and
    `EsrpError` for the server's errors).

    The epochs' loop stays here whole, top to bottom, as CleanRL keeps its training loop; what is
    set up before it and kept after each epoch (the demonstrations, resumption, the log, the
    held-out evaluations) are the helpers below.
    """
    _malloc_setup.apply()  # large buffers freed and made at every step stay mapped (esrp._malloc_setup)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    checkpoint = run_folder(out, resume)
    device = resolve_device(config.device)
    torch.manual_seed(config.seed)
    windows = _demo_windows(config, progress)
    model = DiffusionPolicy(config).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    epoch, steps = _resume_or_init(
        config, checkpoint, model, optimizer, device, resume=resume, init=init, progress=progress
    )
    (out / "config.json").write_text(json.dumps(config.to_dict(), indent=2) + "\n", encoding="utf-8")
    noise_scheduler, _ = schedulers(config)
    log_path = out / "log.csv"
    _trim_log(log_path, LOG_FIELDS, epoch)
    held_out = _HeldOut(config, out, checkpoint, windows.resolution, final_eval=final_eval, progress=progress)
    held_out.start_log(epoch)
    own_server = server is None
    used = server if server is not None else TrainServer()
    try:
        held_out.choose_scenes(used)
        # An evaluation the interrupted run owed (the checkpoint is written before each).
        if held_out.owed(epoch):
            held_out.run(used, epoch, steps)
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
            _log_epoch(log_path, config, epoch, steps, sums / max(batches, 1), started, progress)
            due = held_out.due(epoch)
            if epoch % config.checkpoint_every == 0 or epoch == config.epochs or due:
                save_checkpoint(checkpoint, "esrp-bc", model, optimizer, epoch=epoch, steps=steps)
            if due:
                held_out.run(used, epoch, steps)
        if not checkpoint.exists():
            save_checkpoint(checkpoint, "esrp-bc", model, optimizer, epoch=epoch, steps=steps)
    finally:
        if own_server:
            used.close()
    return checkpoint


def _demo_windows(config: BcConfig, progress: bool) -> DemoWindows:
    """The training windows of `config`'s demonstration stores (read into memory with `in_memory`),
    checked to hold views of `config.resolution` pixels.
    """
    windows = DemoWindows(
        config.demos, config.n_obs, config.horizon, in_memory=config.in_memory, progress=progress
    )
    if windows.resolution != config.resolution:
        raise ValueError(
            f"the demonstrations hold {windows.resolution} px views and the config says resolution = "
            f"{config.resolution}: set resolution = {windows.resolution} in [bc]"
        )
    return windows


def _resume_or_init(
    config: BcConfig,
    checkpoint: Path,
    model: DiffusionPolicy,
    optimizer: torch.optim.Optimizer,
    device: torch.device,
    *,
    resume: bool,
    init: Path | None,
    progress: bool,
) -> tuple[int, int]:
    """The epoch and optimizer step the run goes on after. With `resume` and a `checkpoint`, those
    of the checkpoint, whose model and optimizer (and torch's random state) are loaded: more epochs
    (or another checkpoint interval, thread count, device or evaluation) may be asked of a resumed
    run. Else 0 and 0, from the model and optimizer of `init` when given (a model with the same
    settings, `FINE_TUNE_FREE` aside), or from fresh weights.
    """
    if resume and checkpoint.exists():
        state = resume_from(checkpoint, "esrp-bc", model, optimizer, RESUME_FREE, device)
        epoch, steps = int(state["epoch"]), int(state["steps"])
        print(f"resuming {checkpoint} after epoch {epoch}", file=sys.stderr)
        return epoch, steps
    if init is not None:
        resume_from(init, "esrp-bc", model, optimizer, FINE_TUNE_FREE, device, restore_rng=False)
        if progress:
            print(f"starting from the model and optimizer of {init}", file=sys.stderr)
    return 0, 0


def _log_epoch(
    path: Path,
    config: BcConfig,
    epoch: int,
    steps: int,
    mean: np.ndarray,
    started: float,
    progress: bool,
) -> None:
    """Appends epoch `epoch`'s line to the run's `log.csv` at `path` (`mean`: the epoch's mean loss,
    noise MSE and cross-entropy; `started`: the training's `time.monotonic()` at its start), and
    prints its losses with `progress`.
    """
    with open(path, "a", newline="") as file:
        row = [
            epoch,
            steps,
            *(f"{v:.6f}" for v in mean),
            config.lr,
            f"{time.monotonic() - started:.1f}",
        ]
        csv.writer(file).writerow(row)
    if progress:
        losses = f"loss {mean[0]:.4f} (mse {mean[1]:.4f}, ce {mean[2]:.4f})"
        print(f"epoch {epoch}/{config.epochs}  {losses}", file=sys.stderr)


class _HeldOut:
    """The held-out evaluations of a run (`eval_every`, or after the last epoch with `final_eval`):
    when one is due, and each run on the run's checkpoint, its results in `eval/epoch-NNNN.jsonl`
    and its line in `eval.csv`. A run that does not evaluate chooses no scenes and writes no log.
    """

    def __init__(
        self,
        config: BcConfig,
        out: Path,
        checkpoint: Path,
        resolution: int,
        *,
        final_eval: bool,
        progress: bool,
    ) -> None:
        self.config = config
        self.out = out
        self.checkpoint = checkpoint
        self.resolution = resolution
        self.progress = progress
        self.evaluating = config.eval_every > 0 or final_eval
        """Whether the run evaluates at all."""
        self.log_path = out / "eval.csv"
        self.scenes: list[str] = []
        """The scenes every evaluation plays (`choose_scenes`)."""

    def start_log(self, epoch: int) -> None:
        """Makes `eval.csv` the log of the evaluations up to `epoch` (when the run evaluates)."""
        if self.evaluating:
            _trim_log(self.log_path, EVAL_FIELDS, epoch)

    def choose_scenes(self, server: TrainServer) -> None:
        """Fixes the scenes of the run's evaluations (`heldout_scenes`; none when it does not
        evaluate, and then `server` is not asked).
        """
        self.scenes = heldout_scenes(server, self.config) if self.evaluating else []

    def due(self, epoch: int) -> bool:
        """Whether an evaluation follows epoch `epoch`: every `eval_every` epochs, and after the last."""
        config = self.config
        return self.evaluating and (
            (config.eval_every > 0 and epoch % config.eval_every == 0) or epoch == config.epochs
        )

    def owed(self, epoch: int) -> bool:
        """Whether the evaluation after epoch `epoch`, the one a resumed run starts after, is due and
        missing from `eval.csv` (an interruption cut it short).
        """
        return (
            epoch > 0
            and self.due(epoch)
            and not any(int(row["epoch"]) == epoch for row in read_eval_log(self.log_path))
        )

    def run(self, server: TrainServer, epoch: int, steps: int) -> None:
        """Evaluates the checkpoint written after epoch `epoch` (`steps` optimizer steps) on `server`,
        appends its line to `eval.csv` and, with `progress`, prints it.
        """
        result = evaluate_checkpoint(
            server,
            self.checkpoint,
            self.config,
            self.scenes,
            self.resolution,
            self.out / "eval" / f"epoch-{epoch:04d}.jsonl",
            progress=self.progress,
        )
        with open(self.log_path, "a", newline="") as file:
            csv.writer(file).writerow(result.row(epoch, steps))
        if self.progress:
            print(f"held-out after epoch {epoch}: {result.text()}", file=sys.stderr)
