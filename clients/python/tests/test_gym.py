"""The Gymnasium env esrp/Rearrange-v1: registration, spaces, check_env, seeding, render, close."""

from __future__ import annotations

import warnings

import gymnasium
import numpy as np
import pytest
from conftest import settled_live_episodes
from gymnasium.utils.env_checker import check_env

import esrp
from esrp.envs import RearrangeEnv


def test_registered_on_import() -> None:
    spec = gymnasium.spec(esrp.ENV_ID)
    assert spec.entry_point == "esrp.envs:RearrangeEnv"
    assert spec.vector_entry_point == "esrp.envs:RearrangeVectorEnv"


def test_check_env(server: esrp.LocalServer, client: esrp.Client) -> None:
    before = client.server_info().live_episodes
    env = gymnasium.make(esrp.ENV_ID, address=server.address, split="test", difficulty="easy", horizon=20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # check_env warns about anything dubious: fail on it
        check_env(env.unwrapped)
    env.close()
    env.close()  # closing twice is allowed
    assert settled_live_episodes(client, before) == before


def test_check_env_with_render_and_sensors(server: esrp.LocalServer) -> None:
    """check_env with its render checks, over every sensor: no warning but the one about depth's
    unbounded Box (depth is +inf where nothing is seen, so the bound is the true one)."""
    everything = esrp.Sensors(depth=True, segmentation=True, current_top_down=True, resolution=16)
    env = gymnasium.make(
        esrp.ENV_ID, address=server.address, split="test", sensors=everything, render_mode="rgb_array"
    )
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_env(env.unwrapped, skip_render_check=False)
        messages = [str(w.message) for w in caught]
        assert len(messages) == 1, messages
        assert "Box observation space maximum value is infinity" in messages[0]
    finally:
        env.close()


def test_spaces_and_observations(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    sensors = esrp.Sensors(depth=True, segmentation=True, current_top_down=True, resolution=32)
    env = gymnasium.make(esrp.ENV_ID, address=server.address, scene=easy_scenes[0], sensors=sensors)
    try:
        assert env.action_space == gymnasium.spaces.Discrete(6)
        space = env.observation_space
        assert isinstance(space, gymnasium.spaces.Dict)
        assert set(space.spaces) == {
            "ego_rgb",
            "goal_rgb",
            "grasping",
            "depth",
            "segmentation",
            "current_top_down",
        }
        observation, info = env.reset(seed=0)
        assert info["scene_id"] == easy_scenes[0]
        assert space.contains(observation)
        assert observation["ego_rgb"].shape == (32, 32, 3)
        assert observation["depth"].dtype == np.float32
        assert observation["segmentation"].dtype == np.uint32
        assert observation["grasping"] == 0
        observation, reward, terminated, truncated, info = env.step(esrp.Action.FETCH)
        assert space.contains(observation)
        assert isinstance(reward, float)
        assert not terminated
        assert not truncated
        assert set(info) == {"accepted", "collided", "placed_count", "step_index"}
        assert info["step_index"] == 1
    finally:
        env.close()


def test_seed_picks_the_scene_deterministically(server: esrp.LocalServer, client: esrp.Client) -> None:
    first = RearrangeEnv(server.address, split="test", difficulty="medium")
    second = RearrangeEnv(client=client, split="test", difficulty="medium")
    try:
        medium = [s.id for s in client.scenes("test", "medium", page_size=1000)]
        assert first.scenes == tuple(medium)
        chosen = []
        for seed in (1, 2, 3, 1):
            a, info_a = first.reset(seed=seed)
            b, info_b = second.reset(seed=seed)
            assert info_a == info_b
            assert info_a["scene_id"] in medium
            assert np.array_equal(a["ego_rgb"], b["ego_rgb"])
            assert np.array_equal(a["goal_rgb"], b["goal_rgb"])
            chosen.append(info_a["scene_id"])
        assert chosen[0] == chosen[3]
        assert len(set(chosen)) > 1
        # Without a seed the generator goes on: the same sequence in both envs.
        assert first.reset()[1] == second.reset()[1]
        assert first.reset(options={"scene": medium[0]})[1]["scene_id"] == medium[0]
    finally:
        first.close()
        second.close()
    assert second.client.server_info().dataset == "esrp-bench-v2"  # the shared client was not closed


def test_episode_ends_and_metrics(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    env = RearrangeEnv(server.address, scene=easy_scenes[0], horizon=3)
    try:
        env.reset(seed=5)
        ended = [env.step(esrp.Action.LEFT) for _ in range(3)]
        assert [step[3] for step in ended] == [False, False, True]
        metrics = ended[-1][4]["metrics"]
        assert metrics["steps"] == 3
        assert metrics["stage"] in (1, 2)
        with pytest.raises(esrp.EpisodeEnded):
            env.step(esrp.Action.LEFT)
        env.reset()
        assert env.step(esrp.Action.LEFT)[4]["step_index"] == 1
    finally:
        env.close()


def test_render(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    env = gymnasium.make(esrp.ENV_ID, address=server.address, scene=easy_scenes[0], render_mode="rgb_array")
    try:
        observation, _ = env.reset(seed=0)
        frame = env.render()
        assert isinstance(frame, np.ndarray)
        assert frame.shape == (128, 256, 3)
        assert frame.dtype == np.uint8
        assert np.array_equal(frame[:, :128], observation["ego_rgb"])
        assert np.array_equal(frame[:, 128:], observation["goal_rgb"])
    finally:
        env.close()
    top_down = esrp.Sensors(current_top_down=True)
    env = gymnasium.make(
        esrp.ENV_ID, address=server.address, scene=easy_scenes[0], sensors=top_down, render_mode="rgb_array"
    )
    try:
        observation, _ = env.reset(seed=0)
        frame = env.render()
        assert isinstance(frame, np.ndarray)
        assert frame.shape == (128, 384, 3)
        assert np.array_equal(frame[:, 256:], observation["current_top_down"])
    finally:
        env.close()


def test_env_starts_its_own_server() -> None:
    """Without an address the env runs a LocalServer of its own, and stops it on close."""
    env = RearrangeEnv(split="test", difficulty="hard")
    (server,) = env._setup.servers  # noqa: SLF001
    assert server.is_running()
    env.reset(seed=0)
    env.close()
    assert not server.is_running()


def test_bad_render_mode(server: esrp.LocalServer) -> None:
    with pytest.raises(ValueError, match="render_mode"):
        RearrangeEnv(server.address, render_mode="human")


def test_scene_list_is_drawn_from(client: esrp.Client, easy_scenes: list[str]) -> None:
    chosen = easy_scenes[:3]
    env = RearrangeEnv(client=client, scene=chosen)
    try:
        assert env.scenes == tuple(chosen)
        drawn = {env.reset(seed=seed)[1]["scene_id"] for seed in range(12)}
        assert drawn == set(chosen)
    finally:
        env.close()
    for bad in ([], ["esrp-bench-v2/00003", ""], [3]):
        with pytest.raises(ValueError, match="scene"):
            RearrangeEnv(client=client, scene=bad)  # type: ignore[arg-type]


def test_a_reset_on_the_same_scene_starts_as_a_fresh_episode(
    client: esrp.Client, easy_scenes: list[str]
) -> None:
    # Resetting onto the scene the episode plays restarts it in place (no new scene sent); the
    # first observation and the goal must be those of a fresh episode, sensors included.
    sensors = esrp.Sensors(depth=True, segmentation=True, current_top_down=True, resolution=32)
    scenes = easy_scenes[:2]
    played = RearrangeEnv(client=client, scene=scenes, sensors=sensors)
    fresh = RearrangeEnv(client=client, scene=scenes, sensors=sensors)
    try:
        seeds = [0, 1, 2, 3, 4, 5, 6, 7]
        drawn = []
        for seed in seeds:
            observation, info = played.reset(seed=seed)
            drawn.append(info["scene_id"])
            expected, expected_info = fresh.reset(seed=seed)
            fresh.close()
            fresh = RearrangeEnv(client=client, scene=scenes, sensors=sensors)
            assert info == expected_info
            assert observation.keys() == expected.keys()
            for key in expected:
                assert np.array_equal(observation[key], expected[key]), (seed, key)
            # Move something (a fetch where one is in reach, turns and moves otherwise).
            for action in (0, 4, 2, 0, 0, 5, 3):
                played.step(action)
        # Both kinds of reset were met: onto the same scene and onto the other one.
        repeats = [a == b for a, b in zip(drawn, drawn[1:], strict=False)]
        assert any(repeats), drawn
        assert not all(repeats), drawn
    finally:
        played.close()
        fresh.close()


def test_reset_info_describes_the_scene(server: esrp.LocalServer, client: esrp.Client) -> None:
    """The reset info held the scene id alone: it now has the scene's difficulty, room type,
    movable-object count and the episode's step limit (the env's horizon, else the scene's)."""
    summaries = {s.id: s for s in client.scenes("test", page_size=1000)}
    for horizon in (0, 7):
        env = gymnasium.make(esrp.ENV_ID, address=server.address, split="test", horizon=horizon)
        try:
            for seed in (0, 1, 2):
                _, info = env.reset(seed=seed)
                assert list(info) == ["scene_id", "difficulty", "room_type", "objects", "horizon"]
                scene = summaries[info["scene_id"]]
                assert scene.difficulty is not None
                assert info["difficulty"] == scene.difficulty.value
                assert info["room_type"] == scene.room_type
                assert info["objects"] == scene.movable_objects
                with client.create_episode(scene.id) as episode:
                    scene_horizon = episode.scene.horizon  # built now, so known
                assert info["horizon"] == (horizon or scene_horizon)
                assert scene_horizon > 0
        finally:
            env.close()


def test_max_episode_steps_is_the_scenes(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    """No TimeLimit: the server truncates at the horizon, which is each scene's (so the spec has no
    max_episode_steps); the reset info gives it."""
    env = gymnasium.make(esrp.ENV_ID, address=server.address, scene=easy_scenes[0], horizon=4)
    try:
        assert env.spec is not None
        assert env.spec.max_episode_steps is None
        _, info = env.reset(seed=0)
        steps = [env.step(esrp.Action.LEFT) for _ in range(info["horizon"])]
        assert [truncated for *_, truncated, _ in steps] == [False, False, False, True]
    finally:
        env.close()


def test_is_success_on_the_last_step(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str]
) -> None:
    """The SB3 convention: info["is_success"] on the step that ends the episode, true on success."""
    from esrp.eval.evaluation import expert_trajectory

    with client.create_episode(easy_scenes[0], privileged=True) as episode:
        expert = expert_trajectory(episode.privileged_state().scene_json)
    env = RearrangeEnv(server.address, scene=easy_scenes[0])
    try:
        env.reset(seed=0)
        infos = []
        for action in expert:
            _, _, terminated, truncated, info = env.step(action)
            infos.append(info)
        assert terminated
        assert not truncated
        assert infos[-1]["is_success"] is True
        assert infos[-1]["metrics"]["success"] is True
        assert all("is_success" not in info for info in infos[:-1])
        _, reset_info = env.reset(seed=0)
        ends = [env.step(esrp.Action.LEFT)[4] for _ in range(reset_info["horizon"])]
        assert ends[-1]["is_success"] is False
        assert all("is_success" not in info for info in ends[:-1])
    finally:
        env.close()


def test_sensors_and_reward_as_mappings(server: esrp.LocalServer) -> None:
    """Env kwargs that are JSON (as an env spec stores them): mappings of the fields."""
    env = gymnasium.make(
        esrp.ENV_ID, address=server.address, split="test", sensors={"resolution": 32}, reward={"success": 5.0}
    )
    try:
        observation, _ = env.reset(seed=0)
        assert observation["ego_rgb"].shape == (32, 32, 3)
    finally:
        env.close()
    with pytest.raises(ValueError, match=r"sensors: unknown fields in \{'resolutio': 32\}"):
        gymnasium.make(esrp.ENV_ID, address=server.address, sensors={"resolutio": 32})
    with pytest.raises(ValueError, match="reward: unknown fields"):
        gymnasium.make(esrp.ENV_ID, address=server.address, reward={"bonus": 1.0})
