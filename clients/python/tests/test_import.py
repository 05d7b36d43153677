"""`import esrp` leaves the process as it was: no environment variable set or changed, glibc malloc's
thresholds untouched, neither grpc nor gymnasium imported; checked in a fresh interpreter."""

from __future__ import annotations

import os
import subprocess
import sys

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


def test_every_public_name_resolves() -> None:
    import esrp

    # Each name of `esrp.__all__` is imported from its module on first use (esrp/__init__).
    assert all(getattr(esrp, name) is not None for name in esrp.__all__)
    assert set(esrp.__all__) <= set(dir(esrp))
