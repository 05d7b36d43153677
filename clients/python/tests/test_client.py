"""Every call of the sync client against the real server, and the shape of what comes back."""

from __future__ import annotations

import json
from typing import Any, cast

import numpy as np
import numpy.typing as npt
import pytest

import esrp


def buffer_of(array: npt.NDArray[np.generic]) -> object:
    """The object at the end of an array's `.base` chain."""
    base: object = array
    while isinstance(base, np.ndarray):
        base = base.base
    return base


def test_server_info(client: esrp.Client) -> None:
    info = client.server_info()
    assert info.version
    assert info.dataset == "esrp-bench-v2"
    assert info.renderer_backend in ("gl", "vulkan")
    assert info.renderer_rasterizer == "pipeline"
    assert info.limits.max_batch == 1024
    assert info.limits.max_message_bytes == 64 << 20
    assert info.limits.max_resolution >= 128
    assert info.live_episodes >= 0


def test_the_challenge_splits_the_agent_label_and_the_caller_convert_both_ways() -> None:
    """The esrp.v1 fields of the challenge (splits 3 and 4, CreateEpisode's `agent`, ServerInfo's
    caller, role, challenge and recording) as the client sends and reads them."""
    from esrp import _convert
    from esrp.v1 import esrp_pb2 as pb

    assert _convert.split_code("challenge") == pb.SPLIT_CHALLENGE
    assert _convert.split_code(esrp.Split.MINIVAL) == pb.SPLIT_MINIVAL
    with pytest.raises(esrp.InvalidRequest, match="'train', 'test', 'challenge', 'minival'"):
        _convert.split_code("validation")
    listed = _convert.scene_summary(pb.SceneSummary(id="challenge/00012", split=pb.SPLIT_CHALLENGE))
    assert listed.split is esrp.Split.CHALLENGE

    def create(agent: str | None) -> pb.CreateEpisodeRequest:
        return _convert.create_request(
            "minival/00003",
            scene_json=None,
            split=None,
            seed=0,
            horizon=0,
            reward=None,
            sensors=None,
            privileged=False,
            agent=agent,
        )

    assert (create("my-vlm v3").scene_id, create("my-vlm v3").agent) == ("minival/00003", "my-vlm v3")
    assert create(None).agent == ""  # the server's "unnamed"
    answer = pb.ServerInfoResponse(
        version="0.2.0", dataset="d", caller="team-a", role="agent", challenge=True, recording="challenge"
    )
    info = _convert.server_info(answer)
    assert (info.caller, info.role, info.challenge, info.recording) == ("team-a", "agent", True, "challenge")


def test_an_agent_label_is_sent_with_a_create(client: esrp.Client, easy_scenes: list[str]) -> None:
    # A server without records keeps the label nowhere; the episode is the same.
    with client.create_episode(easy_scenes[0], agent="my-vlm v3", horizon=3) as episode:
        assert episode.scene.id == easy_scenes[0]
        assert episode.step(esrp.Action.LEFT).info.accepted


def test_describe_dataset(client: esrp.Client) -> None:
    dataset = client.describe_dataset()
    assert dataset.name == "esrp-bench-v2"
    assert dataset.scenes == 5495
    assert dataset.by_split == {"train": 4951, "test": 544}
    assert sum(dataset.by_difficulty.values()) == dataset.scenes
    assert sum(dataset.by_room_type.values()) == dataset.scenes
    assert dataset.source.startswith("built-in")
    # The counts come sorted by name, whatever order the message's maps had on the wire or in
    # upb's hash table (seeded per process): the same dataset, the same values, printed alike.
    for counts in (dataset.by_split, dataset.by_difficulty, dataset.by_room_type):
        assert list(counts) == sorted(counts)
    assert len(dataset.by_room_type) > 10


