"""LocalServer: finding the binary, the metrics address, a graceful stop."""

from __future__ import annotations

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
