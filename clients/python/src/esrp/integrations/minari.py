r"""`esrp demos export --format minari`: demonstrations as a Minari dataset (needs the `minari` extra).

Minari is Farama's standard for offline-RL and imitation datasets (the Gymnasium sibling that
d3rlpy- and CORL-style code reads). The export replays each episode through the Gymnasium env
(`esrp.envs.RearrangeEnv`) and writes what it saw with Minari's own writer
(`minari.create_dataset_from_buffers`, then `MinariDataset.update_dataset_from_buffer` a chunk of
episodes at a time), under `--out` laid out as a Minari datasets root:

    esrp demos export --format minari --split train --difficulty easy --limit 100 \
        --resolution 64 --out datasets
    MINARI_DATASETS_PATH=datasets python -c \
        "import minari; d = minari.load_dataset('esrp/esrp-bench-v2-easy/expert-v0'); print(d.total_steps)"

Each episode holds Gymnasium's observations (`ego_rgb`, `goal_rgb`, `grasping`; one more than its
actions: the last is the observation after the last action), actions, rewards (the server's, with
its default weights or a record's own), terminations and truncations; its reset options are
`{"scene": SCENE_ID}`, so `env.reset(options=episode_options)` plays the same scene again. Images
are stored raw (Minari's JPEG encoding is off: pixels equal the zarr export's). The dataset's
`env_spec` is `esrp/Rearrange-v1` with JSON kwargs (the split, difficulty and `sensors`, no
address), so `dataset.recover_environment()` makes the env on a local server (the `server` extra)
or one named by `address=`.

Sources are those of the zarr export: the chosen scenes' expert trajectories, or with `records`
the episodes of `esrp.results/v1` files (replayed with each record's horizon and reward weights,
and checked against it as `esrp verify` and the zarr export check: the same end, metrics and
total reward; the reward weights go into the `env_spec` when every record played with the
same). A record whose agent stopped before the episode ended is marked truncated at its last
step, as Minari's DataCollector marks an episode reset before its end. The dataset appears whole
or not at all: it is written under a temporary folder in `--out` and moved into place at the end;
an interrupted export leaves nothing to resume (run it again), and the staging folder of one that
was killed is removed by the next export into the same root.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, cast

import gymnasium
import minari
import numpy as np
from minari.data_collector import EpisodeBuffer
from minari.dataset.minari_dataset import parse_dataset_id
from minari.namespace import create_namespace, list_local_namespaces

from .._client import Client
from .._registration import ENV_ID, register_envs
from ..envs import RearrangeEnv
from ..train.demos import DemoExportError, DemoSettings, ExportOutcome, RecordSource, check_resolution
from ._replay import Replay, check_target, env_for, env_kwargs, replay, staging_folder
from ._replay import sources as replay_sources

__all__ = ["CHUNK_EPISODES", "default_dataset_id", "export_minari"]

CHUNK_EPISODES = 16
"""Episodes replayed, then written, at a time (a chunk of 16 Easy episodes at 128 px is ~60 MB)."""


def default_dataset_id(dataset: str, settings: DemoSettings) -> str:
    """`esrp/DATASET-DIFFICULTY/expert-v0` (`all` without a difficulty) for the expert's
    demonstrations of the train split, `esrp/DATASET-SPLIT-DIFFICULTY/expert-v0` of another split;
    `esrp/DATASET/AGENT-v0` (`records` without `--agent`) for records.
    """
    if settings.records:
        return f"esrp/{dataset}/{settings.agent or 'records'}-v0"
    split = "" if settings.split == "train" else f"{settings.split}-"
    return f"esrp/{dataset}-{split}{settings.difficulty or 'all'}/expert-v0"


def export_minari(
    client: Client,
    settings: DemoSettings,
    dataset_id: str | None = None,
    sources: Sequence[RecordSource] | None = None,
) -> tuple[str, ExportOutcome]:
    """Writes the demonstrations `settings` chooses as Minari dataset `dataset_id`
    (`default_dataset_id` when None) under the datasets root `settings.out`; returns the id and
    what was written. Raises `DemoExportError` for what cannot be exported (a DAgger export, an
    existing dataset of that id, a record the replay does not reproduce...).
    """
    if settings.dagger is not None:
        raise DemoExportError("--format minari writes demonstrations and records, not DAgger's labels")
    info = client.server_info()
    check_resolution(settings.resolution, info.limits.max_resolution)
    given = dataset_id is not None
    dataset_id = dataset_id if dataset_id is not None else default_dataset_id(info.dataset, settings)
    try:
        parse_dataset_id(dataset_id)
    except ValueError as error:
        if given:
            raise DemoExportError(f"--dataset-id {dataset_id!r}: {error}") from None
        raise DemoExportError(f"the default id {dataset_id!r}: {error} (pass --dataset-id)") from None
    root = settings.out.absolute()  # under a relative root, Minari doubled its paths
    check_target(root, root / dataset_id, "Minari")
    episodes = replay_sources(client, settings, sources, info.dataset)
    resolution = settings.resolution or 128
    kwargs = env_kwargs(settings, episodes, resolution)  # `recover_environment()` plays them again
    register_envs()
    spec = dataclasses.replace(gymnasium.spec(ENV_ID), kwargs=kwargs)
    envs: dict[tuple[int, str], RearrangeEnv] = {}
    steps = 0
    every = max(len(episodes) // 20, 1)
    with staging_folder(root, _STAGING) as staging:
        try:
            dataset: Any = None
            with _datasets_root(staging):
                for start in range(0, len(episodes), CHUNK_EPISODES):
                    chunk = episodes[start : start + CHUNK_EPISODES]
                    buffers = [
                        _buffer(replay(env_for(envs, client, source, resolution, spec), source), start + k)
                        for k, source in enumerate(chunk)
                    ]
                    steps += sum(len(buffer.rewards) for buffer in buffers)
                    if dataset is None:
                        dataset = _create(dataset_id, buffers, next(iter(envs.values())), settings)
                    else:
                        dataset.update_dataset_from_buffer(buffers)
                    done = start + len(chunk)
                    if settings.progress and (done // every != start // every or done == len(episodes)):
                        print(f"{done}/{len(episodes)} episodes, {steps} steps", file=sys.stderr)
            _publish(staging, root, dataset_id)
        finally:
            for env in envs.values():
                env.close()
    return dataset_id, ExportOutcome(len(episodes), steps, len(episodes))


_STAGING = ".esrp-minari-"
"""The start of a staging folder's name in the datasets root, then its export's process id and `-`."""


def _buffer(played: Replay, episode_id: int) -> EpisodeBuffer:
    """Minari's episode buffer of a replayed episode."""
    observations = played.observations
    return EpisodeBuffer(
        id=episode_id,
        options=played.options,
        observations={key: np.stack([o[key] for o in observations]) for key in observations[0]},
        # An array, as Minari stores it (its annotation names lists and dicts only).
        actions=cast("list[int]", np.array(played.actions, dtype=np.int64)),
        rewards=played.rewards,
        terminations=played.terminations,
        truncations=played.truncations,
    )


