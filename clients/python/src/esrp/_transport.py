"""`Calls`: every unary esrp.v1 call of one `Client`, over one transport, with its token, its
deadline and its errors mapped to `EsrpError` in one place; `AsyncCalls`, the same for an
`AsyncClient` over grpc.aio; `UnaryCall`, one such call as data, which either of them makes.

The transport of `Calls` is the native channel (the `esrp-native` package) for the methods it
carries (the hot path: Step, Reset, StepBatch) where the client uses it, and grpcio for the others
and otherwise. Both take the same request messages and give the same answer messages.
"""

from __future__ import annotations

import concurrent.futures
import math
import numbers
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final, Generic, TypeVar

import grpc
import grpc.aio
from google.protobuf.message import Message

from . import _native
from ._errors import Cancelled, DeadlineExceeded, from_rpc_error
from .v1 import esrp_pb2 as pb
from .v1 import esrp_pb2_grpc as pb_grpc

__all__ = ["CLIENT_TIMEOUT", "AsyncCalls", "Calls", "Pending", "UnaryCall"]

_SERVICE: Final = pb.DESCRIPTOR.services_by_name["Esrp"]
# The answer's message class of each unary method, by name.
_ANSWERS: Final[dict[str, type[Message]]] = {
    method.name: getattr(pb, method.output_type.name)
    for method in _SERVICE.methods
    if not method.client_streaming and not method.server_streaming
}


class _Default:
    """The client's own deadline (`Calls.timeout`), as opposed to None (no deadline)."""


CLIENT_TIMEOUT: Final = _Default()

_T = TypeVar("_T")


LONGEST_DEADLINE: Final = 1e8
"""Seconds (about three years): a longer timeout is no deadline (grpcio fails a call at once whose
deadline is too far to represent; the native transport would wait)."""


def checked_timeout(value: object, what: str = "timeout") -> float | None:
    """`value` as a deadline in seconds, the same on both transports: None (none), or a number of
    at least 0 (a call given 0 fails with `DeadlineExceeded` unsent: `_deadline`), infinity and
    anything past `LONGEST_DEADLINE` none. Raises `ValueError` for NaN, a negative number or
    anything but a number (a bool included).
    """
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{what} must be None or a number of seconds, got {value!r}")
    seconds = float(value)
    if math.isnan(seconds) or seconds < 0:
        raise ValueError(f"{what} must be None or a non-negative number of seconds, got {value!r}")
    if seconds > LONGEST_DEADLINE:
        return None
    return seconds


def client_closed() -> Cancelled:
    """The error of a call made on a closed client (either transport, sync or async)."""
    return Cancelled("the client is closed", code=grpc.StatusCode.CANCELLED)


def _deadline(client_timeout: float | None, timeout: float | None | _Default) -> float | None:
    """The deadline of a call: `timeout` (checked), or the client's (checked when it was set)
    where it is `CLIENT_TIMEOUT`; raises `DeadlineExceeded` where it is 0.
    """
    deadline = client_timeout if isinstance(timeout, _Default) else checked_timeout(timeout)
    if deadline == 0:
        # No time for the call: it fails unsent (grpcio would read 0 as no deadline, and cannot
        # time a call out within its timer's millisecond anyway).
        raise DeadlineExceeded("the call's timeout is 0 s: not sent", code=grpc.StatusCode.DEADLINE_EXCEEDED)
    return deadline


@dataclass(frozen=True)
class UnaryCall(Generic[_T]):
    """One unary call, described and not made: `Calls.run` (sync) or `AsyncCalls.run` (awaited)
    makes it and returns `value(answer)`.

    Attributes:
        method: The unary method's name, e.g. "GetGoal".
        request: Its request message.
        value: What the call returns, of the method's answer message (`esrp._convert`'s readers).
        timeout: The call's deadline, seconds; None: none; `CLIENT_TIMEOUT`: the client's.
    """

    method: str
    request: Message
    value: Callable[[Any], _T]
    timeout: float | None | _Default = CLIENT_TIMEOUT


