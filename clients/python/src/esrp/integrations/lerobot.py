r"""`esrp demos export --format lerobot`: demonstrations as a LeRobot dataset (the `lerobot` extra).

LeRobot is Hugging Face's library of robot-learning datasets and policies. The export replays each
episode through the Gymnasium env (`esrp.envs.RearrangeEnv`) and writes what it saw with LeRobot's
own writer (`LeRobotDataset.create`, `add_frame`, `save_episode`, `finalize`; format v3.0), under
`--out` laid out as a LeRobot home (`HF_LEROBOT_HOME`): the dataset is the folder `OUT/REPO_ID`.

    esrp demos export --format lerobot --split train --difficulty easy --limit 100 \
        --resolution 64 --out lerobot-home
    HF_LEROBOT_HOME=lerobot-home python -c "from lerobot.datasets.lerobot_dataset import \
        LeRobotDataset; d = LeRobotDataset('esrp/esrp-bench-v2-easy-expert'); print(d.num_frames)"

A frame is a step: the observation the agent acted on and the action it took, LeRobot's way (the
observation after an episode's last action is not stored). Its features:

- `observation.images.ego`, `observation.images.goal`: the views, `image` features of (R, R, 3),
  stored as PNG (lossless: the pixels equal the zarr and Minari exports'); LeRobot loads them as
  float (3, R, R) tensors in [0, 1].
- `observation.state`: the grasp flag, float32 (1,) (`names: ["grasping"]`).
- `action`: the action's index, int64 (1,) (0 forward, 1 backward, 2 left, 3 right, 4 fetch,
  5 release; `esrp.Action`).
- `next.reward`: the step's reward, float32 (the server's default weights, or a record's own).
- `next.done`: the episode ended at this step (success or the horizon); false at the last frame of
  a record whose agent stopped before the end.
- `next.success`: the step solved the scene.

LeRobot gives the (1,) features of a frame as 0-d tensors (a `DataLoader` batch's `action` is (B,)).

Every frame's task is `TASK`. The dataset's `fps` is `FPS` (an ESRP step takes no time; LeRobot
needs a rate to give timestamps). What LeRobot's format has no place for is in `meta/esrp.json`
(`esrp.lerobot/v1`): the server's dataset, the env's id and kwargs (as the Minari export's env spec:
`sensors`, and `split` and `difficulty` or the records' shared `horizon` and `reward`), the action
names, and each episode's index, scene id, reset options (`{"scene": SCENE_ID}`: what
`env.reset(options=...)` takes to play it again), steps, end and source.

Sources and checks are those of the Minari export (`esrp.integrations._replay`). The id must be a
Hugging Face repository id `NAMESPACE/NAME`: a default one that is not (an `--agent` named
`MODULE:CALLABLE`) asks for `--dataset-id`. The dataset appears whole or not at all: it is written
in a staging folder in `--out` and moved into place at the end; an interrupted export leaves
nothing to resume (run it again), and the staging folder of one that was killed is removed by the
next export into the same folder.
"""

from __future__ import annotations

import json
import shutil
import sys
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import datasets  # pyright: ignore[reportMissingImports]  # LeRobot's venv only (mypy: Any)
import numpy as np
from huggingface_hub.errors import HFValidationError
from huggingface_hub.utils import validate_repo_id  # type: ignore[attr-defined]  # lazily exported
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # pyright: ignore[reportMissingImports]

from .._client import Client
from .._registration import ENV_ID
from .._values import Action
from ..envs import RearrangeEnv
from ..train.demos import DemoExportError, DemoSettings, ExportOutcome, RecordSource, check_resolution
from ._replay import (
    Replay,
    Source,
    check_target,
    env_for,
    env_kwargs,
    replay,
    staging_folder,
)
from ._replay import sources as replay_sources

__all__ = ["FORMAT", "FPS", "TASK", "default_repo_id", "export_lerobot", "features"]

FORMAT = "esrp.lerobot/v1"
"""The `format` of `meta/esrp.json`."""

FPS = 10
"""The dataset's frames per second: a frame's timestamp is its index / 10."""

TASK = "Rearrange the furniture to match the goal image."
"""Every frame's task (LeRobot's language instruction)."""

_STAGING = ".esrp-lerobot-"
"""The start of a staging folder's name in `--out`, then its export's process id and `-`."""


def default_repo_id(dataset: str, settings: DemoSettings) -> str:
    """`esrp/DATASET-DIFFICULTY-expert` (`all` without a difficulty) for the expert's demonstrations
    of the train split, `esrp/DATASET-SPLIT-DIFFICULTY-expert` of another split;
    `esrp/DATASET-AGENT` (`records` without `--agent`) for records.
    """
    if settings.records:
        return f"esrp/{dataset}-{settings.agent or 'records'}"
    split = "" if settings.split == "train" else f"{settings.split}-"
    return f"esrp/{dataset}-{split}{settings.difficulty or 'all'}-expert"


def features(resolution: int) -> dict[str, dict[str, Any]]:
    """The dataset's features (LeRobot's `features` argument) at views of `resolution` pixels."""
    image = {"dtype": "image", "shape": (resolution, resolution, 3), "names": ["height", "width", "channels"]}
    return {
        "observation.images.ego": dict(image),
        "observation.images.goal": dict(image),
        "observation.state": {"dtype": "float32", "shape": (1,), "names": ["grasping"]},
        "action": {"dtype": "int64", "shape": (1,), "names": ["action"]},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }


def export_lerobot(
    client: Client,
    settings: DemoSettings,
    repo_id: str | None = None,
    sources: Sequence[RecordSource] | None = None,
) -> tuple[str, ExportOutcome]:
    """Writes the demonstrations `settings` chooses as LeRobot dataset `repo_id`
    (`default_repo_id` when None) in the folder `settings.out / repo_id`; returns the id and what
    was written. Raises `DemoExportError` for what cannot be exported (a DAgger export, an existing
    dataset of that id, a record the replay does not reproduce...).
    """
    if settings.dagger is not None:
        raise DemoExportError("--format lerobot writes demonstrations and records, not DAgger's labels")
    info = client.server_info()
    check_resolution(settings.resolution, info.limits.max_resolution)
    if repo_id is None:
        repo_id = default_repo_id(info.dataset, settings)
        _check_repo_id(repo_id, f"the default id {repo_id!r}", " (pass --dataset-id NAMESPACE/NAME)")
    else:
        _check_repo_id(repo_id, f"--dataset-id {repo_id!r}")
    root = settings.out.absolute()
    target = root / repo_id
    check_target(root, target, "LeRobot")
    episodes = replay_sources(client, settings, sources, info.dataset)
    resolution = settings.resolution or 128
    kwargs = env_kwargs(settings, episodes, resolution)
    envs: dict[tuple[int, str], RearrangeEnv] = {}
    steps = 0
    every = max(len(episodes) // 20, 1)
    described: list[dict[str, Any]] = []
    with staging_folder(root, _STAGING) as staging:
        try:
            with _quiet():
                dataset = LeRobotDataset.create(
                    repo_id,
                    fps=FPS,
                    features=features(resolution),
                    root=staging / "dataset",
                    use_videos=False,
                )
                try:
                    for index, source in enumerate(episodes):
                        played = replay(env_for(envs, client, source, resolution), source)
                        _write(dataset, played)
                        described.append(_described(index, source, played))
                        steps += len(played.actions)
                        done = index + 1
                        if settings.progress and (done // every != index // every or done == len(episodes)):
                            print(f"{done}/{len(episodes)} episodes, {steps} steps", file=sys.stderr)
                finally:
                    dataset.finalize()
            written = staging / "dataset"
            _remove_empty_image_folders(written)
            sidecar = {
                "format": FORMAT,
                "dataset": info.dataset,
                "env": {"id": ENV_ID, "kwargs": kwargs},
                "actions": [action.name.lower() for action in Action],
                "episodes": described,
            }
            (written / "meta" / "esrp.json").write_text(json.dumps(sidecar, indent=1) + "\n")
            target.parent.mkdir(parents=True, exist_ok=True)
            written.replace(target)
        finally:
            for env in envs.values():
                env.close()
    return repo_id, ExportOutcome(len(episodes), steps, len(episodes))


def _check_repo_id(repo_id: str, what: str, hint: str = "") -> None:
    """Refuses an id that is not a Hugging Face repository id `NAMESPACE/NAME`, saying `what` it is
    (`--dataset-id ID`, or the default id, made of the server's dataset and `--agent`) and `hint`.
    """
    if repo_id.count("/") != 1:
        raise DemoExportError(f"{what}: a LeRobot dataset's id is NAMESPACE/NAME{hint}")
    try:
        validate_repo_id(repo_id)
    except HFValidationError as error:
        raise DemoExportError(f"{what}: {error}{hint}") from None


def _write(dataset: LeRobotDataset, played: Replay) -> None:
    """Adds `played`'s steps to `dataset` as frames, then saves them as one episode."""
    last = len(played.actions) - 1
    for k, action in enumerate(played.actions):
        observation = played.observations[k]
        ended_here = k == last and played.ended
        dataset.add_frame(
            {
                "observation.images.ego": observation["ego_rgb"],
                "observation.images.goal": observation["goal_rgb"],
                "observation.state": np.array([observation["grasping"]], dtype=np.float32).reshape(1),
                "action": np.array([action], dtype=np.int64),
                "next.reward": np.array([played.rewards[k]], dtype=np.float32),
                "next.done": np.array([ended_here]),
                "next.success": np.array([ended_here and played.success]),
                "task": TASK,
            }
        )
    dataset.save_episode()


def _described(index: int, source: Source, played: Replay) -> dict[str, Any]:
    """`meta/esrp.json`'s entry of episode `index`."""
    end = ("success" if played.success else "horizon") if played.ended else "agent"
    return {
        "episode_index": index,
        "scene_id": source.scene_id,
        "options": played.options,
        "steps": len(played.actions),
        "end": end,
        "source": "expert" if source.record is None else source.record.where,
    }


def _remove_empty_image_folders(root: Path) -> None:
    """Removes `images/`, where LeRobot stages each frame's PNG before it embeds them in the
    episode's parquet file, when nothing is left in it.
    """
    images = root / "images"
    if images.is_dir() and not any(path.is_file() for path in images.rglob("*")):
        shutil.rmtree(images)


@contextmanager
def _quiet() -> Iterator[None]:
    """The `datasets` library's progress bars off (one per episode otherwise), and for the block,
    LeRobot's warning about statistics of boolean features and `datasets`' about the (1,) arrays
    LeRobot asks for (numpy's deprecation of their conversion to scalars) silenced.
    """
    bars = datasets.is_progress_bar_enabled()
    datasets.disable_progress_bars()
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=RuntimeWarning, module=r"lerobot\.")
            warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"datasets\.")
            yield
    finally:
        if bars:
            datasets.enable_progress_bars()
