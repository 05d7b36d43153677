"""What `esrp train` and the learned agents make of bad input, without training: every setting of
the wrong kind or out of range is refused by name; a damaged checkpoint file is named, not a
traceback; an agent's unknown or mistyped setting is refused; a config of another command says so;
a resume says which settings differ, and that there is nothing to resume; a loss that diverges is
one line; and a checkpoint being written when a signal comes is finished first."""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path

import pytest

import esrp
from esrp import _signals
from esrp.cli import main

torch = pytest.importorskip("torch", reason="esrp[train] is not installed")

from esrp.agents.bc import BcConfig, BcPolicy, load_policy  # noqa: E402
from esrp.agents.ppo import PpoConfig, PpoNet, PpoPolicy, load_network  # noqa: E402
from esrp.train import ppo_bc  # noqa: E402
from esrp.train._config import read_table  # noqa: E402
from esrp.train._training import run_folder, save_checkpoint, settings_differences  # noqa: E402


@pytest.mark.parametrize(
    ("values", "said"),
    [
        ({"epochs": -3}, "epochs must be at least 1"),
        ({"batch_size": 0}, "batch_size must be at least 1"),
        ({"checkpoint_every": 0}, "checkpoint_every must be at least 1"),
        ({"epochs": 2.5}, "epochs must be an integer"),
        ({"epochs": "2"}, "epochs must be an integer"),
        ({"epochs": True}, "epochs must be an integer"),
        ({"lr": "abc"}, "lr must be a number"),
        ({"lr": -1e-4}, "lr must be at least 0"),
        ({"lr": float("nan")}, "lr must be a number"),
        ({"threads": -2}, "threads must be at least 0"),
        ({"epsilon": 5}, "epsilon must be from 0 to 1"),
        ({"unet_channels": 5}, "unet_channels must be a list of integers"),
        ({"unet_channels": [16, 0]}, "unet_channels must be a list of integers"),
        # Models that would fail mid-training (a traceback) or play nowhere, refused at the start.
        ({"unet_channels": [12, 24]}, "unet_channels must be a list of integers, each a multiple of 8"),
        ({"kernel_size": 4}, "kernel_size must be odd"),
        ({"ddim_steps": 100}, r"ddim_steps \(100\) must be at most diffusion_steps \(50\)"),
        ({"eval_limit": 0}, "eval_limit must be at least 1"),
        ({"ema": 1}, "ema must be true or false"),
    ],
)
def test_bc_settings_of_the_wrong_kind_or_out_of_range_are_refused_by_name(
    values: dict[str, object], said: str
) -> None:
    with pytest.raises(ValueError, match=said):
        BcConfig.from_mapping(values)


@pytest.mark.parametrize(
    ("values", "said"),
    [
        ({"lr": "abc"}, "lr must be a number"),
        ({"ent_coef": "x"}, "ent_coef must be a number"),
        ({"clip_coef": -1.0}, "clip_coef must be at least 0"),
        ({"num_envs": "2"}, "num_envs must be an integer"),
        ({"num_envs": 2.5}, "num_envs must be an integer"),
        ({"max_grad_norm": 0}, "max_grad_norm must be above 0"),
        ({"scene": 3}, "scene must be a string"),
    ],
)
def test_ppo_settings_of_the_wrong_kind_or_out_of_range_are_refused_by_name(
    values: dict[str, object], said: str
) -> None:
    with pytest.raises(ValueError, match=said):
        PpoConfig.from_mapping(values)


def test_imitation_settings_are_checked_against_the_network(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="epochs must be an integer"):
        ppo_bc.ImitationConfig.from_mapping({"demos": "x", "epochs": True})
    config = tmp_path / "shift.toml"
    config.write_text('[ppo]\nresolution = 64\n[ppo_bc]\ndemos = "x"\naugment_shift = 400\n')
    with pytest.raises(ValueError, match="augment_shift 400: less than half the network's resolution"):
        ppo_bc.load_configs(config)


