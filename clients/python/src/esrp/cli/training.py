"""The training commands: `esrp demos export` and `esrp train bc|ppo` (their parsers and handlers)."""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from ._args import (
    Parser,
    json_object,
    on_server,
    one_line_errors,
    plan_budget,
    positive,
    scene_options,
    server_options,
)

if TYPE_CHECKING:
    from .._client import Client
    from ..train.demos import DemoSettings, RecordSource


def add_commands(commands: argparse._SubParsersAction[Parser]) -> None:
    """Adds `demos` and `train` to `commands`."""
    _add_demos(commands)
    _add_train(commands)


def _add_demos(commands: argparse._SubParsersAction[Parser]) -> None:
    """`esrp demos` and its one command, `export`."""
    demos = commands.add_parser(
        "demos",
        help="demonstrations for imitation learning (zarr; docs/demonstrations.md)",
        description="Demonstrations for imitation learning: the expert's, or recorded episodes'.",
    )
    demo_commands = demos.add_subparsers(dest="demos_command", required=True, metavar="COMMAND")
    _add_demos_export(demo_commands)
    demos.set_defaults(handler=_demos)


def _add_demos_export(demo_commands: argparse._SubParsersAction[Parser]) -> None:
    """`esrp demos export`: the expert's (or recorded, or DAgger) trajectories into a zarr store."""
    export = demo_commands.add_parser(
        "export",
        help="replay the scenes' expert trajectories (or recorded episodes) on the server into a zarr store",
        description="Replay each chosen scene's expert trajectory on the server and append its "
        "observations (ego view, grasp flag), actions and goal image to a zarr store "
        "(docs/demonstrations.md), resuming a store an interrupted run left. With --records, "
        "replay the episodes of esrp.results/v1 files instead (e.g. people's play in the web "
        "viewer: --agent human).",
    )
    scene_options(
        export,
        ("train", "test"),
        default=None,
        split_help="the scenes' split (default train)",
        limit_help="at most N scenes (or records)",
    )
    export.add_argument(
        "--records",
        type=Path,
        nargs="+",
        default=[],
        metavar="FILE.jsonl",
        help="replay these esrp.results/v1 files' episodes (each record's actions from its scene's "
        "start) instead of the scenes' expert trajectories",
    )
    export.add_argument(
        "--agent", metavar="NAME", help="--records: only the records of agent NAME (human: the web viewer's)"
    )
    export.add_argument(
        "--successful-only", action="store_true", help="--records: only the records of successful episodes"
    )
    export.add_argument(
        "--resolution",
        type=int,
        default=0,
        help="the views' side in pixels, 16 to the server's largest (512 by default); 0: 128",
    )
    export.add_argument(
        "--out",
        type=Path,
        required=True,
        help="the zarr store (a folder); with --format minari, the Minari datasets root the dataset goes "
        "in; with --format lerobot, the LeRobot home (the dataset is the folder OUT/ID)",
    )
    export.add_argument(
        "--format",
        choices=("zarr", "minari", "lerobot"),
        default="zarr",
        help="zarr (default): ESRP-BC's store, resumable; minari: a Minari dataset "
        "(pip install 'esrp[minari]'), loaded with MINARI_DATASETS_PATH=OUT minari.load_dataset(ID); "
        "lerobot: a LeRobot dataset (pip install 'esrp[lerobot]'), loaded with "
        "LeRobotDataset(ID, root=OUT/ID)",
    )
    export.add_argument(
        "--dataset-id",
        metavar="ID",
        help="--format minari or lerobot: the dataset's id (minari: default "
        "esrp/DATASET-DIFFICULTY/expert-v0 for the train split, esrp/DATASET-SPLIT-DIFFICULTY/expert-v0 "
        "for another, esrp/DATASET/AGENT-v0 with --records; lerobot: esrp/DATASET-DIFFICULTY-expert, "
        "esrp/DATASET-SPLIT-DIFFICULTY-expert, esrp/DATASET-AGENT)",
    )
    export.add_argument(
        "--dagger",
        metavar="AGENT",
        help="DAgger: let AGENT (random, bc, ppo, vlm or MODULE:CALLABLE) drive and record the "
        "server planner's action at each state it visits, instead of the expert's demonstrations",
    )
    export.add_argument("--checkpoint", type=Path, metavar="PATH", help="--dagger bc or ppo: the policy")
    export.add_argument(
        "--agent-config", type=json_object, default={}, metavar="JSON", help="--dagger: the agent's config"
    )
    export.add_argument(
        "--beta",
        type=float,
        default=0.0,
        help="--dagger: probability of stepping the planner's label instead of the agent's action (0)",
    )
    export.add_argument(
        "--seed", type=int, help="--dagger: base seed (scene ID: seed XOR fnv1a64(ID); default 0)"
    )
    export.add_argument(
        "--plan-budget-ms",
        type=plan_budget,
        help="--dagger: planning budget per label, 1 to 4294967295 ms (default 10000)",
    )
    export.add_argument(
        "--max-steps",
        type=positive,
        metavar="N",
        help="--dagger: record at most N states per episode, then close it (default: until it ends)",
    )
    export.add_argument(
        "--label-horizon",
        type=positive,
        metavar="H",
        help="--dagger: record the plan's first H actions at each state, the chunk a policy learns "
        "there (default 8, ESRP-BC's horizon)",
    )
    export.add_argument(
        "--episodes-in-flight",
        type=positive,
        metavar="N",
        help="play N scenes' episodes at a time (default 1; the store is the same, written in the "
        "scenes' order; --dagger's agent must then be safe to use from several threads, as the "
        "built-in ones are)",
    )
    export.add_argument("--no-progress", dest="progress", action="store_false")
    server_options(export)


