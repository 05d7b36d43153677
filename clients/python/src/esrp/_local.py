"""`LocalServer`: an esrp-server child process on a free local port, for tests, notebooks and tools
that want a server without a second terminal.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import importlib.metadata
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Literal

from . import _signals
from ._client import Client, health_check
from ._common import channel_options, open_channel
from ._errors import LocalServerError
from ._release import same_release

__all__ = ["LocalServer", "find_server_binary", "same_release", "server_version"]

_LISTENING = "esrp-server listening on "
_METRICS = "esrp-server metrics on "
_VIEWER = "esrp-server viewer on "
_BINARY = "esrp-server.exe" if os.name == "nt" else "esrp-server"


def _checkout_targets() -> list[Path]:
    """`target` folders of repository checkouts above this package and the working directory
    (`CARGO_TARGET_DIR` first): `pip install ./clients/python` into a venv inside the checkout, an
    editable install, or running from the checkout all find the workspace's build.
    """
    targets = []
    if os.environ.get("CARGO_TARGET_DIR"):
        targets.append(Path(os.environ["CARGO_TARGET_DIR"]))
    for start in (Path(__file__).resolve().parent, Path.cwd().resolve()):
        for folder in (start, *start.parents):
            if (folder / "Cargo.toml").is_file() and (folder / "server" / "service").is_dir():
                targets.append(folder / "target")
                break
    return targets


def _bundled_binary() -> Path | None:
    """esrp-server as the `esrp-server` wheel installed it (the file its RECORD names, in the
    environment's scripts folder), or None when that wheel is not installed.
    """
    try:
        distribution = importlib.metadata.distribution("esrp-server")
    except importlib.metadata.PackageNotFoundError:
        return None
    for file in distribution.files or ():
        if file.name == _BINARY:
            path = Path(str(distribution.locate_file(file))).resolve()
            if path.is_file():
                return path
    return None


def find_server_binary() -> Path:
    """Where `LocalServer` finds esrp-server, in order: `ESRP_SERVER_BIN`; the binary of the
    installed `esrp-server` wheel (`pip install 'esrp[server]'`); `PATH`; the repository's
    `target/release` then `target/debug` (or `CARGO_TARGET_DIR`'s) when run from a checkout.
    """
    variable = os.environ.get("ESRP_SERVER_BIN")
    if variable:
        path = Path(variable)
        if not path.is_file():
            raise LocalServerError(f"ESRP_SERVER_BIN={variable} is not a file")
        return path
    bundled = _bundled_binary()
    if bundled is not None:
        return bundled
    on_path = shutil.which(_BINARY)
    if on_path:
        return Path(on_path)
    for target in _checkout_targets():
        for profile in ("release", "debug"):
            candidate = target / profile / _BINARY
            if candidate.is_file():
                return candidate
    raise LocalServerError(
        f"cannot find {_BINARY}: install it with `pip install 'esrp[server]'` (or the esrp-server "
        "wheel from scripts/build-wheels.sh), build it with `cargo build --release -p esrp-server`, "
        "put it on PATH, or set ESRP_SERVER_BIN"
    )


_VERSIONS: dict[tuple[str, int, int], str] = {}
_INSTALL_HINT = (
    "install it with `pip install 'esrp[server]'` or build it with `cargo build --release -p esrp-server`"
)


def server_version(binary: str | os.PathLike[str]) -> str:
    """The version an esrp-server binary reports (`esrp-server --version`), asked once per file
    (path, size and modification time); raises `LocalServerError` when it does not answer.
    """
    path = Path(binary)
    try:
        stat = path.stat()
    except OSError as error:
        raise LocalServerError(f"cannot run {path}: {error}") from error
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    if key not in _VERSIONS:
        try:
            answer = subprocess.run(
                [str(path), "--version"], capture_output=True, text=True, timeout=30, check=False
            )
        except (OSError, subprocess.TimeoutExpired) as error:
            raise LocalServerError(f"cannot run {path}: {error}") from error
        words = answer.stdout.split()
        if answer.returncode != 0 or len(words) < 2 or words[0] != "esrp-server":
            tail = (answer.stderr or answer.stdout).strip().splitlines()[-1:] or ["no output"]
            raise LocalServerError(f"{path} --version did not name an esrp-server version: {tail[0]}")
        _VERSIONS[key] = words[-1]
    return _VERSIONS[key]


def _package_version() -> str:
    from . import __version__

    return __version__


def _check_version(binary: Path) -> None:
    """Raises `LocalServerError` when `binary` is not of this package's major.minor release."""
    version, package = server_version(binary), _package_version()
    if not same_release(package, version):
        minor = ".".join(package.split(".")[:2])
        raise LocalServerError(
            f"{binary} is esrp-server {version}, but this esrp package is {package}: a client and a server "
            f"must share their major.minor version. Install esrp-server {minor}.x "
            f"(`pip install 'esrp[server]=={package}'`), or set ESRP_SERVER_BIN to a matching build"
        )


# A socket's path must fit `sockaddr_un`: 108 bytes with its final zero on Linux, 104 on macOS.
_SOCKET_PATH_BYTES = 104
_SOCKET_NAME = re.compile(r"esrp-server-(\d+)-[0-9a-f]+\.sock")


def _sweep_sockets() -> None:
    """Removes the socket files that local servers left in the temporary folder when they were
    killed (a Ray worker's process group, SIGKILL): those whose starting process (the PID in the
    name) is gone and on which nothing answers. The Rust `LocalServer` names its sockets alike.
    """
    folder = tempfile.gettempdir()
    try:
        names = os.listdir(folder)
    except OSError:
        return
    for name in names:
        match = _SOCKET_NAME.fullmatch(name)
        if match is None or _alive(int(match.group(1))):
            continue
        path = os.path.join(folder, name)
        probe = socket.socket(socket.AF_UNIX)
        try:
            probe.connect(path)
        except ConnectionRefusedError:
            with contextlib.suppress(OSError):
                os.unlink(path)
        except OSError:
            pass
        finally:
            probe.close()


def _alive(pid: int) -> bool:
    """Whether a process `pid` exists (one of another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


class LocalServer:
    """An esrp-server child process on a free port of 127.0.0.1 (and, with `unix_socket=True`, on
    a Unix domain socket in the temporary folder).

    `start()` (or entering the `with` block) runs `esrp-server --listen 127.0.0.1:0
    --stop-on-stdin-close ARGS...` with a pipe on its stdin (so that the server stops when this
    process ends, however it ends: the system closes the pipe), reads the bound address from its
    first line, and waits until its health service says serving (a
    server started with `--tls-cert` is taken as ready once it prints its address, as the Rust
    `LocalServer` does: its certificate is not known to be trusted here);
    `stop()` (or leaving the block) sends SIGTERM, waits `stop_timeout` seconds for the graceful
    shutdown, then kills it. A server that does not start raises `LocalServerError` with the tail
    of its stderr.

    Args:
        *args: More server flags, e.g. `"--token", "s3cret"` or `"--max-episodes", "64"`.
        binary: The esrp-server to run (default: `find_server_binary()`).
        env: Extra environment variables of the process (`ESRP_LOG` defaults to `warn`; `NO_COLOR`
            is set, so that its log, kept for `log_tail`, holds no ANSI colour codes).
        startup_timeout: Seconds to wait for the address and for health.
        stop_timeout: Seconds to wait after SIGTERM before killing.
        check_version: Refuse (`LocalServerError`) a binary whose `--version` is not of this
            package's major.minor release (`same_release`), before starting it.
        unix_socket: Serve a Unix domain socket too (`--listen-unix`), and make `address` it
            (`unix:PATH`, `esrp-server-PID-RANDOM.sock` in the temporary folder): the clients of
            this machine then pass a step's observation with about half the kernel work of
            loopback TCP. `tcp_address` stays the TCP one. The server removes the file as it
            stops; the files of killed servers whose process (PID) is gone are removed at the next
            start. Who may connect: the file's permissions (the umask's), as anyone on the machine
            may connect to the TCP port. Not with `--tls-cert` (the socket is plain HTTP/2);
            `"auto"`: a socket unless `--tls-cert` is among `args` or the temporary folder's path
            is too deep for a socket's (104 bytes), where it is TCP only (what the package's own
            tools use for the servers they start and talk to).

    Example:
        >>> with esrp.LocalServer() as server, server.client() as client:    # doctest: +SKIP
        ...     print(client.server_info().dataset)
    """

    def __init__(
        self,
        *args: str,
        binary: str | os.PathLike[str] | None = None,
        env: Mapping[str, str] | None = None,
        startup_timeout: float = 60.0,
        stop_timeout: float = 10.0,
        check_version: bool = True,
        unix_socket: bool | Literal["auto"] = False,
    ) -> None:
        for name, seconds in (("startup_timeout", startup_timeout), ("stop_timeout", stop_timeout)):
            if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not seconds > 0:
                raise ValueError(f"{name} must be a positive number of seconds, got {seconds!r}")
        args = tuple(os.fspath(arg) if isinstance(arg, os.PathLike) else arg for arg in args)
        if not all(isinstance(arg, str) for arg in args):
            raise TypeError(f"the server's arguments are strings (or paths), got {list(args)!r}")
        self.args: Sequence[str] = args
        if unix_socket is True and self.asks_for_tls:
            raise ValueError("unix_socket=True serves plain HTTP/2: leave out --tls-cert, or unix_socket")
        if unix_socket == "auto" and self.asks_for_tls:
            unix_socket = False
        self._unix_socket: bool | Literal["auto"] = unix_socket
        self.unix_socket = False
        """Whether the running server serves a Unix domain socket (`address` is then `unix:PATH`)."""
        self._socket: str | None = None
        self.binary = Path(binary) if binary is not None else None
        self.env = dict(env or {})
        self.startup_timeout = startup_timeout
        self.stop_timeout = stop_timeout
        self.check_version = check_version
        self.process: subprocess.Popen[str] | None = None
        self._stderr: IO[bytes] | None = None
        self._log = _Log()
        self._address: str | None = None
        self._tcp_address: str | None = None
        self.metrics_url: str | None = None
        """`http://127.0.0.1:PORT/metrics`, the Prometheus endpoint, when started with `--metrics-listen`."""
        self.viewer_url: str | None = None
        """`http://127.0.0.1:PORT/`, the web viewer, when started with `--http-listen`."""

    @property
    def address(self) -> str:
        """What a client of this machine connects to: `unix:PATH` with `unix_socket=True`, else
        `127.0.0.1:PORT`.
        """
        if self._address is None:
            raise LocalServerError("the server is not running: call start() or use `with`")
        return self._address

    @property
    def asks_for_tls(self) -> bool:
        """Whether `args` give `--tls-cert` (the server then serves TLS, and no socket)."""
        return self._names("--tls-cert")

    def _names(self, flag: str) -> bool:
        """Whether `args` give `flag`, as `--flag VALUE` or `--flag=VALUE`."""
        return any(a == flag or a.startswith(f"{flag}=") for a in self.args)

    @property
    def tcp_address(self) -> str:
        """`127.0.0.1:PORT` of the running server (the same as `address` without a socket)."""
        if self._tcp_address is None:
            raise LocalServerError("the server is not running: call start() or use `with`")
        return self._tcp_address

    @property
    def pid(self) -> int:
        """The process id."""
        if self.process is None:
            raise LocalServerError("the server is not running")
        return self.process.pid

    def is_running(self) -> bool:
        """Whether the process is alive."""
        return self.process is not None and self.process.poll() is None

    def client(self, **options: Any) -> Client:  # noqa: ANN401
        """A `Client` of this server; `options` as `Client`'s (token, timeout...)."""
        return Client(self.address, **options)

    def stderr_tail(self, lines: int = 40) -> str:
        """The last `lines` lines the server wrote to stderr."""
        if self._stderr is None:
            return ""
        self._stderr.flush()
        self._stderr.seek(0)
        text = self._stderr.read().decode(errors="replace")
        return "\n".join(text.splitlines()[-lines:])

    def log_tail(self, lines: int = 40) -> str:
        """The last `lines` lines of the server's log: what it wrote to stdout after its address
        (esrp-server logs there, at the level `ESRP_LOG` sets), without colour codes.
        """
        return self._log.tail(lines)

    def start(self) -> LocalServer:
        """Starts the server and waits until it is healthy; returns self."""
        if self.process is not None:
            raise LocalServerError("the server was already started")
        binary = self.binary or find_server_binary()
        if not Path(binary).is_file():
            raise LocalServerError(f"cannot start {binary}: no such file ({_INSTALL_HINT})")
        if self.check_version:
            _check_version(binary)
        environment = dict(os.environ)
        environment.setdefault("ESRP_LOG", "warn")
        # Its output goes to files and pipes (read back into `log_tail` and errors), never to a
        # terminal: no ANSI colours, which the server's log formatter writes unless NO_COLOR is set.
        environment["NO_COLOR"] = "1"
        environment.update(self.env)
        # A socket comes from `unix_socket` only: one from this environment would print a line
        # `_await_start` does not expect.
        environment.pop("ESRP_LISTEN_UNIX", None)
        socket: list[str] = []
        self.unix_socket = False
        if self._unix_socket:
            # A fresh name in the temporary folder, no folder of its own: the server removes the
            # file when it stops, even when this process is killed (its stdin closes).
            name = f"esrp-server-{os.getpid()}-{secrets.token_hex(6)}.sock"
            path = os.path.join(tempfile.gettempdir(), name)
            if len(os.fsencode(path)) < _SOCKET_PATH_BYTES:
                _sweep_sockets()
                self._socket = path
                self.unix_socket = True
                socket = ["--listen-unix", path]
            elif self._unix_socket is True:
                raise LocalServerError(
                    f"{path} is too long for a Unix domain socket (at most {_SOCKET_PATH_BYTES - 1} bytes): "
                    "set TMPDIR to a shorter folder, or leave unix_socket out"
                )
            # "auto" with a temporary folder too deep for a socket's path: TCP only.
        # A file, not a pipe: nobody reads stderr while the server runs, and a pipe could fill up.
        # It lives as long as the server and is closed by stop().
        self._stderr = tempfile.TemporaryFile()  # noqa: SIM115
        # A command's SIGTERM must not come between the child's start and its tracking: a server
        # nobody knows of would outlive the command.
        with _signals.deferred():
            try:
                self.process = subprocess.Popen(
                    [str(binary), "--listen", "127.0.0.1:0", "--stop-on-stdin-close", *socket, *self.args],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=self._stderr,
                    env=environment,
                    text=True,
                )
            except OSError as error:
                self._remove_socket()
                raise LocalServerError(f"cannot start {binary}: {error} ({_INSTALL_HINT})") from error
            _signals.track(self.process)
        try:
            self._await_start()
        except BaseException:
            self._terminate()
            raise
        return self

    def _await_start(self) -> None:
        assert self.process is not None
        assert self.process.stdout is not None
        deadline = time.monotonic() + self.startup_timeout
        listening = 2 if self.unix_socket else 1  # TCP, then the socket
        wanted = [_LISTENING] * listening
        wanted += [_METRICS] if self._names("--metrics-listen") else []
        wanted += [_VIEWER] if self._names("--http-listen") else []
        found: list[str] = []
        for prefix in wanted:
            line = self._read_line(self.process.stdout, deadline)
            # Log lines the server's start wrote before its own (a driver's complaint while its
            # renderer is made) are kept in the log and passed over.
            while line and not line.startswith("esrp-server "):
                self._log.write(line)
                line = self._read_line(self.process.stdout, deadline)
            if not line.startswith(prefix):
                self._fail(f"printed {line!r} where {prefix!r} was expected")
            found.append(line.removeprefix(prefix).strip())
        self._tcp_address, self._address = found[0], found[listening - 1]
        for prefix, value in zip(wanted[listening:], found[listening:], strict=True):
            if prefix == _METRICS:
                self.metrics_url = value
            else:
                self.viewer_url = value
        # Keep reading stdout, the server's log, so that a chatty server never blocks on a full pipe;
        # its lines are kept (in a file) for `log_tail` and for errors.
        threading.Thread(target=self._log.drain, args=(self.process.stdout,), daemon=True).start()
        if self.asks_for_tls:
            return
        options = channel_options(None, (), self._address)
        with open_channel(self._address, None, options) as channel:
            while not health_check(channel, timeout=max(min(deadline - time.monotonic(), 1.0), 0.01)):
                if not self.is_running():
                    self._fail("exited before it was healthy")
                if time.monotonic() >= deadline:
                    self._fail(f"was not healthy within {self.startup_timeout} s")
                time.sleep(0.05)

    def _read_line(self, stream: IO[str], deadline: float) -> str:
        """A line of stdout, read on a helper thread so that a silent server times out."""
        result: list[str] = []
        reader = threading.Thread(target=lambda: result.append(stream.readline()), daemon=True)
        reader.start()
        reader.join(max(deadline - time.monotonic(), 0))
        if reader.is_alive():
            self._fail(f"printed no address within {self.startup_timeout} s")
        return result[0]

    def _fail(self, what: str) -> None:
        code = None
        if self.process is not None:
            # A server that closed its output is exiting: its status, once it has.
            with contextlib.suppress(subprocess.TimeoutExpired):
                code = self.process.wait(timeout=0.5)
        status = f"exit code {code}" if code is not None else "still running"
        tail = self.stderr_tail()
        log = self.log_tail(20)
        logged = f"\nits log ends with:\n{log}" if log else ""
        raise LocalServerError(
            f"esrp-server did not start: it {what} ({status}); its stderr ends with:\n{tail or '(nothing)'}"
            + logged
        )

    def stop(self) -> int | None:
        """Stops the server (SIGTERM, then kill after `stop_timeout`); returns its exit code."""
        code = self._terminate()
        self._address = self._tcp_address = None
        return code

    def _remove_socket(self) -> None:
        # The server removes it as it stops; not when it was killed.
        if self._socket is not None:
            with contextlib.suppress(OSError):
                os.unlink(self._socket)
            self._socket = None

    def _terminate(self) -> int | None:
        with _signals.deferred():  # a signal now would leave the server running
            process, self.process = self.process, None
            code = None
            if process is not None:
                if process.poll() is None:
                    process.send_signal(signal.SIGTERM)
                    try:
                        process.wait(timeout=self.stop_timeout)
                    except subprocess.TimeoutExpired:
                        process.kill()
                        process.wait()
                _signals.untrack(process)
                code = process.returncode
                for pipe in (process.stdin, process.stdout):
                    if pipe is not None:
                        pipe.close()
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None
        self._log.close()
        self._remove_socket()
        return code

    def __enter__(self) -> LocalServer:
        return self.start()

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.stop()