def test_a_config_of_another_command_says_so(tmp_path: Path) -> None:
    config = tmp_path / "ppo.toml"
    config.write_text("[ppo]\nnum_envs = 2\n")
    with pytest.raises(ValueError, match=r"has no \[bc\] table \(it has \[ppo\]\)"):
        read_table(config, "bc")
    flat = tmp_path / "flat.toml"
    flat.write_text("epochs = 2\n")
    assert read_table(flat, "bc") == {"epochs": 2}  # a file of one table's keys is that table


def _tiny_ppo(path: Path) -> Path:
    config = PpoConfig.from_mapping({"resolution": 48, "feature_dim": 8, "grasp_dim": 2, "hidden": 8})
    network = PpoNet(config)
    optimizer = torch.optim.Adam(network.parameters())
    save_checkpoint(path, "esrp-ppo", network, optimizer, update=0, steps=0)
    return path


def test_damaged_checkpoints_are_named_not_tracebacks(tmp_path: Path) -> None:
    whole = _tiny_ppo(tmp_path / "whole.pt")
    assert not (tmp_path / "whole.partial").exists()
    load_network(whole)  # the real one loads
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    cut = tmp_path / "cut.pt"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    text = tmp_path / "text.pt"
    text.write_text("garbage\n")
    for damaged in (empty, cut, text):
        with pytest.raises(ValueError, match=f"{damaged} is not a readable checkpoint"):
            load_network(damaged)
        with pytest.raises(ValueError, match=f"{damaged} is not a readable checkpoint"):
            load_policy(damaged)
    bare = tmp_path / "bare.pt"
    torch.save({"kind": "esrp-ppo"}, bare)
    with pytest.raises(ValueError, match="is not an ESRP-PPO checkpoint"):
        load_network(bare)
    with pytest.raises(ValueError, match="is not an ESRP-BC checkpoint"):
        load_policy(whole)


def test_an_agents_unknown_or_mistyped_setting_is_refused(tmp_path: Path) -> None:
    checkpoint = str(_tiny_ppo(tmp_path / "ppo.pt"))
    with pytest.raises(ValueError, match="the ppo agent has no setting determinstic"):
        PpoPolicy({"checkpoint": checkpoint, "determinstic": True})
    with pytest.raises(ValueError, match="the ppo agent's deterministic must be true or false"):
        PpoPolicy({"checkpoint": checkpoint, "deterministic": "yes"})
    PpoPolicy({"checkpoint": checkpoint, "deterministic": True, "threads": 1})
    with pytest.raises(ValueError, match="the bc agent has no setting epsilo"):
        BcPolicy({"checkpoint": checkpoint, "epsilo": 0})
    with pytest.raises(ValueError, match="the bc agent's epsilon must be a number from 0 to 1"):
        BcPolicy({"checkpoint": checkpoint, "epsilon": 5})


