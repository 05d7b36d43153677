"""ESRP-VLM (`esrp eval --agent vlm`) without a model: a fake OpenAI-compatible server answers from a
script and checks what it gets — two PNG images that are exactly the episode's ego view and goal
image, the grasp flag and the action history — against a parallel episode of the same scene on the
real server. A "model" that answers with the scene's expert trajectory solves it; malformed
answers are asked again and counted; 429 and 500 are retried; traces are written and overwritten."""

from __future__ import annotations

import asyncio
import hashlib
import json
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fake_openai import FakeServer, Reply, Request, fake_openai

import esrp
import esrp.agents.vlm
from esrp.agents import is_async_agent
from esrp.agents.vlm import (
    ACTION_NAMES,
    VlmAgentFactory,
    VlmSettings,
    default_trace_dir,
    encode_png,
    parse_answer,
    trace_file_name,
)
from esrp.cli import main
from esrp.eval.evaluation import expert_trajectory
from esrp.eval.results import read_records

# ---------------------------------------------------------------------------------------------
# Parsing and settings


PARSE_CASES: list[tuple[str, str, str | None, str | None]] = [
    # (answer, constrained mode, the action it gives, or the kind of error)
    ("Thought: the chair is ahead.\nAction: move_forward", "none", "move_forward", None),
    ("Thought: turn.\nAction: 3", "none", "turn_right", None),
    ("**Thought:** go\n**Action:** `fetch`", "none", "fetch", None),
    ("Thought: x\nAction: Turn left.", "none", "turn_left", None),
    ("Thought: x\nAction: 2 (turn_left)", "none", "turn_left", None),
    ("action: RELEASE", "none", "release", None),
    ("<think>long musing</think>\nThought: x\nAction: move_backward", "none", "move_backward", None),
    ("turn_right", "none", "turn_right", None),
    ("", "none", None, "empty"),
    ("I would move forward and then fetch.", "none", None, "no_action"),
    ("Thought: x\nAction: move_forward\nAction: turn_left", "none", None, "several_actions"),
    ("Thought: x\nAction: move_forward, then turn_left", "none", None, "not_one_action"),
    ("Thought: x\nAction: 2 (fetch)", "none", None, "not_one_action"),
    ("Thought: x\nAction: jump", "none", None, "not_one_action"),
    ("Thought: x\nAction: 7", "none", None, "not_one_action"),
    ("Thought: x\nAction: forward", "none", None, "not_one_action"),
    # A thinking model served without a reasoning parser: the template opened the block.
    ("Plan:\nAction: fetch\n</think>\n\nThought: x\nAction: turn_left", "none", "turn_left", None),
    ("<think>unclosed\nAction: fetch", "none", "fetch", None),
    ('{"thought": "go", "action": "turn_left"}', "json_schema", "turn_left", None),
    ('```json\n{"thought": "go", "action": 4}\n```', "json_schema", "fetch", None),
    ('{"thought": "go", "action": "fly"}', "json_schema", None, "not_one_action"),
    ('{"thought": "go"}', "json_schema", None, "not_json"),
    ("Action: turn_left", "json_schema", None, "not_json"),
]


@pytest.mark.parametrize(("answer", "mode", "action", "kind"), PARSE_CASES)
def test_parse_answer(answer: str, mode: str, action: str | None, kind: str | None) -> None:
    parsed = parse_answer(answer, mode)
    assert (None if parsed.action is None else parsed.action.api_name) == action
    assert parsed.kind == kind
    assert (parsed.error is None) == (kind is None)


def test_parse_answer_keeps_the_thought() -> None:
    assert parse_answer("Thought: the sofa is left.\nAction: turn_left").thought == "the sofa is left."
    assert parse_answer("<think>hmm</think>Thought: go\nAction: fetch").thought == "hmm\ngo"
    assert parse_answer("weigh it</think>Thought: go\nAction: fetch").thought == "weigh it\ngo"


