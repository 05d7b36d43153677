"""Each error class from a real bad request, with the server's message, code and gRPC error kept."""

from __future__ import annotations

import asyncio
import re
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import grpc
import pytest
from conftest import settled_live_episodes

import esrp
from esrp.cli import main as esrp_main
from esrp.envs import RearrangeEnv


def check(error: esrp.EsrpError, code: grpc.StatusCode, needle: str) -> None:
    """The error has the status code, the server's message, and the gRPC error as its cause."""
    assert error.code == code
    assert needle in error.message
    assert needle in str(error)
    assert isinstance(error.rpc_error, grpc.RpcError)
    assert error.__cause__ is error.rpc_error
    assert error.rpc_error.details() == error.message


@pytest.fixture(scope="module")
def strict_server() -> Iterator[esrp.LocalServer]:
    """A server with a token and tiny limits."""
    with esrp.LocalServer("--token", "s3cret", "--max-episodes", "2", "--max-batch", "2") as running:
        yield running


def test_episode_not_found(client: esrp.Client) -> None:
    with pytest.raises(esrp.EpisodeNotFound) as caught:
        client.episode("0" * 32).step(esrp.Action.LEFT)
    check(caught.value, grpc.StatusCode.NOT_FOUND, 'no episode "00000000')
    assert isinstance(caught.value, esrp.NotFound)
    episode = client.create_episode(split="test")
    episode.close()
    with pytest.raises(esrp.EpisodeNotFound):
        episode.metrics()
    # Closed by another handle: this one's close finds nothing.
    elsewhere = client.create_episode(split="test")
    client.episode(elsewhere.id).close()
    with pytest.raises(esrp.EpisodeNotFound):
        elsewhere.close()


def test_scene_not_found(client: esrp.Client) -> None:
    with pytest.raises(esrp.SceneNotFound) as caught:
        client.create_episode("esrp-bench-v2/99999")
    check(caught.value, grpc.StatusCode.NOT_FOUND, 'no scene "esrp-bench-v2/99999"')


def test_invalid_request(client: esrp.Client) -> None:
    with client.create_episode(split="test") as episode:
        with pytest.raises(esrp.InvalidRequest) as caught:
            episode.step(9)
        check(caught.value, grpc.StatusCode.INVALID_ARGUMENT, "unknown action code 9")
        assert episode.metrics().metrics.steps == 0  # a refused step does not count
        with pytest.raises(esrp.InvalidRequest) as caught:
            client.step_batch([(episode, 0), (episode, 1)])
        check(caught.value, grpc.StatusCode.INVALID_ARGUMENT, "appears twice in one batch")
    with pytest.raises(esrp.InvalidRequest) as caught:
        client.create_episode(split="test", sensors=esrp.Sensors(resolution=5))
    check(caught.value, grpc.StatusCode.INVALID_ARGUMENT, "sensors.resolution 5 is out of range")
    with pytest.raises(esrp.InvalidRequest) as caught:
        client.create_episode(scene_json="{not json")
    check(caught.value, grpc.StatusCode.INVALID_ARGUMENT, "invalid scene")
    with pytest.raises(esrp.InvalidRequest) as caught:
        list(client.scenes(page_size=5000))
    check(caught.value, grpc.StatusCode.INVALID_ARGUMENT, "5000")
    # Client-side checks raise the same class, without a gRPC error.
    with pytest.raises(esrp.InvalidRequest, match="unknown split"):
        client.scenes("validation")
    with pytest.raises(esrp.InvalidRequest, match="not both"):
        client.create_episode("esrp-bench-v2/00000", scene_json="{}")


def test_episode_ended(client: esrp.Client) -> None:
    with client.create_episode(split="test", horizon=1) as episode:
        assert episode.step(esrp.Action.LEFT).truncated
        with pytest.raises(esrp.EpisodeEnded) as caught:
            episode.step(esrp.Action.LEFT)
        check(caught.value, grpc.StatusCode.FAILED_PRECONDITION, "has ended after 1 steps")
        episode.reset()  # a reset starts it over
        assert episode.step(esrp.Action.LEFT).truncated


