"""The client's exceptions: one class per kind of failure a caller may want to handle.

Every error from the server keeps the server's message (which says what to change), its gRPC status
code as `code`, and the original `grpc.RpcError` as `rpc_error` and as `__cause__`. Errors that a
stream carries in-band have a code and a message but no `rpc_error`.
"""

from __future__ import annotations

import grpc

# Its public names are listed once, in esrp._EXPORTS (esrp/__init__.py), which exports them all.


class EsrpError(Exception):
    """Base class of every error this package raises.

    Attributes:
        message: The server's message (or the client's, for client-side errors).
        code: The gRPC status code, or None for client-side errors.
        rpc_error: The `grpc.RpcError` (sync) or `grpc.aio.AioRpcError` the error came from, or None.
    """

    def __init__(
        self,
        message: str,
        *,
        code: grpc.StatusCode | None = None,
        rpc_error: grpc.RpcError | None = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        self.code = code
        self.rpc_error = rpc_error

    def __str__(self) -> str:
        if self.code is None:
            return self.message
        return f"{self.code.name}: {self.message}"


class NotFound(EsrpError):
    """NOT_FOUND: the episode or scene does not exist."""


class EpisodeNotFound(NotFound):
    """NOT_FOUND for an episode: it never existed, was closed, or was reaped after being idle."""


class SceneNotFound(NotFound):
    """NOT_FOUND for a scene id that is not in the served dataset (`Client.scenes` lists them)."""


class InvalidRequest(EsrpError):
    """INVALID_ARGUMENT (or OUT_OF_RANGE): a malformed request; the message names the field."""


class EpisodeEnded(EsrpError):
    """FAILED_PRECONDITION: a step of an episode that has ended; reset it or create a new one."""


class AlreadyPlayed(EsrpError):
    """FAILED_PRECONDITION for a create (or reset) on a challenge scene this token has played: each
    token gets one counted attempt per challenge scene; the message says when it was played.
    """


class ServerBusy(EsrpError):
    """RESOURCE_EXHAUSTED: a server limit was reached (live episodes, batch size, message size), or
    one of the token's quotas (`max_episodes`, `max_streams`): the message names it.
    """


class Unauthenticated(EsrpError):
    """UNAUTHENTICATED: the server wants a bearer token (`token=`), or a different one."""


class PermissionDenied(EsrpError):
    """PERMISSION_DENIED: privileged state of an episode not created with `privileged=True`, a call
    the token's role does not allow (the message names the role and what it lacks), or another
    token's episode.
    """


class ServerUnavailable(EsrpError):
    """UNAVAILABLE: the server cannot be reached (not running, wrong address or TLS setting)."""


class DeadlineExceeded(EsrpError):
    """DEADLINE_EXCEEDED: the call's timeout passed before the answer came."""


class Cancelled(EsrpError):
    """CANCELLED: the call was cancelled (by this client, or because the channel closed)."""


class ServerError(EsrpError):
    """Any other status: INTERNAL (rendering failed, a server fault), UNKNOWN, UNIMPLEMENTED..."""


class ProtocolError(EsrpError):
    """The server answered something this client cannot read: a version mismatch or a bug."""


class LocalServerError(EsrpError):
    """`LocalServer` could not find, start or stop esrp-server."""


_BY_CODE: dict[grpc.StatusCode, type[EsrpError]] = {
    grpc.StatusCode.INVALID_ARGUMENT: InvalidRequest,
    grpc.StatusCode.OUT_OF_RANGE: InvalidRequest,
    grpc.StatusCode.FAILED_PRECONDITION: EpisodeEnded,
    grpc.StatusCode.RESOURCE_EXHAUSTED: ServerBusy,
    grpc.StatusCode.UNAUTHENTICATED: Unauthenticated,
    grpc.StatusCode.PERMISSION_DENIED: PermissionDenied,
    grpc.StatusCode.UNAVAILABLE: ServerUnavailable,
    grpc.StatusCode.DEADLINE_EXCEEDED: DeadlineExceeded,
    grpc.StatusCode.CANCELLED: Cancelled,
}

_CODES_BY_NUMBER: dict[int, grpc.StatusCode] = {code.value[0]: code for code in grpc.StatusCode}


def error_class(code: grpc.StatusCode, message: str) -> type[EsrpError]:
    """The exception class for a status code and message."""
    if code == grpc.StatusCode.NOT_FOUND:
        # The server's messages: `no scene "…" in the served dataset` and `no episode "…": …`.
        return SceneNotFound if message.startswith("no scene") else EpisodeNotFound
    if code == grpc.StatusCode.FAILED_PRECONDITION and message.startswith("challenge scene"):
        # The server's message: `challenge scene "…" was already played by token …`.
        return AlreadyPlayed
    return _BY_CODE.get(code, ServerError)


def from_status(code: grpc.StatusCode | int, message: str) -> EsrpError:
    """The error for a status code (a `grpc.StatusCode` or its number, as streams carry it)."""
    if isinstance(code, int):
        code = _CODES_BY_NUMBER.get(code, grpc.StatusCode.UNKNOWN)
    return error_class(code, message)(message, code=code)


def from_rpc_error(error: grpc.RpcError) -> EsrpError:
    """The error for a failed call (sync `grpc.RpcError`, which is a `grpc.Call`, or aio's)."""
    code_method = getattr(error, "code", None)
    details_method = getattr(error, "details", None)
    code = code_method() if callable(code_method) else grpc.StatusCode.UNKNOWN
    details = details_method() if callable(details_method) else None
    message = details if isinstance(details, str) and details else str(error)
    if not isinstance(code, grpc.StatusCode):
        code = grpc.StatusCode.UNKNOWN
    converted = error_class(code, message)(message, code=code, rpc_error=error)
    converted.__cause__ = error
    return converted