@pytest.mark.parametrize(
    "answer",
    [
        "<think>" * 20_000,  # a degenerate model repeating a tag: was quadratic (seconds)
        "Thought: x\nAction: a" + " " * 40_000 + "b",  # a run of spaces in the action line: the same
    ],
)
def test_parse_answer_takes_linear_time(answer: str) -> None:
    # The parse runs on the event loop every episode shares: a slow one stalls the whole run.
    started = time.monotonic()
    parsed = parse_answer(answer)
    assert time.monotonic() - started < 0.5
    assert parsed.action is None
    assert parsed.error is not None
    assert len(parsed.error) < 200


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ({}, "needs a model"),
        ({"model": "m", "temprature": 0.2}, "unknown vlm agent config keys ['temprature']"),
        ({"model": "m", "history": "8"}, "'history' must be int"),
        ({"model": "m", "history": True}, "'history' must be int"),
        ({"model": "m", "constrained": "grammar"}, "constrained must be one of"),
        ({"model": "m", "fallback_action": "jump"}, "is not an action"),
        ({"model": "m", "max_concurrent_requests": 0}, "must be at least 1"),
        ({"model": "m", "timeout_s": 0}, "timeout_s must be more than 0"),
        ({"model": "m", "timeout_s": float("nan")}, "timeout_s must be more than 0"),
        ({"model": "m", "temperature": -0.5}, "temperature must be 0 or more"),
        ({"model": "m", "base_url": "http://me:sk-123@gateway:8000/v1"}, "base_url holds a password"),
    ],
)
def test_settings_say_what_is_wrong(config: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")) as raised:
        VlmSettings.from_config(config)
    assert "sk-123" not in str(raised.value)


def test_settings_defaults_and_paths() -> None:
    settings = VlmSettings.from_config({"model": "m", "temperature": 1, "fallback_action": 3})
    assert settings.fallback == esrp.Action.RIGHT
    assert settings.temperature == 1
    assert default_trace_dir(Path("runs/qwen.jsonl")) == Path("runs/qwen.traces")
    assert trace_file_name("esrp-bench-v2/00007") == "esrp-bench-v2_00007.jsonl"
    assert is_async_agent(VlmAgentFactory({"model": "m"}, client=object())())


# ---------------------------------------------------------------------------------------------
# A scripted "model" checked against a parallel episode


@dataclass
class Parallel:
    """A privileged episode of the same scene, stepped with the actions the fake model answers: what
    the agent's next request must show."""

    scene_id: str
    episode: esrp.Episode
    trajectory: list[esrp.Action]
    observation: esrp.Observation
    horizon: int
    taken: list[esrp.Action] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def check(self, request: Request, history: int) -> None:
        """The request shows this episode's state now: the images, the step, the flag, the history."""
        assert len(request.images) == 2, f"{len(request.images)} images"
        ego, goal = request.images
        assert ego.shape == goal.shape == (128, 128, 3)
        assert np.array_equal(ego, self.observation.ego_rgb), f"{self.scene_id}: ego view differs"
        step = len(self.taken)
        text = request.text
        assert f"Step {step + 1} of {self.horizon} " in text
        assert f"Holding an object: {'yes' if self.observation.grasping else 'no'}." in text
        lines = [line for line in text.splitlines() if line.startswith("- step ")]
        recent = list(enumerate(self.taken, start=1))[-history:] if history else []
        assert [line.split(" (")[0] for line in lines] == [f"- step {i}: {a.api_name}" for i, a in recent]
        if not self.taken:
            assert "Your last actions: none yet." in text

    def take(self, action: esrp.Action) -> None:
        self.taken.append(action)
        self.observation = self.episode.step(action).observation


class Scenes:
    """Parallel episodes by goal image, so that the fake model knows which episode a request is of."""

    def __init__(self, client: esrp.Client, scene_ids: list[str]) -> None:
        self.by_goal: dict[bytes, Parallel] = {}
        self.episodes: list[esrp.Episode] = []
        for scene_id in scene_ids:
            episode = client.create_episode(scene_id, privileged=True)
            self.episodes.append(episode)
            first = episode.observation
            assert first is not None
            assert first.goal_rgb is not None
            trajectory = expert_trajectory(episode.privileged_state().scene_json)
            parallel = Parallel(scene_id, episode, trajectory, first, episode.scene.horizon)
            self.by_goal[first.goal_rgb.tobytes()] = parallel

    def of(self, request: Request) -> Parallel:
        assert len(request.images) == 2
        return self.by_goal[request.images[1].tobytes()]

    def close(self) -> None:
        for episode in self.episodes:
            episode.close()


@pytest.fixture
def scenes(client: esrp.Client, easy_scenes: list[str]) -> Iterator[Scenes]:
    opened = Scenes(client, easy_scenes[:3])
    yield opened
    opened.close()


def eval_args(fake: FakeServer, server: esrp.LocalServer, out: Path, scene_ids: list[str]) -> list[str]:
    return [
        "eval",
        "--agent",
        "vlm",
        "--base-url",
        fake.base_url,
        "--model",
        "fake-vlm",
        "--scenes",
        ",".join(scene_ids),
        "--out",
        str(out),
        "--server",
        server.address,
        "--no-progress",
    ]


def trace_lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_an_expert_model_solves_its_scenes_through_esrp_eval(
    server: esrp.LocalServer, scenes: Scenes, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("ESRP_VLM_API_KEY", "test-key")
    history = 4

    def expert(request: Request) -> Reply:
        parallel = scenes.of(request)
        with parallel.lock:
            parallel.check(request, history)
            assert request.headers["authorization"] == "Bearer test-key"
            assert request.body["model"] == "fake-vlm"
            assert request.body["temperature"] == 0.0
            assert not request.corrections
            action = parallel.trajectory[len(parallel.taken)]
            parallel.take(action)
        return Reply(f"Thought: expert step {len(parallel.taken)}.\nAction: {action.api_name}")

    out = tmp_path / "vlm.jsonl"
    ids = [p.scene_id for p in scenes.by_goal.values()]
    config = json.dumps({"history": history, "max_concurrent_requests": 2})
    with fake_openai(expert) as fake:
        args = [*eval_args(fake, server, out, ids), "--agent-config", config, "--episodes-in-flight", "3"]
        assert main(args) == 0
    assert fake.failures == []
    assert 1 <= fake.most_in_flight <= 2  # the factory's semaphore, shared by the three episodes

    records = {r.scene_id: r for r in read_records(out).records}
    assert sorted(records) == sorted(ids)
    for parallel in scenes.by_goal.values():
        record = records[parallel.scene_id]
        steps = len(parallel.trajectory)
        assert record.agent == "vlm"
        assert record.success
        assert record.end == "success"
        assert record.actions == [int(a) for a in parallel.trajectory]
        assert record.agent_config == {
            "history": 4,
            "max_concurrent_requests": 2,
            "base_url": fake.base_url,
            "model": "fake-vlm",
        }
        stats = record.agent_stats
        assert stats["model"] == "fake-vlm"
        assert stats["steps"] == stats["requests"] == steps
        assert stats["invalid_answers"] == stats["reprompts"] == stats["fallbacks"] == 0
        assert stats["http_retries"] == 0
        assert stats["prompt_tokens"] == 100 * steps
        assert stats["completion_tokens"] == 10 * steps
        assert stats["total_tokens"] == 110 * steps
        assert stats["model_seconds"] > 0
        assert stats["model_seconds_max"] >= stats["model_seconds_mean"]

        trace = Path(stats["trace"])
        assert trace.parent == tmp_path / "vlm.traces"
        lines = trace_lines(trace)
        assert [line["type"] for line in lines] == ["episode"] + ["step"] * steps + ["end"]
        assert lines[0]["scene_id"] == parallel.scene_id
        assert lines[0]["model"] == "fake-vlm"
        assert "move_forward (0)" in lines[0]["system_prompt"]
        assert lines[-1]["stats"] == stats
        sent = [r for r in fake.requests if scenes.of(r) is parallel]
        for line, request, action in zip(lines[1:-1], sent, parallel.trajectory, strict=True):
            assert line["prompt"] == request.texts[0]
            assert line["ego_image"]["png_bytes"] == len(request.pngs[0])
            assert line["action"] == action.api_name
            assert line["source"] == "model"
            (attempt,) = line["attempts"]
            assert attempt["thought"].startswith("expert step")
            assert attempt["usage"] == {"prompt_tokens": 100, "completion_tokens": 10, "total_tokens": 110}
    assert "**vlm** (this run)" in (tmp_path / "vlm.md").read_text()


Scripted = list[tuple[Reply, "esrp.Action | None"]]


def scripted(replies: Scripted, scenes: Scenes, checks: list[str]) -> Any:  # noqa: ANN401
    """A fake model answering `replies` in order, each with the action the agent then plays (the
    parallel episode takes it), checking every request against the parallel episode; a correction
    request must repeat the step's images and carry the correction.
    """
    queue = list(replies)

    def script(request: Request) -> Reply:
        parallel = scenes.of(request)
        reply, then = queue.pop(0)
        if request.corrections:
            checks.append("correction")
            assert len(request.answers) == len(request.corrections)
            assert "could not be used" in request.corrections[-1]
            assert all(name in request.corrections[-1] for name in ACTION_NAMES)
        parallel.check(request, 8)
        if then is not None:
            parallel.take(then)
        return reply

    return script


def test_malformed_answers_are_asked_again_then_fall_back(
    server: esrp.LocalServer, scenes: Scenes, tmp_path: Path
) -> None:
    parallel = next(iter(scenes.by_goal.values()))
    checks: list[str] = []
    left, right = esrp.Action.LEFT, esrp.Action.RIGHT
    replies: Scripted = [
        (Reply("I will go forward."), None),  # no Action line: asked again
        (Reply("Thought: fine.\nAction: turn_left"), left),
        (Reply("Action: move_forward\nAction: turn_left"), None),  # two actions: asked again
        (Reply("Thought: x\nAction: fly"), right),  # still unusable: the fallback (turn_right here)
        (Reply("Thought: x\nAction: 2"), left),
    ]
    out = tmp_path / "vlm.jsonl"
    config = json.dumps({"max_steps": 3, "fallback_action": "turn_right"})
    with fake_openai(scripted(replies, scenes, checks)) as fake:
        assert main([*eval_args(fake, server, out, [parallel.scene_id]), "--agent-config", config]) == 0
    assert fake.failures == []
    assert checks == ["correction", "correction"]
    (record,) = read_records(out).records
    assert record.actions == [2, 3, 2]
    assert record.end == "agent"
    stats = record.agent_stats
    assert stats["steps"] == 3
    assert stats["requests"] == 5
    assert stats["invalid_answers"] == 3
    assert stats["reprompts"] == 2
    assert stats["fallbacks"] == 1
    assert stats["invalid_kinds"] == {"no_action": 1, "several_actions": 1, "not_one_action": 1}
    lines = trace_lines(Path(stats["trace"]))
    steps = [line for line in lines if line["type"] == "step"]
    assert [s["source"] for s in steps] == ["model", "fallback", "model"]
    assert [len(s["attempts"]) for s in steps] == [2, 2, 1]
    assert steps[1]["attempts"][0]["error"] == "it has several 'Action:' lines"
    # What the history told the model: the turns were done (the view changed).
    assert "- step 1: turn_left (done)\n- step 2: turn_right (done)" in steps[2]["prompt"]


def test_http_429_and_500_are_retried(server: esrp.LocalServer, scenes: Scenes, tmp_path: Path) -> None:
    parallel = next(iter(scenes.by_goal.values()))
    turn = Reply("Thought: go\nAction: turn_left")
    left = esrp.Action.LEFT
    replies: Scripted = [(Reply(status=429), None), (Reply(status=500), None), (turn, left)]
    replies += [(Reply(status=503), None), (turn, left)]
    out = tmp_path / "vlm.jsonl"
    with fake_openai(scripted(replies, scenes, [])) as fake:
        args = [*eval_args(fake, server, out, [parallel.scene_id]), "--agent-config", '{"max_steps": 2}']
        assert main(args) == 0
    assert fake.failures == []
    assert len(fake.requests) == 5
    (record,) = read_records(out).records
    assert record.actions == [2, 2]
    stats = record.agent_stats
    assert stats["requests"] == 2
    assert stats["http_retries"] == 3
    assert stats["invalid_answers"] == 0
    steps = [line for line in trace_lines(Path(stats["trace"])) if line["type"] == "step"]
    assert [s["attempts"][0]["http_retries"] for s in steps] == [2, 1]


def test_a_model_that_keeps_failing_fails_the_episode_and_a_rerun_overwrites_its_trace(
    server: esrp.LocalServer, scenes: Scenes, tmp_path: Path
) -> None:
    parallel = next(iter(scenes.by_goal.values()))
    out = tmp_path / "vlm.jsonl"
    trace_dir = tmp_path / "traces"
    config = json.dumps({"max_steps": 2, "max_retries": 1})

    def turn_then_fail(request: Request) -> Reply:
        if len(parallel.taken) == 0:
            parallel.check(request, 8)
            parallel.take(esrp.Action.LEFT)
            return Reply("Thought: go\nAction: turn_left")
        return Reply(status=500)

    with fake_openai(turn_then_fail) as fake:
        args = [*eval_args(fake, server, out, [parallel.scene_id]), "--agent-config", config]
        assert main([*args, "--trace-dir", str(trace_dir)]) == 1  # failed, not recorded
    assert len(fake.requests) == 1 + 2  # one answer, then a 500 retried once
    assert read_records(out).records == []
    trace = trace_dir / trace_file_name(parallel.scene_id)
    assert [line["type"] for line in trace_lines(trace)] == ["episode", "step"]

    def fetcher(request: Request) -> Reply:
        return Reply("Thought: grab\nAction: fetch")

    with fake_openai(fetcher) as fake:
        args = [*eval_args(fake, server, out, [parallel.scene_id]), "--agent-config", config]
        assert main([*args, "--trace-dir", str(trace_dir)]) == 0  # the rerun retries the episode
    (record,) = read_records(out).records
    assert record.actions == [4, 4]
    assert record.agent_stats["trace"] == str(trace)
    lines = trace_lines(trace)
    assert [line["type"] for line in lines] == ["episode", "step", "step", "end"]
    assert [line["action"] for line in lines[1:3]] == ["fetch", "fetch"]


def test_a_misbehaving_endpoint_fails_its_episode_in_one_line_and_the_run_goes_on(
    server: esrp.LocalServer, scenes: Scenes, tmp_path: Path
) -> None:
    # By scene: an HTML page with status 200 (a proxy's), a 400 (a request it refused), good answers.
    page, refused, good = scenes.by_goal.values()
    replies = {
        page.scene_id: Reply(raw="<html><body>Welcome to nginx!</body></html>"),
        refused.scene_id: Reply(status=400),
        good.scene_id: Reply("Thought: go\nAction: turn_left"),
    }

    def script(request: Request) -> Reply:
        return replies[scenes.of(request).scene_id]

    out = tmp_path / "vlm.jsonl"
    ids = [p.scene_id for p in (page, refused, good)]
    with fake_openai(script) as fake:
        args = [*eval_args(fake, server, out, ids), "--agent-config", '{"max_steps": 1}']
        assert main(args) == 1
    assert fake.failures == []
    assert len(fake.requests) == 3  # none of these is retried
    (record,) = read_records(out).records  # the run went on with the others
    assert record.scene_id == good.scene_id
    assert record.actions == [2]
    log = (tmp_path / "vlm.errors.log").read_text()
    where = f"VlmEndpointError: the model endpoint {fake.base_url}"
    assert f"## {page.scene_id}: {where} answered HTTP 200 but not a chat completion (text/html: " in log
    assert "Welcome to nginx!" in log
    assert f"## {refused.scene_id}: {where} answered HTTP 400 (scripted 400)" in log


@pytest.mark.parametrize("status", [401, 403, 404])
def test_a_wrong_key_url_or_model_stops_the_run_there_and_a_rerun_resumes(
    server: esrp.LocalServer, scenes: Scenes, tmp_path: Path, capsys: pytest.CaptureFixture[str], status: int
) -> None:
    # Every request of the run would get the same answer: the run stops at the first, keeping what
    # it recorded, instead of failing each episode in turn.
    first, refused, last = scenes.by_goal.values()
    answer = {first.scene_id: Reply("Action: turn_left"), refused.scene_id: Reply(status=status)}

    def script(request: Request) -> Reply:
        return answer[scenes.of(request).scene_id]

    out = tmp_path / "vlm.jsonl"
    ids = [p.scene_id for p in (first, refused, last)]
    config = ["--agent-config", '{"max_steps": 1}', "--episodes-in-flight", "1"]
    with fake_openai(script) as fake:
        capsys.readouterr()
        assert main([*eval_args(fake, server, out, ids), *config]) == 1
        err = capsys.readouterr().err
        assert len(fake.requests) == 2  # the last scene was never started
        assert [r.scene_id for r in read_records(out).records] == [first.scene_id]
        where = f"the model endpoint {fake.base_url} answered HTTP {status}"
        assert f"esrp eval: {refused.scene_id}: VlmEndpointError: {where}" in err, err
        said = "as every episode would fail the same way (1 episode recorded by this run is kept"
        assert said in err
        # Fixed (the key, the URL or the model), the same command resumes.
        answer.update({refused.scene_id: Reply("Action: turn_right"), last.scene_id: Reply("Action: fetch")})
        assert main([*eval_args(fake, server, out, ids), *config]) == 0
    assert [r.scene_id for r in read_records(out).records] == ids


def test_a_resumed_run_may_change_how_requests_are_made_but_not_what_is_asked(
    server: esrp.LocalServer, scenes: Scenes, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    first, second, third = scenes.by_goal.values()

    def script(request: Request) -> Reply:
        return Reply("Action: turn_left")

    out = tmp_path / "vlm.jsonl"
    ids = [p.scene_id for p in (first, second, third)]

    def run(scene_ids: list[str], config: dict[str, Any]) -> int:
        return main([*eval_args(fake, server, out, scene_ids), "--agent-config", json.dumps(config)])

    with fake_openai(script) as fake:
        assert run(ids[:1], {"max_steps": 1, "timeout_s": 60}) == 0
        # Another timeout, more requests at once, fewer retries, no traces: the same run, resumed.
        changed = {"max_steps": 1, "timeout_s": 5, "max_concurrent_requests": 2, "max_retries": 1}
        changed["traces"] = False
        capsys.readouterr()
        assert run(ids[:2], changed) == 0
        assert "1 of 2 scenes already done" in capsys.readouterr().err
        # Another step limit (or model, prompt, temperature...) is another run.
        assert run(ids, {"max_steps": 2, "timeout_s": 60}) == 2
        err = capsys.readouterr().err
        assert "with other settings" in err, err
        free = "max_concurrent_requests, max_retries, timeout_s, trace_dir, traces"
        assert f"only {free} may change" in err, err
    assert [r.scene_id for r in read_records(out).records] == ids[:2]


def test_an_endpoint_that_echoes_the_api_key_in_its_error_does_not_put_it_in_the_messages(
    server: esrp.LocalServer,
    scenes: Scenes,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    key = "sk-secret-1234567890"
    monkeypatch.setenv("ESRP_VLM_API_KEY", key)
    first, refused, _ = scenes.by_goal.values()

    def script(request: Request) -> Reply:
        said = request.headers["authorization"].removeprefix("Bearer ")
        if scenes.of(request).scene_id == refused.scene_id:
            # A 400 (not retried, not stopping the run) and a 401 (stopping it), each quoting the key.
            return Reply(status=400, body={"error": {"message": f"Incorrect API key provided: {said}"}})
        return Reply(status=401, body={"error": {"message": f"Incorrect API key provided: {said}"}})

    out = tmp_path / "vlm.jsonl"
    config = ["--agent-config", '{"max_steps": 1}', "--episodes-in-flight", "1"]
    with fake_openai(script) as fake:
        capsys.readouterr()
        assert main([*eval_args(fake, server, out, [refused.scene_id, first.scene_id]), *config]) == 1
        err = capsys.readouterr().err
        assert len(fake.requests) == 2
    assert "Incorrect API key provided: [the API key]" in err, err
    log = (tmp_path / "vlm.errors.log").read_text()
    assert "Incorrect API key provided: [the API key]" in log, log
    for text, where in ((err, "stderr"), (log, "the errors log")):
        assert key not in text, f"the key in {where}: {text}"
    for path in tmp_path.rglob("*"):
        if path.is_file():
            assert key not in path.read_text(errors="replace"), path


def test_an_endpoint_that_is_not_there_too_slow_or_elsewhere_names_itself(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    first = esrp.Observation(
        ego_rgb=rng.integers(0, 256, (128, 128, 3), dtype=np.uint8),
        grasping=False,
        goal_rgb=rng.integers(0, 256, (128, 128, 3), dtype=np.uint8),
    )

    async def one_step(config: dict[str, Any]) -> str:
        factory = VlmAgentFactory({"model": "m", "traces": False, **config})
        agent = factory()
        await agent.reset(first, {"scene_id": "s/1", "horizon": 200})
        try:
            with pytest.raises(esrp.agents.vlm.VlmEndpointError) as raised:
                await agent.act(first)
        finally:
            await factory.aclose()
        return str(raised.value)

    def slow(request: Request) -> Reply:
        time.sleep(0.5)
        return Reply("Action: turn_left")

    with fake_openai(slow) as fake:
        message = asyncio.run(one_step({"base_url": fake.base_url, "timeout_s": 0.1, "max_retries": 1}))
        assert message == (
            f"the model endpoint {fake.base_url} did not answer within timeout_s 0.1 s, after 1 retries"
        )
        assert len(fake.requests) == 2
        # Without /v1 the fake has no such route: 404.
        elsewhere = fake.base_url.removesuffix("/v1")
        message = asyncio.run(one_step({"base_url": elsewhere}))
        assert message.startswith(f"the model endpoint {elsewhere} answered HTTP 404 (")
        assert message.endswith("; check --base-url (e.g. http://localhost:8000/v1) and --model 'm'")
        closed = fake.base_url
    message = asyncio.run(one_step({"base_url": closed, "max_retries": 0}))
    assert message == (
        f"the model endpoint {closed} could not be reached (max_retries 0): is it running? (--base-url)"
    )


def test_an_endpoint_that_cannot_be_reached_stops_the_run(
    server: esrp.LocalServer, scenes: Scenes, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Still unreachable after the client's retries, it would be for every episode, each waiting
    # through the same retries: the run stops at the first, as for a wrong key (a rerun resumes).
    with fake_openai(lambda request: Reply("Action: fetch")) as fake:
        pass
    out = tmp_path / "vlm.jsonl"
    ids = [p.scene_id for p in scenes.by_goal.values()]
    config = ["--agent-config", '{"max_steps": 1, "max_retries": 0}', "--episodes-in-flight", "1"]
    capsys.readouterr()
    assert main([*eval_args(fake, server, out, ids), *config]) == 1
    err = capsys.readouterr().err
    assert f"esrp eval: {ids[0]}: VlmEndpointError: the model endpoint {fake.base_url} could not" in err
    assert "stopped the run there, as every episode would fail the same way (0 episodes" in err
    assert ids[1] not in err
    assert read_records(out).records == []


async def _one_step(base_url: str, tmp_path: Path) -> tuple[esrp.Action | None, dict[str, Any]]:
    rng = np.random.default_rng(3)
    first = esrp.Observation(
        ego_rgb=rng.integers(0, 256, (128, 128, 3), dtype=np.uint8),
        grasping=False,
        goal_rgb=rng.integers(0, 256, (128, 128, 3), dtype=np.uint8),
    )
    config = {"model": "fake-vlm", "base_url": base_url, "max_retries": 0}
    factory = VlmAgentFactory(config, results_path=tmp_path / "r.jsonl")
    agent = factory()
    try:
        await agent.reset(first, {"scene_id": "s/1", "horizon": 200})
        action = await agent.act(first)
    finally:
        await factory.aclose()
    return action, agent.stats()


@pytest.mark.parametrize(
    ("body", "said"),
    [
        # A gateway's upstream failure, sent with status 200: was played as an empty answer.
        (
            {"error": {"message": "upstream  overloaded", "code": 502}},
            "with an error instead of a completion",
        ),
        ({}, "but not a chat completion ('{}')"),  # was played as an empty answer too
        ({"choices": "x"}, "but not a chat completion (\"{'choices': 'x'}\")"),  # was an AttributeError
        ({"choices": [{"message": {"content": 5}}]}, "but not a chat completion ("),
        ({"choices": [{"message": {"content": [3]}}]}, "but not a chat completion ("),
        ({"choices": [{"message": "Action: fetch"}]}, "but not a chat completion ("),
    ],
)
def test_a_200_that_is_no_completion_fails_the_step_instead_of_playing_the_fallback(
    body: dict[str, Any], said: str, tmp_path: Path
) -> None:
    with fake_openai(lambda request: Reply(body=body)) as fake:
        with pytest.raises(esrp.agents.vlm.VlmEndpointError) as raised:
            asyncio.run(_one_step(fake.base_url, tmp_path))
        assert len(fake.requests) == 1  # not asked again as if the model had answered badly
    message = str(raised.value)
    assert message.startswith(f"the model endpoint {fake.base_url} answered HTTP 200 {said}"), message
    if "error" in body:
        assert message.endswith("(upstream overloaded)")
    assert not raised.value.stops_run


def test_content_parts_are_read_and_the_stats_say_what_was_asked_and_served(tmp_path: Path) -> None:
    body = {
        "object": "chat.completion",
        "model": "fake-vlm-2025-01-01",  # the dated snapshot an alias resolved to
        "choices": [
            {
                "index": 0,
                "message": {
                    "role": "assistant",
                    "content": [
                        {"type": "thinking", "thinking": [{"type": "text", "text": "Action: release?"}]},
                        {"type": "text", "text": "Thought: grab it\n"},
                        {"type": "text", "text": "Action: fetch"},
                    ],
                },
                "finish_reason": "stop",
            }
        ],
        "usage": "not counted",  # was an AttributeError
    }
    with fake_openai(lambda request: Reply(body=body)) as fake:
        action, stats = asyncio.run(_one_step(fake.base_url, tmp_path))
    assert action == esrp.Action.FETCH
    assert stats["requests"] == stats["requests_without_usage"] == 1
    assert stats["invalid_answers"] == 0
    assert stats["model"] == "fake-vlm"
    assert stats["served_models"] == ["fake-vlm-2025-01-01"]
    # Every setting in effect, defaults included: a record says how it was played.
    settings = stats["settings"]
    assert settings["base_url"] == fake.base_url
    assert (settings["temperature"], settings["max_tokens"], settings["history"]) == (0.0, 256, 8)
    assert (settings["reprompts"], settings["fallback_action"], settings["constrained"]) == (
        1,
        "turn_left",
        "none",
    )
    assert "trace_dir" not in settings
    assert "traces" not in settings
    prompt = esrp.agents.vlm.system_prompt("none").encode()
    assert stats["system_prompt_sha256"] == hashlib.sha256(prompt).hexdigest()
    json.dumps(stats, allow_nan=False)  # what a record can carry


def test_vlm_flags_and_config_errors(server: esrp.LocalServer, tmp_path: Path) -> None:
    out = str(tmp_path / "x.jsonl")
    base = ["eval", "--out", out, "--server", server.address, "--limit", "1", "--no-progress"]
    assert main([*base, "--agent", "random", "--model", "m"]) == 2
    assert main([*base, "--agent", "vlm"]) == 2  # no model
    assert main([*base, "--agent", "vlm", "--model", "m", "--agent-config", '{"colour": 1}']) == 2


# ---------------------------------------------------------------------------------------------
# Constrained decoding: what each mode sends


@pytest.mark.parametrize(
    ("mode", "answer"),
    [
        ("json_schema", '{"thought": "go", "action": "turn_right"}'),
        ("vllm", "Thought: go\nAction: turn_right"),
        ("vllm-guided", "Thought: go\nAction: turn_right"),
    ],
)
def test_constrained_decoding_requests(mode: str, answer: str, tmp_path: Path) -> None:
    bodies: list[dict[str, Any]] = []

    def script(request: Request) -> Reply:
        bodies.append(request.body)
        return Reply(answer)

    rng = np.random.default_rng(1)
    ego = rng.integers(0, 256, (128, 128, 3), dtype=np.uint8)
    goal = rng.integers(0, 256, (128, 128, 3), dtype=np.uint8)
    first = esrp.Observation(ego_rgb=ego, grasping=False, goal_rgb=goal)
    config = {
        "model": "m",
        "constrained": mode,
        "extra_body": {"top_k": 20},
        "send_seed": True,
        "image_scale": 2,
    }

    async def one_step(base_url: str) -> esrp.Action | None:
        factory = VlmAgentFactory({**config, "base_url": base_url}, results_path=tmp_path / "r.jsonl")
        agent = factory()
        await agent.reset(first, {"scene_id": "s/1", "horizon": 200, "seed": 7})
        action = await agent.act(first)
        await factory.aclose()
        return action

    with fake_openai(script) as fake:
        assert asyncio.run(one_step(fake.base_url)) == esrp.Action.RIGHT
        (request,) = fake.requests
    assert fake.failures == []
    (body,) = bodies
    assert body["top_k"] == 20
    assert body["seed"] == 7
    # image_scale 2: the images are sent at 256x256, each pixel a 2x2 block.
    assert np.array_equal(request.images[0], np.repeat(np.repeat(ego, 2, axis=0), 2, axis=1))
    assert request.pngs[1] == encode_png(goal, 2)
    if mode == "json_schema":
        schema = body["response_format"]["json_schema"]["schema"]
        assert schema["properties"]["action"]["enum"] == list(ACTION_NAMES)
        assert "Answer with one JSON object" in body["messages"][0]["content"]
    elif mode == "vllm":
        assert body["structured_outputs"]["regex"].startswith("Thought: ")
    else:
        assert body["guided_regex"].endswith("|fetch|release)")
    assert (tmp_path / "r.traces" / "s_1.jsonl").exists()
