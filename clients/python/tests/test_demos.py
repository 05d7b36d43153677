"""`esrp demos export` against the real server: the zarr store holds each episode's observations
and expert actions, which replay to success; an interrupted export resumes; a store of another
resolution is refused. With `--records`, recorded episodes (people's, from the web viewer) are
replayed and stored, filtered by agent and success, and a record the replay does not reproduce
stops the export."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_same_stores
from demo_records import export, played, write_records

import esrp
from esrp.agents import RandomAgent
from esrp.cli import main
from esrp.eval.results import EpisodeRecord, scene_seed

zarr = pytest.importorskip("zarr", reason="esrp[train] is not installed")

__all__ = ["played"]  # the records fixture of demo_records, used here


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
    server: esrp.LocalServer, easy_scenes: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "demos.zarr"
    scenes = ",".join(easy_scenes[:3])
    assert export(server, out, "--split", "test", "--scenes", ",".join(easy_scenes[:1])) == 0
    # A torn episode: steps written after the last whole one, no episode end.
    store = zarr.open_group(str(out), mode="a")
    store["data/ego_rgb"].append(np.zeros((5, 128, 128, 3), np.uint8), axis=0)
    store["data/action"].append(np.zeros(5, np.uint8), axis=0)
    capsys.readouterr()
    assert export(server, out, "--split", "test", "--scenes", scenes) == 0
    # The one whole episode kept, the two others added (an expert export counted none before).
    assert f"{out}: 3 episodes" in (said := capsys.readouterr().out)
    assert "(2 added now)" in said
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


def test_a_resolution_the_server_cannot_render_is_refused_before_anything_is_written(
    server: esrp.LocalServer, easy_scenes: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "demos.zarr"
    for resolution in ("-5", "7", "4096"):
        flags = ["--split", "test", "--scenes", easy_scenes[0], "--resolution", resolution]
        assert export(server, out, *flags) == 2
        err = capsys.readouterr().err
        assert f"--resolution {resolution} is out of range: use 16 to 512 pixels" in err, err
        assert len(err.strip().splitlines()) == 1, err
        assert not out.exists()
    # The corrected command runs.
    assert export(server, out, "--split", "test", "--scenes", easy_scenes[0], "--resolution", "64") == 0
    assert zarr.open_group(str(out), mode="r").attrs["resolution"] == 64


def test_a_store_that_holds_no_episode_takes_the_new_settings(
    server: esrp.LocalServer, easy_scenes: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "demos.zarr"
    # A run stopped before its first episode left its settings and no episode.
    empty = zarr.open_group(str(out), mode="a")
    stamp = {"format": "esrp.demos/v1", "dataset": "esrp-bench-v2", "resolution": 32, "labels": "expert"}
    empty.attrs.update(stamp)
    empty.create_array("meta/episode_ends", shape=(0,), dtype="int64")
    assert export(server, out, "--split", "test", "--scenes", easy_scenes[0]) == 0
    store = zarr.open_group(str(out), mode="r")
    assert (store.attrs["resolution"], store.attrs["scene_ids"]) == (128, [easy_scenes[0]])
    assert store["data/ego_rgb"].shape[1:] == (128, 128, 3)


def test_a_folder_of_other_files_and_a_store_of_another_split_are_refused(
    server: esrp.LocalServer,
    client: esrp.Client,
    easy_scenes: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    folder = tmp_path / "datasets"
    folder.mkdir()
    (folder / "readme.txt").write_text("mine")
    assert export(server, folder, "--split", "test", "--scenes", easy_scenes[0]) == 2
    assert "is a folder of other files, not an esrp.demos/v1 store" in capsys.readouterr().err
    assert sorted(p.name for p in folder.iterdir()) == ["readme.txt"]
    # A store of test scenes takes no train scenes (nor the other way round).
    out = tmp_path / "test.zarr"
    assert export(server, out, "--split", "test", "--scenes", easy_scenes[0]) == 0
    train = next(iter(client.scenes("train"))).id
    assert export(server, out, "--split", "train", "--scenes", train) == 2
    assert "holds scenes of the test split, not train" in capsys.readouterr().err
    assert zarr.open_group(str(out), mode="r").attrs["scene_ids"] == [easy_scenes[0]]


def test_scenes_named_twice_or_not_at_all_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = str(tmp_path / "never.zarr")
    cases = (("a,b,a", "lists a more than once"), ("", "names no scene"), (" , ", "names no scene"))
    for scenes, said in cases:
        with pytest.raises(SystemExit) as exited:
            main(["demos", "export", "--out", out, "--scenes", scenes])
        assert exited.value.code == 2
        assert said in capsys.readouterr().err


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


def test_a_dagger_agent_config_the_agent_does_not_take_is_refused(
    server: esrp.LocalServer, easy_scenes: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "dagger.zarr"
    arguments = ["--split", "test", "--scenes", easy_scenes[0], "--dagger", "random"]
    assert export(server, out, *arguments, "--agent-config", '{"bogus": 1}') == 2
    assert "the random agent has no setting bogus: it takes none" in capsys.readouterr().err
    assert not out.exists()


def test_dagger_records_the_policys_own_actions_and_stops_at_max_steps(
    server: esrp.LocalServer,
    easy_scenes: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "capped.zarr"
    scenes = ["--split", "test", "--scenes", ",".join(easy_scenes[:2])]
    assert export(server, out, *scenes, "--max-steps", "4") == 2
    assert "--max-steps only apply with --dagger" in capsys.readouterr().err
    assert export(server, out, *scenes, "--label-horizon", "4") == 2
    assert "--label-horizon only apply with --dagger" in capsys.readouterr().err
    assert export(server, out, *scenes, "--dagger", "random", "--seed", "3", "--max-steps", "4") == 0
    printed = capsys.readouterr().out
    store = zarr.open_group(str(out), mode="r")
    assert list(store["meta/episode_ends"][:]) == [4, 8]
    labels, policy = store["data/action"][:], store["data/policy_action"][:]
    # The random agent, seeded as the export seeds it, chose the recorded actions.
    for episode, scene in enumerate(easy_scenes[:2]):
        agent = RandomAgent()
        agent.reset(None, {"seed": scene_seed(3, scene)})  # type: ignore[arg-type]
        assert [int(agent.act(None)) for _ in range(4)] == list(policy[4 * episode : 4 * episode + 4])  # type: ignore[arg-type]
    agreed = int((labels == policy).sum())
    assert f"the policy's action was the planner's label at {agreed} of 8 states" in printed

    # A DAgger store made before the policy's actions were recorded goes on without them.
    group = zarr.open_group(str(out), mode="a")
    del group["data/policy_action"]
    more = ["--split", "test", "--scenes", ",".join(easy_scenes[:3]), "--dagger", "random", "--seed", "3"]
    assert export(server, out, *more, "--max-steps", "4") == 0
    assert "planner's label" not in capsys.readouterr().out
    store = zarr.open_group(str(out), mode="r")
    assert list(store["meta/episode_ends"][:]) == [4, 8, 12]
    assert "data/policy_action" not in store


def padded(plan: list[int], horizon: int) -> list[int]:
    """A plan's first `horizon` actions as a store's label chunk holds them (255 past its end)."""
    return plan[:horizon] + [255] * max(horizon - len(plan), 0)


def test_dagger_with_beta_one_follows_the_plan(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "beta1.zarr"
    scene = easy_scenes[1]
    arguments = ["--split", "test", "--scenes", scene, "--dagger", "random", "--beta", "1"]
    assert export(server, out, *arguments) == 0
    store = zarr.open_group(str(out), mode="r")
    labels, chunks = store["data/action"][:], store["data/label_chunk"][:]
    with client.create_episode(scene, privileged=True) as episode:
        plan = episode.plan_actions()
    assert plan.reaches_success
    planned = [int(a) for a in plan.actions]
    assert [int(a) for a in labels] == planned
    # Each state's chunk is the rest of that plan: its next 8 actions, NO_ACTION past its end.
    assert chunks.shape == (len(planned), 8)
    for t, chunk in enumerate(chunks):
        assert chunk.tolist() == padded(planned[t:], 8)


def test_dagger_labels_each_state_with_the_plan_from_that_state(
    server: esrp.LocalServer, client: esrp.Client, easy_scenes: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "chunks.zarr"
    scene = easy_scenes[1]
    arguments = ["--split", "test", "--scenes", scene, "--dagger", "random", "--max-steps", "12"]
    assert export(server, out, *arguments, "--label-horizon", "5") == 0
    store = zarr.open_group(str(out), mode="r")
    stepped, chunks = store["data/policy_action"][:], store["data/label_chunk"][:]
    assert chunks.shape == (12, 5)
    assert np.array_equal(chunks[:, 0], store["data/action"][:])
    # Replayed to each state (beta 0: the random agent's actions were stepped), the planner's
    # first five actions from there are that state's chunk.
    for t in (0, 4, 11):
        with client.create_episode(scene, privileged=True) as episode:
            for action in stepped[:t]:
                episode.step(int(action))
            plan = [int(a) for a in episode.plan_actions(max_actions=5).actions]
        assert chunks[t].tolist() == padded(plan, 5), t
    # A store of other chunks does not take more episodes.
    assert export(server, out, *arguments, "--label-horizon", "8") == 2


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
    ego = batch["frames"][batch["frame_index"]].numpy()
    assert np.array_equal(ego[1, 0], stores[1]["data/ego_rgb"][0])
    assert np.array_equal(ego[2, 1], stores[1]["data/ego_rgb"][1])
    assert np.array_equal(ego[0, 1], stores[0]["data/ego_rgb"][0])
    assert np.array_equal(batch["goals"][batch["goal_index"]][1].numpy(), stores[1]["meta/goal_rgb"][0])
    # A DAgger state learns the plan from it, not the labels of the states the agent went on to.
    chunk = [int(a) for a in stores[1]["data/label_chunk"][0][:3]]
    labelled = batch["mask"][1].tolist()
    assert [a for a, known in zip(batch["actions"][1].tolist(), labelled, strict=True) if known] == [
        a for a in chunk if a != 255
    ]
    assert labelled == [a != 255 for a in chunk]


# --- Recorded episodes: `esrp demos export --records`.


def test_records_export_holds_each_records_steps_and_trains(
    server: esrp.LocalServer,
    client: esrp.Client,
    played: list[EpisodeRecord],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    records = write_records(tmp_path / "records.jsonl", played)
    out = tmp_path / "records.zarr"
    assert export(server, out, "--records", str(records), "--limit", "1") == 0
    assert export(server, out, "--records", str(records)) == 0  # resumed: the other two added
    store = zarr.open_group(str(out), mode="r")
    assert store.attrs["format"] == "esrp.demos/v1"
    assert store.attrs["labels"] == "records"
    assert "policy" not in store.attrs
    assert store.attrs["scene_ids"] == [r.scene_id for r in played]
    assert store.attrs["agents"] == ["human", "human", "random"]
    ends = store["meta/episode_ends"][:]
    assert ends.tolist() == np.cumsum([len(r.actions) for r in played]).tolist()
    assert store["data/action"][:].tolist() == [a for r in played for a in r.actions]
    assert store["data/ego_rgb"].shape == (ends[-1], 128, 128, 3)
    assert store["data/grasping"].shape == (ends[-1],)
    assert store["meta/goal_rgb"].shape == (3, 128, 128, 3)
    # What the agent saw before each action: the second record's views, stepped afresh.
    ego, grasping = store["data/ego_rgb"], store["data/grasping"][:]
    with client.create_episode(played[1].scene_id, horizon=12) as episode:
        observation = episode.observation
        assert observation is not None
        assert observation.goal_rgb is not None
        assert np.array_equal(store["meta/goal_rgb"][1], observation.goal_rgb)
        for t in range(int(ends[0]), int(ends[1])):
            assert np.array_equal(ego[t], observation.ego_rgb)
            assert bool(grasping[t]) == observation.grasping
            observation = episode.step(int(store["data/action"][t])).observation
    # Other records, or the expert's demonstrations, do not go on with this store.
    others = write_records(tmp_path / "others.jsonl", played[1:])
    assert export(server, out, "--records", str(others)) == 2
    assert "holds other episodes than the first 3 of these records" in capsys.readouterr().err
    assert export(server, out, "--split", "test", "--scenes", played[0].scene_id) == 2
    assert "holds recorded episodes (--records), not expert demonstrations" in capsys.readouterr().err
    assert zarr.open_group(str(out), mode="r")["meta/episode_ends"][:].tolist() == ends.tolist()
    pytest.importorskip("torch", reason="esrp[train] is not installed")
    from esrp.train.bc import DemoWindows

    windows = DemoWindows([str(out)], n_obs=2, horizon=3)
    assert len(windows) == ends[-1]
    assert windows.batch(np.array([0, int(ends[0])]))["actions"][1].tolist() == played[1].actions[:3]
    assert windows.batch(np.array([0, int(ends[0])]))["mask"][1].all()


def test_records_export_filters_by_agent_and_success(
    server: esrp.LocalServer, played: list[EpisodeRecord], tmp_path: Path
) -> None:
    records = write_records(tmp_path / "records.jsonl", played)
    humans = tmp_path / "humans.zarr"
    assert export(server, humans, "--records", str(records), "--agent", "human") == 0
    store = zarr.open_group(str(humans), mode="r")
    assert store.attrs["agents"] == ["human", "human"]
    assert store["data/action"][:].tolist() == played[0].actions + played[1].actions
    wins = tmp_path / "wins.zarr"
    assert export(server, wins, "--records", str(records), "--agent", "human", "--successful-only") == 0
    store = zarr.open_group(str(wins), mode="r")
    assert (store.attrs["scene_ids"], store.attrs["agents"]) == ([played[0].scene_id], ["human"])
    assert store["meta/episode_ends"][:].tolist() == [len(played[0].actions)]
    assert store["data/action"][:].tolist() == played[0].actions


def test_a_record_the_replay_does_not_reproduce_stops_the_export(
    server: esrp.LocalServer,
    played: list[EpisodeRecord],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    tampered = dataclasses.replace(played[0], actions=list(played[0].actions))
    k = len(tampered.actions) // 2
    tampered.actions[k] = (tampered.actions[k] + 1) % 4  # another move or turn
    records = write_records(tmp_path / "tampered.jsonl", [played[1], tampered])
    out = tmp_path / "tampered.zarr"
    assert export(server, out, "--records", str(records)) == 2
    err = capsys.readouterr().err
    assert f"{records}:2: {played[0].scene_id}: the replay does not reproduce the record" in err
    store = zarr.open_group(str(out), mode="r")
    assert store.attrs["scene_ids"] == [played[1].scene_id]  # the good record only
    assert store["meta/episode_ends"][:].tolist() == [len(played[1].actions)]
    # A record of another dataset is refused before anything is replayed.
    other = write_records(tmp_path / "other.jsonl", [dataclasses.replace(played[1], dataset="other-bench")])
    assert export(server, tmp_path / "other.zarr", "--records", str(other)) == 2
    assert (
        f"{other}:1: {played[1].scene_id}: the record is of dataset 'other-bench'" in capsys.readouterr().err
    )


def test_records_export_refuses_bad_input_in_one_line(
    played: list[EpisodeRecord], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    records = write_records(tmp_path / "records.jsonl", played)
    out = str(tmp_path / "never.zarr")

    def refused(*arguments: str) -> str:
        # No server: these fail before one is needed.
        assert main(["demos", "export", "--out", out, "--no-progress", *arguments]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1, err
        return err

    for flags in (["--split", "test"], ["--scenes", "x"], ["--difficulty", "easy"], ["--dagger", "random"]):
        assert f"--records does not go with {flags[0]}" in refused("--records", str(records), *flags)
    assert "--agent only apply with --records" in refused("--agent", "human")
    assert "--successful-only only apply with --records" in refused("--successful-only")
    assert "hold 3 records, none (agent 'nobody', with actions)" in refused(
        "--records", str(records), "--agent", "nobody"
    )
    assert "none (agent 'random', successful, with actions)" in refused(
        "--records", str(records), "--agent", "random", "--successful-only"
    )
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"schema": "esrp.results/v2"}\n' + played[0].to_json() + "\n")
    assert f"{bad}:1: not an esrp.results/v1 record" in refused("--records", str(bad))
    # A whole last line that is not a record is no interrupted write: refused, not left out.
    last = tmp_path / "last.jsonl"
    last.write_text(played[0].to_json() + '\n{"bad": 1}\n')
    assert f"{last}:2: its last line is not an esrp.results/v1 record" in refused("--records", str(last))
    assert f"cannot read {tmp_path / 'missing.jsonl'}" in refused(
        "--records", str(tmp_path / "missing.jsonl")
    )


def test_dagger_skips_a_scene_without_a_plan_from_its_start_and_a_later_run_takes_it(
    server: esrp.LocalServer,
    easy_scenes: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "skipped.zarr"
    scenes = ["--split", "test", "--scenes", ",".join(easy_scenes[:2]), "--dagger", "random"]
    # 1 ms is too little to plan from a start away from the objects: no state gets a label.
    assert export(server, out, *scenes, "--max-steps", "4", "--plan-budget-ms", "1") == 0
    captured = capsys.readouterr()
    for scene in easy_scenes[:2]:
        assert f"{scene}: the planner found no plan from its start: skipped" in captured.err
    assert "0 episodes, 0 steps (0 added now)" in captured.out
    assert "2 scenes skipped" in captured.out
    # The skipped scenes are not marked done: a run with time to plan takes them.
    assert export(server, out, *scenes, "--max-steps", "4") == 0
    assert "scenes skipped" not in capsys.readouterr().out
    store = zarr.open_group(str(out), mode="r")
    assert store.attrs["scene_ids"] == easy_scenes[:2]
    assert list(store["meta/episode_ends"][:]) == [4, 8]


def test_episodes_in_flight_write_the_store_of_one_episode_at_a_time(
    server: esrp.LocalServer, easy_scenes: list[str], tmp_path: Path
) -> None:
    scenes = ["--split", "test", "--scenes", ",".join(easy_scenes[:4]), "--resolution", "32"]
    dagger = [*scenes, "--dagger", "random", "--seed", "7", "--beta", "0.5", "--max-steps", "12"]
    assert export(server, tmp_path / "dagger-1.zarr", *dagger) == 0
    assert export(server, tmp_path / "dagger-3.zarr", *dagger, "--episodes-in-flight", "3") == 0
    assert_same_stores(tmp_path / "dagger-1.zarr", tmp_path / "dagger-3.zarr")
    store = zarr.open_group(str(tmp_path / "dagger-3.zarr"), mode="r")
    assert store.attrs["scene_ids"] == easy_scenes[:4], "written in the scenes' order"
    # The expert's demonstrations too.
    assert export(server, tmp_path / "expert-1.zarr", *scenes) == 0
    assert export(server, tmp_path / "expert-2.zarr", *scenes, "--episodes-in-flight", "2") == 0
    assert_same_stores(tmp_path / "expert-1.zarr", tmp_path / "expert-2.zarr")


def test_episodes_in_flight_do_not_apply_to_records_or_minari(
    server: esrp.LocalServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    records = tmp_path / "none.jsonl"
    records.write_text("")
    assert export(server, tmp_path / "r.zarr", "--records", str(records), "--episodes-in-flight", "2") == 2
    assert "--episodes-in-flight applies to scene exports to zarr" in capsys.readouterr().err
    assert export(server, tmp_path / "m", "--format", "minari", "--episodes-in-flight", "2") == 2
    assert "--episodes-in-flight applies to scene exports to zarr" in capsys.readouterr().err


def test_in_order_plays_items_at_a_time_and_yields_them_in_order() -> None:
    import threading
    import time

    from esrp.train.demos import _in_order

    running, most = 0, 0
    lock = threading.Lock()
    first_three = threading.Barrier(3, timeout=30)  # broken unless three play at once

    def play(item: int) -> int:
        nonlocal running, most
        with lock:
            running += 1
            most = max(most, running)
        if item < 3:
            first_three.wait()
        time.sleep(0.01 * (5 - item))  # the earlier items end last
        with lock:
            running -= 1
        if item == 4:
            raise ValueError("item 4")
        return item * 10

    played = _in_order(play, range(6), 3)
    assert [next(played) for _ in range(4)] == [(0, 0), (1, 10), (2, 20), (3, 30)]
    with pytest.raises(ValueError, match="item 4"):
        next(played)
    assert most == 3, "three at a time, never more"
    assert list(_in_order(lambda item: item + 1, [5, 6], 1)) == [(5, 6), (6, 7)]


def test_without_zarr_the_export_says_what_to_install(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "zarr", None)  # `import zarr` raises ImportError
    assert main(["demos", "export", "--out", str(tmp_path / "demos.zarr"), "--limit", "1"]) == 2
    err = capsys.readouterr().err
    assert "pip install 'esrp[train]'" in err, err
    assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "demos.zarr").exists()