def test_scenes_are_paged_and_filtered(client: esrp.Client) -> None:
    dataset = client.describe_dataset()
    # 544 test scenes in pages of 100: six requests, read lazily.
    test = list(client.scenes(esrp.Split.TEST, page_size=100))
    assert len(test) == dataset.by_split["test"]
    assert len({scene.id for scene in test}) == len(test)
    assert all(scene.split is esrp.Split.TEST for scene in test)
    hard = list(client.scenes("test", "hard", page_size=1000))
    assert hard
    assert all(scene.difficulty is esrp.Difficulty.HARD and 4 <= scene.movable_objects <= 6 for scene in hard)
    assert [s.id for s in hard] == [s.id for s in test if s.difficulty is esrp.Difficulty.HARD]
    first = next(iter(client.scenes(page_size=1)))
    assert first.id == "esrp-bench-v2/00000"


def test_episode_lifecycle(client: esrp.Client, easy_scenes: list[str]) -> None:
    before = client.server_info().live_episodes
    episode = client.create_episode(easy_scenes[0], horizon=7)
    assert len(episode.id) == 32
    assert episode.scene.id == easy_scenes[0]
    assert episode.scene.horizon == 7 or episode.scene.horizon > 0
    assert episode.spec.actions == tuple(action.api_name for action in esrp.Action)
    assert [a.name for a in episode.spec.arrays][:3] == ["ego_rgb", "goal_rgb", "grasping"]
    first = episode.observation
    assert first is not None
    assert first.goal_rgb is not None
    assert client.server_info().live_episodes == before + 1

    result = episode.step(esrp.Action.LEFT)
    assert result.info.step_index == 1
    assert result.info.accepted
    assert result.observation.goal_rgb is None
    assert not result.ended
    assert result.metrics is None
    assert result.reward == pytest.approx(sum(vars(result.info.reward_terms).values()))
    with_goal = episode.step(esrp.Action.RIGHT, include_goal=True)
    assert with_goal.observation.goal_rgb is not None
    assert np.array_equal(with_goal.observation.goal_rgb, first.goal_rgb)
    # Turning left then right comes back to the start: the same view.
    assert np.array_equal(with_goal.observation.ego_rgb, first.ego_rgb)

    goal = episode.goal()
    assert np.array_equal(goal.image, first.goal_rgb)
    assert goal.frame is not None
    assert goal.frame.resolution == 128
    assert goal.frame.metres_per_pixel > 0

    progress = episode.metrics()
    assert not progress.ended
    assert progress.metrics.steps == 2
    assert progress.metrics.movable_objects == 1

    again = episode.reset()
    assert np.array_equal(again.ego_rgb, first.ego_rgb)
    assert episode.metrics().metrics.steps == 0
    moved = episode.reset(easy_scenes[1])
    assert episode.scene.id == easy_scenes[1]
    assert moved.goal_rgb is not None
    assert not np.array_equal(moved.goal_rgb, first.goal_rgb)

    final = episode.close()
    assert final.steps == 0
    assert episode.closed
    assert client.server_info().live_episodes == before


def test_episode_context_manager_closes(client: esrp.Client) -> None:
    before = client.server_info().live_episodes
    with client.create_episode(split="test", seed=3) as episode:
        assert client.server_info().live_episodes == before + 1
        episode.step(esrp.Action.FETCH)
    assert client.server_info().live_episodes == before
    # A handle closed inside the block is not closed twice.
    with client.create_episode(split="test", seed=3) as episode:
        episode.close()
    assert client.server_info().live_episodes == before


def test_seeded_create_picks_the_split_scene(client: esrp.Client) -> None:
    test = [scene.id for scene in client.scenes("test", page_size=1000)]
    with client.create_episode(split="test", seed=len(test) + 5) as episode:
        assert episode.scene.id == test[5]


