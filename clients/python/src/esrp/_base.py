"""What `Client` and `AsyncClient` do apart from waiting: every request they build and every answer
they read, once, without I/O (as httpx's `BaseClient` serves its `Client` and `AsyncClient`).

`ClientBase`, `EpisodeBase` and `EpisodeStreamBase` hold the state and the steps of the sync and
async twins (`Client`/`AsyncClient`, `Episode`/`AsyncEpisode`, `EpisodeStream`/
`AsyncEpisodeStream`), which keep only the calling: `calls.run(call)` or `await calls.run(call)`
of a `UnaryCall` (esrp._transport) built here, a read of the stream or an await of it. The calls
that take more than one message have their halves here too: `ScenePages` (the pages of
`scenes()`), `StepWave` (the StepBatch requests and columns of `step_columns`), `HealthPolls` (the
deadlines of `wait_healthy`) and `abandoning` (what a create does when its caller gives up).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import grpc

from . import _convert
from ._common import RequestKind, StreamLedger, TlsSetting, batch_size, bearer_metadata, credentials, target
from ._errors import DeadlineExceeded, EsrpError, ServerUnavailable, from_rpc_error
from ._transport import UnaryCall, checked_timeout
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
    SceneSummary,
    Sensors,
    ServerInfo,
    Split,
    StepColumns,
    StepResult,
)
from .v1 import esrp_pb2 as pb

if TYPE_CHECKING:
    from ._transport import AsyncCalls, Calls

__all__ = [
    "ClientBase",
    "EpisodeBase",
    "EpisodeStreamBase",
    "HealthPolls",
    "ScenePages",
    "StepWave",
    "abandoning",
    "dataset_call",
    "episode_id",
    "server_info_call",
    "step_batch_call",
]


CallsT = TypeVar("CallsT", "Calls", "AsyncCalls")
"""The unary calls' runner of a client: the sync client's `Calls`, the async client's `AsyncCalls`."""


class ClientBase(Generic[CallsT]):
    """The state both clients keep besides their channel: the address, the call metadata (the
    bearer token), the calls' default deadline (`timeout`, held by `_calls`), the steps per
    StepBatch the server allows, by sensors, and the server's default planning budget once learnt.

    Args:
        address: `host:port`, `http://host:port`, or `https://host:port` (TLS).
        token: Sent as `authorization: Bearer TOKEN` on every call.
        tls: The TLS setting (`TlsSetting`); the channel's credentials come of it and the address.
    """

    _calls: CallsT

    def __init__(self, address: str, token: str | None, tls: TlsSetting) -> None:
        host, https = target(address)
        self.address = host
        self._metadata = bearer_metadata(token)
        # What the subclass's channel is made with (None: a plain channel).
        self._credentials = credentials(tls, https)
        # Steps per StepBatch of `step_columns`, by sensors (from the server's limits).
        self._batch_sizes: dict[Sensors, int] = {}
        # The server's PlanActions budget of a call that names none (`ServerLimits.plan_budget_ms`),
        # once learnt: it sets such a call's deadline.
        self._plan_budget_ms: int | None = None

    @property
    def timeout(self) -> float | None:
        """The deadline of each call, seconds (None: none); settable."""
        return self._calls.timeout

    @timeout.setter
    def timeout(self, value: float | None) -> None:
        self._calls.timeout = checked_timeout(value)

    @property
    def metadata(self) -> tuple[tuple[str, str], ...] | None:
        """The call metadata (the bearer token), for calls through `raw`."""
        return self._metadata

    def _create_wait(self, timeout: float | None) -> float | None:
        """How long `create_episode` waits for its answer: `timeout`, else the client's."""
        return checked_timeout(timeout) if timeout is not None else self.timeout

    def _learn_batch_size(self, sensors: Sensors, info: ServerInfo) -> int:
        """Keeps and returns `batch_size` of the server's limits in `info` for `sensors`."""
        size = self._batch_sizes[sensors] = batch_size(info.limits, sensors)
        return size

    def _learn_plan_budget(self, info: ServerInfo) -> None:
        """Keeps the server's PlanActions budget of a call that names none, from `info`."""
        self._plan_budget_ms = info.limits.plan_budget_ms


def server_info_call() -> UnaryCall[ServerInfo]:
    """The ServerInfo call of `server_info()`."""
    return UnaryCall("ServerInfo", pb.ServerInfoRequest(), _convert.server_info)


def dataset_call() -> UnaryCall[DatasetInfo]:
    """The DescribeDataset call of `describe_dataset()`."""
    return UnaryCall("DescribeDataset", pb.DescribeDatasetRequest(), _convert.dataset_info)


def episode_id(episode: EpisodeBase[Any] | str) -> str:
    """The id of an episode given as its handle or its id."""
    return episode if isinstance(episode, str) else episode.id