def _create(dataset_id: str, buffers: list[EpisodeBuffer], env: RearrangeEnv, settings: DemoSettings) -> Any:  # noqa: ANN401
    """The dataset, made of its first chunk of episodes (Minari's metadata warnings silenced:
    what they ask for, the export fills in or cannot know).
    """
    source = "records" if settings.records else "expert"
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=UserWarning, module=r"minari\.")
        return minari.create_dataset_from_buffers(
            dataset_id,
            buffers,
            env=env,
            algorithm_name=f"esrp demos export ({source})",
            author="esrp demos export",
            description=_description(settings),
            data_format="hdf5",
            jpeg_encoding=False,
        )


def _description(settings: DemoSettings) -> str:
    if settings.records:
        which = f"agent {settings.agent}'s" if settings.agent else "the"
        return f"ESRP: {which} recorded episodes, replayed on esrp-server (esrp demos export --records)."
    difficulty = f"{settings.difficulty} " if settings.difficulty else ""
    return (
        f"ESRP: the expert demonstrations of the {settings.split} split's {difficulty}scenes, replayed on "
        "esrp-server (esrp demos export)."
    )


@contextmanager
def _datasets_root(path: Path) -> Iterator[None]:
    """`MINARI_DATASETS_PATH` set to `path` (Minari reads it at every call) for the block."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    try:
        yield
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def _publish(staging: Path, root: Path, dataset_id: str) -> None:
    """Moves the finished dataset from `staging` into the datasets root `root`, creating its
    namespace there (as Minari does) if it is new.
    """
    namespace, _, _ = parse_dataset_id(dataset_id)
    with _datasets_root(root):
        if namespace is not None and namespace not in list_local_namespaces():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                create_namespace(namespace)
    target = root / dataset_id
    target.parent.mkdir(parents=True, exist_ok=True)
    os.replace(staging / dataset_id, target)
