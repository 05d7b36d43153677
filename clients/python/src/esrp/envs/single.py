"""`RearrangeEnv`: the Gymnasium env `esrp/Rearrange-v1`, one server episode stepped with unary calls."""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from typing import Any, SupportsFloat, cast

import gymnasium
import numpy as np
import numpy.typing as npt
from gymnasium import spaces

from .._client import Client, Episode
from .._common import TlsSetting
from .._errors import EpisodeNotFound, ServerUnavailable
from .._values import ActionLike, Difficulty, RewardWeights, Sensors, Split
from ._shared import METADATA, Images, ObsDict, Setup, frame, observation_space, reset_info, step_info


class RearrangeEnv(gymnasium.Env[ObsDict, np.int64]):
    """The ESRP task as a Gymnasium env (`gymnasium.make("esrp/Rearrange-v1", ...)`).

    Args:
        address: The server (`host:port`, or `unix:PATH` for a `--listen-unix` socket); None
            starts a `LocalServer` that the env owns, reached over its Unix domain socket.
        client: A `Client` to share instead (the env then does not close it).
        token: The server's bearer token.
        tls: TLS setting, as `Client`'s.
        split: Scenes to draw from: `train` (default), `test`, `challenge`, `minival`, or None for
            all.
        difficulty: Only `easy`, `medium` or `hard` scenes (None: all).
        scene: Always play this scene id, or draw from these ids (ignores split and difficulty).
        sensors: Optional sensors and image size (default: none, 128 px), as `Sensors` or a
            mapping of its fields (`{"resolution": 64}`: JSON, for env specs).
        horizon: Step limit; 0: each scene's own (the server truncates).
        reward: Reward weights (the server's defaults for fields left None), as `RewardWeights`
            or a mapping of its fields.
        agent: The agent's name for the server's records of its episodes (`Client.create_episode`'s
            `agent`; None: `"unnamed"`).
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

    metadata = METADATA

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
        sensors: Sensors | Mapping[str, Any] | None = None,
        horizon: int = 0,
        reward: RewardWeights | Mapping[str, Any] | None = None,
        agent: str | None = None,
        render_mode: str | None = None,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r}: use None or 'rgb_array'")
        self.render_mode = render_mode
        one_address = address is None or isinstance(address, str)
        if not one_address or not (client is None or isinstance(client, Client)):
            raise TypeError(
                "RearrangeEnv plays one episode on one server: give one address or client "
                "(RearrangeVectorEnv spreads its sub-envs over several)"
            )
        self._setup = Setup.connect(
            address, client, token, tls, split, difficulty, scene, sensors, horizon, reward, agent
        )
        self.observation_space = cast(spaces.Space[ObsDict], observation_space(self._setup.sensors))
        self.action_space = spaces.Discrete(6)
        self._image_spec = Images(self._setup.sensors)
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
                scene, sensors=setup.sensors, horizon=setup.horizon, reward=setup.reward, agent=setup.agent
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
        return self._last, reset_info(self._episode.scene, self._setup.horizon)

    def step(self, action: ActionLike) -> tuple[ObsDict, SupportsFloat, bool, bool, dict[str, Any]]:
        """Takes one action (0..5, see `esrp.Action`)."""
        if self._episode is None or self._goal is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        spec = self._image_spec
        columns = self._episode.step_columns(action, spec.sensors)
        observation = spec.observation(
            {key: column[0] for key, column in columns.images.items()}, columns.grasping[0], self._goal
        )
        self._last = observation
        return (
            observation,
            columns.rewards[0],
            columns.terminated[0],
            columns.truncated[0],
            step_info(columns, 0),
        )

    def render(self) -> npt.NDArray[np.uint8] | None:
        """With `render_mode="rgb_array"`: the ego view, the goal and the current top-down (when
        the sensor is on) side by side, (R, 2R or 3R, 3) uint8.
        """
        if self.render_mode != "rgb_array" or self._last is None or self._goal is None:
            return None
        return frame(self._last, self._goal)

    def close(self) -> None:
        """Closes the server episode (and the client and server the env started)."""
        episode, self._episode = self._episode, None
        if episode is not None:
            with contextlib.suppress(EpisodeNotFound, ServerUnavailable):
                episode.close()
        self._setup.close()
        super().close()