def step_batch_call(
    steps: Sequence[tuple[EpisodeBase[Any] | str, ActionLike]], include_goal: bool
) -> UnaryCall[list[StepResult]]:
    """The StepBatch call of `step_batch(steps)`: each action checked (an error names it
    `steps[k]`), the results in request order.
    """
    request = pb.StepBatchRequest(
        steps=[
            _convert.step_request(episode_id(episode), action, include_goal, f"steps[{k}]")
            for k, (episode, action) in enumerate(steps)
        ]
    )
    return UnaryCall("StepBatch", request, lambda answer: _convert.step_results(answer.responses, len(steps)))


class ScenePages:
    """`scenes()` without its I/O: the ListScenes call of each page in turn, whose value is the
    page's scenes, until the server says there is no next page.
    """

    def __init__(
        self, split: Split | str | None, difficulty: Difficulty | str | None, page_size: int
    ) -> None:
        # Built here, so that a bad split, difficulty or page size raises when `scenes()` is called.
        if isinstance(page_size, bool) or not isinstance(page_size, int) or not 0 <= page_size < 2**32:
            raise ValueError(f"page_size: 0 (the server's) or a number of scenes per page, got {page_size!r}")
        self._request: pb.ListScenesRequest | None = pb.ListScenesRequest(
            split=_convert.split_code(split),
            difficulty=_convert.difficulty_code(difficulty),
            page_size=page_size,
        )

    def next_call(self) -> UnaryCall[list[SceneSummary]] | None:
        """The call of the next page; None after the last one."""
        if self._request is None:
            return None
        return UnaryCall("ListScenes", self._request, self._page)

    def _page(self, page: pb.ListScenesResponse) -> list[SceneSummary]:
        assert self._request is not None
        if page.next_page_token:
            self._request.page_token = page.next_page_token
        else:
            self._request = None
        return [_convert.scene_summary(scene) for scene in page.scenes]


class StepWave:
    """`step_columns` without its I/O: the StepBatch requests of one step in each of several
    episodes and of `resets` (`_convert.step_batch_requests`), and the `columns` their answers fill
    in request order (appended to `columns` where given: the waves of several servers, one after
    the other).
    """

    def __init__(
        self,
        episode_ids: Sequence[str],
        actions: Sequence[ActionLike],
        sensors: Sensors,
        resets: Sequence[tuple[str, str | None]],
        columns: StepColumns | None = None,
    ) -> None:
        self._episode_ids = episode_ids
        self._actions = actions
        self._resets = resets
        self._resolution = sensors.resolution
        self._layout = _convert.image_layout(sensors)
        self.columns = columns if columns is not None else StepColumns([key for key, _, _, _ in self._layout])

    @property
    def empty(self) -> bool:
        """Whether there is nothing to send (`columns` is then the answer, empty)."""
        return not self._episode_ids and not self._actions and not self._resets

    def requests(self, size: int) -> list[pb.StepBatchRequest]:
        """The StepBatch requests, of at most `size` steps each (a reset counting as two)."""
        return _convert.step_batch_requests(self._episode_ids, self._actions, size, self._resets)

    def add(self, answer: pb.StepBatchResponse, request: pb.StepBatchRequest) -> StepColumns:
        """Appends the answer to `request` to `columns` (answers in the order of the requests)."""
        return _convert.batch_columns(answer, request, self._layout, self._resolution, into=self.columns)


class HealthPolls:
    """`wait_healthy` without its I/O: the deadline of each health check and the pause after a
    failed one, until `timeout` seconds of `clock` (a monotonic clock, seconds) have passed.
    """

    def __init__(self, address: str, timeout: float, clock: Callable[[], float]) -> None:
        if not float(timeout) >= 0:  # NaN, negative
            raise ValueError(f"timeout must be a non-negative number of seconds, got {timeout!r}")
        self._address = address
        self._timeout = timeout
        self._clock = clock
        self._deadline = clock() + timeout

    def next_check(self) -> float:
        """The deadline of the next check, seconds (at most 1); raises `DeadlineExceeded` when the
        time is up.
        """
        left = self._deadline - self._clock()
        if left <= 0:
            raise DeadlineExceeded(f"the server at {self._address} was not healthy within {self._timeout} s")
        return min(left, 1.0)

    def pause(self) -> float:
        """The wait before the next check, seconds: 50 ms, or what is left of the time."""
        return min(0.05, max(self._deadline - self._clock(), 0))


