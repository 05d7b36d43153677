"""ESRP-BC: a conditional Diffusion Policy over one-hot action chunks (SPEC §8), and its agent.

The condition c_t = MLP(concat(encoder features of the last n ego views, encoder features of the
goal image, embeddings of the last n grasp flags)). The expert's next h actions, as one-hot vectors
scaled to [-1, 1], are noised by DDPM (`diffusers`' `DDPMScheduler`, 50 steps) and a conditional 1D
U-Net (FiLM-conditioned residual blocks over the h positions) predicts the noise. Loss: noise MSE +
λ_CE × cross-entropy of the denoised chunk (clipped to [-1, 1] as sampling clips it, read as
per-position logits) against the expert's actions. At inference `diffusers`' `DDIMScheduler`
denoises in 16 steps; the agent executes the first 6 of the 8 predicted actions, each replaced by a
uniform random one with probability ε.

The paper's image encoders are ImageNet-pretrained ResNet-50s; no weights can be downloaded here,
so the encoder is trained from scratch: a small CNN by default (`encoder = "cnn"`, for CPUs), or a
ResNet-18-style network (`encoder = "resnet18"`, written here, no torchvision).

`esrp eval --agent bc --checkpoint RUN/ckpt.pt` plays a trained policy (`esrp train bc` makes one).
With the agent config's `batch` (e.g. `--agent-config '{"batch": 8}'` and as many episodes in
flight), the episodes' agents are asynchronous and share the policy: the requests of the agents
that ask within a few milliseconds of each other are denoised as one batch, several times faster
on a CPU than one at a time (each agent's noise is its own, so its actions are those it would take
alone, up to the floating-point differences of a batched computation).
"""

from __future__ import annotations

import asyncio
import math
import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F  # noqa: N812 - the usual name

from .._values import Action, Observation, Sensors
from ._checkpoint import policy_checkpoint, read_checkpoint
from ._config import check_agent_config, check_at_least, check_kinds, reject_unknown
from .encoders import ENCODERS, check_device, float_images, make_encoder

__all__ = [
    "LEGACY_SETTINGS",
    "BatchedBcAgent",
    "BcAgent",
    "BcConfig",
    "BcPolicy",
    "DiffusionPolicy",
    "checkpoint_settings",
    "load_policy",
    "random_shift",
]

ACTIONS = len(Action)

LR_SCHEDULES = ("cosine", "constant")
"""The learning-rate schedules of `BcConfig.lr_schedule`."""

LEGACY_SETTINGS: dict[str, Any] = {
    "lr_schedule": "constant",
    "lr_warmup_steps": 0,
    "span": 1,
    "ema": False,
    "augment_shift": 0,
}
"""What a checkpoint written before these settings existed was trained with (its config lacks them)."""


