"""`Client`: a synchronous connection to an ESRP server; `Episode`, a handle to one live episode;
`EpisodeStream`, a pipelined driver of one StepStream.
"""

from __future__ import annotations

import contextlib
import functools
import queue
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from types import TracebackType
from typing import Any

import grpc

from . import _convert, _native
from ._base import (
    ClientBase,
    EpisodeBase,
    EpisodeStreamBase,
    HealthPolls,
    ScenePages,
    StepWave,
    abandoning,
    dataset_call,
    server_info_call,
    step_batch_call,
)
from ._common import (
    HEALTH_METHOD,
    HEALTH_REQUEST,
    SERVING,
    ChannelOptions,
    RequestKind,
    StreamAnswer,
    TlsSetting,
    channel_options,
    collect_run,
    open_channel,
    run_rounds,
)
from ._errors import Cancelled, EpisodeNotFound, EsrpError, ServerUnavailable
from ._transport import Calls, Pending, checked_timeout, client_closed, run_all
from ._values import (
    ActionLike,
    Created,
    DatasetInfo,
    Difficulty,
    EpisodeMetrics,
    Goal,
    Observation,
    PlanAnswer,
    PrivilegedState,
    Progress,
    RewardWeights,
    SceneSummary,
    Sensors,
    ServerInfo,
    Split,
    StepColumns,
    StepResult,
)
from .v1 import esrp_pb2 as pb
from .v1 import esrp_pb2_grpc as pb_grpc

__all__ = ["Client", "Episode", "EpisodeStream", "health_check"]


def health_check(channel: grpc.Channel, timeout: float) -> bool:
    """Whether the server's health service says `esrp.v1.Esrp` is serving (one call)."""
    check: grpc.UnaryUnaryMultiCallable[bytes, bytes] = channel.unary_unary(HEALTH_METHOD)
    try:
        answer = check(HEALTH_REQUEST, timeout=timeout)
    except grpc.RpcError:
        return False
    return bool(answer == SERVING)


