"""`esrp eval`: runs an agent over the scenes of a split and writes one `esrp.results/v1` record
per episode (docs/evaluation.md), with a progress bar, resumption, and the Markdown summary with the
paper's rows beside it — the Python twin of the Rust `esrp-eval`, writing the same files.

Agents: `plan` (the server's planner through PlanActions: the whole plan, stepped, then replanned
as the Rust agent does), `expert` (the scene's expert trajectory), `random` (`RandomAgent`), `vlm`
(ESRP-VLM, `esrp.agents.vlm`: a ReAct agent over an OpenAI-compatible endpoint), or
`MODULE:CALLABLE`, a factory of `esrp.agents.Agent` / `AsyncAgent` called with the agent config.

Episodes run concurrently on one `AsyncClient` (`episodes_in_flight` at a time); the scenes are
fixed up front, in dataset order, and taken in that order, so no scene waits on how long another
takes. Records are appended and flushed in completion order.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import inspect
import json
import math
import sys
import time
import traceback
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any

import numpy as np

from .. import __version__
from .._async_client import AsyncClient, AsyncEpisode
from .._common import unreachable
from .._errors import (
    AlreadyPlayed,
    DeadlineExceeded,
    EpisodeEnded,
    EsrpError,
    InvalidRequest,
    PermissionDenied,
    ProtocolError,
    SceneNotFound,
    ServerUnavailable,
    Unauthenticated,
)
from .._local import LocalServer
from .._signals import run_async
from .._values import Action, EpisodeMetrics, SceneSummary, Sensors, ServerInfo, action_value
from ..agents import (
    Agent,
    AgentFactory,
    AsyncAgent,
    RandomAgent,
    is_async_agent,
    load_factory,
    raised_at,
)
from ._pool import run_workers
from .results import (
    SCHEMA,
    EpisodeRecord,
    Summary,
    Tally,
    append_record,
    fnv1a64,
    read_records,
    scene_seed,
    truncate_to,
)

__all__ = [
    "BUILTIN_AGENTS",
    "CLIENT_NAME",
    "EvalError",
    "EvalOutcome",
    "EvalSettings",
    "errors_log_path",
    "evaluate",
    "expert_trajectory",
    "format_failures",
    "run_eval",
]

BUILTIN_AGENTS = ("random", "expert", "plan", "vlm", "bc", "ppo", "map")
"""The agents `esrp eval` knows by name."""

CLIENT_NAME = f"esrp eval (Python) {__version__}"
"""The `client` field of the records this tool writes."""

_API_CODES = {action.api_name: action for action in Action}


class EvalError(Exception):
    """The evaluation cannot run as asked (bad arguments, a results file of another agent)."""


class ServerGone(EvalError):
    """The server died, or stayed unreachable, in the middle of the run: it stopped there. The
    records of the episodes that ended are kept; running the same command again resumes.
    """


class AgentStopped(EvalError):
    """The agent failed an episode in a way every episode would (its exception says so with a true
    `stops_run` attribute, as `VlmEndpointError` does for a wrong API key, URL or model, or a model
    endpoint that cannot be reached): the run stopped there instead of failing each episode in
    turn. The records of the episodes that ended are kept; once the cause is fixed, running the
    same command again resumes.
    """


def stops_the_run(scene_id: str, error: BaseException, written: int) -> AgentStopped | None:
    """`AgentStopped` for `scene_id`'s `error` when the agent said every episode would fail the
    same way (`error.stops_run` is true), None otherwise; `written`: the records this run kept.
    """
    if getattr(error, "stops_run", False) is not True:
        return None
    kept = f"{written} episodes recorded by this run are kept"
    if written == 1:
        kept = "1 episode recorded by this run is kept"
    return AgentStopped(
        f"{scene_id}: {type(error).__name__}: {error}; stopped the run there, as every episode would "
        f"fail the same way ({kept}: run the same command again to resume once it is fixed)"
    )


SERVER_RETRY_SECONDS = 10.0
"""How long a run waits for a server that stopped answering before it stops (`ServerGone`)."""


@dataclass
class EvalSettings:
    """What `esrp eval` runs; the fields are its flags.

    Attributes:
        agent: `random`, `expert`, `plan`, `vlm` (`esrp.agents.vlm`, configured by `agent_config`),
            or `MODULE:CALLABLE` (a factory of agents).
        out: The results file (JSON Lines); scenes already in it are skipped.
        split: The split whose scenes to run (`train`, `test`, `challenge` or `minival`).
        difficulty: Only scenes of this difficulty (`easy`, `medium`, `hard`).
        scenes: Only these scene ids, in this order (they must be in the split).
        limit: At most this many scenes (after the filters), the first in order.
        episodes_in_flight: Episodes played at the same time.
        seed: Base seed; scene `id` plays with `seed XOR fnv1a64(id)`.
        fresh: Start the results file over instead of resuming it.
        summary: The Markdown summary's path (default: `out` with `.md`).
        agent_config: The agent's settings (a factory's argument; recorded as `agent_config`).
        plan_budget_ms: The planner's time budget per PlanActions call (plan agent), 1 to 2³²−1
            milliseconds (the server caps it at its `--max-plan-ms`).
        replans: PlanActions calls after the first when the episode goes on (plan agent), 0 or
            more.
        sensors: Optional sensors of a `MODULE:CALLABLE` agent's episodes.
        privileged: Create a `MODULE:CALLABLE` agent's episodes privileged (for reference agents
            that read the state or call PlanActions; not an ESRP agent proper then).
        progress: Show a progress bar (on a terminal) or a line every 5 % (otherwise).
        resume: What a run stopped by a lost server tells its user to do (`esrp eval`'s: rerun
            the same command; a training run's: its `--resume`).
    """

    agent: str
    out: Path
    split: str = "test"
    difficulty: str | None = None
    scenes: Sequence[str] = ()
    limit: int | None = None
    episodes_in_flight: int = 8
    seed: int = 0
    fresh: bool = False
    summary: Path | None = None
    agent_config: dict[str, Any] = field(default_factory=dict)
    plan_budget_ms: int = 60_000
    replans: int = 2
    sensors: Sensors | None = None
    privileged: bool = False
    progress: bool = True
    resume: str = "re-run the same command to resume"

    def recorded_config(self) -> dict[str, Any]:
        """The record's `agent_config`: the plan agent's settings as the Rust tool writes them, `{}`
        for expert and random, the given config for a factory.
        """
        if self.agent == "plan":
            return {"budget_ms": self.plan_budget_ms, "replans": self.replans}
        if self.agent in ("expert", "random"):
            return {}
        return dict(self.agent_config)

    def plays_privileged(self) -> bool:
        """Whether the episodes are created privileged: `plan` and `expert` always, another agent
        with `privileged`. A run of another agent with `privileged` marks its records
        (`"privileged": true`, a field the schema's table does not list), so that `esrp report`
        shows them as references.
        """
        return self.agent in ("plan", "expert") or self.privileged

    def seeded(self) -> bool:
        """Whether the agent gets (and the record stores) a per-scene seed: random and factories."""
        return self.agent not in ("plan", "expert")


@dataclass
class EvalOutcome:
    """What an evaluation did.

    Attributes:
        records: The records of the chosen scenes: earlier runs' and this one's, in file order.
        written: How many records this run wrote.
        failed: `(scene_id, error)` of the episodes that failed and were not recorded.
        summary: The summary of `records`.
        summary_path: Where the Markdown summary was written.
        errors_log: The tracebacks of the failed episodes (None when none failed).
        refused: The scene ids among `failed` that the server refused for a reason a rerun would
            meet again (a challenge scene already played, an unknown scene, a malformed request,
            a token or role that does not allow it); a rerun may play the others.
    """

    records: list[EpisodeRecord]
    written: int
    failed: list[tuple[str, str]]
    summary: Summary
    summary_path: Path
    errors_log: Path | None = None
    refused: list[str] = field(default_factory=list)


@dataclass
class _Played:
    scene: SceneSummary
    metrics: EpisodeMetrics
    actions: list[int]
    end: str
    stats: dict[str, Any]


def _now_rfc3339() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _end_of(metrics: EpisodeMetrics) -> str:
    return "success" if metrics.success else "horizon"


async def _take(
    client: AsyncClient, episode: AsyncEpisode, actions: Sequence[Action | int]
) -> tuple[list[int], EpisodeMetrics | None]:
    """Steps `actions` on a pipelined stream until the episode ends; returns the actions taken
    and, if the episode ended, its final metrics.
    """
    if not actions:
        return [], None
    async with await client.episode_stream(window=min(len(actions), 64)) as stream:
        results = (await stream.run({episode.id: actions}))[episode.id]
    taken: list[int] = []
    for action, result in zip(actions, results, strict=True):
        if isinstance(result, EsrpError):
            raise result
        taken.append(int(action))
        if result.ended:
            if result.metrics is None:
                raise ProtocolError("an ended step without metrics")
            return taken, result.metrics
    return taken, None


def expert_trajectory(scene_json: str) -> list[Action]:
    """The expert trajectory of a scene's JSON (`expert_trajectory`: action codes or API names)."""
    try:
        scene = json.loads(scene_json)
        trajectory = scene["expert_trajectory"]
        return [_API_CODES[a] if isinstance(a, str) else Action(a) for a in trajectory]
    except (ValueError, KeyError, TypeError) as error:
        raise ProtocolError(
            f"the privileged scene JSON holds no readable expert_trajectory: {error}"
        ) from None


async def _play_expert(client: AsyncClient, episode: AsyncEpisode) -> tuple[list[int], EpisodeMetrics | None]:
    trajectory = expert_trajectory((await episode.privileged_state()).scene_json)
    return await _take(client, episode, trajectory)


async def _play_plan(
    client: AsyncClient, episode: AsyncEpisode, settings: EvalSettings
) -> tuple[list[int], EpisodeMetrics | None, dict[str, Any]]:
    """ESRP-PLAN as the Rust agent plays it: the whole plan, stepped; asked again while the episode
    goes on (at most `replans` more calls); after a failure, the actions the planner took before
    failing are stepped and the planner asked again; no actions ends the episode's play.
    """
    actions: list[int] = []
    calls, nodes, seconds, relocated = 0, 0, 0.0, 0
    failure: tuple[str, str] | None = None
    metrics: EpisodeMetrics | None = None
    while calls <= settings.replans:
        calls += 1
        try:
            answer = await episode.plan_actions(0, settings.plan_budget_ms)
        except DeadlineExceeded as error:
            failure = ("deadline_exceeded", error.message)
            break
        if not answer.cached:
            nodes += answer.stats.nodes_expanded
            seconds += answer.stats.planning_seconds
            relocated += answer.stats.objects_relocated
        failure = None if answer.failure is None else (answer.failure.value, answer.failure_message)
        if not answer.actions:
            break
        taken, metrics = await _take(client, episode, answer.actions)
        actions.extend(taken)
        if metrics is not None:
            break
    stats = {
        "plan_calls": calls,
        "nodes_expanded": nodes,
        "planning_seconds": seconds,
        "objects_relocated": relocated,
        "failure": None if failure is None else failure[0],
        "failure_message": None if failure is None else failure[1],
    }
    return actions, metrics, stats


def agent_info(scene: SceneSummary, seed: int, episode_id: str) -> dict[str, Any]:
    """The `info` an agent's `reset` is given (see `esrp.agents.Agent.reset`)."""
    return {
        "scene_id": scene.id,
        "room_type": scene.room_type,
        "difficulty": None if scene.difficulty is None else scene.difficulty.value,
        "objects": scene.movable_objects,
        "horizon": scene.horizon,
        "split": None if scene.split is None else scene.split.value,
        "seed": seed,
        "episode_id": episode_id,
    }


async def _play_agent(
    episode: AsyncEpisode, factory: AgentFactory, settings: EvalSettings, seed: int
) -> tuple[list[int], EpisodeMetrics | None, dict[str, Any]]:
    """Plays an `Agent` or `AsyncAgent`: reset, then act and step until the episode ends or the agent
    returns None. Each observation is given the goal image of the first one.
    """
    agent: Any = factory(dict(settings.agent_config))
    asynchronous = is_async_agent(agent)
    first = episode.observation
    if first is None:
        raise ProtocolError("a created episode without its first observation")
    goal = first.goal_rgb
    info = agent_info(episode.scene, seed, episode.id)
    if asynchronous:
        await agent.reset(first, info)
    else:
        agent.reset(first, info)
    observation = first
    actions: list[int] = []
    metrics: EpisodeMetrics | None = None
    while True:
        action = await agent.act(observation) if asynchronous else agent.act(observation)
        if action is None:
            break
        result = await episode.step(action)
        code = action_value(action)
        assert code is not None, "an action the step took"
        actions.append(code)
        if result.ended:
            metrics = result.metrics
            if metrics is None:
                raise ProtocolError("an ended step without metrics")
            break
        observation = dataclasses.replace(result.observation, goal_rgb=goal)
    stats_method: Callable[[], Any] | None = getattr(agent, "stats", None)
    stats = as_json(dict(stats_method()), "its stats()") if callable(stats_method) else {}
    return actions, metrics, stats


def as_json(value: Any, where: str) -> Any:  # noqa: ANN401 - free-form agent statistics
    """`value` as a record can carry it: numpy scalars and arrays as numbers and lists, tuples as
    lists, and numbers JSON has no form for (NaN, infinities) as null. Raises `TypeError` naming
    `where` for anything else JSON cannot carry (an episode that fails, not a run that stops).
    """
    if value is None or isinstance(value, (bool, str, int)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (np.generic, np.ndarray)):
        return as_json(value.tolist(), where)
    if isinstance(value, (list, tuple)):
        return [as_json(v, where) for v in value]
    if isinstance(value, Mapping):
        if not all(isinstance(key, str) for key in value):
            raise TypeError(f"the agent's {where} has keys that are not strings: {list(value)!r}")
        return {key: as_json(v, where) for key, v in value.items()}
    raise TypeError(f"the agent's {where} holds a {type(value).__name__}, which a record cannot carry")


async def _play(
    client: AsyncClient, scene: SceneSummary, settings: EvalSettings, factory: AgentFactory | None, seed: int
) -> _Played:
    kind = settings.agent
    privileged = settings.plays_privileged()
    # A learned policy asks for the views it was trained on (`sensors`) unless the settings say.
    sensors = (settings.sensors or getattr(factory, "sensors", None)) if factory is not None else None
    # The agent's name, as the record's `agent` says it, labels the episode in the server's records.
    episode = await client.create_episode(scene.id, privileged=privileged, sensors=sensors, agent=kind)
    stats: dict[str, Any] = {}
    try:
        if kind == "expert":
            actions, metrics = await _play_expert(client, episode)
        elif kind == "plan":
            actions, metrics, stats = await _play_plan(client, episode, settings)
        else:
            assert factory is not None
            actions, metrics, stats = await _play_agent(episode, factory, settings, seed)
    except BaseException:
        # The agent's error comes first; the close is best effort.
        closing = asyncio.ensure_future(episode.close())
        # Cancelled while it closes (the run stops), the close goes on alone: its outcome is
        # taken when it ends, so that asyncio reports no "exception never retrieved".
        closing.add_done_callback(lambda task: task.cancelled() or task.exception())
        with contextlib.suppress(EsrpError, asyncio.CancelledError):
            await asyncio.shield(closing)
        raise
    closed = await episode.close()
    end = "agent" if metrics is None else _end_of(metrics)
    return _Played(episode.scene, metrics if metrics is not None else closed, actions, end, stats)


def check_config(config: Mapping[str, Any]) -> None:
    """Raises `EvalError` unless `config` (a record's `agent_config`) is plain JSON: every record
    carries it, so a value JSON has no form for (NaN, an object) is refused before any episode.
    """
    try:
        json.dumps(config, allow_nan=False)
    except (TypeError, ValueError) as error:
        raise EvalError(
            f"the agent config {config!r} is not plain JSON, which records carry: {error}"
        ) from None


def agent_factory(settings: EvalSettings) -> AgentFactory | None:
    """The factory of `settings.agent`'s agents; None for the server-driven `expert` and `plan`.
    Raises `EvalError` when a named module or callable cannot be loaded, or the config is bad (one
    the agent does not take, or one that is not plain JSON: `check_config`).
    """
    check_config(settings.recorded_config())
    return make_factory(settings.agent, settings.agent_config, settings.out)


def make_factory(agent: str, config: dict[str, Any], results_path: Path) -> AgentFactory | None:
    """The factory of agent `agent` (random, vlm, bc, ppo, map or MODULE:CALLABLE) with `config`; None
    for the server-driven `expert` and `plan`. `results_path` places a vlm agent's traces. Raises
    `EvalError` when a named module or callable cannot be loaded, or the config is bad.
    """
    if agent in ("expert", "plan") and config:
        raise EvalError(f"the {agent} agent takes no --agent-config: the server plays it")
    if agent == "random":
        return checked_config(RandomAgent, config)
    if agent == "vlm":
        from ..agents.vlm import VlmAgentFactory

        try:
            return VlmAgentFactory(config, results_path=results_path)
        except ValueError as error:
            raise EvalError(str(error)) from None
    if agent == "map":
        from ..agents.esrp_map.agent import MapAgent

        return checked_config(MapAgent, config)
    if agent in ("bc", "ppo"):
        try:
            from ..agents.bc import BcPolicy
            from ..agents.ppo import PpoPolicy
        except ImportError as error:
            raise EvalError(
                f"--agent {agent} needs the train extra (pip install 'esrp[train]'): {error}"
            ) from None
        try:
            policy = BcPolicy if agent == "bc" else PpoPolicy
            return policy(config)
        except ValueError as error:
            raise EvalError(str(error)) from None
    if agent not in BUILTIN_AGENTS:
        try:
            factory = load_factory(agent)
        except ValueError as error:
            raise EvalError(str(error)) from None
        return checked_factory(factory, agent, config)
    return None


def free_on_resume(settings: EvalSettings) -> frozenset[str]:
    """The agent's settings that a resumed run may change: its factory's `settings_free_on_resume`
    (`esrp.agents.AgentFactory`), read without making the factory; none for the others.
    """
    if settings.agent == "vlm":
        from ..agents.vlm import VlmAgentFactory

        return VlmAgentFactory.settings_free_on_resume
    if settings.agent in BUILTIN_AGENTS:
        return frozenset()
    try:
        factory = load_factory(settings.agent)
    except ValueError:
        return frozenset()  # said when the factory is made
    return frozenset(getattr(factory, "settings_free_on_resume", ()))


def checked_config(factory: AgentFactory, config: dict[str, Any]) -> AgentFactory:
    """`factory`, once an agent made by it with `config` has shown that the config is one it takes
    (its `ValueError` becomes an `EvalError`): before any episode, not once per episode.
    """
    try:
        factory(dict(config))
    except ValueError as error:
        raise EvalError(str(error)) from None
    return factory


def check_agent(agent: object, spec: str) -> None:
    """Raises `EvalError` unless `agent` (what `spec`'s factory returned) follows the `Agent` or
    `AsyncAgent` protocol: callable `reset` and `act`, both `async def` or neither.
    """
    wanted = "an esrp.agents.Agent, with reset(observation, info) and act(observation) methods"
    missing = [name for name in ("reset", "act") if not callable(getattr(agent, name, None))]
    if missing:
        what = "None" if agent is None else f"a {type(agent).__name__} object without {' or '.join(missing)}"
        raise EvalError(f"--agent {spec} returned {what}, not {wanted}")
    asynchronous = [inspect.iscoroutinefunction(getattr(agent, name)) for name in ("reset", "act")]
    if asynchronous[0] != asynchronous[1]:
        raise EvalError(
            f"--agent {spec} returned a {type(agent).__name__} whose reset and act are not both "
            "`async def` (an AsyncAgent) or both plain (an Agent)"
        )


def checked_factory(factory: AgentFactory, spec: str, config: dict[str, Any]) -> AgentFactory:
    """`factory`, called once here, before any episode, with `config`: raises `EvalError` when it
    raises or returns something that is not an agent (`check_agent`). The agent it made is handed
    to the first episode, so the factory is still called once per episode.
    """
    try:
        agent = factory(dict(config))
    except Exception as error:  # noqa: BLE001 - the user's factory: said in one line.
        raise EvalError(
            f"--agent {spec}: the factory raised {type(error).__name__}: {error}{raised_at(error)} "
            f"(called with the agent config {config})"
        ) from error
    check_agent(agent, spec)
    first: list[Agent | AsyncAgent] = [agent]

    def make(config: dict[str, Any]) -> Agent | AsyncAgent:
        return first.pop() if first else factory(config)

    return make


def episode_record(
    settings: EvalSettings, info: ServerInfo, scene: SceneSummary, seed: int, wall: float, played: _Played
) -> EpisodeRecord:
    """The `esrp.results/v1` record of an episode played on the server described by `info`."""
    m = played.metrics
    return EpisodeRecord(
        schema=SCHEMA,
        scene_id=scene.id,
        dataset=info.dataset,
        split=scene.split.value if scene.split is not None else "unknown",
        room_type=scene.room_type,
        difficulty=scene.difficulty.value if scene.difficulty is not None else "unknown",
        objects=scene.movable_objects,
        agent=settings.agent,
        agent_config=settings.recorded_config(),
        seed=seed if settings.seeded() else None,
        success=m.success,
        osr=m.object_success_rate,
        rdr=m.remaining_distance_ratio,
        stage=m.stage,
        placed=m.placed,
        steps=m.steps,
        horizon=played.scene.horizon,
        end=played.end,
        total_reward=m.total_reward,
        actions=played.actions,
        wall_seconds=wall,
        agent_stats=played.stats,
        server_version=info.version,
        client=CLIENT_NAME,
        finished_at=_now_rfc3339(),
        extra=privileged_mark(settings),
    )


def privileged_mark(settings: EvalSettings) -> dict[str, Any]:
    """The extra field of a run's records that says its agent read the privileged state, where its
    name does not say it (`{"privileged": true}` for an agent other than plan and expert run with
    `privileged`); `{}` otherwise.
    """
    return {"privileged": True} if settings.privileged and settings.agent not in ("plan", "expert") else {}


async def play_episode(
    client: AsyncClient,
    info: ServerInfo,
    scene: SceneSummary,
    settings: EvalSettings,
    factory: AgentFactory | None,
) -> EpisodeRecord:
    """Plays one episode of `scene` as `esrp eval` does and returns its record (errors propagate)."""
    seed = scene_seed(settings.seed, scene.id)
    clock = time.monotonic()
    played = await _play(client, scene, settings, factory, seed)
    return episode_record(settings, info, scene, seed, time.monotonic() - clock, played)


def missing_scene(
    wanted: str,
    split: str,
    difficulty: str | None,
    chosen: Mapping[str, SceneSummary],
    every: Sequence[SceneSummary],
) -> str:
    """Why `--scenes` id `wanted` is not among the `chosen` scenes (those of `split` and
    `difficulty`), with the full id where `wanted` is its end (`00003` for `esrp-bench-v1/00003`)
    and the split and difficulty of a scene the filters leave out.
    """
    where = f"{split}{'' if difficulty is None else ' ' + difficulty} scenes"
    known = {s.id: s for s in every}
    scene = known.get(wanted)
    if scene is None:
        ends = [s for s in every if s.id.endswith("/" + wanted)]
        if len(ends) != 1:
            example = f" (ids look like {every[0].id!r})" if every else ""
            return f"scene {wanted!r} is not in the served dataset{example}"
        scene = ends[0]
        if scene.id in chosen:
            return f"scene {wanted!r} is not a scene id: did you mean {scene.id!r}?"
    named = "" if scene.id == wanted else f" (did you mean {scene.id!r}?)"
    its_split = "unknown" if scene.split is None else scene.split.value
    its_difficulty = "unknown" if scene.difficulty is None else scene.difficulty.value
    return (
        f"scene {wanted!r}{named} is not among the {where} of this dataset: it is a {its_split} "
        f"{its_difficulty} scene (check --split and --difficulty)"
    )


async def pick_scenes(client: AsyncClient, settings: EvalSettings) -> list[SceneSummary]:
    """The scenes to run, fixed up front: the split's (filtered), or the ones named, in order."""
    listed = [s async for s in client.scenes(settings.split, settings.difficulty, page_size=1000)]
    if settings.scenes:
        by_id = {s.id: s for s in listed}
        missing = [s for s in settings.scenes if s not in by_id]
        if missing:
            every = [s async for s in client.scenes(page_size=1000)]
            raise EvalError(missing_scene(missing[0], settings.split, settings.difficulty, by_id, every))
        picked = [by_id[s] for s in settings.scenes]
    else:
        picked = listed
    if settings.limit is not None:
        picked = picked[: settings.limit]
    if not picked:
        raise EvalError(f"no scene matches: the {settings.split} split has none with these filters")
    return picked


@dataclasses.dataclass
class Resumed:
    """A run's results file, ready to append to (`open_results`).

    Attributes:
        records: The records the file holds of the run's scenes (the run appends its own).
        done: Scenes the file already holds.
        todo: The run's scenes still to play, in order.
        earlier: How many of the run's scenes the file already holds.
        tally: Their metrics, for the progress line.
    """

    records: list[EpisodeRecord]
    done: set[str]
    todo: list[SceneSummary]
    earlier: int
    tally: Tally


def open_results(
    settings: EvalSettings, scenes: Sequence[SceneSummary], free: frozenset[str] = frozenset()
) -> Resumed:
    """Prepares `settings.out` for a run over `scenes`: started over with `fresh`, else what an
    earlier run of the same agent and settings (but the agent's settings `free`) wrote is kept
    (`resume_records`) and said.
    """
    out = settings.out
    if settings.fresh and out.exists():
        out.unlink()
    out.parent.mkdir(parents=True, exist_ok=True)
    seed = settings.seed if settings.seeded() else None
    mark = privileged_mark(settings)
    records = resume_records(out, settings.agent, settings.recorded_config(), mark, seed, free=free)
    done = {r.scene_id for r in records}
    wanted = {s.id for s in scenes}
    earlier = sum(1 for r in records if r.scene_id in wanted)
    if earlier:
        print(f"resuming {out}: {earlier} of {len(scenes)} scenes already done", file=sys.stderr)
    todo = [s for s in scenes if s.id not in done]
    mine = [r for r in records if r.scene_id in wanted]
    return Resumed(mine, done, todo, earlier, Tally.of(mine))


def _bound(config: Mapping[str, Any], free: frozenset[str]) -> dict[str, Any]:
    """The settings of `config` that a resumed run must keep."""
    return {key: value for key, value in config.items() if key not in free}


def resume_records(
    path: Path,
    agent: str,
    config: dict[str, Any],
    mark: Mapping[str, Any] | None = None,
    seed: int | None = None,
    *,
    free: frozenset[str] = frozenset(),
) -> list[EpisodeRecord]:
    """What an earlier run wrote (a torn last line is cut off first). Refuses a file of another
    agent, or of the same agent with other settings (another model, budget, ...): one file, one run;
    and a file whose last line is whole (it ends with its newline) but not a record, which no
    interrupted write leaves (it is not cut off). `mark`: the run's `privileged_mark`, which the
    file's records must carry too (a privileged run and another are not mixed). `seed`: the base
    seed of a run whose agent draws random numbers (None for one that draws none): the file's
    records must have played with it (their per-scene seeds say so), and have been written by
    this tool, whose random numbers differ from the Rust `esrp-eval`'s for the same seed. `free`:
    the agent's settings that may differ (its factory's `settings_free_on_resume`).
    """
    if not path.exists():
        return []
    read = read_records(path)
    if read.compressed:
        raise EvalError(
            f"{path} is gzip-compressed: esrp eval appends to plain files (decompress it with gunzip to "
            "resume it, or write to another --out)"
        )
    if read.torn_whole:
        # Not what an interrupted append leaves (it never writes the newline without the rest):
        # a line of something else, which is not cut off.
        raise EvalError(
            f"{read.torn_note(path)}: is it a results file? Write to another --out, or pass --fresh "
            "to start it over"
        )
    if read.torn_tail:
        print(f"{path}: dropping a last line an interruption cut short", file=sys.stderr)
        truncate_to(path, read.complete_bytes)
    for record in read.records:
        if record.agent != agent:
            raise EvalError(
                f"{path} holds results of agent {record.agent!r}, not {agent!r}: write to another --out, "
                "or pass --fresh to start it over"
            )
        if _bound(record.agent_config, free) != _bound(config, free):
            may = f" (only {', '.join(sorted(free))} may change)" if free else ""
            raise EvalError(
                f"{path} holds results of agent {agent!r} with other settings ({record.agent_config}, not "
                f"{config}){may}: write to another --out, or pass --fresh to start it over"
            )
        if seed is not None:
            _check_seed(path, agent, record, seed)
        if bool(record.extra.get("privileged")) != bool((mark or {}).get("privileged")):
            had = "privileged" if record.extra.get("privileged") else "not privileged"
            raise EvalError(
                f"{path} holds results of agent {agent!r} played {had}, unlike this run (--privileged): "
                "write to another --out, or pass --fresh to start it over"
            )
    return read.records


def _tool(client: str) -> str:
    """The tool of a record's `client`, without its version: `esrp eval (Python)`, `esrp-eval`."""
    name, _, version = client.rpartition(" ")
    return name if name and version[:1].isdigit() else client


def _check_seed(path: Path, agent: str, record: EpisodeRecord, seed: int) -> None:
    """Raises `EvalError` unless `record` was played by this tool with base seed `seed`."""
    again = "write to another --out, or pass --fresh to start it over"
    if record.seed is None:
        raise EvalError(f"{path} holds results of agent {agent!r} without a seed, unlike this run: {again}")
    if _tool(record.client) != _tool(CLIENT_NAME):
        raise EvalError(
            f"{path} holds results of agent {agent!r} written by {record.client}, whose random numbers "
            f"differ from {_tool(CLIENT_NAME)}'s for the same seed: {again}"
        )
    base = record.seed ^ fnv1a64(record.scene_id)
    if base != seed % (1 << 64):  # scene_seed's 64 bits
        raise EvalError(
            f"{path} holds results of agent {agent!r} played with --seed {base}, not {seed}: {again}"
        )


def _running(tally: Tally) -> str:
    if tally.episodes == 0:
        return ""
    return f"SR {100 * tally.sr:.1f} %  OSR {100 * tally.osr:.1f} %  RDR {tally.rdr:.3f}"


class Progress:
    """tqdm on a terminal (episodes, ETA, running SR); a plain line every 5 % otherwise."""

    def __init__(self, total: int, done: int, enabled: bool, unit: str = "episode") -> None:
        self.total = total
        self.unit = unit
        self.position = done
        self.enabled = enabled
        self.every = max(total // 20, 1)
        self._bar: Any = None
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=total, initial=done, unit=unit, file=sys.stderr, dynamic_ncols=True)

    def note(self, message: str) -> None:
        if self._bar is not None:
            self._bar.write(message, file=sys.stderr)
        else:
            print(message, file=sys.stderr)

    def advance(self, status: Tally | str) -> None:
        """One more done; `status` (the running SR of a tally, or a text) beside the bar."""
        self.position += 1
        text = _running(status) if isinstance(status, Tally) else status
        if self._bar is not None:
            self._bar.set_postfix_str(text, refresh=False)
            self._bar.update(1)
        elif self.enabled and self.position % self.every == 0:
            print(f"{self.position}/{self.total} {self.unit}s  {text}", file=sys.stderr)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


async def server_gone(
    client: AsyncClient,
    local: LocalServer | None,
    done: int,
    *,
    what: str = "episodes",
    resume: str = "re-run the same command to resume",
) -> str | None:
    """Why a run cannot go on after a call found the server unavailable: the local server exited,
    or the server stayed unhealthy for `SERVER_RETRY_SECONDS`; None if it answers again. The
    message says how far the run got (`done` `what` of this run) and what to do (`resume`).
    """
    if local is not None and not local.is_running():
        return _local_exit(local, f"{done} {what}", resume)
    try:
        await client.wait_healthy(SERVER_RETRY_SECONDS)
    except EsrpError:
        if local is not None and not local.is_running():
            return _local_exit(local, f"{done} {what}", resume)
        return (
            f"the server at {client.address} has been unavailable for {SERVER_RETRY_SECONDS:.0f} s "
            f"after {done} {what} of this run; {resume} once it is back"
        )
    return None


def _local_exit(local: LocalServer, done: str, resume: str) -> str:
    code = local.process.poll() if local.process is not None else None
    if code is None:
        how = "stopped answering"
    else:
        how = f"exited with signal {-code}" if code < 0 else f"exited with status {code}"
    tail = "\n".join(part for part in (local.log_tail(10).strip(), local.stderr_tail(10).strip()) if part)
    lines = f"; its last log lines:\n{tail}\n" if tail else " (it logged nothing); "
    return f"the local esrp-server {how} after {done} of this run{lines}{resume}"


def errors_log_path(out: Path) -> Path:
    """The errors log of results file `out`: `out` with `.errors.log` (`results/mine.errors.log`)."""
    return out.with_suffix(".errors.log")


# The errors by which the server refuses a call for a reason the same call would meet again.
_REFUSALS = (SceneNotFound, InvalidRequest, EpisodeEnded, AlreadyPlayed, Unauthenticated, PermissionDenied)


class FailureLog:
    """The episodes of a run that failed with an error: the first one's traceback is printed, each
    one's is written to the errors log beside the results file (`errors_log_path`). The log
    describes the last run: an earlier run's is removed when the run starts. `refused` lists those
    the server refused for good (`EvalOutcome.refused`).
    """

    def __init__(self, out: Path, progress: Progress) -> None:
        self.path = errors_log_path(out)
        self.progress = progress
        self.failed: list[tuple[str, str]] = []
        self.refused: list[str] = []
        self.path.unlink(missing_ok=True)

    def add(self, scene_id: str, error: BaseException, trace: str | None = None) -> None:
        """Records that `scene_id`'s episode failed with `error` (`trace`: its traceback as text,
        where it is not `error`'s own, e.g. a Ray worker's).
        """
        message = f"{type(error).__name__}: {error}"
        if trace is None:
            trace = "".join(traceback.format_exception(type(error), error, error.__traceback__))
        if not self.failed:
            self.progress.note(
                f"{scene_id}: {message}\n{trace.rstrip()}\n(the first failure's traceback; "
                f"every failure's goes to {self.path})"
            )
        else:
            self.progress.note(f"{scene_id}: {message}")
        with open(self.path, "a", encoding="utf-8") as log:
            if not self.failed:
                log.write(f"# esrp eval: episodes that failed with an error, {_now_rfc3339()}\n")
            log.write(f"\n## {scene_id}: {message}\n\n{trace.rstrip()}\n")
        self.failed.append((scene_id, message))
        if isinstance(error, _REFUSALS):
            self.refused.append(scene_id)

    @property
    def written(self) -> Path | None:
        """The log's path, if any episode failed."""
        return self.path if self.failed else None


def summary_path_of(out: Path, summary: Path | None) -> Path:
    """Where the Markdown summary of results file `out` goes: `summary`, else `out` with `.md`.
    Raises `EvalError` when that is `out` itself (`--out run.md`, or `--summary` naming the results
    file): the summary would overwrite the results.
    """
    path = summary or out.with_suffix(".md")
    if path.absolute() == out.absolute():
        raise EvalError(
            f"the summary would overwrite the results in {out}: give --out a .jsonl file, or --summary "
            "another path"
        )
    return path


async def evaluate(
    client: AsyncClient, settings: EvalSettings, local: LocalServer | None = None
) -> EvalOutcome:
    """Runs `settings.agent` over the chosen scenes on `client`'s server; appends a record per
    finished episode to `settings.out`, writes the summary beside it, and returns what happened.
    Episodes that fail with an error are not recorded (a rerun retries them). A server that dies
    (`local`, the server started for the run, exits) or stays unreachable stops the run at once
    with `ServerGone`.
    """
    if settings.episodes_in_flight < 1:
        raise EvalError("--episodes-in-flight must be at least 1")
    if settings.agent == "plan" and not 1 <= settings.plan_budget_ms < 2**32:
        budget = settings.plan_budget_ms
        raise EvalError(f"--plan-budget-ms must be 1 to 4294967295 milliseconds, not {budget}")
    if settings.agent == "plan" and settings.replans < 0:
        raise EvalError(f"--replans must be at least 0, not {settings.replans}")
    summary_path_of(settings.out, settings.summary)
    factory = agent_factory(settings)
    info: ServerInfo = await client.server_info()
    print(
        f"esrp-server {info.version} at {client.address}: dataset {info.dataset}, "
        f"renderer {info.renderer_adapter}",
        file=sys.stderr,
    )
    scenes = await pick_scenes(client, settings)
    out = settings.out
    resumed = open_results(settings, scenes, free_on_resume(settings))
    records, todo, earlier, tally = resumed.records, resumed.todo, resumed.earlier, resumed.tally
    progress = Progress(len(scenes), earlier, settings.progress)
    failures = FailureLog(out, progress)
    written = 0
    started = time.monotonic()
    queue = iter(todo)

    async def worker(file: IO[bytes]) -> None:
        nonlocal written
        for scene in queue:  # shared: each scene is taken once, in order
            seed = scene_seed(settings.seed, scene.id)
            clock = time.monotonic()
            try:
                played = await _play(client, scene, settings, factory, seed)
            except Exception as error:  # noqa: BLE001 - reported, not recorded; a rerun retries it.
                if isinstance(error, ServerUnavailable):
                    gone = await server_gone(client, local, written, resume=settings.resume)
                    if gone is not None:
                        raise ServerGone(gone) from error
                stopped = stops_the_run(scene.id, error, written)
                if stopped is not None:
                    raise stopped from error
                failures.add(scene.id, error)
                progress.advance(tally)
                continue
            record = episode_record(settings, info, scene, seed, time.monotonic() - clock, played)
            append_record(file, record)
            written += 1
            records.append(record)
            tally.add(record)
            progress.advance(tally)

    try:
        with open(out, "ab") as file:
            # One worker that stops the run (ServerGone, a signal) stops the others with it before
            # the file closes.
            workers = min(settings.episodes_in_flight, max(len(todo), 1))
            await run_workers(workers, lambda: worker(file))
    finally:
        progress.close()
        close = getattr(factory, "aclose", None)  # a factory holding a connection (vlm)
        if close is not None:
            await close()

    return finish(settings, info, records, written, failures, time.monotonic() - started)


def finish(
    settings: EvalSettings,
    info: ServerInfo,
    mine: list[EpisodeRecord],
    written: int,
    failures: FailureLog,
    seconds: float,
) -> EvalOutcome:
    """Prints the summary of a run's records (`mine`: those of its scenes), writes it as Markdown
    beside the results file, and returns the outcome.
    """
    summary = Summary.of(mine, settings.agent)
    failed = f", {len(failures.failed)} more failed (not recorded)" if failures.failed else ""
    print(f"{settings.agent} on {len(mine)} scenes of {info.dataset}{failed} ({seconds:.0f} s):")
    print(summary.text(), end="")
    summary_path = summary_path_of(settings.out, settings.summary)
    markdown = summary.markdown(f"{settings.agent} on {info.dataset} ({settings.split} split)")
    markdown += (
        f"\nWritten by {CLIENT_NAME} against esrp-server {info.version} ({info.renderer_adapter} renderer) "
        f"on {_now_rfc3339()}; results in `{settings.out.name}`.\n"
    )
    summary_path.write_text(markdown, encoding="utf-8")
    print(f"summary: {summary_path}")
    return EvalOutcome(
        mine, written, failures.failed, summary, summary_path, failures.written, failures.refused
    )


def run_eval(
    settings: EvalSettings,
    *,
    server: str | None = None,
    token: str | None = None,
    server_args: Sequence[str] = (),
) -> EvalOutcome:
    """`evaluate` against `server` (`host:port`), or against a `LocalServer` started for the run
    (with `server_args`) and stopped at its end.
    """

    async def main(address: str, local: LocalServer | None = None) -> EvalOutcome:
        async with AsyncClient(address, token=token, timeout=120) as client:
            if server is not None:
                await reach(client, server)
            await client.wait_healthy(30)
            return await evaluate(client, settings, local)

    if server is not None:
        return run_async(main(server))
    with LocalServer(*server_args, unix_socket="auto") as local:
        return run_async(main(local.address, local))


async def reach(client: AsyncClient, address: str) -> None:
    """One call to the server `address` names, which fails at once (`EvalError`, naming the address
    as gRPC read it) when nothing answers there, instead of waiting for it to become healthy.
    """
    try:
        await client.server_info()
    except ServerUnavailable as error:
        raise EvalError(unreachable(address, error)) from None


def format_failures(
    failed: Sequence[tuple[str, str]], errors_log: Path | None = None, refused: Collection[str] = ()
) -> str:
    """The closing message of a run with failed episodes: those a rerun may play, those among
    `refused` it would be refused again (`EvalOutcome.refused`), and where their tracebacks are.
    The same words as `esrp-eval`'s.
    """
    retry = sorted(scene for scene, _ in failed if scene not in refused)
    again = sorted(scene for scene, _ in failed if scene in refused)
    n, m = len(retry), len(again)

    def one(count: int, single: str, plural: str) -> str:
        # The words agree with the count: "1 episode ... was ... it", "2 episodes ... were ... them".
        return single if count == 1 else plural

    retry_text = (
        f"{n} {one(n, 'episode', 'episodes')} failed with an error and {one(n, 'was', 'were')} not "
        f"recorded (rerun to retry {one(n, 'it', 'them')}): " + ", ".join(retry)
    )
    again_text = f"refused by the server and not recorded, as {one(m, 'it', 'they')} would be again: "
    again_text += ", ".join(again)
    where = f"; tracebacks in {errors_log}" if errors_log is not None else ""
    if not again:
        return retry_text + where
    if not retry:
        return f"{m} {one(m, 'episode', 'episodes')} {one(m, 'was', 'were')} {again_text}{where}"
    return f"{retry_text}; {m} more {one(m, 'was', 'were')} {again_text}{where}"