@dataclass
class BcConfig:
    """The model's and the training's settings (the `[bc]` table of a training config).

    Defaults are the paper's (SPEC §8) except the encoder (from scratch: no pretrained weights),
    with Diffusion Policy's training recipe where the paper is silent: the learning rate warms up
    linearly over `lr_warmup_steps` optimizer steps and then follows a cosine to 0 at the last
    epoch's last step (`lr_schedule = "constant"`: `lr` throughout), and the weights' exponential
    moving average (`ema`: decay 1 - (1 + step) ** -`ema_power`, at most `ema_max_decay`) is what
    the checkpoints play and the evaluations measure. `span` windows of consecutive steps of one
    episode are sampled together, so that a batch encodes each view once for the windows sharing
    it (1: each window drawn alone). `augment_shift` pads both images by that many pixels (edges
    repeated) and crops them back at a random offset, each view its own (0: no augmentation).
    `resolution` is the side of the views the model takes: the demonstrations' (`esrp demos export
    --resolution`), and the one its agent asks the server for.
    `in_memory` reads the stores' views into memory once instead of from their chunks every batch
    (the same batches). The `eval_*` settings are the held-out evaluation of `esrp train bc`: every
    `eval_every` epochs (0: never) and after the last, the policy plays the `eval_scenes` (or the
    `eval_limit` scenes from `eval_offset` in the listing of `eval_split` and `eval_difficulty`) as
    `esrp eval --agent bc` plays them, with `eval_epsilon` (None: `epsilon`), base seed `eval_seed`,
    `eval_episodes_in_flight` at a time (their requests to the policy batched), the policy on
    `eval_threads` torch threads (0: the training's): on a small machine more than one thread
    contends with the server's renderer and is several times slower. `esrp train bc --dagger`'s
    rollouts play the policy on `eval_threads` too. `eval_keep_checkpoints` keeps each evaluated
    checkpoint, made for playing, beside its results (`eval/epoch-NNNN.pt`), for choosing by
    another held-out measure than the run's `best.pt` does. None of these change what is trained.
    """

    demos: str | list[str] = "demos/train.zarr"
    resolution: int = 128
    encoder: str = "cnn"
    feature_dim: int = 256
    grasp_dim: int = 16
    cond_dim: int = 256
    unet_channels: tuple[int, ...] = (64, 128, 256)
    kernel_size: int = 3
    n_obs: int = 4
    horizon: int = 8
    n_execute: int = 6
    diffusion_steps: int = 50
    ddim_steps: int = 16
    lambda_ce: float = 0.2
    epsilon: float = 0.1
    lr: float = 1e-4
    lr_schedule: str = "cosine"
    lr_warmup_steps: int = 500
    weight_decay: float = 1e-6
    batch_size: int = 1024
    epochs: int = 500
    span: int = 16
    ema: bool = True
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999
    augment_shift: int = 0
    seed: int = 0
    threads: int = 0
    checkpoint_every: int = 10
    device: str = "auto"
    in_memory: bool = False
    eval_every: int = 0
    eval_split: str = "train"
    eval_difficulty: str | None = None
    eval_scenes: list[str] = field(default_factory=list)
    eval_limit: int | None = None
    eval_offset: int = 0
    eval_epsilon: float | None = None
    eval_seed: int = 0
    eval_episodes_in_flight: int = 8
    eval_threads: int = 1
    eval_keep_checkpoints: bool = False

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> BcConfig:
        """A config from a mapping (a TOML/JSON table); unknown keys raise `ValueError`."""
        reject_unknown(cls, values, "bc")
        given: dict[str, Any] = {
            k: tuple(v) if k == "unet_channels" and isinstance(v, list | tuple) else v
            for k, v in values.items()
        }
        config = cls(**given)
        config._check_numbers()
        if config.encoder not in ENCODERS:
            raise ValueError(f"encoder {config.encoder!r}: one of {', '.join(ENCODERS)}")
        if not 16 <= config.resolution <= 512:
            raise ValueError(f"resolution {config.resolution}: 16 to 512 pixels")
        check_device(config.device)
        if not 1 <= config.n_execute <= config.horizon:
            raise ValueError("n_execute must be between 1 and horizon")
        if config.horizon % 2 ** (len(config.unet_channels) - 1):
            raise ValueError("horizon must be divisible by 2 ** (len(unet_channels) - 1)")
        config._check_recipe()
        config._check_evaluation()
        return config

    def _check_numbers(self) -> None:
        """Raises `ValueError` for a setting of the wrong kind, or a size, count or rate out of range
        (the evaluation's are `_check_evaluation`'s).
        """
        check_kinds(self, "bc")
        if (
            not isinstance(self.unet_channels, tuple)
            or not self.unet_channels
            or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 1 for c in self.unet_channels)
        ):
            raise ValueError(
                "bc setting unet_channels must be a list of integers of at least 1, "
                f"not {self.unet_channels!r}"
            )
        if any(c % 8 for c in self.unet_channels):
            # Each block's GroupNorm has 8 groups.
            raise ValueError(
                "bc setting unet_channels must be a list of integers, each a multiple of 8 (the U-Net's "
                f"group norms have 8 groups), not {list(self.unet_channels)!r}"
            )
        sizes = ("feature_dim", "grasp_dim", "cond_dim", "kernel_size", "n_obs", "horizon")
        counts = ("diffusion_steps", "ddim_steps", "batch_size", "epochs", "checkpoint_every")
        check_at_least(self, "bc", 1, (*sizes, *counts))
        if self.kernel_size % 2 == 0:
            # An even kernel changes the length of the U-Net's convolutions' outputs.
            raise ValueError(f"bc setting kernel_size must be odd, not {self.kernel_size!r}")
        if self.ddim_steps > self.diffusion_steps:
            # DDIM samples from the DDPM schedule the model was trained on: at most its steps.
            raise ValueError(
                f"bc setting ddim_steps ({self.ddim_steps}) must be at most diffusion_steps "
                f"({self.diffusion_steps})"
            )
        # lr 0 trains nothing: a run that only evaluates, or checks what a fine-tuning starts from.
        check_at_least(self, "bc", 0, ("lr", "threads", "weight_decay", "lambda_ce"))
        if not 0.0 <= self.epsilon <= 1.0:
            raise ValueError(f"bc setting epsilon must be from 0 to 1, not {self.epsilon!r}")

    def _check_recipe(self) -> None:
        """Raises `ValueError` for schedule, EMA, sampling and augmentation settings out of range."""
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule {self.lr_schedule!r}: one of {', '.join(LR_SCHEDULES)}")
        if self.lr_warmup_steps < 0 or self.augment_shift < 0:
            raise ValueError("lr_warmup_steps and augment_shift must be 0 or more")
        if self.span < 1:
            raise ValueError(f"span must be at least 1, not {self.span}")
        if self.augment_shift >= self.resolution // 2:
            raise ValueError(f"augment_shift {self.augment_shift}: less than half the resolution")
        if not 0.0 < self.ema_power <= 1.0 or not 0.0 <= self.ema_max_decay < 1.0:
            raise ValueError("ema_power must be in (0, 1] and ema_max_decay in [0, 1)")

    def lr_at(self, step: int, total_steps: int) -> float:
        """The learning rate of optimizer step `step` (0-based) of a run of `total_steps` steps."""
        if self.lr_schedule == "constant":
            return self.lr
        if step < self.lr_warmup_steps:
            return self.lr * (step + 1) / self.lr_warmup_steps
        decaying = max(total_steps - self.lr_warmup_steps, 1)
        progress = min((step - self.lr_warmup_steps) / decaying, 1.0)
        return self.lr * 0.5 * (1.0 + math.cos(math.pi * progress))

    def _check_evaluation(self) -> None:
        """Raises `ValueError` for `eval_*` settings out of range (their kinds are `check_kinds`')."""
        if self.eval_every < 0 or self.eval_offset < 0 or self.eval_threads < 0:
            raise ValueError("eval_every, eval_offset and eval_threads must be 0 or more")
        if self.eval_episodes_in_flight < 1:
            raise ValueError("eval_episodes_in_flight must be at least 1")
        if self.eval_split not in ("train", "test", "challenge", "minival"):
            raise ValueError(f"eval_split {self.eval_split!r}: train, test, challenge or minival")
        if self.eval_difficulty not in (None, "easy", "medium", "hard"):
            raise ValueError(f"eval_difficulty {self.eval_difficulty!r}: easy, medium or hard")
        if not isinstance(self.eval_scenes, list | tuple) or not all(
            isinstance(s, str) for s in self.eval_scenes
        ):
            raise ValueError(f"eval_scenes must be a list of scene ids, not {self.eval_scenes!r}")
        self.eval_scenes = list(self.eval_scenes)
        if self.eval_limit is not None and self.eval_limit < 1:
            raise ValueError(f"eval_limit must be at least 1, not {self.eval_limit!r}")
        if self.eval_scenes and (self.eval_limit is not None or self.eval_offset):
            raise ValueError("eval_scenes names the scenes: no eval_limit or eval_offset with it")
        if self.eval_epsilon is not None and not 0.0 <= self.eval_epsilon <= 1.0:
            raise ValueError(f"eval_epsilon must be between 0 and 1, not {self.eval_epsilon!r}")

    def to_dict(self) -> dict[str, Any]:
        """The config as plain values (for checkpoints and logs)."""
        values = asdict(self)
        values["unet_channels"] = list(self.unet_channels)
        return values


