"""The `esrp` command: `esrp eval` (run an agent over a split, write `esrp.results/v1` records),
`esrp report` (tables and plots of results files as Markdown and one self-contained HTML page) and
`esrp replay` (re-run a recorded episode on the server and write it as a GIF, MP4 or PNG).
`esrp COMMAND --help` says more; docs/evaluation.md describes the results files.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NoReturn

from . import __version__
from ._errors import EsrpError
from ._signals import run_command
from ._values import Sensors
from .results import ResultsError

__all__ = ["main"]


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line: `esrp eval: error: ... (esrp eval --help)`."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _one_line_errors(handler: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
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


def _comma_list(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, not {text}")
    return value


def _json_object(text: str) -> dict[str, object]:
    try:
        value = json.loads(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"not JSON: {error}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError("must be a JSON object, e.g. '{\"temperature\": 0.2}'")
    return value


def _sensors(text: str) -> Sensors:
    names = set(_comma_list(text))
    known = {"depth", "segmentation", "current_top_down"}
    if names - known:
        raise argparse.ArgumentTypeError(f"unknown sensors {sorted(names - known)}: use {sorted(known)}")
    return Sensors(
        depth="depth" in names,
        segmentation="segmentation" in names,
        current_top_down="current_top_down" in names,
    )


def _server_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--server", metavar="ADDR", help="a running esrp-server (host:port); without it, one is started"
    )
    parser.add_argument(
        "--server-arg",
        dest="server_args",
        action="append",
        default=[],
        metavar="ARG",
        help="an argument for the server started here (repeat for several)",
    )
    parser.add_argument(
        "--token",
        default=os.environ.get("ESRP_TOKEN"),
        help="bearer token of a server started with --token (default: $ESRP_TOKEN)",
    )


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="esrp", description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--version", action="version", version=f"esrp {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    ev = commands.add_parser(
        "eval",
        help="run an agent over the scenes of a split; write one esrp.results/v1 record per episode",
        description="Run an agent over the scenes of a split and write one esrp.results/v1 record per "
        "episode (docs/evaluation.md), resuming what --out already holds; a Markdown summary is written "
        "beside it. The exit status is 1 when episodes failed with an error (they are not recorded).",
    )
    ev.add_argument(
        "--agent",
        required=True,
        help="random, expert, plan, vlm (ESRP-VLM over an OpenAI-compatible endpoint: --base-url, "
        "--model), bc (ESRP-BC: --checkpoint), ppo (ESRP-PPO: --checkpoint), or MODULE:CALLABLE "
        "(a factory called with the agent config, once per episode, "
        "returning an esrp.agents.Agent or AsyncAgent)",
    )
    ev.add_argument("--split", choices=("train", "test"), default="test")
    ev.add_argument("--difficulty", choices=("easy", "medium", "hard"))
    ev.add_argument(
        "--scenes", type=_comma_list, default=[], metavar="ID,...", help="only these scenes, in order"
    )
    ev.add_argument(
        "--limit", type=_positive, metavar="N", help="at most N scenes (the first after the filters)"
    )
    ev.add_argument("--episodes-in-flight", type=_positive, default=8, metavar="N")
    ev.add_argument("--seed", type=int, default=0, help="base seed; scene ID uses seed XOR fnv1a64(ID)")
    ev.add_argument("--out", type=Path, required=True, help="the results file (JSON Lines)")
    ev.add_argument("--fresh", action="store_true", help="start --out over instead of resuming it")
    ev.add_argument("--summary", type=Path, help="the Markdown summary (default: --out with .md)")
    ev.add_argument(
        "--agent-config",
        type=_json_object,
        default={},
        metavar="JSON",
        help="a vlm or MODULE:CALLABLE agent's config",
    )
    ev.add_argument(
        "--base-url",
        metavar="URL",
        help="vlm: the OpenAI-compatible endpoint, e.g. http://localhost:8000/v1 (the config's base_url); "
        "the API key is $ESRP_VLM_API_KEY or $OPENAI_API_KEY",
    )
    ev.add_argument("--model", metavar="NAME", help="vlm: the model it serves (the config's model)")
    ev.add_argument(
        "--checkpoint",
        type=Path,
        metavar="PATH",
        help="bc, ppo: the trained policy (RUN/ckpt.pt of esrp train; the config's checkpoint)",
    )
    ev.add_argument(
        "--trace-dir",
        type=Path,
        metavar="DIR",
        help="vlm: the per-episode traces' folder (default: --out without .jsonl, plus .traces)",
    )
    ev.add_argument(
        "--plan-budget-ms", type=_positive, default=60_000, help="plan: budget per PlanActions call"
    )
    ev.add_argument("--replans", type=int, default=2, help="plan: PlanActions calls after the first")
    ev.add_argument(
        "--sensors",
        type=_sensors,
        metavar="NAME,...",
        help="MODULE:CALLABLE: depth,segmentation,current_top_down",
    )
    ev.add_argument("--privileged", action="store_true", help="MODULE:CALLABLE: privileged episodes")
    ev.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar or lines")
    ray = ev.add_argument_group(
        "Ray",
        "distribute the evaluation over a Ray cluster (pip install 'esrp[ray]'): one actor per server, "
        "--episodes-in-flight episodes on each; the same results file as a local run",
    )
    ray.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run on Ray: no ADDRESS starts a local Ray for the run, `auto` joins this machine's "
        "cluster, or ray://HOST:PORT",
    )
    ray.add_argument(
        "--servers",
        type=_comma_list,
        metavar="HOST:PORT,...",
        help="--ray: pin one actor to each of these servers (default: $ESRP_SERVERS; without it, actors "
        "spawn their own)",
    )
    ray.add_argument(
        "--spawn-servers",
        type=_positive,
        metavar="N",
        help="--ray: N actors, each starting an esrp-server next to itself (default: one per CPU of the "
        "cluster; --server-arg flags apply to them)",
    )
    ray.add_argument(
        "--cpus-per-actor", type=float, default=1.0, metavar="N", help="--ray: CPUs each actor reserves"
    )
    ray.add_argument(
        "--max-restarts",
        type=int,
        default=3,
        metavar="N",
        help="--ray: restarts of an actor whose server died (its episodes are re-run from their start)",
    )
    _server_options(ev)

    rep = commands.add_parser(
        "report",
        help="tables and plots of results files: Markdown and one self-contained HTML page",
        description="Read esrp.results/v1 files and write report.md and report.html (images inlined) "
        "with the paper's Table I/II/III layouts for every run, the paper's rows beside them, plots, "
        "and replay stills of chosen episodes (those need a server).",
    )
    rep.add_argument("results", nargs="+", type=Path, help="results files (JSON Lines)")
    rep.add_argument("--out", type=Path, required=True, help="the report's folder")
    rep.add_argument("--replays", type=int, default=0, metavar="N", help="stills of N episodes per run")
    rep.add_argument(
        "--replay-scenes", type=_comma_list, default=[], metavar="ID,...", help="stills of these scenes"
    )
    rep.add_argument("--title", default="ESRP evaluation report")
    _server_options(rep)

    rp = commands.add_parser(
        "replay",
        help="re-run a recorded episode on the server; write it as a GIF, MP4 or PNG",
        description="Re-run the recorded actions of one episode on the server (privileged, with the "
        "current top-down view) and write its frames: ego view | goal | current top-down with the "
        "agent's path (red) and each carried object's path (blue). The format follows --out's "
        "extension: .gif, .mp4 (needs imageio-ffmpeg) or .png (the final frame). Fails when the "
        "replay does not reproduce the record's metrics.",
    )
    rp.add_argument("--results", type=Path, required=True, help="the results file")
    rp.add_argument("--scene", required=True, help="the scene id of the episode to replay")
    rp.add_argument("--out", type=Path, required=True, help="ep.gif, ep.mp4 or ep.png")
    rp.add_argument("--fps", type=_positive_float, default=10.0, help="frames per second (10)")
    rp.add_argument("--scale", type=_positive, default=2, help="pixels per image pixel")
    _server_options(rp)
    demos = commands.add_parser(
        "demos",
        help="expert demonstrations for imitation learning (zarr; docs/demonstrations.md)",
        description="Expert demonstrations for imitation learning.",
    )
    demo_commands = demos.add_subparsers(dest="demos_command", required=True, metavar="COMMAND")
    export = demo_commands.add_parser(
        "export",
        help="replay the scenes' expert trajectories on the server into a zarr store",
        description="Replay each chosen scene's expert trajectory on the server and append its "
        "observations (ego view, grasp flag), actions and goal image to a zarr store "
        "(docs/demonstrations.md), resuming a store an interrupted run left.",
    )
    export.add_argument("--split", choices=("train", "test"), default="train")
    export.add_argument("--difficulty", choices=("easy", "medium", "hard"))
    export.add_argument(
        "--scenes", type=_comma_list, default=[], metavar="ID,...", help="only these scenes, in order"
    )
    export.add_argument("--limit", type=_positive, metavar="N", help="at most N scenes")
    export.add_argument("--resolution", type=int, default=0, help="the views' side in pixels (0: 128)")
    export.add_argument("--out", type=Path, required=True, help="the zarr store (a folder)")
    export.add_argument(
        "--dagger",
        metavar="AGENT",
        help="DAgger: let AGENT (random, bc, ppo, vlm or MODULE:CALLABLE) drive and record the "
        "server planner's action at each state it visits, instead of the expert's demonstrations",
    )
    export.add_argument("--checkpoint", type=Path, metavar="PATH", help="--dagger bc or ppo: the policy")
    export.add_argument(
        "--agent-config", type=_json_object, default={}, metavar="JSON", help="--dagger: the agent's config"
    )
    export.add_argument(
        "--beta",
        type=float,
        default=0.0,
        help="--dagger: probability of stepping the planner's label instead of the agent's action (0)",
    )
    export.add_argument(
        "--seed", type=int, default=0, help="--dagger: base seed (scene ID: seed XOR fnv1a64(ID))"
    )
    export.add_argument(
        "--plan-budget-ms", type=_positive, default=10_000, help="--dagger: planning budget per label"
    )
    export.add_argument("--no-progress", dest="progress", action="store_false")
    _server_options(export)
    train = commands.add_parser(
        "train",
        help="train a learning baseline (ESRP-BC, ESRP-PPO) from a config file",
        description="Train a learning baseline. Configs: clients/python/configs/ "
        "(pip install 'esrp[train]').",
    )
    train_commands = train.add_subparsers(dest="train_command", required=True, metavar="AGENT")
    bc = train_commands.add_parser(
        "bc",
        help="ESRP-BC (Diffusion Policy) on an esrp demos export store",
        description="Train ESRP-BC on the demonstrations its config names; writes RUN/config.json, "
        "RUN/log.csv and RUN/ckpt.pt (esrp eval --agent bc --checkpoint RUN/ckpt.pt plays it).",
    )
    bc.add_argument("--config", type=Path, required=True, help="a TOML file with a [bc] table, or JSON")
    bc.add_argument("--out", type=Path, default=Path("runs/bc"), help="the run folder (default runs/bc)")
    bc.add_argument("--resume", action="store_true", help="go on from RUN/ckpt.pt")
    bc.add_argument("--no-progress", dest="progress", action="store_false")
    ppo = train_commands.add_parser(
        "ppo",
        help="ESRP-PPO (CNN + LSTM) on the native vector env, with the dense reward",
        description="Train ESRP-PPO on the scenes its config names, on a server (one is started "
        "without --server); writes RUN/config.json, RUN/log.csv, RUN/episodes.csv and RUN/ckpt.pt "
        "(esrp eval --agent ppo --checkpoint RUN/ckpt.pt plays it).",
    )
    ppo.add_argument("--config", type=Path, required=True, help="a TOML file with a [ppo] table, or JSON")
    ppo.add_argument("--out", type=Path, default=Path("runs/ppo"), help="the run folder (default runs/ppo)")
    ppo.add_argument("--resume", action="store_true", help="go on from RUN/ckpt.pt (with fresh episodes)")
    ppo.add_argument("--no-progress", dest="progress", action="store_false")
    _server_options(ppo)
    commands.add_parser(
        "bench",
        add_help=False,
        help="throughput of the Python client and env beside the Rust client and MiniWorld "
        "(python -m esrp.bench; `esrp bench --help` lists its options)",
    )
    return parser


@_one_line_errors
def _eval(args: argparse.Namespace) -> int:
    from .evaluation import EvalError, EvalSettings, ServerGone, format_failures, run_eval

    # `--agent my_agents:make` imports from the working directory, as `python -m` would.
    if "" not in sys.path and os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    agent_config = dict(args.agent_config)
    vlm_flags = {"base_url": args.base_url, "model": args.model, "trace_dir": args.trace_dir}
    given = {key: value for key, value in vlm_flags.items() if value is not None}
    if given and args.agent != "vlm":
        flags = ", ".join("--" + key.replace("_", "-") for key in given)
        print(f"esrp eval: {flags} only apply to --agent vlm", file=sys.stderr)
        return 2
    agent_config.update({key: str(value) for key, value in given.items()})
    if args.checkpoint is not None:
        if args.agent not in ("bc", "ppo"):
            print("esrp eval: --checkpoint only applies to --agent bc or ppo", file=sys.stderr)
            return 2
        agent_config["checkpoint"] = str(args.checkpoint)
    settings = EvalSettings(
        agent=args.agent,
        out=args.out,
        split=args.split,
        difficulty=args.difficulty,
        scenes=args.scenes,
        limit=args.limit,
        episodes_in_flight=args.episodes_in_flight,
        seed=args.seed,
        fresh=args.fresh,
        summary=args.summary,
        agent_config=agent_config,
        plan_budget_ms=args.plan_budget_ms,
        replans=args.replans,
        sensors=args.sensors,
        privileged=args.privileged,
        progress=args.progress,
    )
    ray_only = (("--servers", args.servers is not None), ("--spawn-servers", args.spawn_servers))
    ray_flags = [flag for flag, given in ray_only if given]
    if args.ray is None and ray_flags:
        print(f"esrp eval: {', '.join(ray_flags)} only apply with --ray", file=sys.stderr)
        return 2
    servers = args.servers if args.servers is not None else _comma_list(os.environ.get("ESRP_SERVERS", ""))
    if args.ray is not None and (args.server is not None or (servers and args.spawn_servers)):
        message = "with --ray, name servers with --servers, or spawn them (--spawn-servers)"
        print(f"esrp eval: {message}", file=sys.stderr)
        return 2
    try:
        if args.ray is not None:
            from .ray_eval import RaySettings, run_ray_eval

            cluster = RaySettings(
                address=None if args.ray == "local" else args.ray,
                servers=servers,
                spawn_servers=args.spawn_servers or 0,
                cpus_per_actor=args.cpus_per_actor,
                episodes_per_actor=args.episodes_in_flight,
                max_restarts=args.max_restarts,
                token=args.token,
                server_args=args.server_args,
            )
            outcome = run_ray_eval(settings, cluster)
        else:
            outcome = run_eval(settings, server=args.server, token=args.token, server_args=args.server_args)
    except ServerGone as error:
        print(f"esrp eval: {error}", file=sys.stderr)
        return 3
    except EvalError as error:
        print(f"esrp eval: {error}", file=sys.stderr)
        return 2
    if outcome.failed:
        print(f"esrp eval: {format_failures(outcome.failed, outcome.errors_log)}", file=sys.stderr)
        return 1
    return 0


def _on_server(args: argparse.Namespace, run: Callable[[str], int]) -> int:
    """`run(address)` on the server `--server` names, or on one started here (`--server-arg`)."""
    if args.server is not None:
        return run(args.server)
    from ._local import LocalServer

    with LocalServer(*args.server_args) as local:
        return run(local.address)


@_one_line_errors
def _demos(args: argparse.Namespace) -> int:
    try:
        from .demos import DemoExportError, DemoSettings, export_demos
    except ImportError as error:
        print(f"esrp demos: {error} (pip install 'esrp[train]')", file=sys.stderr)
        return 2
    settings = DemoSettings(
        out=args.out,
        split=args.split,
        difficulty=args.difficulty,
        scenes=args.scenes,
        limit=args.limit,
        resolution=args.resolution,
        progress=args.progress,
        dagger=args.dagger,
        agent_config=dict(args.agent_config),
        beta=args.beta,
        seed=args.seed,
        plan_budget_ms=args.plan_budget_ms,
    )
    dagger_flags = [
        flag
        for flag, given in (
            ("--checkpoint", args.checkpoint is not None),
            ("--agent-config", bool(args.agent_config)),
            ("--beta", args.beta != 0.0),
        )
        if given
    ]
    if args.dagger is None and dagger_flags:
        print(f"esrp demos export: {', '.join(dagger_flags)} only apply with --dagger", file=sys.stderr)
        return 2
    if args.checkpoint is not None:
        settings.agent_config["checkpoint"] = str(args.checkpoint)

    from ._client import Client

    def run(address: str) -> int:
        with Client(address, token=args.token, timeout=120) as client:
            outcome = export_demos(client, settings)
        print(f"{args.out}: {outcome.episodes} episodes, {outcome.steps} steps ({outcome.added} added now)")
        return 0

    try:
        return _on_server(args, run)
    except DemoExportError as error:
        print(f"esrp demos export: {error}", file=sys.stderr)
        return 2


@_one_line_errors
def _train(args: argparse.Namespace) -> int:
    name = f"esrp train {args.train_command}"
    try:
        if args.train_command == "ppo":
            return _train_ppo(args, name)
        from .train_bc import load_config, train
    except ImportError as error:
        print(f"{name}: {error} (pip install 'esrp[train]')", file=sys.stderr)
        return 2
    try:
        config = load_config(args.config)
        checkpoint = train(config, args.out, resume=args.resume, progress=args.progress)
    except (OSError, ValueError) as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2
    print(f"checkpoint: {checkpoint}")
    return 0


def _train_ppo(args: argparse.Namespace, name: str) -> int:
    from ._client import Client
    from ._errors import EsrpError
    from .train_ppo import load_config, train

    try:
        config = load_config(args.config)
    except ValueError as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2

    def run(address: str) -> int:
        with Client(address, token=args.token, timeout=120) as client:
            checkpoint = train(config, args.out, client, resume=args.resume, progress=args.progress)
        print(f"checkpoint: {checkpoint}")
        return 0

    try:
        return _on_server(args, run)
    except (OSError, ValueError, EsrpError) as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2


@_one_line_errors
def _report(args: argparse.Namespace) -> int:
    from .report import ReportError, write_report

    try:
        paths = write_report(
            args.results,
            args.out,
            title=args.title,
            replays=args.replays,
            replay_scenes=args.replay_scenes,
            server=args.server,
            token=args.token,
            server_args=args.server_args,
        )
    except ReportError as error:
        print(f"esrp report: {error}", file=sys.stderr)
        return 2
    for path in paths:
        print(path)
    return 0


@_one_line_errors
def _replay(args: argparse.Namespace) -> int:
    from .replay import ReplayError, replay_to_file

    try:
        replay_to_file(
            args.results,
            args.scene,
            args.out,
            fps=args.fps,
            scale=args.scale,
            server=args.server,
            token=args.token,
            server_args=args.server_args,
        )
    except ReplayError as error:
        print(f"esrp replay: {error}", file=sys.stderr)
        return 2
    print(args.out)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Runs `esrp ARGS` (`argv` without the program name; default `sys.argv[1:]`); returns the exit
    status: 0 done, 1 episodes failed (eval), 2 bad arguments or input, 3 the server died or stayed
    unreachable (eval: the run stopped there), 130 interrupted, 143 terminated (SIGTERM, when run
    as the `esrp` command).
    """
    arguments = list(sys.argv[1:] if argv is None else argv)
    command = f"esrp {arguments[0]}" if arguments and not arguments[0].startswith("-") else "esrp"
    # The command line's process (not a call from Python code): SIGTERM (kill, a job scheduler)
    # unwinds as Ctrl-C does, so a server started here is stopped and files are closed instead of
    # being left behind, and neither signal is ever lost (esrp._signals).
    handle_signals = argv is None and threading.current_thread() is threading.main_thread()
    return run_command(command, lambda: _run(arguments), handle_signals=handle_signals)


def _run(arguments: list[str]) -> int:
    if arguments[:1] == ["bench"]:
        # Its own parser and options (also `python -m esrp.bench`).
        from . import bench

        return bench.main(arguments[1:])
    args = _parser().parse_args(arguments)
    handlers = {"eval": _eval, "report": _report, "replay": _replay, "demos": _demos, "train": _train}
    try:
        return handlers[args.command](args)
    except EsrpError as error:
        print(f"esrp {args.command}: {type(error).__name__}: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
