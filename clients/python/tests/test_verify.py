"""`esrp verify` against the real server: an honest `esrp eval` file (and the same records as a
server writes them) verifies; a changed action, a changed metric, another dataset, a challenge
scene and inconsistent ends are named, file:line, and nothing else is."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import esrp
from esrp.cli import main
from esrp.eval.results import read_records
from esrp.eval.verify import compare


@pytest.fixture(scope="module")
def honest(
    server: esrp.LocalServer, easy_scenes: list[str], tmp_path_factory: pytest.TempPathFactory
) -> Path:
    """Random-agent records of three easy test scenes (horizon 200), written by `esrp eval`."""
    out = tmp_path_factory.mktemp("verify") / "random.jsonl"
    scenes = ",".join(easy_scenes[:3])
    args = ["eval", "--agent", "random", "--seed", "5", "--scenes", scenes, "--no-progress"]
    assert main([*args, "--out", str(out), "--server", server.address]) == 0
    return out


def lines_of(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def write(path: Path, records: list[dict[str, Any]]) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return path


def verify(server: esrp.LocalServer, *paths: Path) -> int:
    return main(["verify", *map(str, paths), "--server", server.address, "--no-progress"])


def test_an_honest_file_and_the_servers_records_of_it_verify(
    server: esrp.LocalServer, honest: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The same episodes as the server records them (docs/evaluation.md): its own fields besides.
    as_server = [
        r
        | {
            "agent": "unnamed",
            "agent_config": {},
            "seed": None,
            "agent_stats": {},
            "client": "esrp-server 0.1.0",
        }
        | {
            "token": "team-a",
            "started_at": r["finished_at"],
            "dataset_hash": "0123456789abcdef",
            "counted": False,
        }
        for r in lines_of(honest)
    ]
    recorded = write(tmp_path / "team-a.jsonl", as_server)
    capsys.readouterr()
    assert verify(server, honest, recorded) == 0
    assert capsys.readouterr().out == "6 records verified, all match\n"


def first_effective_fetch(client: esrp.Client, record: dict[str, Any]) -> int | None:
    """The index of the record's first action that fetched an object, replayed on `client`."""
    with client.create_episode(record["scene_id"], horizon=record["horizon"]) as episode:
        for k, action in enumerate(record["actions"]):
            if episode.step(action).info.fetched is not None:
                return k
    return None


def test_a_changed_action_and_a_changed_metric_are_named(
    server: esrp.LocalServer,
    client: esrp.Client,
    honest: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    records = lines_of(honest)
    # An action whose change must show: the first fetch that took an object becomes a left turn,
    # so the object is held fewer steps (the holding reward) at the least.
    fetches = [first_effective_fetch(client, r) for r in records]
    changed = next(k for k, fetch in enumerate(fetches) if fetch is not None)
    fetch = fetches[changed]
    assert fetch is not None
    records[changed]["actions"][fetch] = int(esrp.Action.LEFT)
    edited_action = write(tmp_path / "action.jsonl", records)
    capsys.readouterr()
    assert verify(server, edited_action) == 1
    out = capsys.readouterr().out.splitlines()
    scene = records[changed]["scene_id"]
    assert len(out) == 2, out
    assert out[0].startswith(f"{edited_action}:{changed + 1}: {scene}: "), out
    assert "total_reward: recorded " in out[0]
    assert out[1] == "1 of 3 records do not match"

    records = lines_of(honest)
    other = (changed + 1) % 3
    recorded_osr = records[other]["osr"]
    records[other]["osr"] = 0.5 if recorded_osr != 0.5 else 0.25
    edited_metric = write(tmp_path / "metric.jsonl", records)
    assert verify(server, edited_metric) == 1
    out = capsys.readouterr().out.splitlines()
    assert out == [
        f"{edited_metric}:{other + 1}: {records[other]['scene_id']}: osr: recorded "
        f"{records[other]['osr']!r}, replayed {recorded_osr!r}",
        "1 of 3 records do not match",
    ]


def test_records_that_cannot_replay_here_are_said_why(
    server: esrp.LocalServer, honest: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    first = lines_of(honest)[0]
    records = [
        first | {"dataset": "esrp-bench-v1"},
        first | {"scene_id": "challenge/00012", "split": "challenge"},
        first | {"end": "agent"},  # it ended at the horizon with its last action
        first | {"actions": [*first["actions"], 0], "steps": first["steps"] + 1},  # one past its end
        first,
    ]
    path = write(tmp_path / "odd.jsonl", records)
    capsys.readouterr()
    assert verify(server, path) == 1
    out = capsys.readouterr().out.splitlines()
    scene = first["scene_id"]
    assert out[0] == (
        f"{path}:1: {scene}: dataset: the record is of 'esrp-bench-v1', the server serves 'esrp-bench-v2' "
        "(start a server of that dataset)"
    )
    assert out[1].startswith(
        f"{path}:2: challenge/00012: not replayed: challenge scenes replay only on a server started with "
        "the challenge's --challenge-seed (and an admin token)"
    )
    assert out[2] == f"{path}:3: {scene}: end: recorded 'agent', replayed 'horizon'"
    assert out[3] == (
        f"{path}:4: {scene}: the replay ended (horizon) after 200 of the record's 201 actions; "
        "steps: recorded 201, replayed 200"
    )
    assert out[4:] == ["4 of 5 records do not match"]


def test_ends_are_checked_against_where_the_replay_ended(honest: Path) -> None:
    record = read_records(honest).records[0]
    metrics = esrp.EpisodeMetrics(
        success=record.success,
        object_success_rate=record.osr,
        remaining_distance_ratio=record.rdr,
        stage=record.stage,
        placed=record.placed,
        movable_objects=record.objects,
        steps=record.steps,
        total_reward=record.total_reward,
    )
    assert record.end == "horizon"
    assert compare(record, metrics, len(record.actions)) == []
    # Still running after its last action: the record says it ended.
    assert compare(record, metrics, None) == ["end: recorded 'horizon', replayed 'agent'"]
    record.end = "agent"
    assert compare(record, metrics, None) == []


def test_bad_input_is_one_line_with_status_2(
    server: esrp.LocalServer, honest: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    not_results = tmp_path / "notes.jsonl"
    not_results.write_text('{"schema": "esrp.demos/v1"}\n{"x": 1}\n')
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    cases = [
        ([str(tmp_path / "missing.jsonl")], "esrp verify: cannot read"),
        ([str(not_results)], f"esrp verify: {not_results}:1: not an esrp.results/v1 record"),
        ([str(empty)], "esrp verify: the results files hold no records"),
    ]
    for args, message in cases:
        capsys.readouterr()
        assert main(["verify", *args, "--server", server.address]) == 2, args
        err = capsys.readouterr().err
        assert err.startswith(message), err
        assert err.count("\n") == 1, err
    # argparse's errors exit (status 2) from the parser.
    with pytest.raises(SystemExit) as exited:
        main(["verify", str(honest), "--episodes-in-flight", "0"])
    assert exited.value.code == 2
    assert capsys.readouterr().err == (
        "esrp verify: error: argument --episodes-in-flight: must be at least 1, not 0 "
        "(see esrp verify --help)\n"
    )
