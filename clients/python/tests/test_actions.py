"""What a step takes as its action, everywhere (Episode, AsyncEpisode, step_batch, the stream, the
single and the vector env): an Action or int, a numpy integer, an integer-valued float, or a numpy
array of one; a non-integer float is refused with the words a code out of range gets."""

from __future__ import annotations

import asyncio
from typing import Any

import gymnasium
import numpy as np
import pytest

import esrp
from esrp.envs import RearrangeEnv

TAKEN = [2, esrp.Action.LEFT, np.int64(2), np.int32(2), np.uint8(2), 2.0, np.float64(2.0), np.array(2)]
TAKEN += [np.array([2]), np.array([2.0])]


def refused(call: Any) -> str:  # noqa: ANN401
    with pytest.raises(esrp.InvalidRequest) as caught:
        call()
    return str(caught.value)


def test_episode_step(client: esrp.Client) -> None:
    with client.create_episode(split="test") as episode:
        for k, action in enumerate(TAKEN, start=1):
            result = episode.step(action)
            assert result.info.step_index == k, action
            assert result.info.accepted  # a turn is always accepted
        out_of_range = refused(lambda: episode.step(7))
        assert out_of_range.startswith("INVALID_ARGUMENT: step.action: unknown action code 7: use 0")
        # Codes beyond the request's int32 are refused in the same words (not protobuf's).
        cases: list[tuple[object, str]] = [(2.7, "2.7"), (np.float32(2.5), "2.5"), (np.array([2.7]), "2.7")]
        cases += [("2", "'2'"), (2**40, str(2**40)), (np.int64(-(2**31) - 1), str(-(2**31) - 1))]
        for bad, shown in cases:
            message = refused(lambda bad=bad: episode.step(bad))
            assert message == out_of_range.replace("code 7", f"code {shown}"), message
        assert "array of shape (2,)" in refused(lambda: episode.step(np.array([2, 3])))
        # Nothing refused moved the episode.
        assert episode.metrics().metrics.steps == len(TAKEN)


def test_step_batch_and_stream(client: esrp.Client) -> None:
    with client.create_episode(split="test") as a, client.create_episode(split="test") as b:
        results = client.step_batch([(a, np.int64(2)), (b, np.array([3]))])
        assert [r.info.step_index for r in results] == [1, 1]
        out_of_range = refused(lambda: client.step_batch([(a, 2), (b, 7)]))
        assert "steps[1].action: unknown action code 7" in out_of_range
        assert refused(lambda: client.step_batch([(a, 2), (b, 2.7)])) == out_of_range.replace(  # type: ignore[list-item]
            "code 7", "code 2.7"
        )
        with client.episode_stream() as stream:
            stream.step(a.id, np.float64(1.0))
            answer = stream.next()
            assert answer is not None
            assert answer.step_result().info.step_index == 2
            assert "step.action: unknown action code 2.7" in refused(lambda: stream.step(a.id, 2.7))  # type: ignore[arg-type]


def test_async_episode(server: esrp.LocalServer) -> None:
    async def run() -> str:
        async with esrp.AsyncClient(server.address) as client:
            episode = await client.create_episode(split="test")
            async with episode:
                result = await episode.step(np.array([2]))
                assert result.info.step_index == 1
                with pytest.raises(esrp.InvalidRequest) as caught:
                    await episode.step(2.7)  # type: ignore[arg-type]
                return str(caught.value)

    assert asyncio.run(run()).startswith("INVALID_ARGUMENT: step.action: unknown action code 2.7: use 0")


def test_single_env(server: esrp.LocalServer) -> None:
    env = RearrangeEnv(server.address, split="test", difficulty="easy")
    try:
        env.reset(seed=0)
        for k, action in enumerate(TAKEN, start=1):
            _, _, _, _, info = env.step(action)
            assert info["step_index"] == k
        out_of_range = refused(lambda: env.step(7))
        assert refused(lambda: env.step(2.7)) == out_of_range.replace("code 7", "code 2.7")  # type: ignore[arg-type]
    finally:
        env.close()


def test_vector_env(server: esrp.LocalServer) -> None:
    envs = gymnasium.make_vec(
        esrp.ENV_ID, num_envs=2, vectorization_mode="vector_entry_point", address=server.address, split="test"
    )
    try:
        envs.reset(seed=0)
        taken: list[Any] = [np.array([2, 3]), [2, 3], np.array([2.0, 3.0]), np.array([2, 3], dtype=np.uint8)]
        # Each sub-env's action as the single env takes it: shape-(1,) arrays, numpy scalars,
        # integer-valued floats, in a list or as an array of shape (2, 1).
        taken += [[np.array([2]), np.array([3])], [np.int64(2), 3.0], np.array([[2], [3]])]
        taken += [(esrp.Action.LEFT, 3)]
        for actions in taken:
            _, _, _, _, infos = envs.step(actions)
            assert infos["accepted"].all(), actions
        # A code out of range and a non-integer float are refused alike, in the words the single
        # env's step gets from the server, naming the sub-env; nothing moves.
        out_of_range = refused(lambda: envs.step(np.array([2, 7])))
        assert out_of_range == (
            "INVALID_ARGUMENT: actions[1].action: unknown action code 7: "
            "use 0 move_forward, 1 move_backward, 2 turn_left, 3 turn_right, 4 fetch, 5 release"
        )
        for bad, shown in (([2, 2.7], "2.7"), (np.array([2, 2.7]), "2.7"), ([2, np.float32(2.5)], "2.5")):
            message = refused(lambda bad=bad: envs.step(bad))
            assert message == out_of_range.replace("code 7", f"code {shown}"), message
        assert "actions[0].action: unknown action code '2'" in refused(lambda: envs.step(["2", 3]))
        _, _, _, _, infos = envs.step([2, 3])
        assert infos["step_index"].tolist() == [len(taken) + 1] * 2
        with pytest.raises(ValueError, match="shape"):
            envs.step(np.array([[2, 3]]))
    finally:
        envs.close()