def test_a_resume_says_which_settings_differ_and_that_there_is_nothing_to_resume(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    differences = settings_differences({"lr": 3e-4, "epochs": 5}, {"lr": 1e-3, "epochs": 9}, {"epochs"})
    assert differences == ["lr: 0.0003 → 0.001"]
    run_folder(tmp_path / "new", resume=True)
    assert (
        f"no checkpoint in {tmp_path / 'new'} to resume: starting a new run there" in capsys.readouterr().err
    )
    # A DAgger run's folder is not a plain run's (a forgotten --dagger on its --resume).
    (tmp_path / "dagger").mkdir()
    (tmp_path / "dagger" / "state.json").write_text("{}")
    with pytest.raises(ValueError, match=r"holds a DAgger run \(state.json\)"):
        run_folder(tmp_path / "dagger", resume=True)


def test_a_run_refused_at_its_start_leaves_no_folder(
    server: esrp.LocalServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every `esrp train` made its run folder (and its parents) before reading the demonstrations
    (bc, ppo-bc: config.json and log.csv in it too) or creating its episodes (ppo), and a run
    refused there left it behind: a rerun with the mistake fixed was then told the folder is taken,
    or wrote into a stale one. A folder that was there before is left as it was."""
    missing = tmp_path / "missing.zarr"
    configs = {
        "bc": f'[bc]\ndemos = "{missing}"\n',
        "dagger": f'[bc]\ndemos = "{missing}"\n[dagger]\niterations = 1\n',
        "ppo-bc": f'[ppo]\nresolution = 64\n[ppo_bc]\ndemos = "{missing}"\n',
        "ppo": '[ppo]\nnum_envs = 1\nscene = "esrp-bench-v2/no-such-scene"\n',
    }
    commands = {
        "bc": (["bc"], str(missing)),
        "dagger": (["bc", "--dagger"], f"cannot open the demonstration store {missing}"),
        "ppo-bc": (["ppo-bc"], str(missing)),
        "ppo": (["ppo", "--server", server.address], 'no scene "esrp-bench-v2/no-such-scene"'),
    }
    for name, (command, said) in commands.items():
        config = tmp_path / f"{name}.toml"
        config.write_text(configs[name], encoding="utf-8")
        runs = tmp_path / "runs"
        arguments = ["train", *command, "--config", str(config), "--no-progress"]
        assert main([*arguments, "--out", str(runs / name)]) == 2, name
        err = capsys.readouterr().err
        assert said in err, err
        assert err.count("\n") == 1, err
        assert not runs.exists(), f"esrp train {name} left {sorted(runs.rglob('*'))}"
        # A folder of the user's (--resume of a folder without a run, an empty one) is kept whole.
        for kept, resume in ((tmp_path / "mine", ["--resume"]), (tmp_path / "empty", [])):
            kept.mkdir(exist_ok=True)
            if resume:
                (kept / "notes.txt").write_text("mine\n")
            assert main([*arguments, *resume, "--out", str(kept)]) == 2, name
            capsys.readouterr()
            assert sorted(p.name for p in kept.iterdir()) == (["notes.txt"] if resume else []), name


def test_a_diverging_loss_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def diverge(*args: object, **kwargs: object) -> Path:
        raise FloatingPointError("epoch 1: the loss is nan")  # what the trainers raise

    config = tmp_path / "ppobc.toml"
    config.write_text('[ppo]\nresolution = 64\n[ppo_bc]\ndemos = "x"\n')
    monkeypatch.setattr(ppo_bc, "train", diverge)
    assert main(["train", "ppo-bc", "--config", str(config), "--out", str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err
    assert "training diverged: epoch 1: the loss is nan (the last checkpoint is kept" in err, err
    assert len(err.strip().splitlines()) == 1, err


def test_a_checkpoint_being_written_when_a_signal_comes_is_finished_first(tmp_path: Path) -> None:
    # A network whose save takes a while (an LSTM of 2,048 units: about 70 MB), and a SIGINT sent
    # 20 ms into it: the interrupt comes once the checkpoint is in place.
    config = PpoConfig.from_mapping({"resolution": 48, "feature_dim": 8, "grasp_dim": 2, "hidden": 2048})
    network = PpoNet(config)
    optimizer = torch.optim.Adam(network.parameters())
    path = tmp_path / "ckpt.pt"
    timer = threading.Timer(0.02, os.kill, (os.getpid(), signal.SIGINT))

    def save_while_signalled() -> None:
        with _signals.stop_on_signals("test"):
            timer.start()
            save_checkpoint(path, "esrp-ppo", network, optimizer, update=1, steps=8)
            timer.join()

    with pytest.raises(KeyboardInterrupt):
        save_while_signalled()
    assert torch.load(path, weights_only=False)["update"] == 1
    assert not path.with_suffix(".partial").exists()
