"""What the settings tables of the learned baselines (`[bc]`, `[ppo]`, `[dagger]`, `[ppo_bc]`)
check alike when read from a mapping.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
from typing import Any


def reject_unknown(settings: type[Any], values: Mapping[str, Any], table: str) -> None:
    """Raises `ValueError` naming the keys of `values` that are not fields of the dataclass
    `settings`, and the known ones (`table`: the table's name in the message).
    """
    known = {f.name for f in fields(settings)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown {table} settings {unknown}: known are {sorted(known)}")
