"""The pipelined EpisodeStream: answers in request order, identical to unary calls, windows kept,
episodes of the stream closed with it."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import settled_live_episodes

import esrp

ACTIONS = [2, 2, 0, 0, 4, 3, 1, 5, 0, 2]


def test_run_matches_unary_steps(client: esrp.Client, easy_scenes: list[str]) -> None:
    scenes = easy_scenes[:3]
    with client.episode_stream(window=4) as stream:
        for scene in scenes:
            stream.create(scene)
        created = [answer.created() for answer in stream]
        assert [c.scene.id for c in created] == scenes
        plans = {c.episode_id: ACTIONS[: 4 + i * 3] for i, c in enumerate(created)}
        results = stream.run(plans)
        assert stream.outstanding == 0
    for c, scene in zip(created, scenes, strict=True):
        streamed = results[c.episode_id]
        with client.create_episode(scene) as episode:
            assert np.array_equal(episode.observation.ego_rgb, c.observation.ego_rgb)  # type: ignore[union-attr]
            for action, got in zip(plans[c.episode_id], streamed, strict=True):
                assert isinstance(got, esrp.StepResult)
                expected = episode.step(action)
                assert np.array_equal(got.observation.ego_rgb, expected.observation.ego_rgb)
                assert got.reward == expected.reward
                assert got.info == expected.info


def test_run_checks_every_action_before_sending_one(client: esrp.Client) -> None:
    with client.episode_stream() as stream:
        stream.create(split="test")
        first = stream.next()
        assert first is not None
        episode = first.created().episode_id
        refused = r"plans\['[0-9a-f]+'\]\[2\]\.action: unknown action code 'x'"
        with pytest.raises(esrp.InvalidRequest, match=refused):
            stream.run({episode: [2, 2, "x"]})  # type: ignore[list-item]
        assert stream.outstanding == 0  # nothing was sent: the stream goes on
        results = stream.run({episode: [2, 2]})
        assert [r.info.step_index for r in results[episode] if isinstance(r, esrp.StepResult)] == [1, 2]


def test_window_bounds_steps_in_flight(client: esrp.Client) -> None:
    with client.create_episode(split="test") as episode, client.episode_stream(window=2) as stream:
        ids = [stream.step(episode.id, esrp.Action.LEFT) for _ in range(5)]
        assert ids == [1, 2, 3, 4, 5]
        # Sending the 3rd and 5th steps had to read the oldest answers first; all stay in order.
        answers = list(stream)
        assert [a.request_id for a in answers] == ids
        assert [a.step_result().info.step_index for a in answers] == [1, 2, 3, 4, 5]
        assert all(a.kind is esrp.RequestKind.STEP and a.episode_id == episode.id for a in answers)
        assert stream.next() is None


def test_reset_and_close_on_a_stream(client: esrp.Client) -> None:
    before = client.server_info().live_episodes
    with client.episode_stream() as stream:
        stream.create(split="test", seed=1)
        first = stream.next()
        assert first is not None
        episode = first.created().episode_id
        stream.step(episode, esrp.Action.FORWARD)
        stream.reset(episode)
        stream.close_episode(episode)
        step, reset, closed = list(stream)
        assert step.step_result().info.step_index == 1
        assert np.array_equal(reset.observation().ego_rgb, first.created().observation.ego_rgb)
        assert closed.metrics().steps == 0
        assert closed.kind is esrp.RequestKind.CLOSE
    assert settled_live_episodes(client, before) == before


def test_stream_episodes_die_with_the_stream(client: esrp.Client) -> None:
    before = client.server_info().live_episodes
    stream = client.episode_stream()
    for seed in range(3):
        stream.create(split="test", seed=seed)
    assert len(list(stream)) == 3
    assert client.server_info().live_episodes == before + 3
    stream.close()
    assert settled_live_episodes(client, before) == before
    with pytest.raises(esrp.ServerUnavailable, match="ended"):
        stream.step("0" * 32, 0)


def test_window_must_be_positive(client: esrp.Client) -> None:
    with pytest.raises(esrp.InvalidRequest, match="window"):
        client.episode_stream(window=0)
