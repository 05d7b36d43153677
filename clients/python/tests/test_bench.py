"""`python -m esrp.bench` runs every scenario against the real server and prints it (tiny windows:
the performance goals live in the benchmark, never in tests)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import settled_live_episodes

import esrp
from esrp.cli import bench


def test_bench_prints_every_scenario(
    server: esrp.LocalServer, client: esrp.Client, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = client.server_info().live_episodes
    report = tmp_path / "bench.json"
    arguments = ["--server", server.address, "--seconds", "0.3", "--warmup", "0.1", "--warmup-rounds", "1"]
    arguments += ["--json", str(report)]
    assert bench.main(arguments) == 0
    out, err = capsys.readouterr()
    # One unmeasured round first, then the measured one.
    assert "warm-up round 1: vec-64 (not counted)" in err, err
    assert "\n  round 1: vec-64" in err, err
    rows = {line.split()[0]: line for line in out.splitlines() if line and not line.startswith(" ")}
    assert "machine:" in rows
    assert out.count("load average") == 2
    for name in ("client-1", "env-1", "stream-64", "vec-64"):
        assert name in rows, out
        assert "skipped" not in rows[name]
        assert float(rows[name].split()[2].replace(",", "")) > 0
    # The Rust client and MiniWorld run where they are installed, and say why not otherwise.
    assert "rust:unary-1" in rows or "skipped" in rows["rust"]
    assert "miniworld" in rows
    results = {row["scenario"]: row for row in json.loads(report.read_text())["results"]}
    assert results["vec-64"]["episodes"] == 64
    assert results["vec-64"]["steps_per_second"] > 0
    if "rust:unary-1" in results:
        assert results["env-1"]["ratio_to_rust"] > 0
    assert settled_live_episodes(client, before) == before


def test_bench_rejects_unknown_scenarios(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        bench.main(["--scenarios", "env-1,warp-9"])
    assert "warp-9" in capsys.readouterr().err


def test_esrp_bench_is_the_same_command(capsys: pytest.CaptureFixture[str]) -> None:
    from esrp.cli import main

    with pytest.raises(SystemExit):
        main(["bench", "--scenarios", "env-1,warp-9"])
    assert "warp-9" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    assert "--scenarios" in capsys.readouterr().out


def test_rust_bench_missing(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("ESRP_BENCH_BIN", str(tmp_path / "absent"))
    [skipped] = bench.bench_rust("127.0.0.1:1", None, 0.1, ["unary-1"])
    assert skipped.skipped is not None
    assert "ESRP_BENCH_BIN" in skipped.skipped


def test_bench_runs_each_transport(
    server: esrp.LocalServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "bench.json"
    arguments = ["--server", server.address, "--seconds", "0.2", "--warmup", "0.05", "--warmup-rounds", "0"]
    arguments += ["--scenarios", "client-1,env-1,stream-64", "--transport", "grpcio,auto"]
    arguments += ["--json", str(report)]
    assert bench.main(arguments) == 0
    out, _ = capsys.readouterr()
    rows = {line.split()[0] for line in out.splitlines() if line and not line.startswith(" ")}
    # The first transport's rows keep the plain names; stream-64 (always grpcio) runs once.
    assert {"client-1", "client-1@auto", "env-1", "env-1@auto", "stream-64"} <= rows, out
    assert "stream-64@auto" not in rows
    data = json.loads(report.read_text())
    with server.client() as auto:
        assert data["transports"] == {"grpcio": "grpcio", "auto": auto.transport}
    assert all(row["steps_per_second"] > 0 for row in data["results"])


def test_bench_rejects_unknown_transports(capsys: pytest.CaptureFixture[str]) -> None:
    for bad in ("pigeon", "grpcio,grpcio", ","):
        with pytest.raises(SystemExit):
            bench.main(["--transport", bad])
        assert "--transport" in capsys.readouterr().err


def test_bench_runs_in_several_processes_and_sums_them(
    server: esrp.LocalServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "bench.json"
    arguments = ["--server", server.address, "--scenarios", "client-1,vec-64", "--processes", "2"]
    arguments += ["--seconds", "0.3", "--warmup", "0.1", "--warmup-rounds", "0", "--json", str(report)]
    assert bench.main(arguments) == 0
    out = capsys.readouterr().out
    assert "2 processes at once" in out
    written = json.loads(report.read_text())
    assert written["processes"] == 2
    assert len(written["children"]) == 2
    rows = {row["scenario"]: row for row in written["results"]}
    assert rows["vec-64"]["episodes"] == 128
    each = rows["vec-64"]["processes_steps_per_second"]
    assert len(each) == 2
    assert all(rate > 0 for rate in each)
    assert rows["vec-64"]["steps_per_second"] == pytest.approx(sum(each))
    assert rows["client-1"]["p50_ms"] > 0


def assert_refused(capsys: pytest.CaptureFixture[str], arguments: list[str], said: str) -> None:
    """The command refuses `arguments` as a usage error (status 2) that says `said`."""
    with pytest.raises(SystemExit) as exit_info:
        bench.main(arguments)
    assert exit_info.value.code == 2
    assert said in capsys.readouterr().err


def test_bench_processes_leave_other_programs_out(capsys: pytest.CaptureFixture[str]) -> None:
    assert_refused(capsys, ["--processes", "2", "--scenarios", "vec-64,rust"], "leave rust and miniworld out")
    assert_refused(capsys, ["--processes", "0"], "between 1 and 256")


def test_bench_reaches_a_server_it_starts_over_its_socket(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "bench.json"
    arguments = ["--socket", "--scenarios", "client-1,vec-64,rust", "--seconds", "0.3", "--warmup", "0.1"]
    arguments += ["--warmup-rounds", "0", "--json", str(report)]
    assert bench.main(arguments) == 0
    out = capsys.readouterr().out
    written = json.loads(report.read_text())
    assert written["server"].startswith("unix:"), written["server"]
    assert written["server"].endswith(".sock"), written["server"]
    rows = {row["scenario"]: row for row in written["results"]}
    assert rows["vec-64"]["steps_per_second"] > 0, out
    # The Rust esrp-bench, where built, is pointed at the same socket.
    assert "rust:unary-1" in rows or "skipped" in out
    assert not Path(written["server"].removeprefix("unix:")).exists()


def test_bench_socket_is_for_its_own_server(capsys: pytest.CaptureFixture[str]) -> None:
    assert_refused(capsys, ["--socket", "--server", "127.0.0.1:1"], "--server unix:PATH")


def test_bench_spreads_vec_64_over_the_servers_it_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--servers 2` starts two servers, spreads vec-64 over them (its row says so), plays the
    other scenarios on the first, and stops both."""
    report = tmp_path / "bench.json"
    arguments = ["--servers", "2", "--socket", "--scenarios", "client-1,vec-64", "--seconds", "0.3"]
    arguments += ["--warmup", "0.1", "--warmup-rounds", "0", "--json", str(report)]
    assert bench.main(arguments) == 0
    out = capsys.readouterr().out
    assert "vec-64 over 2 servers" in out
    written = json.loads(report.read_text())
    assert len(written["servers"]) == 2
    assert written["server"] == written["servers"][0]
    rows = {row["scenario"]: row for row in written["results"]}
    assert set(rows) == {"client-1", "vec-64/2-servers"}
    assert rows["vec-64/2-servers"]["steps_per_second"] > 0
    assert not any(Path(address.removeprefix("unix:")).exists() for address in written["servers"])


