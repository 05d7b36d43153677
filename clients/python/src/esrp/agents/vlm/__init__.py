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
honouring `Retry-After`); a request that still fails, any other HTTP error (401, 404...), or an
answer that is not a chat completion raises `VlmEndpointError`, which fails the episode. Each
episode writes a trace (JSON Lines, `trace_dir/<scene>.jsonl`): the prompt text, image sizes and
hashes, each answer with its thought, usage and latency.
The package's modules: `_settings` (`VlmSettings`, the API key, trace paths), `_prompt` (the
prompt and the images), `_parse` (reading an answer); the agent and its factory are here.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import json
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..._values import Action, Observation
from ._parse import ParsedAnswer, parse_action_value, parse_answer
from ._prompt import (
    _ACTION_REGEX,
    _JSON_SCHEMA,
    ACTION_NAMES,
    CONSTRAINED_MODES,
    HistoryEntry,
    _data_url,
    _image_note,
    correction_message,
    encode_png,
    outcome_of,
    system_prompt,
    user_text,
)
from ._settings import API_KEY_VARIABLES, VlmSettings, api_key, default_trace_dir, trace_file_name

__all__ = [
    "ACTION_NAMES",
    "API_KEY_VARIABLES",
    "CONSTRAINED_MODES",
    "HistoryEntry",
    "ParsedAnswer",
    "VlmAgent",
    "VlmAgentFactory",
    "VlmEndpointError",
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


# ---------------------------------------------------------------------------------------------
# The agent


class VlmEndpointError(RuntimeError):
    """The model endpoint failed a request for good (after the `openai` client's retries): it
    refused the connection, timed out, answered an HTTP error, or answered something that is not a
    chat completion. It fails the episode (not recorded; a rerun retries it); the message names
    the endpoint and what to check.

    Attributes:
        stops_run: The endpoint refused the request for a reason every request meets (HTTP 401 or
            403: the API key; 404: the URL or the model), or could not be reached at all after the
            retries: `esrp eval` stops the run there instead of failing every episode in turn
            (`esrp.eval.evaluation.AgentStopped`).
    """

    def __init__(self, message: str, *, stops_run: bool = False) -> None:
        super().__init__(message)
        self.stops_run = stops_run


_LASTING = (401, 403, 404)
"""The HTTP statuses that every request of the run would get too: a wrong key, URL or model."""


def _endpoint_error(error: Exception, settings: VlmSettings) -> VlmEndpointError | None:
    """`error` (raised by the `openai` client) as a `VlmEndpointError`, or None if it is not one of
    the client's.
    """
    try:
        import openai
    except ImportError:  # a client passed in (tests) without the package
        return None
    where = f"the model endpoint {settings.base_url or '(OPENAI_BASE_URL, else OpenAI)'}"
    retried = f"after {settings.max_retries} retries" if settings.max_retries else "(max_retries 0)"
    if isinstance(error, openai.APITimeoutError):
        timeout = f"timeout_s {settings.timeout_s:g} s"
        return VlmEndpointError(f"{where} did not answer within {timeout}, {retried}")
    if isinstance(error, openai.APIConnectionError):
        # Still unreachable after the client's retries (seconds of backoff): every episode would
        # wait as long and fail the same way, so the run stops here (a rerun resumes).
        return VlmEndpointError(
            f"{where} could not be reached {retried}: is it running? (--base-url)", stops_run=True
        )
    if isinstance(error, openai.APIStatusError):
        status = error.status_code
        body = error.body
        said = body.get("message") if isinstance(body, dict) else body  # the error object's message
        message = " ".join(str(said if said is not None else error.message).split())[:200]
        hint = {
            401: "; check the API key (ESRP_VLM_API_KEY, else OPENAI_API_KEY)",
            403: "; check the API key (ESRP_VLM_API_KEY, else OPENAI_API_KEY)",
            404: f"; check --base-url (e.g. http://localhost:8000/v1) and --model {settings.model!r}",
        }.get(status, "")
        if status in (408, 409, 429) or status >= 500:
            hint = f" {retried}" + hint
        return VlmEndpointError(
            f"{where} answered HTTP {status} ({message}){hint}", stops_run=status in _LASTING
        )
    return None


def _usage_of(usage: object) -> dict[str, int] | None:
    """A completion's token counts, or None when it has none (or ones that are not numbers)."""
    keys = ("prompt_tokens", "completion_tokens", "total_tokens")
    values = [getattr(usage, key, None) for key in keys]
    if all(value is None for value in values) or any(
        value is not None and (isinstance(value, bool) or not isinstance(value, int)) for value in values
    ):
        return None
    return {key: int(value or 0) for key, value in zip(keys, values, strict=True)}


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

    settings_free_on_resume = frozenset(
        {"max_concurrent_requests", "timeout_s", "max_retries", "trace_dir", "traces"}
    )
    """Settings a resumed `esrp eval` may change: how requests are made and where traces go,
    not what the model is asked or answers."""

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
        settings = dataclasses.asdict(self.settings)
        for where in ("trace_dir", "traces"):  # where the traces go: no part of what was asked
            settings.pop(where)
        self._stats = {
            "model": self.settings.model,
            "served_models": [],
            "settings": settings,
            "system_prompt_sha256": hashlib.sha256(self._system.encode()).hexdigest(),
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
        """One chat completion; an endpoint failure never carries the API key, where the endpoint
        echoed it in its error text (its message blanks it out, and the `openai` error that held it
        is not chained: the errors log prints the chain).
        """
        try:
            return await self._request(messages)
        except VlmEndpointError as error:
            key = getattr(self.factory.client, "api_key", None)
            if not isinstance(key, str) or len(key) < 4 or key == "EMPTY":
                raise
            if key not in str(error) and key not in str(error.__cause__ or ""):
                raise
            message = str(error).replace(key, "[the API key]")
            raise VlmEndpointError(message, stops_run=error.stops_run) from None

    async def _request(self, messages: list[dict[str, Any]]) -> _Call:
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
            try:
                raw = await self.factory.client.chat.completions.with_raw_response.create(**request)
            except Exception as error:
                endpoint = _endpoint_error(error, settings)
                if endpoint is None:
                    raise
                raise endpoint from error
            latency = time.monotonic() - started
        completion = raw.parse()
        where = f"the model endpoint {settings.base_url or '(OPENAI_BASE_URL, else OpenAI)'}"
        if not hasattr(completion, "choices"):  # a 200 whose body is no JSON object (a proxy's page)
            kind = raw.headers.get("content-type", "no content type")
            body = " ".join(str(completion).split())[:80]
            raise VlmEndpointError(
                f"{where} answered HTTP 200 but not a chat completion ({kind}: {body!r}): is "
                "--base-url the API's (e.g. http://localhost:8000/v1)?"
            )
        choices = completion.choices
        failed = (getattr(completion, "model_extra", None) or {}).get("error")
        if failed is not None and not choices:
            # Some gateways answer an upstream failure with status 200 and an error object: an
            # endpoint failure, not an empty answer (which would be played as the fallback).
            said = failed.get("message", failed) if isinstance(failed, dict) else failed
            text = " ".join(str(said).split())[:200]
            raise VlmEndpointError(
                f"{where} answered HTTP 200 with an error instead of a completion ({text})"
            )
        choice = choices[0] if isinstance(choices, list) and choices else None
        message = getattr(choice, "message", None)
        content = getattr(message, "content", None)
        if isinstance(content, list) and all(isinstance(part, dict) for part in content):
            # Content parts (`[{"type": "text", "text": ...}]`): the text ones, in order.
            texts = [part.get("text") for part in content if part.get("type") == "text"]
            if all(isinstance(text, str) for text in texts):
                content = "".join(texts)
        if (
            not isinstance(choices, list)
            or (choice is not None and not hasattr(choice, "message"))
            or (message is not None and not hasattr(message, "content"))
            or not isinstance(content, (str, type(None)))
        ):
            body = " ".join(str(completion.to_dict(warnings=False)).split())[:120]
            raise VlmEndpointError(f"{where} answered HTTP 200 but not a chat completion ({body!r})")
        retries = int(getattr(raw, "retries_taken", 0) or 0)
        extra = (getattr(message, "model_extra", None) or {}) if message is not None else {}
        reasoning = extra.get("reasoning_content") or extra.get("reasoning")
        usage = _usage_of(getattr(completion, "usage", None))
        served = getattr(completion, "model", None)
        if isinstance(served, str) and served not in self._stats["served_models"]:
            self._stats["served_models"].append(served)
        self._count(latency, started - queued, retries, usage)
        return _Call(
            content=content,
            finish_reason=getattr(choice, "finish_reason", None),
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

        `model` the model asked for, `served_models` the names the answers gave (a dated snapshot
        of an alias, a server's own name), `settings` every setting in effect (defaults included;
        not where the traces go), `system_prompt_sha256` the prompt's hash; `steps` actions taken;
        `requests` model calls (a correction is one more); `invalid_answers` unusable answers by
        `invalid_kinds`; `reprompts` corrections asked; `fallbacks` steps that played
        `fallback_action`; `http_retries` retries the `openai` client made (429, 5xx, timeouts);
        token counts summed from the answers' `usage` (`requests_without_usage` had none);
        `model_seconds` (sum, mean, max) the calls' latency; `queue_seconds` the time spent waiting
        for the concurrency limit; `trace` the trace file.
        """
        stats = dict(self._stats)
        stats["invalid_kinds"] = dict(stats.get("invalid_kinds", {}))
        stats["served_models"] = list(stats.get("served_models", []))
        for key in ("model_seconds", "model_seconds_mean", "model_seconds_max", "queue_seconds"):
            if key in stats:
                stats[key] = round(float(stats[key]), 6)
        self._write({"type": "end", "stats": stats})
        return stats
