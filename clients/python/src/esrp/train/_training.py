"""What `esrp train bc` and `esrp train ppo` share: the run folder, checkpoints written atomically,
and resumption that refuses other settings. The agents' `checkpoint` option is
`esrp.agents._checkpoint`: an agent loads a checkpoint without this module.
"""

from __future__ import annotations

import csv
import os
import sys
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from .._signals import deferred
from ..agents._checkpoint import read_checkpoint

__all__ = [
    "load_resumable",
    "logged_seconds",
    "resume_from",
    "rewrite_csv",
    "run_folder",
    "save_checkpoint",
    "save_for_playing",
    "settings_differences",
    "trim_epoch_log",
]


def run_folder(out: Path, resume: bool) -> Path:
    """The path of the checkpoint of run folder `out`, `out/ckpt.pt`, checked and not made: raises
    `ValueError` when `out` is a file, holds a DAgger run (`state.json`: `esrp train bc --dagger`'s),
    or already holds a run's checkpoint and not `resume`; with
    `resume` and no checkpoint there, says on stderr that the run starts anew (a mistyped `--out`
    shows at once).

    A trainer makes the folder (`out.mkdir(parents=True, exist_ok=True)`) only once every check
    that can fail before training has passed (the demonstrations, the settings, the server), so
    that a run refused at its start leaves no folder behind.
    """
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} is a file, not a run folder: give another --out")
    if (out / "state.json").exists():
        # `esrp train bc --dagger`'s folder: a run here would write its files among the DAgger run's.
        raise ValueError(
            f"{out} holds a DAgger run (state.json): esrp train bc --dagger --resume goes on with it; "
            "give another --out"
        )
    checkpoint = out / "ckpt.pt"
    if not resume and checkpoint.exists():
        raise ValueError(f"{out} already holds a run: pass --resume to go on with it, or another --out")
    if resume and not checkpoint.exists():
        print(f"no checkpoint in {out} to resume: starting a new run there", file=sys.stderr)
    return checkpoint


def save_checkpoint(
    path: Path,
    kind: str,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    *,
    extra: Mapping[str, Any] | None = None,
    **progress: int,
) -> None:
    """Writes `model` (with its `config`), `optimizer`, `progress` (epoch, update, steps...) and
    torch's random state to `path` as checkpoint kind `kind`, atomically: the checkpoint is written
    to a file beside it, flushed to disk, and renamed over `path`, so a crash never leaves half a
    checkpoint (the earlier one stays whole until the new one is). `extra` entries are added last:
    a run whose played weights are not its trained ones (a moving average) gives those as `model`
    and the trained ones as `train_model`.
    """
    config: Any = model.config
    state = {
        "kind": kind,
        "config": config.to_dict(),
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        **progress,
        "torch_rng": torch.get_rng_state(),
        **(extra or {}),
    }
    _save_atomically(state, path)


def _save_atomically(state: Mapping[str, Any], path: Path) -> None:
    """`torch.save`s `state` to a file beside `path`, flushed to disk, then renamed over `path`. A
    signal that comes meanwhile (Ctrl-C, SIGTERM) waits until the checkpoint is in place: torch's
    writer does not survive an exception raised inside it. A file left half-written by an error is
    removed.
    """
    partial = path.with_suffix(".partial")
    with deferred():
        try:
            with open(partial, "wb") as file:
                torch.save(state, file)
                file.flush()
                os.fsync(file.fileno())
            partial.replace(path)
        finally:
            partial.unlink(missing_ok=True)


def settings_differences(
    held: Mapping[str, Any], wanted: Mapping[str, Any], free: Collection[str]
) -> list[str]:
    """The settings (but `free` ones) whose values differ between a run's `held` ones (its
    checkpoint's config) and the `wanted` ones, in words: `lr: 0.0003 → 0.001`, one per setting.
    """
    return [
        f"{key}: {held.get(key)!r} → {wanted.get(key)!r}"
        for key in sorted(set(held) | set(wanted))
        if key not in free and held.get(key) != wanted.get(key)
    ]


PLAYING_KEYS = ("kind", "config", "model", "epoch", "steps", "update")
"""What a checkpoint made for playing keeps (those present): the played weights, their settings and
progress; not the optimizer, the trained weights beside an average, or the random state."""


