"""Whole episodes through dm_env_rpc's DmEnvAdaptor, the dm_env.Environment agents use."""

from __future__ import annotations

from collections.abc import Iterator

import dm_env
import numpy as np
import pytest
from dm_env import specs
from dm_env_rpc.v1 import dm_env_adaptor
from dm_env_rpc.v1 import dm_env_rpc_pb2 as dm
from dm_env_rpc.v1 import error as dm_error

from harness import ExpertScene, RunningServer, Session


@pytest.fixture
def session(server: RunningServer) -> Iterator[Session]:
    """A connection of its own: the worlds a test creates end with it."""
    session = server.connect()
    yield session
    session.close()


def make_env(session: Session, **settings: object) -> tuple[dm_env_adaptor.DmEnvAdaptor, str]:
    world_name = dm_env_adaptor.create_world(session.connection, settings)
    env = dm_env_adaptor.join_world(session.connection, world_name, {})
    return env, world_name


def test_specs_follow_the_esrp_observations_and_actions(session: Session) -> None:
    env, _ = make_env(session, resolution=64)
    observations = env.observation_spec()
    assert set(observations) == {"ego_rgb", "goal_rgb", "grasping"}
    assert observations["ego_rgb"] == specs.Array((64, 64, 3), np.uint8, "ego_rgb")
    assert observations["goal_rgb"] == specs.Array((64, 64, 3), np.uint8, "goal_rgb")
    assert observations["grasping"] == specs.Array((), np.bool_, "grasping")
    action = env.action_spec()["action"]
    assert isinstance(action, specs.BoundedArray)
    assert (action.shape, action.dtype, action.minimum, action.maximum) == ((), np.int32, 0, 5)
    assert env.reward_spec() == specs.Array((), np.float64, "reward")
    assert env.discount_spec() == specs.BoundedArray((), np.float64, 0.0, 1.0, "discount")
    env.close()


def test_the_expert_succeeds(session: Session, expert: ExpertScene) -> None:
    env, world_name = make_env(session, scene=expert.scene_id)
    first = env.reset()
    assert first.step_type == dm_env.StepType.FIRST
    assert first.observation["ego_rgb"].shape == (128, 128, 3)
    assert first.observation["ego_rgb"].dtype == np.uint8
    assert first.observation["goal_rgb"].any(), "the goal image is not blank"
    assert not first.observation["grasping"]

    total = 0.0
    grasped = False
    for i, code in enumerate(expert.expert_actions):
        timestep = env.step({"action": np.int32(code)})
        total += float(timestep.reward)
        grasped |= bool(timestep.observation["grasping"])
        last = i + 1 == len(expert.expert_actions)
        assert timestep.step_type == (dm_env.StepType.LAST if last else dm_env.StepType.MID), i
    assert timestep.discount == 0.0, "success terminates: discount 0"
    assert grasped, "the expert carried something"
    assert total > 10.0, f"the return {total} includes the success bonus"

    # dm_env: stepping after LAST starts the next episode.
    again = env.step({"action": np.int32(0)})
    assert again.step_type == dm_env.StepType.FIRST
    np.testing.assert_array_equal(again.observation["ego_rgb"], first.observation["ego_rgb"])
    env.close()
    session.connection.send(dm.DestroyWorldRequest(world_name=world_name))


def test_the_horizon_truncates(session: Session) -> None:
    env, _ = make_env(session, horizon=4, split="train", seed=5, resolution=32)
    rng = np.random.default_rng(7)
    for episode in range(2):
        timestep = env.reset()
        assert timestep.first()
        steps = 0
        while not timestep.last():
            timestep = env.step({"action": np.int32(rng.integers(0, 4))})  # motions only: no success
            steps += 1
        assert steps == 4, episode
        assert timestep.discount == 1.0, "truncation keeps discount 1 (INTERRUPTED)"


def test_errors_raise_and_the_connection_goes_on(server: RunningServer, session: Session) -> None:
    env, world_name = make_env(session, resolution=32)
    env.reset()
    with pytest.raises(dm_error.DmEnvRpcError, match="out of range"):
        env.step({"action": np.int32(6)})
    with server.connect() as other, pytest.raises(dm_error.DmEnvRpcError, match="already has its agent"):
        other.send(dm.JoinWorldRequest(world_name=world_name))
    assert env.step({"action": np.int32(2)}).mid()
    env.close()
