"""`esrp train ppo`: trains ESRP-PPO (`esrp.agents.ppo`) on the native vector env, CleanRL-style.

One readable loop, as CleanRL's `ppo_atari_lstm.py`: `num_envs` episodes run on one
`RearrangeVectorEnv` (SAME_STEP autoreset, the server's dense reward of SPEC §6 unless the config
sets weights); each update collects `num_steps` steps of every episode, computes GAE advantages
and runs `update_epochs` epochs of clipped PPO over minibatches of whole sequences, the LSTM
starting from the state it had at the rollout's start. Truncated episodes (the horizon) are
bootstrapped with the value of their final observation; terminated ones (success) are not.
With `norm_reward` the learner's rewards are scaled by the running standard deviation of the
discounted return (its statistics kept in the checkpoint); with `norm_adv_scope = "batch"` the
advantages are normalised once over the rollout instead of in each minibatch. With `init` the
network starts from a checkpoint's weights (e.g. `esrp train ppo-bc`'s imitation), and for the first
`critic_warmup` updates only its critic head learns.

A run folder holds `config.json`, `log.csv` (one line per update: steps, episodes finished,
their mean return, length and success rate, the losses, approximate KL, clip fraction, explained
variance, learning rate, steps per second, seconds, and where the update's time went: in the
environment's steps, in choosing actions, in learning), `episodes.csv` (every finished episode:
step, return, length, success) and `ckpt.pt` (network, optimizer, update, step, random states:
`--resume` goes on from it with fresh episodes; `esrp eval --agent ppo --checkpoint` plays it).
"""

from __future__ import annotations

import csv
import json
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers.utils import RunningMeanStd
from torch import nn

from .. import _malloc_setup
from .._client import Client
from .._values import Sensors
from ..agents._checkpoint import read_checkpoint
from ..agents.encoders import resolve_device
from ..agents.ppo import NETWORK_SETTINGS, LstmState, PpoConfig, PpoNet
from ..envs import RearrangeVectorEnv
from ._config import read_table
from ._training import logged_seconds, resume_from, rewrite_csv, run_folder, save_checkpoint

__all__ = [
    "RewardScale",
    "UpdateStats",
    "critic_and_policy",
    "gae",
    "group_rates",
    "load_config",
    "load_initial_weights",
    "make_env",
    "parameter_groups",
    "ppo_loss",
    "train",
]

LOG_FIELDS = (
    "update",
    "steps",
    "episodes",
    "return_mean",
    "length_mean",
    "success_rate",
    "policy_loss",
    "value_loss",
    "entropy",
    "approx_kl",
    "clipfrac",
    "explained_variance",
    "lr",
    "steps_per_second",
    "seconds",
    "env_seconds",
    "act_seconds",
    "learn_seconds",
)
# Settings a resumed run may change: its length, its checkpoint interval, where and how it runs.
RESUMABLE = {"total_steps", "checkpoint_every", "threads", "device"}
# The values of settings an older run's checkpoint predates (it was trained as these say).
LEGACY = {"init": None, "critic_warmup": 0, "policy_lr": None}


def load_config(path: Path) -> PpoConfig:
    """The `[ppo]` table of a TOML file (or the top level of a JSON file) as a `PpoConfig`."""
    table = read_table(path, "ppo")
    try:
        return PpoConfig.from_mapping(table)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: {error}") from None


@dataclass
class UpdateStats:
    """What one update did (a line of `log.csv`)."""

    update: int
    steps: int
    episodes: int
    return_mean: float
    length_mean: float
    success_rate: float
    policy_loss: float
    value_loss: float
    entropy: float
    approx_kl: float
    clipfrac: float
    explained_variance: float
    lr: float
    steps_per_second: float
    seconds: float
    env_seconds: float = 0.0
    """Of this update: waiting for the vector env's steps (the server's work and the transport)."""
    act_seconds: float = 0.0
    """Choosing the rollout's actions: preprocessing, the network's forward pass, sampling."""
    learn_seconds: float = 0.0
    """The advantages and the PPO epochs (forward, backward, optimizer)."""


def _tensor(array: np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array)).to(device)


def make_env(config: PpoConfig, client: Client) -> RearrangeVectorEnv:
    """The vector env a config trains on: `num_envs` episodes of its scenes with its horizon, reward
    weights and resolution, SAME_STEP autoreset.
    """
    return RearrangeVectorEnv(
        config.num_envs,
        client=client,
        split=config.split,
        difficulty=config.difficulty,
        scene=config.scene,
        sensors=Sensors(resolution=config.resolution),
        horizon=config.horizon,
        reward=config.reward_weights(),
        autoreset_mode=AutoresetMode.SAME_STEP,
    )