def test_permission_denied(client: esrp.Client) -> None:
    with client.create_episode(split="test") as episode:
        with pytest.raises(esrp.PermissionDenied) as caught:
            episode.privileged_state()
        check(caught.value, grpc.StatusCode.PERMISSION_DENIED, "privileged = true")


def test_unauthenticated(strict_server: esrp.LocalServer) -> None:
    for token in (None, "wrong"):
        with strict_server.client(token=token) as anonymous, pytest.raises(esrp.Unauthenticated) as caught:
            anonymous.server_info()
        assert caught.value.code == grpc.StatusCode.UNAUTHENTICATED
        assert isinstance(caught.value.rpc_error, grpc.RpcError)
    with strict_server.client(token="s3cret") as allowed:
        assert allowed.server_info().limits.max_episodes == 2
    with pytest.raises(esrp.InvalidRequest, match="printable ASCII"):
        strict_server.client(token="bad\ntoken")


def test_server_busy(strict_server: esrp.LocalServer) -> None:
    with strict_server.client(token="s3cret") as client:
        with client.create_episode(split="test") as a, client.create_episode(split="test", seed=1) as b:
            with pytest.raises(esrp.ServerBusy) as caught:
                client.create_episode(split="test", seed=2)
            check(caught.value, grpc.StatusCode.RESOURCE_EXHAUSTED, "maximum of 2 live episodes")
            with pytest.raises(esrp.ServerBusy) as caught:
                client.step_batch([(a, 0), (b, 0), ("0" * 32, 0)])
            limit = "a batch of 3 steps and resets exceeds the limit of 2"
            check(caught.value, grpc.StatusCode.RESOURCE_EXHAUSTED, limit)
        assert client.server_info().live_episodes == 0


def test_server_unavailable() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    # Nothing listens there any more.
    with (
        esrp.Client(f"127.0.0.1:{port}", timeout=10) as client,
        pytest.raises(esrp.ServerUnavailable) as caught,
    ):
        client.server_info()
    assert caught.value.code == grpc.StatusCode.UNAVAILABLE
    assert isinstance(caught.value.__cause__, grpc.RpcError)
    with (
        esrp.Client(f"127.0.0.1:{port}") as client,
        pytest.raises(esrp.DeadlineExceeded, match="not healthy"),
    ):
        client.wait_healthy(timeout=0.3)


def test_deadline_exceeded() -> None:
    """A port that accepts connections and never speaks: the call's deadline passes."""
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(1)
        port = silent.getsockname()[1]
        with (
            esrp.Client(f"127.0.0.1:{port}", timeout=0.3) as client,
            pytest.raises(esrp.DeadlineExceeded) as caught,
        ):
            client.server_info()
    assert caught.value.code == grpc.StatusCode.DEADLINE_EXCEEDED
    assert isinstance(caught.value.__cause__, grpc.RpcError)


def test_cancelled(client: esrp.Client) -> None:
    before = client.server_info().live_episodes
    stream = client.episode_stream()
    stream.create(split="test")
    stream.cancel()
    with pytest.raises(esrp.Cancelled) as caught:
        stream.next()
    assert caught.value.code == grpc.StatusCode.CANCELLED
    assert isinstance(caught.value.rpc_error, grpc.RpcError)
    # The server closes what the cancelled stream created.
    assert settled_live_episodes(client, before) == before


