"""`esrp._malloc_setup.apply()` raises glibc malloc's thresholds unless the user set them;
checked in fresh interpreters, by where a 20 MiB buffer lands: the heap, not a mapping of its own."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc", reason="glibc only"
)

# Where the buffer of a fresh 20 MiB bytearray lies: the name of its /proc/self/maps line (after
# `s`, the module, was imported).
WHERE = """
import ctypes
buffer = bytearray(20 << 20)
address = ctypes.addressof((ctypes.c_char * len(buffer)).from_buffer(buffer))
for line in open("/proc/self/maps"):
    fields = line.split()
    start, end = (int(x, 16) for x in fields[0].split("-"))
    if start <= address < end:
        print(s.APPLIED, fields[5] if len(fields) > 5 else "anonymous")
"""

PROBE = "import esrp._malloc_setup as s\ns.apply()\n" + WHERE

_VARIABLES = (
    "MALLOC_MMAP_THRESHOLD_",
    "MALLOC_TRIM_THRESHOLD_",
    "MALLOC_TOP_PAD_",
    "GLIBC_TUNABLES",
    "ESRP_KEEP_MALLOC_DEFAULTS",
)


def _run(**env: str) -> str:
    environment = {k: v for k, v in os.environ.items() if k not in _VARIABLES} | env
    done = subprocess.run(
        [sys.executable, "-c", PROBE],
        env=environment,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_large_buffers_come_from_the_heap() -> None:
    assert _run() == "True [heap]"


@pytest.mark.parametrize(
    "setting",
    [
        {"MALLOC_TRIM_THRESHOLD_": "131072"},
        {"MALLOC_MMAP_THRESHOLD_": "131072"},
        {"MALLOC_TOP_PAD_": "0"},
        {"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=131072"},
        {"ESRP_KEEP_MALLOC_DEFAULTS": "1"},
    ],
)
def test_the_users_setting_stands(setting: dict[str, str]) -> None:
    # glibc's own dynamic threshold: a first allocation this large gets a mapping of its own.
    assert _run(**setting) == "False anonymous"
