"""Starts the real esrp-server binary on an ephemeral port, and opens dm_env_rpc connections to it."""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import grpc
from dm_env_rpc.v1 import connection as dm_connection

REPO = Path(__file__).resolve().parents[2]

# The server prints this, then its bound address, as its first line on stdout.
LISTENING = "esrp-server listening on "


def binary(name: str) -> Path:
    """The path of a workspace binary: $ESRP_<NAME>_BIN, else the default cargo target folder."""
    variable = f"ESRP_{name.removeprefix('esrp-').upper()}_BIN"
    path = Path(os.environ.get(variable) or REPO / "target" / "debug" / name)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} does not exist: build it (cargo build -p {name}) or set {variable}; "
            "scripts/python-tests.sh does both"
        )
    return path


@dataclass
class RunningServer:
    """A running esrp-server process."""

    process: subprocess.Popen[str]
    address: str  # host:port

    def connect(self) -> Session:
        """A new dm_env_rpc connection (one stream) to the server."""
        return Session(self.address)


@contextmanager
def start_server(*args: str) -> Iterator[RunningServer]:
    """Runs `esrp-server --listen 127.0.0.1:0 ARGS...` until the block ends."""
    environment = dict(os.environ, NODEVICE_SELECT="1", ESRP_LOG=os.environ.get("ESRP_LOG", "warn"))
    process = subprocess.Popen(
        [str(binary("esrp-server")), "--listen", "127.0.0.1:0", *args],
        stdout=subprocess.PIPE,
        text=True,
        env=environment,
    )
    try:
        assert process.stdout is not None
        line = process.stdout.readline()
        if not line.startswith(LISTENING):
            raise RuntimeError(f"esrp-server did not start: first line {line!r}, exit code {process.poll()}")
        yield RunningServer(process, line.removeprefix(LISTENING).strip())
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


class Session:
    """A gRPC channel and one dm_env_rpc connection over it; closing it ends the stream."""

    def __init__(self, address: str) -> None:
        self.channel = grpc.insecure_channel(address)
        self.connection = dm_connection.Connection(self.channel)

    def close(self) -> None:
        self.connection.close()
        self.channel.close()

    def __enter__(self) -> dm_connection.Connection:
        return self.connection

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class ExpertScene:
    """A scene of the built-in benchmark with its expert trajectory."""

    scene_id: str
    horizon: int
    expert_actions: list[int]


def expert_scene(index: int) -> ExpertScene:
    """Scene `index` of esrp-bench-v2 as `esrp-dataset generate` writes it.

    Generation depends only on (seed, index), so this is the scene the server builds for the same
    id; its file carries the expert trajectory, which the dm_env_rpc API does not reveal.
    """
    with tempfile.TemporaryDirectory() as folder:
        subprocess.run(
            [
                str(binary("esrp-dataset")),
                "generate",
                "--out",
                folder,
                "--first",
                str(index),
                "--scenes",
                "1",
                "--threads",
                "1",
            ],
            check=True,
            capture_output=True,
        )
        (path,) = Path(folder, "scenes").glob("*.json")
        scene = json.loads(path.read_text())
    return ExpertScene(scene["id"], int(scene["horizon"]), [int(a) for a in scene["expert_trajectory"]])
