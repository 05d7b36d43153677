"""`esrp train bc`: trains ESRP-BC (`esrp.agents.bc`) on an `esrp.demos/v1` store.

Samples are windows of the store: for step t of an episode, the ego views and grasp flags of steps
t-n+1..t (the episode's first repeated before its start) and the goal image, and the h actions the
window learns (`DemoWindows` says which: a trajectory's own next actions, or the planner's plan from
that state), with a mask where there is none (past the episode's end, or past what the plan
covered): those positions count in no loss. Each epoch visits every step once: the episodes are cut
into runs of `span` consecutive steps (at a random phase), the runs are shuffled, and a batch takes
the next `batch_size` steps of them, so that the windows of a run share their views and goal, and
each is encoded once. A batch reads only the chunks its windows touch, or, with `in_memory`, the
views read into memory once at the start (the same batches).

The learning rate follows `BcConfig.lr_at` step by step, and with `ema` the checkpoint's `model` is
the weights' moving average (diffusers' `EMAModel`), the policy `esrp eval --agent bc` plays and the
held-out evaluations measure; the trained weights and the average's state are kept beside it, for
`--resume`.

A run folder holds `config.json` (the settings), `log.csv` (one line per epoch: epoch, optimizer
steps, mean loss, noise MSE and cross-entropy, learning rate, seconds) and `ckpt.pt` (model,
optimizer, epoch, random states: `--resume` goes on from it; `esrp eval --agent bc --checkpoint`
plays it). With `eval_every` (or `final_eval`), the held-out evaluations (`esrp.train.heldout`)
write `eval.csv` (one line each: epoch, optimizer steps, SR, OSR, RDR, episodes recorded and
failed, seconds) and their results files `eval/epoch-NNNN.jsonl`; the checkpoint is written before
each, so an evaluation an interruption cut short is finished first when the run resumes. The
checkpoint with the best held-out SR so far is kept as `best.pt` (`best.json` says which epoch):
the one to evaluate on the test split.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from .. import _malloc_setup
from ..agents.bc import LEGACY_SETTINGS, BcConfig, DiffusionPolicy, bc_loss, random_shift, schedulers
from ..agents.encoders import resolve_device
from ._config import read_table
from ._training import (
    logged_seconds,
    resume_from,
    run_folder,
    save_checkpoint,
    save_for_playing,
    trim_epoch_log,
)
from .heldout import EVAL_FIELDS, TrainServer, evaluate_checkpoint, heldout_scenes, read_eval_log

__all__ = [
    "FINE_TUNE_FREE",
    "LOG_FIELDS",
    "NO_LABEL",
    "RESUME_FREE",
    "DemoWindows",
    "check_resolution",
    "load_config",
    "train",
]

LOG_FIELDS = ("epoch", "steps", "loss", "mse", "ce", "lr", "seconds")
"""The columns of a run's `log.csv`: one line per epoch."""

RESUME_FREE = frozenset(
    {"epochs", "checkpoint_every", "threads", "device", "in_memory"}
    | {name for name in BcConfig.__dataclass_fields__ if name.startswith("eval_")}
)
"""Settings a resumed run may change: more epochs, the checkpoint interval, threads, device, where
the batches are read from, and the held-out evaluation (none changes what is trained)."""

FINE_TUNE_FREE = RESUME_FREE | {"demos", "seed", "lr"}
"""Settings in which a run that starts from another run's weights (`train(init=...)`) may differ
from it: the model and the optimizer must be the same."""

_LOAD_BLOCK = 4096
"""Steps read at a time when a store's views are read into memory."""

