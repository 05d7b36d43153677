"""TorchRL through `esrp.integrations.torchrl`: TorchRL's `check_env_specs` on the single env
(`GymEnv`) and the batched one (over the native vector env), a planned episode solved through
both with the same observations and `is_success` on its last step, a `Collector` rollout whose
ended episodes TorchRL resets, and clear errors."""

from __future__ import annotations

import warnings
from collections.abc import Iterator

import numpy as np
import pytest
from conftest import settled_live_episodes

import esrp

pytest.importorskip("torchrl", reason="esrp[torchrl] is not installed")

import torch  # noqa: E402
from tensordict import TensorDict, TensorDictBase  # noqa: E402
from torchrl.collectors import Collector  # noqa: E402
from torchrl.envs import EnvBase  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

from esrp.integrations.torchrl import make_env  # noqa: E402

SENSORS = esrp.Sensors(resolution=32)


@pytest.fixture(autouse=True)
def _quiet() -> Iterator[None]:
    # TorchRL warns once that the single env's views (read-only numpy arrays) become tensors.
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
        yield


@pytest.mark.parametrize("num_envs", [None, 3])
@pytest.mark.parametrize("categorical", [False, True])
def test_check_env_specs(server: esrp.LocalServer, num_envs: int | None, categorical: bool) -> None:
    env = make_env(
        num_envs,
        server.address,
        categorical_action_encoding=categorical,
        split="test",
        difficulty="easy",
        sensors=SENSORS,
        horizon=4,
    )
    try:
        check_env_specs(env)
        batch = () if num_envs is None else (num_envs,)
        assert tuple(env.batch_size) == batch
        assert env.observation_spec["ego_rgb"].shape == (*batch, 32, 32, 3)
        assert env.observation_spec["ego_rgb"].dtype == torch.uint8
        assert env.observation_spec["is_success"].shape == (*batch, 1)
        assert env.full_action_spec["action"].shape == ((*batch,) if categorical else (*batch, 6))
    finally:
        env.close()


def plan(client: esrp.Client, scene: str) -> list[int]:
    """The planner's actions that solve `scene` from its start."""
    with client.create_episode(scene, privileged=True) as episode:
        answer = episode.plan_actions()
    assert answer.reaches_success
    return [int(action) for action in answer.actions]


def play(env: EnvBase, actions: list[int]) -> TensorDictBase:
    """A rollout of `env` taking `actions` (the same in every episode of the batch)."""
    steps = iter(actions)

    def policy(tensordict: TensorDictBase) -> TensorDictBase:
        action = torch.full(env.batch_size, next(steps), dtype=torch.int64)
        return tensordict.set("action", action)

    return env.rollout(len(actions), policy, break_when_any_done=False)


def test_a_planned_episode_through_both_envs(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str]
) -> None:
    scene = easy_scenes[1]
    actions = plan(client, scene)
    single = make_env(None, server.address, categorical_action_encoding=True, scene=scene, sensors=SENSORS)
    batched = make_env(
        2,
        server.address,
        categorical_action_encoding=True,
        scene=[scene, scene],
        scene_per_env=True,
        sensors=SENSORS,
    )
    try:
        one, two = play(single, actions), play(batched, actions)
    finally:
        single.close()
        batched.close()
    assert one.batch_size == (len(actions),)
    assert two.batch_size == (2, len(actions))
    for rollout in (one, two[0], two[1]):
        done = rollout["next", "done"].squeeze(-1)
        success = rollout["next", "is_success"].squeeze(-1)
        assert done.tolist() == [False] * (len(actions) - 1) + [True]
        assert success.tolist() == done.tolist()  # the last step solved it, no step before
        assert rollout["next", "terminated"][-1].item()
    for key in ("ego_rgb", "goal_rgb", "grasping"):
        assert torch.equal(one[key], two[0][key]), key
        assert torch.equal(one["next", key], two[1]["next", key]), key
    assert one["next", "reward"].sum().item() == pytest.approx(two[0]["next", "reward"].sum().item())


def test_collector_resets_ended_episodes(server: esrp.LocalServer, client: esrp.Client) -> None:
    before = client.server_info().live_episodes
    env = make_env(3, server.address, split="train", difficulty="easy", sensors=SENSORS, horizon=5)
    collector = Collector(env, policy=None, frames_per_batch=3 * 12, total_frames=3 * 24)
    batches: list[TensorDict] = []
    try:
        for batch in collector:
            batches.append(batch.clone())
    finally:
        collector.shutdown()
    assert [tuple(batch.batch_size) for batch in batches] == [(3, 12), (3, 12)]
    done = torch.cat([batch["next", "done"].squeeze(-1) for batch in batches], dim=1).numpy()
    # Random actions never solve an episode in 5 steps: each ends at the horizon, then restarts.
    assert np.array_equal(done, np.tile(np.arange(1, 25) % 5 == 0, (3, 1)))
    truncated = torch.cat([batch["next", "truncated"].squeeze(-1) for batch in batches], dim=1)
    assert torch.equal(truncated, torch.as_tensor(done))
    # The step after an end starts a new episode: its observation is a reset's, not the end's.
    first = batches[0]
    assert not torch.equal(first["ego_rgb"][:, 5], first["next", "ego_rgb"][:, 4])
    assert settled_live_episodes(client, before) == before


def test_clear_errors(server: esrp.LocalServer) -> None:
    with pytest.raises(ValueError, match="autoreset_mode"):
        make_env(2, server.address, autoreset_mode="same-step")
    with pytest.raises(ValueError, match="num_envs"):
        make_env(0, server.address)