def test_cancelled_async_stream(server: esrp.LocalServer, client: esrp.Client) -> None:
    before = client.server_info().live_episodes

    async def main() -> None:
        async with esrp.AsyncClient(server.address) as aclient:
            stream = await aclient.episode_stream()
            await stream.create(split="test")
            stream.cancel()
            stream.cancel()  # again: nothing more
            with pytest.raises(esrp.Cancelled) as caught:
                await stream.next()
            assert caught.value.code == grpc.StatusCode.CANCELLED
            with pytest.raises(esrp.ServerUnavailable, match="ended"):
                await stream.create(split="test")
            await stream.close()  # after a cancel: nothing to do

    asyncio.run(main())
    assert settled_live_episodes(client, before) == before


@pytest.mark.parametrize("transport", ["native", "grpcio"])
def test_abandoned_create_leaves_no_episode(
    server: esrp.LocalServer, transport: Literal["native", "grpcio"]
) -> None:
    """A create whose caller gives up is closed when its answer arrives (cancellation-safe)."""
    if transport == "native":
        pytest.importorskip("esrp_native", reason="the esrp-native package is not installed")
    with server.client(transport=transport) as client:
        before = client.server_info().live_episodes
        abandoned: list[esrp.DeadlineExceeded] = []
        for seed, timeout in enumerate([0, 0.0002, 0.0005, 0.001, 0.002, 0.005, 0]):
            try:
                client.create_episode(split="test", seed=seed, timeout=timeout).close()
            except esrp.DeadlineExceeded as error:
                abandoned.append(error)
        assert abandoned
        # Given up on the client side (no status): the call itself ran on.
        assert all(error.code is None for error in abandoned)
        assert settled_live_episodes(client, before) == before


def test_stream_errors_are_in_band(client: esrp.Client) -> None:
    with client.episode_stream() as stream:
        stream.create(split="test")
        created = stream.next()
        assert created is not None
        episode = created.created().episode_id
        stream.step(episode, 9)
        stream.step("f" * 32, 0)
        stream.step(episode, esrp.Action.LEFT)
        bad, missing, good = (stream.next() for _ in range(3))
        assert bad is not None
        assert isinstance(bad.error, esrp.InvalidRequest)
        assert bad.error.code == grpc.StatusCode.INVALID_ARGUMENT
        assert bad.error.rpc_error is None
        assert "unknown action code 9" in bad.error.message
        with pytest.raises(esrp.InvalidRequest):
            bad.step_result()
        assert missing is not None
        assert isinstance(missing.error, esrp.EpisodeNotFound)
        assert good is not None
        assert good.step_result().info.step_index == 1  # the stream went on


def test_local_server_that_does_not_start(tmp_path: Path) -> None:
    with pytest.raises(esrp.LocalServerError) as caught:
        esrp.LocalServer("--no-such-flag").start()
    assert "did not start" in caught.value.message
    assert "--no-such-flag" in caught.value.message  # the tail of its stderr says why
    with pytest.raises(esrp.LocalServerError, match="cannot start") as caught:
        esrp.LocalServer(binary=tmp_path / "missing").start()
    assert "pip install 'esrp[server]'" in caught.value.message  # it says what to do


def test_error_mapping_covers_every_code() -> None:
    from esrp._errors import from_status

    expected = {
        grpc.StatusCode.INVALID_ARGUMENT: esrp.InvalidRequest,
        grpc.StatusCode.OUT_OF_RANGE: esrp.InvalidRequest,
        grpc.StatusCode.NOT_FOUND: esrp.EpisodeNotFound,
        grpc.StatusCode.FAILED_PRECONDITION: esrp.EpisodeEnded,
        grpc.StatusCode.RESOURCE_EXHAUSTED: esrp.ServerBusy,
        grpc.StatusCode.UNAUTHENTICATED: esrp.Unauthenticated,
        grpc.StatusCode.PERMISSION_DENIED: esrp.PermissionDenied,
        grpc.StatusCode.UNAVAILABLE: esrp.ServerUnavailable,
        grpc.StatusCode.DEADLINE_EXCEEDED: esrp.DeadlineExceeded,
        grpc.StatusCode.CANCELLED: esrp.Cancelled,
        grpc.StatusCode.INTERNAL: esrp.ServerError,
        grpc.StatusCode.UNKNOWN: esrp.ServerError,
    }
    for code, kind in expected.items():
        error = from_status(code.value[0], "message")
        assert type(error) is kind
        assert error.code == code
    assert type(from_status(5, 'no scene "x" in the served dataset')) is esrp.SceneNotFound


