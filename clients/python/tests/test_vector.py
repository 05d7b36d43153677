"""The native vector env against Gymnasium's own SyncVectorEnv over N single envs: the same
observations (bit for bit), rewards, terminations, truncations and infos, in every autoreset mode."""

from __future__ import annotations

import json
from typing import Any

import gymnasium
import numpy as np
import pytest
from conftest import settled_live_episodes
from gymnasium.vector import AutoresetMode

import esrp
from esrp.envs import RearrangeVectorEnv

NUM_ENVS = 3
SMALL = esrp.Sensors(resolution=32)


def assert_same(a: Any, b: Any, path: str = "") -> None:  # noqa: ANN401
    """Deep equality of observations and infos: dicts, arrays (object arrays element-wise), scalars."""
    if isinstance(a, dict):
        assert isinstance(b, dict), path
        assert list(a) == list(b), f"{path}: {list(a)} != {list(b)}"  # the same keys in the same order
        for key in a:
            assert_same(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), path
        assert (a.dtype, a.shape) == (b.dtype, b.shape), path
        if a.dtype == object:
            for i, (x, y) in enumerate(zip(a.flat, b.flat, strict=True)):
                assert_same(x, y, f"{path}[{i}]")
        else:
            assert np.array_equal(a, b), path
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


def assert_same_returns(got: list[Any], expected: list[Any]) -> int:
    """Asserts that two envs returned the same from each call (resets and steps, in order);
    returns how many episodes the steps ended."""
    ended = 0
    for g, e in zip(got, expected, strict=True):
        assert len(g) == len(e)
        for part_g, part_e in zip(g, e, strict=True):
            assert_same(part_g, part_e)
        if len(g) == 5:
            ended += int(np.sum(g[2] | g[3]))
    return ended


def make_pair(address: str, mode: AutoresetMode, **kwargs: Any) -> tuple[Any, Any]:  # noqa: ANN401
    """The native vector env and Gymnasium's SyncVectorEnv over the same settings."""
    settings: dict[str, Any] = {"address": address, "split": "test", "difficulty": "easy", "sensors": SMALL}
    settings.update(kwargs)
    native = gymnasium.make_vec(
        esrp.ENV_ID,
        num_envs=NUM_ENVS,
        vectorization_mode="vector_entry_point",
        autoreset_mode=mode,
        **settings,
    )
    reference = gymnasium.make_vec(
        esrp.ENV_ID,
        num_envs=NUM_ENVS,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": mode},
        **settings,
    )
    return native, reference


def drive(envs: Any, steps: int, seed: int) -> list[Any]:  # noqa: ANN401
    """Resets with `seed`, steps with seeded actions, resets sub-env 0 alone after the first step
    (so the episodes end at different steps); returns everything the env returned."""
    actions = np.random.default_rng(seed).integers(0, 6, size=(steps, NUM_ENVS))
    record: list[Any] = [envs.reset(seed=seed)]
    for t in range(steps):
        record.append(envs.step(actions[t]))
        if t == 0:
            mask = np.zeros(NUM_ENVS, dtype=np.bool_)
            mask[0] = True
            record.append(envs.reset(options={"reset_mask": mask}))
    return record


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_identical_to_sync_vector_env(
    server: esrp.LocalServer, client: esrp.Client, mode: AutoresetMode
) -> None:
    before = client.server_info().live_episodes
    native, reference = make_pair(server.address, mode, horizon=3)
    try:
        assert isinstance(native.unwrapped, RearrangeVectorEnv)
        assert native.metadata["autoreset_mode"] is mode
        assert native.single_observation_space == reference.single_observation_space
        assert native.observation_space == reference.observation_space
        assert native.action_space == reference.action_space
        got, expected = drive(native, 8, seed=11), drive(reference, 8, seed=11)
        assert client.server_info().live_episodes == before + 2 * NUM_ENVS
        ended = assert_same_returns(got, expected)
        assert ended >= NUM_ENVS  # the horizon of 3 ended episodes, which were autoreset
        if mode is AutoresetMode.SAME_STEP:
            assert any("final_obs" in g[4] for g in got if len(g) == 5)
    finally:
        native.close()
        reference.close()
    assert settled_live_episodes(client, before) == before


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_identical_with_every_sensor(server: esrp.LocalServer, mode: AutoresetMode) -> None:
    """Depth (float32), segmentation (uint32) and the current top-down batch bit for bit too."""
    sensors = esrp.Sensors(depth=True, segmentation=True, current_top_down=True, resolution=16)
    native, reference = make_pair(server.address, mode, horizon=2, sensors=sensors)
    try:
        got, expected = drive(native, 5, seed=3), drive(reference, 5, seed=3)
        for g, e in zip(got, expected, strict=True):
            for part_g, part_e in zip(g, e, strict=True):
                assert_same(part_g, part_e)
        assert got[-1][0]["depth"].dtype == np.float32
        assert got[-1][0]["segmentation"].shape == (NUM_ENVS, 16, 16)
    finally:
        native.close()
        reference.close()


