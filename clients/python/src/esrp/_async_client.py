"""`AsyncClient`: the asyncio twin of `Client` (grpc.aio), with `AsyncEpisode` and
`AsyncEpisodeStream`. Same names, same arguments, same values; every call is awaited.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import AsyncIterator, Mapping, Sequence
from types import TracebackType
from typing import Any

import grpc
import grpc.aio

from . import _convert
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
    open_aio_channel,
    run_rounds,
)
from ._errors import Cancelled, EpisodeNotFound, EsrpError, ServerUnavailable
from ._transport import AsyncCalls, checked_timeout, client_closed
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

__all__ = ["AsyncClient", "AsyncEpisode", "AsyncEpisodeStream"]


async def _serving(check: grpc.aio.UnaryUnaryMultiCallable[bytes, bytes], timeout: float) -> bool:
    """Whether the server's health service says `esrp.v1.Esrp` is serving (one call of `check`)."""
    try:
        return await check(HEALTH_REQUEST, timeout=timeout) == SERVING
    except grpc.aio.AioRpcError:
        return False


class AsyncClient(ClientBase[AsyncCalls]):
    """An asyncio connection to an ESRP server; the twin of `Client` (same arguments).

    Use it as an async context manager, or `await client.close()`.

    Example:
        >>> async with esrp.AsyncClient("127.0.0.1:50051") as client:            # doctest: +SKIP
        ...     async with await client.create_episode("esrp-bench-v2/00017") as episode:
        ...         result = await episode.step(esrp.Action.LEFT)
    """

    _calls: AsyncCalls

    def __init__(
        self,
        address: str = "127.0.0.1:50051",
        *,
        token: str | None = None,
        tls: TlsSetting = None,
        tls_server_name: str | None = None,
        timeout: float | None = None,
        options: ChannelOptions = (),
    ) -> None:
        timeout = checked_timeout(timeout)  # before a channel is made
        super().__init__(address, token, tls)
        creds = self._credentials
        arguments = channel_options(tls_server_name, options, self.address)
        self._channel: grpc.aio.Channel = open_aio_channel(self.address, creds, arguments)
        self._stub: Any = pb_grpc.EsrpStub(self._channel)
        # Every unary call goes through it; streams and the health check use the channel.
        self._calls = AsyncCalls(self._stub, self._metadata, timeout)
        # Creates whose callers gave up, and the closes of their episodes: kept referenced until
        # they finish, and awaited by close() so that closing the channel cancels none of them.
        self._background: set[asyncio.Task[Any]] = set()

    @property
    def raw(self) -> pb_grpc.EsrpAsyncStub:
        """The generated stub, for what the typed API does not cover (pass `metadata=client.metadata`)."""
        stub: pb_grpc.EsrpAsyncStub = self._stub
        return stub

    @property
    def channel(self) -> grpc.aio.Channel:
        """The gRPC channel."""
        return self._channel

    async def close(self, grace: float = 5.0) -> None:
        """Closes the channel, after waiting up to `grace` seconds for abandoned creates to be
        answered and their episodes closed.
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + grace
        while self._background and loop.time() < deadline:
            await asyncio.wait(set(self._background), timeout=deadline - loop.time())
        self._calls.close()
        await self._channel.close()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        await self.close()

    async def wait_healthy(self, timeout: float = 10.0) -> None:
        """Waits until the server's health service says `esrp.v1.Esrp` is serving, polling every
        50 ms; raises `DeadlineExceeded` after `timeout` seconds.
        """
        if self._calls.closed:
            raise client_closed()
        polls = HealthPolls(self.address, timeout, asyncio.get_running_loop().time)
        check: grpc.aio.UnaryUnaryMultiCallable[bytes, bytes] = self._channel.unary_unary(HEALTH_METHOD)
        while not await _serving(check, polls.next_check()):
            await asyncio.sleep(polls.pause())

    async def server_info(self) -> ServerInfo:
        """The server's version, renderer, limits, live episode count and dataset, and who it takes
        the caller for (`caller`, `role`), whether it serves a challenge and what it records.
        """
        return await self._calls.run(server_info_call())

    async def describe_dataset(self) -> DatasetInfo:
        """The served dataset: name, size, counts by split, difficulty and room type."""
        return await self._calls.run(dataset_call())

    def scenes(
        self,
        split: Split | str | None = None,
        difficulty: Difficulty | str | None = None,
        *,
        page_size: int = 0,
    ) -> AsyncIterator[SceneSummary]:
        """Every scene of `split` and `difficulty`, fetched page by page as it is read (`async for`)."""
        return self._scene_pages(ScenePages(split, difficulty, page_size))

    async def _scene_pages(self, pages: ScenePages) -> AsyncIterator[SceneSummary]:
        while (call := pages.next_call()) is not None:
            for scene in await self._calls.run(call):
                yield scene

    async def create_episode(
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
    ) -> AsyncEpisode:
        """Creates an episode (arguments as `Client.create_episode`).

        Cancellation-safe, as the Rust client: the call runs in a task of its own, so a caller that
        gives up (a timeout, a cancelled task) leaves no episode behind: an answer that arrives
        after the caller left is closed on the server at once.
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
        # No gRPC deadline: one that expired while the answer travelled would drop the new id.
        task: asyncio.Task[pb.CreateEpisodeResponse] = asyncio.ensure_future(
            self._calls("CreateEpisode", request, timeout=None)
        )
        wait = self._create_wait(timeout)
        with abandoning(functools.partial(self._abandon, task), wait):
            answer = await asyncio.wait_for(asyncio.shield(task), wait)
        return AsyncEpisode(self, _convert.created(answer))

    def _abandon(self, task: asyncio.Task[pb.CreateEpisodeResponse]) -> None:
        """Lets a create nobody waits for run on; its episode is closed when the answer comes."""
        self._background.add(task)
        task.add_done_callback(self._close_abandoned)

    def _close_abandoned(self, task: asyncio.Task[pb.CreateEpisodeResponse]) -> None:
        self._background.discard(task)
        if task.cancelled() or task.exception() is not None:
            return
        request = pb.CloseEpisodeRequest(episode_id=task.result().episode_id)
        close: asyncio.Task[Any] = asyncio.ensure_future(self._close_quietly(request))
        self._background.add(close)
        close.add_done_callback(self._background.discard)

    async def _close_quietly(self, request: pb.CloseEpisodeRequest) -> None:
        # Already gone, or the server is: its reaper remains.
        with contextlib.suppress(EsrpError):
            await self._calls("CloseEpisode", request, timeout=None)

    def episode(self, episode_id: str) -> AsyncEpisode:
        """A handle to the live episode `episode_id` (made elsewhere)."""
        return AsyncEpisode(self, None, episode_id=episode_id)

    async def step_batch(
        self, steps: Sequence[tuple[AsyncEpisode | str, ActionLike]], *, include_goal: bool = False
    ) -> list[StepResult]:
        """One step in each of several episodes in one call; all or nothing; results in order."""
        return await self._calls.run(step_batch_call(steps, include_goal))

    async def step_columns(
        self,
        episode_ids: Sequence[str],
        actions: Sequence[ActionLike],
        sensors: Sensors,
        *,
        resets: Sequence[tuple[str, str | None]] = (),
    ) -> StepColumns:
        """The twin of `Client.step_columns`: one step in each of several episodes (and `resets` of
        others), the answers as columns in request order, in one StepBatch or, beyond the server's
        limits, several at once.
        """
        wave = StepWave(episode_ids, actions, sensors, resets)
        if wave.empty:
            return wave.columns
        requests = wave.requests(await self._batch_size(sensors))
        answers = await asyncio.gather(*(self._calls("StepBatch", request) for request in requests))
        for request, answer in zip(requests, answers, strict=True):
            wave.add(answer, request)
        return wave.columns

    async def _batch_size(self, sensors: Sensors) -> int:
        """`batch_size` for this server, asked once per client and sensors."""
        size = self._batch_sizes.get(sensors)
        return size if size is not None else self._learn_batch_size(sensors, await self.server_info())

    async def episode_stream(self, window: int = 8) -> AsyncEpisodeStream:
        """Opens a StepStream driven by an `AsyncEpisodeStream` (up to `window` steps of each
        episode in flight).
        """
        if self._calls.closed:
            raise client_closed()
        return AsyncEpisodeStream(self, window)


