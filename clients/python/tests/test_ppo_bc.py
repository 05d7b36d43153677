"""ESRP-PPO's network by imitation (`esrp train ppo-bc`) and PPO fine-tuning from it (`init`,
`critic_warmup`), on the real server with a tiny network: the streams read every step once with
episode starts where episodes begin, the loss falls, the checkpoint plays with `esrp eval --agent
ppo`, resumes, starts a PPO run, and the critic warm-up moves the critic head alone."""

from __future__ import annotations

import csv
import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import esrp
from esrp.cli import main

torch = pytest.importorskip("torch", reason="esrp[train] is not installed")

from esrp.agents.ppo import NETWORK_SETTINGS, PpoConfig, PpoNet, load_network  # noqa: E402
from esrp.train import ppo, ppo_bc  # noqa: E402
from esrp.train.bc import DemoWindows  # noqa: E402


@pytest.fixture(scope="module")
def demos(server: esrp.LocalServer, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The expert demonstrations of the first two easy test scenes, at 64 px."""
    with server.client() as client:
        scenes = [s.id for s in client.scenes("test", "easy", page_size=2)][:2]
    out = tmp_path_factory.mktemp("demos") / "two.zarr"
    arguments = [
        "demos",
        "export",
        "--server",
        server.address,
        "--split",
        "test",
        "--scenes",
        ",".join(scenes),
    ]
    assert main([*arguments, "--resolution", "64", "--out", str(out), "--no-progress"]) == 0
    return out


def network_config(scene: str = "", **more: object) -> PpoConfig:
    values: dict[str, object] = {
        "split": "test",
        "horizon": 5,
        "resolution": 64,
        "encoder": "nature",
        "pool": 1,
        "feature_dim": 16,
        "grasp_dim": 4,
        "hidden": 16,
        "num_envs": 2,
        "num_steps": 8,
        "minibatch_size": 8,
        "update_epochs": 2,
        "total_steps": 32,
        "threads": 1,
        "checkpoint_every": 1,
        "device": "cpu",
    }
    if scene:
        values["scene"] = scene
    values.update(more)
    return PpoConfig.from_mapping(values)


def imitation(demos: Path, **more: object) -> ppo_bc.ImitationConfig:
    values: dict[str, object] = {"demos": str(demos), "epochs": 2, "streams": 2, "seq_len": 16, "threads": 1}
    values.update(more)
    return ppo_bc.ImitationConfig.from_mapping(values)


def test_streams_read_every_step_once_with_starts_where_episodes_begin() -> None:
    lengths = [5, 3, 7, 1, 4]
    steps, starts = ppo_bc.stream_order(lengths, 3, seed=4)
    assert steps.shape == starts.shape == (20 // 3, 3)
    flat = steps.T.reshape(-1)  # each stream in order, one after the other
    assert len(set(flat.tolist())) == len(flat)  # no step twice
    firsts = set(np.concatenate([[0], np.cumsum(lengths)[:-1]]).tolist())
    for column in range(3):
        for row in range(steps.shape[0]):
            step = int(steps[row, column])
            # A start where an episode begins, and at each stream's first position; nowhere else.
            assert bool(starts[row, column]) == (step in firsts or row == 0)
            if row and step not in firsts:
                assert int(steps[row - 1, column]) == step - 1  # an episode's steps stay in order
    whole, _ = ppo_bc.stream_order(lengths, 1, seed=4)
    assert sorted(whole.ravel().tolist()) == list(range(20))
    again, _ = ppo_bc.stream_order(lengths, 3, seed=4)
    assert np.array_equal(again, steps)
    with pytest.raises(ValueError, match="streams"):
        ppo_bc.stream_order([2], 3, seed=0)


def test_the_labels_are_the_demonstrations_actions(demos: Path) -> None:
    store = DemoWindows(demos, 1, 1, in_memory=True)
    network = PpoNet(network_config())
    steps, starts = ppo_bc.stream_order(np.bincount(store.episode), 2, seed=0)
    batch = ppo_bc._batch(
        network,
        store,
        steps,
        starts,
        imitation(demos, augment_shift=0),
        torch.Generator(),
        torch.device("cpu"),
    )
    assert torch.equal(batch["labels"], torch.from_numpy(store.actions[steps.reshape(-1)]))
    assert bool(batch["mask"].all())
    # Without a shift, the views are the store's (time-major), each goal its episode's.
    expected = network.preprocess(torch.from_numpy(store.memory["data/ego_rgb"][steps.reshape(-1)]))
    assert torch.equal(batch["ego"], expected)
    goals = batch["goal"][batch["goal_index"]]
    wanted = network.preprocess(
        torch.from_numpy(store.memory["meta/goal_rgb"][store.episode[steps.reshape(-1)]])
    )
    assert torch.equal(goals, wanted)


def test_imitation_lowers_the_loss_and_the_checkpoint_plays(
    demos: Path, tmp_path: Path, server: esrp.LocalServer, client: esrp.Client
) -> None:
    run = tmp_path / "run"
    checkpoint = ppo_bc.train(
        network_config(),
        imitation(demos, epochs=30, lr=3e-3, lr_warmup_steps=0, augment_shift=0),
        run,
        progress=False,
    )
    with open(run / "log.csv", newline="") as file:
        log = list(csv.DictReader(file))
    assert [row["epoch"] for row in log] == [str(e) for e in range(1, 31)]
    assert float(log[-1]["loss"]) < 0.85 * float(log[0]["loss"])
    assert json.loads((run / "config.json").read_text())["ppo_bc"]["epochs"] == 30
    network = load_network(checkpoint)
    assert network.config.hidden == 16
    # esrp eval plays it as any ESRP-PPO checkpoint.
    scene = next(iter(client.scenes("test", "easy", page_size=1))).id
    out = tmp_path / "eval.jsonl"
    arguments = ["eval", "--agent", "ppo", "--checkpoint", str(checkpoint), "--server", server.address]
    assert main([*arguments, "--split", "test", "--scenes", scene, "--out", str(out), "--no-progress"]) == 0
    assert len(out.read_text().splitlines()) == 1


def test_imitation_resumes_and_refuses_other_settings(demos: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    ppo_bc.train(network_config(), imitation(demos, epochs=1), run, progress=False)
    with pytest.raises(ValueError, match="already holds a run"):
        ppo_bc.train(network_config(), imitation(demos, epochs=2), run, progress=False)
    with pytest.raises(ValueError, match="other"):
        ppo_bc.train(network_config(), imitation(demos, epochs=2, lr=1e-2), run, resume=True, progress=False)
    # The resumed run's seconds count on from the interrupted run's last line.
    with open(run / "log.csv", newline="") as file:
        (first,) = [row | {"seconds": "1000.0"} for row in csv.DictReader(file)]
    with open(run / "log.csv", "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(first))
        writer.writeheader()
        writer.writerow(first)
    ppo_bc.train(network_config(), imitation(demos, epochs=2), run, resume=True, progress=False)
    with open(run / "log.csv", newline="") as file:
        log = list(csv.DictReader(file))
    assert [row["epoch"] for row in log] == ["1", "2"]
    assert 1000.0 < float(log[1]["seconds"]) < 1000.0 + 600
    assert torch.load(run / "ckpt.pt", weights_only=False)["epoch"] == 2


def test_imitation_resumes_only_on_the_demonstrations_it_began_with(demos: Path, tmp_path: Path) -> None:
    import zarr

    store = tmp_path / "store.zarr"
    shutil.copytree(demos, store)
    run = tmp_path / "run"
    ppo_bc.train(network_config(), imitation(store, epochs=1), run, progress=False)
    data: Any = zarr.open_group(str(store), mode="r+")["data/action"]
    first = int(data[0])
    data[0] = (first + 1) % 6
    with pytest.raises(ValueError, match="trained on other demonstrations .* exported again or appended to"):
        ppo_bc.train(network_config(), imitation(store, epochs=2), run, resume=True, progress=False)
    data[0] = first
    ppo_bc.train(network_config(), imitation(store, epochs=2), run, resume=True, progress=False)
    assert torch.load(run / "ckpt.pt", weights_only=False)["epoch"] == 2


def test_ppo_starts_from_the_weights_and_the_warmup_moves_the_critic_alone(
    demos: Path, tmp_path: Path, client: esrp.Client, easy_scenes: list[str]
) -> None:
    start = ppo_bc.train(network_config(), imitation(demos, epochs=1), tmp_path / "bc", progress=False)
    initial = torch.load(start, weights_only=False)["model"]
    config = network_config(easy_scenes[0], init=str(start), critic_warmup=1, total_steps=16)
    after_warmup = torch.load(
        ppo.train(config, tmp_path / "warm", client, progress=False), weights_only=False
    )
    for name, weights in after_warmup["model"].items():
        if name.startswith("critic."):
            assert not torch.equal(weights, initial[name]), name
        else:
            assert torch.equal(weights, initial[name]), name
    # After the warm-up, the whole network learns.
    longer = dataclasses.replace(config, total_steps=32)
    after = torch.load(
        ppo.train(longer, tmp_path / "warm", client, resume=True, progress=False), weights_only=False
    )
    assert not torch.equal(after["model"]["actor.2.weight"], initial["actor.2.weight"])


def test_bad_inits_and_imitation_configs_are_refused(
    demos: Path, tmp_path: Path, client: esrp.Client
) -> None:
    with pytest.raises(ValueError, match="does not exist"):
        ppo.train(network_config("x", init=str(tmp_path / "none.pt")), tmp_path / "a", client, progress=False)
    other = ppo_bc.train(
        network_config(hidden=8), imitation(demos, epochs=1), tmp_path / "bc8", progress=False
    )
    with pytest.raises(ValueError, match="other settings"):
        ppo.train(network_config("x", init=str(other)), tmp_path / "b", client, progress=False)
    with pytest.raises(ValueError, match="critic_warmup"):
        network_config(critic_warmup=-1)
    with pytest.raises(ValueError, match="demos"):
        ppo_bc.ImitationConfig.from_mapping({})
    with pytest.raises(ValueError, match="unknown"):
        ppo_bc.ImitationConfig.from_mapping({"demos": "x", "epoch": 3})
    with pytest.raises(ValueError, match="64 px"):
        ppo_bc.train(network_config(resolution=128, pool=2), imitation(demos), tmp_path / "c", progress=False)
    with pytest.raises(ValueError, match="cannot fill 100000 streams: fewer streams"):
        ppo_bc.train(network_config(), imitation(demos, streams=100_000), tmp_path / "e", progress=False)
    # Refused at their start, the runs made no folder.
    assert not any((tmp_path / name).exists() for name in ("a", "b", "c", "e"))
    bad = tmp_path / "bad.toml"
    bad.write_text('[ppo]\nresolution = 64\n[ppo_bc]\ndemos = "x"\nstreams = 0\n')
    assert main(["train", "ppo-bc", "--config", str(bad), "--out", str(tmp_path / "d")]) == 2


def test_the_shipped_imitation_configs_load() -> None:
    root = Path(__file__).resolve().parents[1] / "configs"
    network, settings = ppo_bc.load_configs(root / "ppo-bc-v2-easy-plan-cpu.toml")
    bcinit = ppo.load_config(root / "ppo-v2-easy-bcinit-cpu.toml")
    assert {k: getattr(bcinit, k) for k in NETWORK_SETTINGS} == {
        k: getattr(network, k) for k in NETWORK_SETTINGS
    }
    assert settings.demos == ["demos/v2-easy-64-plan.zarr"]
    assert bcinit.init == "runs/ppo-bc-v2-easy-plan/ckpt.pt"
    assert bcinit.critic_warmup > 0
    # The others start from or stand beside it: the same network.
    for other in sorted(root.glob("ppo-bc-*.toml")):
        again, more = ppo_bc.load_configs(other)
        assert {k: getattr(again, k) for k in NETWORK_SETTINGS} == {
            k: getattr(network, k) for k in NETWORK_SETTINGS
        }, other.name
        assert more.init in (None, "runs/ppo-bc-v2-easy-plan/ckpt.pt"), other.name


def test_esrp_train_ppo_bc_end_to_end(
    demos: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    network = {k: v for k, v in network_config().to_dict().items() if v is not None and k != "reward"}
    lines = ["[ppo]", *(f"{k} = {json.dumps(v)}" for k, v in network.items())]
    lines += ["[ppo_bc]", f"demos = {json.dumps(str(demos))}", "epochs = 1", "streams = 2", "seq_len = 16"]
    config = tmp_path / "c.toml"
    config.write_text("\n".join(lines) + "\n")
    run = tmp_path / "run"
    assert main(["train", "ppo-bc", "--config", str(config), "--out", str(run), "--no-progress"]) == 0
    assert f"checkpoint: {run / 'ckpt.pt'}" in capsys.readouterr().out
    assert load_network(run / "ckpt.pt").config.resolution == 64
    # Again without --resume: refused, the run kept.
    assert main(["train", "ppo-bc", "--config", str(config), "--out", str(run), "--no-progress"]) == 2
    assert "--resume" in capsys.readouterr().err


def test_policy_lr_moves_the_policy_at_its_own_rate(
    tmp_path: Path, client: esrp.Client, easy_scenes: list[str]
) -> None:
    config = network_config(easy_scenes[0], lr=1e-3, policy_lr=1e-5, total_steps=16, anneal_lr=False)
    network = PpoNet(config)
    critic, policy = ppo.parameter_groups(network, config)
    named = dict(network.named_parameters())
    assert {id(p) for p in critic["params"]} == {id(p) for n, p in named.items() if n.startswith("critic.")}
    assert len(critic["params"]) + len(policy["params"]) == len(named)
    assert ppo.group_rates(config) == [1e-3, 1e-5]
    assert ppo.group_rates(dataclasses.replace(config, policy_lr=None)) == [1e-3]
    state = torch.load(ppo.train(config, tmp_path / "run", client, progress=False), weights_only=False)
    assert [group["lr"] for group in state["optimizer"]["param_groups"]] == [1e-3, 1e-5]
    with pytest.raises(ValueError, match="policy_lr"):
        network_config(policy_lr=0)


def test_dagger_exports_at_the_policys_resolution_and_imitation_learns_the_labels(
    demos: Path, tmp_path: Path, server: esrp.LocalServer, capsys: pytest.CaptureFixture[str]
) -> None:
    start = ppo_bc.train(network_config(), imitation(demos, epochs=1), tmp_path / "bc", progress=False)
    with server.client() as client:
        scene = next(iter(client.scenes("test", "easy", page_size=1))).id
    store = tmp_path / "dagger.zarr"
    arguments = ["demos", "export", "--server", server.address, "--dagger", "ppo", "--checkpoint", str(start)]
    arguments += [
        "--split",
        "test",
        "--scenes",
        scene,
        "--max-steps",
        "6",
        "--label-horizon",
        "1",
        "--no-progress",
    ]
    # The policy takes 64 px views: other ones are refused, none asked for gives the policy's.
    assert main([*arguments, "--resolution", "128", "--out", str(store)]) == 2
    assert "64 px" in capsys.readouterr().err
    assert main([*arguments, "--out", str(store)]) == 0
    windows = DemoWindows(store, 1, 1, in_memory=True)
    assert windows.resolution == 64
    assert len(windows) == 6
    # A fine-tuning from the first weights on both stores: the DAgger states' label is the planner's.
    config = imitation(demos, epochs=1, init=str(start))
    config.demos.append(str(store))
    both = DemoWindows(config.demos, 1, 1)
    assert np.array_equal(both.targets[-6:, 0], windows.targets[:, 0])
    run = tmp_path / "fine"
    ppo_bc.train(network_config(), config, run, progress=False)
    assert torch.load(run / "ckpt.pt", weights_only=False)["imitation"]["init"] == str(start)
