"""`esrp demos export`: the benchmark's expert demonstrations, replayed through the server, written
as a zarr store that training reads a window at a time (docs/demonstrations.md has the format).

Each scene's expert trajectory (in its privileged scene JSON) is stepped on the server; the store
gets, per step, the observation the agent saw before acting (ego view, grasp flag) and the expert's
action, and per episode the goal image and the scene id. Episodes are appended whole, in the order
of the scenes chosen; an interrupted export resumes where it stopped (a partly written episode is
cut off first), and the store records the dataset and resolution it was made with.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._client import Client
from ._values import SceneSummary, Sensors
from .evaluation import expert_trajectory

__all__ = ["FORMAT", "DemoExportError", "DemoSettings", "ExportOutcome", "export_demos"]

FORMAT = "esrp.demos/v1"
"""The store's `format` attribute."""

CHUNK_STEPS = 256
"""Steps per chunk of the per-step arrays (a chunk of ego views is 256 × 49,152 bytes, 12 MB raw)."""


class DemoExportError(Exception):
    """The export cannot run as asked (a store of another dataset or resolution, no scenes)."""


@dataclass
class DemoSettings:
    """What `esrp demos export` writes; the fields are its flags.

    Attributes:
        out: The zarr store (a folder, created if missing, resumed if present).
        split: The split whose scenes to export.
        difficulty: Only scenes of this difficulty.
        scenes: Only these scene ids, in this order.
        limit: At most this many scenes (after the filters).
        resolution: The views' side in pixels (0: the server's default, 128).
        progress: Print a line every 5 % of the scenes.
    """

    out: Path
    split: str = "train"
    difficulty: str | None = None
    scenes: Sequence[str] = ()
    limit: int | None = None
    resolution: int = 0
    progress: bool = True


@dataclass
class ExportOutcome:
    """What an export did: episodes and steps in the store, and how many this run added."""

    episodes: int
    steps: int
    added: int


def _pick(client: Client, settings: DemoSettings) -> list[SceneSummary]:
    listed = list(client.scenes(settings.split, settings.difficulty, page_size=1000))
    if settings.scenes:
        by_id = {s.id: s for s in listed}
        missing = [s for s in settings.scenes if s not in by_id]
        if missing:
            raise DemoExportError(f"scene {missing[0]!r} is not among the {settings.split} scenes")
        listed = [by_id[s] for s in settings.scenes]
    if settings.limit is not None:
        listed = listed[: settings.limit]
    if not listed:
        raise DemoExportError(f"no scene matches: the {settings.split} split has none with these filters")
    return listed


_Episode = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""One episode's goal image, ego views, grasp flags and actions."""