def start_servers(count: int, *args: str, **options: Any) -> list[LocalServer]:  # noqa: ANN401
    """`count` `LocalServer(*args, **options)`s, started at once (each takes a while to load its
    dataset and renderer); should one fail to start, the others are stopped and its
    `LocalServerError` raised.
    """
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    servers = [LocalServer(*args, **options) for _ in range(count)]
    if count == 1:
        return [servers[0].start()]
    try:
        with concurrent.futures.ThreadPoolExecutor(count) as pool:
            errors = [future.exception() for future in [pool.submit(server.start) for server in servers]]
        failed = [error for error in errors if error is not None]
        if failed:
            raise failed[0]
    except BaseException:  # one that failed, or an interrupt while they started
        for server in servers:
            server.stop()
        raise
    return servers


class _Log:
    """The server's log lines (its stdout but its own `esrp-server ...` lines), kept in a temporary
    file while it runs: written by the thread that drains the pipe (and by the start, for log lines
    before the address), read by `tail`.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._file: IO[bytes] | None = None
        self._closed = False

    def write(self, line: str) -> None:
        """Appends `line` (nothing once closed)."""
        with self._lock:
            if self._closed:
                return
            if self._file is None:
                self._file = tempfile.TemporaryFile()  # noqa: SIM115 - closed by close()
            self._file.seek(0, os.SEEK_END)
            self._file.write(line.encode(errors="replace"))

    def drain(self, stream: IO[str]) -> None:
        """Writes every line of `stream` until it ends (and reads on once closed)."""
        try:
            for line in stream:
                self.write(line)
        except (OSError, ValueError):
            pass

    def tail(self, lines: int) -> str:
        with self._lock:
            if self._file is None:
                return ""
            self._file.seek(0)
            text = self._file.read().decode(errors="replace")
        return "\n".join(text.splitlines()[-lines:])

    def close(self) -> None:
        with self._lock:
            self._closed = True
            if self._file is not None:
                self._file.close()
                self._file = None