NO_LABEL = 255
"""A target position without a label (`esrp.train.demos.NO_ACTION` in a store's `data/label_chunk`)."""


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

    What a window at step t learns (`targets`, `NO_LABEL` where nothing), by the store's labels:
    - a trajectory's (the expert's, or recorded episodes'): its actions t..t+h-1, those within the
      episode;
    - a DAgger store's with `data/label_chunk`: the first h actions of the planner's plan from that
      state, those the plan has;
    - a DAgger store's without it (written before it existed): the planner's next action alone.
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
        local_ends: list[np.ndarray] = []
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
            local_ends.append(ends)
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
        self.targets = np.concatenate(
            [
                _store_targets(store, store_actions, store_ends, horizon)
                for store, store_actions, store_ends in zip(self.stores, actions, local_ends, strict=True)
            ]
        )
        """The labels each step's window learns, (steps, h) uint8, `NO_LABEL` where none."""
        # Where each store's steps and episodes begin in the joined numbering.
        self.step_offsets = np.cumsum([0, *(len(a) for a in actions)])
        self.episode_offsets = np.cumsum([0, *(len(e) for e in ends_list)])
        self.paths = [str(path) for path in listed]
        digest = hashlib.sha256()
        for part in (ends, self.actions, self.grasping, self.targets):
            digest.update(np.ascontiguousarray(part).tobytes())
        self.fingerprint = f"{len(ends)} episodes, {len(self.episode)} steps, {digest.hexdigest()[:16]}"
        """What the windows learn from, in a line: episodes, steps and a hash of their bounds, actions,
        grasp flags and labels (a store appended to or exported again changes it)."""
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

    def epoch_order(self, seed: int, span: int) -> np.ndarray:
        """Every step once, in runs of up to `span` consecutive steps of one episode (cut at a phase
        drawn per episode), the runs in a random order; all drawn from `seed`.
        """
        rng = np.random.default_rng(seed)
        steps = np.arange(len(self.episode))
        phase = rng.integers(0, span, size=int(self.episode[-1]) + 1)
        run = (steps - self.start + phase[self.episode]) // span
        # One key per run: runs of one episode are numbered apart from any other episode's.
        longest = int((self.end - self.start).max()) // span + 2
        _, run_of = np.unique(self.episode * longest + run, return_inverse=True)
        rank = rng.permutation(int(run_of.max()) + 1)
        return steps[np.lexsort((steps, rank[run_of]))]

    def batch(self, steps: np.ndarray) -> dict[str, torch.Tensor]:
        """The windows of `steps` (indices into the stores' joined steps) as tensors: each view and
        goal they use once (`frames`, `goals`) with each window's indices into them (`frame_index`
        (B, n), `goal_index` (B,)), the grasp flags (B, n), and the targets: `actions` (B, h) with
        `mask` true where a label is (a position without one repeats the label before it, so that
        the chunk is whole; it counts in no loss).
        """
        offsets = np.arange(-self.n_obs + 1, 1)
        frames = np.maximum(steps[:, None] + offsets[None], self.start[steps][:, None])
        unique, inverse = np.unique(frames, return_inverse=True)
        ego = self._read("data/ego_rgb", unique, self.step_offsets)
        episodes, goal_index = np.unique(self.episode[steps], return_inverse=True)
        goal = self._read("meta/goal_rgb", episodes, self.episode_offsets)
        targets = self.targets[steps]
        mask = targets != NO_LABEL
        actions = targets.astype(np.int64)
        for k in range(1, actions.shape[1]):
            actions[:, k] = np.where(mask[:, k], actions[:, k], actions[:, k - 1])
        return {
            "frames": torch.from_numpy(ego),
            "frame_index": torch.from_numpy(inverse.reshape(frames.shape).astype(np.int64)),
            "goals": torch.from_numpy(goal),
            "goal_index": torch.from_numpy(goal_index.reshape(-1).astype(np.int64)),
            "grasping": torch.from_numpy(self.grasping[frames]),
            "actions": torch.from_numpy(actions),
            "mask": torch.from_numpy(mask),
        }