class Client(ClientBase[Calls]):
    """A synchronous connection to an ESRP server (esrp.v1 over gRPC).

    One channel, shared by every call (HTTP/2 multiplexes them; it is safe to use from several
    threads). Use it as a context manager, or call `close()`.

    Args:
        address: `host:port`, `http://host:port`, `https://host:port` (TLS), or `unix:PATH` (a
            server's `--listen-unix` socket on this machine: less kernel work per step than TCP).
        token: Sent as `authorization: Bearer TOKEN` on every call (the server's `--token`).
        tls: TLS setting: True (system roots), the CA's PEM bytes, a path to the CA's PEM file, or
            `grpc.ChannelCredentials`; None/False for a plain channel (unless `https://`).
        tls_server_name: Check the server's certificate against this name instead of the host.
        timeout: Default deadline of unary calls, seconds (None: none).
        options: Extra gRPC channel arguments; they override the tuned defaults.
        transport: What carries the hot-path calls (Step, Reset, StepBatch): `auto` (default) the
            native transport where the `esrp-native` package is installed and the channel is
            plain, else grpcio; `native` insists on it (ValueError where it cannot be had);
            `grpcio` never uses it. Every other call goes through grpcio. `client.transport`
            says which one is used.

    Example:
        >>> with esrp.Client("127.0.0.1:50051") as client:            # doctest: +SKIP
        ...     with client.create_episode("esrp-bench-v2/00017") as episode:
        ...         result = episode.step(esrp.Action.LEFT)
    """

    _calls: Calls

    def __init__(
        self,
        address: str = "127.0.0.1:50051",
        *,
        token: str | None = None,
        tls: TlsSetting = None,
        tls_server_name: str | None = None,
        timeout: float | None = None,
        options: ChannelOptions = (),
        transport: _native.Transport = "auto",
    ) -> None:
        timeout = checked_timeout(timeout)  # before a channel is made
        super().__init__(address, token, tls)
        creds = self._credentials
        self.transport = _native.resolve(transport, creds is not None, self.address)
        arguments = channel_options(tls_server_name, options, self.address)
        self._channel: grpc.Channel = open_channel(self.address, creds, arguments)
        self._stub = pb_grpc.EsrpStub(self._channel)
        native = _native.channel(self.address, token) if self.transport == "native" else None
        # Every unary call goes through it; streams and the health check use the channel.
        self._calls = Calls(self._stub, native, self._metadata, timeout)
        # Creates whose callers gave up, and the closes of their episodes, until they finish:
        # close() waits for them so that closing the channel cancels none of them.
        self._background: set[Pending] = set()
        self._background_done = threading.Condition()

    @property
    def raw(self) -> pb_grpc.EsrpStub:
        """The generated stub, for what the typed API does not cover (pass `metadata=client.metadata`)."""
        return self._stub

    @property
    def channel(self) -> grpc.Channel:
        """The gRPC channel."""
        return self._channel

    def close(self, grace: float = 5.0) -> None:
        """Closes the channel (calls in flight are cancelled), after waiting up to `grace` seconds
        for abandoned creates to be answered and their episodes closed.
        """
        with self._background_done:
            self._background_done.wait_for(lambda: not self._background, timeout=grace)
        self._calls.close()
        self._channel.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()

    def wait_healthy(self, timeout: float = 10.0) -> None:
        """Waits until the server's health service says `esrp.v1.Esrp` is serving, polling every
        50 ms; raises `DeadlineExceeded` after `timeout` seconds.
        """
        if self._calls.closed:
            raise client_closed()
        polls = HealthPolls(self.address, timeout, time.monotonic)
        while not health_check(self._channel, timeout=polls.next_check()):
            time.sleep(polls.pause())

    def server_info(self) -> ServerInfo:
        """The server's version, renderer, limits, live episode count and dataset, and who it takes
        the caller for (`caller`, `role`), whether it serves a challenge and what it records.
        """
        return self._calls.run(server_info_call())

    def describe_dataset(self) -> DatasetInfo:
        """The served dataset: name, size, counts by split, difficulty and room type."""
        return self._calls.run(dataset_call())

    def scenes(
        self,
        split: Split | str | None = None,
        difficulty: Difficulty | str | None = None,
        *,
        page_size: int = 0,
    ) -> Iterator[SceneSummary]:
        """Every scene of `split` and `difficulty` (all when None), in dataset order, fetched page by
        page (`page_size` per request; 0: the server's 100, at most 1,000) as the iterator is read.
        """
        return self._scene_pages(ScenePages(split, difficulty, page_size))

    def _scene_pages(self, pages: ScenePages) -> Iterator[SceneSummary]:
        while (call := pages.next_call()) is not None:
            yield from self._calls.run(call)

    def create_episode(
        self,
        scene: str | None = None,
        *,
        scene_json: str | None = None,
        split: Split | str | None = None,
        seed: int = 0,
        horizon: int = 0,
        reward: RewardWeights | Mapping[str, Any] | None = None,
        sensors: Sensors | Mapping[str, Any] | None = None,
        privileged: bool = False,
        agent: str | None = None,
        timeout: float | None = None,
    ) -> Episode:
        """Creates an episode and returns its handle, whose `observation` is the first one (with goal).

        Args:
            scene: A scene id of the served dataset (`scenes()` lists them).
            scene_json: An inline `esrp.scene/v1` scene instead.
            split: With neither: pick from this split (default test) ...
            seed: ... its scene number `seed mod count`, in dataset order.
            horizon: The step limit; 0: the scene's own.
            reward: Reward weights (the server's defaults for fields left None), or a mapping of
                their fields.
            sensors: Optional sensors and the image size (default: none, 128 px), or a mapping of
                their fields (`{"resolution": 64}`).
            privileged: Allow `Episode.privileged_state()` (planners, debugging).
            agent: The agent's name, kept in the server's records of the episode (a server started
                with `--records`), e.g. `"my-vlm-agent v3"`: free text, at most 200 bytes (the
                server refuses longer); None or empty: `"unnamed"`.
            timeout: Give up waiting after this many seconds (default: the client's `timeout`).

        Arguments the request cannot carry (an empty scene id, a negative seed or horizon, a
        string where a number goes) raise `ValueError` or `TypeError` naming them, before anything
        is sent.

        Cancellation-safe, as the Rust client: the call runs to its end whatever happens to the
        caller, and an answer that arrives after the caller gave up (a `timeout`, a
        KeyboardInterrupt) is closed on the server at once, so no episode is left behind that
        nobody knows of. (The server closes an episode whose call is abandoned before its answer
        is sent.)
        """
        request = _convert.create_request(
            scene,
            scene_json=scene_json,
            split=split,
            seed=seed,
            horizon=horizon,
            reward=reward,
            sensors=sensors,
            privileged=privileged,
            agent=agent,
        )
        # No gRPC deadline: a deadline that expires while the answer travels would drop the answer,
        # and with it the only copy of the new episode's id.
        pending = self._calls.start("CreateEpisode", request, timeout=None)
        wait = self._create_wait(timeout)
        with abandoning(functools.partial(self._abandon, pending), wait):
            answer = pending.result(timeout=wait)
        return Episode(self, _convert.created(answer))

    def _track(self, pending: Pending) -> None:
        with self._background_done:
            self._background.add(pending)
        pending.add_done_callback(self._untrack)

    def _untrack(self, pending: Pending) -> None:
        with self._background_done:
            self._background.discard(pending)
            self._background_done.notify_all()

    def _abandon(self, pending: Pending) -> None:
        """Lets a create nobody waits for run on; its episode is closed when the answer comes."""
        # Tracked first: the close is tracked by _close_abandoned before the create is untracked
        # (callbacks run in the order added), so close() never sees a gap.
        with self._background_done:
            self._background.add(pending)
        pending.add_done_callback(self._close_abandoned)
        pending.add_done_callback(self._untrack)

    def _close_abandoned(self, pending: Pending) -> None:
        """Closes the episode of a CreateEpisode answer nobody waits for any more (best effort)."""
        try:
            if not pending.succeeded():
                return
            episode_id = pending.result().episode_id
            request = pb.CloseEpisodeRequest(episode_id=episode_id)
            self._track(self._calls.start("CloseEpisode", request, timeout=None))
        except Exception:  # noqa: BLE001 - the channel may be closing; the server's reaper remains.
            return

    def episode(self, episode_id: str) -> Episode:
        """A handle to the live episode `episode_id` (made elsewhere); its scene and spec are unknown
        (empty) and its `observation` None until a reset.
        """
        return Episode(self, None, episode_id=episode_id)

    def step_batch(
        self, steps: Sequence[tuple[Episode | str, ActionLike]], *, include_goal: bool = False
    ) -> list[StepResult]:
        """One step in each of several episodes, in one call (at most one per episode; the server's
        `max_batch` caps the count). All or nothing: a bad entry fails the call and no episode
        moves. Results are in request order.
        """
        return self._calls.run(step_batch_call(steps, include_goal))

    def step_columns(
        self,
        episode_ids: Sequence[str],
        actions: Sequence[ActionLike],
        sensors: Sensors,
        *,
        resets: Sequence[tuple[str, str | None]] = (),
    ) -> StepColumns:
        """One step in each of several episodes (at most one per episode), the answers as columns in
        request order (`StepColumns`: what a vector env reads, without per-step values; its images
        the answers' bytes, each checked to be `sensors`' size). The episodes must have been made
        with `sensors`. `resets` restarts other episodes in the same call (a vector env's
        autoresets): each an episode id and its new scene, or None for the same one; their first
        observations and scenes come in `StepColumns.resets`, in order.

        The steps go in one StepBatch call, or where the server's `max_batch` or half its message
        limit wants it in several, sent at once (the server renders one while another's answer
        travels); below the limits one call is best: splitting a wave measured no faster and costs
        the client more. Each call is all or nothing; a failed one raises its error, and the other
        calls' episodes may have moved.
        """
        return step_columns_across([(self, episode_ids, actions, resets)], sensors)

    def _batch_size(self, sensors: Sensors) -> int:
        """`batch_size` for this server, asked once per client and sensors."""
        size = self._batch_sizes.get(sensors)
        return size if size is not None else self._learn_batch_size(sensors, self.server_info())

    def episode_stream(self, window: int = 8) -> EpisodeStream:
        """Opens a StepStream driven by an `EpisodeStream` with up to `window` steps of each
        episode in flight.
        """
        if self._calls.closed:
            raise client_closed()
        return EpisodeStream(self, window)


