"""Reading the training configs of `esrp train` (TOML, or JSON)."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path
from typing import Any

__all__ = ["TABLES", "read_document", "read_table"]

TABLES = ("bc", "dagger", "ppo", "ppo_bc")
"""The tables of the training configs (`esrp train bc`, `--dagger`, `ppo`, `ppo-bc`)."""


def read_document(path: Path) -> dict[str, Any]:
    """The whole of a TOML file (or of a JSON file holding an object). Raises `ValueError` naming
    the file for unreadable or malformed ones.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise ValueError(f"cannot read {path}: {error.strerror}") from None
    try:
        if path.suffix == ".json":
            values: Any = json.loads(text)
        else:
            # tomllib is Python 3.11's; on 3.10, tomli (the same parser) if installed.
            module = importlib.import_module("tomllib" if sys.version_info >= (3, 11) else "tomli")
            values = module.loads(text)
    except ValueError as error:  # JSONDecodeError and TOMLDecodeError are ValueErrors
        raise ValueError(f"{path}: {error}") from None
    if not isinstance(values, dict):
        raise ValueError(f"{path}: the file does not hold a table (a JSON object)")
    return values


def read_table(path: Path, name: str) -> dict[str, Any]:
    """The `[name]` table of a TOML file (or the top level of a JSON file, or of a TOML file without
    that table). Raises `ValueError` naming the file for unreadable or malformed ones, and for a
    file without that table that has another command's (`TABLES`).
    """
    values = read_document(path)
    others = sorted(key for key in TABLES if key != name and isinstance(values.get(key), dict))
    if name not in values and others:
        listed = ", ".join(f"[{key}]" for key in others)
        raise ValueError(
            f"{path} has no [{name}] table (it has {listed}): is it the config of another command?"
        )
    table = values.get(name, values)
    if not isinstance(table, dict):
        raise ValueError(f"{path}: [{name}] is not a table")
    return table
