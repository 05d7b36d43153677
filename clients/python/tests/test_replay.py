"""`esrp replay`: recorded actions re-run on the server reproduce the record, frame for frame."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import esrp
from esrp.cli import main
from esrp.replay import AGENT_PATH, OBJECT_PATH, ReplayError, replay_record
from esrp.results import EpisodeRecord, read_records


@pytest.fixture(scope="module")
def random_records(server: esrp.LocalServer, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A random agent's records on two medium scenes (they fetch now and then)."""
    out = tmp_path_factory.mktemp("replay") / "random.jsonl"
    args = ["eval", "--agent", "random", "--difficulty", "medium", "--limit", "2", "--seed", "5"]
    assert main([*args, "--out", str(out), "--server", server.address]) == 0
    return out


def test_replay_frames_are_identical_across_runs(client: esrp.Client, random_records: Path) -> None:
    record = read_records(random_records).records[0]
    first = replay_record(client, record)
    second = replay_record(client, record)
    assert len(first.frames) == len(record.actions) + 1
    assert all(np.array_equal(a, b) for a, b in zip(first.frames, second.frames, strict=True))
    assert first.metrics.steps == record.steps
    assert first.metrics.object_success_rate == record.osr
    assert first.metrics.remaining_distance_ratio == record.rdr
    # Three panels side by side under a caption, the paths drawn on the top-down view.
    last = first.frames[-1]
    assert last.shape == (256 + 14, 3 * 256 + 8, 3)
    top_down = last[14:, 2 * (256 + 4) :]
    assert (top_down == AGENT_PATH).all(axis=-1).sum() > 50
    if record.stage >= 3:  # something was carried
        assert (top_down == OBJECT_PATH).all(axis=-1).sum() > 10
    # A still is the last frame alone.
    still = replay_record(client, record, every_frame=False)
    assert len(still.frames) == 1
    assert np.array_equal(still.frames[0], last)


def test_replay_files(server: esrp.LocalServer, random_records: Path, tmp_path: Path) -> None:
    from PIL import Image

    scene = read_records(random_records).records[1].scene_id
    for name in ("ep.gif", "ep.png"):
        out = tmp_path / name
        args = [
            "replay",
            "--results",
            str(random_records),
            "--scene",
            scene,
            "--out",
            str(out),
            "--scale",
            "1",
        ]
        assert main([*args, "--server", server.address]) == 0
        with Image.open(out) as image:
            assert image.size == (3 * 128 + 8, 128 + 14)
            frames = getattr(image, "n_frames", 1)
        record = read_records(random_records).records[1]
        assert frames == (len(record.actions) + 1 if name.endswith(".gif") else 1)


def test_a_record_that_does_not_replay_is_an_error(
    client: esrp.Client, random_records: Path, capsys: pytest.CaptureFixture[str], server: esrp.LocalServer
) -> None:
    record: EpisodeRecord = read_records(random_records).records[0]
    wrong = dataclasses.replace(record, rdr=record.rdr + 0.25)
    with pytest.raises(ReplayError, match=r"does not reproduce the record: rdr"):
        replay_record(client, wrong, every_frame=False)
    fewer = dataclasses.replace(record, actions=record.actions[:10])
    with pytest.raises(ReplayError, match="steps 200 \\(replay 10\\)"):
        replay_record(client, fewer, every_frame=False)
    other = dataclasses.replace(record, dataset="another-dataset")
    with pytest.raises(ReplayError, match="serves 'esrp-bench-v2'"):
        replay_record(client, other, every_frame=False)
    args = ["replay", "--results", str(random_records), "--scene", "nope", "--out", "x.gif"]
    assert main([*args, "--server", server.address]) == 2
    assert "has no record of scene 'nope'" in capsys.readouterr().err