StepPart = tuple[Client, Sequence[str], Sequence[ActionLike], Sequence[tuple[str, str | None]]]
"""One server's share of a wave of `step_columns_across`: its client, its episodes' ids, their
actions, and its resets (as `Client.step_columns`'s arguments)."""


def step_columns_across(parts: Sequence[StepPart], sensors: Sensors) -> StepColumns:
    """`Client.step_columns` over several clients (a vector env's sub-envs spread over servers):
    every part's StepBatch calls are made at once (`_transport.run_all`), so that the servers step
    and render at once; the answers as one `StepColumns`, the parts' steps (and resets) one after
    the other in the order of `parts`, each part's in its own order.

    Each call is all or nothing; the first failed one (in the order of `parts`) raises its error,
    and the episodes of the other calls may have moved.
    """
    layout = _convert.image_layout(sensors)
    columns = StepColumns([key for key, _, _, _ in layout])
    calls: list[tuple[Client, StepWave, pb.StepBatchRequest]] = []
    for client, episode_ids, actions, resets in parts:
        wave = StepWave(episode_ids, actions, sensors, resets, columns)
        if not wave.empty:
            calls += [(client, wave, r) for r in wave.requests(client._batch_size(sensors))]
    if not calls:
        return columns
    answers = run_all("StepBatch", [(client._calls, request) for client, _, request in calls])
    for answer, (_, wave, request) in zip(answers, calls, strict=True):
        wave.add(answer, request)
    return columns


