"""ESRP-PPO: the paper's recurrent PPO baseline (SPEC §8), its network and its agent.

The network: an encoder for the ego view and one for the goal image (`esrp.agents.encoders`,
trained from scratch), a learnable embedding of the grasp flag, a linear layer joining them, one
LSTM layer, and two MLP heads (six action logits, one value). As CleanRL's `ppo_atari_lstm`, the
LSTM state is zeroed before the first observation of each episode, and training back-propagates
through sequences of `num_steps` steps (the paper's context length l = 64).

`esrp train ppo --config ...` trains one (`esrp.train.ppo`); `esrp eval --agent ppo --checkpoint
RUN/ckpt.pt` plays it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F  # noqa: N812 - the usual name

from .._values import Action, Observation, RewardWeights, Sensors
from ._checkpoint import policy_checkpoint, read_checkpoint
from ._config import check_agent_config, check_at_least, check_kinds, reject_unknown
from .encoders import ENCODERS, check_device, make_encoder

__all__ = ["NETWORK_SETTINGS", "PpoAgent", "PpoConfig", "PpoNet", "PpoPolicy", "load_network"]

ACTIONS = len(Action)

LstmState = tuple[torch.Tensor, torch.Tensor]


@dataclass
class PpoConfig:
    """The network's, the environment's and the training's settings (the `[ppo]` table of a config).

    Defaults are the paper's (SPEC §8: lr 1.5e-4, value-loss coefficient 5e-3, batch 2,048 =
    `num_envs` × `num_steps`, minibatch 64, 6 M environment steps, context length 64 = `num_steps`)
    and otherwise CleanRL's PPO defaults. A minibatch is whole sequences: `minibatch_size` must be a
    multiple of `num_steps` (64 = one environment's 64 steps).

    `init` names an ESRP-PPO checkpoint (e.g. one `esrp train ppo-bc` trained by imitation) whose
    weights the network starts from, with a fresh optimizer; its network settings must be this
    config's. For the first `critic_warmup` updates only the critic head learns (the policy and the
    shared trunk stay as they are), so that a trained policy is not moved by the advantages of a
    critic that has not learnt its returns yet (PIRLNav's critic warm-up). `policy_lr` (None: `lr`)
    is the learning rate of every parameter but the critic head's (the encoders, the LSTM, the
    actor head), annealed as `lr` is: a fine-tuning moves a trained policy slowly while its critic
    learns at `lr`.

    `norm_adv_scope` says over what `norm_adv` normalises the advantages: each `"minibatch"`
    (CleanRL's), or the whole rollout (`"batch"`: a minibatch of near-zero advantages is not
    blown up to unit scale). `norm_reward` divides the rewards the learner sees (not the reward
    the server gives, nor the returns logged) by the running standard deviation of the
    discounted return (Gymnasium's `NormalizeReward`), so that the value targets are of unit
    scale whatever the reward's.
    """

    # Environment: scenes and reward.
    split: str = "train"
    difficulty: str | None = None
    scene: str | None = None
    horizon: int = 0
    reward: dict[str, float] = field(default_factory=dict)
    resolution: int = 128
    # Network.
    encoder: str = "nature"
    pool: int = 1
    feature_dim: int = 256
    grasp_dim: int = 16
    hidden: int = 256
    # PPO.
    num_envs: int = 32
    num_steps: int = 64
    total_steps: int = 6_000_000
    lr: float = 1.5e-4
    anneal_lr: bool = True
    gamma: float = 0.99
    gae_lambda: float = 0.95
    minibatch_size: int = 64
    update_epochs: int = 4
    norm_adv: bool = True
    norm_adv_scope: str = "minibatch"
    norm_reward: bool = False
    clip_coef: float = 0.2
    clip_vloss: bool = True
    ent_coef: float = 0.01
    vf_coef: float = 5e-3
    max_grad_norm: float = 0.5
    target_kl: float = 0.0
    # Run.
    seed: int = 0
    device: str = "auto"
    threads: int = 0
    checkpoint_every: int = 10
    # A start from trained weights.
    init: str | None = None
    critic_warmup: int = 0
    policy_lr: float | None = None

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> PpoConfig:
        """A config from a mapping (a TOML/JSON table); unknown keys and bad values raise
        `ValueError`.
        """
        reject_unknown(cls, values, "ppo")
        config = cls(**dict(values))
        config.validate()
        return config

    def validate(self) -> None:
        """Raises `ValueError` for settings that cannot train."""
        check_kinds(self, "ppo")
        check_at_least(self, "ppo", 0, ("lr", "horizon", "threads", "vf_coef", "target_kl", "clip_coef"))
        if not self.max_grad_norm > 0:
            raise ValueError(f"ppo setting max_grad_norm must be above 0, not {self.max_grad_norm!r}")
        if self.encoder not in ENCODERS:
            raise ValueError(f"encoder {self.encoder!r}: one of {', '.join(ENCODERS)}")
        if self.split not in ("train", "test"):
            raise ValueError(f"split {self.split!r}: train or test")
        positive = ("num_envs", "num_steps", "total_steps", "minibatch_size", "update_epochs", "pool")
        for name in (*positive, "feature_dim", "grasp_dim", "hidden", "resolution", "checkpoint_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.resolution % self.pool:
            raise ValueError(f"pool {self.pool} must divide the resolution {self.resolution}")
        if self.minibatch_size % self.num_steps:
            raise ValueError(
                f"minibatch_size {self.minibatch_size} must be a multiple of num_steps {self.num_steps} "
                "(a minibatch is whole sequences)"
            )
        if (self.num_envs * self.num_steps) % self.minibatch_size:
            raise ValueError(
                f"the batch num_envs × num_steps = {self.num_envs * self.num_steps} must be a multiple "
                f"of minibatch_size {self.minibatch_size}"
            )
        if self.init == "":
            raise ValueError(f"init must be a checkpoint's path, got {self.init!r}")
        if self.critic_warmup < 0:
            raise ValueError(
                f"critic_warmup must be a number of updates (0 or more), got {self.critic_warmup!r}"
            )
        if self.policy_lr is not None and self.policy_lr <= 0:
            raise ValueError(f"policy_lr must be a learning rate above 0 (or absent), got {self.policy_lr!r}")
        if self.norm_adv_scope not in ("minibatch", "batch"):
            raise ValueError(f"norm_adv_scope {self.norm_adv_scope!r}: minibatch or batch")
        if not 0 < self.gamma <= 1 or not 0 <= self.gae_lambda <= 1:
            raise ValueError("gamma must be in (0, 1] and gae_lambda in [0, 1]")
        check_device(self.device)
        terms = {f.name for f in fields(RewardWeights)}
        if set(self.reward) - terms:
            raise ValueError(
                f"unknown reward terms {sorted(set(self.reward) - terms)}: known are {sorted(terms)}"
            )
        if any(isinstance(v, bool) or not isinstance(v, int | float) for v in self.reward.values()):
            raise ValueError(f"reward weights must be numbers: {self.reward}")

    @property
    def batch_size(self) -> int:
        """Steps per update (num_envs × num_steps)."""
        return self.num_envs * self.num_steps

    @property
    def num_updates(self) -> int:
        """Updates to reach `total_steps`."""
        return max(1, self.total_steps // self.batch_size)

    def reward_weights(self) -> RewardWeights | None:
        """The reward weights to ask the server for (None: its defaults, SPEC §6)."""
        return RewardWeights(**self.reward) if self.reward else None

    def to_dict(self) -> dict[str, Any]:
        """The config as plain values (for checkpoints and logs)."""
        return asdict(self)


NETWORK_SETTINGS = ("resolution", "encoder", "pool", "feature_dim", "grasp_dim", "hidden")
"""The settings of a `PpoConfig` that shape its network: a checkpoint's weights fit another config's
network when these are equal."""


def _layer(layer: nn.Linear, std: float = float(np.sqrt(2)), bias: float = 0.0) -> nn.Linear:
    """CleanRL's orthogonal initialisation."""
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


class PpoNet(nn.Module):
    """Encoders, grasp embedding, one LSTM layer, actor and critic heads."""

    def __init__(self, config: PpoConfig) -> None:
        super().__init__()
        self.config = config
        side = config.resolution // config.pool
        self.ego = make_encoder(config.encoder, config.feature_dim, side)
        self.goal = make_encoder(config.encoder, config.feature_dim, side)
        self.grasp = nn.Embedding(2, config.grasp_dim)
        width = 2 * config.feature_dim + config.grasp_dim
        self.fuse = nn.Sequential(_layer(nn.Linear(width, config.hidden)), nn.ReLU())
        self.lstm = nn.LSTM(config.hidden, config.hidden)
        for name, parameter in self.lstm.named_parameters():
            if "bias" in name:
                nn.init.constant_(parameter, 0)
            elif "weight" in name:
                nn.init.orthogonal_(parameter, 1.0)
        self.actor = nn.Sequential(
            _layer(nn.Linear(config.hidden, config.hidden)),
            nn.Tanh(),
            _layer(nn.Linear(config.hidden, ACTIONS), std=0.01),
        )
        self.critic = nn.Sequential(
            _layer(nn.Linear(config.hidden, config.hidden)),
            nn.Tanh(),
            _layer(nn.Linear(config.hidden, 1), std=1.0),
        )

    def initial_state(self, batch: int, device: torch.device | str = "cpu") -> LstmState:
        """The zero LSTM state for `batch` episodes."""
        shape = (1, batch, self.config.hidden)
        return torch.zeros(shape, device=device), torch.zeros(shape, device=device)

    def preprocess(self, rgb: torch.Tensor) -> torch.Tensor:
        """uint8 images (B, R, R, 3) → the encoders' inputs: float (B, 3, R/pool, R/pool) in [-1, 1]
        (training keeps these, so that its epochs do not convert the same images again).
        """
        if rgb.shape[-2] != self.config.resolution:
            raise ValueError(
                f"the network takes {self.config.resolution}×{self.config.resolution} images, got "
                f"{rgb.shape[-2]}×{rgb.shape[-3]} (the server's resolution must be the config's)"
            )
        images = rgb.permute(0, 3, 1, 2).float()
        if self.config.pool > 1:
            images = F.avg_pool2d(images, self.config.pool)
        return images.mul_(1 / 127.5).sub_(1.0)

    def recurrent(
        self, features: torch.Tensor, state: LstmState, starts: torch.Tensor
    ) -> tuple[torch.Tensor, LstmState]:
        """Runs the LSTM over (T × N) features in time-major order, zeroing an episode's state before
        its first step (`starts`, (T × N) floats, 1 where a new episode begins); returns the outputs
        (T × N, hidden) and the state after the last step.
        """
        n = state[0].shape[1]
        features = features.reshape(-1, n, self.lstm.input_size)
        starts = starts.reshape(-1, n)
        # One LSTM call per run of steps in which no episode starts (episodes are long, so a
        # minibatch has a few runs, not a call per step): the same outputs, far cheaper to run and
        # to differentiate.
        cuts = (torch.nonzero((starts[1:] > 0).any(dim=1)).flatten() + 1).tolist()
        bounds = [0, *cuts, features.shape[0]]
        outputs = []
        for first, end in zip(bounds[:-1], bounds[1:], strict=True):
            keep = (1.0 - starts[first]).view(1, -1, 1)
            out, state = self.lstm(features[first:end], (keep * state[0], keep * state[1]))
            outputs.append(out)
        return torch.flatten(torch.cat(outputs), 0, 1), state

    def forward(
        self,
        ego: torch.Tensor,
        goal: torch.Tensor,
        grasping: torch.Tensor,
        state: LstmState,
        starts: torch.Tensor,
        goal_index: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, LstmState]:
        """Action logits (T × N, 6), values (T × N,) and the LSTM state after the last step, from
        preprocessed images (`preprocess`), grasp flags and episode starts, in time-major order.

        `goal` holds one goal image per step or, with `goal_index` (T × N longs), the distinct goal
        images, step k's being `goal[goal_index[k]]`: an episode keeps one goal, so encoding each
        once gives the same outputs for a fraction of the encoder's cost.
        """
        goal_features = self.goal(goal)
        if goal_index is not None:
            goal_features = goal_features[goal_index]
        return self.forward_features(ego, goal_features, grasping, state, starts)

    def forward_features(
        self,
        ego: torch.Tensor,
        goal_features: torch.Tensor,
        grasping: torch.Tensor,
        state: LstmState,
        starts: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, LstmState]:
        """`forward` with the goal images already encoded (`self.goal(goal)`, one row per step)."""
        joined = torch.cat([self.ego(ego), goal_features, self.grasp(grasping.long())], dim=-1)
        hidden, state = self.recurrent(self.fuse(joined), state, starts)
        return self.actor(hidden), self.critic(hidden).squeeze(-1), state


def load_network(path: str | Path, device: torch.device | str = "cpu") -> PpoNet:
    """The network of a checkpoint `esrp train ppo` wrote, in eval mode."""
    state = read_checkpoint(path, "esrp-ppo", "ESRP-PPO", device)
    network = PpoNet(PpoConfig.from_mapping(state["config"])).to(device)
    network.load_state_dict(state["model"])
    network.eval()
    return network


class PpoAgent:
    """Plays a `PpoNet` for one episode: the LSTM state starts at zero, each action is drawn from
    the policy's distribution (seeded by `info["seed"]`: same seed, same actions) or, with
    `deterministic`, its most likely action.
    """

    def __init__(self, network: PpoNet, config: Mapping[str, Any]) -> None:
        self.network = network
        self.deterministic = bool(config.get("deterministic", False))
        self.state = network.initial_state(1)
        self.goal: torch.Tensor | None = None
        self.generator = torch.Generator().manual_seed(0)

    @torch.no_grad()
    def reset(self, observation: Observation, info: Mapping[str, Any]) -> None:
        """Starts an episode: zero LSTM state, the goal image encoded once for the whole episode."""
        self.generator = torch.Generator().manual_seed(int(info["seed"]))
        self.state = self.network.initial_state(1)
        goal = self.network.preprocess(torch.from_numpy(np.array(observation.goal_rgb))[None])
        self.goal = self.network.goal(goal)

    @torch.no_grad()
    def act(self, observation: Observation) -> Action:
        """The next action."""
        if self.goal is None:
            raise RuntimeError("act() before reset()")
        ego = self.network.preprocess(torch.from_numpy(np.array(observation.ego_rgb))[None])
        grasping = torch.tensor([int(observation.grasping)])
        logits, _, self.state = self.network.forward_features(
            ego, self.goal, grasping, self.state, torch.zeros(1)
        )
        if self.deterministic:
            return Action(int(logits.argmax(dim=-1)[0]))
        probs = torch.softmax(logits[0], dim=-1)
        return Action(int(torch.multinomial(probs, 1, generator=self.generator)[0]))


class PpoPolicy:
    """The agent factory of `esrp eval --agent ppo`: loads the checkpoint (`config["checkpoint"]`)
    once; each call makes an agent for one episode. Config keys: `checkpoint`, `deterministic`
    (the most likely action instead of a draw), `threads` (torch's, default 1).
    """

    def __init__(self, config: Mapping[str, Any]) -> None:
        check_agent_config(config, "ppo", {"checkpoint": "path", "deterministic": "bool", "threads": "int"})
        self.network = load_network(policy_checkpoint(config, "ppo"))
        self.sensors = Sensors(resolution=self.network.config.resolution)
        """What its episodes must be created with: views at the network's resolution."""

    def __call__(self, config: dict[str, Any]) -> PpoAgent:
        """An agent for one episode."""
        return PpoAgent(self.network, config)
