"""The Gymnasium environment `esrp/Rearrange-v1` and its native vector env (needs the `gym` extra).

`RearrangeEnv` owns one server episode and steps it with unary calls. `RearrangeVectorEnv` owns N
episodes on one StepStream and advances them all with one pipelined round trip per step (steps and
autoresets together): no subprocesses, no per-env threads. Both follow Gymnasium 1.x exactly:
`reset(seed=s)` seeds the env's `np_random`, which picks the scene from the filtered scene list, so
the same seed plays the same scene; the vector env seeds sub-env i with `s + i`, exactly as
`SyncVectorEnv` over N `RearrangeEnv`s would, and gives bit-identical observations.

Observations are dicts: `ego_rgb` and `goal_rgb` (R, R, 3) uint8, `grasping` 0/1 (Discrete(2)), and
`depth` (R, R) float32, `segmentation` (R, R) uint32 and `current_top_down` (R, R, 3) uint8 for the
sensors that are on. Actions are `Discrete(6)` with the codes of `esrp.Action`. Infos: the scene's
id, difficulty, room type, object count and horizon on resets; `is_success` on the step that ends an
episode.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, SupportsFloat, cast

import gymnasium
import numpy as np
import numpy.typing as npt
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from . import _convert
from ._client import Client, Episode, EpisodeStream
from ._common import TlsSetting
from ._errors import (
    EpisodeEnded,
    EpisodeNotFound,
    EsrpError,
    InvalidRequest,
    ProtocolError,
    ServerUnavailable,
)
from ._local import LocalServer
from ._values import ActionLike, Difficulty, EpisodeMetrics, RewardWeights, SceneSummary, Sensors, Split

__all__ = ["RearrangeEnv", "RearrangeVectorEnv", "observation_space"]

ObsDict = dict[str, npt.NDArray[Any]]

_METADATA: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 10}


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


def _step_info(columns: _convert.StepColumns, position: int) -> dict[str, Any]:
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
        info["metrics"] = _metrics_info(metrics)
        info["is_success"] = metrics.success
    return info


def _reset_info(scene: SceneSummary, horizon: int) -> dict[str, Any]:
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


def _metrics_info(metrics: EpisodeMetrics) -> dict[str, Any]:
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


def _frame(observation: ObsDict, goal: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """The ego view, the goal and (when the sensor is on) the current top-down, side by side."""
    views = [observation["ego_rgb"], goal]
    if "current_top_down" in observation:
        views.append(observation["current_top_down"])
    return np.concatenate(views, axis=1)


class _Images:
    """Where a step answer's images go in an observation: the sensors' layout (key, message field,
    bytes per pixel, dtype), and each key's array shape.
    """

    def __init__(self, sensors: Sensors) -> None:
        side = sensors.resolution
        self.resolution = side
        self.layout = _convert.image_layout(sensors)
        self.keys = tuple(key for key, _, _, _ in self.layout)
        self.shapes = {key: (side, side, 3) if size == 3 else (side, side) for key, _, size, _ in self.layout}
        self.dtypes = {key: dtype for key, _, _, dtype in self.layout}

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


@dataclass
class _Setup:
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
        sensors: Sensors | None,
        horizon: int,
        reward: RewardWeights | None,
    ) -> _Setup:
        server = None
        owned = client is None
        if client is None:
            if address is None:
                server = LocalServer().start()
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
        return cls(client, owned, server, scenes, sensors or Sensors(), horizon, reward)

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


class RearrangeEnv(gymnasium.Env[ObsDict, np.int64]):
    """The ESRP task as a Gymnasium env (`gymnasium.make("esrp/Rearrange-v1", ...)`).

    Args:
        address: The server (`host:port`); None starts a `LocalServer` that the env owns.
        client: A `Client` to share instead (the env then does not close it).
        token: The server's bearer token.
        tls: TLS setting, as `Client`'s.
        split: Scenes to draw from: `train` (default), `test`, or None for all.
        difficulty: Only `easy`, `medium` or `hard` scenes (None: all).
        scene: Always play this scene id, or draw from these ids (ignores split and difficulty).
        sensors: Optional sensors and image size (default: none, 128 px).
        horizon: Step limit; 0: each scene's own (the server truncates).
        reward: Reward weights (the server's defaults for fields left None).
        render_mode: None or `rgb_array` (ego view, goal and, with the sensor, current top-down).

    `reset(seed=s)` seeds `np_random`, which draws the scene; `reset(options={"scene": id})` plays
    `id` instead. The reset info has `scene_id`, `difficulty`, `room_type`, `objects` (movable
    objects) and `horizon` (the episode's step limit); a step's info has `accepted`, `collided`,
    `placed_count`, `step_index` and, on the step that ends the episode, `metrics` and
    `is_success` (Stable-Baselines3's convention). The horizon is each scene's and the server
    truncates at it: the registered spec has no `max_episode_steps` (no `TimeLimit`).

    Actions: an `esrp.ActionLike` (an int 0..5, a numpy integer, an integer-valued float, or a numpy
    array of one); any other value raises `InvalidRequest` before anything is sent.
    """

    metadata = _METADATA

    def __init__(
        self,
        address: str | None = None,
        *,
        client: Client | None = None,
        token: str | None = None,
        tls: TlsSetting = None,
        split: Split | str | None = "train",
        difficulty: Difficulty | str | None = None,
        scene: str | Sequence[str] | None = None,
        sensors: Sensors | None = None,
        horizon: int = 0,
        reward: RewardWeights | None = None,
        render_mode: str | None = None,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r}: use None or 'rgb_array'")
        self.render_mode = render_mode
        self._setup = _Setup.connect(
            address, client, token, tls, split, difficulty, scene, sensors, horizon, reward
        )
        self.observation_space = cast(spaces.Space[ObsDict], observation_space(self._setup.sensors))
        self.action_space = spaces.Discrete(6)
        self._image_spec = _Images(self._setup.sensors)
        self._episode: Episode | None = None
        self._scene: str | None = None  # the episode's scene id
        self._goal: npt.NDArray[np.uint8] | None = None
        self._last: ObsDict | None = None

    @property
    def client(self) -> Client:
        """The client the env uses."""
        return self._setup.client

    @property
    def scenes(self) -> tuple[str, ...]:
        """The scene ids `reset` draws from."""
        return self._setup.scenes

    @property
    def episode(self) -> Episode | None:
        """The server episode (None before the first reset)."""
        return self._episode

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[ObsDict, dict[str, Any]]:
        """Starts an episode on a scene drawn with `np_random` (or `options["scene"]`)."""
        super().reset(seed=seed)
        scene = self._setup.pick_scene(self.np_random, options)
        if self._episode is None:
            setup = self._setup
            self._episode = setup.client.create_episode(
                scene, sensors=setup.sensors, horizon=setup.horizon, reward=setup.reward
            )
            first = self._episode.observation
        else:
            # The same scene again restarts the episode where it is (the same first observation
            # and goal as a fresh one, without building the episode anew).
            first = self._episode.reset(None if scene == self._scene else scene)
        self._scene = scene
        assert first is not None
        assert first.goal_rgb is not None
        self._goal = first.goal_rgb
        images = {key: getattr(first, key) for key in self._image_spec.keys}
        self._last = self._image_spec.observation(images, first.grasping, self._goal)
        return self._last, _reset_info(self._episode.scene, self._setup.horizon)

    def step(self, action: ActionLike) -> tuple[ObsDict, SupportsFloat, bool, bool, dict[str, Any]]:
        """Takes one action (0..5, see `esrp.Action`)."""
        if self._episode is None or self._goal is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        message = self._episode._step_message(action)  # noqa: SLF001 - the package's own hot path
        spec = self._image_spec
        columns = _convert.step_columns((message,), spec.layout, spec.resolution)
        observation = spec.observation(
            {key: column[0] for key, column in columns.images.items()}, columns.grasping[0], self._goal
        )
        self._last = observation
        return (
            observation,
            columns.rewards[0],
            columns.terminated[0],
            columns.truncated[0],
            _step_info(columns, 0),
        )

    def render(self) -> npt.NDArray[np.uint8] | None:
        """With `render_mode="rgb_array"`: the ego view, the goal and the current top-down (when
        the sensor is on) side by side, (R, 2R or 3R, 3) uint8.
        """
        if self.render_mode != "rgb_array" or self._last is None or self._goal is None:
            return None
        return _frame(self._last, self._goal)

    def close(self) -> None:
        """Closes the server episode (and the client and server the env started)."""
        episode, self._episode = self._episode, None
        if episode is not None:
            with contextlib.suppress(EpisodeNotFound, ServerUnavailable):
                episode.close()
        self._setup.close()
        super().close()


_STEP_KEYS = ("accepted", "collided", "placed_count", "step_index")
_ENDED_KEYS = (*_STEP_KEYS, "metrics", "is_success")
# The dtypes `_add_info` gives the step keys: those of their Python values.
_STEP_DTYPES = (("accepted", bool), ("collided", bool), ("placed_count", int), ("step_index", int))
_RESET_KEYS = ("scene_id", "difficulty", "room_type", "objects", "horizon")
_FINAL_KEYS = ("final_obs", "final_info", *_RESET_KEYS)

# Reserve for a StepBatch answer's framing, per step (the info, reward and flags take ~60 bytes).
_STEP_OVERHEAD_BYTES = 512


class RearrangeVectorEnv(VectorEnv[ObsDict, npt.NDArray[np.int64], npt.NDArray[Any]]):
    """N ESRP episodes stepped together (`gymnasium.make_vec("esrp/Rearrange-v1", num_envs=N,
    vectorization_mode="vector_entry_point", ...)`): one StepBatch call per step, no subprocesses,
    no per-env threads.

    Arguments as `RearrangeEnv`'s, plus `num_envs` and `autoreset_mode` (`AutoresetMode` or its
    value; declared in `metadata["autoreset_mode"]`):

    - `NEXT_STEP` (default): the step after an episode ended resets it instead of stepping it, with
      reward 0, not terminated, not truncated and the reset's info.
    - `SAME_STEP`: an episode that ends is reset in the same step; the returned observation is the
      reset's, and `infos["final_obs"]` / `infos["final_info"]` (masks `_final_obs`,
      `_final_info`) hold the last step's.
    - `DISABLED`: no autoreset; reset ended episodes with `reset(options={"reset_mask": mask})`.
      Stepping an ended one raises `EpisodeEnded` and moves no episode.

    With `scene_per_env=True`, `scene` lists one scene id per sub-env and sub-env i plays
    `scene[i]` at every reset (unless `options["scene"]` names another): a fixed set of scenes,
    each episode restarted where it is when it ends (no new scene sent, no episode built anew).
    Seeds still advance each sub-env's generator as a drawn scene would.

    Infos are dicts of arrays with `_key` masks, exactly as Gymnasium's `VectorEnv._add_info`
    builds them (here a column at a time). Observations are fresh arrays at every call (keeping
    them is safe). The episodes are created, reset and closed on the env's StepStream, so the
    server closes them should the env's process die; the steps of a wave go in one StepBatch
    (split only beyond the server's `max_batch` or half its message limit), whose single answer
    costs far less to receive in Python than one stream answer per episode.
    """

    metadata = {**_METADATA, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 1,
        address: str | None = None,
        *,
        client: Client | None = None,
        token: str | None = None,
        tls: TlsSetting = None,
        split: Split | str | None = "train",
        difficulty: Difficulty | str | None = None,
        scene: str | Sequence[str] | None = None,
        sensors: Sensors | None = None,
        horizon: int = 0,
        reward: RewardWeights | None = None,
        render_mode: str | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        scene_per_env: bool = False,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        if render_mode is not None and render_mode not in _METADATA["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r}: use None or 'rgb_array'")
        self.autoreset_mode = (
            autoreset_mode if isinstance(autoreset_mode, AutoresetMode) else AutoresetMode(autoreset_mode)
        )
        self.metadata = {**_METADATA, "autoreset_mode": self.autoreset_mode}
        self.num_envs = num_envs
        self.render_mode = render_mode
        if scene_per_env and (scene is None or (1 if isinstance(scene, str) else len(scene)) != num_envs):
            raise ValueError(
                f"scene_per_env: scene must list one scene id per sub-env ({num_envs}), got {scene!r}"
            )
        self._setup = _Setup.connect(
            address, client, token, tls, split, difficulty, scene, sensors, horizon, reward
        )
        self._scene_per_env = scene_per_env
        self.single_observation_space = observation_space(self._setup.sensors)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.single_action_space = spaces.Discrete(6)
        self.action_space = batch_space(self.single_action_space, num_envs)
        side = self._setup.sensors.resolution
        self._image_spec = _Images(self._setup.sensors)
        # The observation keys in the space's order (that of Gymnasium's batches).
        self._keys = tuple(self.single_observation_space.spaces)
        self._stream: EpisodeStream | None = None
        self._episode_ids: list[str | None] = [None] * num_envs
        self._scene_ids: list[str | None] = [None] * num_envs  # each episode's scene
        self._rngs: list[np.random.Generator | None] = [None] * num_envs
        # Each sub-env's last observation: its images as the answer's bytes or read-only views (never
        # written), whether it grasps, and its goal, in a batch array that only resets write to.
        self._last_images: dict[str, list[Any]] = {key: [None] * num_envs for key in self._image_spec.keys}
        self._grasping = np.zeros(num_envs, dtype=np.int64)
        self._goals = np.zeros((num_envs, side, side, 3), dtype=np.uint8)
        self._started = np.zeros(num_envs, dtype=np.bool_)
        self._autoreset_envs = np.zeros(num_envs, dtype=np.bool_)
        self._chunk: int | None = None  # steps per StepBatch, from the server's limits

    @property
    def client(self) -> Client:
        """The client the env uses."""
        return self._setup.client

    @property
    def scenes(self) -> tuple[str, ...]:
        """The scene ids resets draw from (with `scene_per_env`, sub-env i's is the i-th)."""
        return self._setup.scenes

    @property
    def episode_ids(self) -> tuple[str | None, ...]:
        """The server episode of each sub-env (None before its first reset)."""
        return tuple(self._episode_ids)

    def _rng(self, index: int) -> np.random.Generator:
        rng = self._rngs[index]
        if rng is None:
            rng, _ = seeding.np_random()
            self._rngs[index] = rng
        return rng

    def _open_stream(self) -> EpisodeStream:
        if self._stream is None:
            self._stream = self._setup.client.episode_stream(window=1)
        return self._stream

    def _send_reset(self, stream: EpisodeStream, index: int, options: Mapping[str, Any] | None) -> str:
        """Sends sub-env `index`'s reset (its creation, the first time); returns the scene."""
        own = self._setup.scenes[index] if self._scene_per_env else None
        scene = self._setup.pick_scene(self._rng(index), options, own)
        episode = self._episode_ids[index]
        if episode is None:
            setup = self._setup
            stream.create(scene, sensors=setup.sensors, horizon=setup.horizon, reward=setup.reward)
        else:
            # The same scene again restarts the episode where it is (see `RearrangeEnv.reset`).
            stream.reset(episode, None if scene == self._scene_ids[index] else scene)
        return scene

    def _take_reset(self, stream: EpisodeStream, index: int, scene: str) -> dict[str, Any]:
        """Reads sub-env `index`'s reset answer (sent by `_send_reset` for `scene`) into its last
        observation; returns the reset's info (as `RearrangeEnv.reset`'s).
        """
        answer = stream.next()
        assert answer is not None
        if self._episode_ids[index] is None:
            created = answer.created()
            self._episode_ids[index] = created.episode_id
            first = created.observation
        else:
            first = answer.observation()
        if answer.scene is None:
            raise ProtocolError(f"the answer to the reset of sub-env {index} names no scene")
        self._scene_ids[index] = scene
        assert first.goal_rgb is not None
        for key in self._image_spec.keys:
            self._last_images[key][index] = getattr(first, key)
        self._grasping[index] = first.grasping
        self._goals[index] = first.goal_rgb
        self._started[index] = True
        return _reset_info(answer.scene, self._setup.horizon)

    def reset(
        self,
        *,
        seed: int | list[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[ObsDict, dict[str, Any]]:
        """Resets every sub-env, or those of `options["reset_mask"]` (a bool array of shape
        (num_envs,)). `seed`: None, an int (sub-env i gets seed + i) or one seed per sub-env.
        """
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(
                "If seeds are passed as a list the length must match "
                f"num_envs={self.num_envs} but got length={len(seeds)}."
            )
        options = dict(options) if options is not None else None
        mask = self._reset_mask(options)
        self._autoreset_envs[mask] = False
        if not np.all(self._started[~mask]):
            raise ValueError("the first reset must reset every sub-environment (no reset_mask)")
        stream = self._open_stream()
        scenes: dict[int, str] = {}
        for index in np.flatnonzero(mask).tolist():
            if seeds[index] is not None:
                self._rngs[index], _ = seeding.np_random(seeds[index])
            scenes[index] = self._send_reset(stream, index, options)
        infos: dict[str, Any] = {}
        for index, scene in scenes.items():
            infos = self._add_info(infos, self._take_reset(stream, index, scene), index)
        return self._batch(), infos

    def _reset_mask(self, options: dict[str, Any] | None) -> npt.NDArray[np.bool_]:
        if options is None or "reset_mask" not in options:
            return np.ones(self.num_envs, dtype=np.bool_)
        mask = options.pop("reset_mask")
        if not isinstance(mask, np.ndarray):
            raise TypeError(f"`options['reset_mask']` must be a numpy array, got {type(mask)}")
        if mask.shape != (self.num_envs,):
            raise ValueError(
                f"`options['reset_mask']` must have shape `({self.num_envs},)`, got {mask.shape}"
            )
        if mask.dtype != np.bool_:
            raise TypeError(f"`options['reset_mask']` must have `dtype=np.bool_`, got {mask.dtype}")
        if not np.any(mask):
            raise ValueError(
                "`options['reset_mask']` must contain a boolean array with at least one True value, "
                f"got reset_mask={mask}"
            )
        return mask

    def step(
        self, actions: npt.NDArray[np.int64] | Sequence[int]
    ) -> tuple[
        ObsDict, npt.NDArray[np.float64], npt.NDArray[np.bool_], npt.NDArray[np.bool_], dict[str, Any]
    ]:
        """Steps every sub-env (or autoresets it, in NEXT_STEP mode) in one StepBatch round trip;
        the autoresets go on the stream at the same time.
        """
        actions = np.asarray(actions)
        n = self.num_envs
        if actions.shape != (n,):
            raise ValueError(f"actions must have shape ({n},), got {actions.shape}")
        if actions.dtype.kind == "f" and np.all(np.isfinite(actions) & (actions == np.round(actions))):
            actions = actions.astype(np.int64)  # integer-valued floats, as RearrangeEnv takes them
        if actions.dtype.kind not in "iu" or np.any((actions < 0) | (actions > 5)):
            raise InvalidRequest(f"actions must be codes 0..5 (esrp.Action), got {actions}")
        if self._stream is None or not np.all(self._started):
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        if self.autoreset_mode == AutoresetMode.DISABLED and np.any(self._autoreset_envs):
            ended = np.flatnonzero(self._autoreset_envs).tolist()
            raise EpisodeEnded(
                f"sub-environments {ended} have ended and autoreset_mode is DISABLED: reset them with "
                "reset(options={'reset_mask': mask}) first (no episode moved)"
            )
        stream = self._stream
        sent: dict[int, str] = {}
        resets: dict[int, dict[str, Any]] = {}
        if self.autoreset_mode == AutoresetMode.NEXT_STEP and np.any(self._autoreset_envs):
            sent = {
                i: self._send_reset(stream, i, None) for i in np.flatnonzero(self._autoreset_envs).tolist()
            }
            stepped: list[int] = np.flatnonzero(~self._autoreset_envs).tolist()
        else:
            stepped = list(range(n))
        try:
            columns = self._step_batch(stepped, actions)
        finally:
            # The resets were answered on the stream meanwhile (whatever became of the batch).
            for i, scene in sent.items():
                resets[i] = self._take_reset(stream, i, scene)
        rewards = np.zeros(n, dtype=np.float64)
        terminations = np.zeros(n, dtype=np.bool_)
        truncations = np.zeros(n, dtype=np.bool_)
        if stepped:
            rewards[stepped] = columns.rewards
            terminations[stepped] = columns.terminated
            truncations[stepped] = columns.truncated
            self._grasping[stepped] = columns.grasping
            for key, column in columns.images.items():
                if len(stepped) == n:
                    self._last_images[key] = column
                else:
                    images = self._last_images[key]
                    for i, data in zip(stepped, column, strict=True):
                        images[i] = data
        finals: dict[int, tuple[ObsDict, dict[str, Any]]] = {}
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            ended = np.flatnonzero(terminations | truncations).tolist()
            # The final observations are handed out one by one: each gets a goal of its own.
            # (Every sub-env was stepped, so sub-env i's answer is at position i.)
            finals = {i: (self._single_observation(i), _step_info(columns, i)) for i in ended}
            sent = {i: self._send_reset(stream, i, None) for i in ended}
            resets = {i: self._take_reset(stream, i, sent[i]) for i in ended}
        infos = self._step_infos(columns, stepped, resets, finals)
        self._autoreset_envs = np.logical_or(terminations, truncations)
        return self._batch(), rewards, terminations, truncations, infos

    def _step_batch(self, stepped: list[int], actions: npt.NDArray[Any]) -> _convert.StepColumns:
        """Steps sub-envs `stepped` (in order) with one StepBatch, or several when the server's
        limits want it; their answers as columns in the same order.
        """
        spec = self._image_spec
        columns = _convert.StepColumns(spec.keys)
        if not stepped:
            return columns
        client = self._setup.client
        if self._chunk is None:
            limits = client.server_info().limits
            per_step = _STEP_OVERHEAD_BYTES + sum(spec.resolution**2 * size for _, _, size, _ in spec.layout)
            self._chunk = max(1, min(limits.max_batch, limits.max_message_bytes // 2 // per_step))
        episode_ids = self._episode_ids
        codes = actions.tolist()
        size = self._chunk
        # Beyond the limits, the chunks go at once (the server renders one while another's answer
        # travels); below them one call is best: splitting a wave measured no faster and costs
        # the client more.
        chunks = [stepped[start : start + size] for start in range(0, len(stepped), size)]
        waits = [
            client._step_batch_started(  # noqa: SLF001 - the package's own hot path
                [cast(str, episode_ids[i]) for i in chunk], [codes[i] for i in chunk]
            )
            for chunk in chunks[:-1]
        ]
        last = chunks[-1]
        messages = client._step_batch_messages(  # noqa: SLF001
            [cast(str, episode_ids[i]) for i in last], [codes[i] for i in last]
        )
        for wait in waits:
            _convert.step_columns(wait(), spec.layout, spec.resolution, into=columns)
        _convert.step_columns(messages, spec.layout, spec.resolution, into=columns)
        return columns

    def _step_infos(
        self,
        columns: _convert.StepColumns,
        stepped: list[int],
        resets: Mapping[int, dict[str, Any]],
        finals: Mapping[int, tuple[ObsDict, dict[str, Any]]],
    ) -> dict[str, Any]:
        """The step's infos, equal to what `_add_info` over each sub-env's info makes (the same
        keys in the same order, arrays of the same dtypes, masks), built a column at a time.
        """
        n = self.num_envs
        kinds: list[tuple[str, ...]] = [_STEP_KEYS] * n
        metrics_envs: dict[int, EpisodeMetrics] = {}
        for position, metrics in columns.metrics.items():
            metrics_envs[stepped[position]] = metrics
            kinds[stepped[position]] = _ENDED_KEYS
        for i in resets:
            kinds[i] = _RESET_KEYS
        for i in finals:
            kinds[i] = _FINAL_KEYS
        # `_add_info` adds a key (then its mask) when the first sub-env that has it comes.
        order: dict[str, None] = {}
        for kind in dict.fromkeys(kinds):
            order.update(dict.fromkeys(kind))
        values: dict[str, Any] = {}
        masks: dict[str, npt.NDArray[np.bool_]] = {}
        if stepped:
            step_mask = np.zeros(n, dtype=np.bool_)
            step_mask[stepped] = True
            step_mask[list(finals)] = False
            for key, dtype in _STEP_DTYPES:
                column = np.zeros(n, dtype=dtype)
                column[stepped] = getattr(columns, key)
                column[~step_mask] = 0
                values[key], masks[key] = column, step_mask.copy()
        metrics_infos: dict[str, Any] = {}
        for i, metrics in metrics_envs.items():
            if i not in finals:
                metrics_infos = self._add_info(metrics_infos, _metrics_info(metrics), i)
        if metrics_infos:
            ended_here = [i for i in metrics_envs if i not in finals]
            values["metrics"] = metrics_infos
            masks["metrics"] = np.zeros(n, dtype=np.bool_)
            masks["metrics"][ended_here] = True
            values["is_success"] = np.zeros(n, dtype=bool)
            values["is_success"][ended_here] = [metrics_envs[i].success for i in ended_here]
            masks["is_success"] = masks["metrics"].copy()
        final_infos: dict[str, Any] = {}
        if finals:
            final_obs = np.full(n, None, dtype=object)
            for i, (observation, info) in finals.items():
                final_obs[i] = observation
                final_infos = self._add_info(final_infos, info, i)
            values["final_obs"], values["final_info"] = final_obs, final_infos
            masks["final_obs"] = np.zeros(n, dtype=np.bool_)
            masks["final_obs"][list(finals)] = True
            masks["final_info"] = masks["final_obs"].copy()
        if resets:
            reset_infos: dict[str, Any] = {}
            for i, info in resets.items():
                reset_infos = self._add_info(reset_infos, info, i)
            for key in _RESET_KEYS:
                values[key], masks[key] = reset_infos[key], reset_infos[f"_{key}"]
        infos: dict[str, Any] = {}
        for key in order:
            infos[key], infos[f"_{key}"] = values[key], masks[key]
        return infos

    def _single_observation(self, index: int) -> ObsDict:
        """Sub-env `index`'s last observation as `RearrangeEnv` gives it (views, a goal copy)."""
        images = {key: column[index] for key, column in self._last_images.items()}
        return self._image_spec.observation(images, self._grasping[index], self._goals[index])

    def _batch(self) -> ObsDict:
        """The sub-envs' last observations in fresh arrays (never reused, so keeping them is safe),
        in the key order of the observation space.
        """
        n = self.num_envs
        batch: dict[str, npt.NDArray[Any]] = {
            "goal_rgb": self._goals.copy(),
            "grasping": self._grasping.copy(),
        }
        spec = self._image_spec
        for key in spec.keys:
            # One copy of every sub-env's bytes into a new buffer (the answers' bytes and views
            # export their memory as they are).
            joined = bytearray().join(self._last_images[key])
            batch[key] = np.frombuffer(joined, dtype=spec.dtypes[key]).reshape(n, *spec.shapes[key])
        return {key: batch[key] for key in self._keys}

    def render(self) -> tuple[npt.NDArray[np.uint8], ...] | None:
        """With `render_mode="rgb_array"`: one frame per sub-env, as `RearrangeEnv.render`."""
        if self.render_mode != "rgb_array" or not np.all(self._started):
            return None
        return tuple(_frame(self._single_observation(i), self._goals[i]) for i in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:  # noqa: ANN401
        """Closes every server episode (on the stream, waiting for the answers), the stream, and
        the client and server the env started.
        """
        stream, self._stream = self._stream, None
        if stream is not None:
            try:
                for answer in stream:  # answers of a step that raised
                    del answer
                for episode in self._episode_ids:
                    if episode is not None:
                        stream.close_episode(episode)
                for answer in stream:
                    del answer  # An episode already gone is as good as closed.
            except EsrpError:
                pass  # The stream broke: the server closes its episodes with it.
            finally:
                stream.close()
        self._episode_ids = [None] * self.num_envs
        self._setup.close()
