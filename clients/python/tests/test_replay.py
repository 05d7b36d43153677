"""`esrp replay`: recorded actions re-run on the server reproduce the record, frame for frame."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

import esrp
from esrp.cli import main
from esrp.eval.replay import AGENT_PATH, OBJECT_PATH, ReplayError, replay_record
from esrp.eval.results import EpisodeRecord, read_records


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
    # Three panels side by side under a header, the paths drawn on the top-down view.
    from esrp.eval.replay import header_height

    header = header_height(2)
    last = first.frames[-1]
    assert last.shape == (256 + header, 3 * 256 + 8, 3)
    top_down = last[header:, 2 * (256 + 4) :]
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
        from esrp.eval.replay import header_height

        with Image.open(out) as image:
            assert image.size == (3 * 128 + 8, 128 + header_height(1))
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
    with pytest.raises(ReplayError, match="steps: recorded 200, replayed 10"):
        replay_record(client, fewer, every_frame=False)
    other = dataclasses.replace(record, dataset="another-dataset")
    with pytest.raises(ReplayError, match="serves 'esrp-bench-v2'"):
        replay_record(client, other, every_frame=False)
    args = ["replay", "--results", str(random_records), "--scene", "nope", "--out", "x.gif"]
    assert main([*args, "--server", server.address]) == 2
    assert "has no record of scene 'nope'" in capsys.readouterr().err


def test_a_replay_is_compared_with_its_record_as_verify_compares_it(
    client: esrp.Client, random_records: Path
) -> None:
    """The replay compared OSR, RDR and the reward within a relative 1e-9 and ignored `end`, where
    `esrp verify` compares all exactly: a record one double off, or ended otherwise, replayed
    without a word. Both now share `esrp.eval.verify.compare`."""
    record: EpisodeRecord = read_records(random_records).records[0]
    assert replay_record(client, record, every_frame=False).metrics.total_reward == record.total_reward

    def above(value: float) -> float:  # the next double: one unit in the last place off
        return math.nextafter(value, math.inf)

    offs = {
        "osr": dataclasses.replace(record, osr=above(record.osr)),
        "rdr": dataclasses.replace(record, rdr=above(record.rdr)),
        "total_reward": dataclasses.replace(record, total_reward=above(record.total_reward)),
    }
    for name, off in offs.items():
        with pytest.raises(ReplayError, match=rf"does not reproduce the record: {name}: recorded "):
            replay_record(client, off, every_frame=False)
    assert record.end == "horizon"
    with pytest.raises(ReplayError, match="end: recorded 'agent', replayed 'horizon'"):
        replay_record(client, dataclasses.replace(record, end="agent"), every_frame=False)
    # Actions past the episode's end: the replay ends first, which `compare` says.
    longer = dataclasses.replace(record, actions=[*record.actions, 2, 2])
    with pytest.raises(ReplayError, match=rf"ended \(horizon\) after {record.steps} of the record's"):
        replay_record(client, longer, every_frame=False)


def test_a_record_replays_with_the_reward_weights_it_played_with(
    server: esrp.LocalServer, client: esrp.Client, random_records: Path, tmp_path: Path
) -> None:
    # A server record of an episode whose client set its own weights (a living cost here) says so
    # in `reward_weights`; its replay pays the same rewards, as `esrp verify`'s does.
    base: EpisodeRecord = read_records(random_records).records[0]
    weights = {"success": 10.0, "place": 1.0, "unplace": -1.0, "potential": 1.0, "holding": 0.01}
    weights["living"] = -0.05
    reward = esrp.RewardWeights(**weights)
    with client.create_episode(base.scene_id, horizon=base.horizon, reward=reward) as episode:
        for action in base.actions:
            episode.step(action)
        metrics = episode.close()
    record = dataclasses.replace(base, total_reward=metrics.total_reward, reward_weights=weights)
    assert record.total_reward != base.total_reward
    assert replay_record(client, record, every_frame=False).metrics.total_reward == record.total_reward
    results = tmp_path / "weighted.jsonl"
    results.write_text(record.to_json() + "\n")
    args = ["replay", "--results", str(results), "--scene", record.scene_id, "--out", str(tmp_path / "w.png")]
    assert main([*args, "--server", server.address]) == 0


def test_frames_say_what_each_step_did(client: esrp.Client, random_records: Path) -> None:
    """Frames carried a one-line caption alone: each now names its action, whether it was accepted,
    collided or had no effect, the grasp flag and the reward, and labels its three panels."""
    from esrp.eval.replay import PANEL_TITLES, header_height

    record = read_records(random_records).records[0]
    replay = replay_record(client, record, scale=2)
    assert len(replay.notes) == len(replay.frames) == len(record.actions) + 1
    assert replay.notes[0].action == "start (no action yet)"
    assert replay.notes[0].state == "grasping: no  reward +0.000  total +0.000"
    # The same steps again, to compare each note with what the step answered.
    total = 0.0
    outcomes = set()
    with client.create_episode(record.scene_id, horizon=record.horizon) as episode:
        for k, action in enumerate(record.actions, start=1):
            result = episode.step(action)
            total += result.reward
            note = replay.notes[k]
            assert note.caption == f"{record.scene_id}  random  step {k}/{len(record.actions)}"
            assert note.action.startswith(f"{esrp.Action(action).api_name} ({action}): ")
            if result.info.collided_with is not None:
                expected = "collided"
                assert f"rejected, collided with {result.info.collided_with.name}" in note.action
            elif not result.info.accepted:
                expected = "no effect"
            else:
                expected = "accepted"
            assert note.outcome == expected, (k, note, result.info)
            outcomes.add(expected)
            grasping = "yes" if result.observation.grasping else "no"
            assert note.state == f"grasping: {grasping}  reward {result.reward:+.3f}  total {total:+.3f}"
    assert {"accepted", "collided"} <= outcomes  # a random walk of 200 steps bumps into things
    # The panels' labels: text (dark pixels) in the header above each of the three panels.
    assert len(PANEL_TITLES) == 3
    header, side = header_height(2), 256
    frame = replay.frames[5]
    for k in range(3):
        strip = frame[header - header // 4 : header - 2, k * (side + 4) : k * (side + 4) + side]
        assert (strip.max(axis=-1) < 120).sum() > 20, k


def test_a_carried_path_is_outlined_so_it_shows_over_a_blue_object(client: esrp.Client) -> None:
    """The blue path of a carried object vanished where it crossed a blue object: it is drawn
    with a white outline now."""
    from esrp.eval.replay import _Paths, compose_frame, header_height, step_note

    with client.create_episode(split="test", sensors=esrp.Sensors(current_top_down=True)) as episode:
        observation = episode.observation
        assert observation is not None
        goal = episode.goal()
    frame = goal.frame
    assert frame is not None
    # The floor all blue, as under a blue object, and an object carried across it.
    blue = np.empty_like(observation.current_top_down)
    blue[...] = OBJECT_PATH
    observation = dataclasses.replace(observation, current_top_down=blue)
    span = frame.resolution * frame.metres_per_pixel
    paths = _Paths()
    paths.carried[0] = [[(frame.min_x + span * t, frame.min_z + span / 2) for t in (0.2, 0.5, 0.8)]]
    note = step_note("caption", None, None, False, 0.0)
    image = compose_frame(observation, goal.image, frame, paths, scale=2, note=note)
    panel = image[header_height(2) :, 2 * (256 + 4) :]
    row = panel[:, 128]  # a column across the path, in the middle of the panel
    white = np.flatnonzero((row == 255).all(axis=-1))
    assert len(white) >= 2, "no outline"
    assert white.min() < 128 < white.max()  # on both sides of the path
    assert (row[white.min() + 1 : white.max()] == OBJECT_PATH).all(axis=-1).any()  # the path between
