"""Stable-Baselines3 through `esrp.integrations.sb3`: SB3's own env checker on the single env, the
adapter step for step against SB3's DummyVecEnv over single envs (observations bit for bit,
rewards, dones, infos, terminal observations, reset infos), a short `learn()` of SB3's PPO, and
clear errors for what the adapter cannot do."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
from conftest import load_tool, settled_live_episodes

import esrp

pytest.importorskip("stable_baselines3", reason="esrp[sb3] is not installed")

from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.env_checker import check_env  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecMonitor  # noqa: E402

from esrp.integrations.sb3 import EsrpVecEnv, make_vec_env, unbatch_infos  # noqa: E402

NUM_ENVS = 3
SETTINGS: dict[str, Any] = {"split": "test", "difficulty": "easy", "sensors": esrp.Sensors(resolution=32)}


def assert_same(a: Any, b: Any, path: str = "") -> None:  # noqa: ANN401
    """Deep equality: dicts (the same keys, in any order), arrays (dtype, shape, values), scalars."""
    if isinstance(a, dict):
        assert isinstance(b, dict), path
        assert sorted(a) == sorted(b), f"{path}: {sorted(a)} != {sorted(b)}"
        for key in a:
            assert_same(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), path
        assert (a.dtype, a.shape) == (b.dtype, b.shape), path
        assert np.array_equal(a, b), path
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


def drive(env: VecEnv, steps: int, seed: int) -> list[Any]:
    """Seeds, resets and steps `env` with seeded actions; returns everything it gave, with the
    reset infos after each call."""
    actions = np.random.default_rng(seed).integers(0, 6, size=(steps, NUM_ENVS))
    env.seed(seed)
    record: list[Any] = [env.reset(), [dict(info) for info in env.reset_infos]]
    for t in range(steps):
        record.append(env.step(actions[t]))
        record.append([dict(info) for info in env.reset_infos])
    return record


def test_sb3_check_env_passes_on_the_single_env(server: esrp.LocalServer) -> None:
    """At the default 128 px (SB3's CNN policies need views of 36 px or more)."""
    env = gymnasium.make(esrp.ENV_ID, address=server.address, split="test", difficulty="easy")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # SB3's checker warns about what its policies mishandle
            check_env(env.unwrapped)
    finally:
        env.close()


def test_identical_to_dummy_vec_env(server: esrp.LocalServer, client: esrp.Client) -> None:
    before = client.server_info().live_episodes
    settings = {**SETTINGS, "horizon": 3}
    native = make_vec_env(NUM_ENVS, server.address, monitor=False, **settings)
    reference = DummyVecEnv(
        [lambda: gymnasium.make(esrp.ENV_ID, address=server.address, **settings) for _ in range(NUM_ENVS)]
    )
    try:
        assert isinstance(native, EsrpVecEnv)
        assert native.observation_space == reference.observation_space
        assert native.action_space == reference.action_space
        got, expected = drive(native, 8, seed=5), drive(reference, 8, seed=5)
        assert client.server_info().live_episodes == before + 2 * NUM_ENVS
        ended = 0
        for g, e in zip(got, expected, strict=True):
            if isinstance(g, tuple):  # a step: observations, rewards, dones, infos
                obs_g, rewards_g, dones_g, infos_g = g
                obs_e, rewards_e, dones_e, infos_e = e
                assert_same(obs_g, obs_e)
                assert rewards_g.dtype == rewards_e.dtype == np.float32
                assert np.array_equal(rewards_g, rewards_e)
                assert np.array_equal(dones_g, dones_e)
                assert_same(dict(enumerate(infos_g)), dict(enumerate(infos_e)))
                ended += int(dones_g.sum())
                for i in np.flatnonzero(dones_g):
                    assert "terminal_observation" in infos_g[i]
                    assert "is_success" in infos_g[i]
            elif isinstance(g, list):
                assert_same(dict(enumerate(g)), dict(enumerate(e)))
            else:
                assert_same(g, e)
        assert ended >= NUM_ENVS  # the horizon of 3 ended episodes, which were reset in the step
    finally:
        native.close()
        reference.close()
    assert settled_live_episodes(client, before) == before


def test_ppo_learns_through_the_adapter(server: esrp.LocalServer) -> None:
    """A short `learn()` with SB3's PPO and MultiInputPolicy (NatureCNN needs views of 36 px or
    more): its rollouts end episodes, whose returns and successes reach SB3's buffers."""
    env = make_vec_env(
        2, server.address, split="train", difficulty="easy", horizon=8, sensors=esrp.Sensors(resolution=48)
    )
    try:
        assert isinstance(env, VecMonitor)
        assert isinstance(env.venv, EsrpVecEnv)
        model = PPO("MultiInputPolicy", env, n_steps=16, batch_size=16, n_epochs=1, seed=0, device="cpu")
        model.learn(total_timesteps=64)
        assert model.num_timesteps == 64
        assert model.ep_info_buffer is not None
        assert model.ep_success_buffer is not None
        assert len(model.ep_info_buffer) == 64 // 8  # 32 steps per sub-env, episodes of 8
        assert all(info["l"] == 8 for info in model.ep_info_buffer)  # the horizon ended them
        assert len(model.ep_success_buffer) == len(model.ep_info_buffer)
        observations = env.reset()
        assert isinstance(observations, dict)
        action, _ = model.predict(observations, deterministic=True)
        assert action.shape == (2,)
    finally:
        env.close()


def test_the_example_trains_saves_and_plays(
    server: esrp.LocalServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    example = load_tool("sb3_ppo", folder="examples")
    saved = tmp_path / "model.zip"
    argv = ["--timesteps", "64", "--envs", "2", "--n-steps", "16", "--resolution", "48"]
    argv += ["--test-episodes", "2", "--save", str(saved), "--server", server.address]
    assert example.main(argv) == 0
    assert PPO.load(saved, device="cpu").num_timesteps == 64
    assert "easy test episodes:" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--resolution", "32"], "--resolution must be 36 or more (SB3's NatureCNN), not 32"),
        (["--envs", "0"], "--envs must be at least 1, not 0"),
        (["--test-episodes", "0"], "--test-episodes must be at least 1, not 0"),
        (["--n-steps", "0"], "--n-steps must be at least 1, not 0"),
        (["--envs", "1", "--n-steps", "1"], "--n-steps x --envs must be 2 or more (PPO's minibatch), not 1"),
        (["--timesteps", "-5"], "--timesteps must be 0 or more, not -5"),
    ],
)
def test_the_example_refuses_bad_arguments_before_starting_anything(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], said: str
) -> None:
    """Refused by its parser (a usage line, status 2), before a server or a model is made (the
    server given cannot be reached: it is not tried)."""
    example = load_tool("sb3_ppo", folder="examples")
    with pytest.raises(SystemExit) as exited:
        example.main([*argv, "--server", "127.0.0.1:1", "--save", str(tmp_path / "model.zip")])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert said in err
    assert "Traceback" not in err
    assert not (tmp_path / "model.zip").exists()


