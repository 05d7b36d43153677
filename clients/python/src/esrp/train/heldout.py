"""The held-out evaluation of `esrp train bc` (its `eval_*` settings) and the server a training run
talks to.

An evaluation is `esrp eval --agent bc` run from Python (`esrp.eval.evaluation.evaluate`: episodes
played concurrently on one `AsyncClient`, `eval_episodes_in_flight` at a time, their agents' calls
of the policy batched: the agent config's `batch`) on a checkpoint the run just wrote, over scenes
fixed once per run (`heldout_scenes`), at the resolution of the demonstrations the policy learns
from, the policy on `eval_threads` torch threads. Each evaluation writes an `esrp.results/v1` file
(and its Markdown summary beside it) that a rerun resumes; its SR / OSR / RDR go to the run's
`eval.csv`.
"""

from __future__ import annotations

import contextlib
import csv
import io
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import torch

from .._async_client import AsyncClient
from .._client import Client
from .._common import unreachable
from .._errors import EsrpError, ServerUnavailable
from .._local import LocalServer
from .._signals import run_async
from .._values import Sensors
from ..agents.bc import BcConfig
from ..eval.evaluation import EvalError, EvalSettings, ServerGone, evaluate, missing_scene

__all__ = [
    "EVAL_FIELDS",
    "EvalError",
    "HeldOutResult",
    "ServerGone",
    "TrainServer",
    "evaluate_checkpoint",
    "heldout_scenes",
    "lost_server",
    "read_eval_log",
]

EVAL_FIELDS = ("epoch", "steps", "sr", "osr", "rdr", "episodes", "failed", "seconds")
"""The columns of a run's `eval.csv`: one line per held-out evaluation."""


def lost_server(address: str, token: str | None, error: EsrpError) -> ServerGone | None:
    """The error that stops a training run whose call to the server at `address` failed with
    `error` during the run, when the server no longer answers: one line naming the address as gRPC
    read it, and how to go on. That is an `error` of `ServerUnavailable`, or another one (a stream
    cut off as the server went is `UNKNOWN: transport error`) after which a call (`token`'s) finds
    nothing answering there; None when the server answers: `error` is the call's own.
    """
    if not isinstance(error, ServerUnavailable):
        try:
            with Client(address, token=token, timeout=10) as client:
                client.server_info()
            return None
        except ServerUnavailable as unavailable:
            error = unavailable
        except EsrpError:
            return None
    return _stopped(address, error)


def _stopped(address: str, error: EsrpError) -> ServerGone:
    """`lost_server`'s error, for the server at `address` that `error` (a `ServerUnavailable`)
    found not answering.
    """
    return ServerGone(
        f"{unreachable(address, error)}; the run stopped there: --resume goes on from its last "
        "checkpoint once the server answers"
    )


class TrainServer:
    """The esrp-server a training run uses for held-out evaluations and DAgger exports: the one at
    `address`, or one started here (`LocalServer` with `server_args`) at its first use and stopped
    by `close()` (or leaving the `with` block). A run that never evaluates starts none.

    A server that does not answer is said in one line naming its address: at the first contact
    (`reach`) as `EvalError`, before the run has started anything there; later, when the run
    stops on it, as `ServerGone` (`lost_server`).
    """

    def __init__(
        self, address: str | None = None, token: str | None = None, server_args: Sequence[str] = ()
    ) -> None:
        self.token = token
        self.server_args = list(server_args)
        self._address = address
        self.local: LocalServer | None = None
        self._reached = False
        """Whether a call has reached the server (`reach`)."""

    def address(self) -> str:
        """The server's `host:port` (starting the local server if none is running yet)."""
        if self._address is not None:
            return self._address
        if self.local is None:
            self.local = LocalServer(*self.server_args, unix_socket="auto")
            self.local.start()
        return self.local.address

    def reach(self) -> None:
        """Makes sure the server answers, with one call the first time: raises `EvalError` naming
        the address as gRPC read it when nothing answers there, at once (as `esrp eval` says it).
        """
        if self._reached:
            return
        address = self.address()
        try:
            with Client(address, token=self.token, timeout=30) as client:
                client.server_info()
        except ServerUnavailable as error:
            raise EvalError(unreachable(address, error)) from None
        self._reached = True

    @contextlib.contextmanager
    def client(self) -> Iterator[Client]:
        """A (blocking) client of the server, closed after the block; the server reached first
        (`reach`), and its going away in the block raised as `ServerGone` (`lost_server`).
        """
        self.reach()
        address = self.address()
        try:
            with Client(address, token=self.token, timeout=120) as client:
                yield client
        except EsrpError as error:
            gone = lost_server(address, self.token, error)
            if gone is None:
                raise
            raise gone from None

    def close(self) -> None:
        """Stops the server started here, if any."""
        if self.local is not None:
            self.local.stop()
            self.local = None

    def __enter__(self) -> TrainServer:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()


