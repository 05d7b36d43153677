"""ESRP-VLM, the paper's vision-language baseline: a ReAct agent (a short thought, then one action)
that prompts a pretrained VLM in context, over any OpenAI-compatible chat-completions endpoint
(vLLM serving Qwen3-VL-2B-Instruct as in the paper, Gemini through Google's OpenAI-compatible
endpoint, OpenAI, llama.cpp...). `esrp eval --agent vlm --base-url URL --model NAME` runs it.

Each step sends one request: the system prompt (the task, the six actions, the answer format) and
a user message with the step count, the grasp flag, the last `history` actions with what they
visibly did, and two PNG images as data URLs — the egocentric view `I_ego` and the goal image
`I_goal`. The answer is parsed strictly (`parse_answer`): exactly one action, by name or code. An
unusable answer is counted and answered with a correction message (`reprompts` times); after that
the step plays `fallback_action` (a turn by default), also counted.

The agent sees only observations, never the step's info: whether a move was blocked is inferred
from the ego view being pixel-identical to the one before it (a rejected motion changes nothing,
and rendering is deterministic), whether a fetch or release worked from the grasp flag.

`VlmAgentFactory` (what `esrp eval` builds once per run) owns the one `openai.AsyncOpenAI` client
and a semaphore that caps the model calls in flight over all its episodes; HTTP 429, 5xx, timeouts
and connection errors are retried by the `openai` client (`max_retries`, exponential backoff,
honouring `Retry-After`). Each episode writes a trace (JSON Lines, `trace_dir/<scene>.jsonl`):
the prompt text, image sizes and hashes, each answer with its thought, usage and latency.
"""

from __future__ import annotations

import asyncio
import base64
import dataclasses
import hashlib
import io
import json
import os
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .._values import Action, Observation

__all__ = [
    "ACTION_NAMES",
    "API_KEY_VARIABLES",
    "CONSTRAINED_MODES",
    "HistoryEntry",
    "ParsedAnswer",
    "VlmAgent",
    "VlmAgentFactory",
    "VlmSettings",
    "api_key",
    "correction_message",
    "default_trace_dir",
    "encode_png",
    "outcome_of",
    "parse_action_value",
    "parse_answer",
    "system_prompt",
    "trace_file_name",
    "user_text",
]

ACTION_NAMES: tuple[str, ...] = tuple(action.api_name for action in Action)
"""The action names in code order: `move_forward` (0) ... `release` (5)."""

API_KEY_VARIABLES = ("ESRP_VLM_API_KEY", "OPENAI_API_KEY")
"""Where the API key is read from, first set wins; without either the key is `EMPTY` (a local
vLLM started without `--api-key` accepts any)."""

CONSTRAINED_MODES = ("none", "json_schema", "vllm", "vllm-guided")
"""Constrained decoding: `none` (free text, parsed), `json_schema` (OpenAI `response_format`, JSON
answers: OpenAI, Gemini, vLLM, llama.cpp), `vllm` (vLLM >= 0.10.2 `structured_outputs.regex` over
the Thought/Action text), `vllm-guided` (the same as `guided_regex`, vLLM < 0.12)."""

_BY_NAME = {action.api_name: action for action in Action}
_ACTION_REGEX = "Thought: [^\\n]{1,400}\\nAction: (" + "|".join(ACTION_NAMES) + ")"
_JSON_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "thought": {"type": "string"},
        "action": {"type": "string", "enum": list(ACTION_NAMES)},
    },
    "required": ["thought", "action"],
    "additionalProperties": False,
}


# ---------------------------------------------------------------------------------------------
# Settings


