"""Abandoned creates from a stock gRPC client leave nothing (the server's claim rule,
`--claim-timeout-seconds`): the plain grpcio stubs the package ships, without the client's
cancellation-safe wrapper, give up on creates of unbuilt scenes at deadlines of 20 and 3 ms (or
take the answers of those the server made in time, and never name them); once the claim timeout
has passed, no episode is left. Episodes whose client uses them are never cut by it."""

from __future__ import annotations

import time
from collections.abc import Iterator

import grpc
import pytest

import esrp
from esrp.v1 import esrp_pb2 as pb
from esrp.v1 import esrp_pb2_grpc as pb_grpc

CLAIM = 3  # seconds: the claim timeout of the server of these tests


@pytest.fixture(scope="module")
def claiming() -> Iterator[esrp.LocalServer]:
    """A server that closes unclaimed episodes after CLAIM seconds (and never idle ones)."""
    with esrp.LocalServer("--claim-timeout-seconds", str(CLAIM), "--idle-timeout-seconds", "0") as server:
        yield server


def _live(stub: pb_grpc.EsrpStub) -> int:
    return stub.ServerInfo(pb.ServerInfoRequest(), timeout=10).live_episodes


def _wait_for_live(stub: pb_grpc.EsrpStub, expected: int, timeout: float) -> int:
    deadline = time.monotonic() + timeout
    live = _live(stub)
    while live != expected and time.monotonic() < deadline:
        time.sleep(0.2)
        live = _live(stub)
    return live


def test_abandoned_creates_of_a_stock_client_leave_nothing(claiming: esrp.LocalServer) -> None:
    # Answers of any size are taken: a create a fast server answers in time (the 512 px sensors'
    # answer is over grpcio's 4 MiB default) is one whose client took its id and never named it.
    options = [("grpc.max_receive_message_length", -1)]
    with grpc.insecure_channel(claiming.address, options=options) as channel:
        stub = pb_grpc.EsrpStub(channel)
        scenes = [
            s.id for s in stub.ListScenes(pb.ListScenesRequest(split=pb.SPLIT_TRAIN, page_size=1000)).scenes
        ]
        assert _live(stub) == 0
        sensors = [
            pb.Sensors(resolution=128),
            pb.Sensors(resolution=512, ego_depth=True, ego_segmentation=True, current_top_down=True),
        ]
        codes = []
        # Unbuilt scenes (far into the train split, which no other test of this server uses).
        for index, scene in enumerate(scenes[-60:]):
            request = pb.CreateEpisodeRequest(scene_id=scene, sensors=sensors[index % 2])
            try:
                # Deadlines of 20 ms and of 3 ms in turn: a release server (its scenes read from
                # the built-in pack) makes most 128 px creates within 20 ms.
                stub.CreateEpisode(request, timeout=0.02 if index % 4 < 2 else 0.003)
            except grpc.RpcError as error:
                codes.append(error.code())
        assert set(codes) <= {grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.CANCELLED}, codes
        # A debug server answers none of them in time, a release one most of those given 20 ms.
        assert len(codes) >= 10, "creates of unbuilt scenes outlast their deadlines"
        # Whatever was created lives at most the claim timeout (plus the reaper's tick of 1 s).
        assert _wait_for_live(stub, 0, CLAIM + 15) == 0


def test_episodes_of_a_client_that_vanished_after_creating_them_are_closed(
    claiming: esrp.LocalServer,
) -> None:
    # The server cannot tell this client from one whose create answer never arrived: it got ids,
    # and went away without naming them again.
    with grpc.insecure_channel(claiming.address) as channel:
        stub = pb_grpc.EsrpStub(channel)
        scene = stub.ListScenes(pb.ListScenesRequest(split=pb.SPLIT_TEST, page_size=1)).scenes[0].id
        before = _live(stub)
        for _ in range(5):
            stub.CreateEpisode(pb.CreateEpisodeRequest(scene_id=scene), timeout=60)
        assert _live(stub) == before + 5
        assert _wait_for_live(stub, 0, CLAIM + 15) == 0


def test_an_episode_first_used_late_in_its_claim_time_lives_on(claiming: esrp.LocalServer) -> None:
    with grpc.insecure_channel(claiming.address) as channel:
        stub = pb_grpc.EsrpStub(channel)
        scene = stub.ListScenes(pb.ListScenesRequest(split=pb.SPLIT_TEST, page_size=1)).scenes[0].id
        created = stub.CreateEpisode(pb.CreateEpisodeRequest(scene_id=scene), timeout=60)
        time.sleep(0.9 * CLAIM)
        stub.Step(pb.StepRequest(episode_id=created.episode_id, action=2), timeout=30)
        time.sleep(CLAIM + 2)  # past the claim timeout: claimed episodes stay
        stub.Step(pb.StepRequest(episode_id=created.episode_id, action=2), timeout=30)
        stub.CloseEpisode(pb.CloseEpisodeRequest(episode_id=created.episode_id), timeout=30)


def test_an_episode_created_on_a_stream_lives_while_the_stream_is_open(claiming: esrp.LocalServer) -> None:
    with claiming.client() as client:
        stub = pb_grpc.EsrpStub(client.channel)
        scene = next(iter(client.scenes("test", page_size=1))).id
        with client.episode_stream() as stream:
            stream.create(scene)
            answer = stream.next()
            assert answer is not None
            episode = answer.created().episode_id
            time.sleep(CLAIM + 2)  # the stream never names it: it holds it
            assert _live(stub) == 1
            stream.step(episode, esrp.Action.LEFT)
            assert stream.next() is not None
        assert _wait_for_live(stub, 0, 10) == 0
