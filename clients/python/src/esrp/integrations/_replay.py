"""What the dataset exports of `esrp.integrations` (Minari, LeRobot) share.

The episodes to write are those of the zarr export (`esrp.train.demos`): the chosen scenes'
expert trajectories, or the records of `esrp.results/v1` files. Each is replayed through the
Gymnasium env (`esrp.envs.RearrangeEnv`), which gives the observations a dataset stores, and
checked: an expert trajectory must solve its scene with its last action; a record must replay to
its own end, metrics and total reward (the checks of `esrp verify`). An export writes into a
staging folder beside its target and moves the finished dataset into place; a refused one removes
it, and the `--out` folders it created for it; the staging folders of exports that were killed are
removed by the next export into the same folder.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import gymnasium.envs.registration
import numpy as np

from .._client import Client
from .._errors import EsrpError
from .._values import RewardWeights, Sensors
from ..envs import RearrangeEnv
from ..eval.evaluation import expert_trajectory
from ..eval.verify import compare
from ..train.demos import REPLAY_LABEL, DemoExportError, DemoSettings, RecordSource, pick_scenes, read_sources

__all__ = [
    "Replay",
    "Source",
    "check_target",
    "env_for",
    "env_kwargs",
    "horizon_kwargs",
    "remove_abandoned_staging",
    "replay",
    "reward_kwargs",
    "sources",
    "staging_folder",
]


@dataclass(frozen=True)
class Source:
    """An episode to replay: its scene, its horizon (0: the scene's) and reward weights (None: the
    server's), and the record it comes from (None for an expert trajectory, read when it is played).
    """

    scene_id: str
    horizon: int = 0
    reward: dict[str, float] | None = None
    record: RecordSource | None = None


@dataclass(frozen=True)
class Replay:
    """One replayed episode, as the Gymnasium env gave it.

    Attributes:
        options: The reset options that play the episode's scene again (`{"scene": SCENE_ID}`).
        observations: The observations, one more than the actions (the last is the observation
            after the last action).
        actions: The actions stepped.
        rewards: The reward of each step.
        terminations: Whether each step solved the scene (only the last can).
        truncations: Whether each step reached the horizon; the last is also true when the agent of
            a record stopped before the episode ended (as Minari's DataCollector marks an episode
            reset before its end).
        ended: Whether the episode ended (success or the horizon) at its last step.
        success: Whether it ended solved.
    """

    options: dict[str, str]
    observations: list[dict[str, np.ndarray]]
    actions: list[int]
    rewards: list[float]
    terminations: list[bool]
    truncations: list[bool]
    ended: bool
    success: bool


def sources(
    client: Client, settings: DemoSettings, records: Sequence[RecordSource] | None, dataset: str
) -> list[Source]:
    """The episodes to replay, in order: the chosen scenes, or the chosen records (`records`, read
    from `settings` when None), which must be of the server's `dataset`.
    """
    if not settings.records:
        return [Source(scene.id) for scene in pick_scenes(client, settings)]
    chosen = list(records) if records is not None else read_sources(settings)
    for source in chosen:
        if source.record.dataset != dataset:
            raise DemoExportError(
                f"{source.where}: {source.record.scene_id}: the record is of dataset "
                f"{source.record.dataset!r}, the server serves {dataset!r} (start a server of that dataset)"
            )
    return [Source(s.record.scene_id, s.record.horizon, s.record.reward_weights, record=s) for s in chosen]


def env_for(
    envs: dict[tuple[int, str], RearrangeEnv],
    client: Client,
    source: Source,
    resolution: int,
    spec: gymnasium.envs.registration.EnvSpec | None = None,
) -> RearrangeEnv:
    """The env that replays `source`, one per horizon and reward weights, kept in `envs` (the
    caller closes them); made on first use, with `spec` as its `spec` when given.
    """
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
        if spec is not None:
            env.spec = spec
        envs[key] = env
    return env


def replay(env: RearrangeEnv, source: Source) -> Replay:
    """Replays `source` on `env` and checks it (see the module's docstring); raises
    `DemoExportError` naming the episode (its scene, and a record's `FILE:LINE`) when the check
    fails or the server refuses the replay (a record of a scene it does not serve).
    """
    what = source.scene_id if source.record is None else f"{source.record.where}: {source.scene_id}"
    try:
        return _replay(env, source, what)
    except EsrpError as error:  # a record's scene the server does not serve, a server gone...
        raise DemoExportError(f"{what}: the replay failed: {type(error).__name__}: {error.message}") from None


def _replay(env: RearrangeEnv, source: Source, what: str) -> Replay:
    """`replay`, the episode named `what` in its errors."""
    options = {"scene": source.scene_id}
    observation, _ = env.reset(options=options)
    if source.record is None:
        with env.client.create_episode(source.scene_id, privileged=True) as episode:
            actions = [int(a) for a in expert_trajectory(episode.privileged_state().scene_json)]
    else:
        actions = list(source.record.record.actions)
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
        assert env.episode is not None  # reset made it
        different = compare(source.record.record, env.episode.metrics().metrics, ended_after)
        if different:
            raise DemoExportError(
                f"{what}: the replay does not reproduce the record ({'; '.join(different)}): nothing "
                "of it was written"
            )
    ended = ended_after is not None
    if not ended:
        truncations[-1] = True
    return Replay(options, observations, actions, rewards, terminations, truncations, ended, success)


def check_target(root: Path, target: Path, kind: str) -> None:
    """Raises `DemoExportError`, before anything is replayed, when the dataset cannot go at `target`
    in the folder `root` (`--out`): `root` or a folder between them is a file, or `target` exists
    (datasets of `kind`, `Minari` or `LeRobot`, are never overwritten).
    """
    if root.exists() and not root.is_dir():
        raise DemoExportError(f"--out {root} is a file, not a folder")
    if target.exists() or target.is_symlink():
        raise DemoExportError(
            f"{target} exists: {kind} datasets are never overwritten (remove it, or pass another "
            "--dataset-id)"
        )
    for folder in target.parents:
        if folder == root:
            break
        if folder.exists() and not folder.is_dir():
            raise DemoExportError(
                f"{folder} is a file: the dataset cannot go in it (remove it, or pass another --dataset-id)"
            )


@contextmanager
def staging_folder(root: Path, prefix: str) -> Iterator[Path]:
    """A new staging folder in `root` for the block, named `prefix`, this process's id, `-` and a
    random part; first removes the staging folders of `prefix` left by killed exports. After the
    block the staging folder is removed, and so are the folders made for it (`root`, created if
    missing, and those above it that did not exist) where they are empty: a refused export leaves
    nothing it created, a finished one its dataset. A folder that existed before is never removed.
    """
    made: list[Path] = []  # deepest first
    for folder in (root, *root.parents):
        if folder.exists() or folder.is_symlink():
            break
        made.append(folder)
    root.mkdir(parents=True, exist_ok=True)
    try:
        remove_abandoned_staging(root, prefix)
        staging = Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}-", dir=root))
        try:
            yield staging
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    finally:
        for folder in made:
            try:
                folder.rmdir()
            except OSError:  # not empty: the dataset, or what another process put there since
                break


def remove_abandoned_staging(root: Path, prefix: str) -> None:
    """Removes the staging folders `PREFIX PID-...` in `root` whose export's process has gone
    (killed before it could clean up); says which on stderr. One whose process is still running is
    left alone.
    """
    for path in root.glob(f"{prefix}*"):
        pid = path.name.removeprefix(prefix).partition("-")[0]
        if not path.is_dir() or not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
            print(f"esrp demos export: removed {path}, left by an export that was killed", file=sys.stderr)
        except PermissionError:
            pass  # another user's process: running


def env_kwargs(settings: DemoSettings, episodes: Sequence[Source], resolution: int) -> dict[str, Any]:
    """The kwargs of `esrp/Rearrange-v1` that play `episodes` again, as JSON: the views'
    `sensors`; the `split` and `difficulty` of expert demonstrations; the `horizon` and the
    `reward` weights that every record shares (`horizon_kwargs`, `reward_kwargs`), so that the env
    gives the rewards stored.
    """
    kwargs: dict[str, Any] = {"sensors": {"resolution": resolution}}
    if not settings.records:
        kwargs.update(split=settings.split, difficulty=settings.difficulty)
    kwargs.update(horizon_kwargs(episodes))
    kwargs.update(reward_kwargs(episodes))
    return kwargs


def reward_kwargs(episodes: Sequence[Source]) -> dict[str, Any]:
    """`{"reward": WEIGHTS}` when every episode played with the same reward weights, which are not
    the server's default; `{}` otherwise.
    """
    weights = {repr(sorted(source.reward.items())) if source.reward else None for source in episodes}
    if len(weights) == 1 and episodes and episodes[0].reward:
        return {"reward": dict(episodes[0].reward)}
    return {}


def horizon_kwargs(episodes: Sequence[Source]) -> dict[str, Any]:
    """`{"horizon": H}` when every episode played with the same horizon H, not the scenes' own."""
    horizons = {source.horizon for source in episodes}
    if len(horizons) == 1 and 0 not in horizons:
        return {"horizon": horizons.pop()}
    return {}
