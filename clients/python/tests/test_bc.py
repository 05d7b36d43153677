"""ESRP-BC smoke tests on tiny data (the demonstrations of one easy test scene, a tiny model): an
epoch trains with finite losses, the loss falls over a few steps of a fixed batch, the span
sampler's windows are the windows step by step, no label is made up past an episode's end,
checkpoints play the weights' average and reload to identical actions, batched agents act as
agents alone do, training resumes, and `esrp eval --agent bc` plays a checkpoint."""

from __future__ import annotations

import asyncio
import csv
import dataclasses
import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import esrp
from esrp.cli import main
from esrp.eval.results import read_records

torch = pytest.importorskip("torch", reason="esrp[train] is not installed")
pytest.importorskip("diffusers", reason="esrp[train] is not installed")
pytest.importorskip("zarr", reason="esrp[train] is not installed")

from esrp.agents.bc import (  # noqa: E402
    BatchedBcAgent,
    BcAgent,
    BcConfig,
    BcPolicy,
    DiffusionPolicy,
    bc_loss,
    load_policy,
    random_shift,
    schedulers,
)
from esrp.train.bc import NO_LABEL, DemoWindows, train  # noqa: E402


@pytest.fixture(scope="module")
def demos(server: esrp.LocalServer, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The expert demonstrations of the first easy test scene."""
    with server.client() as client:
        scene = next(iter(client.scenes("test", "easy", page_size=1))).id
    out = tmp_path_factory.mktemp("demos") / "one.zarr"
    arguments = ["demos", "export", "--server", server.address, "--split", "test", "--scenes", scene]
    assert main([*arguments, "--out", str(out), "--no-progress"]) == 0
    return out


def tiny(demos: Path, **more: object) -> BcConfig:
    values: dict[str, object] = {
        "demos": str(demos),
        "feature_dim": 32,
        "grasp_dim": 8,
        "cond_dim": 32,
        "unet_channels": [16, 32],
        "batch_size": 64,
        "epochs": 1,
        "lr": 1e-3,
        "threads": 1,
        "checkpoint_every": 1,
    }
    values.update(more)
    return BcConfig.from_mapping(values)


def log_rows(run: Path) -> list[dict[str, str]]:
    with open(run / "log.csv", newline="") as file:
        return list(csv.DictReader(file))


def test_an_epoch_trains_with_finite_losses(demos: Path, tmp_path: Path) -> None:
    checkpoint = train(tiny(demos), tmp_path / "run", progress=False)
    assert checkpoint.is_file()
    rows = log_rows(tmp_path / "run")
    assert len(rows) == 1
    assert all(math.isfinite(float(rows[0][key])) for key in ("loss", "mse", "ce"))


def fresh_model(demos: Path) -> tuple[BcConfig, DiffusionPolicy, Any, DemoWindows]:
    """A tiny config, its model from seed 0, the training scheduler and the demonstrations' windows."""
    config = tiny(demos)
    torch.manual_seed(0)
    scheduler, _ = schedulers(config)
    return config, DiffusionPolicy(config), scheduler, DemoWindows(demos, config.n_obs, config.horizon)


def test_the_loss_falls_on_a_fixed_batch(demos: Path) -> None:
    _, model, scheduler, windows = fresh_model(demos)
    batch = windows.batch(np.arange(len(windows)))
    assert batch["frames"][batch["frame_index"]].shape[1:] == (4, 128, 128, 3)
    assert batch["actions"].shape[1:] == batch["mask"].shape[1:] == (8,)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    losses = []
    for _ in range(12):
        # The same noise and noise levels every step: the objective is fixed.
        loss, _, _ = bc_loss(model, scheduler, batch, torch.Generator().manual_seed(0))
        optimizer.zero_grad()
        loss.backward()  # type: ignore[no-untyped-call]
        optimizer.step()
        losses.append(loss.item())
    assert all(math.isfinite(v) for v in losses)
    assert losses[-1] < 0.8 * losses[0], losses


def windows_one_by_one(windows: DemoWindows, steps: np.ndarray) -> dict[str, np.ndarray]:
    """Each window of `steps` read on its own from the store, as training read them before spans:
    the ego views of steps t-n+1..t (the episode's first repeated before its start), the goal,
    the grasp flags, and the actions t..t+h-1 that lie within the episode (-1 past its end).
    """
    store = windows.stores[0]
    ego, goal, grasping = store["data/ego_rgb"][:], store["meta/goal_rgb"][:], store["data/grasping"][:]
    ends = [int(e) for e in store["meta/episode_ends"][:]]
    rows: dict[str, list[np.ndarray]] = {"ego": [], "goal": [], "grasping": [], "actions": []}
    for t in steps:
        episode = next(i for i, end in enumerate(ends) if t < end)
        start, end = (ends[episode - 1] if episode else 0), ends[episode]
        history = [max(t - k, start) for k in range(windows.n_obs - 1, -1, -1)]
        rows["ego"].append(ego[history])
        rows["goal"].append(goal[episode])
        rows["grasping"].append(grasping[history])
        ahead = [int(windows.actions[u]) if u < end else -1 for u in range(t, t + windows.horizon)]
        rows["actions"].append(np.array(ahead))
    return {key: np.stack(value) for key, value in rows.items()}


def test_span_batches_hold_the_windows_step_by_step(demos: Path) -> None:
    windows = DemoWindows(demos, 4, 8)
    order = windows.epoch_order(seed=3, span=16)
    batch_steps = np.sort(order[:40])
    batch = windows.batch(batch_steps)
    alone = windows_one_by_one(windows, batch_steps)
    assert np.array_equal(batch["frames"][batch["frame_index"]].numpy(), alone["ego"])
    assert np.array_equal(batch["goals"][batch["goal_index"]].numpy(), alone["goal"])
    assert np.array_equal(batch["grasping"].numpy(), alone["grasping"])
    labelled = alone["actions"] >= 0
    assert np.array_equal(batch["mask"].numpy(), labelled)
    assert np.array_equal(batch["actions"].numpy()[labelled], alone["actions"][labelled])
    # Each view is encoded once: spans share theirs (40 windows of 4 views from a few runs).
    assert len(batch["frames"]) < 40 * 4 / 2
    assert len(batch["goals"]) == 1


def test_an_epoch_visits_every_step_once_in_runs_of_one_episode(demos: Path) -> None:
    windows = DemoWindows(demos, 4, 8)
    for span in (1, 5, 16):
        order = windows.epoch_order(seed=span, span=span)
        assert sorted(order.tolist()) == list(range(len(windows)))
        # Cut where the next step is not the one after: each piece is steps of one episode, and
        # there are no more pieces than runs of `span` an episode can be cut into (two runs may
        # follow each other by chance and make one piece).
        breaks = np.flatnonzero(np.diff(order) != 1) + 1
        pieces = np.split(order, breaks)
        assert all(windows.episode[piece[0]] == windows.episode[piece[-1]] for piece in pieces)
        lengths = np.bincount(windows.episode)
        assert len(pieces) <= int((lengths // span + 2).sum())
    assert not np.array_equal(windows.epoch_order(0, 16), windows.epoch_order(1, 16))
    assert np.array_equal(windows.epoch_order(7, 16), windows.epoch_order(7, 16))


def test_no_label_is_made_up_past_an_episodes_end(demos: Path) -> None:
    windows = DemoWindows(demos, 4, 8)
    last = len(windows) - 1
    batch = windows.batch(np.array([0, last - 2, last]))
    ego = batch["frames"][batch["frame_index"]].numpy()
    # The first step's history is its own view, repeated.
    assert all(np.array_equal(ego[0, i], ego[0, 3]) for i in range(3))
    # The last steps learn their own actions and nothing after: the expert releases once.
    assert batch["mask"][1].tolist() == [True] * 3 + [False] * 5
    assert batch["mask"][2].tolist() == [True] + [False] * 7
    assert (windows.targets[last, 1:] == NO_LABEL).all()
    assert batch["actions"][2].tolist() == [int(windows.actions[last])] * 8


def test_unlabelled_positions_count_in_no_loss(demos: Path) -> None:
    config, model, scheduler, windows = fresh_model(demos)
    batch = windows.batch(np.array([len(windows) - 3, len(windows) - 1]))
    unlabelled = ~batch["mask"][:, None, :].expand(-1, 6, -1)
    # The denoiser's prediction, set by hand: what the loss reads of it is what counts.
    predicted = torch.randn(2, 6, config.horizon, generator=torch.Generator().manual_seed(2))

    from torch import Tensor, nn

    class Fixed(nn.Module):
        def __init__(self, prediction: Tensor) -> None:
            super().__init__()
            self.prediction = prediction

        def forward(self, *_: Tensor) -> Tensor:
            return self.prediction

    def loss_with(prediction: Tensor) -> list[float]:
        model.unet = Fixed(prediction)  # type: ignore[assignment]
        with torch.no_grad():
            return [t.item() for t in bc_loss(model, scheduler, batch, torch.Generator().manual_seed(1))]

    base = loss_with(predicted)
    assert loss_with(torch.where(unlabelled, predicted + 5.0, predicted)) == pytest.approx(base, rel=1e-6)
    assert loss_with(torch.where(unlabelled, predicted, predicted + 0.5))[0] != pytest.approx(
        base[0], rel=1e-3
    )


def test_the_learning_rate_warms_up_then_follows_a_cosine(demos: Path) -> None:
    config = tiny(demos, lr=1e-3, lr_warmup_steps=10)
    assert config.lr_at(0, 100) == pytest.approx(1e-4)
    assert config.lr_at(9, 100) == pytest.approx(1e-3)
    assert config.lr_at(10, 100) == pytest.approx(1e-3)
    assert config.lr_at(55, 100) == pytest.approx(5e-4)
    assert config.lr_at(100, 100) == pytest.approx(0.0, abs=1e-12)
    constant = tiny(demos, lr=1e-3, lr_schedule="constant")
    assert {constant.lr_at(s, 100) for s in (0, 50, 99)} == {1e-3}
    with pytest.raises(ValueError, match="lr_schedule"):
        tiny(demos, lr_schedule="linear")


def test_random_shift_crops_each_view_from_its_padded_self() -> None:
    images = torch.randint(0, 256, (6, 16, 16, 3), dtype=torch.uint8)
    assert random_shift(images, 0) is images
    shifted = random_shift(images, 2, torch.Generator().manual_seed(0))
    assert shifted.shape == images.shape
    assert shifted.dtype == torch.uint8
    padded = torch.nn.functional.pad(images.permute(0, 3, 1, 2).float(), (2, 2, 2, 2), mode="replicate")
    for n in range(6):
        crops = [padded[n, :, y : y + 16, x : x + 16].permute(1, 2, 0) for y in range(5) for x in range(5)]
        assert any(torch.equal(shifted[n].float(), crop) for crop in crops)
    assert not torch.equal(shifted, images)


def test_checkpoints_play_the_weights_average(demos: Path, tmp_path: Path) -> None:
    checkpoint = train(tiny(demos, epochs=2), tmp_path / "run", progress=False)
    state = torch.load(checkpoint, weights_only=False)
    assert set(state["model"]) == set(state["train_model"])
    differing = [k for k in state["model"] if not torch.equal(state["model"][k], state["train_model"][k])]
    assert differing, "the played weights are the average, not the last trained ones"
    played = load_policy(checkpoint).state_dict()
    assert all(torch.equal(played[k], state["model"][k]) for k in played)
    # Without the average, the checkpoint plays what was trained.
    plain = train(tiny(demos, ema=False), tmp_path / "plain", progress=False)
    assert "train_model" not in torch.load(plain, weights_only=False)


def test_a_fine_tuning_goes_on_with_its_initial_average_when_asked(demos: Path, tmp_path: Path) -> None:
    first = torch.load(train(tiny(demos, epochs=2), tmp_path / "first", progress=False), weights_only=False)
    done = int(first["ema"]["optimization_step"])
    assert done > 0
    kept = torch.load(
        train(tiny(demos, seed=1), tmp_path / "kept", init=tmp_path / "first" / "ckpt.pt", init_average=True),
        weights_only=False,
    )
    anew = torch.load(
        train(tiny(demos, seed=1), tmp_path / "anew", init=tmp_path / "first" / "ckpt.pt"), weights_only=False
    )
    steps = int(log_rows(tmp_path / "kept")[-1]["steps"])
    assert int(kept["ema"]["optimization_step"]) == done + steps, "the average's count goes on"
    assert int(anew["ema"]["optimization_step"]) == steps, "a new average starts at the loaded weights"
    # The trained weights are the same either way; the played ones are not.
    assert all(torch.equal(kept["train_model"][k], anew["train_model"][k]) for k in kept["train_model"])
    assert any(not torch.equal(kept["model"][k], anew["model"][k]) for k in kept["model"])
    # A fine-tuning may take another learning rate (DAgger's [dagger] lr), not other settings.
    train(tiny(demos, lr=1e-4), tmp_path / "slower", init=tmp_path / "first" / "ckpt.pt", progress=False)
    with pytest.raises(ValueError, match="batch_size"):
        train(tiny(demos, batch_size=32), tmp_path / "other", init=tmp_path / "first" / "ckpt.pt")
    # A checkpoint without its average has none to go on with.
    del first["ema"]
    bare = tmp_path / "no-average.pt"
    torch.save(first, bare)
    with pytest.raises(ValueError, match="holds no average of the weights"):
        train(tiny(demos), tmp_path / "none", init=bare, init_average=True, progress=False)


def test_esrp_train_bc_init_fine_tunes_a_checkpoint_for_playing_too(demos: Path, tmp_path: Path) -> None:
    first = train(tiny(demos, epochs=2), tmp_path / "first", progress=False)
    state = torch.load(first, weights_only=False)
    # What docs/results/checkpoints holds: the played weights and the config, no optimizer.
    slim = tmp_path / "slim.pt"
    torch.save({k: state[k] for k in ("kind", "config", "model", "epoch", "steps")}, slim)
    config = tmp_path / "fine.json"
    config.write_text(json.dumps({**tiny(demos).to_dict(), "lr": 0.0, "seed": 3}))
    command = ["train", "bc", "--config", str(config), "--no-progress"]
    assert main([*command, "--out", str(tmp_path / "fine"), "--init", str(slim)]) == 0
    fine = torch.load(tmp_path / "fine" / "ckpt.pt", weights_only=False)
    # At lr 0 nothing moves: the run trained on from the slim checkpoint's (averaged) weights.
    assert all(torch.equal(fine["train_model"][k], state["model"][k]) for k in state["model"])
    assert int(fine["ema"]["optimization_step"]) == int(log_rows(tmp_path / "fine")[-1]["steps"])
    # A full checkpoint gives its trained weights, and with --init-average its average goes on.
    assert main([*command, "--out", str(tmp_path / "kept"), "--init", str(first), "--init-average"]) == 0
    kept = torch.load(tmp_path / "kept" / "ckpt.pt", weights_only=False)
    assert all(torch.equal(kept["train_model"][k], state["train_model"][k]) for k in state["train_model"])
    done = int(state["ema"]["optimization_step"])
    assert int(kept["ema"]["optimization_step"]) == done + int(log_rows(tmp_path / "kept")[-1]["steps"])
    # Refused: an average the checkpoint lacks, --init-average alone, --init with --dagger, and
    # resuming from a checkpoint made for playing.
    assert main([*command, "--out", str(tmp_path / "x1"), "--init", str(slim), "--init-average"]) == 2
    assert main([*command, "--out", str(tmp_path / "x2"), "--init-average"]) == 2
    assert main([*command, "--out", str(tmp_path / "x3"), "--init", str(slim), "--dagger"]) == 2
    assert main([*command, "--out", str(tmp_path / "x4"), "--init", str(tmp_path / "missing.pt")]) == 2
    (tmp_path / "x5").mkdir()
    shutil.copyfile(slim, tmp_path / "x5" / "ckpt.pt")
    with pytest.raises(ValueError, match="cannot be resumed"):
        train(tiny(demos, epochs=3), tmp_path / "x5", resume=True, progress=False)


def agent_actions(checkpoint: Path, observation: esrp.Observation, steps: int) -> list[int]:
    agent = BcAgent(load_policy(checkpoint), {})
    agent.reset(observation, {"seed": 7})
    return [int(agent.act(observation)) for _ in range(steps)]


def test_a_checkpoint_reloads_to_identical_actions(
    demos: Path, tmp_path: Path, client: esrp.Client, easy_scenes: list[str]
) -> None:
    checkpoint = train(tiny(demos), tmp_path / "run", progress=False)
    with client.create_episode(easy_scenes[0]) as episode:
        first = episode.observation
    assert first is not None
    actions = agent_actions(checkpoint, first, 14)
    assert all(0 <= a < 6 for a in actions)
    assert agent_actions(checkpoint, first, 14) == actions


def test_batched_agents_act_as_agents_alone_do(
    demos: Path, tmp_path: Path, client: esrp.Client, easy_scenes: list[str]
) -> None:
    checkpoint = train(tiny(demos), tmp_path / "run", progress=False)
    views = []
    with client.create_episode(easy_scenes[0]) as episode:
        observation = episode.observation
        assert observation is not None
        for action in [0, 2, 0, 3, 0, 1, 2, 0, 0, 3, 4, 0, 1, 2] * 2:
            views.append(observation)
            observation = dataclasses.replace(episode.step(action).observation, goal_rgb=views[0].goal_rgb)
    alone = []
    for seed in range(3):
        agent = BcAgent(load_policy(checkpoint), {"epsilon": 0.2})
        agent.reset(views[0], {"seed": seed})
        alone.append([int(agent.act(view)) for view in views])
    policy = BcPolicy({"checkpoint": str(checkpoint), "batch": 3})
    batcher = policy.batcher
    assert batcher is not None
    sizes: list[int] = []
    flush = batcher._flush

    def counted() -> None:
        sizes.append(len(batcher.pending))
        flush()

    batcher._flush = counted  # type: ignore[method-assign]

    async def play(seed: int) -> list[int]:
        agent = policy({"epsilon": 0.2})
        assert isinstance(agent, BatchedBcAgent)
        await agent.reset(views[0], {"seed": seed})
        return [int(await agent.act(view)) for view in views]

    async def main() -> list[list[int]]:
        return list(await asyncio.gather(*(play(seed) for seed in range(3))))

    assert asyncio.run(main()) == alone
    assert sizes, "the policy was asked"
    assert set(sizes) == {3}, "the three agents' requests went as one batch"
    with pytest.raises(ValueError, match="batch must be an integer of at least 1"):
        BcPolicy({"checkpoint": str(checkpoint), "batch": 0})


def test_training_resumes_from_its_checkpoint(demos: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(tiny(demos, epochs=1), run, progress=False)
    with pytest.raises(ValueError, match="--resume"):
        train(tiny(demos, epochs=2), run, progress=False)
    with pytest.raises(ValueError, match="other settings"):
        train(tiny(demos, epochs=2, lr=5e-4), run, resume=True, progress=False)
    # The resumed run's seconds count on from the interrupted run's last line.
    first = log_rows(run)[0] | {"seconds": "1000.0"}
    with open(run / "log.csv", "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(first))
        writer.writeheader()
        writer.writerow(first)
    train(tiny(demos, epochs=2), run, resume=True, progress=False)
    rows = log_rows(run)
    assert [row["epoch"] for row in rows] == ["1", "2"]
    assert 1000.0 < float(rows[1]["seconds"]) < 1000.0 + 600
    assert torch.load(run / "ckpt.pt", weights_only=False)["epoch"] == 2


def test_a_run_resumes_only_on_the_demonstrations_it_began_with(demos: Path, tmp_path: Path) -> None:
    import zarr

    store = tmp_path / "store.zarr"
    shutil.copytree(demos, store)
    run = tmp_path / "run"
    train(tiny(store, epochs=1), run, progress=False)
    # The store exported again at the same path, with another action.
    data: Any = zarr.open_group(str(store), mode="r+")["data/action"]
    first = int(data[0])
    data[0] = (first + 1) % 6
    with pytest.raises(ValueError, match="trained on other demonstrations .* exported again or appended to"):
        train(tiny(store, epochs=2), run, resume=True, progress=False)
    assert torch.load(run / "ckpt.pt", weights_only=False)["epoch"] == 1, "the refused resume changed nothing"
    data[0] = first
    train(tiny(store, epochs=2), run, resume=True, progress=False)
    assert torch.load(run / "ckpt.pt", weights_only=False)["epoch"] == 2


def test_the_best_held_out_checkpoint_is_kept(demos: Path, tmp_path: Path) -> None:
    from esrp.train.bc import _HeldOut

    run = tmp_path / "run"
    run.mkdir()
    held_out = _HeldOut(
        tiny(demos, eval_every=1), run, run / "ckpt.pt", 128, final_eval=False, progress=False
    )
    held_out.start_log(0)

    def evaluated(epoch: int, sr: float) -> None:
        (run / "ckpt.pt").write_text(f"epoch {epoch}")
        with open(run / "eval.csv", "a") as file:
            file.write(f"{epoch},{10 * epoch},{sr},{sr},1.0,50,0,1.0\n")
        held_out.keep_best(epoch)

    evaluated(1, 0.1)
    assert (run / "best.pt").read_text() == "epoch 1"
    evaluated(2, 0.3)
    evaluated(3, 0.3)  # no better than epoch 2
    evaluated(4, 0.2)
    assert (run / "best.pt").read_text() == "epoch 2"
    assert json.loads((run / "best.json").read_text()) == {"epoch": 2, "steps": 20, "sr": 0.3}


def test_a_resumed_run_equals_an_unbroken_one(
    demos: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import esrp.train.bc as bc_module

    config = tiny(demos, epochs=2, span=4, augment_shift=4, lr_warmup_steps=1)
    unbroken = torch.load(train(config, tmp_path / "unbroken", progress=False), weights_only=False)

    class Interrupted(Exception):
        pass

    saving = bc_module.save_checkpoint  # type: ignore[attr-defined]

    def save_then_stop(path: Path, *args: object, **kwargs: object) -> None:
        saving(path, *args, **kwargs)  # type: ignore[arg-type]
        raise Interrupted

    monkeypatch.setattr(bc_module, "save_checkpoint", save_then_stop)
    with pytest.raises(Interrupted):
        train(config, tmp_path / "broken", progress=False)
    monkeypatch.undo()
    resumed = torch.load(train(config, tmp_path / "broken", resume=True, progress=False), weights_only=False)
    assert resumed["epoch"] == unbroken["epoch"] == 2
    for part in ("model", "train_model"):
        assert all(torch.equal(resumed[part][k], unbroken[part][k]) for k in unbroken[part]), part
    assert resumed["ema"]["optimization_step"] == unbroken["ema"]["optimization_step"]


def test_esrp_eval_plays_a_checkpoint(
    demos: Path, tmp_path: Path, server: esrp.LocalServer, easy_scenes: list[str]
) -> None:
    checkpoint = train(tiny(demos), tmp_path / "run", progress=False)
    out = tmp_path / "bc.jsonl"
    arguments = ["eval", "--agent", "bc", "--checkpoint", str(checkpoint), "--split", "test"]
    arguments += ["--scenes", easy_scenes[0], "--out", str(out), "--server", server.address, "--no-progress"]
    assert main(arguments) == 0
    (record,) = read_records(out).records
    assert record.agent == "bc"
    assert record.agent_config == {"checkpoint": str(checkpoint)}
    assert record.actions
    assert all(0 <= a < 6 for a in record.actions)
    other = ["eval", "--agent", "random", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "r.jsonl")]
    assert main(other) == 2, "--checkpoint only applies to bc"


def test_devices_are_checked(demos: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="device 'tpu'"):
        tiny(demos, device="tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            train(tiny(demos, device="cuda"), tmp_path / "run", progress=False)
    # A resumed run may move to another device.
    train(tiny(demos, device="cpu"), tmp_path / "cpu", progress=False)
    train(tiny(demos, device="auto", epochs=2), tmp_path / "cpu", resume=True, progress=False)
    assert [row["epoch"] for row in log_rows(tmp_path / "cpu")] == ["1", "2"]


def test_a_policy_of_smaller_views_plays_at_its_resolution(
    server: esrp.LocalServer, tmp_path: Path, easy_scenes: list[str]
) -> None:
    # Demonstrations at 48 px, the Nature-CNN encoder: the checkpoint's agent asks esrp eval's
    # episodes for 48 px views, and a config that disagrees with the store is refused.
    out = tmp_path / "small.zarr"
    arguments = ["demos", "export", "--server", server.address, "--split", "test", "--scenes", easy_scenes[0]]
    assert main([*arguments, "--resolution", "48", "--out", str(out), "--no-progress"]) == 0
    with pytest.raises(ValueError, match="hold 48 px views and the config says resolution = 128"):
        train(tiny(out, encoder="nature"), tmp_path / "wrong", progress=False)
    checkpoint = train(tiny(out, encoder="nature", resolution=48), tmp_path / "run", progress=False)
    results = tmp_path / "bc.jsonl"
    play = ["eval", "--agent", "bc", "--checkpoint", str(checkpoint), "--split", "test"]
    play += ["--scenes", easy_scenes[0], "--out", str(results), "--server", server.address, "--no-progress"]
    assert main(play) == 0
    (record,) = read_records(results).records
    assert record.actions
    # Fed 128 px views, the agent says what it needs.
    agent = BcAgent(load_policy(checkpoint), {})
    with server.client() as client, client.create_episode(easy_scenes[0]) as episode:
        assert episode.observation is not None
        seen = episode.observation
    with pytest.raises(ValueError, match="takes 48×48 views, got 128×128"):
        agent.reset(seen, {"seed": 0})
    with pytest.raises(ValueError, match="encoder 'big': one of cnn, nature, resnet18"):
        tiny(out, encoder="big")