class Pending:
    """A unary call started without waiting (`Calls.start`): it runs to its end whatever the
    caller does; `result()` waits for its answer.
    """

    def __init__(self, future: grpc.Future[Any] | concurrent.futures.Future[Any]) -> None:
        self._future = future

    def result(self, timeout: float | None = None) -> Any:  # noqa: ANN401
        """The answer; raises `EsrpError` for a call that failed, and `TimeoutError` when no answer
        came within `timeout` seconds (None: wait for it); the call goes on then.
        """
        try:
            return self._future.result(timeout=timeout)
        except (grpc.FutureTimeoutError, concurrent.futures.TimeoutError):
            raise TimeoutError(f"no answer within {timeout} s") from None
        except grpc.RpcError as error:
            raise from_rpc_error(error) from error

    def succeeded(self) -> bool:
        """Whether it has ended with an answer."""
        return self._future.done() and not self._future.cancelled() and self._future.exception() is None

    def add_done_callback(self, function: Callable[[Pending], None]) -> None:
        """Calls `function(self)` when the call ends (at once if it has), on the thread that ends it."""
        self._future.add_done_callback(lambda _: function(self))


class Calls:
    """The unary calls of one client: `calls("GetGoal", request)` answers the method's answer
    message, or raises `EsrpError`.

    Args:
        stub: The grpcio stub of the client's channel.
        native: The client's native channel (`esrp_native.Channel`), or None for grpcio only.
        metadata: What goes with every grpcio call (the bearer token); the native channel was made
            with the token.
        timeout: The deadline of calls that name none, seconds (None: no deadline).
    """

    def __init__(
        self,
        stub: pb_grpc.EsrpStub,
        native: Any | None,  # noqa: ANN401 - esrp_native.Channel, an optional module
        metadata: tuple[tuple[str, str], ...] | None,
        timeout: float | None,
    ) -> None:
        self.timeout = checked_timeout(timeout)
        self._stub = stub
        self._native = native
        self._metadata = metadata
        self.closed = False
        carried = set(_native.methods()) if native is not None else set()
        self._paths = {name: f"/esrp.v1.Esrp/{name}" for name in _ANSWERS}
        self._on_native = {name for name, path in self._paths.items() if path in carried}

    def transport(self, method: str) -> str:
        """The transport that carries `method`: "native" or "grpcio"."""
        return "native" if method in self._on_native else "grpcio"

    def __call__(
        self, method: str, request: Message, *, timeout: float | None | _Default = CLIENT_TIMEOUT
    ) -> Any:  # noqa: ANN401
        """Calls `method` (a unary method's name, e.g. "StepBatch") and waits for its answer."""
        try:
            return self._send(method, request, timeout)
        except grpc.RpcError as error:
            raise from_rpc_error(error) from error

    def run(self, call: UnaryCall[_T]) -> _T:
        """Makes `call` and returns its value."""
        return call.value(self(call.method, call.request, timeout=call.timeout))

    def start(
        self, method: str, request: Message, *, timeout: float | None | _Default = CLIENT_TIMEOUT
    ) -> Pending:
        """Starts `method` without waiting: grpcio's own future, or the native call on a thread
        of its own (the call releases the GIL while it waits).
        """
        if self.closed:
            raise client_closed()
        if method not in self._on_native:
            return Pending(getattr(self._stub, method).future(request, **self._options(timeout)))
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()
        future.set_running_or_notify_cancel()

        def run() -> None:
            try:
                answer = self._send(method, request, timeout)
            except BaseException as error:  # noqa: BLE001 - handed to whoever waits
                future.set_exception(error)
            else:
                future.set_result(answer)

        # A daemon: a call that never ends (no deadline, a server that hangs) must not hold up the
        # interpreter's exit, as a thread pool's workers would.
        threading.Thread(target=run, name=f"esrp-{method}", daemon=True).start()
        return Pending(future)

    def native_call(
        self, method: str, request: Message, *, timeout: float | None | _Default = CLIENT_TIMEOUT
    ) -> tuple[Any, str, Message, float | None] | None:
        """What `esrp._native.call_all` takes to make `method` on this client's native channel
        (channel, path, request, deadline), or None where grpcio carries the method.
        """
        if method not in self._on_native:
            return None
        if self.closed:
            raise client_closed()
        return (self._native, self._paths[method], request, self._options(timeout)["timeout"])

    def close(self) -> None:
        """Refuses further calls (`Cancelled`, on either transport)."""
        self.closed = True
        if self._native is not None:
            self._native.close()

    def _options(self, timeout: float | None | _Default) -> dict[str, Any]:
        return {"metadata": self._metadata, "timeout": _deadline(self.timeout, timeout)}

    def _send(self, method: str, request: Message, timeout: float | None | _Default) -> Any:  # noqa: ANN401
        if self.closed:
            raise client_closed()
        options = self._options(timeout)
        if method in self._on_native:
            path, answer = self._paths[method], _ANSWERS[method]
            return _native.call(self._native, path, request, answer, options["timeout"])
        return getattr(self._stub, method)(request, **options)