def test_same_step_on_success(server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str]) -> None:
    """Sub-env 0 replays the expert and terminates; SAME_STEP reports it in final_obs/final_info."""
    scene = easy_scenes[3]
    with client.create_episode(scene, privileged=True) as episode:
        expert = json.loads(episode.privileged_state().scene_json)["expert_trajectory"]
    native, reference = make_pair(server.address, AutoresetMode.SAME_STEP, scene=scene)
    try:
        for envs in (native, reference):
            envs.reset(seed=0)
        for code in expert:
            actions = np.array([code, esrp.Action.LEFT, esrp.Action.RIGHT])
            got, expected = native.step(actions), reference.step(actions)
            for part_g, part_e in zip(got, expected, strict=True):
                assert_same(part_g, part_e)
        observations, rewards, terminated, truncated, infos = got
        assert terminated.tolist() == [True, False, False]
        assert rewards[0] >= 10
        assert infos["_final_obs"].tolist() == [True, False, False]
        assert infos["final_info"]["metrics"]["success"][0]
        assert infos["final_info"]["_metrics"].tolist() == [True, False, False]
        assert infos["scene_id"][0] == scene
        # The observation returned is the reset's; the last step's is in final_obs.
        assert not np.array_equal(infos["final_obs"][0]["ego_rgb"], observations["ego_rgb"][0])
    finally:
        native.close()
        reference.close()


def test_next_step_autoreset(server: esrp.LocalServer) -> None:
    envs = RearrangeVectorEnv(2, server.address, split="test", sensors=SMALL, horizon=2)
    try:
        first, infos = envs.reset(seed=3)
        reset_keys = {"scene_id", "difficulty", "room_type", "objects", "horizon"}
        assert set(infos) == reset_keys | {f"_{key}" for key in reset_keys}
        envs.step(np.array([2, 2]))
        _, rewards, terminated, truncated, infos = envs.step(np.array([2, 2]))
        assert truncated.tolist() == [True, True]
        assert infos["metrics"]["steps"].tolist() == [2, 2]
        assert infos["is_success"].tolist() == [False, False]
        # The next step resets instead of stepping: reward 0, not ended, the reset's info.
        observations, rewards, terminated, truncated, infos = envs.step(np.array([0, 0]))
        assert rewards.tolist() == [0.0, 0.0]
        assert not terminated.any()
        assert not truncated.any()
        assert set(infos) == reset_keys | {f"_{key}" for key in reset_keys}
        _, step_infos = envs.step(np.array([0, 0]))[::4]
        assert step_infos["step_index"].tolist() == [1, 1]
    finally:
        envs.close()


