"""`esrp demos export --format lerobot` against the real server: LeRobot's own loader reads the
dataset; its frames are what the Gymnasium env gives when the episode is played again from the
scene and actions the dataset names (views, goal, grasp flag, action, reward, ends), and torch's
DataLoader batches them. Records export with their ends as they were and their own reward weights'
rewards; bad input is refused in one line, before anything is replayed where it can be, and a
signal stops an export (130, 143): both leave nothing behind.

LeRobot 0.4 needs protobuf < 7 and torch < 2.11: these tests run in their own venv
(`.venv-lerobot`, made by scripts/python-tests.sh), and skip where the `lerobot` extra is not
installed.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import needs
from demo_records import export, played, write_records

import esrp
from esrp.envs import RearrangeEnv
from esrp.eval.results import EpisodeRecord

needs("lerobot", "lerobot")
torch = needs("torch", "lerobot")
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402 - after the check above

__all__ = ["played"]  # the records fixture of demo_records, used here too

EXPERT_ID = "esrp/esrp-bench-v2-easy-expert"


def pixels(image: Any) -> np.ndarray:  # noqa: ANN401 - a torch tensor
    """LeRobot's float (3, R, R) image in [0, 1] as the uint8 (R, R, 3) view it was made of."""
    return np.asarray((image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8))


def sidecar(folder: Path) -> dict[str, Any]:
    result: dict[str, Any] = json.loads((folder / "meta" / "esrp.json").read_text())
    return result


def frames_of(dataset: Any, episode: int) -> list[dict[str, Any]]:  # noqa: ANN401
    """The frames of `episode`, in order."""
    return [dataset[i] for i in range(len(dataset)) if int(dataset[i]["episode_index"]) == episode]