def test_the_example_says_when_the_server_is_not_there(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A server that cannot be reached (or is lost mid-run) ends the example with a line that
    names the error, status 1, no traceback."""
    example = load_tool("sb3_ppo", folder="examples")
    argv = ["--timesteps", "64", "--envs", "2", "--n-steps", "16", "--resolution", "48"]
    assert example.main([*argv, "--server", "127.0.0.1:1", "--save", str(tmp_path / "model.zip")]) == 1
    err = capsys.readouterr().err
    assert ": ServerUnavailable: UNAVAILABLE" in err  # after the program's name
    assert "Traceback" not in err


def test_per_env_reset_options_may_name_each_sub_envs_scene(
    server: esrp.LocalServer, easy_scenes: list[str]
) -> None:
    env = make_vec_env(2, server.address, monitor=False, **SETTINGS)
    try:
        first, second = easy_scenes[3], easy_scenes[7]
        env.set_options([{"scene": first}, {"scene": second}])
        env.reset()
        assert [info["scene_id"] for info in env.reset_infos] == [first, second]
        env.set_options([{"scene": second}, {}])  # the second sub-env draws its own
        env.reset()
        assert env.reset_infos[0]["scene_id"] == second
        env.set_options({"scene": first})  # one dict: for every sub-env
        env.reset()
        assert [info["scene_id"] for info in env.reset_infos] == [first, first]
    finally:
        env.close()


def test_clear_errors(server: esrp.LocalServer) -> None:
    with pytest.raises(ValueError, match="autoreset_mode"):
        make_vec_env(2, server.address, autoreset_mode="next-step", **SETTINGS)
    env = make_vec_env(2, server.address, monitor=False, **SETTINGS)
    try:
        env.set_options([{"scene": "a", "difficulty": "easy"}, {"scene": "b", "difficulty": "hard"}])
        with pytest.raises(ValueError, match="differ in more than `scene`"):
            env.reset()
        env.set_options([{"scene": "a"}])  # a list, but not one dict per sub-env
        with pytest.raises(ValueError, match="given 1 options dicts for 2 sub-envs"):
            env.reset()
        with pytest.raises(AttributeError, match="cannot set"):
            env.set_attr("horizon", 5)
        assert env.get_attr("num_envs", [0, 1]) == [2, 2]
        assert env.env_is_wrapped(gymnasium.Wrapper) == [False, False]
        # Indices as DummyVecEnv takes them: negative ones count from the end, others out of range
        # are refused (not answered as if the sub-env existed), and no index calls nothing.
        assert env.get_attr("num_envs", -1) == [2]
        with pytest.raises(IndexError, match="sub-env index 2 is out of range"):
            env.get_attr("num_envs", [0, 2])
        with pytest.raises(IndexError, match="sub-env index -3 is out of range"):
            env.env_method("render", indices=-3)
        with pytest.raises(IndexError, match="sub-env index 5 is out of range"):
            env.env_is_wrapped(gymnasium.Wrapper, indices=[5])
        assert env.env_method("close", indices=[]) == []
        assert isinstance(env, EsrpVecEnv)
        assert not env.venv.closed  # `close` was not called
    finally:
        env.close()


def test_render_shows_each_sub_envs_view_beside_its_goal(server: esrp.LocalServer) -> None:
    """With `render_mode="rgb_array"`, `get_images()` gives each sub-env's frame as the single
    env's `render()` does (the view, then the goal image), which SB3's `render()` tiles."""
    env = make_vec_env(2, server.address, monitor=False, render_mode="rgb_array", **SETTINGS)
    try:
        assert env.render_mode == "rgb_array"
        observations = env.reset()
        assert isinstance(observations, dict)
        frames = env.get_images()
        for i, image in enumerate(frames):
            assert image is not None
            expected = np.concatenate([observations["ego_rgb"][i], observations["goal_rgb"][i]], axis=1)
            assert np.array_equal(image, expected)
        tiled = env.render()
        assert tiled is not None
        assert tiled.shape == (2 * 32, 2 * 32, 3)  # SB3 tiles 2 frames of 32 x 64 one above the other
    finally:
        env.close()


def test_unbatch_infos_follows_the_masks() -> None:
    infos = {
        "a": np.array([1, 0, 3]),
        "_a": np.array([True, False, True]),
        "m": {"x": np.array([0.5, 0.0, 0.0]), "_x": np.array([True, False, False])},
        "_m": np.array([True, False, False]),
    }
    assert unbatch_infos(infos, 3) == [{"a": 1, "m": {"x": 0.5}}, {}, {"a": 3}]
    with pytest.raises(ValueError, match="no mask"):
        unbatch_infos({"a": np.array([1])}, 1)


def test_spread_over_two_servers(server: esrp.LocalServer) -> None:
    """A list of addresses reaches the vector env: SB3 sees one VecEnv over both servers."""
    with esrp.LocalServer(unix_socket=True) as other:
        env = make_vec_env(4, [server.address, other.address], monitor=False, **SETTINGS)
        try:
            observations = env.reset()
            assert isinstance(observations, dict)
            assert observations["ego_rgb"].shape[0] == 4
            env.step(np.array([0, 1, 2, 3]))
            assert isinstance(env, EsrpVecEnv)
            assert env.venv.server_of_env == (0, 0, 1, 1)
        finally:
            env.close()
