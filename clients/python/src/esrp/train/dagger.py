"""`esrp train bc --dagger`: DAgger (Ross, Gordon and Bagnell, 2011) around ESRP-BC.

Iteration 0 is `esrp train bc` on the config's expert stores (`[bc]`'s `demos`, `epochs`), or with
`initial` a checkpoint such a training already wrote (with `[bc]`'s settings; copied into
`DIR/iter-00` and evaluated on the held-out scenes, not trained again). Each further iteration
k = 1..`iterations`:

1. exports `DIR/dagger-kk.zarr` (`esrp demos export --dagger bc`): the checkpoint of iteration k-1
   drives `scenes_per_iteration` scenes of `split` / `difficulty` (drawn with seed (`seed`, k) from
   the split's listing, or from `scenes`, never a held-out one), and the server's planner labels
   every state it visits; the planner's label is stepped instead of the policy's action with
   probability `beta` × `beta_decay`^(k-1);
2. fine-tunes the model and optimizer of iteration k-1 for `epochs_per_iteration` epochs on the
   expert stores and every DAgger store so far (DAgger's aggregated data set), in `DIR/iter-kk`
   (a run folder of `esrp train bc`; its seed is `[bc]`'s `seed` + k, its peak learning rate
   `lr`, and with `keep_average` it goes on with iteration k-1's average of the weights);
3. evaluates the result on the held-out scenes (`[bc]`'s `eval_*` settings, as `esrp train bc`
   does after its last epoch).

`DIR/dagger.csv` gets a line per iteration (`DAGGER_FIELDS`), `DIR/state.json` says how far the run
got (written atomically after each phase): `--resume` goes on from there, an interrupted export
resuming its store and an interrupted training its iteration's checkpoint.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import sys
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from ..agents._checkpoint import read_checkpoint
from ..agents._config import reject_unknown
from ..agents.bc import BcConfig, checkpoint_settings
from ..agents.encoders import resolve_device
from ._config import read_document
from ._training import settings_differences
from .bc import RESUME_FREE, check_resolution, train
from .demos import DemoSettings, export_demos
from .heldout import TrainServer, heldout_scenes, read_eval_log

__all__ = [
    "DAGGER_FIELDS",
    "STATE_FORMAT",
    "DaggerConfig",
    "load_dagger_config",
    "run_dagger",
]

STATE_FORMAT = "esrp.dagger-run/v1"
"""The `format` of a DAgger run's `state.json`."""

DAGGER_FIELDS = (
    "iteration",
    "episodes",
    "steps",
    "total_steps",
    "agreement",
    "sr",
    "osr",
    "rdr",
    "eval_episodes",
    "seconds",
)
"""The columns of `dagger.csv`: the iteration; the episodes and steps it added (iteration 0: the
expert stores'); the steps trained on; the fraction of the added states where the policy's own
action was the planner's label (empty for iteration 0); the held-out SR, OSR (fractions) and RDR
after its training and the episodes they are over; its wall seconds (of the phases that ran to
their end: work an interruption threw away is not counted)."""

BC_RESUME_FREE = frozenset(
    {"threads", "device", "checkpoint_every", "in_memory", "eval_episodes_in_flight", "eval_threads"}
)
"""`[bc]` settings a resumed DAgger run may change (none changes what is trained or measured)."""

DAGGER_RESUME_FREE = frozenset({"iterations", "episodes_in_flight"})
"""`[dagger]` settings a resumed DAgger run may change: more (or fewer) iterations, and how many
episodes an export plays at a time (the same stores either way)."""


