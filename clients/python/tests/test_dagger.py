"""`esrp train bc`'s held-out evaluation, its in-memory windows and `esrp train bc --dagger` against
the real server, on tiny data (32-pixel views of a few easy train scenes, a tiny model, an epoch or
two): evaluations write their rows and change nothing trained, in-memory batches are the zarr
batches, a DAgger run writes its stores, logs and checkpoints, and resumes after more iterations
are asked and after interruptions in an export and in a training; bad configs are refused."""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import assert_same_stores, assert_stopped_for_a_lost_server

import esrp
from esrp.cli import main
from esrp.eval.results import read_records

torch = pytest.importorskip("torch", reason="esrp[train] is not installed")
pytest.importorskip("diffusers", reason="esrp[train] is not installed")
zarr = pytest.importorskip("zarr", reason="esrp[train] is not installed")

from esrp.agents.bc import BcConfig  # noqa: E402
from esrp.train import bc as bc_module  # noqa: E402
from esrp.train import demos as demos_module  # noqa: E402
from esrp.train._training import save_checkpoint  # noqa: E402
from esrp.train.bc import DemoWindows, load_config, train  # noqa: E402
from esrp.train.dagger import DaggerConfig, load_dagger_config, run_dagger  # noqa: E402
from esrp.train.heldout import TrainServer, evaluate_checkpoint  # noqa: E402

RESOLUTION = 32


@pytest.fixture(scope="module")
def train_easy(client: esrp.Client) -> list[str]:
    """The first easy train scenes: [0] is held out, [1] and [2] hold the expert demonstrations,
    [1:4] are the DAgger candidates (quick to plan)."""
    return [scene.id for scene in client.scenes("train", "easy", page_size=4)][:4]


