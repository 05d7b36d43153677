"""The optional native transport: the hot-path calls of `Client` (Step, Reset, StepBatch) over the
Rust client's channel, through the `esrp_native` extension module (package `esrp-native`, built
from `clients/python/native` with maturin).

grpcio spends about twice the Rust client's CPU on a unary call, and for one agent stepping one
episode that is most of a step's cost. With `esrp-native` installed, `Client(transport="auto")`
(the default) sends those three calls through it; everything else (and `AsyncClient`, streams,
TLS channels) stays on grpcio. Messages are built and parsed in Python exactly as for grpcio, and
errors come as the same `EsrpError` classes, so the two transports answer alike.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any, Literal

import grpc

from .v1 import esrp_pb2 as pb

_extension: ModuleType | None
try:
    _extension = importlib.import_module("esrp_native")
except ImportError:  # the package is optional
    _extension = None

__all__ = ["Transport", "available", "resolve"]

Transport = Literal["auto", "native", "grpcio"]

_CODES = {code.value[0]: code for code in grpc.StatusCode}


def available() -> bool:
    """Whether the `esrp-native` package is installed."""
    return _extension is not None


def resolve(transport: str, secure: bool) -> Literal["native", "grpcio"]:
    """The transport a `Client` uses for its hot path: `auto` takes the native one where it is
    installed and the channel is plain; `native` insists (ValueError where it cannot be had).
    """
    if transport not in ("auto", "native", "grpcio"):
        raise ValueError(f"transport {transport!r}: use 'auto', 'native' or 'grpcio'")
    if transport == "grpcio":
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


class _Method:
    """One unary method, called as grpcio's stub methods are (`method(request, metadata=,
    timeout=)`; the metadata is the channel's token, given when it was made).
    """

    def __init__(self, channel: Any, path: str, response: Any) -> None:  # noqa: ANN401
        self._unary = channel.unary
        self._path = path
        self._response = response

    def __call__(self, request: Any, metadata: object = None, timeout: float | None = None) -> Any:  # noqa: ANN401
        assert _extension is not None
        try:
            # Parsed in place, from the bytes as they were received (no copy into `bytes`).
            return self._unary(self._path, request.SerializeToString(), timeout, self._response)
        except _extension.CallError as error:
            code, details = error.args
            raise NativeRpcError(_CODES.get(code, grpc.StatusCode.UNKNOWN), details) from None


class HotPath:
    """Step, Reset and StepBatch of esrp.v1 over one native channel to `address` (`host:port`)."""

    def __init__(self, address: str, token: str | None) -> None:
        assert _extension is not None
        self._channel = _extension.Channel(f"http://{address}", token)
        self.Step = _Method(self._channel, "/esrp.v1.Esrp/Step", pb.StepResponse)
        self.Reset = _Method(self._channel, "/esrp.v1.Esrp/Reset", pb.ResetResponse)
        self.StepBatch = _Method(self._channel, "/esrp.v1.Esrp/StepBatch", pb.StepBatchResponse)

    def close(self) -> None:
        """Refuses further calls (the connection closes when the channel is collected)."""
        self._channel.close()
