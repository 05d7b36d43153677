"""LocalServer: finding the binary, the metrics address, a graceful stop."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

import esrp


def test_stop_is_graceful_and_metrics_are_served() -> None:
    server = esrp.LocalServer("--metrics-listen", "127.0.0.1:0").start()
    try:
        assert server.is_running()
        assert server.metrics_url is not None
        assert server.metrics_url.startswith("http://127.0.0.1:")
        with server.client() as client, client.create_episode(split="test"):
            with urllib.request.urlopen(server.metrics_url, timeout=10) as answer:
                text = answer.read().decode()
            assert "esrp_live_episodes 1" in text.splitlines()
    finally:
        # SIGTERM: in-flight calls drain, the process exits 0.
        assert server.stop() == 0
    assert not server.is_running()
    with pytest.raises(esrp.LocalServerError, match="not running"):
        _ = server.address


def test_find_server_binary(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    found = esrp.find_server_binary()
    assert found.is_file()
    monkeypatch.setenv("ESRP_SERVER_BIN", str(tmp_path / "nothing"))
    with pytest.raises(esrp.LocalServerError, match="ESRP_SERVER_BIN"):
        esrp.find_server_binary()
    monkeypatch.setenv("ESRP_SERVER_BIN", str(found))
    assert esrp.find_server_binary() == found


def _alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie not yet reaped by its new parent does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_the_server_stops_when_its_python_process_is_killed() -> None:
    # SIGKILL runs no clean-up: the server sees its stdin pipe close and stops by itself.
    script = "import esrp, time; s = esrp.LocalServer().start(); print(s.pid, flush=True); time.sleep(600)"
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert child.stdout is not None
    server = int(child.stdout.readline())
    assert _alive(server)
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    deadline = time.monotonic() + 15
    while _alive(server) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(server), "the server outlived its killed parent"


def test_the_server_log_is_kept_without_ansi_colours() -> None:
    """esrp-server's log formatter writes ANSI colour codes wherever its output goes (a file, a
    pipe); LocalServer threw the log away. It keeps it now (`log_tail`, and in its errors), with
    the server run with NO_COLOR set: no colour codes."""
    with esrp.LocalServer(env={"ESRP_LOG": "info"}) as server:
        with server.client() as client, client.create_episode(split="test"):
            pass
        deadline = time.monotonic() + 10
        while "serving esrp.v1" not in server.log_tail(200) and time.monotonic() < deadline:
            time.sleep(0.05)
        log = server.log_tail(200)
    assert " INFO esrp_server: serving esrp.v1 address=" in log
    assert "\x1b[" not in log
    assert server.log_tail() == ""  # stopped: the log went with it
