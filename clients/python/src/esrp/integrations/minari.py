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
import shutil
import sys
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import minari
import numpy as np
from minari.data_collector import EpisodeBuffer
from minari.dataset.minari_dataset import parse_dataset_id
from minari.namespace import create_namespace, list_local_namespaces

from .._client import Client
from .._registration import ENV_ID, register_envs
from .._values import RewardWeights, Sensors
from ..envs import RearrangeEnv
from ..eval.evaluation import expert_trajectory
from ..eval.verify import compare
from ..train.demos import (
    REPLAY_LABEL,
    DemoExportError,
    DemoSettings,
    ExportOutcome,
    RecordSource,
    check_resolution,
    pick_scenes,
    read_sources,
)

__all__ = ["CHUNK_EPISODES", "default_dataset_id", "export_minari"]

CHUNK_EPISODES = 16
"""Episodes replayed, then written, at a time (a chunk of 16 Easy episodes at 128 px is ~60 MB)."""


@dataclass(frozen=True)
class _Source:
    """An episode to replay: its scene, its actions, its horizon (0: the scene's) and reward weights,
    and the record it comes from (None for an expert trajectory, read when it is played).
    """

    scene_id: str
    horizon: int = 0
    reward: dict[str, float] | None = None
    record: RecordSource | None = None


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
    dataset_id = dataset_id or default_dataset_id(info.dataset, settings)
    try:
        parse_dataset_id(dataset_id)
    except ValueError as error:
        raise DemoExportError(f"--dataset-id {dataset_id!r}: {error}") from None
    root = settings.out.absolute()  # under a relative root, Minari doubled its paths
    if (root / dataset_id).exists():
        raise DemoExportError(
            f"{root / dataset_id} exists: Minari datasets are never overwritten (remove it, or pass "
            "another --dataset-id)"
        )
    episodes = _sources(client, settings, sources, info.dataset)
    resolution = settings.resolution or 128
    horizons = {source.horizon for source in episodes}
    kwargs: dict[str, Any] = {"sensors": {"resolution": resolution}}
    if not settings.records:
        kwargs.update(split=settings.split, difficulty=settings.difficulty)
    if len(horizons) == 1 and 0 not in horizons:
        kwargs["horizon"] = horizons.pop()
    # The records' reward weights where they all played with the same (the server's default
    # otherwise), so that `recover_environment()` gives the rewards stored.
    weights = {repr(sorted(source.reward.items())) if source.reward else None for source in episodes}
    if len(weights) == 1 and episodes[0].reward:
        kwargs["reward"] = dict(episodes[0].reward)
    register_envs()
    spec = dataclasses.replace(gymnasium.spec(ENV_ID), kwargs=kwargs)
    envs: dict[tuple[int, str], RearrangeEnv] = {}
    root.mkdir(parents=True, exist_ok=True)
    _remove_abandoned_staging(root)
    staging = Path(tempfile.mkdtemp(prefix=f"{_STAGING}{os.getpid()}-", dir=root))
    steps = 0
    every = max(len(episodes) // 20, 1)
    try:
        dataset: Any = None
        with _datasets_root(staging):
            for start in range(0, len(episodes), CHUNK_EPISODES):
                chunk = episodes[start : start + CHUNK_EPISODES]
                buffers = [
                    _play(_env(envs, client, source, resolution, spec), source, start + k)
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
        shutil.rmtree(staging, ignore_errors=True)
    return dataset_id, ExportOutcome(len(episodes), steps, len(episodes))


_STAGING = ".esrp-minari-"
"""The start of a staging folder's name in the datasets root, then its export's process id and `-`."""


def _remove_abandoned_staging(root: Path) -> None:
    """Removes the staging folders in `root` of exports whose process has gone (killed before it
    could clean up); says which on stderr. One whose process is still running is left alone.
    """
    for path in root.glob(f"{_STAGING}*"):
        pid = path.name.removeprefix(_STAGING).partition("-")[0]
        if not path.is_dir() or not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
            print(f"esrp demos export: removed {path}, left by an export that was killed", file=sys.stderr)
        except PermissionError:
            pass  # another user's process: running


def _sources(
    client: Client, settings: DemoSettings, sources: Sequence[RecordSource] | None, dataset: str
) -> list[_Source]:
    """The episodes to replay, in order: the chosen scenes, or the chosen records."""
    if not settings.records:
        return [_Source(scene.id) for scene in pick_scenes(client, settings)]
    chosen = list(sources) if sources is not None else read_sources(settings)
    for source in chosen:
        if source.record.dataset != dataset:
            raise DemoExportError(
                f"{source.where}: {source.record.scene_id}: the record is of dataset "
                f"{source.record.dataset!r}, the server serves {dataset!r} (start a server of that dataset)"
            )
    return [_Source(s.record.scene_id, s.record.horizon, s.record.reward_weights, record=s) for s in chosen]


def _env(
    envs: dict[tuple[int, str], RearrangeEnv],
    client: Client,
    source: _Source,
    resolution: int,
    spec: gymnasium.envs.registration.EnvSpec,
) -> RearrangeEnv:
    """The env that replays `source` (one per horizon and reward weights), made on first use."""
    key = (source.horizon, repr(sorted((source.reward or {}).items())))
    env = envs.get(key)
    if env is None:
        env = RearrangeEnv(
            client=client,
            scene=source.scene_id,  # any scene: each reset names its own
            sensors=Sensors(resolution=resolution),
            horizon=source.horizon,
            reward=RewardWeights(**source.reward) if source.reward else None,
            agent=REPLAY_LABEL if source.record is not None else None,
        )
        env.spec = spec  # what Minari stores as the dataset's env_spec (JSON kwargs, no address)
        envs[key] = env
    return env


def _play(env: RearrangeEnv, source: _Source, episode_id: int) -> EpisodeBuffer:
    """Replays `source` on `env`: its Minari episode buffer."""
    options = {"scene": source.scene_id}
    observation, _ = env.reset(options=options)
    if source.record is None:
        with env.client.create_episode(source.scene_id, privileged=True) as episode:
            actions = [int(a) for a in expert_trajectory(episode.privileged_state().scene_json)]
        what = source.scene_id
    else:
        actions = list(source.record.record.actions)
        what = f"{source.record.where}: {source.scene_id}"
    observations = [observation]
    rewards: list[float] = []
    terminations: list[bool] = []
    truncations: list[bool] = []
    success = False
    ended_after: int | None = None
    for k, action in enumerate(actions, start=1):
        observation, reward, terminated, truncated, info = env.step(action)
        observations.append(observation)
        rewards.append(float(reward))
        terminations.append(bool(terminated))
        truncations.append(bool(truncated))
        if terminated or truncated:
            success, ended_after = bool(info.get("is_success", False)), k
            break
    if source.record is None:
        if ended_after is not None and ended_after != len(actions):
            raise DemoExportError(
                f"{what}: the episode ended after {ended_after} of its {len(actions)} actions"
            )
        if not success:
            raise DemoExportError(f"{what}: the expert trajectory does not solve the scene")
    else:
        # The checks of `esrp verify` and of the zarr export: the same end, metrics and reward.
        assert env.episode is not None  # reset made it
        different = compare(source.record.record, env.episode.metrics().metrics, ended_after)
        if different:
            raise DemoExportError(
                f"{what}: the replay does not reproduce the record ({'; '.join(different)}): nothing "
                "of it was written"
            )
    ended = ended_after is not None
    if not ended:
        truncations[-1] = True  # the agent stopped: as Minari marks an episode reset before its end
    return EpisodeBuffer(
        id=episode_id,
        options=options,
        observations={key: np.stack([o[key] for o in observations]) for key in observations[0]},
        actions=np.array(actions, dtype=np.int64),
        rewards=rewards,
        terminations=terminations,
        truncations=truncations,
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