def test_bench_spreads_over_listed_servers_in_processes(
    server: esrp.LocalServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--server A,B` spreads vec-64 over both, in each of `--processes` children too."""
    with esrp.LocalServer(unix_socket=True) as other:
        report = tmp_path / "bench.json"
        arguments = ["--server", f"{server.address},{other.address}", "--scenarios", "vec-64"]
        arguments += ["--processes", "2", "--seconds", "0.3", "--warmup", "0.1", "--warmup-rounds", "0"]
        assert bench.main([*arguments, "--json", str(report)]) == 0
        addresses = [server.address, other.address]
    capsys.readouterr()
    written = json.loads(report.read_text())
    (row,) = written["results"]
    assert row["scenario"] == "vec-64/2-servers"
    assert len(row["processes_steps_per_second"]) == 2
    assert all(child["servers"] == addresses for child in written["children"])


def test_bench_servers_are_checked(capsys: pytest.CaptureFixture[str]) -> None:
    assert_refused(capsys, ["--servers", "2", "--server", "127.0.0.1:1"], "--servers 2 but --server names 1")
    assert_refused(capsys, ["--servers", "65"], "between 1 and 64")
    assert_refused(capsys, ["--servers", "0"], "between 1 and 64")
    assert_refused(capsys, ["--servers", "2", "--scenarios", "client-1"], "run vec-64")
    assert_refused(capsys, ["--server", " , "], "--server: give an address")
