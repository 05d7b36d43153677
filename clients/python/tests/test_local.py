"""LocalServer: finding the binary, the metrics address, a graceful stop, the Unix domain socket."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

import esrp


@pytest.mark.parametrize("flag", [("--metrics-listen", "127.0.0.1:0"), ("--metrics-listen=127.0.0.1:0",)])
def test_stop_is_graceful_and_metrics_are_served(flag: tuple[str, ...]) -> None:
    """The metrics' address is read whichever way the flag is written."""
    server = esrp.LocalServer(*flag).start()
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


def test_the_installed_server_wheel_s_binary_comes_after_esrp_server_bin_only(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """`pip install 'esrp[server]'` puts esrp-server in the environment's scripts folder and names it
    in the wheel's RECORD: `find_server_binary` takes that file before PATH and any checkout."""
    real = esrp.find_server_binary()
    monkeypatch.delenv("ESRP_SERVER_BIN", raising=False)
    site, scripts = tmp_path / "site-packages", tmp_path / "bin"
    info = site / "esrp_server-0.1.0.dist-info"
    info.mkdir(parents=True)
    scripts.mkdir()
    (scripts / "esrp-server").symlink_to(real)
    (info / "METADATA").write_text("Metadata-Version: 2.4\nName: esrp-server\nVersion: 0.1.0\n")
    (info / "RECORD").write_text(
        "../bin/esrp-server,,\nesrp_server-0.1.0.dist-info/METADATA,,\nesrp_server-0.1.0.dist-info/RECORD,,\n"
    )
    elsewhere = tmp_path / "path"
    elsewhere.mkdir()
    (elsewhere / "esrp-server").symlink_to(real)
    monkeypatch.setenv("PATH", f"{elsewhere}{os.pathsep}{os.environ['PATH']}")
    assert esrp.find_server_binary() == elsewhere / "esrp-server"  # not installed yet: PATH
    monkeypatch.syspath_prepend(str(site))
    assert esrp.find_server_binary() == (scripts / "esrp-server").resolve()
    monkeypatch.setenv("ESRP_SERVER_BIN", str(real))
    assert esrp.find_server_binary() == real


def test_a_server_of_another_release_is_refused_before_it_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    binary = esrp.find_server_binary()
    assert esrp.server_version(binary) == esrp.__version__
    monkeypatch.setattr(esrp, "__version__", "9.9.0")
    server = esrp.LocalServer()
    message = f"{binary} is esrp-server 0.1.0, but this esrp package is 9.9.0"
    with pytest.raises(esrp.LocalServerError, match=message) as caught:
        server.start()
    assert "pip install 'esrp[server]==9.9.0'" in str(caught.value)
    assert not server.is_running()
    with pytest.raises(esrp.LocalServerError, match="did not name an esrp-server version"):
        esrp.server_version("/bin/true")
    # Asked not to check, it starts.
    with esrp.LocalServer(check_version=False) as unchecked, unchecked.client() as client:
        assert client.server_info().version == "0.1.0"


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


def test_a_unix_socket_serves_both_transports_as_tcp(easy_scenes: list[str]) -> None:
    """`unix_socket=True`: `address` is the socket (`unix:PATH`), `tcp_address` the port; the
    same scene and actions answer the same over TCP and over the socket, on grpcio and (where
    installed) the native transport; the socket's file goes with the server.
    """
    server = esrp.LocalServer(unix_socket=True).start()
    try:
        assert server.address.startswith("unix:")
        assert server.address.endswith(".sock")
        assert server.tcp_address.startswith("127.0.0.1:")
        path = Path(server.address.removeprefix("unix:"))
        assert path.is_socket()
        transports = ["grpcio"] + (["native"] if esrp._native.available() else [])
        runs = {}
        for address in (server.tcp_address, server.address):
            for transport in transports:
                with esrp.Client(address, transport=transport) as client:  # type: ignore[arg-type]
                    assert client.transport == transport
                    with client.create_episode(easy_scenes[0]) as episode:
                        actions = [esrp.Action.LEFT, esrp.Action.FORWARD] * 3
                        steps = [episode.step(action) for action in actions]
                runs[(address, transport)] = [
                    (s.observation.ego_rgb.tobytes(), s.reward, s.terminated, s.truncated) for s in steps
                ]
        first = next(iter(runs.values()))
        assert all(run == first for run in runs.values()), list(runs)
    finally:
        assert server.stop() == 0
    assert not path.exists()


def test_an_env_reaches_its_own_server_over_a_socket() -> None:
    from esrp.envs import RearrangeEnv

    env = RearrangeEnv(split="test", difficulty="easy", horizon=4)
    try:
        assert env.client.address.startswith("unix:")
        observation, _ = env.reset(seed=3)
        assert observation["ego_rgb"].shape == (128, 128, 3)
        env.step(0)
    finally:
        env.close()


def test_a_socket_with_tls_is_refused() -> None:
    with pytest.raises(ValueError, match="plain HTTP/2"):
        esrp.LocalServer("--tls-cert", "c.pem", "--tls-key", "k.pem", unix_socket=True)


@pytest.fixture
def short_tmp() -> Iterator[Path]:
    """A fresh folder in /tmp: pytest's own (`tmp_path`) can be too deep for a socket's path."""
    folder = Path(tempfile.mkdtemp(prefix="esrp-t", dir="/tmp"))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def test_sockets_of_killed_servers_are_swept_at_the_next_start(
    short_tmp: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A socket file left by a killed server is removed at the next start when the process that
    started it is gone and nothing answers on it; a live one, and other files, are kept.
    """
    import socket as sockets

    tmp_path = short_tmp
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr(tempfile, "tempdir", None)
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True
    )
    dead_pid = int(gone.stdout)
    stale = tmp_path / f"esrp-server-{dead_pid}-0a1b2c.sock"
    listener = sockets.socket(sockets.AF_UNIX)
    listener.bind(str(stale))
    listener.close()  # the file stays, nothing listens
    live = tmp_path / f"esrp-server-{dead_pid}-3d4e5f.sock"
    answering = sockets.socket(sockets.AF_UNIX)
    answering.bind(str(live))
    answering.listen()
    other = tmp_path / "esrp-server-notes.sock"
    other.write_text("keep")
    try:
        with esrp.LocalServer(unix_socket=True) as server:
            assert server.address.startswith(f"unix:{tmp_path}/esrp-server-{os.getpid()}-")
            assert not stale.exists()
            assert live.exists()
            assert other.read_text() == "keep"
    finally:
        answering.close()


def test_a_temporary_folder_too_deep_for_a_socket(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With a temporary folder whose paths cannot be a socket's, "auto" serves TCP only and True
    says what to change.
    """
    deep = tmp_path / ("d" * 100)
    deep.mkdir()
    monkeypatch.setenv("TMPDIR", str(deep))
    monkeypatch.setattr(tempfile, "tempdir", None)
    with esrp.LocalServer(unix_socket="auto") as server:
        assert not server.unix_socket
        assert server.address == server.tcp_address
        with server.client() as client:
            assert client.server_info().live_episodes == 0
    with pytest.raises(esrp.LocalServerError, match="set TMPDIR to a shorter folder"):
        esrp.LocalServer(unix_socket=True).start()
    # The envs given no address start theirs as "auto" does: over TCP there.
    from esrp.envs import RearrangeEnv, RearrangeVectorEnv

    vector = RearrangeVectorEnv(2, servers=2)
    try:
        assert [client.address.startswith("127.0.0.1:") for client in vector.clients] == [True, True]
        vector.reset(seed=0)
    finally:
        vector.close()
    single = RearrangeEnv()
    try:
        single.reset(seed=0)
    finally:
        single.close()


def test_bad_settings_are_refused_by_name_and_a_failed_start_says_how_it_ended() -> None:
    for name in ("startup_timeout", "stop_timeout"):
        for bad in (0, -1, float("nan"), "1"):
            with pytest.raises(ValueError, match=f"{name} must be a positive number"):
                esrp.LocalServer(**{name: bad})  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="arguments are strings"):
        esrp.LocalServer("--max-episodes", 5)  # type: ignore[arg-type]
    # A flag the server does not know: it exits with status 2, which the error says.
    with pytest.raises(esrp.LocalServerError, match=r"exit code 2") as caught:
        esrp.LocalServer("--no-such-flag").start()
    assert "--no-such-flag" in str(caught.value)
