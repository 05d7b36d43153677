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


def test_a_plan_call_deadline_covers_the_budget() -> None:
    """The client's `timeout` is stretched to the planning budget plus 5 s: the call's own, else
    the server's (`ServerLimits.plan_budget_ms`; 60 s where an older server says none)."""
    from esrp._convert import plan_timeout

    assert plan_timeout(None, None, 90_000) is None  # no deadline stays none
    assert plan_timeout(1.0, 2_000, 90_000) == 7.0  # the call's budget
    assert plan_timeout(1.0, None, 90_000) == 95.0  # the server's
    assert plan_timeout(1.0, None, 0) == 65.0  # an older server's: its cap by default
    assert plan_timeout(300.0, None, 90_000) == 300.0  # a longer timeout is kept


def test_a_client_with_a_timeout_learns_the_server_plan_budget() -> None:
    """A call that names its budget asks nothing more; one that names none learns the server's
    budget once (its deadline is stretched to it), on both clients."""
    with esrp.LocalServer("--plan-budget-ms", "90000", "--max-plan-ms", "120000") as server:
        with esrp.Client(server.address, timeout=30) as client:
            limits = client.server_info().limits
            assert (limits.plan_budget_ms, limits.max_plan_ms) == (90_000, 120_000)
            scene = next(client.scenes("test", "easy")).id
            with client.create_episode(scene, privileged=True) as episode:
                assert episode.plan_actions(budget_ms=5_000).reaches_success
                assert client._plan_budget_ms is None
                assert episode.plan_actions().reaches_success
                assert client._plan_budget_ms == 90_000

        async def main() -> None:
            async with (
                esrp.AsyncClient(server.address, timeout=30) as aclient,
                await aclient.create_episode(scene, privileged=True) as episode,
            ):
                assert (await episode.plan_actions(budget_ms=5_000)).reaches_success
                assert aclient._plan_budget_ms is None
                assert (await episode.plan_actions()).reaches_success
                assert aclient._plan_budget_ms == 90_000

        asyncio.run(main())
