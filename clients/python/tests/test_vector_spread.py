"""A vector env whose sub-envs are spread over several servers (`address` a list, `client` a
list, or `servers=K`): the same observations, rewards, flags and infos as on one server, bit for
bit, in every autoreset mode; each server holds its block's episodes and gets one StepBatch per
step; the env's own servers stop with it; bad settings are refused before anything starts."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from conftest import settled_live_episodes
from gymnasium.vector import AutoresetMode
from test_vector import SMALL, assert_same_returns

import esrp
from esrp.envs import RearrangeEnv, RearrangeVectorEnv

NUM_ENVS = 5


@pytest.fixture(scope="module")
def second() -> Iterator[esrp.LocalServer]:
    """Another server of the same benchmark, over a Unix domain socket."""
    with esrp.LocalServer(unix_socket=True) as running:
        yield running


@pytest.fixture(scope="module")
def third() -> Iterator[esrp.LocalServer]:
    """A third server of the same benchmark, over TCP."""
    with esrp.LocalServer() as running:
        yield running


def drive(envs: RearrangeVectorEnv, steps: int, seed: int) -> list[Any]:
    """Resets with `seed`, steps with seeded actions and resets sub-envs 1 and 3 alone after the
    second step (so that episodes end at different steps, on every server); returns everything
    the env returned. In DISABLED mode, ended sub-envs are reset with a mask before each step.
    """
    n = envs.num_envs
    actions = np.random.default_rng(seed).integers(0, 6, size=(steps, n))
    record: list[Any] = [envs.reset(seed=seed)]
    ended = np.zeros(n, dtype=np.bool_)
    for t in range(steps):
        if envs.autoreset_mode == AutoresetMode.DISABLED and ended.any():
            record.append(envs.reset(options={"reset_mask": ended.copy()}))
        step = envs.step(actions[t])
        ended = step[2] | step[3]
        record.append(step)
        if t == 1:
            mask = np.zeros(n, dtype=np.bool_)
            mask[[1, 3]] = True
            record.append(envs.reset(options={"reset_mask": mask}))
            ended &= ~mask
    return record


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED])
def test_identical_to_one_server(
    server: esrp.LocalServer, second: esrp.LocalServer, third: esrp.LocalServer, mode: AutoresetMode
) -> None:
    settings: dict[str, Any] = {"split": "test", "sensors": SMALL, "horizon": 3, "autoreset_mode": mode}
    one = RearrangeVectorEnv(NUM_ENVS, server.address, **settings)
    spread = RearrangeVectorEnv(NUM_ENVS, [server.address, second.address, third.address], **settings)
    try:
        assert spread.server_of_env == (0, 0, 1, 1, 2)
        assert [c.address for c in spread.clients] == [server.address, second.address, third.address]
        assert spread.client is spread.clients[0]
        got, expected = drive(spread, 9, seed=21), drive(one, 9, seed=21)
        ended = assert_same_returns(got, expected)
        assert ended >= NUM_ENVS  # the horizon of 3 ended episodes on every server
        if mode is AutoresetMode.SAME_STEP:
            assert any("final_obs" in g[4] for g in got if len(g) == 5)
    finally:
        one.close()
        spread.close()


def test_each_server_holds_its_block(server: esrp.LocalServer, second: esrp.LocalServer) -> None:
    """Sub-envs 0-2 live on the first server and 3-4 on the second; closing frees both. (Over
    grpcio: its calls are started together, not made by the native transport at once.)"""
    with (
        server.client(transport="grpcio") as first_client,
        second.client(transport="grpcio") as second_client,
    ):
        before = (first_client.server_info().live_episodes, second_client.server_info().live_episodes)
        envs = RearrangeVectorEnv(NUM_ENVS, client=[first_client, second_client], split="test", sensors=SMALL)
        try:
            envs.reset(seed=4)
            envs.step(np.array([2, 3, 2, 3, 2]))
            assert envs.server_of_env == (0, 0, 0, 1, 1)
            ids = envs.episode_ids
            for i, episode_id in enumerate(ids):
                assert episode_id is not None
                owner = envs.clients[envs.server_of_env[i]]
                other = envs.clients[1 - envs.server_of_env[i]]
                assert owner.episode(episode_id).metrics().metrics.steps == 1
                with pytest.raises(esrp.EpisodeNotFound):
                    other.episode(episode_id).metrics()
            assert first_client.server_info().live_episodes == before[0] + 3
            assert second_client.server_info().live_episodes == before[1] + 2
        finally:
            envs.close()
        # The clients were the caller's: still open, and every episode closed.
        assert settled_live_episodes(first_client, before[0]) == before[0]
        assert settled_live_episodes(second_client, before[1]) == before[1]


def test_one_step_batch_per_server_per_step(
    server: esrp.LocalServer, second: esrp.LocalServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A step sends each server one StepBatch of its block's steps and autoresets, all of them
    made together (one `run_all`, which makes its calls at once)."""
    from esrp._transport import Calls, run_all

    made: list[list[tuple[int, int, int]]] = []

    def counted(method: str, calls: list[tuple[Calls, Any]]) -> list[Any]:  # noqa: ANN401
        if method == "StepBatch":
            made.append([(id(each), len(request.steps), len(request.resets)) for each, request in calls])
        return run_all(method, calls)

    envs = RearrangeVectorEnv(
        NUM_ENVS, [server.address, second.address], split="test", sensors=SMALL, horizon=2
    )
    try:
        calls = [id(client._calls) for client in envs.clients]  # noqa: SLF001
        envs.reset(seed=5)
        monkeypatch.setattr("esrp._client.run_all", counted)
        envs.step(np.array([1, 1, 1, 1, 1]))
        assert made == [[(calls[0], 3, 0), (calls[1], 2, 0)]]
        made.clear()
        _, _, _, truncated, _ = envs.step(np.array([1, 1, 1, 1, 1]))
        assert truncated.all()
        made.clear()
        envs.step(np.array([1, 1, 1, 1, 1]))  # NEXT_STEP: every sub-env autoresets, no step
        assert made == [[(calls[0], 0, 3), (calls[1], 0, 2)]]
    finally:
        envs.close()