@pytest.fixture(scope="module")
def expert(server: esrp.LocalServer, train_easy: list[str], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The expert demonstrations of two easy train scenes, at 32 pixels."""
    out = tmp_path_factory.mktemp("expert") / "expert.zarr"
    arguments = ["demos", "export", "--server", server.address, "--split", "train"]
    arguments += ["--scenes", ",".join(train_easy[1:3]), "--resolution", str(RESOLUTION)]
    assert main([*arguments, "--out", str(out), "--no-progress"]) == 0
    return out


@pytest.fixture
def train_server(server: esrp.LocalServer) -> Iterator[TrainServer]:
    with TrainServer(server.address) as running:
        yield running


def bc_table(expert: Path, **more: object) -> dict[str, object]:
    """A tiny `[bc]` table (4 denoising steps: quick episodes); the held-out scene is the first easy
    train scene."""
    values: dict[str, object] = {
        "demos": str(expert),
        "resolution": RESOLUTION,
        "feature_dim": 32,
        "grasp_dim": 8,
        "cond_dim": 32,
        "unet_channels": [16, 32],
        "ddim_steps": 4,
        "batch_size": 64,
        "epochs": 1,
        "lr": 1e-3,
        "threads": 1,
        "checkpoint_every": 1,
        "eval_split": "train",
        "eval_difficulty": "easy",
        "eval_limit": 1,
    }
    values.update(more)
    return values


def dagger_table(train_easy: list[str], **more: object) -> dict[str, object]:
    """A tiny `[dagger]` table: 2 of the candidate scenes per iteration, 8 states each."""
    values: dict[str, object] = {
        "iterations": 1,
        "epochs_per_iteration": 1,
        "scenes_per_iteration": 2,
        "difficulty": "easy",
        "scenes": train_easy,  # the held-out one among them is left out
        "beta": 0.5,
        "max_steps": 8,
    }
    values.update(more)
    return values


def write_toml(path: Path, tables: dict[str, dict[str, object]]) -> Path:
    """`tables` as a TOML file (JSON's strings, numbers, booleans and lists are TOML's)."""
    lines = []
    for name, table in tables.items():
        lines.append(f"[{name}]")
        lines += [f"{key} = {json.dumps(value)}" for key, value in table.items()]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as file:
        return list(csv.DictReader(file))


def train_cli(server: esrp.LocalServer, config: Path, out: Path, *more: str) -> int:
    arguments = ["train", "bc", "--config", str(config), "--out", str(out), "--server", server.address]
    return main([*arguments, "--no-progress", *more])


# --- Held-out evaluation and in-memory windows.


def test_held_out_evaluations_write_rows_and_change_nothing_trained(
    expert: Path, train_easy: list[str], tmp_path: Path, train_server: TrainServer
) -> None:
    config = BcConfig.from_mapping(bc_table(expert, epochs=2, eval_every=1))
    run = tmp_path / "run"
    checkpoint = train(config, run, progress=False, server=train_server)
    evaluations = rows(run / "eval.csv")
    assert [(r["epoch"], r["steps"], r["episodes"], r["failed"]) for r in evaluations] == [
        ("1", "2", "1", "0"),
        ("2", "4", "1", "0"),
    ]
    for row in evaluations:
        assert 0.0 <= float(row["sr"]) <= float(row["osr"]) <= 1.0
        assert float(row["rdr"]) >= 0.0
    (record,) = read_records(run / "eval" / "epoch-0002.jsonl").records
    assert (record.agent, record.scene_id, record.split) == ("bc", train_easy[0], "train")
    assert record.agent_config == {"checkpoint": str(checkpoint), "epsilon": 0.1, "threads": 1, "batch": 8}
    assert float(evaluations[1]["rdr"]) == pytest.approx(record.rdr, abs=1e-6)
    assert not list((run / "eval").glob("*.pt")), "evaluated checkpoints are kept when asked only"
    # The best held-out checkpoint is kept (the earliest of equals).
    top = max(evaluations, key=lambda row: (float(row["sr"]), -int(row["epoch"])))
    best = json.loads((run / "best.json").read_text())
    assert best["epoch"] == int(top["epoch"])
    assert torch.load(run / "best.pt", weights_only=False)["epoch"] == best["epoch"]
    # The same run without evaluations trains the same weights.
    plain = train(BcConfig.from_mapping(bc_table(expert, epochs=2)), tmp_path / "plain", progress=False)
    trained, untouched = (torch.load(path, weights_only=False)["model"] for path in (checkpoint, plain))
    assert trained.keys() == untouched.keys()
    assert all(torch.equal(value, untouched[key]) for key, value in trained.items())
    assert not (tmp_path / "plain" / "eval.csv").exists()
    # An evaluation an interruption cut short (its row never written) is made when the run resumes.
    with open(run / "eval.csv", "w", newline="") as file:
        csv.writer(file).writerows([list(evaluations[0]), list(evaluations[0].values())])
    train(config, run, resume=True, progress=False, server=train_server)
    assert [r["epoch"] for r in rows(run / "eval.csv")] == ["1", "2"]


def test_an_interruption_before_best_pt_is_copied_is_repaired_on_resume(
    expert: Path, tmp_path: Path, train_server: TrainServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A signal after an evaluation's row reached eval.csv but before its checkpoint was copied to
    best.pt left the run without best.pt (or with an older one) for good: the resumed run owed no
    evaluation, so nothing copied it again."""
    config = BcConfig.from_mapping(bc_table(expert, epochs=1, eval_every=1))
    run = tmp_path / "run"

    def stop(*_: object) -> None:
        raise Interrupted

    monkeypatch.setattr(bc_module._HeldOut, "keep_best", stop)
    with pytest.raises(Interrupted):
        train(config, run, progress=False, server=train_server)
    monkeypatch.undo()
    assert [r["epoch"] for r in rows(run / "eval.csv")] == ["1"]
    assert not (run / "best.pt").exists()
    train(config, run, resume=True, progress=False, server=train_server)
    assert json.loads((run / "best.json").read_text())["epoch"] == 1
    assert torch.load(run / "best.pt", weights_only=False)["epoch"] == 1


def test_evaluated_checkpoints_are_kept_for_playing_when_asked(
    expert: Path, tmp_path: Path, train_server: TrainServer
) -> None:
    from esrp.agents.bc import load_policy

    config = BcConfig.from_mapping(bc_table(expert, epochs=3, eval_every=2, eval_keep_checkpoints=True))
    run = tmp_path / "run"
    checkpoint = train(config, run, progress=False, server=train_server)
    kept = sorted(path.name for path in (run / "eval").glob("*.pt"))
    assert kept == ["epoch-0002.pt", "epoch-0003.pt"], "every evaluation's checkpoint, the last's too"
    last = torch.load(run / "eval" / "epoch-0003.pt", weights_only=False)
    full = torch.load(checkpoint, weights_only=False)
    assert set(last) == {"kind", "config", "model", "epoch", "steps"}
    assert (last["epoch"], last["steps"]) == (full["epoch"], full["steps"])
    assert all(torch.equal(value, full["model"][key]) for key, value in last["model"].items())
    second = torch.load(run / "eval" / "epoch-0002.pt", weights_only=False)
    assert second["epoch"] == 2
    assert any(not torch.equal(v, last["model"][k]) for k, v in second["model"].items())
    played = load_policy(run / "eval" / "epoch-0002.pt").state_dict()
    assert all(torch.equal(played[k], second["model"][k]) for k in played)


def test_in_memory_batches_are_the_zarr_batches(
    server: esrp.LocalServer, expert: Path, train_easy: list[str], tmp_path: Path
) -> None:
    other = tmp_path / "other.zarr"
    arguments = ["demos", "export", "--server", server.address, "--split", "train", "--scenes", train_easy[3]]
    assert main([*arguments, "--resolution", str(RESOLUTION), "--out", str(other), "--no-progress"]) == 0
    stores = [str(expert), str(other)]
    chunked = DemoWindows(stores, n_obs=4, horizon=8)
    held = DemoWindows(stores, n_obs=4, horizon=8, in_memory=True)
    assert not chunked.memory
    assert held.memory["data/ego_rgb"].shape == (len(held), RESOLUTION, RESOLUTION, 3)
    for seed in range(3):
        steps = np.sort(np.random.default_rng(seed).choice(len(chunked), size=40, replace=False))
        a, b = chunked.batch(steps), held.batch(steps)
        assert a.keys() == b.keys()
        for key in a:
            assert a[key].dtype == b[key].dtype
            assert torch.equal(a[key], b[key]), key
    # Every step of both stores, the last episode's goal included.
    everything = np.arange(len(chunked))
    assert all(torch.equal(v, held.batch(everything)[k]) for k, v in chunked.batch(everything).items())


def test_bad_evaluation_settings_are_refused(expert: Path) -> None:
    for values, message in (
        ({"eval_split": "validation"}, "eval_split 'validation'"),
        ({"eval_scenes": ["x"], "eval_limit": 2}, "no eval_limit or eval_offset"),
        ({"eval_every": -1}, "eval_every, eval_offset and eval_threads must be 0 or more"),
        ({"eval_epsilon": 2.0}, "eval_epsilon must be between 0 and 1"),
        ({"in_memory": "yes"}, "in_memory must be true or false"),
        ({"eval_limit": 0}, "eval_limit must be at least 1"),
    ):
        with pytest.raises(ValueError, match=message):
            BcConfig.from_mapping(bc_table(expert, **values))


def test_a_held_out_scene_not_in_the_split_is_named(
    expert: Path, tmp_path: Path, train_server: TrainServer, easy_scenes: list[str]
) -> None:
    config = BcConfig.from_mapping(
        bc_table(expert, eval_limit=None, eval_scenes=[easy_scenes[0]], eval_every=1)
    )
    with pytest.raises(ValueError, match="eval_scenes: scene .* is a test easy scene"):
        train(config, tmp_path / "run", progress=False, server=train_server)


def test_a_dead_server_is_said_at_once_in_one_line_and_leaves_no_folder(
    server: esrp.LocalServer,
    expert: Path,
    train_easy: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`esrp train bc --server 127.0.0.1:1` (nothing listening there) read the demonstrations,
    made the run folder, and then said gRPC's `UNAVAILABLE: failed to connect to all addresses;
    ...`: now it is said first, in one line naming the address as `esrp eval` does, exit status 2.
    Likewise other checks the server makes (a held-out scene it does not serve), and DAgger's
    settings its first training would refuse: no run folder is left behind."""
    plain = write_toml(tmp_path / "plain.toml", {"bc": bc_table(expert, eval_every=1)})
    dagger = {"bc": bc_table(expert), "dagger": dagger_table(train_easy)}
    both = write_toml(tmp_path / "dagger.toml", dagger)
    run = tmp_path / "runs" / "run"
    for config, more in ((plain, []), (both, ["--dagger"])):
        arguments = ["train", "bc", "--config", str(config), "--out", str(run), "--server", "127.0.0.1:1"]
        assert main([*arguments, "--no-progress", *more]) == 2
        err = capsys.readouterr().err
        assert err.startswith("esrp train bc: no esrp-server answers at 127.0.0.1:1: "), err
        assert "Connection refused" in err, err
        assert err.count("\n") == 1, err
        assert not (tmp_path / "runs").exists()
    unknown = {"bc": bc_table(expert, eval_scenes=["esrp-bench-v2/99999"], eval_every=1)}
    del unknown["bc"]["eval_limit"]
    other_size = {"bc": bc_table(expert, resolution=64), "dagger": dagger_table(train_easy)}
    for tables, more, said in (
        (unknown, [], "eval_scenes: scene 'esrp-bench-v2/99999' is not in the served dataset"),
        (other_size, ["--dagger"], "the demonstrations hold 32 px views and the config says resolution = 64"),
    ):
        config = write_toml(tmp_path / "refused.toml", tables)
        assert train_cli(server, config, run, *more) == 2
        assert said in capsys.readouterr().err
        assert not (tmp_path / "runs").exists()


def test_a_server_gone_during_the_run_stops_it_in_one_line(
    expert: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The run's server stops answering at its first held-out evaluation: one line naming the
    address and how to go on, exit status 3 (as `esrp eval` for a server gone during its run), the
    checkpoint kept."""
    config = write_toml(tmp_path / "bc.toml", {"bc": bc_table(expert, eval_every=1)})
    run = tmp_path / "run"
    with esrp.LocalServer() as own:
        address = own.address

        def stop_then_evaluate(server: TrainServer, *args: Any, **kwargs: Any) -> Any:  # noqa: ANN401
            own.stop()
            return evaluate_checkpoint(server, *args, **kwargs)

        monkeypatch.setattr(bc_module, "evaluate_checkpoint", stop_then_evaluate)
        assert train_cli(own, config, run) == 3
    err = capsys.readouterr().err
    assert_stopped_for_a_lost_server(err, "esrp train bc", address)
    assert (run / "ckpt.pt").exists()


# --- The DAgger loop.


def test_dagger_runs_its_iterations_and_resumes_with_more(
    server: esrp.LocalServer,
    expert: Path,
    train_easy: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    run = tmp_path / "run"
    config = write_toml(
        tmp_path / "dagger.toml", {"bc": bc_table(expert), "dagger": dagger_table(train_easy)}
    )
    assert train_cli(server, config, run, "--dagger") == 0
    out, err = capsys.readouterr()
    assert out.strip() == f"checkpoint: {run / 'iter-01' / 'ckpt.pt'}"
    assert "to resume" not in err, "a fresh run's iterations are not resumed (no --resume note)"
    assert train_cli(server, config, run, "--dagger") == 2
    assert "already holds a DAgger run: pass --resume" in capsys.readouterr().err
    first = (run / "iter-01" / "ckpt.pt").stat().st_mtime_ns

    # Two iterations now, the rollouts one at a time (2 by default): the first is kept, the second runs.
    more = {"bc": bc_table(expert), "dagger": dagger_table(train_easy, iterations=2, episodes_in_flight=1)}
    assert train_cli(server, write_toml(config, more), run, "--dagger", "--resume") == 0
    assert (run / "iter-01" / "ckpt.pt").stat().st_mtime_ns == first
    log = rows(run / "dagger.csv")
    assert [r["iteration"] for r in log] == ["0", "1", "2"]
    expert_steps = int(zarr.open_group(str(expert), mode="r")["meta/episode_ends"][-1])
    assert (log[0]["episodes"], log[0]["steps"], log[0]["agreement"]) == ("2", str(expert_steps), "")
    total = expert_steps
    for k in (1, 2):
        store = zarr.open_group(str(run / f"dagger-{k:02d}.zarr"), mode="r")
        assert (store.attrs["labels"], store.attrs["policy"], store.attrs["resolution"]) == (
            "planner",
            "bc",
            32,
        )
        scene_ids = list(store.attrs["scene_ids"])
        assert len(scene_ids) == 2
        assert set(scene_ids) <= set(train_easy[1:]), "never the held-out scene"
        ends = store["meta/episode_ends"][:]
        assert all(0 < int(b) - int(a) <= 8 for a, b in zip([0, *ends[:-1]], ends, strict=True))
        labels, policy = store["data/action"][:], store["data/policy_action"][:]
        acted = policy != demos_module.NO_ACTION
        assert log[k]["episodes"] == "2"
        assert log[k]["steps"] == str(len(labels))
        assert float(log[k]["agreement"]) == pytest.approx((policy[acted] == labels[acted]).mean(), abs=1e-6)
        total += len(labels)
        assert log[k]["total_steps"] == str(total)
        folder = run / f"iter-{k:02d}"
        trained = json.loads((folder / "config.json").read_text())
        assert trained["demos"] == [
            str(expert),
            *(str(run / f"dagger-{i:02d}.zarr") for i in range(1, k + 1)),
        ]
        assert trained["seed"] == k
        # Fine-tuned: the optimizer goes on from the previous iteration's (Adam's step count).
        steps = [int(rows(run / f"iter-{i:02d}" / "log.csv")[-1]["steps"]) for i in range(k + 1)]
        state = torch.load(folder / "ckpt.pt", weights_only=False)["optimizer"]["state"]
        assert int(state[0]["step"]) == sum(steps)
    for row in log:
        assert row["eval_episodes"] == "1"
        assert 0.0 <= float(row["sr"]) <= float(row["osr"]) <= 1.0
        assert float(row["seconds"]) > 0
    state = json.loads((run / "state.json").read_text())
    assert (state["completed"], state["current"]) == (3, None)

    # Settings that change what is trained are refused on resume.
    other = {
        "bc": bc_table(expert),
        "dagger": dagger_table(train_easy, iterations=2, episodes_in_flight=1, beta=0.25),
    }
    assert train_cli(server, write_toml(config, other), run, "--dagger", "--resume") == 2
    assert "other settings (beta: 0.5 → 0.25)" in capsys.readouterr().err


def test_dagger_takes_iteration_0_from_a_finished_bc_run(
    server: esrp.LocalServer,
    expert: Path,
    train_easy: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    plain = write_toml(tmp_path / "bc.toml", {"bc": bc_table(expert, epochs=2)})
    assert train_cli(server, plain, tmp_path / "bc") == 0
    initial = tmp_path / "bc" / "ckpt.pt"
    run = tmp_path / "run"
    # [bc]'s epochs are iteration 0's only when it is trained: the checkpoint says how many it had.
    fine_tuning = {"lr": 2e-4, "keep_average": True}
    tables = {
        "bc": bc_table(expert, epochs=40),
        "dagger": dagger_table(train_easy, initial=str(initial), **fine_tuning),
    }
    config = write_toml(tmp_path / "dagger.toml", tables)
    assert train_cli(server, config, run, "--dagger") == 0
    capsys.readouterr()
    given = torch.load(initial, weights_only=False)
    copied = torch.load(run / "iter-00" / "ckpt.pt", weights_only=False)
    assert copied["epoch"] == 2
    for name, tensor in given["model"].items():
        assert torch.equal(tensor, copied["model"][name]), name
    assert not (run / "iter-00" / "log.csv").exists() or not rows(run / "iter-00" / "log.csv"), "not trained"
    assert [r["epoch"] for r in rows(run / "iter-00" / "eval.csv")] == ["2"], "evaluated after its epoch 2"
    assert [r["iteration"] for r in rows(run / "dagger.csv")] == ["0", "1"]
    # Iteration 1 fine-tunes the given model and optimizer (Adam's step count goes on).
    steps = int(rows(tmp_path / "bc" / "log.csv")[-1]["steps"]) + int(
        rows(run / "iter-01" / "log.csv")[-1]["steps"]
    )
    tuned = torch.load(run / "iter-01" / "ckpt.pt", weights_only=False)
    assert int(tuned["optimizer"]["state"][0]["step"]) == steps
    # At [dagger]'s lr, going on with the given checkpoint's average of the weights.
    assert json.loads((run / "iter-01" / "config.json").read_text())["lr"] == 2e-4
    assert int(tuned["ema"]["optimization_step"]) == steps

    # A model-only checkpoint (as docs/results ships) cannot be fine-tuned; a model of other settings
    # is refused by the settings check.
    slim = tmp_path / "slim.pt"
    torch.save({k: v for k, v in given.items() if k not in ("optimizer", "torch_rng")}, slim)
    tables["dagger"] = dagger_table(train_easy, initial=str(slim))
    assert train_cli(server, write_toml(config, tables), tmp_path / "slim-run", "--dagger") == 2
    assert "holds the model only" in capsys.readouterr().err
    tables = {"bc": bc_table(expert, lr=5e-4), "dagger": dagger_table(train_easy, initial=str(initial))}
    assert train_cli(server, write_toml(config, tables), tmp_path / "other-run", "--dagger") == 2
    assert "was trained with other settings than [bc]'s (lr: 0.001 → 0.0005)" in capsys.readouterr().err
    assert not (tmp_path / "other-run").exists(), "refused before anything is written"


class Interrupted(Exception):
    """Stands for the signal that stops a run."""


def test_an_interrupted_dagger_run_resumes_where_it_stopped(
    expert: Path,
    train_easy: list[str],
    tmp_path: Path,
    train_server: TrainServer,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    run = tmp_path / "run"
    bc = BcConfig.from_mapping(bc_table(expert, checkpoint_every=1))
    dagger = DaggerConfig.from_mapping(dagger_table(train_easy, epochs_per_iteration=2))

    # Interrupted after the first episode of iteration 1's export.
    append = demos_module._Store.append

    def append_once(store: Any, *args: Any, **kwargs: Any) -> None:  # noqa: ANN401
        append(store, *args, **kwargs)
        if store.policy_action is not None:
            raise Interrupted

    monkeypatch.setattr(demos_module._Store, "append", append_once)
    with pytest.raises(Interrupted):
        run_dagger(bc, dagger, run, progress=False, server=train_server)
    monkeypatch.undo()
    state = json.loads((run / "state.json").read_text())
    assert (state["completed"], state["current"]["iteration"], state["current"]["phase"]) == (1, 1, "export")
    store = zarr.open_group(str(run / "dagger-01.zarr"), mode="r")
    (exported,) = store.attrs["scene_ids"]
    first_labels = store["data/action"][:]

    # Interrupted again in iteration 1's training, after its first epoch's checkpoint.
    def save_then_stop(path: Path, kind: str, model: Any, optimizer: Any, **progress: Any) -> None:  # noqa: ANN401
        save_checkpoint(path, kind, model, optimizer, **progress)
        if path.parent.name == "iter-01" and progress["epoch"] == 1:
            raise Interrupted

    monkeypatch.setattr(bc_module, "save_checkpoint", save_then_stop)
    with pytest.raises(Interrupted):
        run_dagger(bc, dagger, run, resume=True, progress=False, server=train_server)
    monkeypatch.undo()
    state = json.loads((run / "state.json").read_text())
    assert (state["current"]["iteration"], state["current"]["phase"]) == (1, "train")
    store = zarr.open_group(str(run / "dagger-01.zarr"), mode="r")
    assert store.attrs["scene_ids"][0] == exported, "the export went on after its first episode"
    assert len(store.attrs["scene_ids"]) == 2
    assert np.array_equal(store["data/action"][: len(first_labels)], first_labels)
    assert torch.load(run / "iter-01" / "ckpt.pt", weights_only=False)["epoch"] == 1

    checkpoint = run_dagger(bc, dagger, run, resume=True, progress=False, server=train_server)
    assert checkpoint == run / "iter-01" / "ckpt.pt"
    assert torch.load(checkpoint, weights_only=False)["epoch"] == 2
    assert [r["epoch"] for r in rows(run / "iter-01" / "log.csv")] == ["1", "2"]
    assert [r["iteration"] for r in rows(run / "dagger.csv")] == ["0", "1"]
    assert rows(run / "dagger.csv")[1]["episodes"] == "2"
    assert json.loads((run / "state.json").read_text())["completed"] == 2


def test_bad_dagger_configs_are_refused(
    server: esrp.LocalServer,
    expert: Path,
    train_easy: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    run = tmp_path / "run"
    plain = write_toml(tmp_path / "plain.toml", {"bc": bc_table(expert)})
    assert train_cli(server, plain, run, "--dagger") == 2
    assert "has no [dagger] table: esrp train bc --dagger needs one" in capsys.readouterr().err
    for values, message in (
        ({"rounds": 2}, "unknown dagger settings ['rounds']"),
        ({"beta": 1.5}, "dagger beta must be between 0 and 1"),
        ({"lr": 0}, "dagger lr must be a positive number"),
        ({"keep_average": "yes"}, "dagger keep_average must be true or false"),
        ({"scenes_per_iteration": 0}, "dagger scenes_per_iteration must be at least 1"),
        ({"episodes_in_flight": 0}, "dagger episodes_in_flight must be at least 1"),
        ({"plan_budget_ms": 2**32}, "dagger plan_budget_ms must be at most 4294967295"),
        ({"iterations": "2"}, "dagger iterations must be an integer"),
        ({"split": "challenge"}, "dagger split 'challenge': train or test"),
    ):
        config = write_toml(
            tmp_path / "bad.toml", {"bc": bc_table(expert), "dagger": dagger_table(train_easy, **values)}
        )
        assert train_cli(server, config, run, "--dagger") == 2
        assert message in capsys.readouterr().err
    # The candidates are all held out.
    held_out = {"bc": bc_table(expert), "dagger": dagger_table(train_easy, scenes=train_easy[:1])}
    assert train_cli(server, write_toml(tmp_path / "held.toml", held_out), run, "--dagger") == 2
    assert "no scene is left for DAgger's rollouts" in capsys.readouterr().err
    assert not run.exists(), "nothing made: the fixed config starts afresh"


def test_dagger_and_plain_runs_keep_out_of_each_others_folders(
    server: esrp.LocalServer,
    expert: Path,
    train_easy: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`--dagger` given a plain run's folder (or forgotten on a DAgger run's `--resume`) wrote its
    files among the other run's, config.json overwritten."""
    plain = write_toml(tmp_path / "bc.toml", {"bc": bc_table(expert)})
    assert train_cli(server, plain, tmp_path / "bc") == 0
    before = (tmp_path / "bc" / "config.json").read_text()
    tables = {"bc": bc_table(expert), "dagger": dagger_table(train_easy)}
    config = write_toml(tmp_path / "dagger.toml", tables)
    assert train_cli(server, config, tmp_path / "bc", "--dagger") == 2
    assert "holds a run without --dagger (ckpt.pt), not a DAgger run" in capsys.readouterr().err
    assert (tmp_path / "bc" / "config.json").read_text() == before
    assert not (tmp_path / "bc" / "state.json").exists()
    # A DAgger run's folder (its state.json) refuses a plain run, with or without --resume.
    dagger_run = tmp_path / "dagger"
    dagger_run.mkdir()
    (dagger_run / "state.json").write_text("{}")
    for more in ((), ("--resume",)):
        assert train_cli(server, plain, dagger_run, *more) == 2
        assert "holds a DAgger run (state.json)" in capsys.readouterr().err
    assert sorted(p.name for p in dagger_run.iterdir()) == ["state.json"]


def test_the_shipped_bc_configs_load() -> None:
    configs = Path(__file__).parent.parent / "configs"
    loaded = {path.stem: load_config(path) for path in sorted(configs.glob("bc-*.toml"))}
    assert {"bc-cpu-small", "bc-paper", "bc-dagger-cpu"} <= set(loaded)
    template = loaded["bc-dagger-cpu"]
    assert (template.demos, template.in_memory, template.eval_limit) == ("demos/v2-easy-64.zarr", True, 50)
    dagger = load_dagger_config(configs / "bc-dagger-cpu.toml")
    assert dagger.iterations >= 1
    with pytest.raises(ValueError, match="has no \\[dagger\\] table"):
        load_dagger_config(configs / "bc-cpu-small.toml")


def test_an_initial_checkpoint_older_than_the_recipe_settings_is_taken_as_trained(
    expert: Path, tmp_path: Path
) -> None:
    from esrp.agents.bc import LEGACY_SETTINGS
    from esrp.train.dagger import _initial_epochs

    legacy = BcConfig.from_mapping(bc_table(expert, **LEGACY_SETTINGS))
    checkpoint = train(legacy, tmp_path / "old", progress=False)
    # As a checkpoint written before these settings existed: its config lacks them.
    state = torch.load(checkpoint, weights_only=False)
    state["config"] = {k: v for k, v in state["config"].items() if k not in LEGACY_SETTINGS}
    torch.save(state, checkpoint)
    assert _initial_epochs(checkpoint, legacy) == 1
    with pytest.raises(ValueError, match="ema"):
        _initial_epochs(checkpoint, BcConfig.from_mapping(bc_table(expert)))


def test_a_bc_rollout_export_with_episodes_in_flight_is_the_one_at_a_time(
    server: esrp.LocalServer, expert: Path, train_easy: list[str], tmp_path: Path
) -> None:
    import subprocess
    import sys

    checkpoint = train(BcConfig.from_mapping(bc_table(expert)), tmp_path / "bc", progress=False)
    stores = {}
    for in_flight in (1, 2):
        stores[in_flight] = tmp_path / f"rollouts-{in_flight}.zarr"
        # A fresh process: the policy's agents are made on the export's threads, diffusers
        # imported by two of them at once (its lazy imports are not thread-safe).
        command = [sys.executable, "-m", "esrp.cli", "demos", "export", "--server", server.address]
        command += ["--split", "train", "--scenes", ",".join(train_easy[1:4]), "--dagger", "bc"]
        command += ["--checkpoint", str(checkpoint), "--resolution", str(RESOLUTION), "--beta", "0.5"]
        command += ["--max-steps", "6", "--episodes-in-flight", str(in_flight), "--no-progress"]
        done = subprocess.run([*command, "--out", str(stores[in_flight])], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
    assert zarr.open_group(str(stores[2]), mode="r").attrs["scene_ids"] == train_easy[1:4]
    assert_same_stores(stores[1], stores[2])
