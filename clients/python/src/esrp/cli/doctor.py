"""`esrp doctor`: checks that this machine can run ESRP, one line per check, and says what to install
or set for each one that fails.

The checks, in order: Python and the package's dependencies; the native transport; the server
binary `LocalServer` would start and its version (skipped with `--server`); whether the servers
the envs and tools start are reached over a Unix domain socket (a warning where the temporary
folder is too deep for one); a server started (or reached) and its version against this
package's; the renderer it chose; a test render (a test scene's first views must not be blank);
and the throughput of a few seconds of random steps, one episode and (with Gymnasium) a vector env
of 16. Exit status 0 when nothing failed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from typing import TYPE_CHECKING

from .. import __version__
from .._release import same_release
from ._args import Parser, server_options

if TYPE_CHECKING:
    from .._client import Client
    from .._local import LocalServer

__all__ = ["Check", "add_commands", "same_release"]

MINIMUM_PYTHON = (3, 10)
# From this many cores, a GPU machine serves more with several servers than with one
# (docs/performance.md: four servers on an H200 with 16 cores made twice one server's steps).
MANY_CORES = 8


@dataclass
class Check:
    """One line of the report: `status` is "ok", "warn" (works, could be better) or "FAIL"."""

    name: str
    status: str
    detail: str
    fix: str = ""


def add_commands(commands: argparse._SubParsersAction[Parser]) -> None:
    """Adds `esrp doctor`."""
    doctor = commands.add_parser(
        "doctor",
        help="check that this machine can run ESRP, and say what to install or set",
        description=__doc__.split("\n\n")[0] if __doc__ else None,  # none under python -OO
    )
    doctor.add_argument(
        "--seconds", type=float, default=5.0, help="seconds of random steps per throughput check (default 5)"
    )
    server_options(doctor)
    doctor.set_defaults(handler=_doctor)


def _minor(version: str) -> str:
    return ".".join(version.split(".")[:2])


def _doctor(args: argparse.Namespace) -> int:
    if args.seconds <= 0:
        print("esrp doctor: --seconds must be more than 0", file=sys.stderr)
        return 2
    checks: list[Check] = []

    def report(check: Check) -> None:
        checks.append(check)
        print(f"{check.status:<5} {check.name:<18} {check.detail}", flush=True)
        if check.fix:
            print(f"{'':<24}→ {check.fix}", flush=True)

    print(f"esrp doctor (esrp {__version__})")
    report(_python())
    for check in _packages():
        report(check)
    report(_native())
    if args.server is None:
        binary = _binary()
        report(binary)
        if binary.status == "FAIL":
            return _summary(checks)
    _on_server(args, report)
    return _summary(checks)


def _summary(checks: list[Check]) -> int:
    failed = [c.name for c in checks if c.status == "FAIL"]
    warned = [c.name for c in checks if c.status == "warn"]
    if failed:
        print(f"\n{len(failed)} check(s) failed: {', '.join(failed)}")
        return 1
    print(f"\nall {len(checks)} checks passed" + (f" ({len(warned)} with a warning)" if warned else ""))
    return 0


def _python() -> Check:
    version = ".".join(map(str, sys.version_info[:3]))
    detail = f"Python {version} on {platform.system()} {platform.machine()} ({sys.executable})"
    if sys.version_info[:2] < MINIMUM_PYTHON:
        return Check("python", "FAIL", detail, "esrp needs Python 3.10 or newer")
    return Check("python", "ok", detail)


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def _packages() -> list[Check]:
    required = {name: _version(name) for name in ("numpy", "grpcio", "protobuf")}
    missing = [name for name, version in required.items() if version is None]
    found = ", ".join(f"{name} {version}" for name, version in required.items() if version)
    checks = [
        Check("dependencies", "FAIL", f"missing: {', '.join(missing)}", "pip install esrp (it installs them)")
        if missing
        else Check("dependencies", "ok", found)
    ]
    extras = {
        "gymnasium": ("gym", "the Gymnasium envs"),
        "torch": ("train", "esrp train bc|ppo and the learned agents"),
        "matplotlib": ("report", "esrp report's plots and esrp replay"),
    }
    have = [f"{name} {_version(name)}" for name in extras if _version(name)]
    lacking = [
        f"{name} (pip install 'esrp[{extra}]' for {what})"
        for name, (extra, what) in extras.items()
        if not _version(name)
    ]
    detail = ", ".join(have) if have else "none installed"
    checks.append(
        Check(
            "optional packages", "ok", detail + (f"; not installed: {'; '.join(lacking)}" if lacking else "")
        )
    )
    return checks


def _native() -> Check:
    from .. import _native

    version = _version("esrp-native")
    if _native.available():
        return Check(
            "native transport", "ok", f"esrp-native {version or '(version unknown)'}: used by default"
        )
    return Check(
        "native transport",
        "warn",
        "esrp-native is not installed: calls go over grpcio (about 40 % more client CPU per step)",
        "pip install esrp-native (a wheel from scripts/build-wheels.sh, or clients/python/native's README)",
    )


def _binary() -> Check:
    from .._errors import LocalServerError
    from .._local import find_server_binary, server_version

    try:
        path = find_server_binary()
    except LocalServerError as error:
        return Check(
            "server binary",
            "FAIL",
            str(error),
            "install the esrp-server wheel or build it, set ESRP_SERVER_BIN, or check a running server "
            "with --server ADDR",
        )
    try:
        version = server_version(path)
    except LocalServerError as error:
        return Check(
            "server binary", "FAIL", str(error), "rebuild it, reinstall esrp-server, or set ESRP_SERVER_BIN"
        )
    if not same_release(__version__, version):
        return Check(
            "server binary",
            "FAIL",
            f"{path} is esrp-server {version}; this package is esrp {__version__}",
            f"install esrp-server {_minor(__version__)}.x, or esrp {_minor(version)}.x",
        )
    return Check("server binary", "ok", f"{path} (esrp-server {version})")


def _on_server(args: argparse.Namespace, report: Callable[[Check], None]) -> None:
    from .._client import Client
    from .._common import unreachable
    from .._errors import EsrpError, LocalServerError, ServerUnavailable

    if args.server is not None:
        try:
            client = Client(args.server, token=args.token, timeout=30)
        except ValueError as error:
            # An address the parser let through that no channel can be made to (`bad host!!`).
            report(Check("server", "FAIL", str(error), "give an address like 127.0.0.1:50051 or unix:PATH"))
            return
        try:
            with client:
                _server_checks(client, f"the server at {args.server}", args.seconds, report, local_cores=None)
        except EsrpError as error:
            detail = unreachable(args.server, error) if isinstance(error, ServerUnavailable) else str(error)
            report(Check("server", "FAIL", detail, "is a server running there?"))
        return
    from .._local import LocalServer

    try:
        # As the envs and tools start theirs: over a Unix domain socket where one can be had.
        with LocalServer(*args.server_args, unix_socket="auto") as local, local.client() as client:
            report(_socket_check(local))
            where = f"a server started here on {local.address}"
            _server_checks(client, where, args.seconds, report, local_cores=os.cpu_count())
    except LocalServerError as error:
        # The server's own message names what to install when no renderer could be made.
        report(
            Check(
                "server",
                "FAIL",
                str(error).strip().replace("\n", "\n" + " " * 24),
                "install what the message names, or try --server-arg=--render-backend --server-arg=gl|vulkan",
            )
        )


def _socket_check(local: LocalServer) -> Check:
    """How the envs and tools reach the servers they start: over a Unix domain socket, or over
    loopback TCP where the temporary folder is too deep for a socket's path (or with TLS).
    """
    if local.unix_socket:
        where = local.address
        return Check("local socket", "ok", f"the envs and tools reach the servers they start over {where}")
    if local.asks_for_tls:
        return Check("local socket", "ok", "TLS was asked for: servers started here are reached over TCP")
    return Check(
        "local socket",
        "warn",
        f"the temporary folder ({tempfile.gettempdir()}) is too deep for a socket's path: servers started "
        "here are reached over loopback TCP, with more CPU per step",
        "set TMPDIR to a shorter folder (e.g. /tmp)",
    )


def _server_checks(
    client: Client, where: str, seconds: float, report: Callable[[Check], None], *, local_cores: int | None
) -> None:
    """The checks of a running server; `local_cores`, for a server on this machine, its cores."""
    info = client.server_info()
    if same_release(__version__, info.version):
        report(Check("server", "ok", f"{where}: esrp-server {info.version}, dataset {info.dataset}"))
    else:
        report(
            Check(
                "server",
                "FAIL",
                f"{where} is esrp-server {info.version}; this package is esrp {__version__}",
                "use a client and a server of the same major.minor version",
            )
        )
    kind = "software (CPU)" if info.software_renderer else "hardware"
    rasterizer = f", {info.renderer_rasterizer} rasterizer" if info.renderer_rasterizer else ""
    renderer = f"{info.renderer_adapter} through {info.renderer_backend}{rasterizer}, {kind}"
    backend, adapter = info.renderer_backend, info.renderer_adapter
    rasterizer_name = info.renderer_rasterizer
    report(renderer_check(renderer, info.software_renderer, adapter, backend, rasterizer_name, local_cores))
    render, scene = _test_render(client)
    report(render)
    if scene is None:
        return
    report(_throughput(client, scene, seconds))
    report(_vector_throughput(client, scene, seconds))


def renderer_check(
    described: str, software: bool, adapter: str, backend: str, rasterizer: str = "", cores: int | None = None
) -> Check:
    """The renderer's line: fine, with a hint where a GPU would render faster, a warning for
    OpenGL on an NVIDIA GPU (it failed there with "Parent device is lost": Vulkan is the path),
    and one for the compute rasteriser on a CPU renderer (Mesa runs compute shaders far slower
    than it draws). For a GPU on a machine of `cores` cores (a server started here), from 8 up,
    the hint that several servers on the GPU, not one, use the machine.
    """
    if software and rasterizer == "compute":
        return Check(
            "renderer",
            "warn",
            described + ": on a CPU renderer the compute rasterizer draws 15 to 25 times slower "
            "than the pipeline",
            "start the server without --render-rasterizer compute (the pipeline is the default)",
        )
    if software:
        return Check("renderer", "ok", described + ": a GPU with Vulkan drivers renders faster")
    if "nvidia" in adapter.lower() and backend.lower() in ("gl", "opengl", "gles"):
        return Check(
            "renderer",
            "warn",
            described + ": OpenGL on NVIDIA GPUs failed with a lost device under load",
            "start the server with --render-backend vulkan (what auto picks on a GPU)",
        )
    if cores is not None and cores >= MANY_CORES:
        return Check(
            "renderer",
            "ok",
            described,
            f"one server renders through one device queue: to use this GPU and its {cores} cores, run "
            "several servers side by side and spread the clients over them (docs/server.md, "
            '"Using a whole GPU machine")',
        )
    return Check("renderer", "ok", described)


def _test_render(client: Client) -> tuple[Check, str | None]:
    """The test render's check, and its scene when the views came back right."""
    import numpy as np

    scenes = list(itertools.islice(client.scenes(split="test"), 1))
    if not scenes:
        return Check("test render", "FAIL", "the server has no test scene", "serve a test split"), None
    with client.create_episode(scenes[0].id) as episode:
        first = episode.observation
        if first is None or first.goal_rgb is None:
            return Check("test render", "FAIL", f"{scenes[0].id}: no first observation came back"), None
        views = {"ego": np.asarray(first.ego_rgb), "goal": np.asarray(first.goal_rgb)}
    blank = [name for name, image in views.items() if image.size == 0 or (image == image.flat[0]).all()]
    shapes = ", ".join(f"{name} {'×'.join(map(str, image.shape))}" for name, image in views.items())
    if blank:
        return (
            Check(
                "test render",
                "FAIL",
                f"{scenes[0].id}: the {' and '.join(blank)} view is one colour ({shapes})",
                "try the other backend: --server-arg=--render-backend --server-arg=gl|vulkan",
            ),
            None,
        )
    colours = len(np.unique(views["ego"].reshape(-1, 3), axis=0))
    return Check(
        "test render", "ok", f"{scenes[0].id}: {shapes}, the ego view has {colours} colours"
    ), scenes[0].id


