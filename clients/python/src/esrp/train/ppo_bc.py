"""`esrp train ppo-bc`: ESRP-PPO's network (`esrp.agents.ppo.PpoNet`) trained by imitation on
`esrp.demos/v1` stores, the start of a PPO fine-tuning (`esrp train ppo` with `init`): the
behaviour-cloning-then-RL recipe of PIRLNav (Ramrakhya et al., CVPR 2023), beyond the paper's
ESRP-PPO, which starts from random weights.

An epoch visits every labelled step once. The episodes, shuffled, are laid end to end and cut into
`streams` parallel streams; the streams are read `seq_len` steps at a time (one batch: `streams` ×
`seq_len` steps, time-major), the LSTM's state carried from one batch to the next without
gradients through it (truncated back-propagation) and zeroed at each episode's first step, as a
PPO rollout of `streams` environments is read. No step is padding. The loss is the cross-entropy of
the actor's logits against the store's label at each step (a trajectory's own action, or a DAgger
store's planner label; steps without one count in no loss); the critic head is left to the PPO
fine-tuning, whose `critic_warmup` updates train it alone before the policy moves. With
`augment_shift`, the ego views and goal images are shifted at random (DrQ's shift, each image its
own). The learning rate warms up linearly over `lr_warmup_steps`, then follows a cosine to zero.

A run folder holds `config.json` (the `[ppo]` and `[ppo_bc]` tables), `log.csv` (one line per
epoch: epoch, optimizer steps, mean loss, accuracy of the most likely action, learning rate,
seconds) and `ckpt.pt`, an ESRP-PPO checkpoint (`esrp eval --agent ppo --checkpoint RUN/ckpt.pt`
plays it, `init` starts a PPO run from it) with the optimizer and the epoch, which `--resume` goes
on from.
"""

from __future__ import annotations

import csv
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812 - the usual name

from .. import _malloc_setup
from ..agents._config import check_kinds, reject_unknown
from ..agents.bc import random_shift
from ..agents.encoders import resolve_device
from ..agents.ppo import NETWORK_SETTINGS, PpoConfig, PpoNet
from ._config import read_table
from ._training import (
    logged_seconds,
    resume_from,
    run_folder,
    save_checkpoint,
    settings_differences,
    trim_epoch_log,
)
from .bc import NO_LABEL, DemoWindows, check_same_demos
from .ppo import load_config, load_initial_weights

__all__ = [
    "LOG_FIELDS",
    "EpochStats",
    "ImitationConfig",
    "imitation_loss",
    "load_configs",
    "stream_order",
    "train",
]

LOG_FIELDS = ("epoch", "steps", "loss", "accuracy", "lr", "seconds")
"""The columns of a run's `log.csv`: one line per epoch."""