def _store_targets(store: Any, actions: np.ndarray, ends: np.ndarray, horizon: int) -> np.ndarray:  # noqa: ANN401
    """The targets of one store's steps (`DemoWindows.targets`): `actions` its labels, `ends` its
    episodes' ends.
    """
    steps = len(actions)
    targets = np.full((steps, horizon), NO_LABEL, dtype=np.uint8)
    if "data/label_chunk" in store:
        chunk = np.asarray(store["data/label_chunk"][:steps], dtype=np.uint8)
        width = min(horizon, chunk.shape[1])
        targets[:, :width] = chunk[:, :width]
        return targets
    if store.attrs.get("labels") == "planner":
        targets[:, 0] = actions
        return targets
    starts = np.concatenate([[0], ends[:-1]])
    end = np.repeat(ends, ends - starts)
    ahead = np.arange(steps)[:, None] + np.arange(horizon)[None]
    within = ahead < end[:, None]
    targets[within] = actions[ahead[within]]
    return targets


def train(
    config: BcConfig,
    out: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    server: TrainServer | None = None,
    init: Path | None = None,
    init_average: bool = False,
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
            settings, `FINE_TUNE_FREE` aside) instead of fresh weights; ignored when resuming. A
            checkpoint made for playing (the model alone, as `docs/results/checkpoints` holds) gives
            its weights, and the optimizer starts afresh.
        init_average: With `init` and `ema`, go on with `init`'s average of the weights (its
            shadow weights and step count, so its decay) instead of starting one from the loaded
            weights: a fine-tuning then moves the played weights gradually.
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
    epoch, steps, average = _resume_or_init(
        config,
        checkpoint,
        model,
        optimizer,
        device,
        resume=resume,
        init=init,
        init_average=init_average,
        progress=progress,
        demos=windows.fingerprint,
    )
    total_steps = config.epochs * math.ceil(len(windows) / config.batch_size)

    def save() -> None:
        extra: dict[str, Any] = {"demos_fingerprint": windows.fingerprint}
        if average is not None:
            extra |= {
                "model": average.weights(model),
                "train_model": model.state_dict(),
                "ema": average.state(),
            }
        save_checkpoint(checkpoint, "esrp-bc", model, optimizer, extra=extra, epoch=epoch, steps=steps)

    noise_scheduler, _ = schedulers(config)
    log_path = out / "log.csv"
    held_out = _HeldOut(config, out, checkpoint, windows.resolution, final_eval=final_eval, progress=progress)
    own_server = server is None
    used = server if server is not None else TrainServer()
    try:
        held_out.choose_scenes(used)
        # Every check that can refuse the run has passed (the folder, the demonstrations, the
        # settings, the initial weights, the server and its held-out scenes): the run folder is
        # made now, so that a refused run leaves none behind.
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps(config.to_dict(), indent=2) + "\n", encoding="utf-8")
        trim_epoch_log(log_path, LOG_FIELDS, epoch)
        held_out.start_log(epoch)
        # An evaluation the interrupted run owed (the checkpoint is written before each); or, if
        # it was made, its checkpoint kept as best.pt where an interruption cut that short.
        if held_out.owed(epoch):
            held_out.run(used, epoch, steps)
        elif epoch > 0 and held_out.evaluating:
            held_out.keep_best(epoch)
        # A resumed run's `seconds` go on from the interrupted run's last logged epoch.
        started = time.monotonic() - logged_seconds(log_path)
        model.train()
        while epoch < config.epochs:
            order = windows.epoch_order(config.seed + epoch, config.span)
            sums = np.zeros(3)
            batches = 0
            for first in range(0, len(order), config.batch_size):
                read = windows.batch(np.sort(order[first : first + config.batch_size]))
                read["frames"] = random_shift(read["frames"], config.augment_shift)
                read["goals"] = random_shift(read["goals"], config.augment_shift)
                batch = {key: value.to(device) for key, value in read.items()}
                loss, mse, ce = bc_loss(model, noise_scheduler, batch)
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"epoch {epoch + 1}: the loss is {loss.item()}")
                for group in optimizer.param_groups:
                    group["lr"] = config.lr_at(steps, total_steps)
                optimizer.zero_grad()
                loss.backward()  # type: ignore[no-untyped-call]
                optimizer.step()
                if average is not None:
                    average.update(model)
                sums += (loss.item(), mse.item(), ce.item())
                batches += 1
                steps += 1
            epoch += 1
            lr = optimizer.param_groups[0]["lr"]
            _log_epoch(log_path, config, epoch, steps, sums / max(batches, 1), lr, started, progress)
            due = held_out.due(epoch)
            if epoch % config.checkpoint_every == 0 or epoch == config.epochs or due:
                save()
            if due:
                held_out.run(used, epoch, steps)
        if not checkpoint.exists():
            save()
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
    check_resolution(windows.resolution, config)
    return windows


