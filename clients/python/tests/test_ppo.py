"""ESRP-PPO smoke tests on the real server with a tiny network: one update trains with finite losses
(episodes cut by a short horizon included), the loss falls over a few steps of a fixed batch, the
LSTM state restarts at episode starts, checkpoints reload to identical outputs, training resumes,
`esrp train ppo` and `esrp eval --agent ppo` work end to end, and bad configs are refused."""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import assert_stopped_for_a_lost_server, settled_live_episodes

import esrp
from esrp.cli import main
from esrp.eval.results import read_records

torch = pytest.importorskip("torch", reason="esrp[train] is not installed")

from esrp.agents.ppo import PpoAgent, PpoConfig, PpoNet, PpoPolicy, load_network  # noqa: E402
from esrp.train._training import save_checkpoint  # noqa: E402
from esrp.train.ppo import RewardScale, gae, load_config, ppo_loss, train  # noqa: E402


def tiny(scene: str, **more: object) -> PpoConfig:
    values: dict[str, object] = {
        "split": "test",
        "scene": scene,
        "horizon": 5,
        "encoder": "nature",
        "pool": 2,
        "feature_dim": 16,
        "grasp_dim": 4,
        "hidden": 16,
        "num_envs": 2,
        "num_steps": 8,
        "minibatch_size": 8,
        "update_epochs": 2,
        "total_steps": 16,
        "threads": 1,
        "checkpoint_every": 1,
        "device": "cpu",
    }
    values.update(more)
    return PpoConfig.from_mapping(values)


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as file:
        return list(csv.DictReader(file))


def test_one_update_trains_with_finite_losses(
    tmp_path: Path, client: esrp.Client, easy_scenes: list[str]
) -> None:
    run = tmp_path / "run"
    checkpoint = train(tiny(easy_scenes[0]), run, client, progress=False)
    assert checkpoint == run / "ckpt.pt"
    assert checkpoint.is_file()
    (row,) = rows(run / "log.csv")
    assert row["update"] == "1"
    assert row["steps"] == "16"
    for key in ("policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac", "lr"):
        assert math.isfinite(float(row[key])), key
    assert 0 < float(row["entropy"]) <= math.log(6) + 1e-6
    # A horizon of 5 ends episodes inside the rollout (SAME_STEP autoreset, truncation bootstrap).
    episodes = rows(run / "episodes.csv")
    assert int(row["episodes"]) == len(episodes) >= 2
    assert all(int(e["length"]) <= 5 for e in episodes)
    assert all(int(e["length"]) == 5 for e in episodes if e["success"] == "0")
    assert settled_live_episodes(client, 0) == 0, "the env closed its episodes"
    state = torch.load(checkpoint, weights_only=False)
    assert state["kind"] == "esrp-ppo"
    assert state["update"] == 1
    assert state["steps"] == 16


def test_the_loss_falls_on_a_fixed_batch() -> None:
    config = PpoConfig.from_mapping(
        {"feature_dim": 16, "grasp_dim": 4, "hidden": 16, "pool": 2, "num_steps": 8, "minibatch_size": 8}
    )
    torch.manual_seed(0)
    network = PpoNet(config)
    generator = torch.Generator().manual_seed(1)
    steps, envs = 8, 2
    images = torch.randint(0, 256, (steps * envs, 128, 128, 3), dtype=torch.uint8, generator=generator)
    with torch.no_grad():
        ego = network.preprocess(images)
        goal = network.preprocess(images.flip(0))
    batch = {
        "ego": ego,
        "goal": goal,
        "grasping": torch.randint(0, 2, (steps * envs,), generator=generator),
        "starts": torch.zeros(steps * envs),
        "actions": torch.randint(0, 6, (steps * envs,), generator=generator),
        "logprobs": torch.full((steps * envs,), -math.log(6)),
        "advantages": torch.randn(steps * envs, generator=generator),
        "returns": torch.randn(steps * envs, generator=generator) + 2,
        "values": torch.zeros(steps * envs),
    }
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-3)
    losses = []
    for _ in range(12):
        loss, parts = ppo_loss(network, config, batch, network.initial_state(envs))
        assert all(torch.isfinite(part) for part in parts)
        optimizer.zero_grad()
        loss.backward()  # type: ignore[no-untyped-call]
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0], losses


