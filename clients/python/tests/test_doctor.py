"""`esrp doctor` against the real server: every check passes on this machine (a server started
from the binary `LocalServer` finds, or one already running); a missing binary, an address where
no server answers and a client/server version pair that cannot talk are failures with what to do."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

import esrp
from esrp import _native
from esrp.cli import main
from esrp.cli.doctor import same_release

CHECKS = ("python", "dependencies", "native transport", "server", "renderer", "test render", "one episode")


def test_every_check_passes_with_a_server_started_from_the_binary(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["doctor", "--seconds", "0.5"]) == 0
    out = capsys.readouterr().out
    lines = {
        line[6:24].strip(): line[:5].strip()
        for line in out.splitlines()
        if line[:5].strip() in ("ok", "warn", "FAIL")
    }
    for name in (*CHECKS, "server binary", "local socket"):
        assert lines.get(name) in ("ok", "warn"), (name, out)
    assert "FAIL" not in lines.values(), out
    assert "reach the servers they start over unix:" in out, out
    assert "steps/s" in out
    assert "the ego view has" in out
    assert "checks passed" in out


def test_a_running_server_is_checked_without_the_binary(
    server: esrp.LocalServer,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    monkeypatch.setenv("ESRP_SERVER_BIN", str(tmp_path / "nowhere"))  # not looked for with --server
    assert main(["doctor", "--seconds", "0.2", "--server", server.address]) == 0
    out = capsys.readouterr().out
    assert "server binary" not in out
    assert f"the server at {server.address}: esrp-server {esrp.__version__}" in out


def test_a_missing_binary_fails_and_says_what_to_do(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("ESRP_SERVER_BIN", str(tmp_path / "nowhere"))
    assert main(["doctor"]) == 1
    out = capsys.readouterr().out
    assert f"FAIL  server binary      ESRP_SERVER_BIN={tmp_path / 'nowhere'} is not a file" in out
    assert "→ install the esrp-server wheel or build it" in out
    assert "1 check(s) failed: server binary" in out


def test_an_address_without_a_server_fails_at_once(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["doctor", "--server", "127.0.0.1:1"]) == 1
    out = capsys.readouterr().out
    assert "FAIL  server             no esrp-server answers at 127.0.0.1:1" in out


def test_an_address_no_channel_can_be_made_to_fails_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    # The parser lets it through (gRPC would resolve it); the native transport refuses it.
    assert main(["doctor", "--server", "bad address!!"]) == 1
    out = capsys.readouterr().out
    assert "FAIL  server             " in out
    if _native.available():  # over grpcio the address fails to resolve: "no esrp-server answers"
        assert "give an address like 127.0.0.1:50051" in out
    assert "1 check(s) failed: server" in out


def test_bad_seconds_are_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["doctor", "--seconds", "0"]) == 2
    assert "--seconds must be more than 0" in capsys.readouterr().err


def test_versions_talk_within_one_minor_release() -> None:
    assert same_release("0.1.0", "0.1.7")
    assert not same_release("0.1.0", "0.2.0")
    assert not same_release("1.1.0", "0.1.0")


def test_a_reader_that_goes_away_ends_the_command_quietly() -> None:
    """`esrp doctor | head -3` printed a BrokenPipeError traceback (twice) once head had its lines:
    the command now stops quietly with 141 (128 + SIGPIPE), as Unix tools do."""
    child = subprocess.Popen(
        [sys.executable, "-m", "esrp.cli", "doctor", "--seconds", "0.5"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert child.stdout is not None
    assert child.stderr is not None
    child.stdout.close()  # before the command writes anything
    stderr = child.stderr.read().decode()
    assert child.wait(timeout=60) == 141, stderr
    assert "Traceback" not in stderr
    assert "BrokenPipeError" not in stderr


def test_opengl_on_an_nvidia_gpu_is_a_warning_that_names_vulkan() -> None:
    from esrp.cli.doctor import renderer_check

    nvidia = renderer_check("NVIDIA H100 through gl, hardware", False, "NVIDIA H100 80GB HBM3", "gl")
    assert nvidia.status == "warn"
    assert "--render-backend vulkan" in nvidia.fix
    assert renderer_check("NVIDIA H100 through vulkan", False, "NVIDIA H100", "vulkan").status == "ok"
    software = renderer_check("llvmpipe through gl, software (CPU)", True, "llvmpipe", "gl")
    assert software.status == "ok"
    assert "GPU" in software.detail


def test_a_gpu_on_a_machine_of_many_cores_gets_the_hint_to_run_several_servers() -> None:
    from esrp.cli.doctor import renderer_check

    many = renderer_check("NVIDIA H200 through vulkan", False, "NVIDIA H200", "vulkan", "pipeline", cores=16)
    assert many.status == "ok"
    assert "several servers" in many.fix, many
    assert "16 cores" in many.fix, many
    # Few cores, a server elsewhere (cores unknown), or a CPU renderer: no such hint.
    assert renderer_check("NVIDIA H200 through vulkan", False, "NVIDIA H200", "vulkan", cores=4).fix == ""
    assert renderer_check("NVIDIA H200 through vulkan", False, "NVIDIA H200", "vulkan").fix == ""
    software = renderer_check("llvmpipe through gl, software (CPU)", True, "llvmpipe", "gl", cores=64)
    assert "several servers" not in software.fix


def test_the_compute_rasterizer_on_a_cpu_renderer_is_a_warning(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--render-backend", "vulkan", "--render-rasterizer", "compute"]
    assert main(["doctor", "--seconds", "0.2", *(f"--server-arg={a}" for a in args)]) == 0
    out = capsys.readouterr().out
    line = next(line for line in out.splitlines() if line.startswith("warn") and "renderer" in line)
    assert "through vulkan, compute rasterizer, software (CPU)" in line, out
    assert "without --render-rasterizer compute" in out, out
    assert "test render" in out, out
    assert "FAIL" not in out, out


def test_a_temporary_folder_too_deep_for_a_socket_is_a_warning(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    deep = tmp_path / ("d" * 100)
    deep.mkdir()
    monkeypatch.setenv("TMPDIR", str(deep))
    monkeypatch.setattr(tempfile, "tempdir", None)
    assert main(["doctor", "--seconds", "0.2"]) == 0
    out = capsys.readouterr().out
    socket_line = next(line for line in out.splitlines() if "local socket" in line)
    assert socket_line.startswith("warn"), out
    assert "set TMPDIR to a shorter folder" in out, out
    assert "a server started here on 127.0.0.1:" in out, out


def test_the_commands_run_without_docstrings() -> None:
    """`python -OO` drops docstrings: `esrp doctor`'s description came of its module's docstring,
    and every command failed there with an AttributeError while the parsers were made."""
    for command in (["doctor", "--help"], ["eval", "--help"], ["--help"]):
        done = subprocess.run(
            [sys.executable, "-OO", "-m", "esrp.cli", *command], capture_output=True, text=True, timeout=60
        )
        assert done.returncode == 0, (command, done.stderr)
        assert "usage: esrp" in done.stdout, command