def check_same_demos(checkpoint: Path, began: object, now: str) -> None:
    """Raises `ValueError` unless a resumed run's stores hold what it began with: `began`, the
    `DemoWindows.fingerprint` its checkpoint keeps (None in a checkpoint from before it: not
    checked), against `now`, theirs today.
    """
    if began is not None and began != now:
        raise ValueError(
            f"{checkpoint} was trained on other demonstrations ({began}; the stores now hold {now}): a "
            "store was exported again or appended to since the run began; resume with the stores it "
            "began with, or start another run"
        )


def check_resolution(resolution: int, config: BcConfig) -> None:
    """Raises `ValueError` unless demonstrations of `resolution` px views suit `config`."""
    if resolution != config.resolution:
        raise ValueError(
            f"the demonstrations hold {resolution} px views and the config says resolution = "
            f"{config.resolution}: set resolution = {resolution} in [bc]"
        )


class _Average:
    """The moving average of a model's weights (diffusers' `EMAModel` with Diffusion Policy's decay:
    1 - (1 + step) ** -power, at most `ema_max_decay`), updated after each optimizer step.
    """

    def __init__(self, model: DiffusionPolicy, config: BcConfig) -> None:
        from diffusers.training_utils import EMAModel

        self.ema = EMAModel(
            model.parameters(),
            decay=config.ema_max_decay,
            use_ema_warmup=True,
            inv_gamma=1.0,
            power=config.ema_power,
        )

    def update(self, model: DiffusionPolicy) -> None:
        """Folds the model's weights after an optimizer step into the average."""
        self.ema.step(model.parameters())

    def weights(self, model: DiffusionPolicy) -> dict[str, torch.Tensor]:
        """`model.state_dict()` with the averaged parameters in place of the trained ones."""
        state = model.state_dict()
        for (name, _), shadow in zip(model.named_parameters(), self.ema.shadow_params, strict=True):
            state[name] = shadow.detach().clone()
        return state

    def state(self) -> dict[str, Any]:
        """What `load` takes back: the average and its step count."""
        return cast(dict[str, Any], self.ema.state_dict())

    def load(self, state: dict[str, Any]) -> None:
        """Restores `state()` of a checkpoint."""
        self.ema.load_state_dict(state)