def test_distinct_goals_with_an_index_give_the_per_step_outputs() -> None:
    config = PpoConfig.from_mapping({"feature_dim": 16, "grasp_dim": 4, "hidden": 8, "pool": 2})
    torch.manual_seed(0)
    network = PpoNet(config)
    generator = torch.Generator().manual_seed(2)
    steps, envs = 5, 3
    images = torch.randint(0, 256, (4, 128, 128, 3), dtype=torch.uint8, generator=generator)
    index = torch.tensor([[0, 1, 2], [0, 1, 2], [3, 1, 2], [3, 1, 2], [3, 1, 2]]).reshape(-1)
    ego = network.preprocess(torch.randint(0, 256, (steps * envs, 128, 128, 3), dtype=torch.uint8))
    grasping = torch.randint(0, 2, (steps * envs,), generator=generator)
    starts = torch.zeros(steps * envs)
    starts[6] = 1.0  # sub-env 0 begins its second episode (goal 3) at step 2
    goals = network.preprocess(images)
    with torch.no_grad():
        per_step = network(ego, goals[index], grasping, network.initial_state(envs), starts)
        indexed = network(ego, goals, grasping, network.initial_state(envs), starts, index)
        wrong = network(ego, goals, grasping, network.initial_state(envs), starts, torch.zeros_like(index))
    assert torch.allclose(per_step[0], indexed[0], atol=1e-6)
    assert torch.allclose(per_step[1], indexed[1], atol=1e-6)
    assert not torch.allclose(per_step[0], wrong[0], atol=1e-6), "the index chooses the goal"


def test_the_lstm_state_restarts_at_episode_starts() -> None:
    config = PpoConfig.from_mapping({"feature_dim": 16, "grasp_dim": 4, "hidden": 8})
    torch.manual_seed(0)
    network = PpoNet(config)
    steps, envs = 6, 2
    features = torch.randn(steps * envs, 8)
    state = (torch.randn(1, envs, 8), torch.randn(1, envs, 8))
    starts = torch.zeros(steps, envs)
    starts[3, 0] = 1.0  # sub-env 0 begins a new episode at step 3
    with torch.no_grad():
        out, _ = network.recurrent(features, state, starts.reshape(-1))
        tail = features.reshape(steps, envs, 8)[3:, :1].reshape(-1, 8)
        fresh, _ = network.recurrent(tail, network.initial_state(1), torch.zeros(3))
        carried, _ = network.recurrent(features, state, torch.zeros(steps * envs))
    out = out.reshape(steps, envs, 8)
    carried = carried.reshape(steps, envs, 8)
    assert torch.allclose(out[3:, 0], fresh.reshape(3, 8), atol=1e-6), "a start zeroes the state"
    assert torch.allclose(out[:3], carried[:3])
    assert torch.allclose(out[:, 1], carried[:, 1])
    assert not torch.allclose(out[3:, 0], carried[3:, 0]), "without a start the state carries over"


def test_a_checkpoint_reloads_to_identical_outputs(
    tmp_path: Path, client: esrp.Client, easy_scenes: list[str]
) -> None:
    config = tiny(easy_scenes[0])
    torch.manual_seed(3)
    network = PpoNet(config)
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, "esrp-ppo", network, torch.optim.Adam(network.parameters()), update=1, steps=16)
    loaded = load_network(path)
    with client.create_episode(easy_scenes[0]) as episode:
        first = episode.observation
    assert first is not None
    ego = network.preprocess(torch.from_numpy(np.array(first.ego_rgb))[None])
    goal = network.preprocess(torch.from_numpy(np.array(first.goal_rgb))[None])
    grasping = torch.tensor([int(first.grasping)])
    with torch.no_grad():
        expected = network(ego, goal, grasping, network.initial_state(1), torch.zeros(1))
        got = loaded(ego, goal, grasping, loaded.initial_state(1), torch.zeros(1))
    assert torch.equal(expected[0], got[0])
    assert torch.equal(expected[1], got[1])

    def actions(seed: int) -> list[int]:
        agent = PpoAgent(loaded, {})
        agent.reset(first, {"seed": seed})
        return [int(agent.act(first)) for _ in range(12)]

    assert actions(7) == actions(7), "same seed, same actions (the state restarts at reset)"
    assert all(0 <= a < 6 for a in actions(7))
    greedy = PpoAgent(loaded, {"deterministic": True})
    with pytest.raises(RuntimeError, match="before reset"):
        greedy.act(first)
    torch.save({"kind": "esrp-bc"}, tmp_path / "bc.pt")
    with pytest.raises(ValueError, match="not an ESRP-PPO checkpoint"):
        load_network(tmp_path / "bc.pt")