def _throughput(client: Client, scene: str, seconds: float) -> Check:
    import numpy as np

    rng = np.random.default_rng(0)
    steps = 0
    started = time.perf_counter()
    while time.perf_counter() - started < seconds:
        with client.create_episode(scene) as episode:
            while time.perf_counter() - started < seconds:
                result = episode.step(int(rng.integers(0, 6)))
                steps += 1
                if result.terminated or result.truncated:
                    break
    rate = steps / (time.perf_counter() - started)
    return Check(
        "one episode", "ok", f"{rate:,.0f} steps/s ({steps:,} random steps on {scene}, 128 px views)"
    )


def _vector_throughput(client: Client, scene: str, seconds: float) -> Check:
    if _version("gymnasium") is None:
        return Check("vector env", "warn", "skipped: Gymnasium is not installed", "pip install 'esrp[gym]'")
    import numpy as np

    from ..envs import RearrangeVectorEnv

    envs = 16
    env = RearrangeVectorEnv(envs, client=client, split="test", scene=scene)
    try:
        env.reset(seed=0)
        rng = np.random.default_rng(0)
        steps = 0
        started = time.perf_counter()
        while time.perf_counter() - started < seconds:
            env.step(rng.integers(0, 6, envs))
            steps += envs
        rate = steps / (time.perf_counter() - started)
    finally:
        env.close()
    return Check("vector env", "ok", f"{rate:,.0f} steps/s ({envs} envs of {scene}, 128 px views)")
