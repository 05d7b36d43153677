"""Process-wide gRPC core settings, applied when `esrp` is imported, before anything imports grpc.

grpcio reads `GRPC_EXPERIMENTS` once, when its core starts (at `import grpc`). On its
EventEngine client path every unary call's answer is read on an EventEngine thread and handed to
the calling thread; with the experiment `event_engine_client` off, the calling thread polls the
socket itself. Measured 2026-11-24 on the 2-core development VM with grpcio 1.85.1, a unary
`Step` (the single env's whole call) cost the client 155-165 µs of CPU instead of 235-255 µs, and
480-520 µs of wall time instead of 570-615 µs. So `import esrp` sets
`GRPC_EXPERIMENTS=-event_engine_client` unless:

- `GRPC_EXPERIMENTS` is already set (even to an empty string): the user's choice stands;
- `grpc` was imported before `esrp`: its core has read the variable already (set it yourself, or
  import esrp first);
- the installed grpcio is not a version this was measured with (`MEASURED`): an experiment that a
  newer grpcio no longer has would only be logged as unknown.

`APPLIED` records whether it was set. Child processes (an esrp-server started by `LocalServer`,
Ray workers) inherit the variable; the Rust server ignores it.
"""

from __future__ import annotations

import importlib.metadata
import os
import sys

#: grpcio (major, minor) versions the setting was measured with.
MEASURED = ((1, 85),)

#: The value set.
EXPERIMENTS = "-event_engine_client"


def _grpcio_version() -> tuple[int, int] | None:
    try:
        major, minor = importlib.metadata.version("grpcio").split(".")[:2]
        return int(major), int(minor)
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return None


def apply() -> bool:
    """Sets `GRPC_EXPERIMENTS` as the module docs say; True when it did."""
    if "GRPC_EXPERIMENTS" in os.environ or "grpc" in sys.modules:
        return False
    if _grpcio_version() not in MEASURED:
        return False
    os.environ["GRPC_EXPERIMENTS"] = EXPERIMENTS
    return True


APPLIED = apply()