@dataclass
class DaggerConfig:
    """The `[dagger]` table of a training config (see the module's docstring).

    Attributes:
        iterations: DAgger iterations after iteration 0 (plain BC).
        epochs_per_iteration: Fine-tuning epochs of each.
        scenes_per_iteration: Scenes each export rolls the policy out on (all the candidates if
            fewer).
        split: The split of those scenes.
        difficulty: Only scenes of this difficulty.
        scenes: The candidate scenes (ids, in `split` and `difficulty`); empty: the split's listing.
        beta: The probability that the planner's label is stepped instead of the policy's action,
            in iteration 1.
        beta_decay: `beta`'s factor per further iteration.
        plan_budget_ms: The planner's budget per label, 1 to 2³²−1 milliseconds.
        max_steps: At most this many labelled states per episode (0: until the episode ends).
        epsilon: The policy's random-action probability in the exports (None: `[bc]`'s `epsilon`).
        seed: The seed of the scene draws and the base seed of the exports' episodes (iteration k
            plays scene `id` with seed `(seed + k) XOR fnv1a64(id)`).
        episodes_in_flight: How many of an export's episodes play at a time (`esrp demos export
            --episodes-in-flight`: the same store, written in the scenes' order; 2 overlaps the
            server's planning with the policy's forward passes on a 2-core machine).
        lr: The peak learning rate of each iteration's fine-tuning (its warm-up and cosine
            schedule start anew); None: `[bc]`'s `lr`.
        keep_average: With `[bc]`'s `ema`, each fine-tuning goes on with the previous
            iteration's average of the weights (its step count, so its decay, included) instead
            of starting one from the trained weights: the played weights then move gradually.
        initial: Iteration 0's checkpoint: a full `ckpt.pt` (model and optimizer) of `esrp train
            bc` with `[bc]`'s settings (its `epochs` and the settings `esrp train bc --resume` may
            change aside), instead of training iteration 0; None: train it.
    """

    iterations: int = 3
    epochs_per_iteration: int = 50
    scenes_per_iteration: int = 50
    split: str = "train"
    difficulty: str | None = None
    scenes: list[str] = field(default_factory=list)
    beta: float = 0.0
    beta_decay: float = 1.0
    plan_budget_ms: int = 10_000
    max_steps: int = 0
    epsilon: float | None = None
    seed: int = 0
    initial: str | None = None
    episodes_in_flight: int = 2
    lr: float | None = None
    keep_average: bool = False

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> DaggerConfig:
        """A config from a mapping (the TOML table); unknown keys and bad values raise `ValueError`."""
        reject_unknown(cls, values, "dagger")
        config = cls(**dict(values))
        config._check()
        return config

    def _check(self) -> None:
        integers = (
            "iterations",
            "epochs_per_iteration",
            "scenes_per_iteration",
            "plan_budget_ms",
            "episodes_in_flight",
        )
        for name in (*integers, "max_steps", "seed"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError(f"dagger {name} must be an integer, not {value!r}")
        if self.iterations < 0 or self.max_steps < 0:
            raise ValueError("dagger iterations and max_steps must be 0 or more")
        for name in integers[1:]:
            if getattr(self, name) < 1:
                raise ValueError(f"dagger {name} must be at least 1, not {getattr(self, name)}")
        if self.plan_budget_ms >= 2**32:
            budget = self.plan_budget_ms
            raise ValueError(f"dagger plan_budget_ms must be at most 4294967295 (32 bits), not {budget}")
        if self.split not in ("train", "test"):
            raise ValueError(f"dagger split {self.split!r}: train or test")
        if self.initial is not None and (not isinstance(self.initial, str) or not self.initial):
            raise ValueError(f"dagger initial must be the path of a checkpoint, not {self.initial!r}")
        if self.difficulty not in (None, "easy", "medium", "hard"):
            raise ValueError(f"dagger difficulty {self.difficulty!r}: easy, medium or hard")
        if not isinstance(self.scenes, list | tuple) or not all(isinstance(s, str) for s in self.scenes):
            raise ValueError(f"dagger scenes must be a list of scene ids, not {self.scenes!r}")
        self.scenes = list(self.scenes)
        if self.lr is not None and (
            isinstance(self.lr, bool) or not isinstance(self.lr, int | float) or not self.lr > 0
        ):
            raise ValueError(f"dagger lr must be a positive number, not {self.lr!r}")
        if not isinstance(self.keep_average, bool):
            raise ValueError(f"dagger keep_average must be true or false, not {self.keep_average!r}")
        for name in ("beta", "beta_decay", "epsilon"):
            value = getattr(self, name)
            if name == "epsilon" and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 1.0:
                raise ValueError(f"dagger {name} must be between 0 and 1, not {value!r}")

    def beta_at(self, iteration: int) -> float:
        """The mixing probability of iteration `iteration` (1 or more)."""
        return float(self.beta * self.beta_decay ** (iteration - 1))

    def to_dict(self) -> dict[str, Any]:
        """The config as plain values (for `state.json`)."""
        return asdict(self)


def load_dagger_config(path: Path) -> DaggerConfig:
    """The `[dagger]` table of a TOML file (or the `dagger` object of a JSON file); raises
    `ValueError` naming the file when it has none or it is bad.
    """
    table = read_document(path).get("dagger")
    if table is None:
        raise ValueError(
            f"{path} has no [dagger] table: esrp train bc --dagger needs one (docs/demonstrations.md)"
        )
    if not isinstance(table, dict):
        raise ValueError(f"{path}: [dagger] is not a table")
    try:
        return DaggerConfig.from_mapping(table)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: {error}") from None


def _write_json(path: Path, value: Mapping[str, Any]) -> None:
    """Writes `value` to `path` atomically (a file beside it, flushed, renamed over it)."""
    partial = path.with_suffix(".partial")
    with open(partial, "w", encoding="utf-8") as file:
        file.write(json.dumps(value, indent=2) + "\n")
        file.flush()
        os.fsync(file.fileno())
    partial.replace(path)


def _store_size(path: str | Path) -> tuple[int, int, int]:
    """(episodes, steps, views' side in pixels) of an `esrp.demos/v1` store."""
    import zarr

    try:
        store = cast(Any, zarr.open_group(str(path), mode="r"))
    except (FileNotFoundError, ValueError) as error:
        raise ValueError(f"cannot open the demonstration store {path}: {error}") from None
    if store.attrs.get("format") != "esrp.demos/v1":
        raise ValueError(f"{path} is not an esrp.demos/v1 store (esrp demos export makes one)")
    ends = np.asarray(store["meta/episode_ends"][:], dtype=np.int64)
    return len(ends), int(ends[-1]) if len(ends) else 0, int(store["data/ego_rgb"].shape[1])


def _initial_epochs(path: Path, bc: BcConfig) -> int:
    """The epochs an `initial` checkpoint was trained for; raises `ValueError` when it is not a full
    `esrp train bc` checkpoint of `bc`'s settings (those a resumed run may change aside).
    """
    if not path.is_file():
        raise ValueError(f"dagger initial: no checkpoint at {path}")
    try:
        state = read_checkpoint(path, "esrp-bc", "ESRP-BC")
    except ValueError as error:
        raise ValueError(f"dagger initial: {error}") from None
    if "optimizer" not in state or "torch_rng" not in state:
        raise ValueError(
            f"dagger initial: {path} holds the model only (a checkpoint for playing): DAgger fine-tunes "
            "the model and its optimizer, so give the run's own ckpt.pt (or ckpt-epoch-N.pt)"
        )
    different = settings_differences(checkpoint_settings(state["config"]), bc.to_dict(), RESUME_FREE)
    if different:
        raise ValueError(
            f"dagger initial: {path} was trained with other settings than [bc]'s ({'; '.join(different)})"
        )
    return int(state["epoch"])


class _Run:
    """One DAgger run folder: its state, its logs, and the steps of its iterations."""

    def __init__(
        self,
        bc: BcConfig,
        dagger: DaggerConfig,
        out: Path,
        server: TrainServer,
        progress: bool,
    ) -> None:
        self.bc, self.dagger, self.out, self.server, self.progress = bc, dagger, out, server, progress
        self.state_path = out / "state.json"
        self.log_path = out / "dagger.csv"
        self.experts = [bc.demos] if isinstance(bc.demos, str) else list(bc.demos)
        if not self.experts:
            raise ValueError("[bc] demos names no demonstration store")
        sizes = [_store_size(path) for path in self.experts]
        self.expert_episodes = sum(size[0] for size in sizes)
        self.expert_steps = sum(size[1] for size in sizes)
        self.resolution = sizes[0][2]
        # What iteration 0's training would refuse, refused before the run folder is made.
        for path, size in zip(self.experts, sizes, strict=True):
            if size[2] != self.resolution:
                raise ValueError(f"{path} holds {size[2]} px views, {self.experts[0]} {self.resolution} px")
        check_resolution(self.resolution, bc)
        resolve_device(bc.device)
        self.state: dict[str, Any] = {}
        self.heldout: list[str] = []
        self.pool: list[str] = []
        self.initial_epochs = 0 if dagger.initial is None else _initial_epochs(Path(dagger.initial), bc)

    def say(self, message: str) -> None:
        if self.progress:
            print(f"dagger: {message}", file=sys.stderr)

    def settings(self) -> dict[str, Any]:
        return {"bc": self.bc.to_dict(), "dagger": self.dagger.to_dict()}

    def open(self, resume: bool) -> None:
        """Reads the state of the run `out` holds (with `resume`) or prepares one (`start` makes the
        folder and writes it).
        """
        if self.out.exists() and not self.out.is_dir():
            raise ValueError(f"{self.out} is a file, not a run folder: give another --out")
        if self.state_path.exists():
            if not resume:
                raise ValueError(
                    f"{self.out} already holds a DAgger run: pass --resume to go on with it, or another --out"
                )
            state = json.loads(self.state_path.read_text(encoding="utf-8"))
            if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
                raise ValueError(f"{self.state_path} is not the state of a DAgger run")
            held = state["settings"]
            # A run made before a [dagger] setting existed ran with its default.
            held_dagger = {**DaggerConfig().to_dict(), **held["dagger"]}
            different = settings_differences(held["bc"], self.settings()["bc"], BC_RESUME_FREE)
            different += settings_differences(held_dagger, self.settings()["dagger"], DAGGER_RESUME_FREE)
            if different:
                raise ValueError(
                    f"{self.out} is a DAgger run with other settings ({'; '.join(different)}): "
                    "resume it with its own config (only iterations, episodes_in_flight, threads, device, "
                    "checkpoint_every, in_memory, eval_episodes_in_flight and eval_threads may change), "
                    "or use another --out"
                )
            self.state = state
            done = int(state["completed"])
            self.say(f"resuming {self.out}: {done} iterations done")
        else:
            if (self.out / "iter-00").exists():
                raise ValueError(
                    f"{self.out} holds iter-00 but no state.json: not a DAgger run; use another --out"
                )
            if (self.out / "ckpt.pt").exists():
                # A run of esrp train bc (or ppo): its config.json would be overwritten.
                raise ValueError(
                    f"{self.out} holds a run without --dagger (ckpt.pt), not a DAgger run: use another "
                    "--out (a [dagger] table's initial = its ckpt.pt starts from it)"
                )
            self.state = {
                "format": STATE_FORMAT,
                "settings": self.settings(),
                "completed": 0,
                "current": None,
            }
        self.state["settings"] = self.settings()

    def start(self) -> None:
        """Makes the run folder and writes the state and the settings: the run is there (once its
        settings, stores and server proved usable: a run refused before leaves no folder behind).
        """
        self.out.mkdir(parents=True, exist_ok=True)
        _write_json(self.state_path, self.state)
        _write_json(self.out / "config.json", self.settings())

    def choose_pool(self) -> None:
        """Fixes the held-out scenes and the candidates of the rollouts (the split's, or `scenes`,
        without the held-out ones).
        """
        self.heldout = heldout_scenes(self.server, self.bc)
        with self.server.client() as client:
            listed = [s.id for s in client.scenes(self.dagger.split, self.dagger.difficulty, page_size=1000)]
        where = f"{self.dagger.split}{'' if self.dagger.difficulty is None else ' ' + self.dagger.difficulty}"
        if self.dagger.scenes:
            known = set(listed)
            missing = [s for s in self.dagger.scenes if s not in known]
            if missing:
                raise ValueError(f"dagger scenes: {missing[0]!r} is not among the {where} scenes")
            listed = list(self.dagger.scenes)
        held = set(self.heldout)
        self.pool = [s for s in listed if s not in held]
        if not self.pool:
            raise ValueError(
                f"no scene is left for DAgger's rollouts: the {len(listed)} {where} scenes are all held out "
                "(choose fewer eval scenes, or another eval_split)"
            )
        if len(self.pool) < self.dagger.scenes_per_iteration:
            self.say(
                f"{len(self.pool)} candidate scenes, fewer than scenes_per_iteration "
                f"({self.dagger.scenes_per_iteration}): each iteration rolls out on all of them"
            )

    def scenes_of(self, iteration: int) -> list[str]:
        """The scenes iteration `iteration` rolls the policy out on, in the candidates' order."""
        count = min(self.dagger.scenes_per_iteration, len(self.pool))
        rng = np.random.default_rng([self.dagger.seed, iteration])
        return [self.pool[i] for i in sorted(rng.choice(len(self.pool), size=count, replace=False))]

    def store(self, iteration: int) -> Path:
        return self.out / f"dagger-{iteration:02d}.zarr"

    def folder(self, iteration: int) -> Path:
        return self.out / f"iter-{iteration:02d}"

    def config_of(self, iteration: int) -> BcConfig:
        """The `esrp train bc` settings of iteration `iteration`."""
        if iteration == 0:
            return self.bc if self.dagger.initial is None else replace(self.bc, epochs=self.initial_epochs)
        demos = [*self.experts, *(str(self.store(k)) for k in range(1, iteration + 1))]
        lr = self.bc.lr if self.dagger.lr is None else float(self.dagger.lr)
        return replace(
            self.bc,
            demos=demos,
            epochs=self.dagger.epochs_per_iteration,
            seed=self.bc.seed + iteration,
            lr=lr,
        )

    def total_steps(self, iteration: int) -> int:
        """The steps iteration `iteration` trains on: the expert stores' and its DAgger stores'."""
        return self.expert_steps + sum(_store_size(self.store(k))[1] for k in range(1, iteration + 1))

    def save(self) -> None:
        _write_json(self.state_path, self.state)

    def export(self, iteration: int, current: dict[str, Any]) -> None:
        """Rolls the previous iteration's policy out into this iteration's store."""
        scenes = self.scenes_of(iteration)
        beta = self.dagger.beta_at(iteration)
        store = self.store(iteration)
        self.say(f"iteration {iteration}: rolling out on {len(scenes)} scenes (beta {beta:.3f}) into {store}")
        epsilon = self.bc.epsilon if self.dagger.epsilon is None else self.dagger.epsilon
        settings = DemoSettings(
            out=store,
            split=self.dagger.split,
            difficulty=self.dagger.difficulty,
            scenes=scenes,
            resolution=self.resolution,
            progress=self.progress,
            dagger="bc",
            agent_config={
                "checkpoint": str(self.folder(iteration - 1) / "ckpt.pt"),
                "epsilon": epsilon,
                "threads": self.bc.eval_threads,
            },
            beta=beta,
            seed=self.dagger.seed + iteration,
            plan_budget_ms=self.dagger.plan_budget_ms,
            max_steps=self.dagger.max_steps,
            label_horizon=self.bc.horizon,
            episodes_in_flight=self.dagger.episodes_in_flight,
        )
        threads = torch.get_num_threads()  # the policy plays on eval_threads; training goes on with these
        try:
            with self.server.client() as client:
                outcome = export_demos(client, settings)
        finally:
            torch.set_num_threads(threads)
        current["export"] = {
            "episodes": outcome.episodes,
            "steps": outcome.steps,
            "agreement": outcome.agreement,
            "skipped": list(outcome.skipped),
        }
        agreement = (
            ""
            if outcome.agreement is None
            else f", the policy's action was the planner's label at {100 * outcome.agreement:.1f} % of them"
        )
        skipped = f" ({len(outcome.skipped)} skipped: no plan from their start)" if outcome.skipped else ""
        self.say(
            f"iteration {iteration}: {outcome.episodes} episodes, {outcome.steps} states{agreement}{skipped}"
        )

    def fit(self, iteration: int) -> None:
        """Trains (iteration 0) or fine-tunes this iteration's model, then evaluates it."""
        config = self.config_of(iteration)
        folder, steps = self.folder(iteration), self.total_steps(iteration)
        init = None if iteration == 0 else self.folder(iteration - 1) / "ckpt.pt"
        if iteration > 0 or self.dagger.initial is None:
            self.say(f"iteration {iteration}: training {config.epochs} epochs on {steps} steps in {folder}")
        elif not (folder / "ckpt.pt").exists():
            # The given checkpoint is iteration 0: training resumes it with nothing left to train
            # (checking its settings) and evaluates it.
            self.say(
                f"iteration 0: {self.dagger.initial} (epoch {config.epochs}), evaluated, not trained again"
            )
            folder.mkdir(parents=True, exist_ok=True)
            partial = folder / "ckpt.pt.partial"
            shutil.copyfile(self.dagger.initial, partial)
            partial.replace(folder / "ckpt.pt")
        train(
            config,
            folder,
            # Resumed where an interruption left a checkpoint; else started, without the note that
            # a --resume found nothing to go on from (the run was not asked to resume).
            resume=(folder / "ckpt.pt").exists(),
            progress=self.progress,
            server=self.server,
            init=init,
            init_average=self.dagger.keep_average,
            final_eval=True,
        )

    def log(self, iteration: int, current: dict[str, Any]) -> dict[str, str]:
        """Writes iteration `iteration`'s `dagger.csv` line (replacing one an interruption left)."""
        config = self.config_of(iteration)
        rows = [
            r for r in read_eval_log(self.folder(iteration) / "eval.csv") if int(r["epoch"]) == config.epochs
        ]
        if not rows:
            raise ValueError(
                f"{self.folder(iteration)}/eval.csv has no evaluation after epoch {config.epochs}"
            )
        evaluation = rows[-1]
        if iteration == 0:
            episodes, steps, agreement = self.expert_episodes, self.expert_steps, ""
        else:
            export = current["export"]
            episodes, steps = int(export["episodes"]), int(export["steps"])
            agreement = "" if export["agreement"] is None else f"{export['agreement']:.6f}"
        line = {
            "iteration": str(iteration),
            "episodes": str(episodes),
            "steps": str(steps),
            "total_steps": str(self.total_steps(iteration)),
            "agreement": agreement,
            "sr": evaluation["sr"],
            "osr": evaluation["osr"],
            "rdr": evaluation["rdr"],
            "eval_episodes": evaluation["episodes"],
            "seconds": f"{float(current['seconds']):.1f}",
        }
        kept: list[dict[str, str]] = []
        if iteration > 0 and self.log_path.exists():
            with open(self.log_path, newline="") as file:
                kept = [r for r in csv.DictReader(file) if int(r["iteration"]) < iteration]
        with open(self.log_path, "w", newline="") as file:
            writer: csv.DictWriter[str] = csv.DictWriter(file, fieldnames=DAGGER_FIELDS)
            writer.writeheader()
            writer.writerows([*kept, line])
        return line

    def iterate(self, iteration: int) -> None:
        """Runs iteration `iteration` from where the state says it stopped."""
        current = self.state.get("current")
        if not isinstance(current, dict) or current.get("iteration") != iteration:
            current = {"iteration": iteration, "phase": "export" if iteration else "train", "seconds": 0.0}
            self.state["current"] = current
            self.save()
        if current["phase"] == "export":
            started = time.monotonic()
            self.export(iteration, current)
            current["phase"] = "train"
            current["seconds"] = float(current["seconds"]) + time.monotonic() - started
            self.save()
        started = time.monotonic()
        self.fit(iteration)
        current["seconds"] = float(current["seconds"]) + time.monotonic() - started
        line = self.log(iteration, current)
        self.state["completed"] = iteration + 1
        self.state["current"] = None
        self.save()
        agreement = f"agreement {100 * float(line['agreement']):.1f} %, " if line["agreement"] else ""
        self.say(
            f"iteration {iteration} done: {agreement}held-out SR {100 * float(line['sr']):.1f} % "
            f"OSR {100 * float(line['osr']):.1f} % RDR {float(line['rdr']):.3f} "
            f"({line['eval_episodes']} episodes), {float(line['seconds']):.0f} s"
        )


def run_dagger(
    bc: BcConfig,
    dagger: DaggerConfig,
    out: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    server: TrainServer | None = None,
) -> Path:
    """Runs (or with `resume` goes on with) the DAgger run in `out`, through iteration
    `dagger.iterations`; returns the last iteration's checkpoint.

    Args:
        bc: The `[bc]` settings: the expert stores, the model, iteration 0's training, the
            held-out evaluation.
        dagger: The `[dagger]` settings.
        out: The run folder.
        resume: Go on with the run `out` holds (its settings must be these, `BC_RESUME_FREE` and
            `DAGGER_RESUME_FREE` aside); without it, a folder holding a run is refused.
        progress: Print progress on stderr.
        server: The server of the exports and evaluations; None: one is started here.

    Raises `ValueError` for bad settings or files, `DemoExportError` when an export cannot run,
    `EvalError` when an evaluation cannot, `EsrpError` for the server's errors.
    """
    run = _Run(bc, dagger, out, server if server is not None else TrainServer(), progress)
    try:
        run.open(resume)
        run.choose_pool()
        run.start()
        first = int(run.state["completed"])
        if first > dagger.iterations:
            run.say(f"nothing to do: iterations 0 to {first - 1} are done, 0 to {dagger.iterations} asked")
        for iteration in range(first, dagger.iterations + 1):
            run.iterate(iteration)
    finally:
        if server is None:
            run.server.close()
    last = min(int(run.state["completed"]), dagger.iterations + 1) - 1
    return run.folder(max(last, 0)) / "ckpt.pt"