def run_all(method: str, calls: Sequence[tuple[Calls, Message]]) -> list[Any]:
    """Makes several calls of the unary `method` at once, each `(calls, request)` on its client's
    `Calls` (a wave of StepBatch calls over one or several servers), and returns their answers in
    order; raises the `EsrpError` of the first one (in order) that failed.

    Where every call goes over the native transport, one `esrp_native.unary_all` makes them all
    with the GIL released once and parses the answers on this thread after all have ended;
    otherwise all but the last are started (`Calls.start`, they run on whatever happens) and the
    last is made here.
    """
    native = [each.native_call(method, request) for each, request in calls] if len(calls) > 1 else []
    made = [call for call in native if call is not None]
    if made and len(made) == len(calls):
        answers = _native.call_all(made, _ANSWERS[method])
        for answer in answers:
            if isinstance(answer, grpc.RpcError):
                raise from_rpc_error(answer) from answer
        return answers
    started = [each.start(method, request) for each, request in calls[:-1]]
    last_calls, last_request = calls[-1]
    last = last_calls(method, last_request)
    return [*(pending.result() for pending in started), last]


class AsyncCalls:
    """The unary calls of one `AsyncClient`, over grpc.aio: `await calls("GetGoal", request)`
    answers the method's answer message, or raises `EsrpError`.

    Args:
        stub: The grpc.aio stub of the client's channel.
        metadata: What goes with every call (the bearer token).
        timeout: The deadline of calls that name none, seconds (None: no deadline).
    """

    def __init__(
        self,
        stub: pb_grpc.EsrpAsyncStub,
        metadata: tuple[tuple[str, str], ...] | None,
        timeout: float | None,
    ) -> None:
        self.timeout = checked_timeout(timeout)
        self.closed = False
        self._stub = stub
        self._metadata = metadata

    async def __call__(
        self, method: str, request: Message, *, timeout: float | None | _Default = CLIENT_TIMEOUT
    ) -> Any:  # noqa: ANN401
        """Calls `method` (a unary method's name, e.g. "StepBatch") and waits for its answer."""
        if self.closed:
            raise client_closed()
        send = getattr(self._stub, method)
        try:
            return await send(request, metadata=self._metadata, timeout=_deadline(self.timeout, timeout))
        except grpc.aio.AioRpcError as error:
            raise from_rpc_error(error) from error

    async def run(self, call: UnaryCall[_T]) -> _T:
        """Makes `call` and returns its value."""
        return call.value(await self(call.method, call.request, timeout=call.timeout))

    def close(self) -> None:
        """Refuses further calls (`Cancelled`)."""
        self.closed = True