def _resume_or_init(
    config: BcConfig,
    checkpoint: Path,
    model: DiffusionPolicy,
    optimizer: torch.optim.Optimizer,
    device: torch.device,
    *,
    resume: bool,
    init: Path | None,
    init_average: bool,
    progress: bool,
    demos: str,
) -> tuple[int, int, _Average | None]:
    """The epoch and optimizer step the run goes on after, and the weights' average (None without
    `ema`). With `resume` and a `checkpoint`, those of the checkpoint, whose trained model,
    optimizer, average (and torch's random state) are loaded: more epochs (or another checkpoint
    interval, thread count, device or evaluation) may be asked of a resumed run. Else 0 and 0,
    from the trained model and optimizer of `init` when given (a model with the same settings,
    `FINE_TUNE_FREE` aside; its average starts anew from them, or with `init_average` goes on from
    `init`'s), or from fresh weights. A resumed run's demonstrations (`demos`: their
    `DemoWindows.fingerprint`) must be those it began with, where its checkpoint says which.
    """
    if resume and checkpoint.exists():
        state = resume_from(
            checkpoint, "esrp-bc", model, optimizer, RESUME_FREE, device, legacy=LEGACY_SETTINGS
        )
        check_same_demos(checkpoint, state.get("demos_fingerprint"), demos)
        epoch, steps = int(state["epoch"]), int(state["steps"])
        if epoch > config.epochs:
            raise ValueError(
                f"{checkpoint} has trained {epoch} epochs, more than the {config.epochs} asked: "
                f"ask for {epoch} or more to go on"
            )
        average = _Average(model, config) if config.ema else None
        if average is not None and "ema" in state:
            average.load(state["ema"])
        print(f"resuming {checkpoint} after epoch {epoch}", file=sys.stderr)
        return epoch, steps, average
    initial: dict[str, Any] | None = None
    if init is not None:
        initial = resume_from(
            init,
            "esrp-bc",
            model,
            optimizer,
            FINE_TUNE_FREE,
            device,
            restore_rng=False,
            legacy=LEGACY_SETTINGS,
        )
        if init_average and config.ema and "ema" not in initial:
            raise ValueError(f"{init} holds no average of the weights to go on with")
        if progress:
            what = "model and optimizer" if "optimizer" in initial else "model (it holds no optimizer)"
            kept = " and its weights' average" if init_average and config.ema else ""
            print(f"starting from the {what}{kept} of {init}", file=sys.stderr)
    average = _Average(model, config) if config.ema else None
    if average is not None and init_average and initial is not None:
        average.load(initial["ema"])
    return 0, 0, average


def _log_epoch(
    path: Path,
    config: BcConfig,
    epoch: int,
    steps: int,
    mean: np.ndarray,
    lr: float,
    started: float,
    progress: bool,
) -> None:
    """Appends epoch `epoch`'s line to the run's `log.csv` at `path` (`mean`: the epoch's mean loss,
    noise MSE and cross-entropy; `lr`: the learning rate of its last step; `started`: the
    training's `time.monotonic()` at its start), and prints its losses with `progress`.
    """
    with open(path, "a", newline="") as file:
        row = [
            epoch,
            steps,
            *(f"{v:.6f}" for v in mean),
            f"{lr:.6g}",
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
            trim_epoch_log(self.log_path, EVAL_FIELDS, epoch)

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
        if self.config.eval_keep_checkpoints:
            save_for_playing(self.checkpoint, self.out / "eval" / f"epoch-{epoch:04d}.pt")
        with open(self.log_path, "a", newline="") as file:
            csv.writer(file).writerow(result.row(epoch, steps))
        if self.progress:
            print(f"held-out after epoch {epoch}: {result.text()}", file=sys.stderr)
        self.keep_best(epoch)

    def keep_best(self, epoch: int) -> None:
        """Copies the checkpoint of epoch `epoch` to `best.pt` (atomically) when its held-out SR is
        the highest in `eval.csv` (the earliest of equals), and says so in `best.json`: the model
        selected on held-out scenes alone, never on the test split.
        """
        rows = read_eval_log(self.log_path)
        if not rows:
            return
        best = max(rows, key=lambda row: (float(row["sr"]), -int(row["epoch"])))
        if int(best["epoch"]) != epoch:
            return
        partial = self.out / "best.partial"
        shutil.copyfile(self.checkpoint, partial)
        partial.replace(self.out / "best.pt")
        chosen = {
            "epoch": epoch,
            "steps": int(best["steps"]),
            "sr": float(best["sr"]),
        }
        (self.out / "best.json").write_text(json.dumps(chosen) + "\n", encoding="utf-8")
