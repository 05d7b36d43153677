"""What the `esrp` commands' parsers share: one-line errors, argument types, the server options."""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from .._values import Sensors, Split
from ..eval.results import ResultsError

SPLITS = tuple(split.value for split in Split)
"""The split names a `--split` flag takes: train, test, challenge, minival."""


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line: `esrp eval: error: ... (esrp eval --help)`.
    A command's parser (one without subcommands) refuses arguments it does not know itself, so the
    message names the command whose `--help` lists them (argparse leaves them to the top parser).
    """

    _has_commands = False

    def add_subparsers(self, **kwargs: Any) -> Any:  # noqa: ANN401 - argparse's own types
        self._has_commands = True
        return super().add_subparsers(**kwargs)

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        # argparse makes the namespace where none is given; made here, its type is Namespace.
        namespace = namespace if namespace is not None else argparse.Namespace()
        parsed, extras = super().parse_known_args(args, namespace)
        if extras and not self._has_commands:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return parsed, extras

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def one_line_errors(handler: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """`handler`, with files that cannot be read or written, and results files that are not
    esrp.results/v1, said in one line (exit status 2) instead of a traceback.
    """

    @functools.wraps(handler)
    def run(args: argparse.Namespace) -> int:
        try:
            return handler(args)
        except OSError as error:
            what = f"{error.strerror}: {error.filename}" if error.strerror and error.filename else error
            print(f"esrp {args.command}: {what}", file=sys.stderr)
            return 2
        except ResultsError as error:
            print(f"esrp {args.command}: {error}", file=sys.stderr)
            return 2

    return run


def comma_list(text: str) -> list[str]:
    """`a,b, c` as `["a", "b", "c"]` (empty parts dropped)."""
    return [part.strip() for part in text.split(",") if part.strip()]


def scene_id_list(text: str) -> list[str]:
    """`--scenes a,b`: at least one scene id, none twice (a scene is played, and resumed, once)."""
    ids = comma_list(text)
    if not ids:
        raise argparse.ArgumentTypeError("names no scene: give scene ids, e.g. esrp-bench-v2/00000")
    twice = sorted({scene for scene in ids if ids.count(scene) > 1})
    if twice:
        raise argparse.ArgumentTypeError(f"lists {', '.join(twice)} more than once")
    return ids


def positive(text: str) -> int:
    """An integer of at least 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


def non_negative(text: str) -> int:
    """An integer of at least 0."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, not {value}")
    return value


def plan_budget(text: str) -> int:
    """A PlanActions budget: milliseconds from 1 to 2³²−1 (the request's `budget_ms` is 32 bits)."""
    value = int(text)
    if not 1 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"must be 1 to 4294967295 milliseconds, not {value}")
    return value


def positive_float(text: str) -> float:
    """A number above 0."""
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, not {text}")
    return value


def _no_constant(name: str) -> object:
    """`NaN`, `Infinity` and `-Infinity`, which Python's json reads but JSON has not."""
    raise ValueError(f"{name} is not a JSON value")


def json_object(text: str) -> dict[str, object]:
    """A JSON object (`--agent-config`)."""
    try:
        value = json.loads(text, parse_constant=_no_constant)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"not JSON: {error}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError("must be a JSON object, e.g. '{\"temperature\": 0.2}'")
    return value


def sensor_list(text: str) -> Sensors:
    """`--sensors depth,segmentation,current_top_down` as `Sensors`."""
    names = set(comma_list(text))
    known = {"depth", "segmentation", "current_top_down"}
    if names - known:
        raise argparse.ArgumentTypeError(f"unknown sensors {sorted(names - known)}: use {sorted(known)}")
    return Sensors(
        depth="depth" in names,
        segmentation="segmentation" in names,
        current_top_down="current_top_down" in names,
    )


def scene_options(
    parser: argparse.ArgumentParser,
    splits: Sequence[str],
    *,
    default: str | None,
    split_help: str,
    limit_help: str,
) -> None:
    """Adds `--split` (one of `splits`), `--difficulty`, `--scenes` and `--limit`: which scenes a
    command runs on, in dataset order.
    """
    parser.add_argument("--split", choices=splits, default=default, help=split_help)
    parser.add_argument("--difficulty", choices=("easy", "medium", "hard"))
    parser.add_argument(
        "--scenes", type=scene_id_list, default=[], metavar="ID,...", help="only these scenes, in order"
    )
    parser.add_argument("--limit", type=positive, metavar="N", help=limit_help)


def server_options(parser: argparse.ArgumentParser) -> None:
    """Adds `--server`, `--server-arg` and `--token` to a command that talks to a server."""
    parser.add_argument(
        "--server",
        type=server_address,
        metavar="ADDR",
        help="a running esrp-server (host:port, or unix:PATH for its --listen-unix socket); without it, "
        "one is started",
    )
    parser.add_argument(
        "--server-arg",
        dest="server_args",
        action="append",
        default=[],
        metavar="ARG",
        help="an argument for the server started here (repeat for several; a flag as --server-arg=--flag)",
    )
    parser.add_argument(
        "--token",
        default=os.environ.get("ESRP_TOKEN"),
        help="bearer token of a server started with --token (default: $ESRP_TOKEN)",
    )


def server_address(text: str) -> str:
    """A `--server` address: `host:port` (or `http://`, `https://`, or another gRPC target), not
    blank.
    """
    if not text.strip():
        raise argparse.ArgumentTypeError("give an address, host:port (e.g. 127.0.0.1:50051)")
    from .._common import target  # imports grpc: here, after the command's grpc settings

    try:
        target(text.strip())
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text.strip()


def command_name(args: argparse.Namespace) -> str:
    """The command `args` were parsed for, as its messages name it: `esrp eval`, `esrp demos export`."""
    sub = getattr(args, f"{args.command}_command", None)
    return f"esrp {args.command}" + (f" {sub}" if isinstance(sub, str) else "")


def on_server(args: argparse.Namespace, run: Callable[[str], int]) -> int:
    """`run(address)` on the server `--server` names, or on one started here (`--server-arg`). A
    `--server` where no server answers is said at once, in one line naming the address as gRPC
    read it (exit status 2), before `run` starts.
    """
    if args.server is not None:
        from .._client import Client
        from .._common import unreachable
        from .._errors import ServerUnavailable

        try:
            with Client(args.server, token=args.token, timeout=30) as client:
                client.server_info()
        except ServerUnavailable as error:
            print(f"{command_name(args)}: {unreachable(args.server, error)}", file=sys.stderr)
            return 2
        return run(args.server)
    from .._local import LocalServer

    with LocalServer(*args.server_args, unix_socket="auto") as local:
        return run(local.address)