def _add_train(commands: argparse._SubParsersAction[Parser]) -> None:
    """`esrp train` and its commands, `bc`, `ppo` and `ppo-bc`."""
    train = commands.add_parser(
        "train",
        help="train a learning baseline (ESRP-BC, ESRP-PPO) from a config file",
        description="Train a learning baseline. Configs: clients/python/configs/ "
        "(pip install 'esrp[train]').",
    )
    train_commands = train.add_subparsers(dest="train_command", required=True, metavar="AGENT")
    _add_train_bc(train_commands)
    _add_train_ppo(train_commands)
    _add_train_ppo_bc(train_commands)
    train.set_defaults(handler=_train)


def _add_train_bc(train_commands: argparse._SubParsersAction[Parser]) -> None:
    """`esrp train bc`: ESRP-BC, and with --dagger the DAgger loop."""
    bc = train_commands.add_parser(
        "bc",
        help="ESRP-BC (Diffusion Policy) on esrp demos export stores; --dagger: the DAgger loop",
        description="Train ESRP-BC on the demonstrations its config names; writes RUN/config.json, "
        "RUN/log.csv and RUN/ckpt.pt (esrp eval --agent bc --checkpoint RUN/ckpt.pt plays it), and "
        "with eval_every RUN/eval.csv (held-out SR/OSR/RDR, on a server: one is started without "
        "--server). With --dagger, run DAgger as the config's [dagger] table says: iteration 0 is "
        "this training (RUN/iter-00), each further one exports the policy's rollouts labelled by the "
        "server's planner (RUN/dagger-NN.zarr), fine-tunes on every store so far (RUN/iter-NN) and "
        "evaluates it; RUN/dagger.csv logs the iterations (docs/demonstrations.md).",
    )
    bc.add_argument("--config", type=Path, required=True, help="a TOML file with a [bc] table, or JSON")
    bc.add_argument("--out", type=Path, default=Path("runs/bc"), help="the run folder (default runs/bc)")
    bc.add_argument(
        "--resume", action="store_true", help="go on from RUN/ckpt.pt (with --dagger: from RUN/state.json)"
    )
    bc.add_argument(
        "--dagger", action="store_true", help="run the DAgger loop of the config's [dagger] table"
    )
    bc.add_argument(
        "--init",
        type=Path,
        metavar="CKPT",
        help="fine-tune: start from this ESRP-BC checkpoint's weights (and optimizer, where it holds "
        "one) instead of fresh ones; the config may differ from its own in demos, seed, lr, epochs, "
        "checkpoint_every, threads, device, in_memory and the evaluation alone (not with --dagger: "
        "its [dagger] initial says where it starts; "
        "a --resume of a run that has a checkpoint goes on from that)",
    )
    bc.add_argument(
        "--init-average",
        action="store_true",
        help="with --init and ema: go on with the checkpoint's average of the weights instead of "
        "starting one from its weights",
    )
    bc.add_argument("--no-progress", dest="progress", action="store_false")
    server_options(bc)


