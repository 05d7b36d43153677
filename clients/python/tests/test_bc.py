"""ESRP-BC smoke tests on tiny data (the demonstrations of one easy test scene, a tiny model): an
epoch trains with finite losses, the loss falls over a few steps of a fixed batch, checkpoints
reload to identical actions, batched agents act as agents alone do, training resumes, and `esrp
eval --agent bc` plays a checkpoint."""

from __future__ import annotations

import asyncio
import csv
import dataclasses
import math
from pathlib import Path

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
    schedulers,
)
from esrp.train.bc import DemoWindows, train  # noqa: E402


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


def test_the_loss_falls_on_a_fixed_batch(demos: Path) -> None:
    config = tiny(demos)
    torch.manual_seed(0)
    model = DiffusionPolicy(config)
    scheduler, _ = schedulers(config)
    windows = DemoWindows(demos, config.n_obs, config.horizon)
    batch = windows.batch(np.arange(len(windows)))
    assert batch["ego"].shape[1:] == (4, 128, 128, 3)
    assert batch["actions"].shape[1:] == (8,)
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


def test_windows_pad_as_diffusion_policy(demos: Path) -> None:
    windows = DemoWindows(demos, 4, 8)
    batch = windows.batch(np.array([0, len(windows) - 1]))
    ego = batch["ego"].numpy()
    # The first step's history is its own view, repeated; the last step's future, its own action.
    assert all(np.array_equal(ego[0, i], ego[0, 3]) for i in range(3))
    assert np.all(batch["actions"][1].numpy() == windows.actions[-1])


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
    train(tiny(demos, epochs=2), run, resume=True, progress=False)
    rows = log_rows(run)
    assert [row["epoch"] for row in rows] == ["1", "2"]
    assert torch.load(run / "ckpt.pt", weights_only=False)["epoch"] == 2


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
