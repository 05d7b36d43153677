"""The evaluation commands: `esrp eval`, `esrp verify`, `esrp report` and `esrp replay` (their parsers
and handlers).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from .._signals import Terminated
from ._args import (
    SPLITS,
    Parser,
    comma_list,
    json_object,
    non_negative,
    one_line_errors,
    plan_budget,
    positive,
    positive_float,
    scene_options,
    sensor_list,
    server_options,
)


def add_commands(commands: argparse._SubParsersAction[Parser]) -> None:
    """Adds `eval`, `report`, `replay` and `verify` to `commands` (in that order: `esrp --help`'s)."""
    _add_eval(commands)
    _add_report(commands)
    _add_replay(commands)
    _add_verify(commands)


def _add_eval(commands: argparse._SubParsersAction[Parser]) -> None:
    """Adds `esrp eval`: the agent, the scenes, the results file, the agents' settings, Ray, the
    server.
    """
    parser = commands.add_parser(
        "eval",
        help="run an agent over the scenes of a split; write one esrp.results/v1 record per episode",
        description="Run an agent over the scenes of a split and write one esrp.results/v1 record per "
        "episode (docs/evaluation.md), resuming what --out already holds; a Markdown summary is written "
        "beside it. The exit status is 1 when episodes failed with an error (they are not recorded).",
    )
    parser.add_argument(
        "--agent",
        required=True,
        help="random, expert, plan, vlm (ESRP-VLM over an OpenAI-compatible endpoint: --base-url, "
        "--model), bc (ESRP-BC: --checkpoint), ppo (ESRP-PPO: --checkpoint), map (ESRP-MAP: maps the "
        "room from its own views and plans, unprivileged), or MODULE:CALLABLE "
        "(a factory called with the agent config, once per episode, "
        "returning an esrp.agents.Agent or AsyncAgent)",
    )
    scene_options(
        parser,
        SPLITS,
        default="test",
        split_help="challenge and minival: the hidden splits of a server started with --challenge-seed",
        limit_help="at most N scenes (the first after the filters)",
    )
    parser.add_argument("--episodes-in-flight", type=positive, default=8, metavar="N")
    parser.add_argument("--seed", type=int, default=0, help="base seed; scene ID uses seed XOR fnv1a64(ID)")
    parser.add_argument("--out", type=Path, required=True, help="the results file (JSON Lines)")
    parser.add_argument("--fresh", action="store_true", help="start --out over instead of resuming it")
    parser.add_argument("--summary", type=Path, help="the Markdown summary (default: --out with .md)")
    _agent_settings(parser)
    parser.add_argument(
        "--no-progress", dest="progress", action="store_false", help="no progress bar or lines"
    )
    _ray_options(parser)
    server_options(parser)
    parser.set_defaults(handler=_eval)


def _agent_settings(parser: argparse.ArgumentParser) -> None:
    """Adds `esrp eval`'s settings of the agents: `--agent-config`, those of vlm, bc and ppo, and
    plan, and the sensors and privilege of a MODULE:CALLABLE agent's episodes.
    """
    parser.add_argument(
        "--agent-config",
        type=json_object,
        default={},
        metavar="JSON",
        help="the agent's config (vlm, bc, ppo, map, MODULE:CALLABLE; docs/evaluation.md)",
    )
    parser.add_argument(
        "--base-url",
        metavar="URL",
        help="vlm: the OpenAI-compatible endpoint, e.g. http://localhost:8000/v1 (the config's base_url); "
        "the API key is $ESRP_VLM_API_KEY or $OPENAI_API_KEY",
    )
    parser.add_argument("--model", metavar="NAME", help="vlm: the model it serves (the config's model)")
    parser.add_argument(
        "--checkpoint",
        type=Path,
        metavar="PATH",
        help="bc, ppo: the trained policy (RUN/ckpt.pt of esrp train; the config's checkpoint)",
    )
    parser.add_argument(
        "--trace-dir",
        type=Path,
        metavar="DIR",
        help="vlm: the per-episode traces' folder (default: --out without .jsonl, plus .traces)",
    )
    parser.add_argument(
        "--plan-budget-ms",
        type=plan_budget,
        default=60_000,
        help="plan: budget per PlanActions call, 1 to 4294967295 ms (the server caps it)",
    )
    parser.add_argument(
        "--replans", type=non_negative, default=2, help="plan: PlanActions calls after the first (0 or more)"
    )
    parser.add_argument(
        "--sensors",
        type=sensor_list,
        metavar="NAME,...",
        help="the optional sensors the agent's episodes serve: depth,segmentation,current_top_down "
        "(not for plan and expert, which the server plays)",
    )
    parser.add_argument(
        "--privileged",
        action="store_true",
        help="privileged episodes for the agent (plan and expert always have them)",
    )


def _ray_options(parser: argparse.ArgumentParser) -> None:
    """Adds `esrp eval`'s Ray group: `--ray`, `--servers`, `--spawn-servers`, `--cpus-per-actor`,
    `--max-restarts`.
    """
    ray = parser.add_argument_group(
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
        type=comma_list,
        metavar="HOST:PORT,...",
        help="--ray: pin one actor to each of these servers (default: $ESRP_SERVERS; without it, actors "
        "spawn their own)",
    )
    ray.add_argument(
        "--spawn-servers",
        type=positive,
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


def _add_report(commands: argparse._SubParsersAction[Parser]) -> None:
    """Adds `esrp report`: results files into a report, or `--leaderboard` from a server's records."""
    parser = commands.add_parser(
        "report",
        help="tables and plots of results files: Markdown and one self-contained HTML page; "
        "--leaderboard: the challenge's ranking from a server's records",
        description="Read esrp.results/v1 files and write report.md and report.html (images inlined) "
        "with the paper's Table I/II/III layouts for every run, the paper's rows beside them, plots, "
        "and replay stills of chosen episodes (those need a server). With --leaderboard DIR instead: "
        "rank the participants of the challenge from a server's records (DIR/*.jsonl: the counted "
        "challenge records, one per participant and scene), each scored over every scene of "
        "DIR/challenge-scenes.json (a scene not played is a failure), reading only records whose "
        "signature checks under the records key (--key, else DIR/records.key), and write one "
        "self-contained HTML page.",
    )
    parser.add_argument("results", nargs="*", type=Path, help="results files (JSON Lines)")
    parser.add_argument(
        "--out",
        type=Path,
        help="the report's folder; with --leaderboard, the page (default: leaderboard.html)",
    )
    parser.add_argument(
        "--leaderboard",
        type=Path,
        metavar="DIR",
        help="rank the challenge's participants from the server's records in DIR (its --records folder)",
    )
    parser.add_argument(
        "--key",
        type=Path,
        metavar="FILE",
        help="--leaderboard: the records key (the server's --records-key; default: DIR/records.key); "
        "records whose signature does not check are rejected, not ranked",
    )
    parser.add_argument(
        "--unsigned",
        action="store_true",
        help="--leaderboard: rank the records unchecked when there is no records key (neither --key "
        "nor DIR/records.key); without it such a folder is refused",
    )
    parser.add_argument("--replays", type=int, default=0, metavar="N", help="stills of N episodes per run")
    parser.add_argument(
        "--replay-scenes", type=comma_list, default=[], metavar="ID,...", help="stills of these scenes"
    )
    parser.add_argument(
        "--title", help="the page's title (default: ESRP evaluation report, ESRP challenge leaderboard)"
    )
    server_options(parser)
    parser.set_defaults(handler=_report)


def _add_replay(commands: argparse._SubParsersAction[Parser]) -> None:
    """Adds `esrp replay`: one recorded episode re-run and written as frames."""
    parser = commands.add_parser(
        "replay",
        help="re-run a recorded episode on the server; write it as a GIF, MP4 or PNG",
        description="Re-run the recorded actions of one episode on the server (privileged, with the "
        "current top-down view) and write its frames: ego view | goal | current top-down with the "
        "agent's path (red) and each carried object's path (blue). The format follows --out's "
        "extension: .gif, .mp4 (needs imageio-ffmpeg) or .png (the final frame). Fails when the "
        "replay does not reproduce the record's metrics.",
    )
    parser.add_argument("--results", type=Path, required=True, help="the results file")
    parser.add_argument("--scene", required=True, help="the scene id of the episode to replay")
    parser.add_argument("--out", type=Path, required=True, help="ep.gif, ep.mp4 or ep.png")
    parser.add_argument("--fps", type=positive_float, default=10.0, help="frames per second (10)")
    parser.add_argument("--scale", type=positive, default=2, help="pixels per image pixel")
    server_options(parser)
    parser.set_defaults(handler=_replay)


def _add_verify(commands: argparse._SubParsersAction[Parser]) -> None:
    """Adds `esrp verify`: results files' records replayed and checked."""
    parser = commands.add_parser(
        "verify",
        help="replay results files' records on a server and check that each replay reproduces its record",
        description="Replay every record of esrp.results/v1 files (esrp eval's, esrp-eval's, or a "
        "server's own records) on a server: create an episode of its scene with its horizon, step its "
        "actions, and check success, osr, rdr, stage, placed, steps, total_reward and end exactly. "
        "Prints one line per record that does not match (FILE:LINE, scene, what differs) and a "
        "summary. With --key, a server's records are first checked against their signatures: a "
        "record unsigned, altered, duplicated, moved to another token's file, or whose split or "
        "horizon is not its scene's is refused (listed with the reason) and not replayed. "
        "Exit status: 0 all match, 1 some do not, 2 bad input, 3 the server died.",
    )
    parser.add_argument("results", nargs="+", type=Path, help="results files (JSON Lines)")
    parser.add_argument(
        "--key",
        type=Path,
        metavar="FILE",
        help="the records key the server signs its records with (its --records-key, or "
        "DIR/records.key): check every record's signature; without it signatures are not checked",
    )
    parser.add_argument("--episodes-in-flight", type=positive, default=8, metavar="N")
    parser.add_argument(
        "--no-progress", dest="progress", action="store_false", help="no progress bar or lines"
    )
    server_options(parser)
    parser.set_defaults(handler=_verify)


def _say_kept(out: Path) -> None:
    """Says, as an interrupted `esrp eval` stops, what its results file keeps and how to go on."""
    from ..eval.results import read_records

    try:
        records = len(read_records(out).records) if out.exists() else 0
    except Exception:  # noqa: BLE001 - only a courtesy on the way out: say nothing
        return
    episodes = "1 episode" if records == 1 else f"{records} episodes"
    print(f"esrp eval: {out} keeps {episodes}: run the same command again to resume", file=sys.stderr)


@one_line_errors
def _eval(args: argparse.Namespace) -> int:
    from ..eval.evaluation import (
        AgentStopped,
        EvalError,
        EvalSettings,
        ServerGone,
        format_failures,
        run_eval,
        summary_path_of,
    )

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
    if args.sensors and args.agent in ("plan", "expert"):
        refused = f"--sensors does not apply to --agent {args.agent}: the server plays it"
        print(f"esrp eval: {refused}", file=sys.stderr)
        return 2
    if args.checkpoint is not None:
        if args.agent not in ("bc", "ppo"):
            print("esrp eval: --checkpoint only applies to --agent bc or ppo", file=sys.stderr)
            return 2
        agent_config["checkpoint"] = str(args.checkpoint)
    try:
        summary_path_of(args.out, args.summary)  # before a server is started
    except EvalError as error:
        print(f"esrp eval: {error}", file=sys.stderr)
        return 2
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
    servers = args.servers if args.servers is not None else comma_list(os.environ.get("ESRP_SERVERS", ""))
    if args.ray is not None and (args.server is not None or (servers and args.spawn_servers)):
        message = "with --ray, name servers with --servers, or spawn them (--spawn-servers)"
        print(f"esrp eval: {message}", file=sys.stderr)
        return 2
    try:
        if args.ray is not None:
            from ..eval.ray_eval import RaySettings, run_ray_eval

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
    except AgentStopped as error:
        print(f"esrp eval: {error}", file=sys.stderr)
        return 1
    except EvalError as error:
        print(f"esrp eval: {error}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, Terminated):
        _say_kept(settings.out)
        raise
    if outcome.failed:
        closing = format_failures(outcome.failed, outcome.errors_log, outcome.refused)
        print(f"esrp eval: {closing}", file=sys.stderr)
        return 1
    return 0


@one_line_errors
def _verify(args: argparse.Namespace) -> int:
    from ..eval.evaluation import ServerGone
    from ..eval.verify import VerifyError, run_verify

    try:
        outcome = run_verify(
            args.results,
            server=args.server,
            token=args.token,
            server_args=args.server_args,
            episodes_in_flight=args.episodes_in_flight,
            progress=args.progress,
            key=args.key,
        )
    except ServerGone as error:
        print(f"esrp verify: {error}", file=sys.stderr)
        return 3
    except VerifyError as error:
        print(f"esrp verify: {error}", file=sys.stderr)
        return 2
    if args.key is None:
        print(
            "esrp verify: signatures not checked (no --key): records were replayed, not authenticated",
            file=sys.stderr,
        )
    for mismatch in outcome.mismatches:
        print(mismatch.text())
    print(outcome.summary())
    return 1 if outcome.mismatches else 0


@one_line_errors
def _report(args: argparse.Namespace) -> int:
    if args.leaderboard is not None:
        return _leaderboard(args)
    leaderboard_only = [flag for flag, given in (("--key", args.key), ("--unsigned", args.unsigned)) if given]
    if leaderboard_only:
        print(f"esrp report: {', '.join(leaderboard_only)} only apply with --leaderboard", file=sys.stderr)
        return 2
    from ..eval.report import ReportError, write_report

    if not args.results or args.out is None:
        missing = " and ".join(
            name for name, given in (("results", args.results), ("--out", args.out)) if not given
        )
        print(
            f"esrp report: error: {missing} needed (or --leaderboard DIR) (see esrp report --help)",
            file=sys.stderr,
        )
        return 2
    try:
        paths = write_report(
            args.results,
            args.out,
            title=args.title or "ESRP evaluation report",
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


def _leaderboard(args: argparse.Namespace) -> int:
    from ..eval.leaderboard import LeaderboardError, ranking_text, write_leaderboard

    given = [
        flag
        for flag, value in (
            ("results files", args.results),
            ("--replays", args.replays),
            ("--replay-scenes", args.replay_scenes),
            ("--server", args.server),
            ("--server-arg", args.server_args),
        )
        if value
    ]
    if given:
        print(f"esrp report: {', '.join(given)} do not apply with --leaderboard", file=sys.stderr)
        return 2
    try:
        board = write_leaderboard(
            args.leaderboard,
            args.out or Path("leaderboard.html"),
            title=args.title or "ESRP challenge leaderboard",
            key=args.key,
            unsigned=args.unsigned,
        )
    except LeaderboardError as error:
        print(f"esrp report: {error}", file=sys.stderr)
        return 2
    if board.key is None:
        print("esrp report: signatures not checked (--unsigned, no records key)", file=sys.stderr)
    for rejected in board.rejected:
        print(
            f"esrp report: rejected {rejected.source.where}: {'; '.join(rejected.reasons)}", file=sys.stderr
        )
    print(ranking_text(board.participants, board.scenes.count()), end="")
    print(board.page)
    return 0


@one_line_errors
def _replay(args: argparse.Namespace) -> int:
    from ..eval.replay import ReplayError, replay_to_file

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
