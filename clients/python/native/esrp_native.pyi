"""Type stubs of the native transport (see src/lib.rs); `esrp._native` wraps it."""

from typing import Any, TypeVar, overload

from google.protobuf.message import Message

M = TypeVar("M", bound=Message)

METHODS: list[str]

class CallError(Exception):
    """A call that failed with a gRPC status: `args` is (code, message), code the status's number."""

class Channel:
    def __init__(self, url: str, token: str | None = None, connect_timeout: float = 10.0) -> None: ...
    @overload
    def unary(
        self, method: str, request: bytes, timeout: float | None = None, response: None = None
    ) -> bytes: ...
    @overload
    def unary(self, method: str, request: bytes, timeout: float | None, response: type[M]) -> M: ...
    def close(self) -> None: ...

def unary_all(
    calls: list[tuple[Channel, str, bytes, float | None]], response: type[Message] | None = None
) -> list[Any]: ...
