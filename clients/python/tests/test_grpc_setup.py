"""`esrp._grpc_setup.apply()` turns grpcio's `event_engine_client` experiment off unless the user
decided; checked in fresh interpreters, since grpcio reads the setting once."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

import esrp

PROBE = (
    "import os, esrp._grpc_setup as s; s.apply(); print(repr(os.environ.get('GRPC_EXPERIMENTS')), s.APPLIED)"
)


def _run(code: str, **env: str) -> str:
    environment = {k: v for k, v in os.environ.items() if k != "GRPC_EXPERIMENTS"} | env
    command = [sys.executable, "-c", code]
    done = subprocess.run(command, env=environment, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_set_when_unset() -> None:
    import grpc

    version = tuple(int(x) for x in grpc.__version__.split(".")[:2])
    from esrp import _grpc_setup

    if version not in _grpc_setup.MEASURED:
        pytest.skip(f"grpcio {grpc.__version__} is not a measured version: nothing is set")
    assert _run(PROBE) == "'-event_engine_client' True"


def test_the_users_setting_stands() -> None:
    assert _run(PROBE, GRPC_EXPERIMENTS="") == "'' False"
    assert _run(PROBE, GRPC_EXPERIMENTS="event_engine_client") == "'event_engine_client' False"


def test_too_late_after_grpc() -> None:
    assert _run("import grpc; " + PROBE) == "None False"


def test_calls_work_with_the_setting(server: esrp.LocalServer) -> None:
    # The whole suite runs with it (conftest applies it first); here one call in a fresh
    # interpreter, sync and asyncio, to be explicit.
    address = server.address
    code = (
        "import asyncio, esrp, esrp._grpc_setup\n"
        "esrp._grpc_setup.apply()\n"
        f"print(esrp.Client({address!r}).server_info().dataset)\n"
        "async def main():\n"
        f"    async with esrp.AsyncClient({address!r}) as c:\n"
        "        print((await c.server_info()).dataset)\n"
        "asyncio.run(main())\n"
    )
    assert _run(code).split() == ["esrp-bench-v2", "esrp-bench-v2"]
