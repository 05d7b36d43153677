"""`import esrp` leaves the process as it was: no environment variable set or changed, glibc malloc's
thresholds untouched, neither grpc nor gymnasium imported; checked in a fresh interpreter. Its
public names resolve, each to its module's, and type checkers see the same names."""

from __future__ import annotations

import ast
import importlib
import os
import subprocess
import sys
from pathlib import Path

# The probe of where a 20 MiB buffer lands (`anonymous`: a mapping of its own, glibc's default
# threshold; `[heap]`: raised), and the skip where that cannot be told (not glibc).
from test_malloc_setup import _VARIABLES, WHERE, pytestmark  # noqa: F401

# The environment before and after the import and the modules it loaded; then where the buffer
# lands; then two public names, imported on first use.
PROBE = (
    """
import os, sys
before = dict(os.environ)
import esrp
changed = sorted(set(os.environ.items()) ^ set(before.items()))
print(changed, sorted(name for name in ("grpc", "gymnasium") if name in sys.modules))
import esrp._malloc_setup as s
"""
    + WHERE
    + "print(esrp.Client.__name__, esrp.Action.LEFT.name)\n"
)


def test_import_changes_nothing() -> None:
    environment = {k: v for k, v in os.environ.items() if k not in (*_VARIABLES, "GRPC_EXPERIMENTS")}
    command = [sys.executable, "-c", PROBE]
    done = subprocess.run(command, env=environment, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[:3] == ["[] []", "False anonymous", "Client LEFT"]


def test_import_imports_no_module_of_a_public_name() -> None:
    probe = "import sys, esrp; print(sorted(name for name in sys.modules if name.startswith('esrp')))"
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "['esrp', 'esrp._registration']"


def test_every_public_name_resolves() -> None:
    import esrp

    # Each name of `esrp.__all__` is imported from its module on first use (esrp/__init__).
    assert all(getattr(esrp, name) is not None for name in esrp.__all__)
    assert set(esrp.__all__) <= set(dir(esrp))
    exports = esrp._EXPORTS  # noqa: SLF001
    assert esrp.__all__ == [
        "ENV_ID",
        "__version__",
        *sorted(name for names in exports.values() for name in names),
    ]


# What a module declares in `__all__` for the package's own modules, not for `esrp`.
INTERNAL = {"._client": {"health_check"}, "._local": {"same_release"}}


def test_each_public_name_is_its_module_s() -> None:
    import esrp

    # `_EXPORTS` (esrp/__init__) names each module's `__all__` but the internal names above, and
    # `esrp.X` is the module's `X` (`_common`, `_values` and `_errors` have no `__all__`: only the second
    # check holds there).
    for module_name, names in esrp._EXPORTS.items():  # noqa: SLF001
        module = importlib.import_module(module_name, "esrp")
        declared = set(getattr(module, "__all__", names))
        assert declared - set(names) == INTERNAL.get(module_name, set()), module_name
        assert set(names) <= declared, module_name
        assert all(getattr(esrp, name) is getattr(module, name) for name in names)


def test_type_checkers_see_the_names_that_run() -> None:
    import esrp

    # The TYPE_CHECKING block of esrp/__init__ (what pyright and mypy read) imports the names of
    # `_EXPORTS` (what `__getattr__` imports), each from its module as a re-export (`X as X`).
    tree = ast.parse(Path(esrp.__file__).read_text(encoding="utf-8"))
    [block] = [
        node for node in tree.body if isinstance(node, ast.If) and ast.unparse(node.test) == "TYPE_CHECKING"
    ]
    seen: dict[str, list[str]] = {}
    for statement in block.body:
        assert isinstance(statement, ast.ImportFrom), ast.unparse(statement)
        assert statement.level == 1, ast.unparse(statement)
        for alias in statement.names:
            assert alias.asname == alias.name, ast.unparse(statement)
            seen.setdefault(f".{statement.module}", []).append(alias.name)
    exports = esrp._EXPORTS  # noqa: SLF001
    assert {module: sorted(names) for module, names in seen.items()} == {
        module: sorted(names) for module, names in exports.items()
    }
