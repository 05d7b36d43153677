"""ESRP-VLM's strict reading of a model's answer: exactly one action, by name or code."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

from ..._values import Action
from ._prompt import _BY_NAME, ACTION_NAMES

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


_THINK_TAG = re.compile(r"<(/?)think>", re.IGNORECASE)
# Linear: no lazy group before a `\s*$` (quadratic in a long run of spaces); the value is stripped.
_ACTION_LINE = re.compile(r"^\s*(?:[-#>]\s*)*action\s*:(.*)$", re.IGNORECASE)
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
    blocks, body = _split_thinking(text)
    thinking = " ".join(block.strip() for block in blocks)
    body = body.replace("*", "").replace("`", "")
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
        shown = value if len(value) <= 80 else value[:77] + "..."  # the correction quotes it
        return ParsedAnswer(
            None, thought, f"'Action: {shown}' does not name exactly one action", "not_one_action"
        )
    return ParsedAnswer(action, thought)


def _split_thinking(text: str) -> tuple[list[str], str]:
    """The `<think>...</think>` blocks of `text` and what is left around them, in one pass (a
    regex per block rescans the rest of the text for each unclosed `<think>`: quadratic in an
    answer that repeats it). Text before a first `</think>` that no `<think>` opened is a block
    too: a chat template that opens the block in the prompt (a thinking model served without a
    reasoning parser) leaves only its end in the answer. An unclosed `<think>` stays in the text.
    """
    tags = [(m.start(), m.end(), m.group(1) == "/") for m in _THINK_TAG.finditer(text)]
    blocks: list[str] = []
    kept: list[str] = []
    position = 0
    index = 0
    if tags and tags[0][2]:
        blocks.append(text[: tags[0][0]])
        position, index = tags[0][1], 1
    while index < len(tags):
        start, end, closing = tags[index]
        if closing:  # a stray end tag: left in the text
            index += 1
            continue
        close = next((i for i in range(index + 1, len(tags)) if tags[i][2]), None)
        if close is None:
            break
        kept.append(text[position:start])
        blocks.append(text[end : tags[close][0]])
        position, index = tags[close][1], close + 1
    kept.append(text[position:])
    return blocks, "".join(kept)


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