@dataclass(frozen=True)
class VlmSettings:
    """The agent configuration (`--agent-config` JSON, `--base-url`, `--model`); every key optional
    but `model`. The API key is never part of it: see `API_KEY_VARIABLES`.

    Attributes:
        model: The model name the endpoint serves (`Qwen/Qwen3-VL-2B-Instruct`, `gemini-2.5-flash-lite`).
        base_url: The endpoint's base URL (`http://localhost:8000/v1`); None: `OPENAI_BASE_URL`,
            else OpenAI's.
        temperature: Sampling temperature (0: greedy).
        max_tokens: The answer's token limit (`max_tokens`).
        history: How many past actions the prompt lists.
        image_scale: Each image is enlarged by this integer factor (nearest neighbour) before encoding.
        max_concurrent_requests: Model calls in flight at once, over all episodes of the run.
        timeout_s: One HTTP request's timeout, seconds.
        max_retries: The `openai` client's retries of 429, 5xx, timeouts and connection errors.
        reprompts: Correction requests after an unusable answer, before the fallback.
        fallback_action: What a step plays when no usable answer came (name or code).
        constrained: One of `CONSTRAINED_MODES`.
        max_steps: Stop the episode (the record's `end` is `agent`) after this many actions.
        send_seed: Send the episode's seed as the request's `seed` (not every server accepts it).
        extra_body: Extra JSON fields of every request (vLLM's `top_k`, `chat_template_kwargs`...).
        trace_dir: The folder of the per-episode traces (default: beside the results file).
        traces: Whether to write traces at all.
    """

    model: str
    base_url: str | None = None
    temperature: float = 0.0
    max_tokens: int = 256
    history: int = 8
    image_scale: int = 1
    max_concurrent_requests: int = 8
    timeout_s: float = 120.0
    max_retries: int = 5
    reprompts: int = 1
    fallback_action: str | int = "turn_left"
    constrained: str = "none"
    max_steps: int | None = None
    send_seed: bool = False
    extra_body: dict[str, Any] = field(default_factory=dict)
    trace_dir: str | None = None
    traces: bool = True

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> VlmSettings:
        """Settings from an agent config; raises `ValueError` naming a missing, unknown or
        ill-typed key.
        """
        known = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(config) - set(known))
        if unknown:
            raise ValueError(f"unknown vlm agent config keys {unknown}: use {sorted(known)}")
        if not isinstance(config.get("model"), str) or not config["model"]:
            raise ValueError("the vlm agent needs a model: --model NAME (or the agent config's 'model')")
        for name, value in config.items():
            _check_type(name, value, known[name].type)
        settings = cls(**dict(config))
        if settings.constrained not in CONSTRAINED_MODES:
            raise ValueError(
                f"constrained must be one of {list(CONSTRAINED_MODES)}, not {settings.constrained!r}"
            )
        if parse_action_value(settings.fallback_action) is None:
            raise ValueError(
                f"fallback_action {settings.fallback_action!r} is not an action: use {ACTION_NAMES}"
            )
        for name in ("max_tokens", "image_scale", "max_concurrent_requests"):
            if getattr(settings, name) < 1:
                raise ValueError(f"{name} must be at least 1")
        for name in ("history", "max_retries", "reprompts"):
            if getattr(settings, name) < 0:
                raise ValueError(f"{name} must not be negative")
        if settings.max_steps is not None and settings.max_steps < 1:
            raise ValueError("max_steps must be at least 1")
        return settings

    @property
    def fallback(self) -> Action:
        """`fallback_action` as an `Action`."""
        action = parse_action_value(self.fallback_action)
        assert action is not None  # checked by from_config
        return action


_TYPES: dict[str, tuple[type, ...]] = {
    "str": (str,),
    "str | None": (str, type(None)),
    "str | int": (str, int),
    "float": (int, float),
    "int": (int,),
    "int | None": (int, type(None)),
    "bool": (bool,),
    "dict[str, Any]": (dict,),
}


def _check_type(name: str, value: object, annotation: object) -> None:
    allowed = _TYPES[str(annotation)]
    # bool is an int in Python; a count given as `true` is a mistake.
    if isinstance(value, bool) and bool not in allowed:
        allowed = ()
    if not isinstance(value, allowed):
        raise ValueError(f"vlm agent config {name!r} must be {annotation}, not {value!r}")


def api_key() -> str:
    """The API key: the first of `API_KEY_VARIABLES` that is set, else `EMPTY`."""
    for variable in API_KEY_VARIABLES:
        value = os.environ.get(variable)
        if value:
            return value
    return "EMPTY"


def default_trace_dir(results: Path) -> Path:
    """Where `esrp eval --out RESULTS` puts the traces: `RESULTS` without its suffix, plus `.traces`
    (`runs/qwen.jsonl` -> `runs/qwen.traces/`).
    """
    return results.with_name(results.stem + ".traces")