def _add_train_ppo(train_commands: argparse._SubParsersAction[Parser]) -> None:
    """`esrp train ppo`: ESRP-PPO on the native vector env."""
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
    ppo.add_argument(
        "--stop-at",
        type=positive,
        metavar="STEPS",
        help="stop, with a checkpoint, after the first update that reaches STEPS environment steps, "
        "the schedule unchanged: --resume goes on (the same settings but total_steps, "
        "checkpoint_every, threads and device; a curriculum changes the server's scenes)",
    )
    ppo.add_argument("--no-progress", dest="progress", action="store_false")
    server_options(ppo)


def _add_train_ppo_bc(train_commands: argparse._SubParsersAction[Parser]) -> None:
    """`esrp train ppo-bc`: ESRP-PPO's network by imitation, the start of a PPO fine-tuning."""
    ppo_bc = train_commands.add_parser(
        "ppo-bc",
        help="ESRP-PPO's network (CNN + LSTM) by imitation of demonstrations: a start for esrp train ppo",
        description="Train ESRP-PPO's network by imitation on the demonstration stores of the "
        "config's [ppo_bc] table, the network as its [ppo] table says; writes RUN/config.json, "
        "RUN/log.csv and RUN/ckpt.pt (esrp eval --agent ppo --checkpoint RUN/ckpt.pt plays it; a "
        "[ppo] table's init = 'RUN/ckpt.pt' starts a PPO run from it). Needs no server.",
    )
    ppo_bc.add_argument(
        "--config", type=Path, required=True, help="a TOML file with [ppo] and [ppo_bc] tables"
    )
    ppo_bc.add_argument(
        "--out", type=Path, default=Path("runs/ppo-bc"), help="the run folder (default runs/ppo-bc)"
    )
    ppo_bc.add_argument("--resume", action="store_true", help="go on from RUN/ckpt.pt (more epochs)")
    ppo_bc.add_argument("--no-progress", dest="progress", action="store_false")


@one_line_errors
def _demos(args: argparse.Namespace) -> int:
    try:
        from ..train.demos import DemoExportError, DemoSettings, export_demos, read_sources
    except ImportError as error:
        print(f"esrp demos: {error} (pip install 'esrp[train]')", file=sys.stderr)
        return 2
    settings = DemoSettings(
        out=args.out,
        split=args.split or "train",
        difficulty=args.difficulty,
        scenes=args.scenes,
        limit=args.limit,
        resolution=args.resolution,
        progress=args.progress,
        dagger=args.dagger,
        agent_config=dict(args.agent_config),
        beta=args.beta,
        seed=args.seed or 0,
        plan_budget_ms=args.plan_budget_ms or 10_000,
        max_steps=args.max_steps or 0,
        label_horizon=args.label_horizon or 8,
        records=args.records,
        agent=args.agent,
        successful_only=args.successful_only,
        episodes_in_flight=args.episodes_in_flight or 1,
    )
    conflict = _export_flag_conflict(args)
    if conflict is not None:
        print(f"esrp demos export: {conflict}", file=sys.stderr)
        return 2
    if args.checkpoint is not None:
        settings.agent_config["checkpoint"] = str(args.checkpoint)
    try:
        # The records are read (and chosen) before a server is started: bad input fails at once.
        sources = read_sources(settings) if args.records else None
    except DemoExportError as error:
        print(f"esrp demos export: {error}", file=sys.stderr)
        return 2

    if args.format == "minari":
        return _demos_minari(args, settings, sources)
    if args.format == "lerobot":
        return _demos_lerobot(args, settings, sources)
    try:
        import zarr  # noqa: F401 - the store's library, imported where the store is made
    except ImportError as error:
        print(f"esrp demos export: {error} (pip install 'esrp[train]')", file=sys.stderr)
        return 2

    def export(client: Client) -> list[str]:
        outcome = export_demos(client, settings, sources)
        lines = [
            f"{args.out}: {outcome.episodes} episodes, {outcome.steps} steps ({outcome.added} added now)"
        ]
        if outcome.skipped:
            lines.append(
                f"{len(outcome.skipped)} scenes skipped (the planner found no plan from their start)"
            )
        if outcome.agreement is not None:
            lines.append(
                f"the policy's action was the planner's label at {outcome.agreed} of {outcome.compared} "
                f"states ({100 * outcome.agreement:.1f} %)"
            )
        return lines

    return _export_on_server(args, export)


