"""Session fixtures: one real esrp-server (started by `esrp.LocalServer` on a free port) and a
client of it; a helper that waits for the server's live-episode count to settle."""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

import esrp
from esrp import _grpc_setup

# The suite runs with the gRPC settings of the `esrp` command (opt-in, before grpc is imported).
_grpc_setup.apply()


@pytest.fixture(scope="session")
def server() -> Iterator[esrp.LocalServer]:
    """esrp-server on the built-in benchmark (ESRP_SERVER_BIN, else PATH, else the checkout's build)."""
    with esrp.LocalServer() as running:
        yield running


@pytest.fixture(scope="session")
def client(server: esrp.LocalServer) -> Iterator[esrp.Client]:
    """A client of the session's server."""
    with server.client(timeout=60) as connected:
        yield connected


@pytest.fixture(scope="session")
def easy_scenes(client: esrp.Client) -> list[str]:
    """The ids of the easy test scenes."""
    return [scene.id for scene in client.scenes("test", "easy", page_size=1000)]


def settled_live_episodes(client: esrp.Client, expected: int, timeout: float = 10.0) -> int:
    """The server's live-episode count once it equals `expected` (closes on a stream that ended are
    asynchronous), or whatever it is after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        live = client.server_info().live_episodes
        if live == expected or time.monotonic() > deadline:
            return live
        time.sleep(0.02)


def child_pids(pid: int) -> list[int]:
    """The processes whose parent is `pid` (from /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            # pid (comm) state ppid ...: comm may hold spaces, so split after its closing paren.
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def needs(module: str, extra: str) -> ModuleType:
    """`module`, imported; a test module that needs it is skipped where the `extra` that brings it
    is not installed, unless `module` is named in `ESRP_TESTS_REQUIRE` (comma-separated), where its
    absence fails the collection instead: the venvs made to run those tests set it, so that they
    cannot pass by skipping.
    """
    required = {name.strip() for name in os.environ.get("ESRP_TESTS_REQUIRE", "").split(",")}
    if module in required:
        return importlib.import_module(module)
    imported: ModuleType = pytest.importorskip(module, reason=f"esrp[{extra}] is not installed")
    return imported


def load_tool(name: str, folder: str = "tools") -> ModuleType:
    """The script `FOLDER/NAME.py` of this package's source tree (`tools`, `examples`), imported as
    module `NAME`."""
    spec = importlib.util.spec_from_file_location(
        name, Path(__file__).resolve().parents[1] / folder / f"{name}.py"
    )
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def assert_same_stores(one: Path, other: Path) -> None:
    """Asserts that two `esrp.demos/v1` stores hold the same attributes and arrays (needs zarr)."""
    from typing import Any, cast

    import numpy as np
    import zarr

    def contents(path: Path) -> dict[str, object]:
        store = cast(Any, zarr.open_group(str(path), mode="r"))
        arrays = {
            f"{group}/{name}": store[f"{group}/{name}"][:]
            for group in ("data", "meta")
            for name in store[group].array_keys()
        }
        return {"attrs": dict(store.attrs), **arrays}

    first, second = contents(one), contents(other)
    assert first.keys() == second.keys()
    for key, value in first.items():
        if isinstance(value, np.ndarray):
            assert np.array_equal(value, second[key]), key  # type: ignore[arg-type]
        else:
            assert value == second[key], key


def assert_stopped_for_a_lost_server(err: str, command: str, address: str) -> None:
    """`err` is the one line of a training `command` (`esrp train bc`) whose server at `address`
    stopped answering during the run: the address, and how to go on."""
    assert err.startswith(f"{command}: no esrp-server answers at {address}: "), err
    assert err.endswith(
        "; the run stopped there: --resume goes on from its last checkpoint once the server answers\n"
    ), err
    assert err.count("\n") == 1, err
