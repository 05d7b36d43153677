"""The container images against a real Docker engine, on the host's network (127.0.0.1 only).

scripts/docker-tests.sh builds the images first (from the debootstrap base and the binaries the
tests built) and names them in ESRP_DOCKER_SERVER_IMAGE and ESRP_DOCKER_EVAL_IMAGE, with the host's
binaries in ESRP_SERVER_BIN and ESRP_EVAL_BIN. Where the engine cannot start it sets
ESRP_DOCKER_UNAVAILABLE to the reason instead, and these tests are skipped with it.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

DOCKER = Path(__file__).resolve().parents[1]

if reason := os.environ.get("ESRP_DOCKER_UNAVAILABLE"):
    pytest.skip(f"the Docker engine is not available: {reason}", allow_module_level=True)
if "ESRP_DOCKER_SERVER_IMAGE" not in os.environ:
    pytest.skip("run through scripts/docker-tests.sh, which builds the images", allow_module_level=True)

SERVER_IMAGE = os.environ["ESRP_DOCKER_SERVER_IMAGE"]
EVAL_IMAGE = os.environ["ESRP_DOCKER_EVAL_IMAGE"]
SERVER_BIN = os.environ["ESRP_SERVER_BIN"]
EVAL_BIN = os.environ["ESRP_EVAL_BIN"]
# Fields of an esrp.results/v1 record that differ from run to run (docs/evaluation.md).
TIME_FIELDS = ("wall_seconds", "finished_at")


def docker(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    """Runs the docker CLI and returns its output."""
    result = subprocess.run(["docker", *args], capture_output=True, text=True)
    if check and result.returncode != 0:
        pytest.fail(f"docker {' '.join(args)} failed ({result.returncode}): {result.stderr.strip()}")
    return result


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def inspect(name: str) -> dict[str, Any]:
    """`docker inspect` of a container or image."""
    found: dict[str, Any] = json.loads(docker("inspect", name).stdout)[0]
    return found


def container_logs(name: str) -> str:
    """A container's output, stdout (where the server logs) and stderr."""
    logs = docker("logs", name, check=False)
    return logs.stdout + logs.stderr


def wait_for_health(container: str, timeout: float = 60.0) -> str:
    """Waits until the container's health status leaves `starting`; returns it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        state = inspect(container)["State"]
        if not state["Running"]:
            pytest.fail(f"the container stopped ({state['ExitCode']}): {container_logs(container)}")
        status = state["Health"]["Status"]
        if status != "starting":
            return str(status)
        time.sleep(0.5)
    return "starting"


@contextlib.contextmanager
def running_server(*server_args: str) -> Iterator[str]:
    """The server image running on a free port of the host's network, as Kubernetes runs it: as
    the image's user, read-only root and /tmp on tmpfs, no capabilities. Yields its address."""
    port = free_port()
    name = f"esrp-test-server-{port}"
    docker(
        "run", "--detach", "--name", name, "--network", "host",
        "--read-only", "--tmpfs", "/tmp", "--cap-drop", "ALL", "--security-opt", "no-new-privileges",
        # The image's own HEALTHCHECK command, asked every second instead of every 10 s.
        "--health-interval", "1s",
        "--env", f"ESRP_LISTEN=127.0.0.1:{port}",
        SERVER_IMAGE, *server_args,
    )  # fmt: skip
    try:
        yield f"127.0.0.1:{port}"
    finally:
        docker("rm", "--force", name, check=False)


@pytest.fixture(scope="module")
def server() -> Iterator[str]:
    """A server container shared by the tests of this module."""
    with running_server() as address:
        yield address


def container_of(address: str) -> str:
    return f"esrp-test-server-{address.rsplit(':', 1)[1]}"


def test_the_image_runs_unprivileged_and_says_what_it_is() -> None:
    config = inspect(SERVER_IMAGE)["Config"]
    assert config["User"] == "10001:10001"
    assert config["Entrypoint"] == ["esrp-server"]
    assert config["Healthcheck"]["Test"] == ["CMD", "esrp-server", "health-check"]
    environment = dict(e.split("=", 1) for e in config["Env"])
    assert environment["ESRP_LISTEN"] == "0.0.0.0:50051"
    assert environment["NODEVICE_SELECT"] == "1"
    assert environment["NVIDIA_DRIVER_CAPABILITIES"] == "graphics,utility"
    assert environment["NO_COLOR"] == "1"
    assert {"50051/tcp", "9090/tcp"} <= set(config["ExposedPorts"])
    assert config["Labels"]["org.opencontainers.image.title"] == "esrp-server"
    size = inspect(SERVER_IMAGE)["Size"]
    print(f"{SERVER_IMAGE}: {size / 1e6:.0f} MB")


