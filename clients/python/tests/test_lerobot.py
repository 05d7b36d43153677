"""`esrp demos export --format lerobot` against the real server: LeRobot's own loader reads the
dataset; its frames are what the Gymnasium env gives when the episode is played again from the
scene and actions the dataset names (views, goal, grasp flag, action, reward, ends), and torch's
DataLoader batches them. Records export with their ends as they were, and bad input is refused in
one line, leaving nothing behind.

LeRobot 0.4 needs protobuf < 7 and torch < 2.11: these tests run in their own venv
(`.venv-lerobot`, made by scripts/python-tests.sh), and skip where the `lerobot` extra is not
installed.
"""

from __future__ import annotations

import dataclasses
import json
import os
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
    # Only the first dataset is there: no staging folder is left behind.
    assert [p.name for p in out.iterdir()] == ["esrp"]
    assert [p.name for p in (out / "esrp").iterdir()] == ["esrp-bench-v2-test-easy-expert"]


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
    assert list(out.iterdir()) == []


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
