"""`esrp demos export` against the real server: the zarr store holds each episode's observations
and expert actions, which replay to success; an interrupted export resumes; a store of another
resolution is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import esrp
from esrp.agents import RandomAgent
from esrp.cli import main
from esrp.eval.results import scene_seed

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
    assert "at 64 px, not esrp-bench-v2 at 128 px" in capsys.readouterr().err


def test_dagger_records_the_planners_label_at_each_state_the_agent_visits(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "dagger.zarr"
    scene = easy_scenes[0]
    assert export(server, out, "--split", "test", "--scenes", scene, "--dagger", "random", "--seed", "5") == 0
    store = zarr.open_group(str(out), mode="r")
    assert (store.attrs["labels"], store.attrs["policy"]) == ("planner", "random")
    (end,) = store["meta/episode_ends"][:]
    ego, grasping, labels = store["data/ego_rgb"], store["data/grasping"][:], store["data/action"][:]
    assert end == len(labels) > 0
    # The same agent, seeded the same way, visits the same states: there the planner (asked afresh)
    # gives the recorded labels, and the views are the recorded ones.
    agent = RandomAgent()
    with client.create_episode(scene, privileged=True) as episode:
        observation = episode.observation
        assert observation is not None
        agent.reset(observation, {"seed": scene_seed(5, scene)})
        for t in range(int(end)):
            assert np.array_equal(ego[t], observation.ego_rgb)
            assert bool(grasping[t]) == observation.grasping
            assert episode.plan_actions(max_actions=1).actions[0] == labels[t]
            result = episode.step(agent.act(observation))
            if result.terminated or result.truncated:
                assert t == end - 1
                break
            observation = result.observation
    assert not (labels == labels[0]).all(), "labels follow the states, not one constant"


def test_dagger_with_beta_one_follows_the_plan(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "beta1.zarr"
    scene = easy_scenes[1]
    arguments = ["--split", "test", "--scenes", scene, "--dagger", "random", "--beta", "1"]
    assert export(server, out, *arguments) == 0
    labels = zarr.open_group(str(out), mode="r")["data/action"][:]
    with client.create_episode(scene, privileged=True) as episode:
        plan = episode.plan_actions()
    assert plan.reaches_success
    assert [int(a) for a in labels] == [int(a) for a in plan.actions]


def test_dagger_and_expert_stores_are_kept_apart_and_train_together(
    server: esrp.LocalServer, easy_scenes: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    expert, dagger = tmp_path / "expert.zarr", tmp_path / "dagger.zarr"
    scenes = ["--split", "test", "--scenes", easy_scenes[2]]
    assert export(server, expert, *scenes) == 0
    assert export(server, expert, *scenes, "--dagger", "random") == 2
    assert "holds expert demonstrations, not planner labels on states of random" in capsys.readouterr().err
    assert export(server, dagger, *scenes, "--beta", "0.5") == 2
    assert "--beta only apply with --dagger" in capsys.readouterr().err
    assert export(server, dagger, *scenes, "--dagger", "expert") == 2
    assert export(server, dagger, *scenes, "--dagger", "random", "--beta", "0.5") == 0
    pytest.importorskip("torch", reason="esrp[train] is not installed")
    from esrp.train.bc import DemoWindows

    windows = DemoWindows([str(expert), str(dagger)], n_obs=2, horizon=3)
    stores = [zarr.open_group(str(p), mode="r") for p in (expert, dagger)]
    first = int(stores[0]["meta/episode_ends"][0])
    assert len(windows) == first + int(stores[1]["meta/episode_ends"][0])
    batch = windows.batch(np.array([0, first, first + 1]))
    # Step `first` is the DAgger store's first: its window repeats its own first view, its goal and
    # labels are that store's.
    assert np.array_equal(batch["ego"][1, 0].numpy(), stores[1]["data/ego_rgb"][0])
    assert np.array_equal(batch["ego"][2, 1].numpy(), stores[1]["data/ego_rgb"][1])
    assert np.array_equal(batch["ego"][0, 1].numpy(), stores[0]["data/ego_rgb"][0])
    assert np.array_equal(batch["goal"][1].numpy(), stores[1]["meta/goal_rgb"][0])
    assert batch["actions"][1].tolist() == [int(a) for a in stores[1]["data/action"][:3]]
