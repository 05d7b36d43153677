"""`esrp eval --ray` on a Ray cluster on this machine (a head and two worker nodes): two actors,
each with its own spawned esrp-server, play 40 test scenes with the expert and the random agents;
every episode is recorded exactly once and its metrics and actions are those of the same
evaluation run locally without Ray. The same when
one actor's server is killed (SIGKILL) mid-run: Ray restarts the actor with a new server and its
unfinished episodes are played again from their start.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import esrp
from esrp.cli import main
from esrp.eval.evaluation import EvalSettings, run_eval
from esrp.eval.results import EpisodeRecord, read_records

ray = pytest.importorskip("ray", reason="esrp[ray] is not installed")

SCENES = 40

# What must not differ between a local and a Ray run of the same evaluation (not the wall times,
# the finishing times or the order of the file).
SAME: tuple[str, ...] = ("agent", "agent_config", "seed", "success", "osr", "rdr", "stage", "placed")
SAME += ("steps", "end", "actions")


@pytest.fixture(scope="module")
def ray_cluster() -> Iterator[None]:
    """A Ray cluster on this machine for this module: a head that runs no tasks (the driver's, as
    on Kubernetes) and two worker nodes of one CPU each, so each actor and its server live on a
    node of their own; no dashboard.
    """
    from ray.cluster_utils import Cluster

    store = 100 * 1024 * 1024
    # A node's start can time out on a loaded 2-core machine: one more try before giving up.
    for attempt in range(2):
        cluster = None
        try:
            cluster = Cluster(
                initialize_head=True,
                head_node_args={"num_cpus": 0, "include_dashboard": False, "object_store_memory": store},
            )
            for _ in range(2):
                cluster.add_node(num_cpus=1, object_store_memory=store)
            ray.init(address=cluster.address, log_to_driver=False)
            break
        except Exception as error:  # noqa: BLE001 - the engine cannot start on this machine.
            ray.shutdown()
            if cluster is not None:
                cluster.shutdown()  # type: ignore[no-untyped-call]
            if attempt == 1:
                pytest.skip(f"a local Ray cluster cannot start here (twice): {error}")
    assert cluster is not None
    yield
    ray.shutdown()
    cluster.shutdown()  # type: ignore[no-untyped-call]


def by_scene(path: Path) -> dict[str, EpisodeRecord]:
    records = read_records(path).records
    ids = [r.scene_id for r in records]
    assert len(ids) == len(set(ids)), "an episode was recorded twice"
    return {r.scene_id: r for r in records}


def assert_same(local: dict[str, EpisodeRecord], distributed: dict[str, EpisodeRecord]) -> None:
    assert sorted(distributed) == sorted(local), "the Ray run recorded other episodes"
    for scene_id, record in local.items():
        other = distributed[scene_id]
        for name in SAME:
            assert getattr(other, name) == getattr(record, name), f"{scene_id}: {name} differs"


@pytest.fixture(scope="module")
def local_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, EpisodeRecord]]:
    """The expert's and the random agent's records of the first 40 test scenes, run locally."""
    folder = tmp_path_factory.mktemp("local")
    runs = {}
    for agent in ("expert", "random"):
        out = folder / f"{agent}.jsonl"
        settings = EvalSettings(agent=agent, out=out, split="test", limit=SCENES, progress=False)
        outcome = run_eval(settings)
        assert not outcome.failed
        runs[agent] = by_scene(out)
        assert len(runs[agent]) == SCENES
    return runs


def ray_eval(out: Path, agent: str, *more: str) -> int:
    """`esrp eval --ray` in this process (the module's Ray cluster): 2 actors, spawned servers."""
    return main(
        [
            "eval",
            "--agent",
            agent,
            "--split",
            "test",
            "--limit",
            str(SCENES),
            "--out",
            str(out),
            "--no-progress",
            "--ray",
            "--spawn-servers",
            "2",
            "--episodes-in-flight",
            "4",
            *more,
        ]
    )


@pytest.mark.usefixtures("ray_cluster")
@pytest.mark.parametrize("agent", ["expert", "random"])
def test_a_ray_run_records_every_episode_once_as_a_local_run(
    agent: str, local_runs: dict[str, dict[str, EpisodeRecord]], tmp_path: Path
) -> None:
    out = tmp_path / f"{agent}.jsonl"
    assert ray_eval(out, agent) == 0
    assert_same(local_runs[agent], by_scene(out))
    # Resuming a complete file plays nothing again.
    before = out.read_bytes()
    assert ray_eval(out, agent) == 0
    assert out.read_bytes() == before


def actor_servers() -> list[int]:
    """The pids of the esrp-server processes whose parent is a Ray actor of the evaluation."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            command = (entry / "cmdline").read_bytes().split(b"\0")
            if not command[0].endswith(b"esrp-server"):
                continue
            parent = (entry / "stat").read_text().rsplit(")", 1)[1].split()[1]
            parent_command = Path(f"/proc/{parent}/cmdline").read_bytes()
        except (OSError, IndexError):
            continue
        if b"EvalActor" in parent_command:
            pids.append(int(entry.name))
    return pids


@pytest.mark.usefixtures("ray_cluster")
def test_a_server_killed_mid_run_changes_nothing(
    local_runs: dict[str, dict[str, EpisodeRecord]], tmp_path: Path
) -> None:
    # The random agent's episodes run to the horizon: the run lasts long enough to be interrupted.
    out = tmp_path / "random.jsonl"
    killed: list[int] = []

    def kill_one_when_started() -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            lines = out.read_bytes().count(b"\n") if out.exists() else 0
            servers = actor_servers()
            if lines >= 3 and len(servers) == 2:
                os.kill(servers[0], signal.SIGKILL)
                killed.append(servers[0])
                return
            time.sleep(0.01)

    killer = threading.Thread(target=kill_one_when_started)
    killer.start()
    status = ray_eval(out, "random", "--episodes-in-flight", "2")
    killer.join()
    assert killed, "no server was killed: the run ended before 3 episodes were recorded"
    assert status == 0
    assert_same(local_runs["random"], by_scene(out))


@pytest.mark.usefixtures("ray_cluster")
def test_actors_pinned_to_given_servers(
    server: esrp.LocalServer, local_runs: dict[str, dict[str, EpisodeRecord]], tmp_path: Path
) -> None:
    out = tmp_path / "expert.jsonl"
    with esrp.LocalServer() as other:
        servers = f"{server.address},{other.address}"
        arguments = ["eval", "--agent", "expert", "--split", "test", "--limit", "10", "--out", str(out)]
        status = main([*arguments, "--no-progress", "--ray", "--servers", servers])
    assert status == 0
    pinned = by_scene(out)
    assert len(pinned) == 10
    assert_same({scene: local_runs["expert"][scene] for scene in pinned}, pinned)


def test_ray_flags_need_ray(tmp_path: Path, capsys: Any) -> None:  # noqa: ANN401
    out = tmp_path / "x.jsonl"
    assert main(["eval", "--agent", "expert", "--out", str(out), "--servers", "127.0.0.1:1"]) == 2
    assert "only apply with --ray" in capsys.readouterr().err
    assert not out.exists()


def test_a_ray_address_with_no_cluster_says_what_to_do(
    tmp_path: Path,
    capsys: Any,  # noqa: ANN401
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Ray's own message named its `--address` flag, which esrp eval does not have. No cluster
    is made absent here (other tests' clusters come and go): `ray.init` fails as Ray's does
    where none runs."""

    def no_cluster(address: str | None = None, **_: Any) -> None:  # noqa: ANN401
        raise ConnectionError(
            "Could not find any running Ray instance. Please specify the one to connect to by setting "
            "`--address` flag or `RAY_ADDRESS` environment variable."
        )

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", no_cluster)
    out = tmp_path / "x.jsonl"
    assert main(["eval", "--agent", "expert", "--out", str(out), "--ray", "auto"]) == 2
    err = capsys.readouterr().err
    assert "--ray auto: no Ray cluster could be reached there" in err, err
    assert "--ray local" in err, err


PRINTING_AGENT = """
import sys
import time


class Printer:
    def reset(self, observation, info):
        print("reset on", info["scene_id"], flush=True)
        print("reset on", info["scene_id"], file=sys.stderr, flush=True)
        time.sleep(3)  # Ray forwards the lines to the driver meanwhile

    def act(self, observation):
        return None


def make(config):
    return Printer()
"""


def test_worker_lines_reach_a_log_file_without_colour_codes(tmp_path: Path) -> None:
    """Ray printed the workers' lines on the driver's stderr with a coloured prefix even when stderr
    was a file: `esrp eval --ray 2> eval.log` held ANSI codes."""
    (tmp_path / "printing.py").write_text(PRINTING_AGENT)
    log, out = tmp_path / "eval.log", tmp_path / "eval.out"
    arguments = ["eval", "--agent", "printing:make", "--split", "test", "--limit", "2"]
    arguments += ["--out", str(tmp_path / "p.jsonl"), "--no-progress", "--ray", "--spawn-servers", "1"]
    environment = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RAY_COLOR_PREFIX")}
    # The agent's module importable in the command and its Ray workers (and the package as here).
    paths = [str(tmp_path), str(Path(esrp.__file__).resolve().parent.parent)]
    environment["PYTHONPATH"] = os.pathsep.join(paths)
    with open(log, "wb") as stderr, open(out, "wb") as stdout:
        status = subprocess.run(
            [sys.executable, "-m", "esrp.cli", *arguments],
            cwd=tmp_path,
            env=environment,
            stdout=stdout,
            stderr=stderr,
            timeout=300,
            check=False,
        ).returncode
    for path in (log, out):  # a worker's stderr lines come to the command's stderr, its stdout's to stdout
        text = path.read_text()
        assert status == 0, text
        assert "(EvalActor pid=" in text  # the actor's lines came through
        assert "reset on esrp-bench-v2/" in text
        assert "\x1b[" not in text, path