def test_observation_arrays_are_read_only_views(client: esrp.Client, easy_scenes: list[str]) -> None:
    sensors = esrp.Sensors(depth=True, segmentation=True, current_top_down=True, resolution=64)
    with client.create_episode(easy_scenes[0], sensors=sensors) as episode:
        arrays = [spec.name for spec in episode.spec.arrays]
        assert arrays == [
            "ego_rgb",
            "goal_rgb",
            "grasping",
            "ego_depth",
            "ego_segmentation",
            "current_top_down",
        ]
        for observation in (episode.observation, episode.step(esrp.Action.FORWARD).observation):
            assert observation is not None
            assert observation.ego_rgb.shape == (64, 64, 3)
            assert observation.ego_rgb.dtype == np.uint8
            assert observation.depth is not None
            assert observation.depth.shape == (64, 64)
            assert observation.depth.dtype == np.float32
            assert observation.segmentation is not None
            assert observation.segmentation.shape == (64, 64)
            assert observation.segmentation.dtype == np.uint32
            assert observation.current_top_down is not None
            assert observation.current_top_down.shape == (64, 64, 3)
            assert isinstance(observation.grasping, bool)
            images: list[npt.NDArray[Any]] = [
                observation.ego_rgb,
                observation.depth,
                observation.segmentation,
                observation.current_top_down,
            ]
            if observation.goal_rgb is not None:
                images.append(observation.goal_rgb)
            for image in images:
                assert not image.flags.writeable
                assert not image.flags.owndata
                # The array is a view of the message's bytes: no copy was made on our side.
                data = buffer_of(image)
                assert isinstance(data, bytes)
                assert len(data) == image.nbytes
                assert np.shares_memory(image, np.frombuffer(data, dtype=np.uint8))
                with pytest.raises(ValueError, match="read-only"):
                    image.flat[0] = 0
            # Depth is finite in metres where something is seen; labels name the floor (1) or walls (2).
            assert np.isfinite(observation.depth).any()
            assert (observation.depth[np.isfinite(observation.depth)] > 0).all()
            assert {1, 2} & set(np.unique(observation.segmentation).tolist())


def test_expert_replay_succeeds(client: esrp.Client, easy_scenes: list[str]) -> None:
    """Privileged state carries the scene and its expert trajectory; replaying it succeeds."""
    with client.create_episode(easy_scenes[2], privileged=True) as episode:
        state = episode.privileged_state()
        assert state.held is None
        assert 0 <= state.agent_heading < 16
        assert len(state.objects) == 1
        assert state.static_obstacles
        assert len(state.floor) >= 3
        scene = json.loads(state.scene_json)
        assert scene["id"] == easy_scenes[2]
        result = None
        for code in scene["expert_trajectory"]:
            result = episode.step(esrp.Action(code))
        assert result is not None
        assert result.terminated
        assert not result.truncated
        assert result.metrics is not None
        assert result.metrics.success
        assert result.metrics.stage == 4
        assert result.metrics.object_success_rate == 1.0
        assert result.metrics.steps == len(scene["expert_trajectory"])
        assert result.reward >= 10
        progress = episode.metrics()
        assert progress.ended
        assert progress.metrics == result.metrics
        assert episode.privileged_state().objects[0].placed


def test_step_batch(client: esrp.Client, easy_scenes: list[str]) -> None:
    with client.create_episode(easy_scenes[0]) as a, client.create_episode(easy_scenes[1]) as b:
        results = client.step_batch([(a, esrp.Action.LEFT), (b.id, 3)], include_goal=True)
        assert [r.info.step_index for r in results] == [1, 1]
        assert all(r.observation.goal_rgb is not None for r in results)
        # Answers come in request order: each matches its own episode stepped alone.
        with client.create_episode(easy_scenes[1]) as alone:
            assert np.array_equal(alone.step(3).observation.ego_rgb, results[1].observation.ego_rgb)
        assert client.step_batch([]) == []