def trace_file_name(scene_id: str) -> str:
    """The trace file of a scene: its id with anything but letters, digits, `.`, `_`, `-` replaced
    by `_` (`esrp-bench-v2/00007` -> `esrp-bench-v2_00007.jsonl`).
    """
    return re.sub(r"[^A-Za-z0-9._-]", "_", scene_id) + ".jsonl"


# ---------------------------------------------------------------------------------------------
# Prompt


def system_prompt(constrained: str = "none") -> str:
    """The system prompt: the task, the images, the six actions and the answer format."""
    actions = "\n".join(
        [
            "- move_forward (0): move 0.25 m forward.",
            "- move_backward (1): move 0.25 m backward.",
            "- turn_left (2): turn 22.5 degrees left, in place.",
            "- turn_right (3): turn 22.5 degrees right, in place.",
            "- fetch (4): pick up the nearest movable object within 1.0 m of you; it then moves with "
            "you, keeping its place relative to you. Does nothing if you already hold one or none is "
            "in reach.",
            "- release (5): put the held object down exactly where it is. Does nothing if you hold nothing.",
        ]
    )
    if constrained == "json_schema":
        answer = (
            'Answer with one JSON object: {"thought": "<one or two short sentences>", "action": '
            '"<one action name>"}.'
        )
    else:
        answer = (
            "Answer with exactly two lines and nothing else:\n"
            "Thought: <one or two short sentences: what you see and what to do next>\n"
            "Action: <one action name>"
        )
    return (
        "You control a mobile robot in a room. Some pieces of furniture are not where they belong: "
        "carry each one to its place in the goal layout (scene rearrangement).\n\n"
        "Each turn you get two images:\n"
        "1. Your egocentric camera view (mounted on top of the robot, looking slightly down).\n"
        "2. The goal layout: the whole room seen from directly above, with every movable object where "
        "it must end up. Each object has the same colour in both images, so you can match them.\n"
        "You also get whether you hold an object, and your last actions with what they did.\n\n"
        f"Actions (name and code):\n{actions}\n\n"
        "A motion that would make you (or the object you hold) hit anything is rejected: you stay "
        "where you are, and the step still counts. An object is in place when its outline on the floor "
        "overlaps its goal outline enough and you are no longer holding it. The task succeeds when "
        "every movable object is in place; you have a limited number of steps.\n\n" + answer
    )


def correction_message(error: str, constrained: str = "none") -> str:
    """The user message that asks again after an unusable answer."""
    if constrained == "json_schema":
        form = 'one JSON object {"thought": "...", "action": "<one action name>"}'
    else:
        form = "exactly two lines:\nThought: <one short sentence>\nAction: <one action name>"
    return (
        f"Your answer could not be used: {error}. Choose exactly one of {', '.join(ACTION_NAMES)} and "
        f"answer with {form}"
    )


@dataclass(frozen=True)
class HistoryEntry:
    """One past action in the prompt: its step number (1-based), name, and what it visibly did."""

    step: int
    action: Action
    outcome: str

    def line(self) -> str:
        """The prompt's line for it."""
        return f"- step {self.step}: {self.action.api_name} ({self.outcome})"


def outcome_of(action: Action, before: Observation, after: Observation) -> str:
    """What `action` visibly did, from the observations around it (the agent gets no step info): a
    motion that left the ego view pixel-identical was blocked; fetch and release are judged by the
    grasp flag.
    """
    if action == Action.FETCH:
        if not before.grasping and after.grasping:
            return "picked up an object"
        return "no effect: already holding" if before.grasping else "no effect: nothing in reach"
    if action == Action.RELEASE:
        if before.grasping and not after.grasping:
            return "put the object down"
        return "no effect: holding nothing"
    if np.array_equal(before.ego_rgb, after.ego_rgb):
        return "view unchanged: probably blocked"
    return "done"


def user_text(step: int, horizon: int, grasping: bool, history: Sequence[HistoryEntry]) -> str:
    """The text of a step's user message (the images follow it)."""
    lines = [
        f"Step {step + 1} of {horizon} ({horizon - step} steps left).",
        f"Holding an object: {'yes' if grasping else 'no'}.",
    ]
    if history:
        lines.append("Your last actions (oldest first):")
        lines.extend(entry.line() for entry in history)
    else:
        lines.append("Your last actions: none yet.")
    lines.append("Image 1 is your egocentric view now; image 2 is the goal layout from above.")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Images