@pytest.mark.parametrize("transport", ["native", "grpcio"])
def test_timeouts_mean_the_same_on_both_transports(
    server: esrp.LocalServer, transport: Literal["native", "grpcio"]
) -> None:
    if transport == "native" and not esrp._native.available():
        pytest.skip("esrp-native is not installed")
    with (
        esrp.Client(server.address, transport=transport) as client,
        client.create_episode(split="test") as episode,
    ):
        # 0: no time for the call, which fails unsent; infinity and beyond years: no deadline.
        client.timeout = 0
        with pytest.raises(esrp.DeadlineExceeded, match="not sent"):
            episode.step(esrp.Action.LEFT)
        with pytest.raises(esrp.DeadlineExceeded):
            client.server_info()
        for none in (float("inf"), 1e10):
            client.timeout = none
            assert client.timeout is None
            episode.step(esrp.Action.LEFT)
        for bad in (-1, float("nan"), True, "1"):
            with pytest.raises(ValueError, match="timeout must be None or"):
                client.timeout = bad  # type: ignore[assignment]
        client.timeout = None
        with pytest.raises(ValueError, match="non-negative"):
            client.wait_healthy(float("nan"))
        with pytest.raises(ValueError, match="timeout must be None or"):
            esrp.Client(server.address, transport=transport, timeout=-1)
    with pytest.raises(ValueError, match="timeout must be None or"):
        esrp.AsyncClient(server.address, timeout=float("nan"))


def test_addresses_that_name_no_server_are_refused_up_front() -> None:
    for bad in ("127.0.0.1:70000", "127.0.0.1:-1", "host:port", "", "  ", "http://", "https://"):
        with pytest.raises(ValueError, match="port|names no server"):
            esrp.Client(bad)
        with pytest.raises(ValueError, match="port|names no server"):
            esrp.AsyncClient(bad)
    for wrong in (None, 50051):
        with pytest.raises(TypeError, match="a string"):
            esrp.Client(wrong)  # type: ignore[arg-type]
    for good in (
        "127.0.0.1:0",
        "127.0.0.1:65535",
        "[::1]:50051",
        "unix:/tmp/x.sock",
        "dns:///localhost:50051",
    ):
        esrp.Client(good, transport="grpcio").close()


