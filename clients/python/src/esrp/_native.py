"""The optional native transport: the hot-path calls of `Client` (Step, Reset, StepBatch) over the
Rust client's channel, through the `esrp_native` extension module (package `esrp-native`, built
from `clients/python/native` with maturin).

grpcio spends about twice the Rust client's CPU on a unary call, and for one agent stepping one
episode that is most of a step's cost. With `esrp-native` installed, `Client(transport="auto")`
(the default) sends those three calls through it (`esrp._transport.Calls` routes each call);
everything else (and `AsyncClient`, streams, TLS channels) stays on grpcio, whose answers to a
server that is not there, or not an esrp-server, are the ones the package's messages are made
of. Messages are built and parsed in Python exactly as for grpcio, and errors come as the same
`EsrpError` classes, so the two transports answer alike.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from types import ModuleType
from typing import Any, Literal, TypeVar, cast

import grpc
from google.protobuf.message import Message

_extension: ModuleType | None
try:
    _extension = importlib.import_module("esrp_native")
except ImportError:  # the package is optional
    _extension = None

__all__ = ["NativeRpcError", "Transport", "available", "call", "call_all", "channel", "methods", "resolve"]

Transport = Literal["auto", "native", "grpcio"]

_CODES = {code.value[0]: code for code in grpc.StatusCode}

M = TypeVar("M", bound=Message)


def available() -> bool:
    """Whether the `esrp-native` package is installed."""
    return _extension is not None


def url(address: str) -> str | None:
    """What the native channel connects to for a gRPC `address` (after `target`): `unix:PATH` as
    it is, `host:port` as `http://host:port`; None for the target forms only grpcio resolves
    (`dns:`, `unix-abstract:`, `vsock:`, `ipv4:`, `ipv6:`).
    """
    if address.startswith("unix:"):
        return address
    if address.startswith(("dns:", "unix-abstract:", "vsock:", "ipv4:", "ipv6:")):
        return None
    return f"http://{address}"


def resolve(transport: str, secure: bool, address: str | None = None) -> Literal["native", "grpcio"]:
    """The transport a `Client` uses for its hot path: `auto` takes the native one where it is
    installed, the channel is plain and the native channel can reach `address` (see `url`);
    `native` insists (ValueError where it cannot be had).
    """
    if transport not in ("auto", "native", "grpcio"):
        raise ValueError(f"transport {transport!r}: use 'auto', 'native' or 'grpcio'")
    if transport == "grpcio":
        return "grpcio"
    if address is not None and url(address) is None:
        if transport == "native":
            raise ValueError(
                f"the native transport reaches host:port and unix:PATH addresses, not {address!r}: "
                "use transport='grpcio'"
            )
        return "grpcio"
    if _extension is None:
        if transport == "native":
            raise ValueError(
                "transport='native' needs the esrp-native package: pip install ./clients/python/native "
                "(a Rust toolchain builds it)"
            )
        return "grpcio"
    if secure:
        if transport == "native":
            raise ValueError("the native transport speaks plain HTTP/2 only: use transport='grpcio' with TLS")
        return "grpcio"
    return "native"


class NativeRpcError(grpc.RpcError):
    """A native call that failed with a gRPC status; `code()` and `details()` as grpcio's errors
    (so `from_rpc_error` maps it to the same `EsrpError` class).
    """

    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        super().__init__(f"{code.name}: {details}")
        self._code = code
        self._details = details

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return self._details


def channel(address: str, token: str | None) -> Any:  # noqa: ANN401
    """A native channel to `address` (`host:port` or `unix:PATH`: `resolve` chose the native
    transport for it) that sends `token` with every call; it connects at the first call.
    """
    assert _extension is not None
    reached = url(address)
    assert reached is not None, f"resolve() gives grpcio for {address!r}"
    return _extension.Channel(reached, token)


def methods() -> list[str]:
    """The paths of the unary methods the installed extension carries (Step, Reset, StepBatch)."""
    return list(_extension.METHODS) if _extension is not None else []


def call(channel: Any, path: str, request: Message, answer: type[M], timeout: float | None) -> M:  # noqa: ANN401
    """Calls the unary method `path` over `channel` and waits: its answer, parsed in place from
    the bytes as they were received (no copy into `bytes`); a failed call raises `NativeRpcError`.
    """
    assert _extension is not None
    try:
        return cast(M, channel.unary(path, request.SerializeToString(), timeout, answer))
    except _extension.CallError as error:
        code, details = error.args
        raise NativeRpcError(_CODES.get(code, grpc.StatusCode.UNKNOWN), details) from None


def call_all(
    calls: Sequence[tuple[Any, str, Message, float | None]], answer: type[M]
) -> list[M | NativeRpcError]:
    """Makes several unary calls at once, each `(channel, path, request, timeout)` (the channels
    may differ), and waits for all of them: each one's answer (parsed in place, as `call`'s), or
    its `NativeRpcError`, in order. The GIL is released once for all; the answers are parsed on
    this thread after they have all come.
    """
    assert _extension is not None
    sent = [(channel, path, request.SerializeToString(), limit) for channel, path, request, limit in calls]
    results: list[M | NativeRpcError] = []
    for result in _extension.unary_all(sent, answer):
        if isinstance(result, _extension.CallError):
            code, details = result.args
            results.append(NativeRpcError(_CODES.get(code, grpc.StatusCode.UNKNOWN), details))
        else:
            results.append(cast(M, result))
    return results
