"""`esrp demos export --format minari` against the real server: Minari's own loader reads the
dataset from a datasets root; its episodes equal the zarr export of the same scenes (views, goal,
grasp flags, actions), carry their scene ids, rewards and ends, and the env spec recovers the env.
Records export too (horizon ends, and an agent's early stop marked truncated), and bad input is
refused in one line, leaving nothing behind."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from demo_records import export, played, write_records

import esrp
from esrp.eval.results import EpisodeRecord

minari = pytest.importorskip("minari", reason="esrp[minari] is not installed")
zarr = pytest.importorskip("zarr", reason="esrp[train] is not installed")

__all__ = ["played"]  # the records fixture of demo_records, used here too

DATASET_ID = "esrp/esrp-bench-v2-easy/expert-v0"


@pytest.fixture
def datasets_root(tmp_path: Path) -> Iterator[Path]:
    """A Minari datasets root, as `MINARI_DATASETS_PATH` for the test."""
    root = tmp_path / "datasets"
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield root
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def test_minari_loads_the_expert_demonstrations_as_the_zarr_export_holds_them(
    server: esrp.LocalServer, datasets_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scenes = ["--split", "train", "--difficulty", "easy", "--limit", "3", "--resolution", "32"]
    assert export(server, datasets_root, "--format", "minari", *scenes) == 0
    assert f"Minari dataset {DATASET_ID}, 3 episodes" in capsys.readouterr().out
    assert export(server, tmp_path / "demos.zarr", *scenes) == 0
    assert DATASET_ID in minari.list_local_datasets()
    dataset = minari.load_dataset(DATASET_ID)
    store = zarr.open_group(str(tmp_path / "demos.zarr"), mode="r")
    ends = store["meta/episode_ends"][:]
    assert dataset.total_episodes == 3
    assert dataset.total_steps == int(ends[-1])
    assert dataset.observation_space["ego_rgb"].shape == (32, 32, 3)
    assert dataset.action_space == gymnasium.spaces.Discrete(6)
    metadata = list(dataset.storage.get_episode_metadata(range(3)))
    assert [m["options"]["scene"] for m in metadata] == store.attrs["scene_ids"]
    start = 0
    for i, episode in enumerate(dataset.iterate_episodes()):
        end = int(ends[i])
        steps = end - start
        assert len(episode) == steps
        observations = episode.observations
        assert observations["ego_rgb"].shape == (steps + 1, 32, 32, 3)
        assert np.array_equal(observations["ego_rgb"][:-1], store["data/ego_rgb"][start:end])
        assert np.array_equal(observations["grasping"][:-1].astype(bool), store["data/grasping"][start:end])
        assert np.array_equal(episode.actions, store["data/action"][start:end].astype(np.int64))
        assert (observations["goal_rgb"] == store["meta/goal_rgb"][i]).all()
        assert episode.terminations.tolist() == [False] * (steps - 1) + [True]  # solved at the end
        assert not episode.truncations.any()
        assert episode.rewards[-1] >= 10  # the success reward on the last step
        start = end
    # The env spec has JSON kwargs (no address) and recovers an env of the same spaces.
    spec = dataset.spec.env_spec
    assert spec.id == esrp.ENV_ID
    assert spec.kwargs == {"sensors": {"resolution": 32}, "split": "train", "difficulty": "easy"}
    env = dataset.recover_environment(address=server.address)
    try:
        assert env.observation_space == dataset.observation_space
        observation, info = env.reset(options=metadata[1]["options"])
        assert info["scene_id"] == store.attrs["scene_ids"][1]
        assert np.array_equal(observation["ego_rgb"], store["data/ego_rgb"][int(ends[0])])
    finally:
        env.close()


def test_records_export_marks_the_ends_as_they_were(
    server: esrp.LocalServer, played: list[EpisodeRecord], datasets_root: Path
) -> None:
    records = write_records(datasets_root.parent / "records.jsonl", played)
    assert export(server, datasets_root, "--format", "minari", "--records", str(records)) == 0
    dataset = minari.load_dataset("esrp/esrp-bench-v2/records-v0")
    episodes = list(dataset.iterate_episodes())
    assert [len(e) for e in episodes] == [len(r.actions) for r in played]
    assert [e.actions.tolist() for e in episodes] == [r.actions for r in played]
    # success, the horizon of 12, and the random agent's stop after 7 (marked truncated).
    assert [(bool(e.terminations[-1]), bool(e.truncations[-1])) for e in episodes] == [
        (True, False),
        (False, True),
        (False, True),
    ]
    assert dataset.spec.env_spec.kwargs == {"sensors": {"resolution": 128}}  # horizons differ
    assert (
        export(server, datasets_root, "--format", "minari", "--records", str(records), "--agent", "human")
        == 0
    )
    assert minari.load_dataset("esrp/esrp-bench-v2/human-v0").total_episodes == 2


def test_bad_input_is_refused_and_leaves_nothing(
    server: esrp.LocalServer, datasets_root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    one = ["--split", "test", "--difficulty", "easy", "--limit", "1", "--resolution", "16"]
    assert export(server, datasets_root, "--format", "minari", *one) == 0
    capsys.readouterr()
    assert export(server, datasets_root, "--format", "minari", *one) == 2
    assert "exists: Minari datasets are never overwritten" in capsys.readouterr().err
    assert export(server, datasets_root, "--format", "minari", "--dataset-id", "no spaces!", *one) == 2
    assert "--dataset-id 'no spaces!'" in capsys.readouterr().err
    assert export(server, datasets_root, "--format", "minari", "--dagger", "random", *one) == 2
    assert "not DAgger's labels" in capsys.readouterr().err
    assert export(server, datasets_root, "--dataset-id", "a/b-v0", *one) == 2
    assert "--dataset-id only applies with --format minari" in capsys.readouterr().err
    # Only the first dataset and its namespace are there: no staging folder is left behind.
    assert sorted(p.name for p in datasets_root.iterdir()) == ["esrp"]
    assert list(minari.list_local_datasets()) == ["esrp/esrp-bench-v2-test-easy/expert-v0"]
    # A namespace that is a file in the root: said at once, not after every episode's replay.
    other = datasets_root.parent / "other"
    other.mkdir()
    (other / "esrp").write_text("mine\n")
    assert export(server, other, "--format", "minari", *one) == 2
    assert f"{other / 'esrp'} is a file: the dataset cannot go in it" in capsys.readouterr().err
    assert [p.name for p in other.iterdir()] == ["esrp"]


def test_a_relative_out_is_the_folder_under_the_working_directory(
    server: esrp.LocalServer, datasets_root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(datasets_root.parent)
    one = ["--split", "test", "--difficulty", "easy", "--limit", "1", "--resolution", "16"]
    assert export(server, Path("datasets"), "--format", "minari", *one) == 0
    assert [path.name for path in datasets_root.iterdir()] == ["esrp"]  # no staging folder left
    assert minari.load_dataset("esrp/esrp-bench-v2-test-easy/expert-v0").total_episodes == 1


def test_a_record_whose_reward_does_not_replay_is_refused(
    server: esrp.LocalServer,
    played: list[EpisodeRecord],
    datasets_root: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    # The same end after the same steps, another total reward: the checks are esrp verify's.
    tampered = dataclasses.replace(played[0], total_reward=played[0].total_reward + 1.0)
    records = write_records(datasets_root.parent / "tampered.jsonl", [tampered])
    assert export(server, datasets_root, "--format", "minari", "--records", str(records)) == 2
    err = capsys.readouterr().err
    assert "the replay does not reproduce the record (total_reward: recorded" in err, err
    assert not (datasets_root / "esrp" / "esrp-bench-v2").exists()


def test_a_refused_export_leaves_no_folder_it_made_and_keeps_those_that_were_there(
    server: esrp.LocalServer,
    played: list[EpisodeRecord],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """An export refused once its replays had begun (a record that does not replay, a scene the
    server does not serve) removed its staging folder but left the `--out` folder it had created,
    empty. It leaves nothing it made now, the folders above `--out` it made included; a folder that
    was there before stays, empty or not."""
    tampered = dataclasses.replace(played[0], total_reward=played[0].total_reward + 1.0)
    unknown = dataclasses.replace(played[0], scene_id="esrp-bench-v2/no-such-scene")
    cases = [
        (write_records(tmp_path / "tampered.jsonl", [played[1], tampered]), "does not reproduce the record"),
        (write_records(tmp_path / "unknown.jsonl", [unknown]), "no-such-scene: the replay failed"),
    ]
    empty = tmp_path / "empty"
    empty.mkdir()
    full = tmp_path / "full"
    (full / "mine").mkdir(parents=True)
    for records, why in cases:
        for out in (tmp_path / "new" / "deeper" / "datasets", empty, full, empty / "new"):
            assert export(server, out, "--format", "minari", "--records", str(records)) == 2
            assert why in capsys.readouterr().err
            assert not (tmp_path / "new").exists()
            assert list(empty.iterdir()) == []
            assert [p.name for p in full.iterdir()] == ["mine"]


def test_the_closing_line_names_the_datasets_root_as_an_absolute_path(
    server: esrp.LocalServer,
    datasets_root: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """It repeated `--out` as typed: a relative root, which loads nothing from another folder."""
    monkeypatch.chdir(datasets_root.parent)
    one = ["--split", "test", "--difficulty", "easy", "--limit", "1", "--resolution", "16"]
    assert export(server, Path("datasets"), "--format", "minari", *one) == 0
    line = capsys.readouterr().out.strip()
    dataset_id = "esrp/esrp-bench-v2-test-easy/expert-v0"
    assert datasets_root.is_absolute()
    assert line.startswith(f"{datasets_root}: Minari dataset {dataset_id}, 1 episodes, ")
    assert line.endswith(f" steps (MINARI_DATASETS_PATH={datasets_root} minari.load_dataset({dataset_id!r}))")


def test_the_records_reward_weights_go_into_the_env_spec(
    server: esrp.LocalServer, client: esrp.Client, played: list[EpisodeRecord], datasets_root: Path
) -> None:
    weights = {"success": 10.0, "place": 1.0, "unplace": -1.0, "potential": 1.0, "holding": 0.01}
    weights["living"] = -0.05
    base = played[2]  # a random agent's episode, closed before it ended
    reward = esrp.RewardWeights(**weights)
    with client.create_episode(base.scene_id, horizon=base.horizon, reward=reward) as episode:
        rewards = [episode.step(action).reward for action in base.actions]
        metrics = episode.close()
    record = dataclasses.replace(base, total_reward=metrics.total_reward, reward_weights=weights)
    assert record.total_reward != base.total_reward
    records = write_records(datasets_root.parent / "weighted.jsonl", [record])
    assert export(server, datasets_root, "--format", "minari", "--records", str(records)) == 0
    dataset = minari.load_dataset("esrp/esrp-bench-v2/records-v0")
    assert dataset.spec.env_spec.kwargs["reward"] == weights
    assert next(dataset.iterate_episodes()).rewards.tolist() == rewards
    env = dataset.recover_environment(address=server.address)
    try:
        env.reset(options={"scene": base.scene_id})
        assert [float(env.step(action)[1]) for action in base.actions] == rewards
    finally:
        env.close()


def test_the_staging_folder_of_a_killed_export_is_removed_by_the_next(
    server: esrp.LocalServer, datasets_root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    stale = datasets_root / f".esrp-minari-{gone.pid}-x1"
    stale.mkdir(parents=True)
    (stale / "main_data.hdf5").write_bytes(b"half written")
    running = datasets_root / f".esrp-minari-{os.getpid()}-x2"  # an export still running
    running.mkdir()
    one = ["--split", "test", "--difficulty", "easy", "--limit", "1", "--resolution", "16"]
    assert export(server, datasets_root, "--format", "minari", *one) == 0
    assert f"removed {stale}, left by an export that was killed" in capsys.readouterr().err
    assert not stale.exists()
    assert running.exists()