def train(
    config: PpoConfig,
    out: Path,
    client: Client,
    *,
    resume: bool = False,
    progress: bool = True,
    on_update: Callable[[UpdateStats], None] | None = None,
    stop_at: int | None = None,
) -> Path:
    """Trains until `config.total_steps` environment steps (from the checkpoint in `out` with
    `resume`) on the server behind `client`; returns the checkpoint's path.

    `stop_at` ends the run early, with a checkpoint, after the first update that reaches that many
    steps, leaving the schedule (the learning rate's annealing) as `total_steps` sets it: a later
    `resume` goes on, for instance on other scenes (a curriculum).
    """
    if stop_at is not None and stop_at < 1:
        raise ValueError(f"stop_at must be at least 1 step, got {stop_at}")
    _malloc_setup.apply()  # the step and batch buffers stay mapped (esrp._malloc_setup)
    device = resolve_device(config.device)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    checkpoint = run_folder(out, resume)
    torch.manual_seed(config.seed)
    network = PpoNet(config).to(device)
    optimizer = torch.optim.Adam(parameter_groups(network, config), lr=config.lr, eps=1e-5)
    update, global_step = 0, 0
    scale = RewardScale(config.gamma, config.num_envs) if config.norm_reward else None
    if resume and checkpoint.exists():
        state = resume_from(checkpoint, "esrp-ppo", network, optimizer, RESUMABLE, device, legacy=LEGACY)
        update, global_step = int(state["update"]), int(state["steps"])
        if update > config.num_updates:
            raise ValueError(
                f"{checkpoint} has made {update} updates ({global_step} steps), more than total_steps "
                f"{config.total_steps} allows ({config.num_updates}): ask for {global_step} or more to go on"
            )
        if scale is not None:
            scale.load(state["reward_scale"])
        print(f"resuming {checkpoint} after update {update} ({global_step} steps)", file=sys.stderr)
        _trim_logs(out, update, global_step)
    elif config.init is not None:
        load_initial_weights(network, Path(config.init), device)
        if progress:
            print(f"starting from the weights of {config.init}", file=sys.stderr)
    if stop_at is not None and global_step >= stop_at:
        _start_files(config, out, update)
        print(f"{checkpoint} has {global_step} steps (stop at {stop_at}): nothing to do", file=sys.stderr)
        return checkpoint
    env = make_env(config, client)
    try:
        # A resumed run starts fresh episodes, seeded apart from the ones before. Their creation
        # checks the config against the server (its scenes, the resolution) before the run folder
        # is made: a run refused at its start leaves none behind.
        observations, _ = env.reset(seed=config.seed + update)
        _start_files(config, out, update)
        _loop(
            config,
            network,
            optimizer,
            env,
            observations,
            device,
            out,
            update,
            global_step,
            progress,
            on_update,
            stop_at,
            scale,
        )
    finally:
        env.close()
    return checkpoint


def _start_files(config: PpoConfig, out: Path, update: int) -> None:
    """Makes the run folder `out` if missing and writes its `config.json`, and at update 0 the
    headers of `log.csv` and `episodes.csv`.
    """
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(config.to_dict(), indent=2) + "\n", encoding="utf-8")
    if update == 0:
        with open(out / "log.csv", "w", newline="") as file:
            csv.writer(file).writerow(LOG_FIELDS)
        with open(out / "episodes.csv", "w", newline="") as file:
            csv.writer(file).writerow(["steps", "return", "length", "success"])


def parameter_groups(network: PpoNet, config: PpoConfig) -> list[dict[str, Any]]:
    """The optimizer's parameter groups, in the order of `group_rates`: one group, or with
    `policy_lr` the critic head's and every other parameter's (the policy's: the encoders, the
    LSTM, the actor head).
    """
    if config.policy_lr is None:
        return [{"params": list(network.parameters()), "lr": config.lr}]
    critic, policy = critic_and_policy(network)
    return [{"params": critic, "lr": config.lr}, {"params": policy, "lr": config.policy_lr}]


def critic_and_policy(network: PpoNet) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
    """The critic head's parameters, and every other one (the policy's: the encoders, the LSTM and
    the actor head, which the critic shares the first two of).
    """
    named = list(network.named_parameters())
    return [p for n, p in named if n.startswith("critic.")], [
        p for n, p in named if not n.startswith("critic.")
    ]