def test_servers_started_by_the_env() -> None:
    """`servers=2` starts two local servers over sockets, one per block, and stops them at close."""
    envs = RearrangeVectorEnv(4, servers=2, split="test", sensors=SMALL)
    servers = list(envs._setup.servers)  # noqa: SLF001
    try:
        assert len(servers) == 2
        assert all(server.is_running() and server.unix_socket for server in servers)
        assert [c.address for c in envs.clients] == [s.address for s in servers]
        sockets = [s.address.removeprefix("unix:") for s in servers]
        observations, _ = envs.reset(seed=0)
        assert observations["ego_rgb"].shape == (4, 32, 32, 3)
        envs.step(np.array([0, 1, 2, 3]))
    finally:
        envs.close()
    assert not any(server.is_running() for server in servers)
    assert not any(os.path.exists(path) for path in sockets)


def test_bad_spreads_are_refused(server: esrp.LocalServer) -> None:
    with pytest.raises(ValueError, match="3 servers for 2 sub-envs"):
        RearrangeVectorEnv(2, servers=3)
    with pytest.raises(ValueError, match="3 servers for 2 sub-envs"):
        RearrangeVectorEnv(2, [server.address] * 3)
    with pytest.raises(ValueError, match="servers is the number of servers started here"):
        RearrangeVectorEnv(2, server.address, servers=2)
    with pytest.raises(ValueError, match="servers must be at least 1"):
        RearrangeVectorEnv(2, servers=0)
    with pytest.raises(ValueError, match="non-empty list of addresses"):
        RearrangeVectorEnv(2, [])
    with pytest.raises(ValueError, match="non-empty list of Clients"):
        RearrangeVectorEnv(2, client=[])
    with pytest.raises(TypeError, match="one episode on one server"):
        RearrangeEnv([server.address, server.address])  # type: ignore[arg-type]


def test_different_datasets_are_refused(server: esrp.LocalServer) -> None:
    """A sub-env's scene must exist on whichever server plays it: the servers must serve one dataset."""
    with (
        esrp.LocalServer("--benchmark", "esrp-bench-v1") as other,
        pytest.raises(ValueError, match="different datasets.*esrp-bench-v2.*esrp-bench-v1"),
    ):
        RearrangeVectorEnv(2, [server.address, other.address], split="test")


def test_a_server_gone_mid_run_is_an_error_the_caller_can_catch(server: esrp.LocalServer) -> None:
    with esrp.LocalServer(unix_socket=True) as doomed:
        envs = RearrangeVectorEnv(2, [server.address, doomed.address], split="test", sensors=SMALL)
        try:
            envs.reset(seed=1)
            doomed.stop()
            with pytest.raises(esrp.EsrpError):
                envs.step(np.array([0, 0]))
        finally:
            envs.close()
