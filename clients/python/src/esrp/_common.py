"""What the sync and async clients share: channel settings, credentials, the bearer token, the
health check's bytes, and the bookkeeping of a pipelined StepStream (request ids, pending requests,
per-episode windows, the order of `EpisodeStream.run`).
"""

from __future__ import annotations

import enum
import ipaddress
import os
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar, Union

import grpc

from . import _convert, _signals
from ._errors import EsrpError, InvalidRequest, ProtocolError, from_status
from ._values import (
    ActionLike,
    Created,
    EpisodeMetrics,
    Observation,
    SceneSummary,
    Sensors,
    ServerLimits,
    StepResult,
    observation_images,
)
from .v1 import esrp_pb2 as pb

MAX_MESSAGE_BYTES = 256 << 20
"""The largest message either side of a client sends (a StepBatch of many high-resolution views)."""

STREAM_WINDOW_BYTES = 16 << 20
"""HTTP/2 stream window the client asks for (gRPC core's `lookahead_bytes`), as the Rust client."""

ChannelOptions = Sequence[tuple[str, Any]]

TlsSetting = Union[bool, bytes, str, "os.PathLike[str]", grpc.ChannelCredentials, None]
"""TLS: None/False (plain, unless the address starts with https://), True (the system's roots), the
PEM bytes of the CA that signed the server's certificate, a path to that PEM file, or ready-made
`grpc.ChannelCredentials` (e.g. `grpc.ssl_channel_credentials(...)`)."""


def channel_options(
    tls_server_name: str | None, extra: ChannelOptions, address: str = ""
) -> list[tuple[str, Any]]:
    """The channel arguments of every client (of a server at `address`).

    An agent waits for every answer and a batch moves megabytes: gRPC core sets TCP_NODELAY on its
    sockets itself; the message limits are raised from grpcio's 4 MiB (an observation is ~49 KB, so a
    StepBatch of ~85 episodes exceeds that); each stream starts with a 16 MiB window, and BDP probing
    (on by default) grows the connection's window as the Rust client's 64 MiB one. Over a Unix domain
    socket (`unix:PATH`) the authority is `localhost`. `extra` options come last and win.
    """
    options: list[tuple[str, Any]] = [
        ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
        ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
        ("grpc.http2.lookahead_bytes", STREAM_WINDOW_BYTES),
        ("grpc.http2.bdp_probe", 1),
    ]
    if tls_server_name is not None:
        options.append(("grpc.ssl_target_name_override", tls_server_name))
    if address.startswith("unix:"):
        # gRPC core sends a socket's path, percent-encoded, as the `:authority`; the server's HTTP/2
        # layer refuses that as malformed (PROTOCOL_ERROR): `localhost`, as Kubernetes and tonic do.
        options.append(("grpc.default_authority", "localhost"))
    names = {name for name, _ in extra}
    return [option for option in options if option[0] not in names] + list(extra)


def open_channel(
    address: str, credentials: grpc.ChannelCredentials | None, options: ChannelOptions
) -> grpc.Channel:
    """A grpcio channel to `address`, plain without `credentials`, made with a signal's exception
    held until it exists (`_signals.deferred`).

    grpcio makes its channels in Cython that runs Python code (the first `grpc.aio` channel starts
    its poller thread) and does not survive an exception raised there: the half-made channel's
    finalizer shuts down what was never set up, and the process dies of SIGSEGV. A SIGTERM or Ctrl-C
    that lands there in an `esrp` command is raised once the channel is whole instead.
    """
    with _signals.deferred():
        if credentials is None:
            return grpc.insecure_channel(address, options=options)
        return grpc.secure_channel(address, credentials, options=options)


def open_aio_channel(
    address: str, credentials: grpc.ChannelCredentials | None, options: ChannelOptions
) -> grpc.aio.Channel:
    """`open_channel` for `grpc.aio`."""
    with _signals.deferred():
        if credentials is None:
            return grpc.aio.insecure_channel(address, options=options)
        return grpc.aio.secure_channel(address, credentials, options=options)