def group_rates(config: PpoConfig) -> list[float]:
    """The learning rate of each of `parameter_groups` before annealing: `lr`, or `lr` for the
    critic head and `policy_lr` for the rest.
    """
    return [config.lr] if config.policy_lr is None else [config.lr, config.policy_lr]


def load_initial_weights(network: PpoNet, path: Path, device: torch.device) -> None:
    """Loads the weights of the ESRP-PPO checkpoint at `path` into `network` (`PpoConfig.init`).
    Raises `ValueError` for a missing file, another kind of checkpoint, or a network of other
    settings (`NETWORK_SETTINGS`).
    """
    if not path.is_file():
        raise ValueError(f"init: {path} does not exist")
    try:
        state = read_checkpoint(path, "esrp-ppo", "ESRP-PPO", device)
    except ValueError as error:
        raise ValueError(f"init: {error}") from None
    theirs = {k: state["config"].get(k) for k in NETWORK_SETTINGS}
    ours = {k: getattr(network.config, k) for k in NETWORK_SETTINGS}
    if theirs != ours:
        raise ValueError(f"init: {path} holds a network of other settings ({theirs}, this config's: {ours})")
    network.load_state_dict(state["model"])


def _loop(
    config: PpoConfig,
    network: PpoNet,
    optimizer: torch.optim.Optimizer,
    env: RearrangeVectorEnv,
    observations: Mapping[str, np.ndarray],
    device: torch.device,
    out: Path,
    update: int,
    global_step: int,
    progress: bool,
    on_update: Callable[[UpdateStats], None] | None,
    stop_at: int | None = None,
    scale: RewardScale | None = None,
) -> None:
    """Runs the updates after `update` (`global_step` environment steps) until `config.num_updates`
    (or `stop_at`), from the `observations` of `env`'s first reset (`train` makes it before the
    run folder): each collects a rollout of `num_steps` steps of every episode of `env`, computes
    GAE advantages, runs the PPO epochs, then logs the update in `out` (and hands it to `on_update`)
    and writes the checkpoint: every `checkpoint_every` updates, after the last, and where it stops.

    One function on purpose, as CleanRL's `ppo_atari_lstm.py`: the rollout's buffers, the LSTM
    state carried from step to step and across updates, and the order of the steps are read top
    to bottom in one place.
    """
    steps_, n = config.num_steps, config.num_envs
    side = config.resolution // config.pool
    # Images are kept preprocessed (float, pooled): the epochs read them without converting again.
    # An episode keeps one goal image: a rollout stores each distinct goal once (`goals`) and the
    # index of each step's (`goal_index`), and encodes a goal once per episode and minibatch.
    ego = torch.zeros((steps_, n, 3, side, side), device=device)
    goal_index = torch.zeros((steps_, n), dtype=torch.long, device=device)
    grasping = torch.zeros((steps_, n), dtype=torch.long, device=device)
    actions = torch.zeros((steps_, n), dtype=torch.long, device=device)
    logprobs = torch.zeros((steps_, n), device=device)
    rewards = torch.zeros((steps_, n), device=device)
    starts = torch.zeros((steps_, n), device=device)
    values = torch.zeros((steps_, n), device=device)
    next_start = torch.ones(n, device=device)  # every sub-env begins an episode
    state = network.initial_state(n, device)
    episode_return = np.zeros(n)
    episode_length = np.zeros(n, dtype=np.int64)
    _, held = critic_and_policy(network)  # what the critic warm-up holds still
    # A resumed run's `seconds` go on from the interrupted run's last logged update.
    started = time.monotonic() - logged_seconds(out / "log.csv")
    while update < config.num_updates:
        update_started = time.monotonic()
        initial = (state[0].clone(), state[1].clone())
        fraction = 1.0 - update / config.num_updates if config.anneal_lr else 1.0
        lr = config.lr * fraction
        for param_group, rate in zip(optimizer.param_groups, group_rates(config), strict=True):
            param_group["lr"] = rate * fraction
        finished: list[tuple[int, float, int, bool]] = []
        env_seconds = 0.0
        goals = [network.preprocess(_tensor(observations["goal_rgb"], device))]
        current = torch.arange(n, device=device)  # each sub-env's goal in `goals`
        with torch.no_grad():
            goal_features = network.goal(goals[0])
        for t in range(steps_):
            ego[t] = network.preprocess(_tensor(observations["ego_rgb"], device))
            goal_index[t] = current
            grasping[t] = _tensor(observations["grasping"], device)
            starts[t] = next_start
            with torch.no_grad():
                logits, value, state = network.forward_features(
                    ego[t], goal_features, grasping[t], state, next_start
                )
                action = torch.multinomial(torch.softmax(logits, dim=-1), 1).squeeze(-1)
                logprob, _ = _log_prob_entropy(logits, action)
            actions[t], logprobs[t], values[t] = action, logprob, value
            stepping = time.monotonic()
            observations, reward, terminated, truncated, infos = env.step(action.cpu().numpy())
            env_seconds += time.monotonic() - stepping
            global_step += n
            episode_return += reward
            episode_length += 1
            reward = reward.copy() if scale is None else scale(reward, terminated | truncated)
            cut = np.flatnonzero(truncated & ~terminated)
            if cut.size:
                # The horizon cut these episodes short: bootstrap with their final observation's
                # value (from the state that saw the step before it).
                finals = [infos["final_obs"][i] for i in cut]
                keep = (state[0][:, cut], state[1][:, cut])
                with torch.no_grad():
                    _, final_value, _ = network.forward_features(
                        network.preprocess(_tensor(np.stack([f["ego_rgb"] for f in finals]), device)),
                        goal_features[torch.from_numpy(cut).to(device)],
                        _tensor(np.array([f["grasping"] for f in finals]), device),
                        keep,
                        torch.zeros(cut.size, device=device),
                    )
                reward[cut] += config.gamma * final_value.cpu().numpy()
            rewards[t] = _tensor(reward.astype(np.float32), device)
            done = terminated | truncated
            for i in np.flatnonzero(done).tolist():
                success = bool(infos["final_info"]["metrics"]["success"][i])
                finished.append((global_step, float(episode_return[i]), int(episode_length[i]), success))
                episode_return[i], episode_length[i] = 0.0, 0
            next_start = _tensor(done.astype(np.float32), device)
            if done.any():
                # Autoreset began new episodes: their goals join the rollout's.
                fresh = torch.from_numpy(np.flatnonzero(done)).to(device)
                images = network.preprocess(_tensor(observations["goal_rgb"][done], device))
                current[fresh] = sum(len(g) for g in goals) + torch.arange(len(fresh), device=device)
                goals.append(images)
                with torch.no_grad():
                    goal_features[fresh] = network.goal(images)

        # Generalised advantage estimation.
        learning = time.monotonic()
        with torch.no_grad():
            _, next_value, _ = network.forward_features(
                network.preprocess(_tensor(observations["ego_rgb"], device)),
                goal_features,
                _tensor(observations["grasping"], device),
                state,
                next_start,
            )
            advantages, returns = gae(
                rewards, values, starts, next_value, next_start, config.gamma, config.gae_lambda
            )
            if config.norm_adv and config.norm_adv_scope == "batch":
                advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)

        # PPO epochs over minibatches of whole sequences (sub-envs), time-major within each.
        def flat(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(steps_ * n, *x.shape[2:])

        columns = {
            "ego": flat(ego),
            "goal_index": flat(goal_index),
            "grasping": flat(grasping),
            "starts": flat(starts),
            "actions": flat(actions),
            "logprobs": flat(logprobs),
            "advantages": flat(advantages),
            "returns": flat(returns),
            "values": flat(values),
        }
        all_goals = torch.cat(goals)
        b_returns, b_values = columns["returns"], columns["values"]
        indices = np.arange(steps_ * n).reshape(steps_, n)
        envs_per_batch = config.minibatch_size // steps_
        rng = np.random.default_rng(config.seed * 1_000_003 + update)
        order = np.arange(n)
        sums = np.zeros(5)
        batches = 0
        for _ in range(config.update_epochs):
            rng.shuffle(order)
            approx_kl = torch.zeros(())
            for first in range(0, n, envs_per_batch):
                group_envs = order[first : first + envs_per_batch]
                mb = torch.from_numpy(indices[:, group_envs].ravel()).to(device)
                envs = torch.from_numpy(group_envs).to(device)
                minibatch = {key: column[mb] for key, column in columns.items()}
                # Only the goals this minibatch's steps look at, each encoded once.
                used, minibatch["goal_index"] = torch.unique(minibatch["goal_index"], return_inverse=True)
                minibatch["goal"] = all_goals[used]
                loss, losses = ppo_loss(
                    network, config, minibatch, (initial[0][:, envs], initial[1][:, envs])
                )
                approx_kl = losses[3]
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"update {update + 1}: the loss is {loss.item()}")
                optimizer.zero_grad()
                loss.backward()  # type: ignore[no-untyped-call]
                if update < config.critic_warmup:
                    for parameter in held:
                        parameter.grad = None  # Adam leaves a parameter without a gradient as it is
                nn.utils.clip_grad_norm_(network.parameters(), config.max_grad_norm)
                optimizer.step()
                sums += [x.item() for x in losses]
                batches += 1
            if config.target_kl > 0 and approx_kl.item() > config.target_kl:
                break
        update += 1
        variance = b_returns.var()
        explained = float("nan") if variance == 0 else float(1 - (b_returns - b_values).var() / variance)
        mean = sums / max(batches, 1)
        now = time.monotonic()
        seconds = now - update_started
        learn_seconds = now - learning
        stats = UpdateStats(
            update=update,
            steps=global_step,
            episodes=len(finished),
            return_mean=float(np.mean([f[1] for f in finished])) if finished else float("nan"),
            length_mean=float(np.mean([f[2] for f in finished])) if finished else float("nan"),
            success_rate=float(np.mean([f[3] for f in finished])) if finished else float("nan"),
            policy_loss=float(mean[0]),
            value_loss=float(mean[1]),
            entropy=float(mean[2]),
            approx_kl=float(mean[3]),
            clipfrac=float(mean[4]),
            explained_variance=explained,
            lr=lr,
            steps_per_second=config.batch_size / seconds,
            seconds=time.monotonic() - started,
            env_seconds=env_seconds,
            act_seconds=seconds - env_seconds - learn_seconds,
            learn_seconds=learn_seconds,
        )
        _log(out, stats, finished)
        if progress:
            print(
                f"update {update}/{config.num_updates}  steps {global_step}  episodes {stats.episodes}  "
                f"return {stats.return_mean:.2f}  success {stats.success_rate:.2f}  "
                f"entropy {stats.entropy:.3f}  {stats.steps_per_second:.0f} steps/s",
                file=sys.stderr,
            )
        if on_update is not None:
            on_update(stats)
        stopping = stop_at is not None and global_step >= stop_at
        if update % config.checkpoint_every == 0 or update == config.num_updates or stopping:
            extra = None if scale is None else {"reward_scale": scale.state()}
            save_checkpoint(
                out / "ckpt.pt", "esrp-ppo", network, optimizer, extra=extra, update=update, steps=global_step
            )
        if stopping:
            print(f"stopped at {global_step} steps (--stop-at {stop_at}): --resume goes on", file=sys.stderr)
            break


