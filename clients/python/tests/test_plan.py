"""PlanActions through the sync and async clients, against the real server's planner."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

import esrp


def _step_all(episode: esrp.Episode, actions: tuple[esrp.Action, ...]) -> esrp.StepResult:
    result = None
    for action in actions:
        result = episode.step(action)
    assert result is not None
    return result


def test_plan_from_the_start_reaches_success(client: esrp.Client, easy_scenes: list[str]) -> None:
    with client.create_episode(easy_scenes[0], privileged=True) as episode:
        answer = episode.plan_actions()
        assert answer.failure is None
        assert answer.failure_message == ""
        assert answer.reaches_success
        assert not answer.cached
        assert answer.plan_length == len(answer.actions) > 0
        assert all(isinstance(a, esrp.Action) for a in answer.actions)
        assert answer.stats.searches >= 1
        assert answer.stats.planning_seconds >= 0
        result = _step_all(episode, answer.actions)
        assert result.terminated
        assert result.metrics is not None
        assert result.metrics.success
        # Planning an ended episode is refused.
        with pytest.raises(esrp.EpisodeEnded):
            episode.plan_actions()


def test_plan_after_random_steps_and_the_cache(client: esrp.Client, easy_scenes: list[str]) -> None:
    rng = np.random.default_rng(5)
    with client.create_episode(easy_scenes[1], privileged=True) as episode:
        for code in rng.integers(0, 4, size=6):  # moves and turns only
            episode.step(int(code))
        head = episode.plan_actions(max_actions=3)
        assert len(head.actions) == 3
        assert head.plan_length > 3
        whole = episode.plan_actions()
        assert whole.cached  # the same state: the cached plan
        assert whole.actions[:3] == head.actions
        assert whole.plan_length == head.plan_length
        _step_all(episode, head.actions)
        rest = episode.plan_actions()
        assert rest.cached  # the episode followed the plan
        assert rest.actions == whole.actions[3:]
        assert rest.plan_length == whole.plan_length - 3
        result = _step_all(episode, rest.actions)
        assert result.metrics is not None
        assert result.metrics.success
        assert result.metrics.steps == 6 + whole.plan_length


def test_plan_errors(client: esrp.Client, easy_scenes: list[str]) -> None:
    with client.create_episode(easy_scenes[0]) as plain, pytest.raises(esrp.PermissionDenied):
        plain.plan_actions()
    hard = next(client.scenes("test", "hard")).id
    with client.create_episode(hard, privileged=True) as episode:
        with pytest.raises(esrp.DeadlineExceeded):
            episode.plan_actions(budget_ms=1)
        with pytest.raises(esrp.InvalidRequest):
            episode.plan_actions(max_actions=-1)
        with pytest.raises(esrp.InvalidRequest):
            episode.plan_actions(budget_ms=0)
    with pytest.raises(esrp.EpisodeNotFound):
        episode.plan_actions()


def test_async_plan_matches_sync(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str]
) -> None:
    with client.create_episode(easy_scenes[2], privileged=True) as episode:
        expected = episode.plan_actions()

    async def main() -> esrp.PlanAnswer:
        async with esrp.AsyncClient(server.address, timeout=60) as aclient:
            async with await aclient.create_episode(easy_scenes[2]) as plain:
                with pytest.raises(esrp.PermissionDenied):
                    await plain.plan_actions()
            async with await aclient.create_episode(easy_scenes[2], privileged=True) as episode:
                answer = await episode.plan_actions()
                for action in answer.actions:
                    result = await episode.step(action)
                assert result.metrics is not None
                assert result.metrics.success
                with pytest.raises(esrp.EpisodeEnded):
                    await episode.plan_actions()
                return answer

    got = asyncio.run(main())
    assert got.actions == expected.actions  # the planner is deterministic
    assert got.plan_length == expected.plan_length