class AsyncEpisode(EpisodeBase["AsyncClient"]):
    """A live episode; the twin of `Episode` (`async with`, or `await episode.close()`)."""

    def __init__(self, client: AsyncClient, created: Created | None, *, episode_id: str = "") -> None:
        super().__init__(client, created, episode_id=episode_id)

    def __repr__(self) -> str:
        return f"AsyncEpisode(id={self.id!r}, scene={self.scene.id!r}, closed={self.closed})"

    async def step(self, action: ActionLike, *, include_goal: bool = False) -> StepResult:
        """Takes `action`; with `include_goal` the observation carries the goal image too."""
        return await self.client._calls.run(self._step_call(action, include_goal))

    async def reset(self, scene: str | None = None, *, scene_json: str | None = None) -> Observation:
        """Restarts the episode (on `scene` if given); returns the first observation (with goal)."""
        return await self.client._calls.run(self._reset_call(scene, scene_json))

    async def goal(self) -> Goal:
        """The goal image and its pixel ↔ floor frame."""
        return await self.client._calls.run(self._goal_call())

    async def metrics(self) -> Progress:
        """The metrics so far (final once ended), and whether the episode has ended."""
        return await self.client._calls.run(self._metrics_call())

    async def privileged_state(self) -> PrivilegedState:
        """The full state; only for episodes created with `privileged=True`."""
        return await self.client._calls.run(self._privileged_state_call())

    async def plan_actions(self, max_actions: int = 0, budget_ms: int | None = None) -> PlanAnswer:
        """The next actions of the server's planner (ESRP-PLAN) from the episode's current state;
        only for episodes created with `privileged=True`. Arguments, answer, caching and errors as
        `Episode.plan_actions`.
        """
        if self._needs_server_budget(budget_ms):
            self.client._learn_plan_budget(await self.client.server_info())
        return await self.client._calls.run(self._plan_call(max_actions, budget_ms))

    async def close(self) -> EpisodeMetrics:
        """Closes the episode on the server; returns its metrics at that moment (again, without a
        call, when it is closed already).
        """
        if self._final is None:
            self._final = await self.client._calls.run(self._close_call())
        return self._final

    def detach(self) -> str:
        """Gives up the handle without closing the episode; returns its id."""
        return self._detach()

    async def __aenter__(self) -> AsyncEpisode:
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        if self.closed:
            return
        with contextlib.suppress(EpisodeNotFound, ServerUnavailable, Cancelled):
            await self.close()