# --- The conditional 1D U-Net ---


def _step_embedding(steps: torch.Tensor, dim: int) -> torch.Tensor:
    half = dim // 2
    scale = math.log(10_000) / max(half - 1, 1)
    frequencies = torch.exp(torch.arange(half, device=steps.device) * -scale)
    angles = steps.float()[:, None] * frequencies[None]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class _FilmBlock(nn.Module):
    """Two 1D convolutions; the condition scales and shifts the first's output (FiLM)."""

    def __init__(self, cin: int, cout: int, cond: int, kernel: int) -> None:
        super().__init__()
        self.conv1 = nn.Sequential(
            nn.Conv1d(cin, cout, kernel, padding=kernel // 2), nn.GroupNorm(8, cout), nn.Mish()
        )
        self.conv2 = nn.Sequential(
            nn.Conv1d(cout, cout, kernel, padding=kernel // 2), nn.GroupNorm(8, cout), nn.Mish()
        )
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond, 2 * cout))
        self.skip: nn.Module = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, shift = self.film(cond)[:, :, None].chunk(2, dim=1)
        y = self.conv1(x) * (1 + scale) + shift
        out: torch.Tensor = self.conv2(y) + self.skip(x)
        return out


class ConditionalUnet1d(nn.Module):
    """Diffusion Policy's conditional 1D U-Net, over (batch, actions, horizon)."""

    def __init__(self, channels: tuple[int, ...], cond_dim: int, kernel: int) -> None:
        super().__init__()
        step_dim = channels[0]
        self.step_mlp = nn.Sequential(
            nn.Linear(step_dim, 4 * step_dim), nn.Mish(), nn.Linear(4 * step_dim, step_dim)
        )
        self.step_dim = step_dim
        cond = cond_dim + step_dim
        self.down = nn.ModuleList()
        cin = ACTIONS
        for i, width in enumerate(channels):
            last = i == len(channels) - 1
            sample: nn.Module = nn.Identity() if last else nn.Conv1d(width, width, 3, stride=2, padding=1)
            self.down.append(
                nn.ModuleList(
                    [_FilmBlock(cin, width, cond, kernel), _FilmBlock(width, width, cond, kernel), sample]
                )
            )
            cin = width
        self.mid = nn.ModuleList([_FilmBlock(cin, cin, cond, kernel), _FilmBlock(cin, cin, cond, kernel)])
        self.up = nn.ModuleList()
        for width in reversed(channels[:-1]):
            self.up.append(
                nn.ModuleList(
                    [
                        nn.ConvTranspose1d(cin, cin, 4, stride=2, padding=1),
                        _FilmBlock(cin + width, width, cond, kernel),
                        _FilmBlock(width, width, cond, kernel),
                    ]
                )
            )
            cin = width
        self.out = nn.Sequential(
            nn.Conv1d(cin, cin, kernel, padding=kernel // 2), nn.Mish(), nn.Conv1d(cin, ACTIONS, 1)
        )

    def forward(self, x: torch.Tensor, steps: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        c = torch.cat([self.step_mlp(_step_embedding(steps, self.step_dim)), cond], dim=-1)
        skips: list[torch.Tensor] = []
        for level in self.down:
            first, second, sample = cast(nn.ModuleList, level)
            x = second(first(x, c), c)
            skips.append(x)
            x = sample(x)
        skips.pop()
        for block in self.mid:
            x = block(x, c)
        for level in self.up:
            upsample, first, second = cast(nn.ModuleList, level)
            x = second(first(torch.cat([upsample(x), skips.pop()], dim=1), c), c)
        out: torch.Tensor = self.out(x)
        return out


class DiffusionPolicy(nn.Module):
    """Observation encoders, the condition MLP and the denoiser."""

    def __init__(self, config: BcConfig) -> None:
        super().__init__()
        self.config = config
        self.ego = make_encoder(config.encoder, config.feature_dim, config.resolution)
        self.goal = make_encoder(config.encoder, config.feature_dim, config.resolution)
        self.grasp = nn.Embedding(2, config.grasp_dim)
        width = (config.n_obs + 1) * config.feature_dim + config.n_obs * config.grasp_dim
        self.cond = nn.Sequential(
            nn.Linear(width, config.cond_dim), nn.Mish(), nn.Linear(config.cond_dim, config.cond_dim)
        )
        self.unet = ConditionalUnet1d(config.unet_channels, config.cond_dim, config.kernel_size)

    def condition(self, ego: torch.Tensor, goal: torch.Tensor, grasping: torch.Tensor) -> torch.Tensor:
        """c_t from uint8 images: ego (B, n, R, R, 3), goal (B, R, R, 3), grasping (B, n) bool."""
        batch, n = ego.shape[:2]
        frames = torch.arange(batch * n, device=ego.device).reshape(batch, n)
        goals = torch.arange(batch, device=ego.device)
        return self.condition_indexed(ego.reshape(batch * n, *ego.shape[2:]), frames, goal, goals, grasping)

    def condition_indexed(
        self,
        frames: torch.Tensor,
        frame_index: torch.Tensor,
        goals: torch.Tensor,
        goal_index: torch.Tensor,
        grasping: torch.Tensor,
    ) -> torch.Tensor:
        """c_t of windows that share views: each of `frames` (U, R, R, 3) and `goals` (G, R, R, 3),
        uint8, is encoded once; window b's ego history is `frames[frame_index[b]]` (B, n) and its goal
        `goals[goal_index[b]]` (B,); grasping (B, n) bool.
        """
        batch = frame_index.shape[0]
        ego_features = self.ego(float_images(frames))[frame_index].reshape(batch, -1)
        goal_features = self.goal(float_images(goals))[goal_index]
        grasp = self.grasp(grasping.long()).reshape(batch, -1)
        out: torch.Tensor = self.cond(torch.cat([ego_features, goal_features, grasp], dim=-1))
        return out


_DIFFUSERS_IMPORT = threading.Lock()
"""Held while importing from diffusers: its lazy imports fail (ImportError) when two threads make
the first one at once, as agents made on the threads of `esrp demos export --episodes-in-flight` do."""


def schedulers(config: BcConfig) -> tuple[Any, Any]:  # noqa: ANN401 - diffusers' classes
    """The DDPM scheduler of training and the DDIM scheduler of inference (same noise schedule)."""
    with _DIFFUSERS_IMPORT:
        from diffusers.schedulers.scheduling_ddim import DDIMScheduler
        from diffusers.schedulers.scheduling_ddpm import DDPMScheduler

    common = {
        "num_train_timesteps": config.diffusion_steps,
        "beta_schedule": "squaredcos_cap_v2",
        "clip_sample": True,
        "prediction_type": "epsilon",
    }
    return DDPMScheduler(**common), DDIMScheduler(**common)


def bc_loss(
    model: DiffusionPolicy,
    scheduler: Any,  # noqa: ANN401 - diffusers' DDPMScheduler
    batch: Mapping[str, torch.Tensor],
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(total, noise MSE, cross-entropy) of a batch of windows (`esrp.train.bc.DemoWindows.batch`):
    `frames` (U, R, R, 3) and `goals` (G, R, R, 3) uint8 with `frame_index` (B, n) and `goal_index`
    (B,) into them, `grasping` (B, n) bool, `actions` (B, h) int64 and `mask` (B, h) bool, true
    where `actions` holds a label. Positions without a label (past the episode's end, or past what
    the planner's plan covered) count in neither term: their `actions` only make the noised chunk
    whole.
    """
    actions = batch["actions"]
    mask = batch["mask"].to(torch.float32)
    x0 = F.one_hot(actions, ACTIONS).float().transpose(1, 2) * 2 - 1  # (B, 6, h) in [-1, 1]
    # Drawn on the CPU (where a seeded generator lives), then moved: the same draws on any device.
    noise = torch.randn(x0.shape, generator=generator).to(x0.device)
    steps = torch.randint(0, scheduler.config.num_train_timesteps, (x0.shape[0],), generator=generator)
    steps = steps.to(x0.device)
    noisy = scheduler.add_noise(x0, noise, steps)
    cond = model.condition_indexed(
        batch["frames"], batch["frame_index"], batch["goals"], batch["goal_index"], batch["grasping"]
    )
    predicted = model.unet(noisy, steps, cond)
    labelled = mask.sum().clamp(min=1.0)
    mse = ((predicted - noise) ** 2 * mask[:, None, :]).sum() / (labelled * ACTIONS)
    alpha = scheduler.alphas_cumprod.to(x0.device)[steps].float()[:, None, None]
    # The denoised chunk, clipped to the one-hot range as sampling clips it, read as logits: at
    # high noise levels the unclipped estimate divides by a tiny sqrt(alpha) and would swamp the MSE.
    denoised = ((noisy - (1 - alpha).sqrt() * predicted) / alpha.sqrt()).clamp(-1, 1)
    ce = (F.cross_entropy(denoised, actions, reduction="none") * mask).sum() / labelled
    return mse + model.config.lambda_ce * ce, mse, ce


def random_shift(images: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """`images` (N, R, R, 3) uint8, each padded by `pad` pixels (edges repeated) and cropped back to
    R × R at an offset of its own drawn from `generator` (DrQ's random shift); `pad` 0: `images`.
    """
    if pad == 0:
        return images
    count, side = images.shape[0], images.shape[1]
    padded = F.pad(images.permute(0, 3, 1, 2).float(), (pad, pad, pad, pad), mode="replicate")
    offsets = torch.randint(0, 2 * pad + 1, (count, 2), generator=generator).to(images.device)
    span = torch.arange(side, device=images.device)
    rows = (offsets[:, 0:1] + span)[:, :, None]  # (N, R, 1)
    cols = (offsets[:, 1:2] + span)[:, None, :]  # (N, 1, R)
    which = torch.arange(count, device=images.device)[:, None, None]
    shifted = padded.permute(0, 2, 3, 1)[which, rows, cols]  # (N, R, R, 3)
    return shifted.to(torch.uint8)


# --- Checkpoints and the agent ---


def checkpoint_settings(config: Mapping[str, Any]) -> dict[str, Any]:
    """A checkpoint's `config` with the settings it predates filled in as it was trained
    (`LEGACY_SETTINGS`).
    """
    return {**LEGACY_SETTINGS, **config}


def load_policy(path: str | Path) -> DiffusionPolicy:
    """The policy of a checkpoint `esrp train bc` wrote, in eval mode: its `model` weights (the
    moving average of the weights, for a run with `ema`).
    """
    state = read_checkpoint(path, "esrp-bc", "ESRP-BC")
    model = DiffusionPolicy(BcConfig.from_mapping(checkpoint_settings(state["config"])))
    model.load_state_dict(state["model"])
    model.eval()
    return model


@torch.no_grad()
def sample_actions(
    model: DiffusionPolicy,
    scheduler: Any,  # noqa: ANN401 - diffusers' DDIMScheduler
    ego: torch.Tensor,
    goal: torch.Tensor,
    grasping: torch.Tensor,
    generator: torch.Generator | None,
    noise: torch.Tensor | None = None,
) -> torch.Tensor:
    """The h actions DDIM denoises for a batch of observation histories: (B, h) int64. The chain
    starts from `noise` (B, 6, h), or without it from noise drawn from `generator` (DDIM's steps
    draw nothing more).
    """
    return denoise_actions(model, scheduler, model.condition(ego, goal, grasping), generator, noise)


def denoise_actions(
    model: DiffusionPolicy,
    scheduler: Any,  # noqa: ANN401 - diffusers' DDIMScheduler
    cond: torch.Tensor,
    generator: torch.Generator | None,
    noise: torch.Tensor | None = None,
) -> torch.Tensor:
    """The h actions DDIM denoises for a batch of conditions `cond` (B, cond_dim), as
    `sample_actions` (which conditions on observation histories first) does: (B, h) int64.
    """
    config = model.config
    scheduler.set_timesteps(config.ddim_steps)
    batch = cond.shape[0]
    x = noise if noise is not None else torch.randn((batch, ACTIONS, config.horizon), generator=generator)
    for step in scheduler.timesteps:
        predicted = model.unet(x, torch.full((batch,), int(step)), cond)
        x = scheduler.step(predicted, step, x, generator=generator).prev_sample
    return x.argmax(dim=1)


class _History:
    """What both agents keep: the last n ego views and grasp flags, the goal, the queue of actions
    to execute, and the episode's random generators (seeded by `info["seed"]`).
    """

    def __init__(self, model: DiffusionPolicy, config: Mapping[str, Any]) -> None:
        self.model = model
        self.epsilon = float(config.get("epsilon", model.config.epsilon))
        self.deterministic = bool(config.get("deterministic", False))
        self.queue: deque[int] = deque()
        self.egos: deque[np.ndarray] = deque(maxlen=model.config.n_obs)
        self.grasps: deque[bool] = deque(maxlen=model.config.n_obs)
        self.goal: np.ndarray | None = None
        self.rng = np.random.default_rng(0)
        self.generator = torch.Generator().manual_seed(0)

    def _reset(self, observation: Observation, info: Mapping[str, Any]) -> None:
        side = self.model.config.resolution
        if observation.ego_rgb.shape[:2] != (side, side):
            height, width = observation.ego_rgb.shape[:2]
            raise ValueError(
                f"the policy takes {side}×{side} views, got {width}×{height}: create its episodes with "
                f"sensors resolution {side} (esrp eval does)"
            )
        seed = int(info["seed"])
        self.rng = np.random.default_rng(seed)
        self.generator = torch.Generator().manual_seed(seed)
        self.goal = np.array(observation.goal_rgb)  # a writable copy, for torch
        self.queue.clear()
        self.egos.clear()
        self.grasps.clear()
        for _ in range(self.model.config.n_obs):
            self.egos.append(observation.ego_rgb)
            self.grasps.append(observation.grasping)

    def _observe(self, observation: Observation) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """Adds `observation` to the history; when the queue is empty, the policy's input (ego, goal,
        grasping, each a batch of one).
        """
        if self.goal is None:
            raise RuntimeError("act() before reset()")
        self.egos.append(observation.ego_rgb)
        self.grasps.append(observation.grasping)
        if self.queue:
            return None
        ego = torch.from_numpy(np.stack(self.egos))[None]  # np.stack copies
        return ego, torch.from_numpy(self.goal)[None], torch.tensor([list(self.grasps)])

    def _noise(self) -> torch.Tensor:
        """The starting noise of the next chunk (1, 6, h), from the episode's generator."""
        return torch.randn((1, ACTIONS, self.model.config.horizon), generator=self.generator)

    def _next(self, chunk: torch.Tensor | None) -> Action:
        """Queues the first `n_execute` of `chunk` (if any), and the next action, replaced by a
        random one with probability ε.
        """
        if chunk is not None:
            self.queue.extend(int(a) for a in chunk[: self.model.config.n_execute])
        action = self.queue.popleft()
        if not self.deterministic and self.rng.random() < self.epsilon:
            action = int(self.rng.integers(0, ACTIONS))
        return Action(action)


class BcAgent(_History):
    """Plays a `DiffusionPolicy`: keeps the last n ego views and grasp flags, asks the policy for h
    actions when its queue is empty, executes the first `n_execute`, each replaced by a random
    action with probability ε. Seeded per episode by `info["seed"]` (same seed, same actions).
    """

    def __init__(self, model: DiffusionPolicy, config: Mapping[str, Any]) -> None:
        super().__init__(model, config)
        _, self.scheduler = schedulers(model.config)

    def reset(self, observation: Observation, info: Mapping[str, Any]) -> None:
        """Starts an episode: the history is the first observation, repeated. Raises `ValueError`
        when the views are not the model's resolution.
        """
        self._reset(observation, info)

    def act(self, observation: Observation) -> Action:
        """The next action."""
        inputs = self._observe(observation)
        chunk = None
        if inputs is not None:
            chunk = sample_actions(self.model, self.scheduler, *inputs, None, self._noise())[0]
        return self._next(chunk)


class _Batcher:
    """Denoises the requests of several agents as one batch: a request waits at most `window`
    seconds for others (at most `size` in a batch), then the policy runs once for all of them.
    """

    def __init__(self, model: DiffusionPolicy, size: int, window: float = 0.02) -> None:
        self.model = model
        self.size = size
        self.window = window
        _, self.scheduler = schedulers(model.config)
        self.pending: list[tuple[tuple[torch.Tensor, ...], asyncio.Future[torch.Tensor]]] = []
        self.timer: asyncio.TimerHandle | None = None

    async def sample(
        self, ego: torch.Tensor, goal: torch.Tensor, grasping: torch.Tensor, noise: torch.Tensor
    ) -> torch.Tensor:
        """The chunk (h,) of one agent's request, denoised with the others pending."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[torch.Tensor] = loop.create_future()
        self.pending.append(((ego, goal, grasping, noise), future))
        if len(self.pending) >= self.size:
            self._flush()
        elif self.timer is None:
            self.timer = loop.call_later(self.window, self._flush)
        return await future

    def _flush(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        batch, self.pending = self.pending, []
        waiting = [(inputs, future) for inputs, future in batch if not future.done()]  # not cancelled
        if not waiting:
            return
        ego, goal, grasping, noise = (torch.cat([inputs[i] for inputs, _ in waiting]) for i in range(4))
        try:
            chunks = sample_actions(self.model, self.scheduler, ego, goal, grasping, None, noise)
        except Exception as error:  # noqa: BLE001 - handed to every agent that asked
            for _, future in waiting:
                future.set_exception(error)
            return
        for (_, future), chunk in zip(waiting, chunks, strict=True):
            future.set_result(chunk)


class BatchedBcAgent(_History):
    """`BcAgent` as an `AsyncAgent` whose requests to the policy go through a `_Batcher` shared with
    the other episodes' agents (`BcPolicy` with `batch`).
    """

    def __init__(self, model: DiffusionPolicy, config: Mapping[str, Any], batcher: _Batcher) -> None:
        super().__init__(model, config)
        self.batcher = batcher

    async def reset(self, observation: Observation, info: Mapping[str, Any]) -> None:
        """Starts an episode: the history is the first observation, repeated. Raises `ValueError`
        when the views are not the model's resolution.
        """
        self._reset(observation, info)

    async def act(self, observation: Observation) -> Action:
        """The next action."""
        inputs = self._observe(observation)
        chunk = None
        if inputs is not None:
            chunk = await self.batcher.sample(*inputs, self._noise())
        return self._next(chunk)


AGENT_SETTINGS = {
    "checkpoint": "path",
    "epsilon": "probability",
    "deterministic": "bool",
    "threads": "int",
    "batch": "int",
}
"""The bc agent's config keys (`esrp eval --agent bc --agent-config`) and their kinds."""


class BcPolicy:
    """The agent factory of `esrp eval --agent bc`: loads the checkpoint (`config["checkpoint"]`)
    once; each call makes an agent for one episode. Config keys: `checkpoint`, `epsilon` (default
    the training config's, 0.1), `deterministic` (no random replacements), `threads` (torch's),
    `batch` (at most this many episodes' requests denoised together: `BatchedBcAgent`s; default 1,
    `BcAgent`s).
    """

    def __init__(self, config: Mapping[str, Any]) -> None:
        check_agent_config(config, "bc", AGENT_SETTINGS)
        self.model = load_policy(policy_checkpoint(config, "bc"))
        self.sensors = Sensors(resolution=self.model.config.resolution)
        """What its episodes must be created with: views at the model's resolution."""
        batch = config.get("batch", 1)
        if not isinstance(batch, int) or isinstance(batch, bool) or batch < 1:
            raise ValueError(f"the bc agent's batch must be an integer of at least 1, not {batch!r}")
        self.batcher = _Batcher(self.model, batch) if batch > 1 else None

    def __call__(self, config: dict[str, Any]) -> BcAgent | BatchedBcAgent:
        """An agent for one episode."""
        if self.batcher is not None:
            return BatchedBcAgent(self.model, config, self.batcher)
        return BcAgent(self.model, config)