def test_step_columns(client: esrp.Client, easy_scenes: list[str]) -> None:
    sensors = esrp.Sensors(depth=True, resolution=64)
    scenes = easy_scenes[:3]
    batched = [client.create_episode(scene, sensors=sensors) for scene in scenes]
    alone = [client.create_episode(scene, sensors=sensors) for scene in scenes]
    try:
        ids = [episode.id for episode in batched]
        # One call, then (the batch size forced down) two calls at once: the same columns as the
        # same episodes stepped one by one, in request order.
        for actions in ([esrp.Action.LEFT, 3, np.int64(0)], [2, 2, 1]):
            columns = client.step_columns(ids, actions, sensors)
            assert list(columns.images) == ["ego_rgb", "depth"]
            for k, (episode, action) in enumerate(zip(alone, actions, strict=True)):
                result = episode.step(action)
                assert columns.rewards[k] == result.reward
                assert (columns.terminated[k], columns.truncated[k]) == (result.terminated, result.truncated)
                assert columns.step_index[k] == result.info.step_index
                assert bytes(columns.images["ego_rgb"][k]) == result.observation.ego_rgb.tobytes()
                depth = result.observation.depth
                assert depth is not None
                assert bytes(columns.images["depth"][k]) == depth.tobytes()
            client._batch_sizes[sensors] = 2  # noqa: SLF001 - as the server's limits would
        assert client.step_columns([], [], sensors).rewards == []
        bad: list[Any] = [0, 2.5]
        with pytest.raises(esrp.InvalidRequest, match=r"steps\[1\]\.action"):
            client.step_columns(ids[:2], bad, sensors)
    finally:
        client._batch_sizes.clear()  # noqa: SLF001
        for episode in batched + alone:
            episode.close()


def test_step_columns_with_resets(client: esrp.Client, easy_scenes: list[str]) -> None:
    sensors = esrp.Sensors(resolution=32)
    episodes = [client.create_episode(scene, sensors=sensors) for scene in easy_scenes[:4]]
    ids = [episode.id for episode in episodes]
    firsts = [cast(esrp.Observation, episode.observation).ego_rgb.tobytes() for episode in episodes]
    try:
        # One call, then with the batch size forced down to 2 (a reset counts as two steps) three
        # calls: [step, step], [reset], [reset]; the answers in request order either way.
        for size in (None, 2):
            if size is not None:
                client._batch_sizes[sensors] = size  # noqa: SLF001 - as the server's limits would
            client.step_columns(ids[:2], [3, 3], sensors)
            resets: list[tuple[str, str | None]] = [(ids[2], None), (ids[3], easy_scenes[0])]
            columns = client.step_columns(ids[:2], [2, 2], sensors, resets=resets)
            assert columns.step_index == [2, 2]
            assert [scene.id for _, scene in columns.resets] == [easy_scenes[2], easy_scenes[0]]
            assert columns.resets[0][0].ego_rgb.tobytes() == firsts[2]
            assert columns.resets[1][0].ego_rgb.tobytes() == firsts[0]
            assert columns.resets[1][0].goal_rgb is not None
            for episode in episodes[:2]:
                episode.reset()
            client.step_columns([], [], sensors, resets=[(ids[3], easy_scenes[3])])
        client._batch_sizes.clear()  # noqa: SLF001
        with pytest.raises(esrp.InvalidRequest, match=r"resets\[0\]: episode .* appears twice"):
            client.step_columns(ids[:1], [0], sensors, resets=[(ids[0], None)])
    finally:
        client._batch_sizes.clear()  # noqa: SLF001
        for episode in episodes:
            episode.close()


def test_attach_by_id(client: esrp.Client, easy_scenes: list[str]) -> None:
    episode = client.create_episode(easy_scenes[0])
    episode_id = episode.detach()
    with client.episode(episode_id) as attached:
        assert attached.observation is None
        assert attached.step(esrp.Action.LEFT).info.step_index == 1
        attached.reset()
        assert attached.scene.id == easy_scenes[0]


def test_action_values() -> None:
    assert [int(a) for a in esrp.Action] == [0, 1, 2, 3, 4, 5]
    assert esrp.Action.FETCH.api_name == "fetch"
    assert esrp.Action(1) is esrp.Action.BACKWARD