def test_scene_per_env(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    scenes = [easy_scenes[1], easy_scenes[0]]
    envs = RearrangeVectorEnv(2, server.address, scene=scenes, scene_per_env=True, sensors=SMALL, horizon=2)
    try:
        for seed in range(3):
            _, infos = envs.reset(seed=seed)
            assert infos["scene_id"].tolist() == scenes
        first = envs.reset(seed=5)[0]
        envs.step(np.array([0, 2]))
        assert envs.step(np.array([2, 0]))[3].tolist() == [True, True]
        # The autoreset restarts each episode on its own scene: the first observation again.
        observations, _, _, _, infos = envs.step(np.array([0, 0]))
        assert infos["scene_id"].tolist() == scenes
        assert_same(observations, first)
        # options["scene"] still names another.
        mask = np.array([True, False])
        _, infos = envs.reset(options={"reset_mask": mask, "scene": scenes[1]})
        assert infos["scene_id"].tolist() == [scenes[1], None]
    finally:
        envs.close()
    for bad in (None, scenes[0], [*scenes, easy_scenes[2]]):
        with pytest.raises(ValueError, match="one scene id per sub-env"):
            RearrangeVectorEnv(2, server.address, scene=bad, scene_per_env=True)


def test_a_reset_may_name_each_sub_envs_scene(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    envs = RearrangeVectorEnv(3, server.address, split="test", sensors=SMALL)
    drawn = RearrangeVectorEnv(3, server.address, split="test", sensors=SMALL)
    try:
        named = [easy_scenes[4], None, easy_scenes[2]]
        _, infos = envs.reset(seed=11, options={"scene": named})
        _, own = drawn.reset(seed=11)
        assert infos["scene_id"].tolist() == [easy_scenes[4], own["scene_id"][1], easy_scenes[2]]
        # Each generator advanced as a drawn scene's would: the next draws are the same.
        assert envs.reset()[1]["scene_id"].tolist() == drawn.reset()[1]["scene_id"].tolist()
        # A masked reset reads the entries of the sub-envs it resets.
        mask = np.array([True, False, False])
        _, infos = envs.reset(options={"reset_mask": mask, "scene": [easy_scenes[5], easy_scenes[6], None]})
        assert infos["_scene_id"].tolist() == [True, False, False]
        assert infos["scene_id"][0] == easy_scenes[5]
        for bad in ([easy_scenes[0]] * 2, [easy_scenes[0], "", None], 7):
            with pytest.raises(ValueError, match=r"options\['scene'\]"):
                envs.reset(options={"scene": bad})
    finally:
        envs.close()
        drawn.close()


def test_a_failed_reset_leaves_nothing_for_the_next(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str]
) -> None:
    """Whichever creation or restart fails, the next reset answers as a fresh env's would, and the
    env holds one episode per sub-env."""
    fresh = RearrangeVectorEnv(3, server.address, split="test", sensors=SMALL)
    try:
        expected_observations, expected = fresh.reset(seed=0)
    finally:
        fresh.close()
    before = client.server_info().live_episodes
    envs = RearrangeVectorEnv(3, server.address, split="test", sensors=SMALL)
    try:
        for bad in (["esrp-bench-v2/no-such", None, None], "esrp-bench-v2/no-such"):
            with pytest.raises(esrp.SceneNotFound):
                envs.reset(seed=5, options={"scene": bad})
            observations, infos = envs.reset(seed=0)
            assert infos["scene_id"].tolist() == expected["scene_id"].tolist()
            assert_same(observations, expected_observations)
            assert settled_live_episodes(client, before + 3) == before + 3
        # A restart that fails (every sub-env live now) moves nothing either.
        with pytest.raises(esrp.SceneNotFound):
            envs.reset(options={"scene": [easy_scenes[0], "esrp-bench-v2/no-such", None]})
        observations, infos = envs.reset(seed=0)
        assert infos["scene_id"].tolist() == expected["scene_id"].tolist()
        assert_same(observations, expected_observations)
    finally:
        envs.close()
    assert settled_live_episodes(client, before) == before


def test_disabled_mode_and_reset_mask(server: esrp.LocalServer) -> None:
    envs = RearrangeVectorEnv(
        3, server.address, split="test", sensors=SMALL, horizon=1, autoreset_mode=AutoresetMode.DISABLED
    )
    try:
        assert envs.metadata["autoreset_mode"] is AutoresetMode.DISABLED
        start, _ = envs.reset(seed=[7, 8, 9])
        ended = envs.step(np.array([2, 3, 2]))
        assert ended[3].tolist() == [True, True, True]
        with pytest.raises(esrp.EpisodeEnded, match="reset_mask"):
            envs.step(np.array([0, 0, 0]))
        mask = np.array([True, False, True])
        observations, infos = envs.reset(seed=[7, None, 9], options={"reset_mask": mask})
        assert infos["_scene_id"].tolist() == [True, False, True]
        # Reset sub-envs start over (the same seeds: the same scenes); the other keeps its last
        # observation.
        assert np.array_equal(observations["ego_rgb"][0], start["ego_rgb"][0])
        assert np.array_equal(observations["ego_rgb"][1], ended[0]["ego_rgb"][1])
        with pytest.raises(esrp.EpisodeEnded, match=r"\[1\]"):
            envs.step(np.array([0, 0, 0]))
        for bad, error in [
            ([True, False, True], TypeError),
            (np.array([True, False]), ValueError),
            (np.array([0, 1, 0]), TypeError),
            (np.zeros(3, dtype=np.bool_), ValueError),
        ]:
            with pytest.raises(error):
                envs.reset(options={"reset_mask": bad})
    finally:
        envs.close()


def test_observations_are_fresh_arrays(server: esrp.LocalServer) -> None:
    envs = RearrangeVectorEnv(2, server.address, split="test", sensors=SMALL)
    try:
        first, _ = envs.reset(seed=0)
        second = envs.step(np.array([2, 2]))[0]
        for key in first:
            assert not np.shares_memory(first[key], second[key])
        assert second["ego_rgb"].shape == (2, 32, 32, 3)
        assert second["grasping"].dtype == np.int64
        frames = envs.render()
        assert frames is None
    finally:
        envs.close()


def test_close_frees_every_episode(server: esrp.LocalServer, client: esrp.Client) -> None:
    before = client.server_info().live_episodes
    envs = gymnasium.make_vec(
        esrp.ENV_ID,
        num_envs=4,
        vectorization_mode="vector_entry_point",
        address=server.address,
        split="test",
        sensors=SMALL,
        render_mode="rgb_array",
    )
    envs.reset(seed=1)
    envs.step(np.array([0, 1, 2, 3]))
    frames = envs.render()
    assert isinstance(frames, tuple)
    assert len(frames) == 4
    assert all(isinstance(frame, np.ndarray) and frame.shape == (32, 64, 3) for frame in frames)
    assert client.server_info().live_episodes == before + 4
    envs.close()
    # Closed on the stream, waiting for the answers: no delay.
    assert client.server_info().live_episodes == before
    envs.close()


def test_bad_actions_move_nothing(server: esrp.LocalServer) -> None:
    envs = RearrangeVectorEnv(2, server.address, split="test", sensors=SMALL)
    try:
        with pytest.raises(gymnasium.error.ResetNeeded):
            envs.step(np.array([0, 0]))
        envs.reset(seed=0)
        with pytest.raises(esrp.InvalidRequest):
            envs.step(np.array([0, 6]))
        with pytest.raises(ValueError, match="shape"):
            envs.step(np.array([0, 0, 0]))
        infos = envs.step(np.array([0, 0]))[4]
        assert infos["step_index"].tolist() == [1, 1]
    finally:
        envs.close()


def test_reset_infos_and_is_success(server: esrp.LocalServer, client: esrp.Client) -> None:
    """As the single env's: the reset infos give each scene's difficulty, room type, object count and
    horizon; the step that ends an episode gives is_success (in final_info with SAME_STEP)."""
    summaries = {s.id: s for s in client.scenes("test", "easy", page_size=1000)}
    for mode in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
        native, reference = make_pair(server.address, mode, horizon=2)
        reference.close()
        try:
            _, infos = native.reset(seed=4)
            for key in ("scene_id", "difficulty", "room_type", "objects", "horizon"):
                assert infos[f"_{key}"].all(), key
            assert infos["objects"].dtype == np.int64
            for i in range(NUM_ENVS):
                scene = summaries[infos["scene_id"][i]]
                assert infos["difficulty"][i] == "easy"
                assert infos["room_type"][i] == scene.room_type
                assert infos["objects"][i] == scene.movable_objects
                assert infos["horizon"][i] == 2
            native.step(np.full(NUM_ENVS, 2))
            _, _, _, truncated, infos = native.step(np.full(NUM_ENVS, 2))
            assert truncated.all()
            ended = infos["final_info"] if mode is AutoresetMode.SAME_STEP else infos
            assert ended["_is_success"].all()
            assert not ended["is_success"].any()
            assert ended["is_success"].dtype == np.bool_
            if mode is AutoresetMode.NEXT_STEP:
                _, _, _, _, infos = native.step(np.full(NUM_ENVS, 2))  # the autoresets
                assert infos["_horizon"].all()
                assert "is_success" not in infos
        finally:
            native.close()


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_a_step_and_its_autoresets_are_one_message(
    server: esrp.LocalServer, easy_scenes: list[str], monkeypatch: pytest.MonkeyPatch, mode: AutoresetMode
) -> None:
    """Each vector step sends one StepBatch holding its steps and its autoresets (SAME_STEP: a
    second one for the resets of the episodes the step ended), and nothing on the stream."""
    from esrp._client import EpisodeStream
    from esrp._transport import Calls

    sent: list[tuple[str, int, int]] = []
    call = Calls.__call__

    def counted(self: Calls, method: str, request: Any, **options: Any) -> Any:  # noqa: ANN401
        sent.append((method, len(getattr(request, "steps", ())), len(getattr(request, "resets", ()))))
        return call(self, method, request, **options)

    monkeypatch.setattr(Calls, "__call__", counted)
    on_stream: list[str] = []
    send = EpisodeStream._send  # noqa: SLF001

    def streamed(self: EpisodeStream, kind: Any, episode_id: str, **body: Any) -> int:  # noqa: ANN401
        on_stream.append(kind.value)
        return send(self, kind, episode_id, **body)

    monkeypatch.setattr(EpisodeStream, "_send", streamed)
    envs = RearrangeVectorEnv(
        NUM_ENVS, address=server.address, scene=easy_scenes[:3], sensors=SMALL, horizon=2, autoreset_mode=mode
    )
    try:
        envs.reset(seed=5)
        envs.step(np.array([1, 1, 1]))
        # Sub-env 0 restarts alone (a StepBatch with one reset): it now ends a step after the others.
        sent.clear()
        envs.reset(options={"reset_mask": np.array([True, False, False])})
        assert sent == [("StepBatch", 0, 1)]
        sent.clear()
        _, _, _, truncated, _ = envs.step(np.array([1, 1, 1]))
        assert truncated.tolist() == [False, True, True]
        if mode == AutoresetMode.SAME_STEP:
            assert sent == [("StepBatch", 3, 0), ("StepBatch", 0, 2)]
        else:
            assert sent == [("StepBatch", 3, 0)]
            sent.clear()
            _, _, _, truncated, infos = envs.step(np.array([1, 1, 1]))
            assert sent == [("StepBatch", 1, 2)], "sub-env 0's step and the others' autoresets"
            assert truncated.tolist() == [True, False, False]
            assert infos["_scene_id"].tolist() == [False, True, True]
    finally:
        envs.close()
    # The stream created the three episodes and closed them, and carried nothing else.
    assert on_stream == ["create"] * 3 + ["close"] * 3


def test_np_random_is_each_sub_envs_as_in_sync_vector_env(server: esrp.LocalServer) -> None:
    """`np_random_seed` and `np_random` are the sub-envs' seeds and generators, as `SyncVectorEnv`
    gives them: what a seeded reset set, kept by an unseeded one, the generators in step."""
    native, reference = make_pair(server.address, AutoresetMode.NEXT_STEP)
    try:
        for seed, first in ((5, 5), ([1, None, 3], 1), (None, 1)):
            native.reset(seed=seed)
            reference.reset(seed=seed)
            assert native.np_random_seed == reference.np_random_seed
            assert native.np_random_seed[0] == first
            states = [rng.bit_generator.state for rng in native.np_random]
            assert states == [rng.bit_generator.state for rng in reference.np_random]
    finally:
        native.close()
        reference.close()
    fresh = RearrangeVectorEnv(2, server.address, split="test", sensors=SMALL)
    try:
        # Never seeded: each sub-env draws a seed of its own, once, and its generator is the one
        # its resets then use.
        seeds = fresh.np_random_seed
        assert len(seeds) == 2
        assert all(isinstance(seed, int) for seed in seeds)
        assert fresh.np_random_seed == seeds
        generators = fresh.np_random
        fresh.reset()
        assert fresh.np_random_seed == seeds
        assert all(a is b for a, b in zip(fresh.np_random, generators, strict=True))
    finally:
        fresh.close()


def test_a_closed_env_refuses_resets_and_steps(server: esrp.LocalServer, client: esrp.Client) -> None:
    """As Gymnasium's AsyncVectorEnv: after `close()`, `reset` and `step` raise
    `ClosedEnvironmentError` (a reset made episodes that no later `close()` would free)."""
    before = client.server_info().live_episodes
    envs = RearrangeVectorEnv(2, client=client, split="test", sensors=SMALL)
    envs.reset(seed=0)
    envs.close()
    with pytest.raises(gymnasium.error.ClosedEnvironmentError):
        envs.reset(seed=0)
    with pytest.raises(gymnasium.error.ClosedEnvironmentError):
        envs.step(np.array([0, 0]))
    envs.close()
    assert settled_live_episodes(client, before) == before


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_max_episode_steps_as_sync_vector_envs_time_limit(
    server: esrp.LocalServer, mode: AutoresetMode
) -> None:
    """`make_vec(..., max_episode_steps=N)` hands a vector entry point `max_episode_steps`: the native
    env truncates as `SyncVectorEnv` over `make(..., max_episode_steps=N)` (a `TimeLimit` each)
    does, before the server's horizon or after it."""
    for limit, horizon in ((2, 3), (4, 3)):
        native, reference = make_pair(server.address, mode, horizon=horizon, max_episode_steps=limit)
        try:
            got, expected = drive(native, 9, seed=2), drive(reference, 9, seed=2)
            assert assert_same_returns(got, expected) >= NUM_ENVS
            truncated_at = [t for t, g in enumerate(got) if len(g) == 5 and g[3][1]]
            assert truncated_at[0] == 1 + min(limit, horizon)  # sub-env 1 was never reset alone
        finally:
            native.close()
            reference.close()
    with pytest.raises(ValueError, match="max_episode_steps"):
        RearrangeVectorEnv(2, server.address, split="test", max_episode_steps=0)


def test_identical_to_sync_vector_env_when_disabled(server: esrp.LocalServer) -> None:
    """DISABLED: the ended sub-envs, reset by `reset_mask` (with a seed for some), answer as
    `SyncVectorEnv`'s do; so do the steps between."""
    native, reference = make_pair(server.address, AutoresetMode.DISABLED, horizon=2)
    try:
        actions = np.random.default_rng(6).integers(0, 6, size=(10, NUM_ENVS))
        got, expected = [native.reset(seed=6)], [reference.reset(seed=6)]
        resets = 0
        for t, action in enumerate(actions):
            got.append(native.step(action))
            expected.append(reference.step(action))
            ended = got[-1][2] | got[-1][3]
            if t == 0:
                ended[0] = True  # sub-env 0 restarts early: the episodes end at different steps
            if ended.any():
                resets += 1
                seed = [None, 40 + t, None]
                got.append(native.reset(seed=seed, options={"reset_mask": ended.copy()}))
                expected.append(reference.reset(seed=seed, options={"reset_mask": ended.copy()}))
        assert assert_same_returns(got, expected) >= NUM_ENVS
        assert resets >= 4
    finally:
        native.close()
        reference.close()
