"""The native transport (the esrp-native package): the same answers and errors as grpcio's."""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import esrp
from esrp import _native
from esrp.envs import RearrangeEnv, RearrangeVectorEnv

pytest.importorskip("esrp_native", reason="the esrp-native package is not installed")

ACTIONS = [0, 4, 2, 0, 0, 5, 3, 1, 4, 0, 2, 2, 5, 0, 1]


def test_auto_picks_the_native_transport(server: esrp.LocalServer) -> None:
    with server.client() as auto, server.client(transport="grpcio") as plain:
        assert auto.transport == "native"
        assert plain.transport == "grpcio"
    with pytest.raises(ValueError, match="transport"):
        esrp.Client(server.address, transport="carrier-pigeon")  # type: ignore[arg-type]


def test_native_refuses_tls(tmp_path: Path) -> None:
    pem = b"-----BEGIN CERTIFICATE-----\n-----END CERTIFICATE-----\n"
    with pytest.raises(ValueError, match="plain HTTP/2"):
        esrp.Client("127.0.0.1:1", tls=pem, transport="native")
    # auto falls back to grpcio for a TLS channel.
    with esrp.Client("127.0.0.1:1", tls=pem) as client:
        assert client.transport == "grpcio"


def test_the_same_answers_as_grpcio(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    sensors = esrp.Sensors(depth=True, segmentation=True, current_top_down=True, resolution=32)
    answers: dict[str, list[object]] = {}
    for transport in ("native", "grpcio"):
        with server.client(transport=transport) as client:
            seen: list[object] = []
            with client.create_episode(easy_scenes[0], sensors=sensors, horizon=10) as episode:
                for action in ACTIONS[:10]:
                    result = episode.step(action, include_goal=action == 0)
                    seen.append(result)
                with pytest.raises(esrp.EpisodeEnded):
                    episode.step(0)
                seen.append(episode.reset())
                seen.append(episode.reset(easy_scenes[1]))
                other = client.create_episode(easy_scenes[2], sensors=sensors)
                with other:
                    for action in ACTIONS[:5]:
                        seen.append(client.step_batch([(episode, action), (other, (action + 1) % 6)]))
            answers[transport] = seen
    native, grpcio = answers["native"], answers["grpcio"]
    assert len(native) == len(grpcio) == 17
    for a, b in zip(native, grpcio, strict=True):
        assert _plain(a) == _plain(b)


def _plain(value: object) -> object:
    """`value` with its arrays as (dtype, shape, bytes), for comparing whole results; arrays of
    Python objects (the vector env's `scene_id` and `room_type` infos) as their items, since their
    bytes are the objects' addresses."""
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            return (str(value.dtype), value.shape, [_plain(item) for item in value.tolist()])
        return (str(value.dtype), value.shape, value.tobytes())
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if hasattr(value, "__dataclass_fields__"):
        return {name: _plain(getattr(value, name)) for name in value.__dataclass_fields__}
    return value


UNARY = (
    "ServerInfo",
    "DescribeDataset",
    "ListScenes",
    "CreateEpisode",
    "Reset",
    "Step",
    "StepBatch",
    "GetGoal",
    "GetPrivilegedState",
    "GetMetrics",
    "CloseEpisode",
    "PlanActions",
)


def _every_unary_call(client: esrp.Client, scene: str, *, hot: bool = True) -> list[object]:
    """One call of each unary method (with `hot=False`, of each but Step, Reset and StepBatch),
    through the typed API; their answers (the live-episode count, which other tests change
    meanwhile, left out)."""
    info = client.server_info()
    seen: list[object] = [dataclasses.replace(info, live_episodes=0), client.describe_dataset()]
    seen.append(list(itertools.islice(client.scenes("test", "easy", page_size=2), 5)))
    episode = client.create_episode(scene, privileged=True, horizon=40)
    seen.append(episode.observation)
    if hot:
        seen += [episode.step(esrp.Action.LEFT), client.step_batch([(episode, esrp.Action.RIGHT)])]
        seen.append(episode.reset())
    seen += [episode.goal(), episode.privileged_state(), episode.metrics()]
    plan = episode.plan_actions(max_actions=5)  # its stats hold times: left out
    seen += [(plan.actions, plan.reaches_success, plan.plan_length, plan.failure), episode.close()]
    return seen


def test_each_call_goes_on_its_transport(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    hot = ["Reset", "Step", "StepBatch"]
    with server.client(transport="native") as client, server.client(transport="grpcio") as plain:
        carried = [method for method in UNARY if client._calls.transport(method) == "native"]  # noqa: SLF001
        assert carried == hot
        assert [plain._calls.transport(method) for method in UNARY] == ["grpcio"] * len(UNARY)  # noqa: SLF001
        native, grpcio = (_every_unary_call(c, easy_scenes[3]) for c in (client, plain))
        assert _plain(native) == _plain(grpcio)
        # With its native channel alone closed, the hot path fails and the rest (grpcio's) goes
        # on: each call went where it was said to.
        channel = client._calls._native  # noqa: SLF001
        assert channel is not None
        channel.close()
        episode = client.create_episode(easy_scenes[3], privileged=True)
        for call in (episode.reset, lambda: episode.step(0), lambda: client.step_batch([(episode, 0)])):
            with pytest.raises(esrp.EsrpError, match="the channel is closed"):
                call()
        assert len(_every_unary_call(client, easy_scenes[3], hot=False)) == 9
        assert episode.metrics().metrics.steps == 0
        assert episode.close().steps == 0


def test_errors_are_the_same_classes(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    with server.client(transport="native") as client:
        episode = client.create_episode(easy_scenes[0])
        with pytest.raises(esrp.InvalidRequest):
            client.step_batch([(episode, 0), (episode, 1)])  # one step per episode
        episode.close()
        with pytest.raises(esrp.EpisodeNotFound, match="no episode"):
            episode.step(esrp.Action.LEFT)
        with pytest.raises(esrp.EpisodeNotFound):
            episode.reset()
    with server.client(transport="native", timeout=1e-6) as hurried, server.client() as slow:
        episode = slow.create_episode(easy_scenes[0])
        attached = hurried.episode(episode.id)
        with pytest.raises(esrp.DeadlineExceeded):
            attached.step(esrp.Action.LEFT)
        episode.close()
    nowhere = esrp.Client("127.0.0.1:1", transport="native", timeout=5)
    with nowhere, pytest.raises(esrp.ServerUnavailable):
        nowhere.episode("x").step(esrp.Action.LEFT)


def test_the_token_goes_with_every_call() -> None:
    with (
        esrp.LocalServer("--token", "s3cret") as server,
        server.client(token="s3cret", transport="native") as client,
        client.create_episode(split="test") as episode,
    ):
        assert episode.step(esrp.Action.LEFT).info.step_index == 1
        intruder = server.client(token="wrong", transport="native")
        with intruder, pytest.raises(esrp.Unauthenticated):
            intruder.episode(episode.id).step(esrp.Action.LEFT)


def test_threads_share_one_native_client(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    # Four threads step four episodes through one client at once; each must see exactly what a
    # lone grpcio client sees for its actions.
    def play(client: esrp.Client, scene: str) -> list[bytes]:
        seen = []
        with client.create_episode(scene, horizon=100) as episode:
            for action in ACTIONS:
                result = episode.step(action)
                seen.append(result.observation.ego_rgb.tobytes())
                if result.ended:
                    break
        return seen

    with server.client(transport="grpcio") as plain:
        expected = [play(plain, scene) for scene in easy_scenes[:4]]
    got: list[list[bytes] | BaseException] = [[] for _ in range(4)]
    with server.client(transport="native") as shared:

        def run(index: int) -> None:
            try:
                got[index] = play(shared, easy_scenes[index])
            except BaseException as error:  # noqa: BLE001 - reported by the assertion below
                got[index] = error

        threads = [threading.Thread(target=run, args=(i,)) for i in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60)
    assert got == expected


def test_envs_are_bit_identical_on_both_transports(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    runs = {}
    for transport in ("native", "grpcio"):
        with server.client(transport=transport) as client:
            env = RearrangeEnv(client=client, scene=easy_scenes[:3], horizon=6)
            envs = RearrangeVectorEnv(3, client=client, scene=easy_scenes[:3], horizon=6)
            try:
                seen: list[tuple[object, ...]] = [env.reset(seed=7), envs.reset(seed=7)]
                for action in ACTIONS:
                    step = env.step(action)
                    seen.append(step)
                    if step[2] or step[3]:
                        seen.append(env.reset())
                    seen.append(envs.step(np.array([action, (action + 2) % 6, 5])))
            finally:
                env.close()
                envs.close()
            runs[transport] = _plain(seen)
    assert runs["native"] == runs["grpcio"]


def test_resolve() -> None:
    assert _native.resolve("grpcio", secure=False) == "grpcio"
    assert _native.resolve("auto", secure=True) == "grpcio"
    assert _native.resolve("native", secure=False) == "native"
    # The native channel reaches host:port and unix:PATH; other gRPC target forms are grpcio's.
    assert _native.url("127.0.0.1:50051") == "http://127.0.0.1:50051"
    assert _native.url("unix:/tmp/esrp.sock") == "unix:/tmp/esrp.sock"
    assert _native.url("unix:///tmp/esrp.sock") == "unix:///tmp/esrp.sock"
    for other in ("dns:///localhost:50051", "unix-abstract:esrp", "vsock:3:50051", "ipv4:127.0.0.1:50051"):
        assert _native.url(other) is None
        assert _native.resolve("auto", secure=False, address=other) == "grpcio"
        with pytest.raises(ValueError, match="transport='grpcio'"):
            _native.resolve("native", secure=False, address=other)
    assert _native.resolve("native", secure=False, address="unix:/tmp/esrp.sock") == "native"


def test_answers_are_parsed_in_place(server: esrp.LocalServer, easy_scenes: list[str]) -> None:
    """`Channel.unary(..., response=cls)` parses the answer from the received bytes with protobuf:
    the same message as parsing the `bytes` it returns without; nothing but a message class is
    let near the received memory.
    """
    import esrp_native

    from esrp.v1 import esrp_pb2 as pb

    channel = esrp_native.Channel(f"http://{server.address}")
    with server.client(transport="grpcio") as client, client.create_episode(easy_scenes[0]) as episode:
        request = pb.StepRequest(episode_id=episode.id, action=int(esrp.Action.LEFT)).SerializeToString()
        raw = channel.unary("/esrp.v1.Esrp/Step", request)
        assert isinstance(raw, bytes)
        parsed = channel.unary("/esrp.v1.Esrp/Step", request, None, pb.StepResponse)
        assert isinstance(parsed, pb.StepResponse)
        answers = [pb.StepResponse.FromString(raw), parsed]
        # Two left turns: the step index counts up, each answer carries its 128x128 RGB image.
        assert [a.info.step_index for a in answers] == [1, 2]
        assert [len(a.observation.ego_rgb.data) for a in answers] == [128 * 128 * 3] * 2
        assert answers[1].observation.ego_rgb.data != answers[0].observation.ego_rgb.data
        not_messages: list[Any] = [bytes, memoryview, pb.StepResponse.FromString]
        for not_a_message in not_messages:
            with pytest.raises(TypeError, match="protobuf message class|cast as .type"):
                channel.unary("/esrp.v1.Esrp/Step", request, None, not_a_message)
        # Refused before anything was sent: the episode is still at step 2.
        assert client.episode(episode.id).step(esrp.Action.LEFT).info.step_index == 3
    channel.close()


def test_unary_all_makes_calls_on_several_channels_at_once(
    server: esrp.LocalServer, easy_scenes: list[str]
) -> None:
    """`esrp_native.unary_all` answers each call in order, as `Channel.unary` would, over
    different channels (here two servers); a call that fails comes back as its `CallError`
    without hiding the others' answers, and `run_all` raises it as the client's error kind.
    """
    import esrp_native

    from esrp._transport import run_all
    from esrp.v1 import esrp_pb2 as pb

    path = "/esrp.v1.Esrp/StepBatch"
    with (
        esrp.LocalServer(unix_socket=True) as other,
        server.client(transport="native") as first,
        other.client(transport="native") as second,
        server.client(transport="grpcio") as reference,
    ):
        episodes = [first.create_episode(easy_scenes[0]), second.create_episode(easy_scenes[0])]
        expected_episode = reference.create_episode(easy_scenes[0])
        expected = reference.step_batch([(expected_episode, esrp.Action.LEFT)])[0]

        def request(episode: esrp.Episode, action: int) -> pb.StepBatchRequest:
            return pb.StepBatchRequest(steps=[pb.StepRequest(episode_id=episode.id, action=action)])

        missing = pb.StepBatchRequest(steps=[pb.StepRequest(episode_id="nope")])
        channels = [esrp_native.Channel(f"http://{server.address}"), esrp_native.Channel(other.address)]
        calls = [
            (channels[0], path, request(episodes[0], 2).SerializeToString(), None),
            (channels[1], path, request(episodes[1], 2).SerializeToString(), 30.0),
            (
                channels[1],
                path,
                pb.StepBatchRequest(steps=[pb.StepRequest(episode_id="nope")]).SerializeToString(),
                None,
            ),
        ]
        answers = esrp_native.unary_all(calls, pb.StepBatchResponse)
        assert [type(a) for a in answers[:2]] == [pb.StepBatchResponse] * 2
        assert answers[0].responses[0].observation.ego_rgb.data == expected.observation.ego_rgb.tobytes()
        assert answers[0] == answers[1]  # the same scene and action on either server
        assert isinstance(answers[2], esrp_native.CallError)
        assert "no episode" in answers[2].args[1]
        assert esrp_native.unary_all([], pb.StepBatchResponse) == []
        raw = esrp_native.unary_all(calls[:1])
        assert isinstance(raw[0], bytes)
        assert pb.StepBatchResponse.FromString(raw[0]).responses[0].info.step_index == 2
        with pytest.raises(TypeError, match="protobuf message class"):
            esrp_native.unary_all(calls[:1], bytes)  # type: ignore[arg-type]
        # Through the client's transport: the answers in order, or the first failure's error kind.
        made = run_all(
            "StepBatch",
            [(first._calls, request(episodes[0], 3)), (second._calls, request(episodes[1], 3))],  # noqa: SLF001
        )
        assert [a.responses[0].info.step_index for a in made] == [3, 2]
        with pytest.raises(esrp.EpisodeNotFound):
            run_all(
                "StepBatch",
                [
                    (first._calls, missing),  # noqa: SLF001
                    (second._calls, request(episodes[1], 3)),  # noqa: SLF001
                ],
            )
        # The second call ran all the same: its episode moved.
        assert second.episode(episodes[1].id).metrics().metrics.steps == 3
        channels[1].close()
        with pytest.raises(esrp_native.CallError, match="closed"):
            esrp_native.unary_all(calls[1:2], pb.StepBatchResponse)
        for episode in episodes:
            episode.close()
        expected_episode.close()


def test_a_closed_native_client_leaves_no_connection_open(easy_scenes: list[str]) -> None:
    # A server that stops drains its connections for up to its grace (here a minute): a closed
    # client's connection must be gone at once, not when Python collects the channel.
    server = esrp.LocalServer("--shutdown-grace-ms", "60000", "--no-generate-ahead", stop_timeout=120)
    with server:
        client = esrp.Client(server.address, transport="native")
        with client.create_episode(easy_scenes[0]) as episode:
            episode.step(esrp.Action.LEFT)
        client.close()
        with pytest.raises(esrp.Cancelled, match="closed"):
            client.server_info()
        stopping = time.monotonic()
    assert time.monotonic() - stopping < 20, "the server waited for the closed client's connection"


def test_a_server_that_dies_under_calls_is_unavailable(easy_scenes: list[str]) -> None:
    # tonic reports a connection broken under a call in flight as UNKNOWN "transport error";
    # grpcio, and so every transport of this client, as UNAVAILABLE: ServerUnavailable.
    import os
    import signal

    server = esrp.LocalServer("--no-generate-ahead", unix_socket=False)
    errors: list[BaseException] = []
    with server, server.client(transport="native") as client:
        episodes = [client.create_episode(easy_scenes[0]) for _ in range(4)]

        def steps(episode: esrp.Episode) -> None:
            try:
                while True:
                    if episode.step(esrp.Action.LEFT).ended:
                        episode.reset()
            except Exception as error:  # noqa: BLE001 - what the test looks at
                errors.append(error)

        threads = [threading.Thread(target=steps, args=(e,)) for e in episodes]
        for thread in threads:
            thread.start()
        time.sleep(0.3)
        os.kill(server.pid, signal.SIGKILL)
        for thread in threads:
            thread.join(30)
    assert len(errors) == 4
    for error in errors:
        assert isinstance(error, esrp.ServerUnavailable), repr(error)
