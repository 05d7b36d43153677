"""`esrp demos export` against the real server: the zarr store holds each episode's observations
and expert actions, which replay to success; an interrupted export resumes; a store of another
resolution is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import esrp
from esrp.cli import main

zarr = pytest.importorskip("zarr", reason="esrp[train] is not installed")


def export(server: esrp.LocalServer, out: Path, *more: str) -> int:
    return main(["demos", "export", "--server", server.address, "--out", str(out), "--no-progress", *more])


def test_the_store_holds_episodes_that_replay_to_success(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "demos.zarr"
    scenes = easy_scenes[:2]
    assert export(server, out, "--split", "test", "--scenes", ",".join(scenes)) == 0
    store = zarr.open_group(str(out), mode="r")
    assert store.attrs["format"] == "esrp.demos/v1"
    assert store.attrs["scene_ids"] == scenes
    ends = store["meta/episode_ends"][:]
    ego, grasping, action = store["data/ego_rgb"], store["data/grasping"][:], store["data/action"][:]
    assert ego.shape == (ends[-1], 128, 128, 3)
    assert ego.dtype == np.uint8
    assert grasping.shape == action.shape == (ends[-1],)
    assert store["meta/goal_rgb"].shape == (2, 128, 128, 3)
    start = 0
    for i, scene in enumerate(scenes):
        with client.create_episode(scene) as episode:
            first = episode.observation
            assert first is not None
            assert first.goal_rgb is not None
            assert np.array_equal(store["meta/goal_rgb"][i], first.goal_rgb)
            assert np.array_equal(ego[start], first.ego_rgb), "step 0 holds the first observation"
            for t in range(start, int(ends[i])):
                result = episode.step(int(action[t]))
                if t + 1 < ends[i]:
                    assert np.array_equal(ego[t + 1], result.observation.ego_rgb)
                    assert bool(grasping[t + 1]) == result.observation.grasping
            assert result.terminated, f"{scene}: the recorded actions do not succeed"
        start = int(ends[i])


def test_an_interrupted_export_resumes(
    server: esrp.LocalServer, easy_scenes: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "demos.zarr"
    scenes = ",".join(easy_scenes[:3])
    assert export(server, out, "--split", "test", "--scenes", ",".join(easy_scenes[:1])) == 0
    # A torn episode: steps written after the last whole one, no episode end.
    store = zarr.open_group(str(out), mode="a")
    store["data/ego_rgb"].append(np.zeros((5, 128, 128, 3), np.uint8), axis=0)
    store["data/action"].append(np.zeros(5, np.uint8), axis=0)
    assert export(server, out, "--split", "test", "--scenes", scenes) == 0
    fresh = tmp_path / "fresh.zarr"
    assert export(server, fresh, "--split", "test", "--scenes", scenes) == 0
    a, b = zarr.open_group(str(out), mode="r"), zarr.open_group(str(fresh), mode="r")
    assert a.attrs["scene_ids"] == b.attrs["scene_ids"] == easy_scenes[:3]
    for name in ("data/ego_rgb", "data/grasping", "data/action", "meta/goal_rgb", "meta/episode_ends"):
        assert np.array_equal(a[name][:], b[name][:]), name


def test_a_store_of_another_resolution_is_refused(
    server: esrp.LocalServer, easy_scenes: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "demos.zarr"
    assert export(server, out, "--split", "test", "--scenes", easy_scenes[0], "--resolution", "64") == 0
    assert export(server, out, "--split", "test", "--scenes", easy_scenes[0]) == 2
    assert "at 64 px, not esrp-bench-v1 at 128 px" in capsys.readouterr().err
