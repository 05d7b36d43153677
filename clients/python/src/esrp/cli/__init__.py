"""The `esrp` command: `esrp eval` (run an agent over a split, write `esrp.results/v1` records),
`esrp verify` (replay results files' records on the server and check them), `esrp report` (tables
and plots of results files as Markdown and one self-contained HTML page; `--leaderboard`: the
challenge's ranking from a server's records) and `esrp replay` (re-run a recorded episode on the
server and write it as a GIF, MP4 or PNG); `esrp doctor` checks that this machine can run ESRP.
`esrp COMMAND --help` says more; docs/evaluation.md describes the results files.

Each command group has its module, parser and handlers together: `cli.evaluation` (eval, verify,
report, replay), `cli.training` (demos export, train bc|ppo); `cli._args` holds what their parsers
share.
`esrp bench` hands its arguments to `cli.bench` (the benchmark, also `python -m esrp.bench`), which
parses them itself.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
from collections.abc import Callable, Sequence

from .. import __version__, _grpc_setup
from .._signals import run_command
from . import doctor, evaluation, training
from ._args import Parser, command_name

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = Parser(prog="esrp", description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--version", action="version", version=f"esrp {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    evaluation.add_commands(commands)
    training.add_commands(commands)
    doctor.add_commands(commands)
    commands.add_parser(
        "bench",
        add_help=False,
        help="throughput of the Python client and env beside the Rust client and MiniWorld "
        "(python -m esrp.bench; `esrp bench --help` lists its options)",
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Runs `esrp ARGS` (`argv` without the program name; default `sys.argv[1:]`); returns the exit
    status: 0 done, 1 episodes failed (eval) or records do not match (verify), 2 bad arguments or
    input, 3 the server died or stayed unreachable (eval, verify, train: the run stopped there), 130
    interrupted, 143 terminated (SIGTERM, when run as the `esrp` command).
    """
    arguments = list(sys.argv[1:] if argv is None else argv)
    command = f"esrp {arguments[0]}" if arguments and not arguments[0].startswith("-") else "esrp"
    # The command line's process (not a call from Python code): SIGTERM (kill, a job scheduler)
    # unwinds as Ctrl-C does, so a server started here is stopped and files are closed instead of
    # being left behind, and neither signal is ever lost (esrp._signals).
    handle_signals = argv is None and threading.current_thread() is threading.main_thread()
    if argv is None:
        # The command's own process: grpcio's settings, before anything here imports grpc (this
        # module imports it only in the commands' handlers).
        _grpc_setup.apply()
    try:
        return run_command(command, lambda: _run(arguments), handle_signals=handle_signals)
    except BrokenPipeError:
        if argv is not None:
            raise
        # The reader of stdout went away (`esrp doctor | head`): stop quietly, as Unix tools do,
        # with stdout on /dev/null so that the interpreter's flush at exit does not fail again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141  # 128 + SIGPIPE: the status of a tool that the signal stopped


def _run(arguments: list[str]) -> int:
    if arguments[:1] == ["bench"]:
        # Its own parser and options (also `python -m esrp.bench`).
        from . import bench

        return bench.main(arguments[1:], prog="esrp bench")
    args = _parser().parse_args(arguments)
    from .._errors import EsrpError

    handler: Callable[[argparse.Namespace], int] = args.handler
    try:
        return handler(args)
    except EsrpError as error:
        print(f"{command_name(args)}: {type(error).__name__}: {error}", file=sys.stderr)
        return 2
