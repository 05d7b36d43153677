"""What the single and the vector env share: the observation space, the connection and scene list
(`Setup`), where a step answer's images go in an observation (`Images`), and the infos of steps
and resets.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt
from gymnasium import spaces

from .._client import Client
from .._common import TlsSetting
from .._errors import InvalidRequest
from .._local import LocalServer
from .._values import (
    Difficulty,
    EpisodeMetrics,
    RewardWeights,
    SceneSummary,
    Sensors,
    Split,
    StepColumns,
    observation_images,
)

ObsDict = dict[str, npt.NDArray[Any]]
"""An observation: the keys of `observation_space`, each an array."""

METADATA: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 10}
"""The envs' `metadata` (the vector env adds its `autoreset_mode`)."""


def observation_space(sensors: Sensors) -> spaces.Dict:
    """The observation space of one env with these sensors."""
    side = sensors.resolution
    image = spaces.Box(0, 255, (side, side, 3), np.uint8)
    members: dict[str, spaces.Space[Any]] = {
        "ego_rgb": image,
        "goal_rgb": image,
        "grasping": spaces.Discrete(2),
    }
    if sensors.depth:
        members["depth"] = spaces.Box(0.0, np.inf, (side, side), np.float32)
    if sensors.segmentation:
        members["segmentation"] = spaces.Box(0, np.iinfo(np.uint32).max, (side, side), np.uint32)
    if sensors.current_top_down:
        members["current_top_down"] = image
    return spaces.Dict(members)


def step_info(columns: StepColumns, position: int) -> dict[str, Any]:
    """The info of the step at `position` of `columns`: plain scalars (so vector infos batch them
    into arrays), and the episode's final metrics under `metrics` on the step that ends it.
    """
    info: dict[str, Any] = {
        "accepted": columns.accepted[position],
        "collided": columns.collided[position],
        "placed_count": columns.placed_count[position],
        "step_index": columns.step_index[position],
    }
    metrics = columns.metrics.get(position)
    if metrics is not None:
        info["metrics"] = metrics_info(metrics)
        info["is_success"] = metrics.success
    return info


def reset_info(scene: SceneSummary, horizon: int) -> dict[str, Any]:
    """The info of a reset onto `scene`: its id, difficulty, room type, movable-object count, and the
    episode's step limit (`horizon`, the env's, else the scene's).
    """
    return {
        "scene_id": scene.id,
        "difficulty": None if scene.difficulty is None else scene.difficulty.value,
        "room_type": scene.room_type,
        "objects": scene.movable_objects,
        "horizon": horizon or scene.horizon,
    }


def metrics_info(metrics: EpisodeMetrics) -> dict[str, Any]:
    """The `metrics` entry of a step info."""
    return {
        "success": metrics.success,
        "object_success_rate": metrics.object_success_rate,
        "remaining_distance_ratio": metrics.remaining_distance_ratio,
        "stage": metrics.stage,
        "placed": metrics.placed,
        "steps": metrics.steps,
        "total_reward": metrics.total_reward,
    }


