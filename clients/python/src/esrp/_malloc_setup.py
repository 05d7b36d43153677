"""Opt-in glibc malloc settings: `apply()` raises malloc's mmap and trim thresholds with `mallopt`.

A vector env's step allocates a few buffers of megabytes each (the StepBatch answer as it arrives,
the batch of observations handed to the caller, the goals' copy) and frees them a step later.
glibc's defaults adjust their thresholds as the process goes, and depending on the order in which
buffers came and went, a process either kept that memory or gave it back to the system after every
step and faulted it in again page by page on the next. `apply()` makes the first behaviour certain
(docs/performance.md has the measurements): allocations below `MMAP_THRESHOLD` (32 MiB, glibc's
largest) come from the heap, and free memory at the top of a heap goes back to the system only
beyond `TRIM_THRESHOLD` (64 MiB), so a process keeps up to that much freed memory for its next
allocations. Nothing is set when:

- the C library is not glibc (musl, macOS, Windows): nothing to set;
- the user set malloc's thresholds already: any of `MALLOC_MMAP_THRESHOLD_`,
  `MALLOC_TRIM_THRESHOLD_`, `MALLOC_TOP_PAD_`, or a `glibc.malloc.` tunable in `GLIBC_TUNABLES`:
  their choice stands;
- `ESRP_KEEP_MALLOC_DEFAULTS` is set (to anything): glibc's own behaviour, adjusted as it goes.

Who calls it: `import esrp` does not. `RearrangeVectorEnv` (at construction), `python -m esrp.bench`
and the training loops do; a call at any time takes effect for the allocations that follow. Nothing
is put in the environment: child processes keep glibc's defaults.
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys

#: Allocations below this many bytes come from the heap rather than fresh mappings.
MMAP_THRESHOLD = 32 << 20

#: Free memory at the top of a heap beyond this many bytes goes back to the system.
TRIM_THRESHOLD = 64 << 20

#: Whether `apply()` made both settings (in this process).
APPLIED = False

# mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

_USER_VARIABLES = (
    "MALLOC_MMAP_THRESHOLD_",
    "MALLOC_TRIM_THRESHOLD_",
    "MALLOC_TOP_PAD_",
    "ESRP_KEEP_MALLOC_DEFAULTS",
)


def users_choice() -> bool:
    """Whether the environment sets malloc's thresholds already, or asks for glibc's defaults."""
    return any(name in os.environ for name in _USER_VARIABLES) or "glibc.malloc." in os.environ.get(
        "GLIBC_TUNABLES", ""
    )


def apply() -> bool:
    """Makes the settings as the module docs say; True when both are made (now or by an earlier
    call: calling again changes nothing).
    """
    global APPLIED
    if APPLIED:
        return True
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc" or users_choice():
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    APPLIED = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )
    return APPLIED