def target(address: str) -> tuple[str, bool]:
    """`host:port` of an address (`host:port`, `http://host:port` or `https://host:port`), and
    whether its scheme asks for TLS. Raises `TypeError` for an address that is not a string, and
    `ValueError` for one that names no server, whose port is not a number from 0 to 65535 (gRPC
    would wrap it around: 70000 is port 4464), or that is an IPv6 address and a port without the
    brackets (`::1:50051`, which gRPC reads as a host name on port 443: `[::1]:50051`).
    """
    if not isinstance(address, str):
        raise TypeError(f"address: a string such as '127.0.0.1:50051', got {address!r}")
    host, secure, scheme = address, False, ""
    for prefix, tls in (("http://", False), ("https://", True)):
        if address.startswith(prefix):
            host, secure, scheme = address[len(prefix) :].rstrip("/"), tls, prefix
    if not host.strip():
        raise ValueError(f"address {address!r} names no server: give host:port, e.g. 127.0.0.1:50051")
    _refuse_unbracketed_ipv6_port(address, scheme, host)
    _, port = _host_and_port(host)
    if port and not (port.isdigit() and int(port) <= 65535):
        raise ValueError(f"address {address!r}: its port {port!r} is not a number from 0 to 65535")
    return host, secure


def _refuse_unbracketed_ipv6_port(address: str, scheme: str, host: str) -> None:
    """Raises `ValueError` when `host` (of `address`, after its `scheme`) is an IPv6 address and a
    decimal port without brackets (`::1:50051`, `fe80::1%eth0:8080`). gRPC takes a bare name with
    several colons whole as the host, on port 443: `::1:50051` fails as a misformatted domain name,
    and `::1:8080`, an IPv6 address itself, is reached on port 443. Such an address with a port is
    written `[::1]:50051`; one meant without a port, `[::1:8080]`.
    """
    if host.count(":") < 2 or host.startswith("[") or _host_and_port(host)[0] is None:
        return
    name, _, port = host.rpartition(":")
    if not (port.isascii() and port.isdigit() and _is_ipv6(name)):
        return
    alone = (
        f" ({scheme}[{host}] for the address {host} on gRPC's default port, 443)" if _is_ipv6(host) else ""
    )
    raise ValueError(
        f"address {address!r}: write an IPv6 address with a port in brackets, {scheme}[{name}]:{port}"
        f"{alone}; without them gRPC reads it all as the host"
    )


def _is_ipv6(text: str) -> bool:
    """Whether `text` is an IPv6 address (without brackets)."""
    try:
        ipaddress.IPv6Address(text)
    except ValueError:
        return False
    return True


def _host_and_port(host: str) -> tuple[str, str] | tuple[None, None]:
    """The name and port of a `host:port` (the port "" where there is none; an IPv6 name in
    brackets), or (None, None) for another gRPC target form (`unix:...`, `dns:///...`).
    """
    if "/" in host or host.startswith(("unix:", "unix-abstract:", "vsock:", "ipv4:", "ipv6:")):
        return None, None
    if host.startswith("["):  # [IPv6] or [IPv6]:port
        name, _, port = host[1:].partition("]")
        return f"[{name}]", port.removeprefix(":")
    if host.count(":") == 1:
        name, port = host.split(":")
        return name, port
    if host.count(":") > 1:  # a bare IPv6 address
        return f"[{host}]", ""
    return host, ""


def parsed_address(address: str) -> tuple[str, str]:
    """The `host:port` gRPC connects to for an address (after `target`), and what it made of an
    address without a port: `127.0.0.1` is `127.0.0.1:443` (gRPC's default port), `50051` is host
    `50051` on port 443. The note is empty for a `host:port` address, or another gRPC target form
    (`unix:...`, `dns:///...`).
    """
    host, _ = target(address)
    name, port = _host_and_port(host)
    if name is None:
        return host, ""
    if port:
        return f"{name}:{port}", ""
    note = f"{address!r} has no port, so gRPC's default, 443, is used"
    if name.isdigit():
        note += f": {name!r} is read as a host name (did you mean 127.0.0.1:{name}?)"
    elif not name:
        note = f"{address!r} has no host or port"
    return f"{name}:443", note


def unreachable(address: str, error: EsrpError) -> str:
    """A one-line message for a server that cannot be reached at `address` (a `ServerUnavailable`
    `error`): the address as gRPC read it, what it made of a missing port, and gRPC's reason.
    """
    parsed, note = parsed_address(address)
    given = f" ({note})" if note else "" if parsed == address else f" (from {address!r})"
    return f"no esrp-server answers at {parsed}{given}: {error.message}"


def credentials(tls: TlsSetting, https: bool) -> grpc.ChannelCredentials | None:
    """The channel credentials of a TLS setting, or None for a plain channel."""
    if tls is None:
        return grpc.ssl_channel_credentials() if https else None
    if isinstance(tls, grpc.ChannelCredentials):
        return tls
    if isinstance(tls, bool):
        return grpc.ssl_channel_credentials() if tls else None
    if isinstance(tls, bytes):
        return grpc.ssl_channel_credentials(root_certificates=tls)
    path = Path(tls)
    try:
        return grpc.ssl_channel_credentials(root_certificates=path.read_bytes())
    except OSError as error:
        raise InvalidRequest(f"cannot read the TLS root certificate {path}: {error}") from error


