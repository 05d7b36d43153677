"""What the single and the vector env share: the observation space, the connection and scene list
(`Setup`), where a step answer's images go in an observation (`Images`), and the infos of steps
and resets.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import numpy.typing as npt
from gymnasium import spaces

from .._client import Client
from .._common import TlsSetting
from .._errors import InvalidRequest
from .._local import LocalServer, start_servers
from .._values import (
    Difficulty,
    EpisodeMetrics,
    RewardWeights,
    SceneSummary,
    Sensors,
    Split,
    StepColumns,
    observation_images,
    of_fields,
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
            # A Discrete space's value, a numpy scalar: ObsDict types every value as an array, whose
            # operations the scalar has too.
            "grasping": cast("npt.NDArray[Any]", np.int64(grasping)),
        }
        for key in self.keys[1:]:
            result[key] = self.view(key, images[key])
        return result


@dataclass
class Setup:
    """What the single and the vector env share: the connections (owned or not; the vector env's
    sub-envs may be spread over several servers, one client each), the episode settings, and the
    scene list the seeds pick from.
    """

    clients: tuple[Client, ...]
    owned_client: bool
    servers: list[LocalServer]
    scenes: tuple[str, ...]
    sensors: Sensors
    horizon: int
    reward: RewardWeights | None
    agent: str | None = None

    @property
    def client(self) -> Client:
        """The first (for the single env, the only) client."""
        return self.clients[0]

    @classmethod
    def connect(
        cls,
        address: str | Sequence[str] | None,
        client: Client | Sequence[Client] | None,
        token: str | None,
        tls: TlsSetting,
        split: Split | str | None,
        difficulty: Difficulty | str | None,
        scene: str | Sequence[str] | None,
        sensors: Sensors | Mapping[str, Any] | None,
        horizon: int,
        reward: RewardWeights | Mapping[str, Any] | None,
        agent: str | None = None,
        servers: int | None = None,
    ) -> Setup:
        """Connects to `client` (one or a list), else to `address` (one or a list), else to
        `servers` (default 1) `LocalServer`s started here over Unix domain sockets, started at once.
        Several servers must serve the same dataset (`ValueError` otherwise). The scenes come from
        `scene`, else from the first server's list of `split` and `difficulty`.
        """
        # Mappings of the fields too, so that an env spec's kwargs can be JSON (Minari stores them).
        sensors = of_fields(Sensors, sensors, "sensors")
        reward = of_fields(RewardWeights, reward, "reward")
        if servers is not None and (address is not None or client is not None):
            raise ValueError(
                "servers is the number of servers started here: leave it out with address or client "
                "(a list of addresses spreads the sub-envs over those servers)"
            )
        if servers is not None and servers < 1:
            raise ValueError(f"servers must be at least 1, got {servers}")
        owned = client is None
        started: list[LocalServer] = []
        clients: list[Client] = []
        try:
            if client is not None:
                clients = [client] if isinstance(client, Client) else list(client)
                if not clients or not all(isinstance(c, Client) for c in clients):
                    raise ValueError(f"client: a Client or a non-empty list of Clients, got {client!r}")
            else:
                if address is None:
                    started = start_servers(servers or 1, unix_socket="auto")
                    addresses = [server.address for server in started]
                elif isinstance(address, str):
                    addresses = [address]
                else:
                    addresses = list(address)
                    if not addresses or not all(isinstance(a, str) and a for a in addresses):
                        raise ValueError(
                            f"address: an address or a non-empty list of addresses, got {address!r}"
                        )
                for one in addresses:
                    clients.append(Client(one, token=token, tls=tls))
            if len(clients) > 1:
                _check_same_dataset(clients)
            if isinstance(scene, str):
                if not scene:
                    raise ValueError("scene: an empty scene id (leave it out, None, to draw from the split)")
                scenes: tuple[str, ...] = (scene,)
            elif scene is not None:
                scenes = tuple(scene)
                if not scenes or not all(isinstance(s, str) and s for s in scenes):
                    raise ValueError(f"scene: a scene id or a non-empty list of scene ids, got {scene!r}")
            else:
                scenes = tuple(s.id for s in clients[0].scenes(split, difficulty, page_size=1000))
                if not scenes:
                    raise InvalidRequest(
                        f"the served dataset has no scenes of split {split!r}, difficulty {difficulty!r}"
                    )
        except BaseException:
            if owned:
                for made in clients:
                    made.close()
            for server in started:
                server.stop()
            raise
        return cls(tuple(clients), owned, started, scenes, sensors or Sensors(), horizon, reward, agent)

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
        """Closes the clients the env made and stops the servers it started."""
        if self.owned_client:
            for client in self.clients:
                client.close()
        servers, self.servers = self.servers, []
        for server in servers:
            server.stop()


def _check_same_dataset(clients: Sequence[Client]) -> None:
    """Raises `ValueError` unless every client's server serves the same dataset (name, scene count,
    counts by split): a sub-env's scene must exist on whichever server plays it.
    """
    seen = []
    for client in clients:
        dataset = client.describe_dataset()
        # The counts by split come as a protobuf map, in no fixed order.
        seen.append((client.address, (dataset.name, dataset.scenes, tuple(sorted(dataset.by_split.items())))))
    if len({key for _, key in seen}) > 1:
        listed = "; ".join(f"{address}: {name} ({scenes} scenes)" for address, (name, scenes, _) in seen)
        raise ValueError(f"the servers serve different datasets: {listed}")
