"""ESRP-VLM's prompt: the action names, the system prompt, the correction message, the user
message with its history of what each action visibly did, and the images as PNG data URLs.
"""

from __future__ import annotations

import base64
import hashlib
import io
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..._values import Action, Observation

ACTION_NAMES: tuple[str, ...] = tuple(action.api_name for action in Action)
"""The action names in code order: `move_forward` (0) ... `release` (5)."""

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
