"""ESRP-VLM's settings (`VlmSettings`, from `--agent-config` and flags), the API key, and where the
traces go.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import urllib.parse
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..._values import Action
from ._parse import parse_action_value
from ._prompt import ACTION_NAMES, CONSTRAINED_MODES

API_KEY_VARIABLES = ("ESRP_VLM_API_KEY", "OPENAI_API_KEY")
"""Where the API key is read from, first set wins; without either the key is `EMPTY` (a local
vLLM started without `--api-key` accepts any)."""


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
        temperature: Sampling temperature, 0 or more (0: greedy).
        max_tokens: The answer's token limit (`max_tokens`).
        history: How many past actions the prompt lists.
        image_scale: Each image is enlarged by this integer factor (nearest neighbour) before encoding.
        max_concurrent_requests: Model calls in flight at once, over all episodes of the run.
        timeout_s: One HTTP request's timeout, seconds (more than 0).
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
        if not (math.isfinite(settings.timeout_s) and settings.timeout_s > 0):
            raise ValueError(f"timeout_s must be more than 0 seconds, not {settings.timeout_s!r}")
        if not (math.isfinite(settings.temperature) and settings.temperature >= 0):
            raise ValueError(f"temperature must be 0 or more, not {settings.temperature!r}")
        if settings.max_steps is not None and settings.max_steps < 1:
            raise ValueError("max_steps must be at least 1")
        if settings.base_url is not None and urllib.parse.urlsplit(settings.base_url).password is not None:
            # The URL is recorded in every record, and said in every endpoint error.
            raise ValueError(
                "base_url holds a password: give the key in ESRP_VLM_API_KEY (sent as a bearer token, "
                "never recorded) and the URL without it"
            )
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