def encode_png(image: npt.NDArray[np.uint8], scale: int = 1) -> bytes:
    """An RGB image (H, W, 3) uint8 as PNG bytes (Pillow), enlarged `scale` times (nearest)."""
    from PIL import Image

    pixels = np.ascontiguousarray(image, dtype=np.uint8)
    if scale > 1:
        pixels = np.repeat(np.repeat(pixels, scale, axis=0), scale, axis=1)
    buffer = io.BytesIO()
    Image.fromarray(pixels, "RGB").save(buffer, format="PNG")
    return buffer.getvalue()


def _data_url(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _image_note(png: bytes, shape: tuple[int, ...]) -> dict[str, Any]:
    """What a trace keeps of an image: its size and hash, not its pixels."""
    return {"sha256": hashlib.sha256(png).hexdigest(), "png_bytes": len(png), "shape": list(shape)}


# ---------------------------------------------------------------------------------------------
# Parsing


@dataclass(frozen=True)
class ParsedAnswer:
    """A model answer, parsed.

    Attributes:
        action: The action, or None when the answer is unusable.
        thought: The reasoning part (the `Thought:` text, `<think>` blocks, or JSON `thought`).
        error: Why the answer is unusable (a sentence for the correction message), else None.
        kind: The stats key of the error (`empty`, `no_action`, `several_actions`,
            `not_one_action`, `not_json`), else None.
    """

    action: Action | None
    thought: str = ""
    error: str | None = None
    kind: str | None = None


_THINK = re.compile(r"<think>(.*?)</think>", re.DOTALL | re.IGNORECASE)
_ACTION_LINE = re.compile(r"^\s*(?:[-#>]\s*)*action\s*:\s*(.*?)\s*$", re.IGNORECASE)
_THOUGHT_LINE = re.compile(r"^\s*(?:[-#>]\s*)*thought\s*:\s*", re.IGNORECASE)
_TWO_WORDS = re.compile(r"\b(move|turn)[\s_-]+(forward|backward|left|right)\b")
_TOKENS = re.compile(r"[a-z_]+|\d+")


def parse_action_value(value: object) -> Action | None:
    """The one action a value names — `turn_left`, `Turn left`, `2`, `2 (turn_left)`, an int — or
    None when it names none, several, or anything else besides.
    """
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return Action(value) if 0 <= value < len(ACTION_NAMES) else None
    if not isinstance(value, str):
        return None
    text = _TWO_WORDS.sub(r"\1_\2", value.lower().replace("-", "_"))
    found: set[Action] = set()
    for token in _TOKENS.findall(text):
        if token in _BY_NAME:
            found.add(_BY_NAME[token])
        elif token.isdigit() and int(token) < len(ACTION_NAMES):
            found.add(Action(int(token)))
        else:
            return None
    return found.pop() if len(found) == 1 else None


def parse_answer(text: str | None, constrained: str = "none") -> ParsedAnswer:
    """Parses a model answer: JSON `{"thought", "action"}` when `constrained` is `json_schema`,
    else the `Thought: ...` / `Action: NAME` text. Strict: exactly one `Action:` line naming exactly
    one action (by name or code); an answer that is nothing but one action name is accepted too.
    """
    if text is None or not text.strip():
        return ParsedAnswer(None, "", "the answer was empty", "empty")
    if constrained == "json_schema":
        return _parse_json(text)
    thinking = " ".join(block.strip() for block in _THINK.findall(text))
    body = _THINK.sub("", text).replace("*", "").replace("`", "")
    lines = body.splitlines()
    action_lines = [i for i, line in enumerate(lines) if _ACTION_LINE.match(line)]
    if not action_lines:
        bare = parse_action_value(body.strip().rstrip("."))
        if bare is not None and len(_TOKENS.findall(body.lower())) <= 2:
            return ParsedAnswer(bare, thinking)
        return ParsedAnswer(None, _join(thinking, body.strip()), "it has no 'Action:' line", "no_action")
    if len(action_lines) > 1:
        return ParsedAnswer(
            None, _join(thinking, body.strip()), "it has several 'Action:' lines", "several_actions"
        )
    index = action_lines[0]
    match = _ACTION_LINE.match(lines[index])
    assert match is not None
    value = match.group(1).strip().strip("'\"").rstrip(".").strip()
    thought = "\n".join(lines[:index]).strip()
    thought = _THOUGHT_LINE.sub("", thought, count=1).strip()
    thought = _join(thinking, thought)
    action = parse_action_value(value)
    if action is None:
        return ParsedAnswer(
            None, thought, f"'Action: {value}' does not name exactly one action", "not_one_action"
        )
    return ParsedAnswer(action, thought)


def _parse_json(text: str) -> ParsedAnswer:
    body = text.strip()
    fenced = re.fullmatch(r"```(?:json)?\s*(.*?)\s*```", body, re.DOTALL)
    if fenced:
        body = fenced.group(1)
    try:
        answer = json.loads(body)
    except ValueError:
        return ParsedAnswer(None, text.strip(), "it is not a JSON object", "not_json")
    if not isinstance(answer, dict) or "action" not in answer:
        return ParsedAnswer(None, text.strip(), "it is not a JSON object with an 'action'", "not_json")
    thought = answer.get("thought")
    thought = thought.strip() if isinstance(thought, str) else ""
    action = parse_action_value(answer["action"])
    if action is None:
        error = f"'action': {json.dumps(answer['action'])} does not name exactly one action"
        return ParsedAnswer(None, thought, error, "not_one_action")
    return ParsedAnswer(action, thought)


def _join(first: str, second: str) -> str:
    return "\n".join(part for part in (first, second) if part)


# ---------------------------------------------------------------------------------------------
# The agent


@dataclass
class _Call:
    """One model call: its answer and costs."""

    content: str | None
    finish_reason: str | None
    model_reasoning: str | None
    usage: dict[str, int] | None
    latency_s: float
    queued_s: float
    http_retries: int


class VlmAgentFactory:
    """`esrp eval --agent vlm`'s factory: made once per run with the agent config, then called once
    per episode. Holds what the episodes share: the `openai.AsyncOpenAI` client, the semaphore of
    `max_concurrent_requests` (created here, so every agent of the run waits on the same one), and
    the trace folder.

    Args:
        config: The agent config (`VlmSettings.from_config`; `ValueError` when it is wrong).
        results_path: The results file; the traces go to `default_trace_dir(results_path)` unless
            the config names `trace_dir`. Neither: no traces.
        client: An `openai.AsyncOpenAI` to use instead of one made from the settings (tests).
    """

    def __init__(
        self,
        config: Mapping[str, Any],
        *,
        results_path: Path | None = None,
        client: Any = None,  # noqa: ANN401 - openai.AsyncOpenAI, imported lazily
    ) -> None:
        self.settings = VlmSettings.from_config(config)
        if client is None:
            try:
                import openai
            except ImportError as error:
                raise ValueError("the vlm agent needs the openai package: pip install 'esrp[vlm]'") from error
            client = openai.AsyncOpenAI(
                api_key=api_key(),
                base_url=self.settings.base_url,
                max_retries=self.settings.max_retries,
                timeout=self.settings.timeout_s,
            )
        self.client = client
        self.semaphore = asyncio.Semaphore(self.settings.max_concurrent_requests)
        self.trace_dir: Path | None = None
        if self.settings.traces:
            if self.settings.trace_dir is not None:
                self.trace_dir = Path(self.settings.trace_dir)
            elif results_path is not None:
                self.trace_dir = default_trace_dir(results_path)

    def __call__(self, config: Mapping[str, Any] | None = None) -> VlmAgent:
        """A new agent for one episode (the config was read when the factory was made)."""
        return VlmAgent(self)

    async def aclose(self) -> None:
        """Closes the HTTP client (the runner calls it at the end of the run)."""
        close = getattr(self.client, "close", None)
        if close is not None:
            await close()


class VlmAgent:
    """One episode of ESRP-VLM (an `AsyncAgent`); made by `VlmAgentFactory`."""

    def __init__(self, factory: VlmAgentFactory) -> None:
        self.factory = factory
        self.settings = factory.settings
        self._system = system_prompt(self.settings.constrained)
        self._history: list[HistoryEntry] = []
        self._previous: Observation | None = None
        self._previous_action: Action | None = None
        self._goal_png = b""
        self._info: dict[str, Any] = {}
        self._steps = 0
        self._trace: Path | None = None
        self._stats: dict[str, Any] = {}
        self._latencies: list[float] = []

    async def reset(self, observation: Observation, info: Mapping[str, Any]) -> None:
        """Starts an episode: encodes the goal image once, starts the trace (a rerun overwrites it)."""
        if observation.goal_rgb is None:
            raise ValueError("the vlm agent needs the goal image in the first observation")
        self._info = dict(info)
        self._goal_png = encode_png(observation.goal_rgb, self.settings.image_scale)
        self._history = []
        self._previous = observation
        self._previous_action = None
        self._steps = 0
        self._latencies = []
        self._stats = {
            "model": self.settings.model,
            "steps": 0,
            "requests": 0,
            "invalid_answers": 0,
            "invalid_kinds": {},
            "reprompts": 0,
            "fallbacks": 0,
            "http_retries": 0,
            "prompt_tokens": 0,
            "completion_tokens": 0,
            "total_tokens": 0,
            "requests_without_usage": 0,
            "model_seconds": 0.0,
            "model_seconds_mean": 0.0,
            "model_seconds_max": 0.0,
            "queue_seconds": 0.0,
            "trace": None,
        }
        directory = self.factory.trace_dir
        if directory is not None:
            directory.mkdir(parents=True, exist_ok=True)
            self._trace = directory / trace_file_name(str(info.get("scene_id", "episode")))
            self._stats["trace"] = str(self._trace)
            self._trace.write_text("", encoding="utf-8")
            self._write(
                {
                    "type": "episode",
                    "scene_id": info.get("scene_id"),
                    "episode_id": info.get("episode_id"),
                    "seed": info.get("seed"),
                    "horizon": info.get("horizon"),
                    "model": self.settings.model,
                    "base_url": self.settings.base_url,
                    "constrained": self.settings.constrained,
                    "system_prompt": self._system,
                    "goal_image": _image_note(self._goal_png, observation.goal_rgb.shape),
                }
            )

    async def act(self, observation: Observation) -> Action | None:
        """Asks the model for the next action; None once `max_steps` actions were taken."""
        if self.settings.max_steps is not None and self._steps >= self.settings.max_steps:
            return None
        if self._previous_action is not None and self._previous is not None:
            entry = HistoryEntry(
                self._steps,
                self._previous_action,
                outcome_of(self._previous_action, self._previous, observation),
            )
            self._history.append(entry)
        horizon = int(self._info.get("horizon") or 0) or self._steps + 1
        recent = self._history[-self.settings.history :] if self.settings.history else []
        text = user_text(self._steps, horizon, observation.grasping, recent)
        ego_png = encode_png(observation.ego_rgb, self.settings.image_scale)
        messages: list[dict[str, Any]] = [
            {"role": "system", "content": self._system},
            {
                "role": "user",
                "content": [
                    {"type": "text", "text": text},
                    {"type": "image_url", "image_url": {"url": _data_url(ego_png)}},
                    {"type": "image_url", "image_url": {"url": _data_url(self._goal_png)}},
                ],
            },
        ]
        attempts: list[dict[str, Any]] = []
        action: Action | None = None
        for attempt in range(self.settings.reprompts + 1):
            call = await self._complete(messages)
            parsed = parse_answer(call.content, self.settings.constrained)
            attempts.append(
                {
                    "answer": call.content,
                    "thought": parsed.thought,
                    "model_reasoning": call.model_reasoning,
                    "action": None if parsed.action is None else parsed.action.api_name,
                    "error": parsed.error,
                    "finish_reason": call.finish_reason,
                    "usage": call.usage,
                    "latency_s": round(call.latency_s, 4),
                    "queued_s": round(call.queued_s, 4),
                    "http_retries": call.http_retries,
                }
            )
            if parsed.action is not None:
                action = parsed.action
                break
            self._stats["invalid_answers"] += 1
            kinds = self._stats["invalid_kinds"]
            kinds[parsed.kind or "other"] = kinds.get(parsed.kind or "other", 0) + 1
            if attempt < self.settings.reprompts:
                self._stats["reprompts"] += 1
                messages = [
                    *messages,
                    {"role": "assistant", "content": call.content or ""},
                    {
                        "role": "user",
                        "content": correction_message(parsed.error or "", self.settings.constrained),
                    },
                ]
        source = "model"
        if action is None:
            action = self.settings.fallback
            source = "fallback"
            self._stats["fallbacks"] += 1
        self._steps += 1
        self._stats["steps"] = self._steps
        self._previous = observation
        self._previous_action = action
        self._write(
            {
                "type": "step",
                "step": self._steps,
                "prompt": text,
                "grasping": observation.grasping,
                "ego_image": _image_note(ego_png, observation.ego_rgb.shape),
                "attempts": attempts,
                "action": action.api_name,
                "source": source,
            }
        )
        return action

    async def _complete(self, messages: list[dict[str, Any]]) -> _Call:
        settings = self.settings
        request: dict[str, Any] = {
            "model": settings.model,
            "messages": messages,
            "temperature": settings.temperature,
            "max_tokens": settings.max_tokens,
        }
        extra_body = dict(settings.extra_body)
        if settings.constrained == "json_schema":
            request["response_format"] = {
                "type": "json_schema",
                "json_schema": {"name": "esrp_action", "strict": True, "schema": _JSON_SCHEMA},
            }
        elif settings.constrained == "vllm":
            extra_body["structured_outputs"] = {"regex": _ACTION_REGEX}
        elif settings.constrained == "vllm-guided":
            extra_body["guided_regex"] = _ACTION_REGEX
        if extra_body:
            request["extra_body"] = extra_body
        if settings.send_seed and self._info.get("seed") is not None:
            request["seed"] = int(self._info["seed"]) & 0x7FFF_FFFF_FFFF_FFFF
        queued = time.monotonic()
        async with self.factory.semaphore:
            started = time.monotonic()
            raw = await self.factory.client.chat.completions.with_raw_response.create(**request)
            latency = time.monotonic() - started
        completion = raw.parse()
        retries = int(getattr(raw, "retries_taken", 0) or 0)
        choice = completion.choices[0] if completion.choices else None
        message = None if choice is None else choice.message
        extra = (getattr(message, "model_extra", None) or {}) if message is not None else {}
        reasoning = extra.get("reasoning_content") or extra.get("reasoning")
        usage = None
        if completion.usage is not None:
            usage = {
                "prompt_tokens": int(completion.usage.prompt_tokens or 0),
                "completion_tokens": int(completion.usage.completion_tokens or 0),
                "total_tokens": int(completion.usage.total_tokens or 0),
            }
        self._count(latency, started - queued, retries, usage)
        return _Call(
            content=None if message is None else message.content,
            finish_reason=None if choice is None else choice.finish_reason,
            model_reasoning=reasoning if isinstance(reasoning, str) else None,
            usage=usage,
            latency_s=latency,
            queued_s=started - queued,
            http_retries=retries,
        )

    def _count(self, latency: float, queued: float, retries: int, usage: dict[str, int] | None) -> None:
        stats = self._stats
        stats["requests"] += 1
        stats["http_retries"] += retries
        stats["queue_seconds"] += queued
        self._latencies.append(latency)
        stats["model_seconds"] = sum(self._latencies)
        stats["model_seconds_mean"] = stats["model_seconds"] / len(self._latencies)
        stats["model_seconds_max"] = max(self._latencies)
        if usage is None:
            stats["requests_without_usage"] += 1
        else:
            for key, value in usage.items():
                stats[key] += value

    def _write(self, line: Mapping[str, Any]) -> None:
        if self._trace is not None:
            with self._trace.open("a", encoding="utf-8") as file:
                file.write(json.dumps(line, separators=(",", ":")) + "\n")

    def stats(self) -> dict[str, Any]:
        """The episode's counts (the record's `agent_stats`); also closes the trace with them.

        `steps` actions taken; `requests` model calls (a correction is one more); `invalid_answers`
        unusable answers by `invalid_kinds`; `reprompts` corrections asked; `fallbacks` steps that
        played `fallback_action`; `http_retries` retries the `openai` client made (429, 5xx,
        timeouts); token counts summed from the answers' `usage` (`requests_without_usage` had
        none); `model_seconds` (sum, mean, max) the calls' latency; `queue_seconds` the time spent
        waiting for the concurrency limit; `trace` the trace file.
        """
        stats = dict(self._stats)
        stats["invalid_kinds"] = dict(stats.get("invalid_kinds", {}))
        for key in ("model_seconds", "model_seconds_mean", "model_seconds_max", "queue_seconds"):
            if key in stats:
                stats[key] = round(float(stats[key]), 6)
        self._write({"type": "end", "stats": stats})
        return stats