class Episode(EpisodeBase["Client"]):
    """A live episode on the server. Use it as a context manager (closed on exit) or call `close()`.

    Attributes:
        id: The episode's id (32 hex digits).
        scene: The scene it plays (updated by `reset`).
        spec: Its observation arrays and the action names, as the server described them.
        observation: The first observation of the last creation or reset (with the goal image).
        closed: Whether `close()` was called.
    """

    def __init__(self, client: Client, created: Created | None, *, episode_id: str = "") -> None:
        super().__init__(client, created, episode_id=episode_id)

    def __repr__(self) -> str:
        return f"Episode(id={self.id!r}, scene={self.scene.id!r}, closed={self.closed})"

    def step(self, action: ActionLike, *, include_goal: bool = False) -> StepResult:
        """Takes `action`; with `include_goal` the observation carries the goal image too."""
        return self.client._calls.run(self._step_call(action, include_goal))

    def step_columns(self, action: ActionLike, sensors: Sensors) -> StepColumns:
        """`step`, its answer as one row of `StepColumns` (what the Gymnasium env reads, without
        building values; the images the answer's bytes, checked to be `sensors`' size, the sensors
        the episode was made with).
        """
        answer = self.client._calls("Step", _convert.step_request(self.id, action, False))
        return _convert.step_columns((answer,), _convert.image_layout(sensors), sensors.resolution)

    def reset(self, scene: str | None = None, *, scene_json: str | None = None) -> Observation:
        """Restarts the episode on the same scene (or another one); returns the first observation
        (with the goal image). Works on an ended episode.
        """
        return self.client._calls.run(self._reset_call(scene, scene_json))

    def goal(self) -> Goal:
        """The goal image and its pixel ↔ floor frame."""
        return self.client._calls.run(self._goal_call())

    def metrics(self) -> Progress:
        """The metrics so far (final once ended), and whether the episode has ended."""
        return self.client._calls.run(self._metrics_call())

    def privileged_state(self) -> PrivilegedState:
        """The full state; only for episodes created with `privileged=True` (else `PermissionDenied`)."""
        return self.client._calls.run(self._privileged_state_call())

    def plan_actions(self, max_actions: int = 0, budget_ms: int | None = None) -> PlanAnswer:
        """The next actions of the server's planner (ESRP-PLAN) from the episode's current state;
        only for episodes created with `privileged=True` (else `PermissionDenied`).

        Args:
            max_actions: At most this many next actions; 0: the whole plan.
            budget_ms: Planning time in milliseconds, counted from the call (waiting for a planner
                thread included); None: the server's `--plan-budget-ms` (10 s by default). The
                server caps it at its `--max-plan-ms` (60 s by default). A client `timeout`
                shorter than the budget plus 5 s is stretched to that for this call (the first
                call without a budget asks the server for its own, `ServerLimits.plan_budget_ms`).

        Returns the plan's next actions and how it was made; a plan that does not exist comes back
        as a `PlanAnswer` with `failure` set (and the actions the planner took before failing).
        The answer is cached with the episode: after stepping part of the plan, the next call
        answers the rest at once (`cached`).

        Raises:
            DeadlineExceeded: No plan was found within the budget, or every planner thread of
                the server was busy with other calls for all of it (nothing was planned).
            EpisodeEnded: The episode has ended.
            PermissionDenied: The episode is not privileged.
        """
        if self._needs_server_budget(budget_ms):
            self.client._learn_plan_budget(self.client.server_info())
        return self.client._calls.run(self._plan_call(max_actions, budget_ms))

    def close(self) -> EpisodeMetrics:
        """Closes the episode on the server; returns its metrics at that moment (again, without a
        call, when it is closed already).
        """
        if self._final is None:
            self._final = self.client._calls.run(self._close_call())
        return self._final

    def detach(self) -> str:
        """Gives up the handle without closing the episode (exiting a `with` block then does
        nothing); returns the id, for `Client.episode`.
        """
        return self._detach()

    def __enter__(self) -> Episode:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        if self.closed:
            return
        # Already gone (closed elsewhere, reaped) or the server is: nothing is left to free; or
        # the client is closed, and the server reaps it when idle.
        with contextlib.suppress(EpisodeNotFound, ServerUnavailable, Cancelled):
            self.close()


