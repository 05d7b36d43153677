"""`AsyncClient`: the asyncio twin of `Client` (grpc.aio), with `AsyncEpisode` and
`AsyncEpisodeStream`. Same names, same arguments, same values; every call is awaited.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Mapping, Sequence
from types import TracebackType
from typing import Any

import grpc
import grpc.aio

from . import _convert
from ._common import (
    ChannelOptions,
    RequestKind,
    StreamAnswer,
    StreamLedger,
    TlsSetting,
    batch_size,
    bearer_metadata,
    channel_options,
    collect_run,
    credentials,
    target,
)
from ._errors import DeadlineExceeded, EpisodeNotFound, EsrpError, ServerUnavailable, from_rpc_error
from ._values import (
    ActionLike,
    Created,
    DatasetInfo,
    Difficulty,
    EpisodeMetrics,
    Goal,
    Observation,
    ObservationSpec,
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

_HEALTH_METHOD = "/grpc.health.v1.Health/Check"
_HEALTH_REQUEST = b"\x0a\x0cesrp.v1.Esrp"  # HealthCheckRequest{service: "esrp.v1.Esrp"}
_SERVING = b"\x08\x01"  # HealthCheckResponse{status: SERVING}


class AsyncClient:
    """An asyncio connection to an ESRP server; the twin of `Client` (same arguments).

    Use it as an async context manager, or `await client.close()`.

    Example:
        >>> async with esrp.AsyncClient("127.0.0.1:50051") as client:            # doctest: +SKIP
        ...     async with await client.create_episode("esrp-bench-v2/00017") as episode:
        ...         result = await episode.step(esrp.Action.LEFT)
    """

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
        host, https = target(address)
        self.address = host
        self.timeout = timeout
        self._metadata = bearer_metadata(token)
        creds = credentials(tls, https)
        arguments = channel_options(tls_server_name, options)
        if creds is None:
            self._channel = grpc.aio.insecure_channel(host, options=arguments)
        else:
            self._channel = grpc.aio.secure_channel(host, creds, options=arguments)
        self._stub: Any = pb_grpc.EsrpStub(self._channel)
        # Creates whose callers gave up, and the closes of their episodes: kept referenced until
        # they finish, and awaited by close() so that closing the channel cancels none of them.
        self._background: set[asyncio.Task[Any]] = set()
        # Steps per StepBatch of `step_columns`, by sensors (from the server's limits).
        self._batch_sizes: dict[Sensors, int] = {}

    @property
    def raw(self) -> pb_grpc.EsrpAsyncStub:
        """The generated stub, for what the typed API does not cover (pass `metadata=client.metadata`)."""
        stub: pb_grpc.EsrpAsyncStub = self._stub
        return stub

    @property
    def channel(self) -> grpc.aio.Channel:
        """The gRPC channel."""
        return self._channel

    @property
    def metadata(self) -> tuple[tuple[str, str], ...] | None:
        """The call metadata (the bearer token), for calls through `raw`."""
        return self._metadata

    async def close(self, grace: float = 5.0) -> None:
        """Closes the channel, after waiting up to `grace` seconds for abandoned creates to be
        answered and their episodes closed.
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + grace
        while self._background and loop.time() < deadline:
            await asyncio.wait(set(self._background), timeout=deadline - loop.time())
        await self._channel.close()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        await self.close()

    async def _call(self, method: Any, request: Any, timeout: float | None = None) -> Any:  # noqa: ANN401
        try:
            return await method(
                request, metadata=self._metadata, timeout=timeout if timeout is not None else self.timeout
            )
        except grpc.aio.AioRpcError as error:
            raise from_rpc_error(error) from error

    async def wait_healthy(self, timeout: float = 10.0) -> None:
        """Waits until the server's health service says `esrp.v1.Esrp` is serving, polling every
        50 ms; raises `DeadlineExceeded` after `timeout` seconds.
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        check: grpc.aio.UnaryUnaryMultiCallable[bytes, bytes] = self._channel.unary_unary(_HEALTH_METHOD)
        while True:
            left = deadline - loop.time()
            if left <= 0:
                raise DeadlineExceeded(f"the server at {self.address} was not healthy within {timeout} s")
            try:
                if await check(_HEALTH_REQUEST, timeout=min(left, 1.0)) == _SERVING:
                    return
            except grpc.aio.AioRpcError:
                pass
            await asyncio.sleep(min(0.05, max(deadline - loop.time(), 0)))

    async def server_info(self) -> ServerInfo:
        """The server's version, renderer, limits, live episode count and dataset, and who it takes
        the caller for (`caller`, `role`), whether it serves a challenge and what it records.
        """
        return _convert.server_info(await self._call(self._stub.ServerInfo, pb.ServerInfoRequest()))

    async def describe_dataset(self) -> DatasetInfo:
        """The served dataset: name, size, counts by split, difficulty and room type."""
        return _convert.dataset_info(
            await self._call(self._stub.DescribeDataset, pb.DescribeDatasetRequest())
        )

    def scenes(
        self,
        split: Split | str | None = None,
        difficulty: Difficulty | str | None = None,
        *,
        page_size: int = 0,
    ) -> AsyncIterator[SceneSummary]:
        """Every scene of `split` and `difficulty`, fetched page by page as it is read (`async for`)."""
        request = pb.ListScenesRequest(
            split=_convert.split_code(split),
            difficulty=_convert.difficulty_code(difficulty),
            page_size=page_size,
        )
        return self._scene_pages(request)

    async def _scene_pages(self, request: pb.ListScenesRequest) -> AsyncIterator[SceneSummary]:
        while True:
            page = await self._call(self._stub.ListScenes, request)
            for scene in page.scenes:
                yield _convert.scene_summary(scene)
            if not page.next_page_token:
                return
            request.page_token = page.next_page_token

    async def create_episode(
        self,
        scene: str | None = None,
        *,
        scene_json: str | None = None,
        split: Split | str | None = None,
        seed: int = 0,
        horizon: int = 0,
        reward: RewardWeights | None = None,
        sensors: Sensors | None = None,
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
            self._stub.CreateEpisode(request, metadata=self._metadata)
        )
        wait = timeout if timeout is not None else self.timeout
        try:
            answer = await asyncio.wait_for(asyncio.shield(task), wait)
        except grpc.aio.AioRpcError as error:
            raise from_rpc_error(error) from error
        except asyncio.TimeoutError:
            self._abandon(task)
            raise DeadlineExceeded(f"no answer to CreateEpisode within {wait} s") from None
        except BaseException:
            self._abandon(task)
            raise
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
        with contextlib.suppress(grpc.aio.AioRpcError):
            await self._stub.CloseEpisode(request, metadata=self._metadata)

    def episode(self, episode_id: str) -> AsyncEpisode:
        """A handle to the live episode `episode_id` (made elsewhere)."""
        return AsyncEpisode(self, None, episode_id=episode_id)

    async def step_batch(
        self, steps: Sequence[tuple[AsyncEpisode | str, ActionLike]], *, include_goal: bool = False
    ) -> list[StepResult]:
        """One step in each of several episodes in one call; all or nothing; results in order."""
        request = pb.StepBatchRequest(
            steps=[
                _convert.step_request(
                    episode if isinstance(episode, str) else episode.id, action, include_goal, f"steps[{k}]"
                )
                for k, (episode, action) in enumerate(steps)
            ]
        )
        answer = await self._call(self._stub.StepBatch, request)
        return _convert.step_results(answer.responses, len(steps))

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
        layout = _convert.image_layout(sensors)
        columns = StepColumns([key for key, _, _, _ in layout])
        if not episode_ids and not actions and not resets:
            return columns
        size = self._batch_sizes.get(sensors)
        if size is None:
            size = self._batch_sizes[sensors] = batch_size((await self.server_info()).limits, sensors)
        requests = _convert.step_batch_requests(episode_ids, actions, size, resets)
        answers = await asyncio.gather(*(self._call(self._stub.StepBatch, request) for request in requests))
        for request, answer in zip(requests, answers, strict=True):
            _convert.batch_columns(answer, request, layout, sensors.resolution, into=columns)
        return columns

    async def episode_stream(self, window: int = 8) -> AsyncEpisodeStream:
        """Opens a StepStream driven by an `AsyncEpisodeStream` (up to `window` steps of each
        episode in flight).
        """
        return AsyncEpisodeStream(self, window)


class AsyncEpisode:
    """A live episode; the twin of `Episode` (`async with`, or `await episode.close()`)."""

    def __init__(self, client: AsyncClient, created: Created | None, *, episode_id: str = "") -> None:
        self.client = client
        self.closed = False
        self.observation: Observation | None
        if created is None:
            self.id = episode_id
            self.scene = SceneSummary("", "", None, None, 0, 0, 0)
            self.spec = ObservationSpec((), ())
            self.observation = None
        else:
            self.id = created.episode_id
            self.scene = created.scene
            self.spec = created.spec
            self.observation = created.observation

    def __repr__(self) -> str:
        return f"AsyncEpisode(id={self.id!r}, scene={self.scene.id!r}, closed={self.closed})"

    async def step(self, action: ActionLike, *, include_goal: bool = False) -> StepResult:
        """Takes `action`; with `include_goal` the observation carries the goal image too."""
        raw = self.client._stub  # noqa: SLF001 - the episode is part of the client.
        answer = await self.client._call(raw.Step, _convert.step_request(self.id, action, include_goal))  # noqa: SLF001
        return _convert.step_result(answer)

    async def reset(self, scene: str | None = None, *, scene_json: str | None = None) -> Observation:
        """Restarts the episode (on `scene` if given); returns the first observation (with goal)."""
        request = _convert.reset_request(self.id, scene, scene_json)
        answer = await self.client._call(self.client._stub.Reset, request)  # noqa: SLF001
        observation, summary = _convert.reset_observation(answer)
        if summary is not None:
            self.scene = summary
        self.observation = observation
        return observation

    async def goal(self) -> Goal:
        """The goal image and its pixel ↔ floor frame."""
        request = pb.GetGoalRequest(episode_id=self.id)
        return _convert.goal(await self.client._call(self.client._stub.GetGoal, request))  # noqa: SLF001

    async def metrics(self) -> Progress:
        """The metrics so far (final once ended), and whether the episode has ended."""
        request = pb.GetMetricsRequest(episode_id=self.id)
        answer = await self.client._call(self.client._stub.GetMetrics, request)  # noqa: SLF001
        return Progress(_convert.metrics(answer.metrics), answer.ended)

    async def privileged_state(self) -> PrivilegedState:
        """The full state; only for episodes created with `privileged=True`."""
        request = pb.GetPrivilegedStateRequest(episode_id=self.id)
        answer = await self.client._call(self.client._stub.GetPrivilegedState, request)  # noqa: SLF001
        return _convert.privileged_state(answer)

    async def plan_actions(self, max_actions: int = 0, budget_ms: int | None = None) -> PlanAnswer:
        """The next actions of the server's planner (ESRP-PLAN) from the episode's current state;
        only for episodes created with `privileged=True` (else `PermissionDenied`).

        Args:
            max_actions: At most this many next actions; 0: the whole plan.
            budget_ms: Planning time in milliseconds, counted from the call (waiting for a planner
                thread included); None: the server's `--plan-budget-ms` (10 s by default). The
                server caps it at its `--max-plan-ms` (60 s by default).

        Returns the plan's next actions and how it was made; a plan that does not exist comes back
        as a `PlanAnswer` with `failure` set (and the actions the planner took before failing).
        The answer is cached with the episode: after stepping part of the plan, the next call
        answers the rest at once (`cached`).

        Raises:
            DeadlineExceeded: No plan was found within the budget.
            EpisodeEnded: The episode has ended.
            PermissionDenied: The episode is not privileged.
        """
        request = _convert.plan_request(self.id, max_actions, budget_ms)
        timeout = _convert.plan_timeout(self.client.timeout, budget_ms)
        answer = await self.client._call(self.client._stub.PlanActions, request, timeout)  # noqa: SLF001
        return _convert.plan_answer(answer)

    async def close(self) -> EpisodeMetrics:
        """Closes the episode on the server; returns its metrics at that moment."""
        self.closed = True
        request = pb.CloseEpisodeRequest(episode_id=self.id)
        return _convert.closed_metrics(await self.client._call(self.client._stub.CloseEpisode, request))  # noqa: SLF001

    def detach(self) -> str:
        """Gives up the handle without closing the episode; returns its id."""
        self.closed = True
        return self.id

    async def __aenter__(self) -> AsyncEpisode:
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        if self.closed:
            return
        with contextlib.suppress(EpisodeNotFound, ServerUnavailable):
            await self.close()


class AsyncEpisodeStream:
    """The twin of `EpisodeStream` over grpc.aio: a pipelined StepStream with up to `window` steps
    of each episode in flight, answers in request order, errors in-band.
    """

    def __init__(self, client: AsyncClient, window: int) -> None:
        self._ledger = StreamLedger(window)
        self._call: Any = client._stub.StepStream(metadata=client.metadata)  # noqa: SLF001
        self._ended = False

    @property
    def window(self) -> int:
        """The most steps of one episode in flight."""
        return self._ledger.window

    @property
    def outstanding(self) -> int:
        """Requests sent and not yet returned by `next()`."""
        return self._ledger.outstanding

    async def _send(self, kind: RequestKind, episode_id: str, **body: Any) -> int:  # noqa: ANN401
        if self._ended:
            raise ServerUnavailable("the stream has ended")
        request = self._ledger.request(kind, episode_id, **body)
        try:
            await self._call.write(request)
        except grpc.aio.AioRpcError as error:
            self._ended = True
            raise from_rpc_error(error) from error
        return request.request_id

    async def create(
        self,
        scene: str | None = None,
        *,
        scene_json: str | None = None,
        split: Split | str | None = None,
        seed: int = 0,
        horizon: int = 0,
        reward: RewardWeights | None = None,
        sensors: Sensors | None = None,
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
        if self._ledger.ready:
            return self._ledger.ready.popleft()
        if not self._ledger.pending:
            return None
        return await self._read()

    def __aiter__(self) -> AsyncIterator[StreamAnswer]:
        return self._answers()

    async def _answers(self) -> AsyncIterator[StreamAnswer]:
        while (answer := await self.next()) is not None:
            yield answer

    async def _read(self) -> StreamAnswer:
        try:
            response = await self._call.read()
        except grpc.aio.AioRpcError as error:
            self._ended = True
            raise from_rpc_error(error) from error
        if response is grpc.aio.EOF:
            self._ended = True
            raise ServerUnavailable("the server ended the stream with requests unanswered")
        return self._ledger.answer(response)

    async def run(self, plans: Mapping[str, Sequence[ActionLike]]) -> dict[str, list[StepResult | EsrpError]]:
        """Takes every episode's actions, up to `window` of each in flight, episodes interleaved;
        returns each episode's results in order (errors for refused steps).
        """
        if self.outstanding:
            raise EsrpError("read the stream's earlier answers with next() before a run")
        results: dict[str, list[StepResult | EsrpError]] = {episode: [] for episode in plans}
        longest = max((len(actions) for actions in plans.values()), default=0)
        for k in range(longest):
            for episode, actions in plans.items():
                if k < len(actions):
                    await self.step(episode, actions[k])
            while self._ledger.ready:
                collect_run(self._ledger.ready.popleft(), results)
        async for answer in self:
            collect_run(answer, results)
        return results

    async def close(self) -> None:
        """Half-closes the stream and waits for the server to end it (unread answers are dropped;
        the server closes the episodes created on the stream).
        """
        if self._ended:
            return
        self._ended = True
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