def _demos_minari(
    args: argparse.Namespace, settings: DemoSettings, sources: list[RecordSource] | None
) -> int:
    """`esrp demos export --format minari`."""
    try:
        from ..integrations.minari import export_minari
    except ImportError as error:
        print(f"esrp demos export: {error} (pip install 'esrp[minari]')", file=sys.stderr)
        return 2

    def export(client: Client) -> list[str]:
        dataset_id, outcome = export_minari(client, settings, args.dataset_id, sources)
        # The root as a path that loads from any working directory (quoted for a shell).
        root = args.out.absolute()
        return [
            f"{root}: Minari dataset {dataset_id}, {outcome.episodes} episodes, {outcome.steps} steps "
            f"(MINARI_DATASETS_PATH={shlex.quote(str(root))} minari.load_dataset({dataset_id!r}))"
        ]

    return _export_on_server(args, export)


def _demos_lerobot(
    args: argparse.Namespace, settings: DemoSettings, sources: list[RecordSource] | None
) -> int:
    """`esrp demos export --format lerobot`."""
    try:
        from ..integrations.lerobot import export_lerobot
    except ImportError as error:
        print(f"esrp demos export: {error} (pip install 'esrp[lerobot]')", file=sys.stderr)
        return 2

    def export(client: Client) -> list[str]:
        repo_id, outcome = export_lerobot(client, settings, args.dataset_id, sources)
        folder = args.out.absolute() / repo_id  # a path that loads from any working directory
        return [
            f"{folder}: LeRobot dataset {repo_id}, {outcome.episodes} episodes, "
            f"{outcome.steps} frames (LeRobotDataset({repo_id!r}, root={str(folder)!r}))"
        ]

    return _export_on_server(args, export)


def _export_on_server(args: argparse.Namespace, export: Callable[[Client], list[str]]) -> int:
    """Runs `export` with a client of the server `--server` names (or one started here) and prints
    the lines it returns; a `DemoExportError` is printed as one line, exit status 2.
    """
    from .._client import Client
    from ..train.demos import DemoExportError

    def run(address: str) -> int:
        with Client(address, token=args.token, timeout=120) as client:
            lines = export(client)
        print("\n".join(lines))
        return 0

    try:
        return on_server(args, run)
    except DemoExportError as error:
        print(f"esrp demos export: {error}", file=sys.stderr)
        return 2


def _export_flag_conflict(args: argparse.Namespace) -> str | None:
    """What is wrong with `esrp demos export`'s flags together, or None.

    Scene, DAgger and seed flags do not go with --records, the records' filters need --records,
    and DAgger's flags need --dagger.
    """
    dagger_flags = [
        flag
        for flag, given in (
            ("--checkpoint", args.checkpoint is not None),
            ("--agent-config", bool(args.agent_config)),
            ("--beta", args.beta != 0.0),
            ("--max-steps", args.max_steps is not None),
            ("--label-horizon", args.label_horizon is not None),
        )
        if given
    ]
    # (--seed and --plan-budget-ms without --dagger have always been let be; not with --records.)
    seed_flags = [
        flag
        for flag, given in (
            ("--seed", args.seed is not None),
            ("--plan-budget-ms", args.plan_budget_ms is not None),
        )
        if given
    ]
    records_flags = [
        flag
        for flag, given in (("--agent", args.agent is not None), ("--successful-only", args.successful_only))
        if given
    ]
    if args.records:
        scene_flags = [
            flag
            for flag, given in (
                ("--split", args.split is not None),
                ("--difficulty", args.difficulty is not None),
                ("--scenes", bool(args.scenes)),
                ("--dagger", args.dagger is not None),
            )
            if given
        ]
        if scene_flags + dagger_flags + seed_flags:
            given = ", ".join(scene_flags + dagger_flags + seed_flags)
            return f"--records does not go with {given} (the records say the scenes and the actions)"
    elif records_flags:
        return f"{', '.join(records_flags)} only apply with --records"
    if args.dagger is None and dagger_flags:
        return f"{', '.join(dagger_flags)} only apply with --dagger"
    if args.format != "zarr" and args.dagger is not None:
        return f"--format {args.format} writes demonstrations and records, not DAgger's labels (no --dagger)"
    if args.format == "zarr" and args.dataset_id is not None:
        return "--dataset-id only applies with --format minari or lerobot"
    if args.episodes_in_flight is not None and (args.records or args.format != "zarr"):
        return (
            f"--episodes-in-flight applies to scene exports to zarr (no --records, no --format {args.format})"
            if args.format != "zarr"
            else "--episodes-in-flight applies to scene exports to zarr (no --records)"
        )
    return None