def test_lerobot_loads_the_expert_demonstrations_as_the_env_plays_them(
    server: esrp.LocalServer, client: esrp.Client, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "home"
    scenes = ["--split", "train", "--difficulty", "easy", "--limit", "3", "--resolution", "32"]
    assert export(server, out, "--format", "lerobot", *scenes) == 0
    line = capsys.readouterr().out
    folder = out / EXPERT_ID
    assert f"{folder}: LeRobot dataset {EXPERT_ID}, 3 episodes" in line
    assert f"root={str(folder)!r}" in line

    dataset = LeRobotDataset(EXPERT_ID, root=folder)
    meta = sidecar(folder)
    assert meta["format"] == "esrp.lerobot/v1"
    assert meta["dataset"] == "esrp-bench-v2"
    assert meta["env"] == {
        "id": esrp.ENV_ID,
        "kwargs": {"sensors": {"resolution": 32}, "split": "train", "difficulty": "easy"},
    }
    assert meta["actions"] == ["forward", "backward", "left", "right", "fetch", "release"]
    assert dataset.num_episodes == 3
    assert dataset.fps == 10
    assert dataset.features["observation.images.ego"]["shape"] == (32, 32, 3)
    assert [e["episode_index"] for e in meta["episodes"]] == [0, 1, 2]
    assert all(e["end"] == "success" and e["source"] == "expert" for e in meta["episodes"])
    assert dataset.num_frames == sum(e["steps"] for e in meta["episodes"])
    assert not (folder / "images").exists()

    # Each episode played again from its scene and the dataset's actions gives its frames.
    first = meta["episodes"][0]["scene_id"]
    env = RearrangeEnv(client=client, scene=first, sensors=esrp.Sensors(resolution=32))
    try:
        for described in meta["episodes"]:
            frames = frames_of(dataset, described["episode_index"])
            assert len(frames) == described["steps"]
            observation, _ = env.reset(options=described["options"])
            assert described["options"] == {"scene": described["scene_id"]}
            for k, frame in enumerate(frames):
                assert np.array_equal(pixels(frame["observation.images.ego"]), observation["ego_rgb"])
                assert np.array_equal(pixels(frame["observation.images.goal"]), observation["goal_rgb"])
                assert float(frame["observation.state"]) == float(observation["grasping"])
                assert int(frame["frame_index"]) == k
                assert float(frame["timestamp"]) == pytest.approx(k / 10)
                assert frame["task"] == "Rearrange the furniture to match the goal image."
                observation, reward, terminated, truncated, _ = env.step(int(frame["action"]))
                assert float(frame["next.reward"]) == pytest.approx(reward)
                assert bool(frame["next.done"]) == bool(terminated or truncated) == (k == len(frames) - 1)
                assert bool(frame["next.success"]) == bool(terminated)
    finally:
        env.close()

    # What a LeRobot training loop does with it: torch's DataLoader over the dataset.
    batch = next(iter(torch.utils.data.DataLoader(dataset, batch_size=8)))
    assert tuple(batch["observation.images.ego"].shape) == (8, 3, 32, 32)
    assert tuple(batch["action"].shape) == (8,)

    # A LeRobot home: HF_LEROBOT_HOME=OUT finds the dataset by its id alone.
    code = (
        "from lerobot.datasets.lerobot_dataset import LeRobotDataset; "
        f"print(LeRobotDataset({EXPERT_ID!r}).num_frames)"
    )
    found = subprocess.run(
        [sys.executable, "-c", code],
        env={**os.environ, "HF_LEROBOT_HOME": str(out), "HF_HUB_OFFLINE": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert found.returncode == 0, found.stderr
    assert found.stdout.split()[-1] == str(dataset.num_frames)


def test_records_export_marks_the_ends_as_they_were(
    server: esrp.LocalServer, played: list[EpisodeRecord], tmp_path: Path
) -> None:
    out = tmp_path / "home"
    records = write_records(tmp_path / "records.jsonl", played)
    assert export(server, out, "--format", "lerobot", "--records", str(records)) == 0
    folder = out / "esrp" / "esrp-bench-v2-records"
    dataset = LeRobotDataset("esrp/esrp-bench-v2-records", root=folder)
    meta = sidecar(folder)
    assert meta["env"]["kwargs"] == {"sensors": {"resolution": 128}}  # the horizons differ
    assert [e["scene_id"] for e in meta["episodes"]] == [r.scene_id for r in played]
    assert [e["source"] for e in meta["episodes"]] == [f"{records}:{n}" for n in (1, 2, 3)]
    # success, the horizon of 12, and the random agent's stop after 7 (not an end).
    assert [e["end"] for e in meta["episodes"]] == ["success", "horizon", "agent"]
    for i, record in enumerate(played):
        frames = frames_of(dataset, i)
        assert [int(f["action"]) for f in frames] == record.actions
        assert [bool(f["next.done"]) for f in frames][-1] == (record.end != "agent")
        assert not any(bool(f["next.done"]) for f in frames[:-1])
        assert [bool(f["next.success"]) for f in frames][-1] == record.success
        assert sum(float(f["next.reward"]) for f in frames) == pytest.approx(record.total_reward, abs=1e-4)
    assert export(server, out, "--format", "lerobot", "--records", str(records), "--agent", "human") == 0
    human = out / "esrp" / "esrp-bench-v2-human"
    assert LeRobotDataset("esrp/esrp-bench-v2-human", root=human).num_episodes == 2


def test_bad_input_is_refused_and_leaves_nothing(
    server: esrp.LocalServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "home"
    one = ["--split", "test", "--difficulty", "easy", "--limit", "1", "--resolution", "16"]
    assert export(server, out, "--format", "lerobot", *one) == 0
    capsys.readouterr()
    assert export(server, out, "--format", "lerobot", *one) == 2
    assert "exists: LeRobot datasets are never overwritten" in capsys.readouterr().err
    assert export(server, out, "--format", "lerobot", "--dataset-id", "no spaces!", *one) == 2
    assert "--dataset-id 'no spaces!'" in capsys.readouterr().err
    assert export(server, out, "--format", "lerobot", "--dataset-id", "alone", *one) == 2
    assert "a LeRobot dataset's id is NAMESPACE/NAME" in capsys.readouterr().err
    assert export(server, out, "--format", "lerobot", "--dagger", "random", *one) == 2
    assert "--format lerobot writes demonstrations and records, not DAgger's" in capsys.readouterr().err
    assert export(server, out, "--format", "lerobot", "--episodes-in-flight", "2", *one) == 2
    assert "(no --records, no --format lerobot)" in capsys.readouterr().err
    assert export(server, out, "--dataset-id", "a/b", *one) == 2
    assert "--dataset-id only applies with --format minari or lerobot" in capsys.readouterr().err
    assert export(server, out, "--format", "lerobot", "--dataset-id", "", *one) == 2  # not the default
    assert "--dataset-id '': a LeRobot dataset's id is NAMESPACE/NAME" in capsys.readouterr().err
    assert export(server, out, "--format", "lerobot", "--dataset-id", "a/b/c", *one) == 2
    assert "--dataset-id 'a/b/c': a LeRobot dataset's id is NAMESPACE/NAME\n" in capsys.readouterr().err
    # Only the first dataset is there: no staging folder is left behind.
    assert [p.name for p in out.iterdir()] == ["esrp"]
    assert [p.name for p in (out / "esrp").iterdir()] == ["esrp-bench-v2-test-easy-expert"]


def test_an_out_or_a_namespace_that_is_a_file_is_refused_before_anything_is_replayed(
    server: esrp.LocalServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    one = ["--split", "test", "--difficulty", "easy", "--limit", "1", "--resolution", "16"]
    mine = tmp_path / "mine.txt"
    mine.write_text("mine\n")
    assert export(server, mine, "--format", "lerobot", *one) == 2
    assert capsys.readouterr().err == f"esrp demos export: --out {mine} is a file, not a folder\n"
    # The id's namespace is a file in --out: said at once, not once every episode has been replayed.
    out = tmp_path / "home"
    out.mkdir()
    (out / "esrp").write_text("mine\n")
    assert export(server, out, "--format", "lerobot", *one) == 2
    assert f"{out / 'esrp'} is a file: the dataset cannot go in it" in capsys.readouterr().err
    assert mine.read_text() == (out / "esrp").read_text() == "mine\n"
    assert [p.name for p in out.iterdir()] == ["esrp"]


def test_a_refused_export_leaves_no_folder_it_made_and_the_closing_line_is_absolute(
    server: esrp.LocalServer,
    played: list[EpisodeRecord],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A refused export left the `--out` folder it had made, empty; and the closing line repeated a
    relative `--out` as typed (as the Minari export's did: test_minari checks both further)."""
    tampered = dataclasses.replace(played[0], total_reward=played[0].total_reward + 1.0)
    records = write_records(tmp_path / "tampered.jsonl", [tampered])
    empty = tmp_path / "empty"
    empty.mkdir()
    for out in (tmp_path / "new" / "home", empty):
        assert export(server, out, "--format", "lerobot", "--records", str(records)) == 2
        assert "does not reproduce the record" in capsys.readouterr().err
        assert not (tmp_path / "new").exists()
        assert list(empty.iterdir()) == []
    monkeypatch.chdir(tmp_path)
    one = ["--split", "test", "--difficulty", "easy", "--limit", "1", "--resolution", "16"]
    assert export(server, Path("home"), "--format", "lerobot", *one) == 0
    folder = tmp_path / "home" / "esrp" / "esrp-bench-v2-test-easy-expert"
    line = capsys.readouterr().out
    assert line.startswith(f"{folder}: LeRobot dataset esrp/esrp-bench-v2-test-easy-expert, 1 episodes")
    assert f"root={str(folder)!r}" in line


def test_a_default_id_that_is_no_repository_id_asks_for_one(
    server: esrp.LocalServer, played: list[EpisodeRecord], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The records of `esrp eval --agent MODULE:CALLABLE` carry that name, which no repository id holds.
    agent = "my_agents.policy:make"
    records = write_records(tmp_path / "mine.jsonl", [dataclasses.replace(played[0], agent=agent)])
    out = tmp_path / "home"
    assert export(server, out, "--format", "lerobot", "--records", str(records), "--agent", agent) == 2
    err = capsys.readouterr().err
    assert f"the default id 'esrp/esrp-bench-v2-{agent}': " in err, err
    assert err.endswith(" (pass --dataset-id NAMESPACE/NAME)\n"), err
    assert "--dataset-id 'esrp" not in err
    mine = ["--records", str(records), "--agent", agent, "--dataset-id", "me/policy"]
    assert export(server, out, "--format", "lerobot", *mine) == 0
    assert LeRobotDataset("me/policy", root=out / "me" / "policy").num_episodes == 1


def test_a_record_that_does_not_replay_is_refused_and_nothing_is_written(
    server: esrp.LocalServer, played: list[EpisodeRecord], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "home"
    # The first record replays; the second claims another total reward: the checks are esrp verify's.
    tampered = dataclasses.replace(played[1], total_reward=played[1].total_reward + 1.0)
    records = write_records(tmp_path / "tampered.jsonl", [played[0], tampered])
    assert export(server, out, "--format", "lerobot", "--records", str(records)) == 2
    err = capsys.readouterr().err
    assert f"{records}:2: {played[1].scene_id}: the replay does not reproduce the record (total_reward" in err
    assert not out.exists()  # the export made it, and removed it with nothing in it
    # A record of a scene the server does not serve: the record is named, in one line.
    elsewhere = dataclasses.replace(played[1], scene_id="esrp-bench-v2/99999")
    records = write_records(tmp_path / "elsewhere.jsonl", [played[0], elsewhere])
    assert export(server, out, "--format", "lerobot", "--records", str(records)) == 2
    err = capsys.readouterr().err
    assert err.startswith(
        f"esrp demos export: {records}:2: esrp-bench-v2/99999: the replay failed: SceneNotFound"
    )
    assert err.count("\n") == 1, err
    assert not out.exists()


def test_the_staging_folder_of_a_killed_export_is_removed_by_the_next(
    server: esrp.LocalServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "home"
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    stale = out / f".esrp-lerobot-{gone.pid}-x1"
    (stale / "dataset" / "meta").mkdir(parents=True)
    (stale / "dataset" / "meta" / "info.json").write_text("{half written")
    running = out / f".esrp-lerobot-{os.getpid()}-x2"  # an export still running
    running.mkdir()
    one = ["--split", "test", "--difficulty", "easy", "--limit", "1", "--resolution", "16"]
    assert export(server, out, "--format", "lerobot", *one) == 0
    assert f"removed {stale}, left by an export that was killed" in capsys.readouterr().err
    assert not stale.exists()
    assert running.exists()


def test_a_records_reward_weights_give_its_rewards(
    server: esrp.LocalServer, client: esrp.Client, played: list[EpisodeRecord], tmp_path: Path
) -> None:
    weights = {"success": 10.0, "place": 1.0, "unplace": -1.0, "potential": 1.0, "holding": 0.01}
    weights["living"] = -0.05
    base = played[2]  # a random agent's episode, closed before it ended
    with client.create_episode(
        base.scene_id, horizon=base.horizon, reward=esrp.RewardWeights(**weights)
    ) as episode:
        rewards = [episode.step(action).reward for action in base.actions]
        metrics = episode.close()
    record = dataclasses.replace(base, total_reward=metrics.total_reward, reward_weights=weights)
    assert record.total_reward != base.total_reward
    records = write_records(tmp_path / "weighted.jsonl", [record])
    out = tmp_path / "home"
    assert export(server, out, "--format", "lerobot", "--records", str(records), "--resolution", "16") == 0
    folder = out / "esrp" / "esrp-bench-v2-records"
    frames = frames_of(LeRobotDataset("esrp/esrp-bench-v2-records", root=folder), 0)
    assert [float(frame["next.reward"]) for frame in frames] == pytest.approx(rewards, abs=1e-6)
    assert sidecar(folder)["env"]["kwargs"] == {
        "sensors": {"resolution": 16},
        "horizon": base.horizon,
        "reward": weights,
    }


@pytest.mark.parametrize(
    ("sent", "status", "said"), [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")]
)
def test_a_signal_stops_the_export_and_leaves_nothing(
    server: esrp.LocalServer, tmp_path: Path, sent: signal.Signals, status: int, said: str
) -> None:
    out = tmp_path / "home"
    command = [sys.executable, "-m", "esrp.cli", "demos", "export", "--format", "lerobot"]
    command += ["--server", server.address, "--split", "train", "--difficulty", "easy", "--limit", "20"]
    command += ["--resolution", "16", "--out", str(out)]
    child = subprocess.Popen(
        command, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    assert child.stderr is not None
    first = child.stderr.readline()  # the first episode's progress line: the dataset is being written
    assert first.startswith(b"1/20 episodes, "), first + child.communicate(timeout=60)[1]
    assert [path.name.startswith(".esrp-lerobot-") for path in out.iterdir()] == [True]
    child.send_signal(sent)
    _, err = child.communicate(timeout=60)
    assert child.returncode == status, err
    assert err.decode().endswith(f"esrp demos: {said}\n"), err
    assert not out.exists()  # no dataset, no staging folder, and no --out folder it made
