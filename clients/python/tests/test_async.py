"""AsyncClient, the asyncio twin: the same calls and values as the sync client."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from conftest import settled_live_episodes

import esrp


def test_async_calls(server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str]) -> None:
    before = client.server_info().live_episodes

    async def main() -> None:
        async with esrp.AsyncClient(server.address, timeout=60) as aclient:
            await aclient.wait_healthy()
            info = await aclient.server_info()
            assert info == client.server_info()
            assert (await aclient.describe_dataset()) == client.describe_dataset()
            scenes = [s async for s in aclient.scenes("test", "easy", page_size=100)]
            assert [s.id for s in scenes] == easy_scenes
            async with await aclient.create_episode(easy_scenes[0], privileged=True) as episode:
                assert episode.observation is not None
                result = await episode.step(esrp.Action.LEFT, include_goal=True)
                assert result.info.step_index == 1
                assert result.observation.goal_rgb is not None
                assert not result.observation.ego_rgb.flags.writeable
                goal = await episode.goal()
                assert np.array_equal(goal.image, result.observation.goal_rgb)
                progress = await episode.metrics()
                assert progress.metrics.steps == 1
                assert not progress.ended
                state = await episode.privileged_state()
                assert len(state.objects) == 1
                first = await episode.reset()
                assert np.array_equal(first.ego_rgb, episode.observation.ego_rgb)
                other = await aclient.create_episode(easy_scenes[1])
                batch = await aclient.step_batch([(episode, 2), (other.id, 3)])
                assert [r.info.step_index for r in batch] == [1, 1]
                assert (await other.close()).steps == 1
                with pytest.raises(esrp.EpisodeNotFound):
                    await other.step(0)
                with pytest.raises(esrp.InvalidRequest):
                    await episode.step(9)
            with pytest.raises(esrp.PermissionDenied):
                async with await aclient.create_episode(easy_scenes[0]) as plain:
                    await plain.privileged_state()

    asyncio.run(main())
    assert settled_live_episodes(client, before) == before


def test_async_step_columns_match_sync(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str]
) -> None:
    sensors = esrp.Sensors(segmentation=True, resolution=32)
    scenes = easy_scenes[:3]
    actions = [[2, 0, 3], [4, 1, 1]]
    synced = [client.create_episode(scene, sensors=sensors) for scene in scenes]
    try:
        expected = [client.step_columns([e.id for e in synced], wave, sensors) for wave in actions]
    finally:
        for episode in synced:
            episode.close()

    async def main() -> None:
        async with esrp.AsyncClient(server.address, timeout=60) as aclient:
            episodes = [await aclient.create_episode(scene, sensors=sensors) for scene in scenes]
            ids = [episode.id for episode in episodes]
            # The second wave in two concurrent calls (the batch size forced down).
            for wave, want in zip(actions, expected, strict=True):
                got = await aclient.step_columns(ids, wave, sensors)
                assert (got.rewards, got.step_index) == (want.rewards, want.step_index)
                assert got.grasping == want.grasping
                for key in ("ego_rgb", "segmentation"):
                    assert [bytes(x) for x in got.images[key]] == [bytes(x) for x in want.images[key]]
                aclient._batch_sizes[sensors] = 2  # noqa: SLF001 - as the server's limits would
            for episode in episodes:
                await episode.close()

    asyncio.run(main())


def test_async_stream_matches_sync_stream(server: esrp.LocalServer, client: esrp.Client) -> None:
    actions = [2, 0, 0, 4, 3, 1]
    with client.episode_stream() as stream:
        stream.create(split="test", seed=4)
        created = stream.next()
        assert created is not None
        expected = stream.run({created.created().episode_id: actions})

    async def main() -> list[esrp.StepResult | esrp.EsrpError]:
        async with (
            esrp.AsyncClient(server.address) as aclient,
            await aclient.episode_stream(window=3) as astream,
        ):
            await astream.create(split="test", seed=4)
            answer = await astream.next()
            assert answer is not None
            episode = answer.created().episode_id
            results = await astream.run({episode: actions})
            await astream.step(episode, 9)
            bad = await astream.next()
            assert bad is not None
            assert isinstance(bad.error, esrp.InvalidRequest)
            return results[episode]

    got = asyncio.run(main())
    for a, b in zip(got, next(iter(expected.values())), strict=True):
        assert isinstance(a, esrp.StepResult)
        assert isinstance(b, esrp.StepResult)
        assert np.array_equal(a.observation.ego_rgb, b.observation.ego_rgb)
        assert a.info == b.info


def test_async_abandoned_create_leaves_no_episode(server: esrp.LocalServer, client: esrp.Client) -> None:
    before = client.server_info().live_episodes

    async def main() -> int:
        abandoned = 0
        async with esrp.AsyncClient(server.address) as aclient:
            for seed in range(6):
                try:
                    episode = await aclient.create_episode(split="test", seed=seed, timeout=0.0005 * seed)
                    await episode.close()
                except esrp.DeadlineExceeded:
                    abandoned += 1
            # A cancelled task, too.
            task = asyncio.ensure_future(aclient.create_episode(split="test"))
            await asyncio.sleep(0)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
        return abandoned

    assert asyncio.run(main()) > 0
    assert settled_live_episodes(client, before) == before