def test_the_container_becomes_healthy_and_answers_health_checks_from_the_host(server: str) -> None:
    assert wait_for_health(container_of(server)) == "healthy"
    log = inspect(container_of(server))["State"]["Health"]["Log"][-1]
    assert log["ExitCode"] == 0, log
    assert "SERVING" in log["Output"], log
    result = subprocess.run([SERVER_BIN, "health-check", server], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    # The renderer inside: Mesa's llvmpipe through OpenGL, as on the host.
    logs = container_logs(container_of(server))
    assert "renderer ready" in logs, logs
    assert "llvmpipe" in logs, logs


def test_lavapipe_renders_in_the_container_too() -> None:
    """The Vulkan loader and Mesa's Vulkan driver are in the image (the path a GPU takes too)."""
    with running_server("--render-backend", "vulkan") as address:
        assert wait_for_health(container_of(address)) == "healthy"
        logs = container_logs(container_of(address))
        assert "backend=Vulkan" in logs, logs


def records(path: Path) -> list[dict[str, Any]]:
    """The records of a results file, by scene, without the time fields."""
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    for record in lines:
        for field in TIME_FIELDS:
            record.pop(field)
    return sorted(lines, key=lambda r: r["scene_id"])


@pytest.mark.parametrize("agent", ["expert", "random"])
def test_an_evaluation_in_the_container_matches_one_on_the_host(server: str, agent: str) -> None:
    with tempfile.TemporaryDirectory() as out:
        results = {}
        for where, flags in [("container", ["--server", f"http://{server}"]), ("host", [])]:
            path = Path(out) / f"{where}.jsonl"
            command = [EVAL_BIN, "--agent", agent, "--limit", "6", "--out", str(path), *flags]
            run = subprocess.run(
                command, capture_output=True, text=True, env={**os.environ, "ESRP_SERVER_BIN": SERVER_BIN}
            )
            assert run.returncode == 0, run.stderr
            results[where] = records(path)
        assert len(results["container"]) == 6
        assert results["container"] == results["host"]


def test_the_server_stops_gracefully_on_docker_stop() -> None:
    with running_server() as address:
        name = container_of(address)
        assert wait_for_health(name) == "healthy"
        docker("stop", "--time", "20", name)
        state = inspect(name)["State"]
        logs = container_logs(name)
        assert state["ExitCode"] == 0, logs
        assert "server stopped" in logs, logs


def test_a_stopped_server_s_address_fails_the_health_check() -> None:
    result = subprocess.run(
        [SERVER_BIN, "health-check", f"127.0.0.1:{free_port()}"], capture_output=True, text=True
    )
    assert result.returncode == 1
    assert "cannot connect" in result.stderr


def test_the_eval_image_has_the_python_package_and_esrp_eval() -> None:
    script = (
        "import esrp.envs, gymnasium; print(esrp.Action.LEFT.name, 'esrp/Rearrange-v1' in gymnasium.registry)"
    )
    result = docker("run", "--rm", "--network", "none", EVAL_IMAGE, "python", "-c", script)
    assert result.stdout.split() == ["LEFT", "True"], result.stdout
    assert "--agent" in docker("run", "--rm", "--network", "none", EVAL_IMAGE, "esrp-eval", "--help").stdout
    assert inspect(EVAL_IMAGE)["Config"]["User"] == "10001:10001"


def test_compose_runs_the_replicas_and_an_evaluation_against_them(tmp_path: Path) -> None:
    results = tmp_path / "results"
    results.mkdir()
    results.chmod(0o777)  # the job writes as the image's user
    ports = {f"ESRP_{kind}PORT_{i}": str(free_port()) for kind in ("", "METRICS_") for i in (0, 1)}
    environment = {
        **os.environ,
        **ports,
        "ESRP_SERVER_IMAGE": SERVER_IMAGE,
        "ESRP_EVAL_IMAGE": EVAL_IMAGE,
        "ESRP_EVAL_AGENT": "expert",
        "ESRP_EVAL_ARGS": "--limit 2",
        "ESRP_RESULTS": str(results),
    }
    compose = [
        *compose_command(),
        "-p",
        f"esrp-test-{ports['ESRP_PORT_0']}",
        "-f",
        str(DOCKER / "compose.yaml"),
    ]
    try:
        up = subprocess.run(
            [*compose, "up", "--no-build", "--exit-code-from", "eval"],
            capture_output=True,
            text=True,
            env=environment,
        )
        assert up.returncode == 0, up.stdout + up.stderr
    finally:
        subprocess.run([*compose, "down", "--timeout", "20"], capture_output=True, env=environment)
    for difficulty in ("easy", "medium", "hard"):
        lines = (results / f"expert-{difficulty}.jsonl").read_text().splitlines()
        assert len(lines) == 2, difficulty
        assert all(json.loads(line)["success"] for line in lines)


def compose_command() -> list[str]:
    """`docker compose` (the plugin) or `docker-compose` (v1)."""
    if subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    return ["docker-compose"]