@one_line_errors
def _train(args: argparse.Namespace) -> int:
    name = f"esrp train {args.train_command}"
    try:
        if args.train_command == "ppo":
            return _train_ppo(args, name)
        if args.train_command == "ppo-bc":
            return _train_ppo_bc(args, name)
        from ..train._config import read_document
        from ..train.bc import load_config, train
        from ..train.dagger import load_dagger_config, run_dagger
        from ..train.demos import DemoExportError
        from ..train.heldout import EvalError, ServerGone, TrainServer
    except ImportError as error:
        print(f"{name}: {error} (pip install 'esrp[train]')", file=sys.stderr)
        return 2
    from .._errors import EsrpError

    if args.init is not None and args.dagger:
        print(f"{name}: --init does not go with --dagger (the [dagger] table's initial)", file=sys.stderr)
        return 2
    if args.init_average and args.init is None:
        print(f"{name}: --init-average only applies with --init", file=sys.stderr)
        return 2
    try:
        config = load_config(args.config)
        dagger = load_dagger_config(args.config) if args.dagger else None
        if dagger is None and "dagger" in read_document(args.config) and args.progress:
            print(
                f"{name}: the config's [dagger] table applies with --dagger only: plain ESRP-BC",
                file=sys.stderr,
            )
        with TrainServer(args.server, args.token, args.server_args) as server:
            if args.server is not None and (dagger is not None or config.eval_every > 0):
                # A --server the run will use is reached first: nothing answering there is said
                # at once, before the demonstrations are read and the run folder is made.
                server.reach()
            if dagger is not None:
                checkpoint = run_dagger(
                    config, dagger, args.out, resume=args.resume, progress=args.progress, server=server
                )
            else:
                checkpoint = train(
                    config,
                    args.out,
                    resume=args.resume,
                    progress=args.progress,
                    server=server,
                    init=args.init,
                    init_average=args.init_average,
                )
    except ServerGone as error:  # the server stopped answering during the run (as esrp eval's)
        print(f"{name}: {error}", file=sys.stderr)
        return 3
    except (OSError, ValueError, EvalError, DemoExportError, EsrpError) as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2
    except FloatingPointError as error:
        return _diverged(name, error)
    print(f"checkpoint: {checkpoint}")
    return 0


def _diverged(name: str, error: FloatingPointError) -> int:
    """Says that a run's loss left the numbers (a NaN or an infinity), in one line: exit status 1."""
    print(
        f"{name}: training diverged: {error} (the last checkpoint is kept; a lower lr may help)",
        file=sys.stderr,
    )
    return 1


def _train_ppo_bc(args: argparse.Namespace, name: str) -> int:
    from ..train.ppo_bc import load_configs, train

    try:
        ppo, imitation = load_configs(args.config)
        checkpoint = train(ppo, imitation, args.out, resume=args.resume, progress=args.progress)
    except (OSError, ValueError) as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2
    except FloatingPointError as error:
        return _diverged(name, error)
    print(f"checkpoint: {checkpoint}")
    return 0


def _train_ppo(args: argparse.Namespace, name: str) -> int:
    from .._client import Client
    from .._errors import EsrpError
    from ..train.heldout import lost_server
    from ..train.ppo import load_config, train

    try:
        config = load_config(args.config)
    except ValueError as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2

    def run(address: str) -> int:
        # `on_server` has reached a --server before: its going away now stops the run (status 3).
        try:
            with Client(address, token=args.token, timeout=120) as client:
                checkpoint = train(
                    config, args.out, client, resume=args.resume, progress=args.progress, stop_at=args.stop_at
                )
        except EsrpError as error:
            gone = lost_server(address, args.token, error)
            if gone is None:
                raise
            print(f"{name}: {gone}", file=sys.stderr)
            return 3
        print(f"checkpoint: {checkpoint}")
        return 0

    try:
        return on_server(args, run)
    except (OSError, ValueError, EsrpError) as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2
    except FloatingPointError as error:
        return _diverged(name, error)