class RewardScale:
    """The rewards the learner sees, divided by the running standard deviation of each sub-env's
    discounted return (Gymnasium's `NormalizeReward`, over the vector env's steps).
    """

    def __init__(self, gamma: float, num_envs: int) -> None:
        self.gamma = gamma
        self.returns = np.zeros(num_envs)
        self.statistics = RunningMeanStd(shape=())  # type: ignore[no-untyped-call]

    def __call__(self, reward: np.ndarray, done: np.ndarray) -> np.ndarray:
        """`reward` of one step, scaled; `done` ends the sub-envs' episodes with this step."""
        self.returns = self.returns * self.gamma + reward
        self.statistics.update(self.returns)  # type: ignore[no-untyped-call]
        self.returns[done] = 0.0
        return reward / np.sqrt(self.statistics.var + 1e-8)

    def state(self) -> dict[str, Any]:
        """What `load` takes back (kept in the checkpoint)."""
        return {
            "mean": float(self.statistics.mean),
            "var": float(self.statistics.var),
            "count": float(self.statistics.count),
        }

    def load(self, state: Mapping[str, Any]) -> None:
        """Restores `state()`; a resumed run's episodes start fresh, so their returns start at 0."""
        self.statistics.mean = np.float64(state["mean"])
        self.statistics.var = np.float64(state["var"])
        self.statistics.count = float(state["count"])


def gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    starts: torch.Tensor,
    next_value: torch.Tensor,
    next_start: torch.Tensor,
    gamma: float,
    gae_lambda: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimates and returns of a rollout: `rewards`, `values` and `starts`
    (1 where step t is an episode's first) are (T, N); `next_value` and `next_start` are the step
    after the rollout's. No value is carried across an episode start.
    """
    advantages = torch.zeros_like(rewards)
    last = torch.zeros_like(next_value)
    steps = rewards.shape[0]
    for t in reversed(range(steps)):
        if t == steps - 1:
            continuing, following = 1.0 - next_start, next_value
        else:
            continuing, following = 1.0 - starts[t + 1], values[t + 1]
        delta = rewards[t] + gamma * following * continuing - values[t]
        last = delta + gamma * gae_lambda * continuing * last
        advantages[t] = last
    return advantages, advantages + values


def ppo_loss(
    network: PpoNet, config: PpoConfig, batch: Mapping[str, torch.Tensor], state: LstmState
) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
    """The clipped PPO loss of a minibatch of whole sequences (time-major, flattened: `ego`, `goal`
    preprocessed images, `grasping`, `starts`, `actions`, and the rollout's `logprobs`,
    `advantages`, `returns`, `values`; with `goal_index`, `goal` holds the distinct goal images as
    in `PpoNet.forward`), the LSTM starting from `state`; and (policy loss, value loss, entropy,
    approximate KL, clip fraction), the last two without gradients.
    """
    logits, new_value, _ = network(
        batch["ego"], batch["goal"], batch["grasping"], state, batch["starts"], batch.get("goal_index")
    )
    new_logprob, entropy = _log_prob_entropy(logits, batch["actions"])
    log_ratio = new_logprob - batch["logprobs"]
    ratio = log_ratio.exp()
    with torch.no_grad():
        approx_kl = ((ratio - 1) - log_ratio).mean()
        clipfrac = ((ratio - 1.0).abs() > config.clip_coef).float().mean()
    advantage = batch["advantages"]
    if config.norm_adv and config.norm_adv_scope == "minibatch" and advantage.numel() > 1:
        advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
    policy_loss = torch.max(
        -advantage * ratio, -advantage * torch.clamp(ratio, 1 - config.clip_coef, 1 + config.clip_coef)
    ).mean()
    returns, values = batch["returns"], batch["values"]
    if config.clip_vloss:
        clipped = values + torch.clamp(new_value - values, -config.clip_coef, config.clip_coef)
        value_loss = 0.5 * torch.max((new_value - returns) ** 2, (clipped - returns) ** 2).mean()
    else:
        value_loss = 0.5 * ((new_value - returns) ** 2).mean()
    loss = policy_loss - config.ent_coef * entropy + config.vf_coef * value_loss
    return loss, (policy_loss, value_loss, entropy, approx_kl, clipfrac)


def _log_prob_entropy(logits: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The log-probabilities of `actions` and the mean entropy under the policy's `logits`."""
    log_probs = torch.log_softmax(logits, dim=-1)
    entropy = -(log_probs.exp() * log_probs).sum(dim=-1).mean()
    return log_probs.gather(-1, actions[:, None]).squeeze(-1), entropy


def _log(out: Path, stats: UpdateStats, finished: list[tuple[int, float, int, bool]]) -> None:
    values: dict[str, Any] = vars(stats)
    row = [f"{values[k]:.6g}" if isinstance(values[k], float) else values[k] for k in LOG_FIELDS]
    with open(out / "log.csv", "a", newline="") as file:
        csv.writer(file).writerow(row)
    with open(out / "episodes.csv", "a", newline="") as file:
        writer = csv.writer(file)
        for steps, episode_return, length, success in finished:
            writer.writerow([steps, f"{episode_return:.4f}", length, int(success)])


def _trim_logs(out: Path, update: int, steps: int) -> None:
    """Drops the log lines written after the checkpoint a run resumes from (they are done again)."""
    for name, column, last in (("log.csv", "update", update), ("episodes.csv", "steps", steps)):
        path = out / name
        if not path.exists():
            continue
        with open(path, newline="") as file:
            rows = list(csv.reader(file))
        if not rows:
            continue
        at = rows[0].index(column)
        kept = [rows[0], *(row for row in rows[1:] if int(row[at]) <= last)]
        if name == "log.csv" and rows[0] != list(LOG_FIELDS):
            # A log of an older version: its lines under today's columns, the new ones left empty.
            named = [dict(zip(rows[0], row, strict=False)) for row in kept[1:]]
            kept = [list(LOG_FIELDS), *([line.get(field, "") for field in LOG_FIELDS] for line in named)]
        rewrite_csv(path, kept)