def frame(observation: ObsDict, goal: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """The ego view, the goal and (when the sensor is on) the current top-down, side by side."""
    views = [observation["ego_rgb"], goal]
    if "current_top_down" in observation:
        views.append(observation["current_top_down"])
    return np.concatenate(views, axis=1)


class Images:
    """Where a step answer's images go in an observation: the sensors' images (key, bytes per
    pixel, dtype), and each key's array shape.
    """

    def __init__(self, sensors: Sensors) -> None:
        side = sensors.resolution
        self.sensors = sensors
        images = observation_images(sensors)
        self.keys = tuple(key for key, _, _ in images)
        self.shapes = {key: (side, side, 3) if size == 3 else (side, side) for key, size, _ in images}
        self.dtypes = {key: dtype for key, _, dtype in images}

    def view(self, key: str, image: Any) -> npt.NDArray[Any]:  # noqa: ANN401
        """A read-only array of an answer's `key` image (its bytes, or already an array)."""
        if isinstance(image, np.ndarray):
            return image
        return np.frombuffer(image, dtype=self.dtypes[key]).reshape(self.shapes[key])

    def observation(
        self, images: Mapping[str, Any], grasping: bool | np.integer[Any], goal: npt.NDArray[np.uint8]
    ) -> ObsDict:
        """An observation as the envs return it: read-only views of the answer's images, and a
        read-only copy of the goal image that the server sent at the reset (Gymnasium wants no two
        observations to share memory, and the goal is the one image a step answer does not carry).
        """
        goal = goal.copy()
        goal.flags.writeable = False
        result: ObsDict = {
            "ego_rgb": self.view("ego_rgb", images["ego_rgb"]),
            "goal_rgb": goal,
            "grasping": np.int64(grasping),
        }
        for key in self.keys[1:]:
            result[key] = self.view(key, images[key])
        return result


_T = TypeVar("_T")


def _from_fields(kind: type[_T], fields: Mapping[str, Any], what: str) -> _T:
    """`kind(**fields)`, or a `ValueError` naming `what` and the fields `kind` has."""
    try:
        return kind(**fields)
    except TypeError:
        known = ", ".join(f.name for f in dataclasses.fields(kind))  # type: ignore[arg-type]
        raise ValueError(f"{what}: unknown fields in {dict(fields)!r} (it has {known})") from None


@dataclass
class Setup:
    """What the single and the vector env share: the connection (owned or not), the episode
    settings, and the scene list the seeds pick from.
    """

    client: Client
    owned_client: bool
    server: LocalServer | None
    scenes: tuple[str, ...]
    sensors: Sensors
    horizon: int
    reward: RewardWeights | None
    agent: str | None = None

    @classmethod
    def connect(
        cls,
        address: str | None,
        client: Client | None,
        token: str | None,
        tls: TlsSetting,
        split: Split | str | None,
        difficulty: Difficulty | str | None,
        scene: str | Sequence[str] | None,
        sensors: Sensors | Mapping[str, Any] | None,
        horizon: int,
        reward: RewardWeights | Mapping[str, Any] | None,
        agent: str | None = None,
    ) -> Setup:
        # Mappings of the fields too, so that an env spec's kwargs can be JSON (Minari stores them).
        if isinstance(sensors, Mapping):
            sensors = _from_fields(Sensors, sensors, "sensors")
        if isinstance(reward, Mapping):
            reward = _from_fields(RewardWeights, reward, "reward")
        server = None
        owned = client is None
        if client is None:
            if address is None:
                server = LocalServer(unix_socket=True).start()
                address = server.address
            client = Client(address, token=token, tls=tls)
        try:
            if isinstance(scene, str):
                scenes: tuple[str, ...] = (scene,)
            elif scene is not None:
                scenes = tuple(scene)
                if not scenes or not all(isinstance(s, str) and s for s in scenes):
                    raise ValueError(f"scene: a scene id or a non-empty list of scene ids, got {scene!r}")
            else:
                scenes = tuple(s.id for s in client.scenes(split, difficulty, page_size=1000))
                if not scenes:
                    raise InvalidRequest(
                        f"the served dataset has no scenes of split {split!r}, difficulty {difficulty!r}"
                    )
        except BaseException:
            if owned:
                client.close()
            if server is not None:
                server.stop()
            raise
        return cls(client, owned, server, scenes, sensors or Sensors(), horizon, reward, agent)

    def pick_scene(
        self, rng: np.random.Generator, options: Mapping[str, Any] | None, own: str | None = None
    ) -> str:
        """The scene of a reset: drawn from the list with the env's generator (always, so the
        generator advances the same way), or `own` where given, unless `options["scene"]` names one.
        """
        drawn = self.scenes[int(rng.integers(len(self.scenes)))]
        if options and options.get("scene") is not None:
            return str(options["scene"])
        return drawn if own is None else own

    def close(self) -> None:
        if self.owned_client:
            self.client.close()
        if self.server is not None:
            self.server.stop()
            self.server = None
