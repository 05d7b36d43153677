"""The wheels of scripts/build-wheels.sh as a Python user meets them: installed with pip on Debian
(and no Rust toolchain) in the images scripts/docker-tests.sh builds from docker/wheels.Dockerfile
and names in ESRP_DOCKER_WHEELS_IMAGES: Debian 13 with its Python 3.13 (the newest Python Debian
ships), and Debian 12 with Python 3.10 (the oldest the package supports, which Debian does not
ship: the host's build, copied in). Each test runs in a fresh container without a network: the
server is the one the esrp-server wheel installed, started by `esrp.LocalServer`.
"""

from __future__ import annotations

import json
import os
import subprocess

import pytest

if reason := os.environ.get("ESRP_DOCKER_UNAVAILABLE"):
    pytest.skip(f"the Docker engine is not available: {reason}", allow_module_level=True)
if "ESRP_DOCKER_WHEELS_IMAGES" not in os.environ:
    pytest.skip("run through scripts/docker-tests.sh, which builds the images", allow_module_level=True)

IMAGES = os.environ["ESRP_DOCKER_WHEELS_IMAGES"].split()


def run(image: str, *command: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    """`command` in a fresh container of `image`, with no network."""
    result = subprocess.run(
        ["docker", "run", "--rm", "--network", "none", image, *command], capture_output=True, text=True
    )
    if check and result.returncode != 0:
        pytest.fail(
            f"{' '.join(command)} failed in {image} ({result.returncode}):\n{result.stdout}\n{result.stderr}"
        )
    return result


@pytest.mark.parametrize("image", IMAGES)
def test_the_wheels_install_without_a_rust_toolchain_and_the_bundled_server_is_found(image: str) -> None:
    script = """
import json, shutil, sys
import esrp, esrp._native
print(json.dumps({
    "python": list(sys.version_info[:2]),
    "binary": str(esrp.find_server_binary()),
    "server": esrp.server_version(esrp.find_server_binary()),
    "package": esrp.__version__,
    "native": esrp._native.available(),
    "cargo": shutil.which("cargo"),
    "rustc": shutil.which("rustc"),
}))
"""
    found = json.loads(run(image, "python", "-c", script).stdout)
    assert found["binary"] == "/opt/esrp/bin/esrp-server"
    assert found["server"] == found["package"]
    assert found["native"] is True
    assert found["cargo"] is None
    assert found["rustc"] is None
    assert found["python"][0] == 3
    assert found["python"][1] >= 10
    freeze = run(image, "pip", "list", "--format=freeze").stdout
    for name in ("esrp", "esrp-native", "esrp-server"):
        assert f"\n{name}==" in "\n" + freeze.lower().replace("_", "-"), freeze


@pytest.mark.parametrize("image", IMAGES)
def test_an_evaluation_of_the_planner_runs_on_the_bundled_server(image: str) -> None:
    command = "esrp eval --agent plan --split test --limit 5 --out results.jsonl && cat results.jsonl"
    result = run(image, "bash", "-c", command)
    records = [json.loads(line) for line in result.stdout.splitlines() if line.startswith("{")]
    assert len(records) == 5, result.stdout + result.stderr
    assert all(r["scene_id"].startswith("esrp-bench-v2/") for r in records)
    assert sum(r["success"] for r in records) >= 1, records


@pytest.mark.parametrize("image", IMAGES)
def test_gymnasium_s_check_env_passes(image: str) -> None:
    script = """
import gymnasium as gym
from gymnasium.utils.env_checker import check_env
import esrp.envs
env = gym.make("esrp/Rearrange-v1", split="test")
check_env(env.unwrapped)
env.close()
print("check_env passed")
"""
    assert "check_env passed" in run(image, "python", "-c", script).stdout


@pytest.mark.parametrize("image", IMAGES)
def test_esrp_doctor_finds_nothing_wrong(image: str) -> None:
    result = run(image, "esrp", "doctor", "--seconds", "1", check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "FAIL" not in result.stdout
    assert "/opt/esrp/bin/esrp-server (esrp-server " in result.stdout
