"""The I/O-free halves of the sync and async clients (esrp._base, esrp._common): the calls they
build and how they read the answers, checked without a server."""

from __future__ import annotations

import asyncio
from typing import Any, cast

import pytest

import esrp
from esrp._base import HealthPolls, ScenePages, StepWave, abandoning, step_batch_call
from esrp._common import StreamLedger, run_rounds
from esrp.v1 import esrp_pb2 as pb


def test_a_run_interleaves_the_episodes_round_by_round() -> None:
    plans = {"a": [1, 2, 3], "b": [4], "c": [5, 6]}
    assert list(run_rounds(plans)) == [[("a", 1), ("b", 4), ("c", 5)], [("a", 2), ("c", 6)], [("a", 3)]]
    assert list(run_rounds({})) == []


def test_a_run_waits_for_earlier_answers_to_be_read() -> None:
    ledger = StreamLedger(window=2)
    assert ledger.run_results({"a": [1], "b": []}) == {"a": [], "b": []}
    ledger.request(esrp.RequestKind.STEP, "a")
    assert ledger.unread
    assert ledger.take_ready() is None
    with pytest.raises(esrp.EsrpError, match="before a run"):
        ledger.run_results({"a": [1]})


def test_health_polls_check_within_the_time_and_pause_50_ms() -> None:
    now = [100.0]
    polls = HealthPolls("127.0.0.1:1", 2.5, lambda: now[0])
    assert polls.next_check() == 1.0
    assert polls.pause() == 0.05
    now[0] = 102.0
    assert polls.next_check() == pytest.approx(0.5)
    now[0] = 102.49
    assert polls.pause() == pytest.approx(0.01)
    now[0] = 102.5
    assert polls.pause() == 0
    with pytest.raises(
        esrp.DeadlineExceeded, match=r"the server at 127.0.0.1:1 was not healthy within 2.5 s"
    ):
        polls.next_check()


def test_a_create_is_abandoned_only_when_its_caller_gives_up() -> None:
    abandoned: list[str] = []
    timeout = pytest.raises(esrp.DeadlineExceeded, match="no answer to CreateEpisode within 0.5 s")
    with timeout as caught, abandoning(lambda: abandoned.append("timeout"), 0.5):
        raise TimeoutError
    assert caught.value.__suppress_context__
    with pytest.raises(esrp.DeadlineExceeded), abandoning(lambda: abandoned.append("asyncio"), 1):
        raise asyncio.TimeoutError
    with pytest.raises(KeyboardInterrupt), abandoning(lambda: abandoned.append("interrupt"), None):
        raise KeyboardInterrupt
    with pytest.raises(asyncio.CancelledError), abandoning(lambda: abandoned.append("cancelled"), None):
        raise asyncio.CancelledError
    # The server answered with an error: there is no episode to close.
    with pytest.raises(esrp.ServerBusy), abandoning(lambda: abandoned.append("busy"), None):
        raise esrp.ServerBusy("too many episodes")
    with abandoning(lambda: abandoned.append("answered"), None):
        pass
    assert abandoned == ["timeout", "asyncio", "interrupt", "cancelled"]


def test_scene_pages_follow_the_page_tokens() -> None:
    pages = ScenePages("test", "easy", 2)
    first = pages.next_call()
    assert first is not None
    assert first.method == "ListScenes"
    assert isinstance(first.request, pb.ListScenesRequest)
    assert (first.request.split, first.request.difficulty, first.request.page_size) == (
        pb.SPLIT_TEST,
        pb.DIFFICULTY_EASY,
        2,
    )
    page = pb.ListScenesResponse(
        scenes=[pb.SceneSummary(id="s/1"), pb.SceneSummary(id="s/2")], next_page_token="t"
    )
    assert [scene.id for scene in first.value(page)] == ["s/1", "s/2"]
    second = pages.next_call()
    assert second is not None
    assert isinstance(second.request, pb.ListScenesRequest)
    assert second.request.page_token == "t"
    assert [
        scene.id for scene in second.value(pb.ListScenesResponse(scenes=[pb.SceneSummary(id="s/3")]))
    ] == ["s/3"]
    assert pages.next_call() is None
    with pytest.raises(esrp.InvalidRequest, match="unknown split"):
        ScenePages("nowhere", None, 0)


def test_a_step_wave_without_steps_or_resets_sends_nothing() -> None:
    sensors = esrp.Sensors(resolution=32)
    empty = StepWave([], [], sensors, [])
    assert empty.empty
    assert empty.columns.rewards == []
    wave = StepWave(["a", "b", "c"], [0, 1, 2], sensors, [("d", None)])
    assert not wave.empty
    assert [(len(r.steps), len(r.resets)) for r in wave.requests(2)] == [(2, 0), (1, 0), (0, 1)]


def test_a_step_batch_call_names_a_bad_action_and_counts_the_answers() -> None:
    with pytest.raises(esrp.InvalidRequest, match=r"steps\[1\]"):
        step_batch_call([("a", 0), ("b", cast(Any, "left"))], include_goal=False)
    call = step_batch_call([("a", 0), ("b", 1)], include_goal=True)
    assert isinstance(call.request, pb.StepBatchRequest)
    assert (call.method, [s.include_goal for s in call.request.steps]) == ("StepBatch", [True, True])
    with pytest.raises(esrp.ProtocolError, match="1 answers to a batch of 2 steps"):
        call.value(pb.StepBatchResponse(responses=[pb.StepResponse()]))