class AsyncEpisodeStream(EpisodeStreamBase):
    """The twin of `EpisodeStream` over grpc.aio: a pipelined StepStream with up to `window` steps
    of each episode in flight, answers in request order, errors in-band.
    """

    def __init__(self, client: AsyncClient, window: int) -> None:
        super().__init__(window)
        self._call: Any = client._stub.StepStream(metadata=client.metadata)  # noqa: SLF001
        self._cancelled = False

    async def _send(self, kind: RequestKind, episode_id: str, **body: Any) -> int:  # noqa: ANN401
        request = self._request(kind, episode_id, **body)
        try:
            await self._call.write(request)
        except grpc.aio.AioRpcError as error:
            raise self._broken(error) from error
        return request.request_id

    async def create(
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
        """Sends a create (arguments as `Client.create_episode`); returns the request id."""
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
        return await self._send(RequestKind.CREATE, "", create=request)

    async def step(self, episode_id: str, action: ActionLike, *, include_goal: bool = False) -> int:
        """Sends a step; first reads answers while the episode has `window` steps in flight."""
        while self._ledger.window_full(episode_id):
            self._ledger.ready.append(await self._read())
        step = _convert.step_request(episode_id, action, include_goal)
        return await self._send(RequestKind.STEP, episode_id, step=step)

    async def reset(self, episode_id: str, scene: str | None = None, *, scene_json: str | None = None) -> int:
        """Sends a reset of `episode_id` (to `scene` if given)."""
        reset = _convert.reset_request(episode_id, scene, scene_json)
        return await self._send(RequestKind.RESET, episode_id, reset=reset)

    async def close_episode(self, episode_id: str) -> int:
        """Sends a close of `episode_id`."""
        close = pb.CloseEpisodeRequest(episode_id=episode_id)
        return await self._send(RequestKind.CLOSE, episode_id, close=close)

    async def next(self) -> StreamAnswer | None:
        """The next answer in request order; None when every request sent has been answered."""
        return await self._read() if self._ledger.unread else self._ledger.take_ready()

    def __aiter__(self) -> AsyncIterator[StreamAnswer]:
        return self._answers()

    async def _answers(self) -> AsyncIterator[StreamAnswer]:
        while (answer := await self.next()) is not None:
            yield answer

    async def _read(self) -> StreamAnswer:
        if self._cancelled:
            raise Cancelled("the stream was cancelled by this client", code=grpc.StatusCode.CANCELLED)
        try:
            response = await self._call.read()
        except grpc.aio.AioRpcError as error:
            raise self._broken(error) from error
        if response is grpc.aio.EOF:
            raise self._cut_short()
        return self._ledger.answer(response)

    async def run(self, plans: Mapping[str, Sequence[ActionLike]]) -> dict[str, list[StepResult | EsrpError]]:
        """Takes every episode's actions, up to `window` of each in flight, episodes interleaved;
        returns each episode's results in order (errors for refused steps).
        """
        results = self._ledger.run_results(plans)
        for steps in run_rounds(plans):
            for episode, action in steps:
                await self.step(episode, action)
            self._ledger.collect_ready(results)
        async for answer in self:
            collect_run(answer, results)
        return results

    def cancel(self) -> None:
        """Cancels the stream at once (the server closes the episodes created on it); reading it
        afterwards raises `Cancelled`, sending `ServerUnavailable`, as the sync stream does.
        """
        if self._end():
            self._cancelled = True
            self._call.cancel()

    async def close(self) -> None:
        """Half-closes the stream and waits for the server to end it (unread answers are dropped;
        the server closes the episodes created on the stream).
        """
        if not self._end():
            return
        try:
            await self._call.done_writing()
            while await self._call.read() is not grpc.aio.EOF:
                pass
        except grpc.aio.AioRpcError:
            pass

    async def __aenter__(self) -> AsyncEpisodeStream:
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        await self.close()
