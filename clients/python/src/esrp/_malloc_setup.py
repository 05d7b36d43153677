"""Process-wide glibc malloc settings, applied when `esrp` is imported.

A vector env's step allocates a few buffers of megabytes each (the StepBatch answer as it
arrives, the batch of observations handed to the caller, the goals' copy) and frees them a step
later. glibc's defaults adjust its thresholds as it goes: depending on the order in which the
buffers of the calling thread and of the transport's threads came and went, it either kept that
memory or gave it back to the system after every step, and then faulted it in again page by
page on the next (400 to 2,000 page faults per step of 64 envs, 1.5 to 3 ms of system CPU per
step). Which of the two a process got changed from run to run. Measured 2026-11-25 on the 2-core
development VM, `RearrangeVectorEnv` of 64 envs (native transport, 300 steps after 300): 6,000 to
7,700 steps/s with 35 to 1,900 faults per step, against 7,400 to 8,300 with 30 to 40 faults
per step with these settings in every run.

So `import esrp` calls `mallopt` to serve allocations below `MMAP_THRESHOLD` (32 MiB, glibc's
largest) from the heap, and to give free memory at the top of a heap back to the system only
beyond `TRIM_THRESHOLD` (64 MiB): a process keeps up to that much freed memory for its next
allocations. Not when:

- the C library is not glibc (musl, macOS, Windows): nothing to set;
- the user set malloc's thresholds already: any of `MALLOC_MMAP_THRESHOLD_`,
  `MALLOC_TRIM_THRESHOLD_`, `MALLOC_TOP_PAD_`, or a `glibc.malloc.` tunable in `GLIBC_TUNABLES`:
  their choice stands;
- `ESRP_KEEP_MALLOC_DEFAULTS` is set (to anything): glibc's own behaviour, adjusted as it goes.

`APPLIED` records whether both settings were made. Unlike `GRPC_EXPERIMENTS`, nothing is put in
the environment: child processes keep glibc's defaults.
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
    """Makes the settings as the module docs say; True when both were made."""
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc" or users_choice():
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )


APPLIED = apply()