@contextlib.contextmanager
def abandoning(abandon: Callable[[], None], wait: float | None) -> Iterator[None]:
    """Around the wait for a CreateEpisode answer: when the caller gives up (no answer within
    `wait` seconds: `DeadlineExceeded`; an interrupt, a cancelled task: re-raised), `abandon()`
    lets the call run on, to close its episode when the answer comes. An error the server answered
    goes through as it is: there is no episode to close then.
    """
    try:
        yield
    except EsrpError:
        raise
    except (TimeoutError, asyncio.TimeoutError):
        abandon()
        raise DeadlineExceeded(f"no answer to CreateEpisode within {wait} s") from None
    except BaseException:
        abandon()
        raise


ClientT = TypeVar("ClientT", bound=ClientBase[Any])


class EpisodeBase(Generic[ClientT]):
    """What `Episode` and `AsyncEpisode` share: the handle's state (`Episode` describes it;
    `client` is the client that makes its calls), and the calls of its methods with what each
    does to the state.
    """

    def __init__(self, client: ClientT, created: Created | None, *, episode_id: str = "") -> None:
        self.client = client
        self.closed = False
        self._final: EpisodeMetrics | None = None  # what its close answered
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

    def _step_call(self, action: ActionLike, include_goal: bool) -> UnaryCall[StepResult]:
        return UnaryCall("Step", _convert.step_request(self.id, action, include_goal), _convert.step_result)

    def _reset_call(self, scene: str | None, scene_json: str | None) -> UnaryCall[Observation]:
        return UnaryCall("Reset", _convert.reset_request(self.id, scene, scene_json), self._restarted)

    def _restarted(self, answer: pb.ResetResponse) -> Observation:
        """The first observation of a Reset answer, kept with the scene it names."""
        observation, summary = _convert.reset_observation(answer)
        if summary is not None:
            self.scene = summary
        self.observation = observation
        return observation

    def _goal_call(self) -> UnaryCall[Goal]:
        return UnaryCall("GetGoal", pb.GetGoalRequest(episode_id=self.id), _convert.goal)

    def _metrics_call(self) -> UnaryCall[Progress]:
        return UnaryCall("GetMetrics", pb.GetMetricsRequest(episode_id=self.id), _convert.progress)

    def _privileged_state_call(self) -> UnaryCall[PrivilegedState]:
        request = pb.GetPrivilegedStateRequest(episode_id=self.id)
        return UnaryCall("GetPrivilegedState", request, _convert.privileged_state)

    def _needs_server_budget(self, budget_ms: int | None) -> bool:
        """Whether a PlanActions call's deadline depends on the server's default budget, which the
        client has not learnt yet: the call names no budget and the client has a deadline.
        """
        return budget_ms is None and self.client.timeout is not None and self.client._plan_budget_ms is None

    def _plan_call(self, max_actions: int, budget_ms: int | None) -> UnaryCall[PlanAnswer]:
        request = _convert.plan_request(self.id, max_actions, budget_ms)
        timeout = _convert.plan_timeout(self.client.timeout, budget_ms, self.client._plan_budget_ms or 0)
        return UnaryCall("PlanActions", request, _convert.plan_answer, timeout)

    def _close_call(self) -> UnaryCall[EpisodeMetrics]:
        """Marks the handle closed, and the CloseEpisode call."""
        self.closed = True
        request = pb.CloseEpisodeRequest(episode_id=self.id)
        return UnaryCall("CloseEpisode", request, _convert.closed_metrics)

    def _detach(self) -> str:
        self.closed = True
        return self.id


class EpisodeStreamBase:
    """What `EpisodeStream` and `AsyncEpisodeStream` share: the stream's `StreamLedger` (request
    ids, pending requests, windows, answers read early) and whether the stream has ended.
    """

    def __init__(self, window: int) -> None:
        self._ledger = StreamLedger(window)
        self._ended = False

    @property
    def window(self) -> int:
        """The most steps of one episode in flight."""
        return self._ledger.window

    @property
    def outstanding(self) -> int:
        """Requests sent and not yet returned by `next()`."""
        return self._ledger.outstanding

    def _request(self, kind: RequestKind, episode_id: str, **body: Any) -> pb.StreamRequest:  # noqa: ANN401
        """The next request to send (`StreamLedger.request`); raises `ServerUnavailable` once the
        stream has ended.
        """
        if self._ended:
            raise ServerUnavailable("the stream has ended")
        return self._ledger.request(kind, episode_id, **body)

    def _broken(self, error: grpc.RpcError) -> EsrpError:
        """Ends the stream on a failed read or write; the error to raise."""
        self._ended = True
        return from_rpc_error(error)

    def _cut_short(self) -> ServerUnavailable:
        """Ends the stream that the server ended with requests unanswered; the error to raise."""
        self._ended = True
        return ServerUnavailable("the server ended the stream with requests unanswered")

    def _end(self) -> bool:
        """Marks the stream ended; whether it was live until now (a close has work to do)."""
        live = not self._ended
        self._ended = True
        return live