@dataclass
class ImitationConfig:
    """The `[ppo_bc]` table: the demonstrations and how the network learns them."""

    demos: list[str] = field(default_factory=list)
    """The `esrp.demos/v1` stores (one path, or several aggregated), at the network's resolution."""
    epochs: int = 30
    streams: int = 16
    seq_len: int = 64
    lr: float = 3e-4
    lr_warmup_steps: int = 200
    weight_decay: float = 0.0
    max_grad_norm: float = 0.5
    augment_shift: int = 4
    seed: int = 0
    threads: int = 0
    init: str | None = None
    """An ESRP-PPO checkpoint whose weights the network starts from (a fine-tuning, e.g. on
    DAgger stores added to the demonstrations), with a fresh optimizer and schedule."""

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> ImitationConfig:
        """A config from a mapping; unknown keys and bad values raise `ValueError`."""
        reject_unknown(cls, values, "ppo_bc")
        settings = dict(values)
        if isinstance(settings.get("demos"), str):
            settings["demos"] = [settings["demos"]]
        config = cls(**settings)
        config.validate()
        return config

    def validate(self) -> None:
        """Raises `ValueError` for settings that cannot train."""
        check_kinds(self, "ppo_bc")
        if not self.demos or not all(isinstance(d, str) and d for d in self.demos):
            raise ValueError("demos: a demonstration store's path (or a list of them) is needed")
        for name in ("epochs", "streams", "seq_len"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be an integer of at least 1, got {getattr(self, name)!r}")
        for name in ("lr_warmup_steps", "augment_shift", "seed", "threads"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be an integer of at least 0, got {getattr(self, name)!r}")
        if self.init == "":
            raise ValueError(f"init must be a checkpoint's path, got {self.init!r}")
        if not self.lr > 0 or self.weight_decay < 0 or not self.max_grad_norm > 0:
            raise ValueError("lr and max_grad_norm must be above 0, weight_decay at least 0")

    def lr_at(self, step: int, total_steps: int) -> float:
        """The learning rate of optimizer step `step` (from 0) of `total_steps`: linear warm-up,
        then a cosine to zero.
        """
        if step < self.lr_warmup_steps:
            return self.lr * (step + 1) / self.lr_warmup_steps
        span = max(1, total_steps - self.lr_warmup_steps)
        return 0.5 * self.lr * (1 + math.cos(math.pi * min(1.0, (step - self.lr_warmup_steps) / span)))

    def to_dict(self) -> dict[str, Any]:
        """The config as plain values."""
        return asdict(self)


def load_configs(path: Path) -> tuple[PpoConfig, ImitationConfig]:
    """The `[ppo]` table (the network's settings) and the `[ppo_bc]` table of a TOML (or JSON) file."""
    network = load_config(path)  # the [ppo] table, as esrp train ppo reads it
    try:
        imitation = ImitationConfig.from_mapping(read_table(path, "ppo_bc"))
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: {error}") from None
    if imitation.augment_shift >= network.resolution // 2:
        raise ValueError(
            f"{path}: augment_shift {imitation.augment_shift}: less than half the network's resolution "
            f"({network.resolution})"
        )
    return network, imitation


@dataclass
class EpochStats:
    """What one epoch did (a line of `log.csv`)."""

    epoch: int
    steps: int
    loss: float
    accuracy: float
    lr: float
    seconds: float


def stream_order(
    episode_lengths: Sequence[int] | np.ndarray, streams: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """One epoch's reading order of a store whose episodes have `episode_lengths`: the episodes in a
    random order (drawn from `seed`), end to end, cut into `streams` equal streams (the remainder of
    fewer than `streams` steps left out). Returns (steps, starts), both (T, streams): the joined
    step index each position reads, and 1 where a position begins an episode or a stream.
    """
    lengths = np.asarray(episode_lengths, dtype=np.int64)
    firsts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    order = np.random.default_rng(seed).permutation(len(lengths))
    steps = np.concatenate([np.arange(int(firsts[e]), int(firsts[e] + lengths[e])) for e in order])
    begins = np.zeros(len(steps), dtype=np.float32)
    begins[np.concatenate([[0], np.cumsum(lengths[order])[:-1]])] = 1.0
    per_stream = len(steps) // streams
    if per_stream == 0:
        raise ValueError(f"{len(steps)} steps cannot fill {streams} streams: fewer streams")
    steps = steps[: per_stream * streams].reshape(streams, per_stream).T
    begins = begins[: per_stream * streams].reshape(streams, per_stream).T.copy()
    begins[0] = 1.0
    return steps, begins


def imitation_loss(
    network: PpoNet,
    batch: Mapping[str, torch.Tensor],
    state: tuple[torch.Tensor, torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """The mean cross-entropy of the actor's logits against `batch["labels"]` over the labelled
    steps (`batch["mask"]`), the LSTM starting from `state`; and the accuracy of the most likely
    action there, and the LSTM state after the batch. `batch` holds time-major, flattened `ego`
    (preprocessed), `goal` (distinct preprocessed goals) with `goal_index`, `grasping` and `starts`.
    """
    logits, _, after = network(
        batch["ego"], batch["goal"], batch["grasping"], state, batch["starts"], batch["goal_index"]
    )
    mask = batch["mask"]
    labelled = mask.sum().clamp(min=1)
    loss = (F.cross_entropy(logits, batch["labels"], reduction="none") * mask).sum() / labelled
    with torch.no_grad():
        accuracy = ((logits.argmax(dim=-1) == batch["labels"]).float() * mask).sum() / labelled
    return loss, accuracy, after


def train(
    ppo: PpoConfig,
    config: ImitationConfig,
    out: Path,
    *,
    resume: bool = False,
    progress: bool = True,
) -> Path:
    """Trains the network `ppo` describes on `config.demos` for `config.epochs` epochs (from the
    checkpoint in `out` with `resume`); returns the checkpoint's path.
    """
    _malloc_setup.apply()
    device = resolve_device(ppo.device)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    checkpoint = run_folder(out, resume)
    torch.manual_seed(config.seed)
    network = PpoNet(ppo).to(device)
    optimizer = torch.optim.AdamW(network.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    epoch, step, began = 0, 0, None
    if resume and checkpoint.exists():
        # Only the [ppo] settings of the network count: the others are a later PPO run's.
        free = {f.name for f in fields(PpoConfig)} - set(NETWORK_SETTINGS)
        saved = resume_from(checkpoint, "esrp-ppo", network, optimizer, free, device)
        if not isinstance(saved.get("imitation"), dict) or "optimizer_steps" not in saved:
            raise ValueError(f"{checkpoint} is a checkpoint of esrp train ppo, not of esrp train ppo-bc")
        different = settings_differences(saved["imitation"], config.to_dict(), ("epochs", "threads"))
        if different:
            raise ValueError(
                f"{checkpoint} was trained with other [ppo_bc] settings ({'; '.join(different)})"
            )
        epoch, step = int(saved["epoch"]), int(saved["optimizer_steps"])
        began = saved.get("demos_fingerprint")
        if epoch > config.epochs:
            raise ValueError(
                f"{checkpoint} has trained {epoch} epochs, more than the {config.epochs} asked: "
                f"ask for {epoch} or more to go on"
            )
        print(f"resuming {checkpoint} after epoch {epoch}", file=sys.stderr)
    elif config.init is not None:
        load_initial_weights(network, Path(config.init), device)
        if progress:
            print(f"starting from the weights of {config.init}", file=sys.stderr)
    if epoch >= config.epochs:
        _start_files(ppo, config, out, epoch)
        return checkpoint
    # The demonstrations are read before the run folder is made: a run refused at its start (a
    # missing store, views of another size) leaves none behind.
    demos = DemoWindows(config.demos, 1, 1, in_memory=True, progress=progress)
    if demos.resolution != ppo.resolution:
        raise ValueError(
            f"the demonstrations hold {demos.resolution} px views, the network takes {ppo.resolution}"
        )
    if len(demos) < config.streams:  # as `stream_order` would say in the first epoch
        raise ValueError(f"{len(demos)} steps cannot fill {config.streams} streams: fewer streams")
    check_same_demos(checkpoint, began, demos.fingerprint)
    _start_files(ppo, config, out, epoch)
    lengths = np.bincount(demos.episode)
    batches = (len(demos) // config.streams + config.seq_len - 1) // config.seq_len
    total = batches * config.epochs
    # A resumed run's `seconds` go on from the interrupted run's last logged epoch.
    started = time.monotonic() - logged_seconds(out / "log.csv")
    while epoch < config.epochs:
        network.train()
        order, starts = stream_order(lengths, config.streams, config.seed * 1_000_003 + epoch)
        generator = torch.Generator().manual_seed(config.seed * 1_000_003 + epoch)
        state = network.initial_state(config.streams, device)
        sums, count = np.zeros(2), 0
        lr = config.lr_at(step, total)  # (an epoch has a batch at least: the streams are filled)
        for first in range(0, order.shape[0], config.seq_len):
            lr = config.lr_at(step, total)
            for group in optimizer.param_groups:
                group["lr"] = lr
            batch = _batch(
                network,
                demos,
                order[first : first + config.seq_len],
                starts[first : first + config.seq_len],
                config,
                generator,
                device,
            )
            loss, accuracy, after = imitation_loss(network, batch, state)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"epoch {epoch + 1}: the loss is {loss.item()}")
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            torch.nn.utils.clip_grad_norm_(network.parameters(), config.max_grad_norm)
            optimizer.step()
            state = (after[0].detach(), after[1].detach())
            sums += [loss.item(), accuracy.item()]
            count += 1
            step += 1
        epoch += 1
        stats = EpochStats(epoch, step, sums[0] / count, sums[1] / count, lr, time.monotonic() - started)
        with open(out / "log.csv", "a", newline="") as file:
            csv.writer(file).writerow(
                [f"{v:.6g}" if isinstance(v, float) else v for v in asdict(stats).values()]
            )
        save_checkpoint(
            checkpoint,
            "esrp-ppo",
            network,
            optimizer,
            extra={"imitation": config.to_dict(), "demos_fingerprint": demos.fingerprint},
            epoch=epoch,
            optimizer_steps=step,
            update=0,
            steps=0,
        )
        if progress:
            print(
                f"epoch {epoch}/{config.epochs}  loss {stats.loss:.4f}  accuracy {stats.accuracy:.3f}  "
                f"lr {lr:.2e}  {stats.seconds:.0f} s",
                file=sys.stderr,
            )
    return checkpoint


def _start_files(ppo: PpoConfig, config: ImitationConfig, out: Path, epoch: int) -> None:
    """Makes the run folder `out` if missing, writes its `config.json` and makes its `log.csv` the
    log of the epochs up to `epoch`.
    """
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(
        json.dumps({"ppo": ppo.to_dict(), "ppo_bc": config.to_dict()}, indent=2) + "\n", encoding="utf-8"
    )
    trim_epoch_log(out / "log.csv", LOG_FIELDS, epoch)


def _batch(
    network: PpoNet,
    demos: DemoWindows,
    steps: np.ndarray,
    starts: np.ndarray,
    config: ImitationConfig,
    generator: torch.Generator,
    device: torch.device,
) -> dict[str, torch.Tensor]:
    """The tensors of one batch: `steps` and `starts` (T, streams) flattened time-major, each distinct
    goal preprocessed once.
    """
    flat = steps.reshape(-1)
    ego = torch.from_numpy(demos.memory["data/ego_rgb"][flat])
    episodes, goal_index = np.unique(demos.episode[flat], return_inverse=True)
    goal = torch.from_numpy(demos.memory["meta/goal_rgb"][episodes])
    ego = random_shift(ego, config.augment_shift, generator)
    goal = random_shift(goal, config.augment_shift, generator)
    labels = demos.targets[flat, 0]
    return {
        "ego": network.preprocess(ego.to(device)),
        "goal": network.preprocess(goal.to(device)),
        "goal_index": torch.from_numpy(goal_index.reshape(-1).astype(np.int64)).to(device),
        "grasping": torch.from_numpy(demos.grasping[flat].astype(np.int64)).to(device),
        "starts": torch.from_numpy(starts.reshape(-1)).to(device),
        "labels": torch.from_numpy(np.where(labels == NO_LABEL, 0, labels).astype(np.int64)).to(device),
        "mask": torch.from_numpy((labels != NO_LABEL).astype(np.float32)).to(device),
    }
