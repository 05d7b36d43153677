"""`RearrangeVectorEnv`: N ESRP episodes owned by one StepStream, advanced together with one
StepBatch round trip per step (its steps and autoresets in one message): no subprocesses, no
per-env threads. Its sub-envs may be spread over several servers (one StepStream and one StepBatch
each, sent at once).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, cast

import grpc
import gymnasium
import numpy as np
import numpy.typing as npt
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .. import _malloc_setup
from .._client import Client, EpisodeStream, StepPart, step_columns_across
from .._common import TlsSetting
from .._errors import EpisodeEnded, EsrpError, InvalidRequest, ProtocolError
from .._values import (
    ActionLike,
    Difficulty,
    EpisodeMetrics,
    Observation,
    RewardWeights,
    SceneSummary,
    Sensors,
    Split,
    StepColumns,
    action_value,
    unknown_action,
)
from ._shared import (
    METADATA,
    Images,
    ObsDict,
    Setup,
    frame,
    metrics_info,
    observation_space,
    reset_info,
    step_info,
)

_STEP_KEYS = ("accepted", "collided", "placed_count", "step_index")
_ENDED_KEYS = (*_STEP_KEYS, "metrics", "is_success")
# The dtypes `_add_info` gives the step keys: those of their Python values.
_STEP_DTYPES = (("accepted", bool), ("collided", bool), ("placed_count", int), ("step_index", int))
_RESET_KEYS = ("scene_id", "difficulty", "room_type", "objects", "horizon")
_FINAL_KEYS = ("final_obs", "final_info", *_RESET_KEYS)


def action_codes(actions: npt.NDArray[Any] | Sequence[ActionLike], num_envs: int) -> list[int]:
    """The action codes of a vector step: `num_envs` actions, each taken as a single env's step
    takes it (`esrp.ActionLike`: an int, a numpy integer, an integer-valued float, or a numpy
    array of one), as an array of shape `(num_envs,)` or `(num_envs, 1)` or a sequence. Raises
    `ValueError` for another shape, and `InvalidRequest` for an action that is not a code 0..5, in
    the server's words (`actions[i].action: unknown action code ...`), before anything is sent: a
    batch that the server splits must not move some sub-envs and then fail.
    """
    listed = isinstance(actions, Sequence) and not isinstance(actions, str)
    if not isinstance(actions, np.ndarray) and not listed:
        actions = np.asarray(actions)  # a scalar, or another array-like: its shape says
    if isinstance(actions, np.ndarray):
        if actions.shape == (num_envs, 1):
            actions = actions.reshape(num_envs)
        if actions.shape != (num_envs,):
            raise ValueError(f"actions must have shape ({num_envs},), got {actions.shape}")
        if actions.dtype.kind in "iu" and np.all((actions >= 0) & (actions <= 5)):
            return cast(list[int], actions.tolist())  # the common case, at once
        items: list[object] = list(actions)
    else:
        items = list(cast(Sequence[object], actions))
        if len(items) != num_envs:
            raise ValueError(f"actions must be {num_envs} actions (shape ({num_envs},)), got {len(items)}")
    codes: list[int] = []
    for i, action in enumerate(items):
        code = action_value(action)
        if code is None or not 0 <= code <= 5:
            message = unknown_action(action, f"actions[{i}]")
            raise InvalidRequest(message, code=grpc.StatusCode.INVALID_ARGUMENT)
        codes.append(code)
    return codes


def _server_count(
    address: str | Sequence[str] | None, client: Client | Sequence[Client] | None, servers: int | None
) -> int:
    """How many servers the sub-envs are spread over, as far as the arguments say (what
    `Setup.connect` checks further).
    """
    if client is not None:
        return 1 if isinstance(client, Client) else len(client)
    if address is not None:
        return 1 if isinstance(address, str) else len(address)
    return servers if servers is not None else 1


class RearrangeVectorEnv(VectorEnv[ObsDict, npt.NDArray[np.int64], npt.NDArray[Any]]):
    """N ESRP episodes stepped together (`gymnasium.make_vec("esrp/Rearrange-v1", num_envs=N,
    vectorization_mode="vector_entry_point", ...)`): one StepBatch call per step, no subprocesses,
    no per-env threads.

    Arguments as `RearrangeEnv`'s, plus `num_envs`, `max_episode_steps` (None, or truncate each
    episode after that many steps, as `gymnasium.make(..., max_episode_steps=N)`'s `TimeLimit`
    around a `RearrangeEnv` does; `make_vec` passes it) and `autoreset_mode` (`AutoresetMode` or its
    value; declared in `metadata["autoreset_mode"]`):

    - `NEXT_STEP` (default): the step after an episode ended resets it instead of stepping it, with
      reward 0, not terminated, not truncated and the reset's info.
    - `SAME_STEP`: an episode that ends is reset in the same step; the returned observation is the
      reset's, and `infos["final_obs"]` / `infos["final_info"]` (masks `_final_obs`,
      `_final_info`) hold the last step's.
    - `DISABLED`: no autoreset; reset ended episodes with `reset(options={"reset_mask": mask})`.
      Stepping an ended one raises `EpisodeEnded` and moves no episode.

    `reset(options={"scene": id})` plays `id` in every sub-env reset, and `{"scene": [id_0, ...,
    id_{N-1}]}` plays `id_i` in sub-env i (None: its own pick; a masked reset reads the entries of
    the sub-envs it resets).

    With `scene_per_env=True`, `scene` lists one scene id per sub-env and sub-env i plays
    `scene[i]` at every reset (unless `options["scene"]` names another): a fixed set of scenes,
    each episode restarted where it is when it ends (no new scene sent, no episode built anew).
    Seeds still advance each sub-env's generator as a drawn scene would.

    After `close()` (idempotent), `reset` and `step` raise `gymnasium.error.ClosedEnvironmentError`.

    Infos are dicts of arrays with `_key` masks, exactly as Gymnasium's `VectorEnv._add_info`
    builds them (here a column at a time). Observations are fresh arrays at every call (keeping
    them is safe). The episodes are created and closed on the env's StepStream, so the server
    closes them should the env's process die; a step's steps and autoresets go in one StepBatch
    (split only beyond the server's `max_batch` or half its message limit), whose single answer
    costs far less to receive in Python than one stream answer per episode.

    Several servers: `address` a list of addresses (or `client` a list of clients), or `servers=K`
    with neither, to start K local servers over Unix domain sockets (stopped at `close()`). The
    sub-envs are spread over them in contiguous blocks of near-equal size (with 64 sub-envs over 3
    servers: 0-21, 22-42, 43-63), each block's episodes living on its server; a step sends every
    server its StepBatch before it waits for any answer, so that the servers step and render at
    once. One server's throughput is capped by its device's queue; several on one machine scale
    with its cores and queues. Observations, rewards and infos are those of one server (same
    scenes and actions, same results: the servers must serve the same dataset, checked at the
    start). At most one server per sub-env.
    """

    metadata = {**METADATA, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 1,
        address: str | Sequence[str] | None = None,
        *,
        client: Client | Sequence[Client] | None = None,
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
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        scene_per_env: bool = False,
        servers: int | None = None,
        max_episode_steps: int | None = None,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        limit = max_episode_steps
        if limit is not None and (not isinstance(limit, int) or isinstance(limit, bool) or limit < 1):
            raise ValueError(f"max_episode_steps must be None or a positive int, got {max_episode_steps!r}")
        self.max_episode_steps = max_episode_steps
        spread = _server_count(address, client, servers)
        if spread > num_envs:
            raise ValueError(f"{spread} servers for {num_envs} sub-envs: give at most one server per sub-env")
        # Its multi-megabyte step buffers kept mapped from step to step (see esrp._malloc_setup).
        _malloc_setup.apply()
        if render_mode is not None and render_mode not in METADATA["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r}: use None or 'rgb_array'")
        self.autoreset_mode = (
            autoreset_mode if isinstance(autoreset_mode, AutoresetMode) else AutoresetMode(autoreset_mode)
        )
        self.metadata = {**METADATA, "autoreset_mode": self.autoreset_mode}
        self.num_envs = num_envs
        self.render_mode = render_mode
        if scene_per_env and (scene is None or (1 if isinstance(scene, str) else len(scene)) != num_envs):
            raise ValueError(
                f"scene_per_env: scene must list one scene id per sub-env ({num_envs}), got {scene!r}"
            )
        self._setup = Setup.connect(
            address, client, token, tls, split, difficulty, scene, sensors, horizon, reward, agent, servers
        )
        # Sub-env i lives on server `_shard_of[i]` (each server's sub-envs a contiguous block).
        shards = len(self._setup.clients)
        self._shard_of = [i * shards // num_envs for i in range(num_envs)]
        self._scene_per_env = scene_per_env
        self.single_observation_space = observation_space(self._setup.sensors)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.single_action_space = spaces.Discrete(6)
        self.action_space = batch_space(self.single_action_space, num_envs)
        side = self._setup.sensors.resolution
        self._image_spec = Images(self._setup.sensors)
        # The observation keys in the space's order (that of Gymnasium's batches).
        self._keys = tuple(self.single_observation_space.spaces)
        self._streams: list[EpisodeStream | None] = [None] * shards
        self._episode_ids: list[str | None] = [None] * num_envs
        self._scene_ids: list[str | None] = [None] * num_envs  # each episode's scene
        # Each sub-env's generator and its seed, made at its first seeded reset or first draw.
        self._rngs: list[np.random.Generator | None] = [None] * num_envs
        self._seeds: list[int] = [0] * num_envs
        # Each sub-env's last observation: its images as the answer's bytes or read-only views (never
        # written), whether it grasps, and its goal, in a batch array that only resets write to.
        self._last_images: dict[str, list[Any]] = {key: [None] * num_envs for key in self._image_spec.keys}
        self._grasping = np.zeros(num_envs, dtype=np.int64)
        self._goals = np.zeros((num_envs, side, side, 3), dtype=np.uint8)
        self._started = np.zeros(num_envs, dtype=np.bool_)
        self._elapsed_steps = np.zeros(num_envs, dtype=np.int64)  # since each sub-env's reset
        self._autoreset_envs = np.zeros(num_envs, dtype=np.bool_)

    @property
    def client(self) -> Client:
        """The client the env uses (with several servers, the first server's)."""
        return self._setup.client

    @property
    def clients(self) -> tuple[Client, ...]:
        """The client of each server the sub-envs are spread over, in order (one without spreading)."""
        return self._setup.clients

    @property
    def server_of_env(self) -> tuple[int, ...]:
        """For each sub-env, the index in `clients` of the server its episode lives on."""
        return tuple(self._shard_of)

    @property
    def scenes(self) -> tuple[str, ...]:
        """The scene ids resets draw from (with `scene_per_env`, sub-env i's is the i-th)."""
        return self._setup.scenes

    @property
    def episode_ids(self) -> tuple[str | None, ...]:
        """The server episode of each sub-env (None before its first reset)."""
        return tuple(self._episode_ids)

    @property
    def np_random_seed(self) -> tuple[int, ...]:  # type: ignore[override]
        """Each sub-env's seed, as `SyncVectorEnv.np_random_seed` gives its sub-envs': that of its
        last seeded reset, else one drawn at random once.
        """
        for index in range(self.num_envs):
            self._rng(index)
        return tuple(self._seeds)

    @property  # type: ignore[misc]  # read-only, as SyncVectorEnv's
    def np_random(self) -> tuple[np.random.Generator, ...]:  # type: ignore[override]
        """Each sub-env's generator (which draws its scenes), as `SyncVectorEnv.np_random` gives
        its sub-envs'.
        """
        return tuple(self._rng(index) for index in range(self.num_envs))

    def _rng(self, index: int) -> np.random.Generator:
        rng = self._rngs[index]
        if rng is None:
            rng, self._seeds[index] = seeding.np_random()
            self._rngs[index] = rng
        return rng

    def _open_stream(self, shard: int) -> EpisodeStream:
        """Server `shard`'s StepStream, which creates and owns its sub-envs' episodes."""
        stream = self._streams[shard]
        if stream is None:
            stream = self._streams[shard] = self._setup.clients[shard].episode_stream(window=1)
        return stream

    def _pick_scenes(self, indices: list[int], options: Mapping[str, Any] | None) -> dict[int, str]:
        """The scenes of sub-envs `indices`' next resets, each drawn from its own generator (which
        advances alike whatever `options["scene"]` says): `options["scene"]` names one scene for
        all, or lists one per sub-env (None where the sub-env's own pick stands).
        """
        named = options.get("scene") if options else None
        listed = None if named is None or isinstance(named, str) else self._scene_list(named)
        scenes = {}
        for index in indices:
            own = self._setup.scenes[index] if self._scene_per_env else None
            if listed is None:
                scenes[index] = self._setup.pick_scene(self._rng(index), options, own)
            else:
                picked = self._setup.pick_scene(self._rng(index), None, own)
                entry = listed[index]
                scenes[index] = picked if entry is None else entry
        return scenes

    def _scene_list(self, named: object) -> list[str | None]:
        """`options["scene"]` given as one entry per sub-env, checked."""
        if not isinstance(named, (list, tuple, np.ndarray)) or len(named) != self.num_envs:
            raise ValueError(
                f"options['scene']: a scene id, or a list of {self.num_envs} (one per sub-env, None to "
                f"keep its own pick), got {named!r}"
            )
        listed = [None if entry is None else str(entry) for entry in named]
        if not all(entry is None or entry for entry in listed):
            raise ValueError(f"options['scene']: an empty scene id in {named!r}")
        return listed

    def _take_create(self, stream: EpisodeStream, index: int, scene: str) -> dict[str, Any]:
        """Reads sub-env `index`'s creation answer (sent on `stream` for `scene`) into its last
        observation; returns the reset's info.
        """
        answer = stream.next()
        assert answer is not None
        created = answer.created()
        self._episode_ids[index] = created.episode_id
        if answer.scene is None:
            raise ProtocolError(f"the answer to the creation of sub-env {index} names no scene")
        return self._take_first(index, created.observation, answer.scene, scene)

    def _take_first(
        self, index: int, first: Observation, summary: SceneSummary, scene: str
    ) -> dict[str, Any]:
        """Stores sub-env `index`'s first observation on `scene` (described by `summary`) as its
        last one; returns the reset's info (as `RearrangeEnv.reset`'s).
        """
        self._scene_ids[index] = scene
        assert first.goal_rgb is not None
        for key in self._image_spec.keys:
            self._last_images[key][index] = getattr(first, key)
        self._grasping[index] = first.grasping
        self._goals[index] = first.goal_rgb
        self._started[index] = True
        self._elapsed_steps[index] = 0
        return reset_info(summary, self._setup.horizon)

    def reset(
        self,
        *,
        seed: int | list[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[ObsDict, dict[str, Any]]:
        """Resets every sub-env, or those of `options["reset_mask"]` (a bool array of shape
        (num_envs,)). `seed`: None, an int (sub-env i gets seed + i) or one seed per sub-env.
        """
        self._check_open()
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
        indices: list[int] = np.flatnonzero(mask).tolist()
        for index in indices:
            if seeds[index] is not None:
                self._rngs[index], self._seeds[index] = seeding.np_random(seeds[index])
        scenes = self._pick_scenes(indices, options)
        # New episodes are created on their server's stream (which owns them), every creation sent
        # before any answer is read; live ones restart in one StepBatch per server.
        creates = {i: scene for i, scene in scenes.items() if self._episode_ids[i] is None}
        restarts = {i: scene for i, scene in scenes.items() if i not in creates}
        setup = self._setup
        for index, scene in creates.items():
            self._open_stream(self._shard_of[index]).create(
                scene, sensors=setup.sensors, horizon=setup.horizon, reward=setup.reward, agent=setup.agent
            )
        # Every creation's answer is read even where a call failed (the first error is raised
        # after), so that none is left on a stream for the next reset to take as its own; a failed
        # restart moved no episode (a StepBatch is all or nothing).
        failure: EsrpError | None = None
        restarted: dict[int, dict[str, Any]] = {}
        try:
            _, restarted = self._step_batch([], [], restarts)
        except EsrpError as error:
            failure = error
        created: dict[int, dict[str, Any]] = {}
        for index, scene in creates.items():
            try:
                created[index] = self._take_create(self._open_stream(self._shard_of[index]), index, scene)
            except EsrpError as error:
                failure = failure or error
        if failure is not None:
            raise failure
        infos: dict[str, Any] = {}
        for index in scenes:
            infos = self._add_info(infos, created[index] if index in creates else restarted[index], index)
        return self._batch(), infos

    def _check_open(self) -> None:
        """Raises `ClosedEnvironmentError` after `close()`, as Gymnasium's `AsyncVectorEnv` does (a
        reset would make episodes that no later `close()` frees).
        """
        if self.closed:
            raise gymnasium.error.ClosedEnvironmentError(
                f"{self} is closed: make a new one (reset and step after close() are refused)"
            )

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
        self, actions: npt.NDArray[Any] | Sequence[ActionLike]
    ) -> tuple[
        ObsDict, npt.NDArray[np.float64], npt.NDArray[np.bool_], npt.NDArray[np.bool_], dict[str, Any]
    ]:
        """Steps every sub-env (or autoresets it, in NEXT_STEP mode) in one StepBatch round trip,
        its autoresets in the same message (in SAME_STEP mode, a second StepBatch resets the
        sub-envs the step ended). `actions`: one action per sub-env, each as the single env takes
        it (`action_codes`).
        """
        self._check_open()
        codes = action_codes(actions, self.num_envs)
        n = self.num_envs
        if not np.all(self._started):
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        if self.autoreset_mode == AutoresetMode.DISABLED and np.any(self._autoreset_envs):
            ended = np.flatnonzero(self._autoreset_envs).tolist()
            raise EpisodeEnded(
                f"sub-environments {ended} have ended and autoreset_mode is DISABLED: reset them with "
                "reset(options={'reset_mask': mask}) first (no episode moved)"
            )
        scenes: dict[int, str] = {}
        if self.autoreset_mode == AutoresetMode.NEXT_STEP and np.any(self._autoreset_envs):
            scenes = self._pick_scenes(np.flatnonzero(self._autoreset_envs).tolist(), None)
            stepped: list[int] = np.flatnonzero(~self._autoreset_envs).tolist()
        else:
            stepped = list(range(n))
        columns, resets = self._step_batch(stepped, codes, scenes)
        rewards = np.zeros(n, dtype=np.float64)
        terminations = np.zeros(n, dtype=np.bool_)
        truncations = np.zeros(n, dtype=np.bool_)
        if stepped:
            rewards[stepped] = columns.rewards
            terminations[stepped] = columns.terminated
            truncations[stepped] = columns.truncated
            self._elapsed_steps[stepped] += 1
            if self.max_episode_steps is not None:
                # What a TimeLimit around each sub-env would add (the episode goes on on the server
                # until its reset).
                truncations[stepped] |= self._elapsed_steps[stepped] >= self.max_episode_steps
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
            finals = {i: (self._single_observation(i), step_info(columns, i)) for i in ended}
            _, resets = self._step_batch([], [], self._pick_scenes(ended, None))
        infos = self._step_infos(columns, stepped, resets, finals)
        self._autoreset_envs = np.logical_or(terminations, truncations)
        return self._batch(), rewards, terminations, truncations, infos

    def _step_batch(
        self, stepped: list[int], codes: list[int], restarts: Mapping[int, str]
    ) -> tuple[StepColumns, dict[int, dict[str, Any]]]:
        """Steps sub-envs `stepped` (in increasing order) and restarts the live sub-envs of
        `restarts` onto their scenes with one StepBatch per server (several beyond a server's
        limits: `Client.step_columns`), all sent at once: the steps' answers as columns in the order
        of `stepped`, and each restarted sub-env's reset info (its first observation stored as its
        last one).
        """
        if not stepped and not restarts:
            return StepColumns(self._image_spec.keys), {}
        episode_ids = self._episode_ids
        clients = self._setup.clients
        # Each server's share, in server order: as the blocks are contiguous, the servers' steps one
        # after the other are `stepped` in its order.
        steps: list[list[int]] = [[] for _ in clients]
        restarted: list[list[int]] = [[] for _ in clients]
        for i in stepped:
            steps[self._shard_of[i]].append(i)
        for i in restarts:
            restarted[self._shard_of[i]].append(i)
        parts: list[StepPart] = []
        for client, shard_steps, shard_restarts in zip(clients, steps, restarted, strict=True):
            # The same scene again restarts the episode where it is (see `RearrangeEnv.reset`), so
            # no new scene is sent for it.
            resets = [
                (cast(str, episode_ids[i]), None if restarts[i] == self._scene_ids[i] else restarts[i])
                for i in shard_restarts
            ]
            ids = [cast(str, episode_ids[i]) for i in shard_steps]
            parts.append((client, ids, [codes[i] for i in shard_steps], resets))
        columns = step_columns_across(parts, self._image_spec.sensors)
        order = [i for shard_restarts in restarted for i in shard_restarts]
        infos = {
            i: self._take_first(i, first, summary, restarts[i])
            for i, (first, summary) in zip(order, columns.resets, strict=True)
        }
        return columns, infos

    def _step_infos(
        self,
        columns: StepColumns,
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
                metrics_infos = self._add_info(metrics_infos, metrics_info(metrics), i)
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
        return tuple(frame(self._single_observation(i), self._goals[i]) for i in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:  # noqa: ANN401
        """Closes every server episode (on its server's stream, waiting for the answers), the
        streams, and the clients and servers the env started.
        """
        streams = self._streams
        self._streams = [None for _ in streams]
        self._started[:] = False
        for shard, stream in enumerate(streams):
            if stream is None:
                continue
            try:
                for answer in stream:  # answers of a step that raised
                    del answer
                for episode, owner in zip(self._episode_ids, self._shard_of, strict=True):
                    if episode is not None and owner == shard:
                        stream.close_episode(episode)
                for answer in stream:
                    del answer  # An episode already gone is as good as closed.
            except EsrpError:
                pass  # The stream broke: the server closes its episodes with it.
            finally:
                stream.close()
        self._episode_ids = [None] * self.num_envs
        self._setup.close()