class _Store:
    """The zarr group and its arrays; `episode_ends` is written last, so it says what is whole."""

    def __init__(self, path: Path, dataset: str, resolution: int) -> None:
        import zarr

        self.group: Any = zarr.open_group(str(path), mode="a")
        attrs = dict(self.group.attrs)
        if attrs:
            if attrs.get("format") != FORMAT:
                raise DemoExportError(f"{path} is not an {FORMAT} store (format {attrs.get('format')!r})")
            if attrs.get("dataset") != dataset or attrs.get("resolution") != resolution:
                raise DemoExportError(
                    f"{path} holds demonstrations of {attrs.get('dataset')} at {attrs.get('resolution')} px, "
                    f"not {dataset} at {resolution} px: write to another --out"
                )
        else:
            self.group.attrs.update({"format": FORMAT, "dataset": dataset, "resolution": resolution})
        side = resolution

        def array(name: str, shape: tuple[int, ...], dtype: str, chunk: int) -> Any:  # noqa: ANN401
            if name in self.group:
                return self.group[name]
            return self.group.create_array(name, shape=(0, *shape), chunks=(chunk, *shape), dtype=dtype)

        self.ego = array("data/ego_rgb", (side, side, 3), "uint8", CHUNK_STEPS)
        self.grasping = array("data/grasping", (), "bool", 4096)
        self.action = array("data/action", (), "uint8", 4096)
        self.goal = array("meta/goal_rgb", (side, side, 3), "uint8", 16)
        self.ends = array("meta/episode_ends", (), "int64", 4096)
        listed = self.group.attrs.get("scene_ids", [])
        self.scene_ids: list[str] = [str(s) for s in listed] if isinstance(listed, list) else []
        self._cut_torn()

    def _cut_torn(self) -> None:
        """Drops what an interrupted run wrote past the last whole episode."""
        episodes = self.ends.shape[0]
        steps = int(self.ends[episodes - 1]) if episodes else 0
        for array in (self.ego, self.grasping, self.action):
            if array.shape[0] != steps:
                array.resize((steps, *array.shape[1:]))
        if self.goal.shape[0] != episodes:
            self.goal.resize((episodes, *self.goal.shape[1:]))
        if len(self.scene_ids) != episodes:
            self.scene_ids = self.scene_ids[:episodes]
            self.group.attrs["scene_ids"] = self.scene_ids

    @property
    def steps(self) -> int:
        return int(self.ends[self.ends.shape[0] - 1]) if self.ends.shape[0] else 0

    def append(self, scene_id: str, episode: _Episode) -> None:
        """Appends a whole episode: (goal, ego views, grasp flags, actions)."""
        goal, ego, grasping, actions = episode
        end = self.steps + len(actions)
        self.ego.append(ego, axis=0)
        self.grasping.append(grasping, axis=0)
        self.action.append(actions, axis=0)
        self.goal.append(goal[None], axis=0)
        self.scene_ids.append(scene_id)
        self.group.attrs["scene_ids"] = self.scene_ids
        self.ends.append(np.array([end], dtype=np.int64), axis=0)  # last: the episode is whole


def _replay(
    client: Client, scene: SceneSummary, resolution: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps the expert trajectory of `scene`: (goal, ego views, grasp flags, actions)."""
    sensors = Sensors(resolution=resolution) if resolution else None
    with client.create_episode(scene.id, privileged=True, sensors=sensors) as episode:
        actions = expert_trajectory(episode.privileged_state().scene_json)
        first = episode.observation
        if first is None or first.goal_rgb is None:
            raise DemoExportError(f"{scene.id}: the created episode came without its first observation")
        egos = [first.ego_rgb]
        grasps = [first.grasping]
        for i, action in enumerate(actions):
            result = episode.step(action)
            ended = result.terminated or result.truncated
            if ended and i != len(actions) - 1:
                raise DemoExportError(
                    f"{scene.id}: the expert trajectory ended the episode after {i + 1} steps"
                )
            if not ended:
                egos.append(result.observation.ego_rgb)
                grasps.append(result.observation.grasping)
            elif not result.terminated:
                raise DemoExportError(f"{scene.id}: the expert trajectory does not succeed")
        if len(egos) != len(actions):
            raise DemoExportError(f"{scene.id}: the expert trajectory does not end the episode")
        return (
            np.array(first.goal_rgb),
            np.stack(egos),
            np.array(grasps, dtype=bool),
            np.array([int(a) for a in actions], dtype=np.uint8),
        )


def export_demos(client: Client, settings: DemoSettings) -> ExportOutcome:
    """Exports the expert demonstrations of the chosen scenes into `settings.out` (resuming it)."""
    info = client.server_info()
    scenes = _pick(client, settings)
    resolution = settings.resolution or 128
    store = _Store(settings.out, info.dataset, resolution)
    done = set(store.scene_ids)
    todo = [s for s in scenes if s.id not in done]
    if done:
        print(
            f"resuming {settings.out}: {len(scenes) - len(todo)} of {len(scenes)} scenes already there",
            file=sys.stderr,
        )
    every = max(len(scenes) // 20, 1)
    added = 0
    for scene in todo:
        store.append(scene.id, _replay(client, scene, settings.resolution))
        added += 1
        position = len(scenes) - len(todo) + added
        if settings.progress and (position % every == 0 or position == len(scenes)):
            print(f"{position}/{len(scenes)} episodes, {store.steps} steps", file=sys.stderr)
    return ExportOutcome(len(store.scene_ids), store.steps, added)