def test_training_resumes_from_its_checkpoint(
    tmp_path: Path, client: esrp.Client, easy_scenes: list[str]
) -> None:
    run = tmp_path / "run"
    train(tiny(easy_scenes[0]), run, client, progress=False)
    with pytest.raises(ValueError, match="--resume"):
        train(tiny(easy_scenes[0], total_steps=32), run, client, progress=False)
    with pytest.raises(ValueError, match="other settings"):
        train(tiny(easy_scenes[0], total_steps=32, lr=1e-3), run, client, resume=True, progress=False)
    # A log written before the timing columns existed is carried over under today's columns.
    # Its seconds are made large: the resumed run's count on from them.
    old = [
        {k: v for k, v in row.items() if not k.endswith("_seconds")} | {"seconds": "1000"}
        for row in rows(run / "log.csv")
    ]
    with open(run / "log.csv", "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(old[0]))
        writer.writeheader()
        writer.writerows(old)
    train(tiny(easy_scenes[0], total_steps=32), run, client, resume=True, progress=False)
    log = rows(run / "log.csv")
    assert [row["update"] for row in log] == ["1", "2"]
    assert [row["steps"] for row in log] == ["16", "32"]
    assert log[0]["env_seconds"] == ""
    assert log[0]["entropy"] == old[0]["entropy"]
    assert 1000.0 < float(log[1]["seconds"]) < 1000.0 + 600
    # Where an update's time went: the environment, the actions, the learning.
    parts = [float(log[1][k]) for k in ("env_seconds", "act_seconds", "learn_seconds")]
    assert all(part > 0 for part in parts)
    assert sum(parts) == pytest.approx(16 / float(log[1]["steps_per_second"]), rel=1e-3)
    state = torch.load(run / "ckpt.pt", weights_only=False)
    assert (state["update"], state["steps"]) == (2, 32)


def test_stop_at_ends_early_with_a_checkpoint_and_keeps_the_schedule(
    tmp_path: Path, client: esrp.Client, easy_scenes: list[str]
) -> None:
    config = tiny(easy_scenes[0], total_steps=48, checkpoint_every=10)
    run = tmp_path / "run"
    with pytest.raises(ValueError, match="stop_at must be at least 1"):
        train(config, run, client, progress=False, stop_at=0)
    train(config, run, client, progress=False, stop_at=20)
    steps = [row["steps"] for row in rows(run / "log.csv")]
    assert steps == ["16", "32"], "stops after the update that reaches 20"
    state = torch.load(run / "ckpt.pt", weights_only=False)
    assert (state["update"], state["steps"]) == (2, 32), "a checkpoint though checkpoint_every is 10"
    train(config, run, client, resume=True, progress=False, stop_at=32)  # reached already: nothing runs
    assert len(rows(run / "log.csv")) == 2
    train(config, run, client, resume=True, progress=False)
    log = rows(run / "log.csv")
    assert [row["update"] for row in log] == ["1", "2", "3"]
    # The learning rate anneals over total_steps, stopped or not.
    assert [float(row["lr"]) for row in log] == pytest.approx([config.lr * (1 - u / 3) for u in range(3)])


def test_esrp_train_and_eval_end_to_end(
    tmp_path: Path, server: esrp.LocalServer, easy_scenes: list[str]
) -> None:
    config = tmp_path / "ppo.toml"
    config.write_text(
        "[ppo]\n"
        f'split = "test"\nscene = "{easy_scenes[0]}"\nhorizon = 5\nresolution = 64\nfeature_dim = 16\n'
        "grasp_dim = 4\nhidden = 16\nnum_envs = 2\nnum_steps = 8\nminibatch_size = 8\n"
        'total_steps = 16\nthreads = 1\ndevice = "cpu"\n',
        encoding="utf-8",
    )
    run = tmp_path / "run"
    arguments = ["train", "ppo", "--config", str(config), "--out", str(run), "--server", server.address]
    assert main([*arguments, "--no-progress"]) == 0
    assert load_config(config).scene == easy_scenes[0]
    checkpoint = run / "ckpt.pt"
    # A 64 px policy: esrp eval creates its episodes at the network's resolution.
    assert PpoPolicy({"checkpoint": str(checkpoint)}).sensors.resolution == 64
    evaluation = ["eval", "--agent", "ppo", "--checkpoint", str(checkpoint), "--split", "test"]
    evaluation += ["--scenes", easy_scenes[0], "--server", server.address, "--no-progress"]
    assert main([*evaluation, "--out", str(tmp_path / "ppo.jsonl")]) == 0
    (record,) = read_records(tmp_path / "ppo.jsonl").records
    assert record.agent == "ppo"
    assert record.agent_config == {"checkpoint": str(checkpoint)}
    assert record.actions
    assert all(0 <= a < 6 for a in record.actions)
    # The same checkpoint and seed play the same episode again.
    assert main([*evaluation, "--out", str(tmp_path / "again.jsonl")]) == 0
    assert read_records(tmp_path / "again.jsonl").records[0].actions == record.actions


def test_a_server_gone_during_the_run_stops_it_in_one_line(
    tmp_path: Path,
    easy_scenes: list[str],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The server stops after the first update: gRPC's `UNAVAILABLE: ...` was the message, exit
    status 2; now one line naming the address and how to go on, exit status 3 (as `esrp eval`)."""
    from esrp.train import ppo

    config = tmp_path / "ppo.toml"
    config.write_text(
        "[ppo]\n"
        f'split = "test"\nscene = "{easy_scenes[0]}"\nhorizon = 5\nresolution = 64\nfeature_dim = 16\n'
        "grasp_dim = 4\nhidden = 16\nnum_envs = 2\nnum_steps = 8\nminibatch_size = 8\n"
        'total_steps = 64\ncheckpoint_every = 1\nthreads = 1\ndevice = "cpu"\n',
        encoding="utf-8",
    )
    log = ppo._log
    run = tmp_path / "run"
    with esrp.LocalServer() as own:
        address = own.address

        def log_then_stop(*args: Any) -> None:  # noqa: ANN401
            log(*args)
            own.stop()

        monkeypatch.setattr(ppo, "_log", log_then_stop)
        arguments = ["train", "ppo", "--config", str(config), "--out", str(run), "--server", address]
        assert main([*arguments, "--no-progress"]) == 3
    err = capsys.readouterr().err
    assert_stopped_for_a_lost_server(err, "esrp train ppo", address)
    assert (run / "ckpt.pt").exists()


def test_bad_configs_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match="multiple of num_steps"):
        PpoConfig.from_mapping({"num_steps": 64, "minibatch_size": 96})
    with pytest.raises(ValueError, match="unknown ppo settings"):
        PpoConfig.from_mapping({"learning_rate": 1e-3})
    with pytest.raises(ValueError, match="encoder"):
        PpoConfig.from_mapping({"encoder": "vit"})
    with pytest.raises(ValueError, match="pool"):
        PpoConfig.from_mapping({"pool": 3})
    with pytest.raises(ValueError, match="reward terms"):
        PpoConfig.from_mapping({"reward": {"bonus": 1.0}})
    config = tmp_path / "bad.toml"
    config.write_text("[ppo]\nnum_envs = 3\nnum_steps = 64\nminibatch_size = 128\n", encoding="utf-8")
    assert main(["train", "ppo", "--config", str(config), "--out", str(tmp_path / "run")]) == 2
    assert "must be a multiple of minibatch_size" in capsys.readouterr().err
    assert not (tmp_path / "run").exists(), "nothing is started or written for a bad config"
    with pytest.raises(ValueError, match="needs --checkpoint"):
        PpoPolicy({})
    with pytest.raises(ValueError, match="no checkpoint at"):
        PpoPolicy({"checkpoint": str(tmp_path / "missing.pt")})


def test_the_shipped_configs_load() -> None:
    configs = sorted((Path(__file__).parent.parent / "configs").glob("ppo-*.toml"))
    assert len(configs) >= 2
    loaded = {path.stem: load_config(path) for path in configs}
    paper = loaded["ppo-paper"]
    assert (paper.lr, paper.vf_coef, paper.batch_size, paper.minibatch_size) == (1.5e-4, 5e-3, 2048, 64)
    assert (paper.num_steps, paper.total_steps) == (64, 6_000_000)


def test_advantages_stop_at_episode_starts() -> None:
    # One sub-env; a new episode begins at step 2. By hand (γ = 0.9, λ = 0.8):
    # t=2: δ = 3 + 0.9·1.0 − 0.5 = 3.4;  t=1: δ = 2 − 0.5 = 1.5 (the next step starts an episode)
    # t=0: δ = 1 + 0.9·0.5 − 0.5 = 0.95, A = 0.95 + 0.9·0.8·1.5 = 2.03.
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.full((3, 1), 0.5)
    starts = torch.tensor([[1.0], [0.0], [1.0]])
    advantages, returns = gae(rewards, values, starts, torch.tensor([1.0]), torch.tensor([0.0]), 0.9, 0.8)
    assert torch.allclose(advantages[:, 0], torch.tensor([2.03, 1.5, 3.4]))
    assert torch.allclose(returns, advantages + values)
    # When the step after the rollout starts an episode, its value is not used.
    cut, _ = gae(rewards, values, starts, torch.tensor([100.0]), torch.tensor([1.0]), 0.9, 0.8)
    assert torch.allclose(cut[2, 0], torch.tensor(2.5))


def test_training_is_deterministic(tmp_path: Path, client: esrp.Client, easy_scenes: list[str]) -> None:
    config = tiny(easy_scenes[0], total_steps=32)
    runs = [tmp_path / "a", tmp_path / "b"]
    for run in runs:
        train(config, run, client, progress=False)
    timing = {"steps_per_second", "seconds", "env_seconds", "act_seconds", "learn_seconds"}
    logs = [[{k: v for k, v in r.items() if k not in timing} for r in rows(run / "log.csv")] for run in runs]
    assert logs[0] == logs[1]
    assert (runs[0] / "episodes.csv").read_text() == (runs[1] / "episodes.csv").read_text()
    models = [torch.load(run / "ckpt.pt", weights_only=False)["model"] for run in runs]
    assert all(torch.equal(models[0][key], models[1][key]) for key in models[0])


def test_rewards_are_scaled_by_the_running_deviation_of_the_discounted_return() -> None:
    scale = RewardScale(gamma=0.5, num_envs=2)
    first = scale(np.array([1.0, 0.0]), np.array([False, True]))
    # The returns so far are [1, 0]: their running deviation is 0.5.
    assert first == pytest.approx([1.0 / 0.5, 0.0], rel=1e-3)  # (the statistics start from a tiny prior)
    second = scale(np.array([1.0, 2.0]), np.array([False, False]))
    # Returns [1.5, 2] (the second sub-env's episode began anew); the deviation over all four.
    deviation = np.std([1.0, 0.0, 1.5, 2.0])
    assert second == pytest.approx(np.array([1.0, 2.0]) / deviation, rel=1e-3)
    restored = RewardScale(gamma=0.5, num_envs=2)
    restored.load(scale.state())
    assert restored.state() == scale.state()


def test_batch_normalised_advantages_are_left_as_they_are_in_each_minibatch() -> None:
    config = PpoConfig.from_mapping(
        {"feature_dim": 16, "grasp_dim": 4, "hidden": 16, "pool": 2, "num_steps": 4, "minibatch_size": 4}
    )
    torch.manual_seed(0)
    network = PpoNet(config)
    images = torch.randint(
        0, 256, (4, 128, 128, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(3)
    )
    with torch.no_grad():
        ego = network.preprocess(images)
    batch = {
        "ego": ego,
        "goal": ego.flip(0),
        "grasping": torch.zeros(4, dtype=torch.long),
        "starts": torch.zeros(4),
        "actions": torch.tensor([0, 1, 2, 3]),
        "logprobs": torch.full((4,), -math.log(6)),
        "advantages": torch.tensor([0.001, -0.002, 0.0005, 0.0]),
        "returns": torch.zeros(4),
        "values": torch.zeros(4),
    }
    state = network.initial_state(1)

    def policy_gradient(scope_config: PpoConfig) -> float:
        network.zero_grad()
        ppo_loss(network, scope_config, batch, state)[1][0].backward()  # type: ignore[no-untyped-call]
        return sum(float(p.grad.norm()) for p in network.actor.parameters() if p.grad is not None)

    per_minibatch = policy_gradient(config)
    as_given = policy_gradient(dataclasses.replace(config, norm_adv_scope="batch"))
    raw = policy_gradient(dataclasses.replace(config, norm_adv=False))
    # Tiny advantages: a minibatch's normalisation blows them up; the batch scope leaves them be.
    assert as_given == pytest.approx(raw)
    assert per_minibatch > 100 * as_given
    with pytest.raises(ValueError, match="norm_adv_scope"):
        PpoConfig.from_mapping({"norm_adv_scope": "epoch"})


def test_a_run_with_scaled_rewards_resumes_with_its_statistics(
    tmp_path: Path, client: esrp.Client, easy_scenes: list[str]
) -> None:
    config = tiny(easy_scenes[0], total_steps=32, norm_reward=True, norm_adv_scope="batch")
    unbroken = torch.load(train(config, tmp_path / "a", client, progress=False), weights_only=False)
    train(config, tmp_path / "b", client, progress=False, stop_at=16)
    first = torch.load(tmp_path / "b" / "ckpt.pt", weights_only=False)
    assert first["reward_scale"]["count"] > 1
    resumed = torch.load(
        train(config, tmp_path / "b", client, resume=True, progress=False), weights_only=False
    )
    assert resumed["reward_scale"]["count"] == pytest.approx(unbroken["reward_scale"]["count"])
    assert all(math.isfinite(float(row["value_loss"])) for row in rows(tmp_path / "b" / "log.csv"))
