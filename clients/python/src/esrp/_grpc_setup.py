"""Opt-in gRPC core settings: `apply()` sets `GRPC_EXPERIMENTS=-event_engine_client`.

grpcio reads `GRPC_EXPERIMENTS` once, when its core starts (at `import grpc`). With the experiment
`event_engine_client` off, the thread that makes a unary call polls the socket itself instead of
being handed the answer by an EventEngine thread, which costs a synchronous unary call (the single
env's `Step` over grpcio) about a third less client CPU (docs/performance.md).

`apply()` sets the variable unless:

- `GRPC_EXPERIMENTS` is already set (even to an empty string): the user's choice stands;
- `grpc` is imported already: its core has read the variable (nothing would change);
- the installed grpcio is not a version this was measured with (`MEASURED`): an experiment that a
  newer grpcio no longer has would only be logged as unknown.

Who calls it: `import esrp` does not (nor does it import grpc: its names are imported on first use).
The `esrp` command (`esrp.cli.main`) and `python -m esrp.bench` call it first, before anything
imports grpc, so there it applies. It cannot apply in a process that made a client before: the vector
env and the training loops run after a `Client` exists, so they get it only through the command that
started them (`esrp train ppo`) or through a user who calls `esrp._grpc_setup.apply()` (or sets the
variable) before the first client. Child processes (an esrp-server started by `LocalServer`, Ray
workers) inherit the variable; the Rust server ignores it.
"""

from __future__ import annotations

import importlib.metadata
import os
import sys

#: grpcio (major, minor) versions the setting was measured with.
MEASURED = ((1, 85),)

#: The value set.
EXPERIMENTS = "-event_engine_client"

#: Whether `apply()` set the variable (in this process).
APPLIED = False


def _grpcio_version() -> tuple[int, int] | None:
    try:
        major, minor = importlib.metadata.version("grpcio").split(".")[:2]
        return int(major), int(minor)
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return None


def apply() -> bool:
    """Sets `GRPC_EXPERIMENTS` as the module docs say; True when it is set by this module (now or
    by an earlier call: calling again changes nothing).
    """
    global APPLIED
    if APPLIED:
        return True
    if "GRPC_EXPERIMENTS" in os.environ or "grpc" in sys.modules:
        return False
    if _grpcio_version() not in MEASURED:
        return False
    os.environ["GRPC_EXPERIMENTS"] = EXPERIMENTS
    APPLIED = True
    return True
