"""What the settings tables of the learned baselines (`[bc]`, `[ppo]`, `[dagger]`, `[ppo_bc]`)
check alike when read from a mapping: no unknown key, each value of its field's kind, and numbers
in range; and the same of an agent's config (`--agent-config`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import fields
from pathlib import Path
from typing import Any

_KINDS = {"int": "an integer", "float": "a number", "bool": "true or false", "str": "a string"}


def reject_unknown(settings: type[Any], values: Mapping[str, Any], table: str) -> None:
    """Raises `ValueError` naming the keys of `values` that are not fields of the dataclass
    `settings`, and the known ones (`table`: the table's name in the message).
    """
    known = {f.name for f in fields(settings)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown {table} settings {unknown}: known are {sorted(known)}")


def _is_kind(value: object, kind: str) -> bool:
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "int":
        return isinstance(value, int) and not isinstance(value, bool)
    if kind == "float":
        return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    return isinstance(value, str)


def check_kinds(settings: Any, table: str) -> None:  # noqa: ANN401 - any settings dataclass
    """Raises `ValueError` naming the first field of the dataclass instance `settings` whose value
    is not of its annotated kind: `int`, `float` (finite; an integer is a number), `bool` or `str`,
    or one of them or None. A TOML or JSON value of another kind (`"2"` or `2.5` for an integer,
    `true` for a number) is refused by name before anything is built from it. Fields of other
    annotations (lists, tables) are their own checks'.
    """
    for f in fields(settings):
        annotation = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
        kinds = [part.strip() for part in annotation.split("|")]
        optional = "None" in kinds
        kinds = [kind for kind in kinds if kind != "None"]
        if len(kinds) != 1 or kinds[0] not in _KINDS:
            continue
        value = getattr(settings, f.name)
        if (value is None and optional) or _is_kind(value, kinds[0]):
            continue
        absent = " (or absent)" if optional else ""
        raise ValueError(f"{table} setting {f.name} must be {_KINDS[kinds[0]]}{absent}, not {value!r}")


def check_at_least(settings: Any, table: str, minimum: float, names: Iterable[str]) -> None:  # noqa: ANN401
    """Raises `ValueError` for the first of the fields `names` of `settings` below `minimum` (a
    field that is None, where it may be, is not checked).
    """
    for name in names:
        value = getattr(settings, name)
        if value is not None and value < minimum:
            raise ValueError(f"{table} setting {name} must be at least {minimum}, not {value!r}")


def check_agent_config(config: Mapping[str, Any], agent: str, known: Mapping[str, str]) -> None:
    """Raises `ValueError` for a key of an agent's config (`--agent-config`) that is not one of
    `known` (each key's kind: `bool`, `int`, `positive`, `probability` or `path`), or a value not of its kind:
    a misspelt `deterministic` must not leave a researcher's run sampling. A `positive` int is at
    least 1.
    """
    unknown = sorted(set(config) - set(known))
    if unknown:
        which = f"known are {', '.join(known)}" if known else "it takes none"
        raise ValueError(f"the {agent} agent has no setting {', '.join(unknown)}: {which}")
    for key, kind in known.items():
        value = config.get(key)
        if value is None:
            continue
        number = isinstance(value, int | float) and not isinstance(value, bool)
        fits = {
            "bool": isinstance(value, bool),
            "int": isinstance(value, int) and not isinstance(value, bool),
            "positive": isinstance(value, int) and not isinstance(value, bool) and value >= 1,
            "probability": number and 0.0 <= value <= 1.0,
            "path": isinstance(value, str | Path),
        }[kind]
        if not fits:
            wanted = {
                "bool": "true or false",
                "int": "an integer",
                "positive": "an integer of at least 1",
                "probability": "a number from 0 to 1",
            }
            raise ValueError(f"the {agent} agent's {key} must be {wanted.get(kind, 'a path')}, not {value!r}")