def save_for_playing(source: Path, target: Path) -> None:
    """Writes the checkpoint at `source` as one made for playing to `target` (atomically): what
    `PLAYING_KEYS` names, a fifth of a resumable ESRP-BC checkpoint. `esrp eval --checkpoint` and
    `esrp train bc --init` take it; `--resume` does not.
    """
    state = torch.load(source, map_location="cpu", weights_only=False)
    _save_atomically({k: state[k] for k in PLAYING_KEYS if k in state}, target)


def load_resumable(
    path: Path,
    kind: str,
    settings: Mapping[str, Any],
    free: Collection[str],
    device: torch.device,
    *,
    restore_rng: bool = True,
    legacy: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The checkpoint at `path` to resume a run with `settings` (a config's `to_dict()`); raises
    `ValueError` for another kind of checkpoint or other settings than `free` ones. Settings the
    checkpoint's config lacks (it predates them) are taken as `legacy` gives them. Restores
    torch's random state (unless not `restore_rng`: a run that starts from another's weights).
    """
    state = read_checkpoint(path, kind, kind, device)
    state["config"] = {**(legacy or {}), **state["config"]}
    different = settings_differences(state["config"], settings, free)
    if different:
        raise ValueError(f"{path} was trained with other settings ({'; '.join(different)})")
    if restore_rng:
        if "torch_rng" not in state:
            raise ValueError(f"{path} holds the model only (a checkpoint for playing): it cannot be resumed")
        torch.set_rng_state(state["torch_rng"].cpu())
    return state


def resume_from(
    path: Path,
    kind: str,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    free: Collection[str],
    device: torch.device,
    *,
    restore_rng: bool = True,
    legacy: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Loads the model and optimizer of the checkpoint at `path` (`load_resumable`, against the
    settings of `model.config`: kind `kind`, the same settings but `free` ones, `legacy` those it
    predates) into `model` and `optimizer`; returns the checkpoint, for its progress (epoch,
    update, steps...). The model gets the trained weights: `train_model` where the checkpoint has
    them apart from the played ones (`save_checkpoint`'s `extra`), else `model`. A checkpoint made
    for playing (no optimizer) leaves `optimizer` as it is; with `restore_rng` it is refused
    (`load_resumable`: it cannot be resumed).
    """
    config: Any = model.config
    state = load_resumable(path, kind, config.to_dict(), free, device, restore_rng=restore_rng, legacy=legacy)
    model.load_state_dict(state.get("train_model", state["model"]))
    if "optimizer" in state:
        optimizer.load_state_dict(state["optimizer"])
    return state


def trim_epoch_log(path: Path, fields: Sequence[str], epoch: int) -> None:
    """Makes `path` a CSV log of the epochs up to `epoch`: started over (its header only) when the
    run starts, else its lines after `epoch` (written before an interruption, past the checkpoint
    the run resumes from) dropped. The file is replaced whole (`rewrite_csv`).
    """
    rows: list[list[str]] = []
    if epoch > 0 and path.exists():
        with open(path, newline="") as file:
            rows = [row for row in list(csv.reader(file))[1:] if row and int(row[0]) <= epoch]
    rewrite_csv(path, [list(fields), *rows])


def rewrite_csv(path: Path, rows: Sequence[Sequence[str]]) -> None:
    """Writes `rows` as the CSV file `path` atomically: into a temporary file beside it, then
    renamed over it, so that an interruption leaves the old log or the new one, never a part.
    """
    partial = path.with_name(f".{path.name}.partial")
    with open(partial, "w", newline="") as file:
        csv.writer(file).writerows(rows)
        file.flush()
        os.fsync(file.fileno())
    os.replace(partial, path)


def logged_seconds(path: Path) -> float:
    """The `seconds` column of the last line of the CSV log `path`: the training time a resumed run
    goes on from, so that its lines count on from the interrupted run's (0.0 when the log is
    missing, holds no line, or has no such column).
    """
    if not path.exists():
        return 0.0
    with open(path, newline="") as file:
        rows = [row for row in csv.reader(file) if row]
    if len(rows) < 2 or "seconds" not in rows[0]:
        return 0.0
    at = rows[0].index("seconds")
    try:
        seconds = float(rows[-1][at])
    except (IndexError, ValueError):
        return 0.0
    return seconds if seconds >= 0 and seconds != float("inf") else 0.0