# grpc.health.v1.Health/Check, hand-encoded: the request holds only its `service` string (field 1),
# the answer only its `status` enum (field 1; SERVING is 1). Spares a dependency on
# grpcio-health-checking for two bytes.
HEALTH_METHOD = "/grpc.health.v1.Health/Check"
HEALTH_REQUEST = b"\x0a\x0cesrp.v1.Esrp"  # HealthCheckRequest{service: "esrp.v1.Esrp"}
SERVING = b"\x08\x01"  # HealthCheckResponse{status: SERVING}


def bearer_metadata(token: str | None) -> tuple[tuple[str, str], ...] | None:
    """The `authorization: Bearer TOKEN` metadata of every call, or None without a token."""
    if token is None:
        return None
    if not token or not all(" " <= c <= "~" for c in token):
        raise InvalidRequest("the token must be non-empty printable ASCII (the server's --token)")
    return (("authorization", f"Bearer {token}"),)


# Reserve for a StepBatch answer's framing, per step (the info, reward and flags take ~60 bytes).
_STEP_OVERHEAD_BYTES = 512


def batch_size(limits: ServerLimits, sensors: Sensors) -> int:
    """The most steps of `sensors`' episodes per StepBatch of `step_columns`: the server's
    `max_batch`, and as many answers as fit in half its message limit.
    """
    pixels = sensors.resolution**2
    per_step = _STEP_OVERHEAD_BYTES + sum(pixels * size for _, size, _ in observation_images(sensors))
    return max(1, min(limits.max_batch, limits.max_message_bytes // 2 // per_step))


class RequestKind(enum.Enum):
    """What a stream request asks."""

    CREATE = "create"
    STEP = "step"
    RESET = "reset"
    CLOSE = "close"


AnswerValue = Created | StepResult | Observation | EpisodeMetrics
_T = TypeVar("_T", Created, StepResult, Observation, EpisodeMetrics)


@dataclass(frozen=True, eq=False)
class StreamAnswer:
    """One answer of an episode stream, in request order.

    Attributes:
        request_id: The id the stream gave the request (counting from 1 in sending order).
        kind: What the request asked.
        episode_id: The episode it was about (for a create, the new episode's id; empty if it failed).
        value: `Created` (create), `StepResult` (step), `Observation` (reset, with the goal) or
            `EpisodeMetrics` (close); None when the server refused the request.
        error: The error the server gave this request alone (the stream goes on), or None.
        scene: The scene the episode plays, on the answer of a create or a reset (else None).
    """

    request_id: int
    kind: RequestKind
    episode_id: str
    value: AnswerValue | None
    error: EsrpError | None
    scene: SceneSummary | None = None

    def unwrap(self) -> AnswerValue:
        """The value; raises the request's error if the server refused it."""
        if self.error is not None:
            raise self.error
        assert self.value is not None
        return self.value

    def _typed(self, kind: type[_T]) -> _T:
        value = self.unwrap()
        if not isinstance(value, kind):
            raise ProtocolError(f"request {self.request_id} was a {self.kind.value}, not a {kind.__name__}")
        return value

    def created(self) -> Created:
        """The created episode (raises the request's error)."""
        return self._typed(Created)

    def step_result(self) -> StepResult:
        """The step's result (raises the request's error)."""
        return self._typed(StepResult)

    def observation(self) -> Observation:
        """The first observation after a reset (raises the request's error)."""
        return self._typed(Observation)

    def metrics(self) -> EpisodeMetrics:
        """The metrics of a closed episode (raises the request's error)."""
        return self._typed(EpisodeMetrics)


@dataclass
class _Pending:
    request_id: int
    kind: RequestKind
    episode_id: str


class StreamLedger:
    """The protocol-side state of a pipelined StepStream, without I/O: request ids, the requests
    sent and not yet answered, each episode's steps in flight, and answers read early.
    """

    def __init__(self, window: int) -> None:
        if window < 1:
            raise InvalidRequest("an episode stream needs a window of at least 1")
        self.window = window
        self.pending: deque[_Pending] = deque()
        self.ready: deque[StreamAnswer] = deque()
        self.steps_in_flight: dict[str, int] = {}
        self.next_request_id = 1

    def request(self, kind: RequestKind, episode_id: str, **body: Any) -> pb.StreamRequest:  # noqa: ANN401
        """The next request (its id assigned), recorded as pending."""
        request_id = self.next_request_id
        self.next_request_id += 1
        self.pending.append(_Pending(request_id, kind, episode_id))
        if kind is RequestKind.STEP:
            self.steps_in_flight[episode_id] = self.steps_in_flight.get(episode_id, 0) + 1
        return pb.StreamRequest(request_id=request_id, **body)

    def window_full(self, episode_id: str) -> bool:
        """Whether `episode_id` already has `window` steps in flight."""
        return self.steps_in_flight.get(episode_id, 0) >= self.window

    @property
    def outstanding(self) -> int:
        """Requests sent and not yet handed out."""
        return len(self.pending) + len(self.ready)

    @property
    def unread(self) -> bool:
        """Whether the next answer is still on the stream: none was read early and one is pending."""
        return not self.ready and bool(self.pending)

    def take_ready(self) -> StreamAnswer | None:
        """The oldest answer read early (while a window was full), or None."""
        return self.ready.popleft() if self.ready else None

    def run_results(
        self, plans: Mapping[str, Sequence[ActionLike]]
    ) -> dict[str, list[StepResult | EsrpError]]:
        """The empty results of `EpisodeStream.run(plans)`, by episode; raises `EsrpError` while
        answers to earlier requests are unread (they would land among the run's), and
        `InvalidRequest` for an action that is no action code, before any step is sent.
        """
        if self.outstanding:
            raise EsrpError("read the stream's earlier answers with next() before a run")
        for episode, actions in plans.items():
            for k, action in enumerate(actions):
                _convert.action_code(action, f"plans[{episode!r}][{k}]")
        return {episode: [] for episode in plans}

    def collect_ready(self, results: dict[str, list[StepResult | EsrpError]]) -> None:
        """Files the answers read early under their episodes of a run (`collect_run`)."""
        while self.ready:
            collect_run(self.ready.popleft(), results)

    def answer(self, response: pb.StreamResponse) -> StreamAnswer:
        """The answer of the oldest pending request, from the server's response to it."""
        if not self.pending:
            raise ProtocolError(f"an answer to request {response.request_id}, which was never sent")
        pending = self.pending.popleft()
        if pending.kind is RequestKind.STEP:
            left = self.steps_in_flight[pending.episode_id] - 1
            if left:
                self.steps_in_flight[pending.episode_id] = left
            else:
                del self.steps_in_flight[pending.episode_id]
        if response.request_id != pending.request_id:
            raise ProtocolError(
                f"an answer to request {response.request_id} where request {pending.request_id} was due"
            )
        which = response.WhichOneof("response")
        episode_id = pending.episode_id
        value: AnswerValue | None = None
        error: EsrpError | None = None
        scene: SceneSummary | None = None
        try:
            if which == "error":
                error = from_status(response.error.code, response.error.message)
            elif pending.kind is RequestKind.CREATE and which == "created":
                value = _convert.created(response.created)
                episode_id = value.episode_id
                scene = value.scene
            elif pending.kind is RequestKind.STEP and which == "step":
                value = _convert.step_result(response.step)
            elif pending.kind is RequestKind.RESET and which == "reset":
                value, scene = _convert.reset_observation(response.reset)
            elif pending.kind is RequestKind.CLOSE and which == "closed":
                value = _convert.closed_metrics(response.closed)
            else:
                raise ProtocolError(f"a {pending.kind.value} request answered with {which!r}")
        except ProtocolError as protocol_error:
            error = protocol_error
        return StreamAnswer(pending.request_id, pending.kind, episode_id, value, error, scene)


def run_rounds(plans: Mapping[str, Sequence[ActionLike]]) -> Iterator[list[tuple[str, ActionLike]]]:
    """The steps of `EpisodeStream.run(plans)`, round by round: round k holds the k-th action of
    each episode that has one, in the plans' order (so the episodes interleave).
    """
    longest = max((len(actions) for actions in plans.values()), default=0)
    for k in range(longest):
        yield [(episode, actions[k]) for episode, actions in plans.items() if k < len(actions)]


def collect_run(answer: StreamAnswer, results: dict[str, list[StepResult | EsrpError]]) -> None:
    """Files a step answer of `EpisodeStream.run` under its episode."""
    if answer.episode_id not in results:
        raise InvalidRequest(
            f"an answer for episode {answer.episode_id!r} outside the run: "
            "read earlier answers with next() first"
        )
    if answer.error is not None:
        results[answer.episode_id].append(answer.error)
    else:
        results[answer.episode_id].append(answer.step_result())