def test_an_ipv6_address_with_a_port_is_refused_without_its_brackets(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`::1:50051` is read by gRPC as one host name, on port 443 (`Misformatted domain name` on the
    first call, or another address's port 443): refused at once, saying how to write it."""
    for bare, written in (
        ("::1:50051", "[::1]:50051"),
        ("http://::1:50051", "http://[::1]:50051"),
        ("https://2001:db8::7:443/", "https://[2001:db8::7]:443"),
        ("fe80::1%eth0:8080", "[fe80::1%eth0]:8080"),
        ("::ffff:127.0.0.1:50051", "[::ffff:127.0.0.1]:50051"),
    ):
        for client in (esrp.Client, esrp.AsyncClient):
            with pytest.raises(ValueError, match=f"in brackets, {re.escape(written)}"):
                client(bare)
    # `::1:8080` is also an address on port 443: the message says how to write either.
    with pytest.raises(ValueError, match=re.escape("[::1]:8080 ([::1:8080] for the address ::1:8080")):
        esrp.Client("::1:8080")
    for good in (
        "[::1]:50051",
        "http://[::1]:50051",
        "::1",
        "[::1:8080]",
        "unix:/tmp/a:b:1",
        "localhost:50051",
    ):
        esrp.Client(good, transport="grpcio").close()
    # The commands' --server likewise, in argparse's one line.
    with pytest.raises(SystemExit) as exit_info:
        esrp_main(["eval", "--agent", "random", "--out", "x.jsonl", "--server", "::1:50051"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "argument --server: address '::1:50051': write an IPv6 address with a port in brackets, " in err
    assert "[::1]:50051; without them gRPC reads it all as the host" in err
    assert err.count("\n") == 1, err


def test_create_arguments_the_request_cannot_carry_are_named(client: esrp.Client) -> None:
    refused: list[tuple[dict[str, object], type[Exception], str]] = [
        ({"scene": ""}, ValueError, "scene: an empty scene id"),
        ({"scene": 5}, TypeError, "scene: a string"),
        ({"seed": -1}, ValueError, "seed: an integer from 0"),
        ({"seed": "1"}, TypeError, "seed: an integer"),
        ({"horizon": -1}, ValueError, "horizon: an integer from 0"),
        ({"sensors": {"bogus": 1}}, ValueError, "sensors: unknown fields"),
        ({"sensors": "x"}, TypeError, "sensors: a Sensors or a mapping"),
        ({"sensors": esrp.Sensors(resolution=-5)}, ValueError, "sensors.resolution"),
        ({"agent": 5}, TypeError, "agent: a string"),
        ({"reward": [1.0]}, TypeError, "reward: a RewardWeights or a mapping"),
    ]
    before = client.server_info().live_episodes
    for arguments, kind, message in refused:
        with pytest.raises(kind, match=message):
            client.create_episode(**arguments)  # type: ignore[arg-type]
    assert client.server_info().live_episodes == before  # nothing was sent
    for bad_size in (-1, 2.5, True):
        with pytest.raises(ValueError, match="page_size"):
            client.scenes("test", page_size=bad_size)  # type: ignore[arg-type]
    with client.episode_stream() as stream, pytest.raises(ValueError, match="empty scene id"):
        stream.create("")
    with pytest.raises(ValueError, match="empty scene id"):
        RearrangeEnv(client=client, scene="")
    # A mapping of the fields is a Sensors (as the envs take it), and a second close answers again.
    episode = client.create_episode(split="test", sensors={"resolution": 32})
    assert episode.observation is not None
    assert episode.observation.ego_rgb.shape == (32, 32, 3)
    episode.step(esrp.Action.LEFT)
    first = episode.close()
    assert episode.close() == first
    assert first.steps == 1


@pytest.mark.parametrize("transport", ["native", "grpcio"])
def test_a_closed_client_refuses_every_call_alike(
    server: esrp.LocalServer, transport: Literal["native", "grpcio"]
) -> None:
    if transport == "native" and not esrp._native.available():
        pytest.skip("esrp-native is not installed")
    client = esrp.Client(server.address, transport=transport)
    episode = client.create_episode(split="test")
    client.close()
    calls = [
        client.server_info,
        lambda: client.create_episode(split="test"),
        client.episode_stream,
        client.wait_healthy,
        lambda: episode.step(esrp.Action.LEFT),
        lambda: client.step_batch([(episode, esrp.Action.LEFT)]),
        episode.close,
    ]
    for call in calls:
        with pytest.raises(esrp.Cancelled, match="the client is closed"):
            call()
    client.close()  # again: nothing more
    with client.episode(episode.id):
        pass  # its exit cannot close it now: the server reaps it when idle

    async def closed_async() -> None:
        aclient = esrp.AsyncClient(server.address)
        await aclient.close()
        with pytest.raises(esrp.Cancelled, match="the client is closed"):
            await aclient.server_info()
        with pytest.raises(esrp.Cancelled, match="the client is closed"):
            await aclient.create_episode(split="test")

    asyncio.run(closed_async())
    with esrp.Client(server.address) as other:
        other.episode(episode.id).close()