def heldout_scenes(server: TrainServer, config: BcConfig) -> list[str]:
    """The ids of the scenes `config`'s held-out evaluations play: `eval_scenes` (checked to be in
    `eval_split` and `eval_difficulty`), else the split's listing from `eval_offset`, at most
    `eval_limit`. Raises `ValueError` when a named scene is not there or none is left.
    """
    with server.client() as client:
        listed = list(client.scenes(config.eval_split, config.eval_difficulty, page_size=1000))
        if config.eval_scenes:
            by_id = {s.id: s for s in listed}
            for wanted in config.eval_scenes:
                if wanted not in by_id:
                    every = list(client.scenes(page_size=1000))
                    reason = missing_scene(wanted, config.eval_split, config.eval_difficulty, by_id, every)
                    raise ValueError(f"eval_scenes: {reason}")
            return list(config.eval_scenes)
    end = None if config.eval_limit is None else config.eval_offset + config.eval_limit
    chosen = [s.id for s in listed[config.eval_offset : end]]
    if not chosen:
        which = f"{config.eval_split}{'' if config.eval_difficulty is None else ' ' + config.eval_difficulty}"
        raise ValueError(
            f"no held-out scene: the {which} scenes number {len(listed)}, eval_offset is {config.eval_offset}"
        )
    return chosen


@dataclass
class HeldOutResult:
    """One held-out evaluation: SR, OSR (fractions) and RDR over its recorded episodes, how many
    were recorded and how many failed with an error (not recorded), and its wall seconds.
    """

    sr: float
    osr: float
    rdr: float
    episodes: int
    failed: int
    seconds: float

    def row(self, epoch: int, steps: int) -> list[str]:
        """The `eval.csv` line of this evaluation after `epoch` (`steps` optimizer steps)."""
        values = (self.sr, self.osr, self.rdr)
        return [str(epoch), str(steps), *(f"{v:.6f}" for v in values)] + [
            str(self.episodes),
            str(self.failed),
            f"{self.seconds:.1f}",
        ]

    def text(self) -> str:
        """SR / OSR / RDR in a few words."""
        failed = f", {self.failed} failed" if self.failed else ""
        return (
            f"SR {100 * self.sr:.1f} %  OSR {100 * self.osr:.1f} %  RDR {self.rdr:.3f} "
            f"({self.episodes} episodes{failed}, {self.seconds:.0f} s)"
        )


def evaluate_checkpoint(
    server: TrainServer,
    checkpoint: Path,
    config: BcConfig,
    scenes: Sequence[str],
    resolution: int,
    out: Path,
    *,
    progress: bool = True,
) -> HeldOutResult:
    """Plays the policy of `checkpoint` on `scenes` (of `config.eval_split`) as `esrp eval --agent bc`
    does, with views of `resolution` pixels, writing (or resuming) the results file `out`.
    Raises `EvalError` when the evaluation cannot run (a bad checkpoint; the server not answering
    at the first contact), and `ServerGone` when the server stops answering.
    """
    epsilon = config.epsilon if config.eval_epsilon is None else config.eval_epsilon
    settings = EvalSettings(
        agent="bc",
        out=out,
        split=config.eval_split,
        difficulty=config.eval_difficulty,
        scenes=list(scenes),
        episodes_in_flight=config.eval_episodes_in_flight,
        seed=config.eval_seed,
        # The episodes in flight share the policy, their requests denoised as one batch.
        agent_config={
            "checkpoint": str(checkpoint),
            "epsilon": epsilon,
            "threads": config.eval_threads,
            "batch": config.eval_episodes_in_flight,
        },
        sensors=Sensors(resolution=resolution),
        progress=progress,
        resume="the training run stopped there: --resume goes on from its last checkpoint",
    )
    server.reach()
    address = server.address()

    async def run() -> HeldOutResult:
        async with AsyncClient(address, token=server.token, timeout=120) as client:
            try:
                await client.server_info()
                await client.wait_healthy(30)
                started = time.monotonic()
                outcome = await evaluate(client, settings, server.local)
            except ServerUnavailable as error:  # gone since the run reached it
                raise _stopped(address, error) from None
            tally = outcome.summary.overall
            seconds = time.monotonic() - started
            return HeldOutResult(tally.sr, tally.osr, tally.rdr, tally.episodes, len(outcome.failed), seconds)

    # `evaluate` prints its summary on stdout (it is in the Markdown file beside the results, and
    # the caller prints a line of it): stdout stays the command's. Its progress goes to stderr, or
    # nowhere without `progress`.
    # Loading the policy builds a model, whose initialisation draws from torch's random state, and
    # sets torch's thread count (`eval_threads`): both are restored after, so that evaluating
    # changes nothing the training draws or runs on.
    threads = torch.get_num_threads()
    try:
        with torch.random.fork_rng(devices=[]), contextlib.redirect_stdout(io.StringIO()):
            if progress:
                return run_async(run())
            with contextlib.redirect_stderr(io.StringIO()):
                return run_async(run())
    finally:
        torch.set_num_threads(threads)


def read_eval_log(path: Path) -> list[dict[str, str]]:
    """The lines of an `eval.csv` (none if it does not exist)."""
    if not path.exists():
        return []
    with open(path, newline="") as file:
        return list(csv.DictReader(file))