_END = object()


class _RequestQueue:
    """The request iterator of a sync StepStream call: gRPC reads it on its own thread."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[object] = queue.SimpleQueue()

    def put(self, request: pb.StreamRequest) -> None:
        self._queue.put(request)

    def end(self) -> None:
        self._queue.put(_END)

    def __iter__(self) -> _RequestQueue:
        return self

    def __next__(self) -> pb.StreamRequest:
        item = self._queue.get()
        if item is _END:
            raise StopIteration
        assert isinstance(item, pb.StreamRequest)
        return item


class EpisodeStream(EpisodeStreamBase):
    """A pipelined driver of one StepStream, as the Rust client's `EpisodeStream`.

    It keeps up to `window` steps of each episode in flight: `step()` returns at once unless that
    episode already has `window` steps unanswered, in which case it first reads answers (kept for
    `next()`). Answers come in request order, exactly as the same requests made one by one would
    answer; an error the server gives one request comes in-band in its `StreamAnswer` and the
    stream goes on. Episodes created on the stream are closed by the server when the stream ends.
    Use it as a context manager, or call `close()`.
    """

    def __init__(self, client: Client, window: int) -> None:
        super().__init__(window)
        self._requests = _RequestQueue()
        self._responses: Any = client.raw.StepStream(self._requests, metadata=client.metadata)

    def _send(self, kind: RequestKind, episode_id: str, **body: Any) -> int:  # noqa: ANN401
        request = self._request(kind, episode_id, **body)
        self._requests.put(request)
        return request.request_id

    def create(
        self,
        scene: str | None = None,
        *,
        scene_json: str | None = None,
        split: Split | str | None = None,
        seed: int = 0,
        horizon: int = 0,
        reward: RewardWeights | Mapping[str, Any] | None = None,
        sensors: Sensors | Mapping[str, Any] | None = None,
        privileged: bool = False,
        agent: str | None = None,
    ) -> int:
        """Sends a create (arguments as `Client.create_episode`); the episode lives as long as the
        stream. Returns the request id; the answer's `created()` has the new episode's id.
        """
        request = _convert.create_request(
            scene,
            scene_json=scene_json,
            split=split,
            seed=seed,
            horizon=horizon,
            reward=reward,
            sensors=sensors,
            privileged=privileged,
            agent=agent,
        )
        return self._send(RequestKind.CREATE, "", create=request)

    def step(self, episode_id: str, action: ActionLike, *, include_goal: bool = False) -> int:
        """Sends a step; first reads answers while the episode has `window` steps in flight."""
        while self._ledger.window_full(episode_id):
            self._ledger.ready.append(self._read())
        return self._send(
            RequestKind.STEP, episode_id, step=_convert.step_request(episode_id, action, include_goal)
        )

    def reset(self, episode_id: str, scene: str | None = None, *, scene_json: str | None = None) -> int:
        """Sends a reset of `episode_id` (to `scene` if given)."""
        return self._send(
            RequestKind.RESET, episode_id, reset=_convert.reset_request(episode_id, scene, scene_json)
        )

    def close_episode(self, episode_id: str) -> int:
        """Sends a close of `episode_id`."""
        return self._send(RequestKind.CLOSE, episode_id, close=pb.CloseEpisodeRequest(episode_id=episode_id))

    def next(self) -> StreamAnswer | None:
        """The next answer in request order; None when every request sent has been answered.
        Raises only when the stream itself failed (it cannot go on).
        """
        return self._read() if self._ledger.unread else self._ledger.take_ready()

    def __iter__(self) -> Iterator[StreamAnswer]:
        """Every answer not yet read, in request order."""
        while (answer := self.next()) is not None:
            yield answer

    def _read(self) -> StreamAnswer:
        try:
            response = next(self._responses)
        except StopIteration:
            raise self._cut_short() from None
        except grpc.RpcError as error:
            raise self._broken(error) from error
        return self._ledger.answer(response)

    def run(self, plans: Mapping[str, Sequence[ActionLike]]) -> dict[str, list[StepResult | EsrpError]]:
        """Takes every episode's actions on this stream, up to `window` steps of each in flight,
        episodes interleaved; returns each episode's results in order (an error for a step the
        server refused, e.g. one sent after its episode ended).
        """
        results = self._ledger.run_results(plans)
        for steps in run_rounds(plans):
            for episode, action in steps:
                self.step(episode, action)
            self._ledger.collect_ready(results)
        for answer in self:
            collect_run(answer, results)
        return results

    def close(self) -> None:
        """Half-closes the stream and waits for the server to end it: the answers not yet read are
        dropped, and the server closes the episodes created on the stream.
        """
        if not self._end():
            return
        self._requests.end()
        try:
            for _ in self._responses:
                pass
        except grpc.RpcError:
            pass

    def cancel(self) -> None:
        """Cancels the stream at once (the server closes the episodes created on it)."""
        self._ended = True
        self._responses.cancel()
        self._requests.end()

    def __enter__(self) -> EpisodeStream:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()
