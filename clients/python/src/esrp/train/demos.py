"""`esrp demos export`: the benchmark's expert demonstrations, replayed through the server, written
as a zarr store that training reads a window at a time (docs/demonstrations.md has the format).

Each scene's expert trajectory (in its privileged scene JSON) is stepped on the server; the store
gets, per step, the observation the agent saw before acting (ego view, grasp flag) and the expert's
action, and per episode the goal image and the scene id. Episodes are appended whole, in the order
of the scenes chosen; an interrupted export resumes where it stopped (a partly written episode is
cut off first), and the store records the dataset, split and resolution it was made with.

With `dagger` (DAgger's data collection), another policy drives instead: at every state it visits,
the server's planner (`PlanActions`) gives the label, the action the store records, and the
policy's own action is the one stepped (the label with probability `beta`), and the store records
it too (`data/policy_action`), so that how often the policy agreed with the planner can be read
back. An episode ends when the episode does (success or the horizon), when the policy stops, after
`max_steps` recorded states, or when the planner finds no way on from the state within its budget
(that state then has no label and is not recorded). The store also records, per state, the first
`label_horizon` actions of the planner's plan from it (`data/label_chunk`, `NO_ACTION` past the
plan's end): the action chunk a policy trained on the store learns there, one plan from one state.

With `records` (`esrp.results/v1` files: e.g. the server's records of people playing in its web
viewer, agent `human`), each record's `actions` are stepped instead, on a new, non-privileged episode
of its scene with its horizon: the store gets what that agent saw before each of its actions and the
actions themselves. The replay must reproduce the record (the simulator is deterministic; the checks
are `esrp verify`'s), else the export stops before the episode is written.

`episodes_in_flight` plays that many of the chosen scenes' episodes at a time (threads sharing the
client); they are still written in the scenes' order, and each one's steps depend on its own scene
and seed alone, so the store is the one an export of one episode at a time writes. On a few cores
it overlaps the server's work (rendering, a DAgger label's planning) with the client's (a policy's
forward pass) instead of waiting for each in turn.
"""

from __future__ import annotations

import asyncio
import dataclasses
import sys
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from .._client import Client
from .._errors import DeadlineExceeded, EsrpError
from .._values import Action, SceneSummary, Sensors
from ..agents import is_async_agent
from ..eval.evaluation import EvalError, agent_info, expert_trajectory, make_factory, missing_scene
from ..eval.results import ResultsError, read_records, scene_seed
from ..eval.verify import Numbered, compare

__all__ = [
    "FORMAT",
    "REPLAY_LABEL",
    "DemoExportError",
    "DemoSettings",
    "ExportOutcome",
    "RecordSource",
    "export_demos",
    "pick_scenes",
    "read_sources",
]

FORMAT = "esrp.demos/v1"
"""The store's `format` attribute."""

REPLAY_LABEL = "esrp demos export"
"""The agent label of a records export's replays (`CreateEpisodeRequest.agent`, in a server's records)."""

CHUNK_STEPS = 256
"""Steps per chunk of the per-step arrays (a chunk of ego views is 256 × 49,152 bytes, 12 MB raw)."""

NO_ACTION = 255
"""`data/policy_action` of a state where the DAgger policy gave no action (it stopped there)."""


class DemoExportError(Exception):
    """The export cannot run as asked (a store of another dataset or resolution, no scenes)."""


MIN_RESOLUTION = 16
"""The smallest view side a server renders (0 asks for its default, 128)."""


def check_resolution(resolution: int, most: int) -> None:
    """Raises `DemoExportError` unless `resolution` is 0 (the server's default) or from
    `MIN_RESOLUTION` to `most` (the server's `limits.max_resolution`): checked before anything is
    written, so that a store is never stamped with a resolution no episode can be played at.
    """
    if resolution != 0 and not MIN_RESOLUTION <= resolution <= most:
        raise DemoExportError(
            f"--resolution {resolution} is out of range: use {MIN_RESOLUTION} to {most} pixels (0 means 128)"
        )


@dataclass
class DemoSettings:
    """What `esrp demos export` writes; the fields are its flags.

    Attributes:
        out: The zarr store (a folder, created if missing, resumed if present).
        split: The split whose scenes to export.
        difficulty: Only scenes of this difficulty.
        scenes: Only these scene ids, in this order.
        limit: At most this many scenes (after the filters).
        resolution: The views' side in pixels (0: the server's default, 128).
        progress: Print a line every 5 % of the scenes.
        dagger: The agent whose visited states get the planner's labels (random, bc, ppo, vlm or
            MODULE:CALLABLE, as `esrp eval --agent`); None: the expert's demonstrations.
        agent_config: The dagger agent's config (`checkpoint` for bc and ppo).
        beta: With `dagger`, the probability that the planner's label, not the agent's action, is
            stepped (DAgger's mixing; 0: the agent alone).
        seed: With `dagger`, the base seed: scene `id` plays with `seed XOR fnv1a64(id)`.
        plan_budget_ms: With `dagger`, the planning budget of each label, 1 to 2³²−1 milliseconds.
        label_horizon: With `dagger`, how many of the plan's first actions each state records
            (`data/label_chunk`): the trained policy's action horizon.
        max_steps: With `dagger`, at most this many states recorded per episode (the episode is
            closed there); 0: until it ends.
        records: `esrp.results/v1` files whose records' actions to replay and record, instead of
            the chosen scenes' expert trajectories (`split`, `difficulty`, `scenes` and `dagger`
            do not apply).
        agent: With `records`, only the records of this agent (`human`: people in the web viewer).
        successful_only: With `records`, only the records of successful episodes.
        episodes_in_flight: Without `records`, how many episodes play at a time (the store is the
            same as with 1: see the module's docstring).
    """

    out: Path
    split: str = "train"
    difficulty: str | None = None
    scenes: Sequence[str] = ()
    limit: int | None = None
    resolution: int = 0
    progress: bool = True
    dagger: str | None = None
    agent_config: dict[str, Any] = field(default_factory=dict)
    beta: float = 0.0
    seed: int = 0
    plan_budget_ms: int = 10_000
    label_horizon: int = 8
    max_steps: int = 0
    records: Sequence[Path] = ()
    agent: str | None = None
    successful_only: bool = False
    episodes_in_flight: int = 1

    @property
    def labels(self) -> str:
        """Whose actions the store records: `expert`, `planner` or `records` (the records' agents)."""
        if self.records:
            return "records"
        return "expert" if self.dagger is None else "planner"


@dataclass
class ExportOutcome:
    """What an export did: episodes and steps in the store, and how many episodes this run added.

    Attributes:
        episodes: Episodes in the store.
        steps: Steps in the store.
        added: Episodes this run added.
        compared: A DAgger store's states where the policy gave an action (None for other stores,
            and for DAgger stores made before `data/policy_action` existed).
        agreed: Of those, the states where the policy's action was the planner's label.
        skipped: Scenes of a DAgger export left out because the planner found no plan from their
            start (no state of theirs has a label).
    """

    episodes: int
    steps: int
    added: int
    compared: int | None = None
    agreed: int | None = None
    skipped: tuple[str, ...] = ()

    @property
    def agreement(self) -> float | None:
        """The fraction of a DAgger store's states where the policy's action was the label."""
        if self.compared is None or self.agreed is None or self.compared == 0:
            return None
        return self.agreed / self.compared


def pick_scenes(client: Client, settings: DemoSettings) -> list[SceneSummary]:
    """The scenes `settings` chooses (split, difficulty, ids, limit), in order; `DemoExportError`
    when none matches, a named one is missing or one is named twice.
    """
    twice = sorted({scene for scene in settings.scenes if list(settings.scenes).count(scene) > 1})
    if twice:
        raise DemoExportError(f"scenes lists {', '.join(twice)} more than once (a scene is exported once)")
    listed = list(client.scenes(settings.split, settings.difficulty, page_size=1000))
    if settings.scenes:
        by_id = {s.id: s for s in listed}
        missing = [s for s in settings.scenes if s not in by_id]
        if missing:
            every = list(client.scenes(page_size=1000))
            raise DemoExportError(
                missing_scene(missing[0], settings.split, settings.difficulty, by_id, every)
            )
        listed = [by_id[s] for s in settings.scenes]
    if settings.limit is not None:
        listed = listed[: settings.limit]
    if not listed:
        raise DemoExportError(f"no scene matches: the {settings.split} split has none with these filters")
    return listed


_Item = TypeVar("_Item")
_Played = TypeVar("_Played")


def _in_order(
    play: Callable[[_Item], _Played], items: Sequence[_Item], workers: int
) -> Iterator[tuple[_Item, _Played]]:
    """`(item, play(item))` for each of `items` in their order, `workers` of them played at a time on
    threads (in the caller's thread, one by one, with 1). An error of `play` is raised at its item's
    turn; the items not started by then (or when the caller stops iterating) are not played, and
    those already playing are waited for.
    """
    if workers <= 1:
        for item in items:
            yield item, play(item)
        return
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="esrp-export") as pool:
        pending: deque[tuple[_Item, Future[_Played]]] = deque()
        try:
            for item in items:
                pending.append((item, pool.submit(play, item)))
                if len(pending) == workers:
                    first, future = pending.popleft()
                    yield first, future.result()
            while pending:
                first, future = pending.popleft()
                yield first, future.result()
        finally:
            for _, future in pending:
                future.cancel()


_Episode = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""One episode's goal image, ego views, grasp flags and actions."""


@dataclass
class _DaggerEpisode:
    """A DAgger episode: what the store records of any episode, and the policy's own actions
    (`NO_ACTION` where it gave none).
    """

    episode: _Episode
    policy_actions: np.ndarray
    label_chunks: np.ndarray
    """(states, label_horizon): the plan's first actions from each state, `NO_ACTION` past its end."""


class _Store:
    """The zarr group and its arrays; `episode_ends` is written last, so it says what is whole."""

    def __init__(
        self,
        path: Path,
        dataset: str,
        resolution: int,
        labels: str,
        policy: str | None,
        label_horizon: int | None = None,
        split: str | None = None,
    ) -> None:
        import zarr

        if path.is_dir() and any(path.iterdir()) and not (path / "zarr.json").exists():
            raise DemoExportError(
                f"{path} is a folder of other files, not an {FORMAT} store: write to a new or empty --out"
            )
        self.group: Any = zarr.open_group(str(path), mode="a")
        attrs = dict(self.group.attrs)
        ends: Any = self.group.get("meta/episode_ends", None)
        held_episodes = ends is not None and ends.shape[0] > 0
        wanted = {"dataset": dataset, "resolution": resolution, "labels": labels, "policy": policy}
        if (
            attrs.get("format") == FORMAT
            and not held_episodes
            and any(
                attrs.get(key, "expert" if key == "labels" else None) != value
                for key, value in wanted.items()
            )
        ):
            # Stamped by a run that wrote no episode (refused, or stopped before its first): it holds
            # nothing, so this run's settings replace its own.
            self.group = zarr.open_group(str(path), mode="w")
            attrs = {}
        if attrs:
            if attrs.get("format") != FORMAT:
                raise DemoExportError(f"{path} is not an {FORMAT} store (format {attrs.get('format')!r})")
            held_split = attrs.get("split")
            if split is not None and held_split is not None and held_split != split:
                raise DemoExportError(
                    f"{path} holds scenes of the {held_split} split, not {split}: write to another --out"
                )
            if attrs.get("dataset") != dataset or attrs.get("resolution") != resolution:
                raise DemoExportError(
                    f"{path} holds demonstrations of {attrs.get('dataset')} at {attrs.get('resolution')} px, "
                    f"not {dataset} at {resolution} px: write to another --out"
                )
            # Stores written before DAgger existed hold the expert's actions.
            held_labels, held_policy = str(attrs.get("labels", "expert")), attrs.get("policy")
            if (held_labels, held_policy) != (labels, policy):
                held = _describe(held_labels, None if held_policy is None else str(held_policy))
                raise DemoExportError(
                    f"{path} holds {held}, not {_describe(labels, policy)}: use another --out"
                )
        else:
            self.group.attrs.update(
                {"format": FORMAT, "dataset": dataset, "resolution": resolution, "labels": labels}
            )
            if policy is not None:
                self.group.attrs["policy"] = policy
            if split is not None:
                self.group.attrs["split"] = split
        side = resolution

        def array(name: str, shape: tuple[int, ...], dtype: str, chunk: int) -> Any:  # noqa: ANN401
            if name in self.group:
                return self.group[name]
            return self.group.create_array(name, shape=(0, *shape), chunks=(chunk, *shape), dtype=dtype)

        self.ego = array("data/ego_rgb", (side, side, 3), "uint8", CHUNK_STEPS)
        self.grasping = array("data/grasping", (), "bool", 4096)
        self.action = array("data/action", (), "uint8", 4096)
        self.goal = array("meta/goal_rgb", (side, side, 3), "uint8", 16)
        self.ends = array("meta/episode_ends", (), "int64", 4096)
        # A DAgger store records the policy's own actions too; one made before they were recorded
        # goes on without them (its first episodes have none).
        self.policy_action: Any = None
        if labels == "planner" and ("data/policy_action" in self.group or self.ends.shape[0] == 0):
            self.policy_action = array("data/policy_action", (), "uint8", 4096)
        # And the plan's first actions at each state; a store made before they were recorded (its
        # states have the next action alone) cannot take episodes that have them.
        self.label_chunk: Any = None
        if labels == "planner" and label_horizon is not None:
            if "data/label_chunk" not in self.group and self.ends.shape[0] > 0:
                raise DemoExportError(
                    f"{path} holds planner labels of one action per state (made before label chunks "
                    "were recorded): write to another --out"
                )
            self.label_chunk = array("data/label_chunk", (label_horizon,), "uint8", 4096)
            if self.label_chunk.shape[1] != label_horizon:
                raise DemoExportError(
                    f"{path} holds the plan's first {self.label_chunk.shape[1]} actions per state, not "
                    f"{label_horizon}: pass --label-horizon {self.label_chunk.shape[1]} or another --out"
                )
        listed = self.group.attrs.get("scene_ids", [])
        self.scene_ids: list[str] = [str(s) for s in listed] if isinstance(listed, list) else []
        # A records export says each episode's agent too (parallel to `scene_ids`).
        self.agents: list[str] | None = None
        if labels == "records":
            agents = self.group.attrs.get("agents", [])
            self.agents = [str(a) for a in agents] if isinstance(agents, list) else []
        self._cut_torn()

    def _cut_torn(self) -> None:
        """Drops what an interrupted run wrote past the last whole episode."""
        episodes = self.ends.shape[0]
        steps = int(self.ends[episodes - 1]) if episodes else 0
        per_step = [self.ego, self.grasping, self.action]
        if self.policy_action is not None:
            per_step.append(self.policy_action)
        if self.label_chunk is not None:
            per_step.append(self.label_chunk)
        for array in per_step:
            if array.shape[0] != steps:
                array.resize((steps, *array.shape[1:]))
        if self.goal.shape[0] != episodes:
            self.goal.resize((episodes, *self.goal.shape[1:]))
        if len(self.scene_ids) != episodes:
            self.scene_ids = self.scene_ids[:episodes]
            self.group.attrs["scene_ids"] = self.scene_ids
        if self.agents is not None and len(self.agents) != episodes:
            self.agents = self.agents[:episodes]
            self.group.attrs["agents"] = self.agents

    @property
    def steps(self) -> int:
        return int(self.ends[self.ends.shape[0] - 1]) if self.ends.shape[0] else 0

    def append(
        self,
        scene_id: str,
        episode: _Episode,
        agent: str | None = None,
        policy_actions: np.ndarray | None = None,
        label_chunks: np.ndarray | None = None,
    ) -> None:
        """Appends a whole episode: (goal, ego views, grasp flags, actions), in a records store the
        `agent` whose episode it is, and in a DAgger store the policy's own actions and the plan's
        first actions at each state.
        """
        goal, ego, grasping, actions = episode
        end = self.steps + len(actions)
        if self.policy_action is not None:
            if policy_actions is None or len(policy_actions) != len(actions):
                raise ValueError("a DAgger episode comes with one policy action per label")
            self.policy_action.append(policy_actions, axis=0)
        if self.label_chunk is not None:
            if label_chunks is None or len(label_chunks) != len(actions):
                raise ValueError("a DAgger episode comes with one plan chunk per label")
            self.label_chunk.append(label_chunks, axis=0)
        self.ego.append(ego, axis=0)
        self.grasping.append(grasping, axis=0)
        self.action.append(actions, axis=0)
        self.goal.append(goal[None], axis=0)
        self.scene_ids.append(scene_id)
        self.group.attrs["scene_ids"] = self.scene_ids
        if self.agents is not None:
            self.agents.append("" if agent is None else agent)
            self.group.attrs["agents"] = self.agents
        self.ends.append(np.array([end], dtype=np.int64), axis=0)  # last: the episode is whole

    def agreement(self) -> tuple[int, int] | None:
        """(states where the policy gave an action, those where it was the label) over the whole
        store; None when it does not record the policy's actions.
        """
        if self.policy_action is None:
            return None
        steps = self.steps
        policy = np.asarray(self.policy_action[:steps])
        labels = np.asarray(self.action[:steps])
        acted = policy != NO_ACTION
        return int(acted.sum()), int((policy[acted] == labels[acted]).sum())

    def episode_actions(self, index: int) -> list[int]:
        """The actions of whole episode `index`."""
        start = int(self.ends[index - 1]) if index else 0
        return [int(a) for a in self.action[start : int(self.ends[index])]]


def _describe(labels: str, policy: str | None) -> str:
    if labels == "records":
        return "recorded episodes (--records)"
    return "expert demonstrations" if labels == "expert" else f"planner labels on states of {policy}"


def _replay(
    client: Client, scene: SceneSummary, resolution: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps the expert trajectory of `scene`: (goal, ego views, grasp flags, actions)."""
    sensors = Sensors(resolution=resolution) if resolution else None
    with client.create_episode(scene.id, privileged=True, sensors=sensors) as episode:
        actions = expert_trajectory(episode.privileged_state().scene_json)
        first = episode.observation
        if first is None or first.goal_rgb is None:
            raise DemoExportError(f"{scene.id}: the created episode came without its first observation")
        egos = [first.ego_rgb]
        grasps = [first.grasping]
        for i, action in enumerate(actions):
            result = episode.step(action)
            ended = result.terminated or result.truncated
            if ended and i != len(actions) - 1:
                raise DemoExportError(
                    f"{scene.id}: the expert trajectory ended the episode after {i + 1} steps"
                )
            if not ended:
                egos.append(result.observation.ego_rgb)
                grasps.append(result.observation.grasping)
            elif not result.terminated:
                raise DemoExportError(f"{scene.id}: the expert trajectory does not succeed")
        if len(egos) != len(actions):
            raise DemoExportError(f"{scene.id}: the expert trajectory does not end the episode")
        return (
            np.array(first.goal_rgb),
            np.stack(egos),
            np.array(grasps, dtype=bool),
            np.array([int(a) for a in actions], dtype=np.uint8),
        )


def _dagger(
    client: Client,
    scene: SceneSummary,
    settings: DemoSettings,
    factory: Any,  # noqa: ANN401
) -> _DaggerEpisode | None:
    """Runs `settings.dagger`'s agent on `scene` and labels each state it visits with the planner's
    plan from it: (goal, ego views, grasp flags, labels: each plan's first action), the agent's own
    actions and each plan's first `label_horizon` actions; None when the planner finds no plan from
    the scene's start (no state has a label).
    """
    sensors = Sensors(resolution=settings.resolution) if settings.resolution else None
    seed = scene_seed(settings.seed, scene.id)
    rng = np.random.default_rng(seed)
    loop = asyncio.new_event_loop()
    try:
        with client.create_episode(scene.id, privileged=True, sensors=sensors) as episode:
            first = episode.observation
            if first is None or first.goal_rgb is None:
                raise DemoExportError(f"{scene.id}: the created episode came without its first observation")
            agent = factory(dict(settings.agent_config))
            asynchronous = is_async_agent(agent)

            def call(result: Any) -> Any:  # noqa: ANN401 - an agent's answer
                return loop.run_until_complete(result) if asynchronous else result

            call(agent.reset(first, agent_info(episode.scene, seed, episode.id)))
            observation = first
            egos: list[np.ndarray] = []
            grasps: list[bool] = []
            labels: list[int] = []
            chunks: list[list[int]] = []
            policy: list[int] = []
            while not settings.max_steps or len(labels) < settings.max_steps:
                try:
                    answer = episode.plan_actions(
                        max_actions=settings.label_horizon, budget_ms=settings.plan_budget_ms
                    )
                except DeadlineExceeded:
                    break  # no plan within the budget: this state has no label
                if not answer.actions:
                    break  # no way on from here: this state has no label
                label = int(answer.actions[0])
                plan = [int(a) for a in answer.actions[: settings.label_horizon]]
                chunks.append(plan + [NO_ACTION] * (settings.label_horizon - len(plan)))
                egos.append(observation.ego_rgb)
                grasps.append(observation.grasping)
                labels.append(label)
                action = call(agent.act(observation))
                if action is None:
                    policy.append(NO_ACTION)
                    break
                own = int(Action(int(action)))
                policy.append(own)
                stepped = label if rng.random() < settings.beta else own
                result = episode.step(stepped)
                if result.terminated or result.truncated:
                    break
                observation = dataclasses.replace(result.observation, goal_rgb=first.goal_rgb)
    finally:
        loop.close()
    if not labels:
        return None  # the planner found no plan from the scene's start: nothing to label
    recorded = (
        np.array(first.goal_rgb),
        np.stack(egos),
        np.array(grasps, dtype=bool),
        np.array(labels, dtype=np.uint8),
    )
    chunked = np.array(chunks, dtype=np.uint8).reshape(-1, settings.label_horizon)
    return _DaggerEpisode(recorded, np.array(policy, dtype=np.uint8), chunked)


# A record to export and where it was read (file and line): verify's `Numbered`, one type for both.
RecordSource = Numbered


def read_sources(settings: DemoSettings) -> list[RecordSource]:
    """The records of `settings.records` to export, in file order: those of `settings.agent` (all
    without it), successful ones only with `successful_only`, at most `limit`; records without
    actions hold no step and are left out. Raises `DemoExportError` for a file that cannot be read
    or is not `esrp.results/v1` (a last line too, when it is whole: only a line cut short by an
    interrupted write is said on stderr and left out), and when no record is left.
    """
    sources: list[RecordSource] = []
    for path in settings.records:
        try:
            read = read_records(path)
        except OSError as error:
            raise DemoExportError(f"cannot read {path}: {error.strerror or error}") from None
        except ResultsError as error:
            raise DemoExportError(str(error)) from None
        if read.torn_whole:  # a whole line that is not a record: not an interrupted write
            raise DemoExportError(read.torn_note(path))
        if read.torn_tail:
            print(f"esrp demos export: {read.torn_note(path)} (left out)", file=sys.stderr)
        sources += [
            RecordSource(Path(path), n, r) for n, r in zip(read.line_numbers, read.records, strict=True)
        ]
    kept = [
        source
        for source in sources
        if (settings.agent is None or source.record.agent == settings.agent)
        and (source.record.success or not settings.successful_only)
        and source.record.actions
    ]
    if settings.limit is not None:
        kept = kept[: settings.limit]
    if not kept:
        filters = [f"agent {settings.agent!r}"] if settings.agent is not None else []
        filters += ["successful"] if settings.successful_only else []
        which = f" ({', '.join(filters)}, with actions)" if filters else " with actions"
        raise DemoExportError(
            f"no record to export: the records files hold {len(sources)} records, none{which}"
        )
    return kept


def _replay_record(client: Client, source: RecordSource, resolution: int) -> _Episode:
    """Steps `source`'s actions on a new, non-privileged episode of its scene with its horizon:
    (goal, ego views, grasp flags, actions). Raises `DemoExportError` naming the record when the
    replay does not reproduce it.
    """
    record = source.record
    what = f"{source.where}: {record.scene_id}"
    sensors = Sensors(resolution=resolution) if resolution else None
    actions = record.actions
    try:
        with client.create_episode(
            record.scene_id, horizon=record.horizon, sensors=sensors, agent=REPLAY_LABEL
        ) as episode:
            first = episode.observation
            if first is None or first.goal_rgb is None:
                raise DemoExportError(f"{what}: the created episode came without its first observation")
            egos = [first.ego_rgb]
            grasps = [first.grasping]
            metrics = None
            ended_after: int | None = None
            for k, action in enumerate(actions, start=1):
                result = episode.step(action)
                if result.ended:
                    metrics, ended_after = result.metrics, k
                    break
                if k < len(actions):
                    egos.append(result.observation.ego_rgb)
                    grasps.append(result.observation.grasping)
            if metrics is None and ended_after is None:
                metrics = episode.close()  # still running after the last action: the agent ended it
    except EsrpError as error:
        raise DemoExportError(f"{what}: the replay failed: {type(error).__name__}: {error.message}") from None
    different = (
        ["the server answered no final metrics"] if metrics is None else compare(record, metrics, ended_after)
    )
    if different:
        raise DemoExportError(
            f"{what}: the replay does not reproduce the record ({'; '.join(different)}): nothing of it "
            "was written"
        )
    return (
        np.array(first.goal_rgb),
        np.stack(egos),
        np.array(grasps, dtype=bool),
        np.array(actions, dtype=np.uint8),
    )


def _export_records(
    client: Client, settings: DemoSettings, sources: Sequence[RecordSource] | None
) -> ExportOutcome:
    """`export_demos` with `settings.records`."""
    if settings.dagger is not None:
        raise DemoExportError("--records and --dagger do not go together")
    if settings.scenes or settings.difficulty is not None:
        raise DemoExportError("--records replaces the scene choice: no --scenes or --difficulty with it")
    info = client.server_info()
    check_resolution(settings.resolution, info.limits.max_resolution)
    chosen = list(sources) if sources is not None else read_sources(settings)
    for source in chosen:
        if source.record.dataset != info.dataset:
            raise DemoExportError(
                f"{source.where}: {source.record.scene_id}: the record is of dataset "
                f"{source.record.dataset!r}, the server serves {info.dataset!r} "
                "(start a server of that dataset)"
            )
    resolution = settings.resolution or 128
    store = _Store(settings.out, info.dataset, resolution, settings.labels, None)
    held = len(store.scene_ids)
    if held:
        agents = store.agents or []
        same = held <= len(chosen) and all(
            (store.scene_ids[i], agents[i] if i < len(agents) else None, store.episode_actions(i))
            == (chosen[i].record.scene_id, chosen[i].record.agent, chosen[i].record.actions)
            for i in range(held)
        )
        if not same:
            raise DemoExportError(
                f"{settings.out} holds other episodes than the first {held} of these records: "
                "use another --out"
            )
        print(f"resuming {settings.out}: {held} of {len(chosen)} records already there", file=sys.stderr)
    every = max(len(chosen) // 20, 1)
    for position, source in enumerate(chosen[held:], start=held + 1):
        store.append(
            source.record.scene_id, _replay_record(client, source, settings.resolution), source.record.agent
        )
        if settings.progress and (position % every == 0 or position == len(chosen)):
            print(f"{position}/{len(chosen)} episodes, {store.steps} steps", file=sys.stderr)
    return ExportOutcome(len(store.scene_ids), store.steps, len(chosen) - held)


def export_demos(
    client: Client, settings: DemoSettings, sources: Sequence[RecordSource] | None = None
) -> ExportOutcome:
    """Exports the expert demonstrations of the chosen scenes into `settings.out` (resuming it); with
    `settings.records`, those records' episodes (`sources`: the records `read_sources` chose, read
    here when None).
    """
    if settings.records:
        return _export_records(client, settings, sources)
    info = client.server_info()
    check_resolution(settings.resolution, info.limits.max_resolution)
    scenes = pick_scenes(client, settings)
    resolution = settings.resolution or 128
    factory = None
    if settings.dagger is not None:
        if not 0.0 <= settings.beta <= 1.0:
            raise DemoExportError(f"beta must be between 0 and 1, got {settings.beta}")
        if settings.dagger in ("expert", "plan"):
            raise DemoExportError(
                f"--dagger {settings.dagger}: the policy must be an agent, not the labeller"
            )
        if settings.max_steps < 0:
            raise DemoExportError(f"max_steps must be 0 (no limit) or more, got {settings.max_steps}")
        if settings.label_horizon < 1:
            raise DemoExportError(f"label_horizon must be at least 1, got {settings.label_horizon}")
        if not 1 <= settings.plan_budget_ms < 2**32:
            raise DemoExportError(f"plan_budget_ms must be 1 to 4294967295, got {settings.plan_budget_ms}")
        try:
            factory = make_factory(settings.dagger, dict(settings.agent_config), settings.out)
        except EvalError as error:
            raise DemoExportError(str(error)) from None
        # A trained policy (ESRP-BC's, ESRP-PPO's) says the views it takes: the store's, unless
        # --resolution asks for others, which it could not play on.
        wanted = getattr(getattr(factory, "sensors", None), "resolution", None)
        if isinstance(wanted, int) and wanted:
            if settings.resolution and settings.resolution != wanted:
                raise DemoExportError(
                    f"--dagger {settings.dagger}: the policy takes {wanted} px views, not the "
                    f"--resolution {settings.resolution} asked for (leave it out, or give {wanted})"
                )
            settings = dataclasses.replace(settings, resolution=wanted)
            resolution = wanted
    if settings.episodes_in_flight < 1:
        raise DemoExportError(f"episodes_in_flight must be at least 1, got {settings.episodes_in_flight}")
    chunk = settings.label_horizon if settings.dagger is not None else None
    store = _Store(
        settings.out, info.dataset, resolution, settings.labels, settings.dagger, chunk, settings.split
    )
    done = set(store.scene_ids)
    todo = [s for s in scenes if s.id not in done]
    if done:
        there = len(scenes) - len(todo)
        others = f" (it holds {len(done)} episodes in all)" if len(done) != there else ""
        print(
            f"resuming {settings.out}: {there} of {len(scenes)} scenes already there{others}",
            file=sys.stderr,
        )
    every = max(len(scenes) // 20, 1)
    added = 0
    skipped: list[str] = []

    def play(scene: SceneSummary) -> _Episode | _DaggerEpisode | None:
        if factory is None:
            return _replay(client, scene, settings.resolution)
        return _dagger(client, scene, settings, factory)

    for scene, played in _in_order(play, todo, settings.episodes_in_flight):
        if isinstance(played, tuple):
            store.append(scene.id, played)
            added += 1
        else:
            if played is None:
                skipped.append(scene.id)
                print(f"{scene.id}: the planner found no plan from its start: skipped", file=sys.stderr)
            else:
                store.append(
                    scene.id,
                    played.episode,
                    policy_actions=played.policy_actions,
                    label_chunks=played.label_chunks,
                )
                added += 1
        position = len(scenes) - len(todo) + added + len(skipped)
        if settings.progress and (position % every == 0 or position == len(scenes)):
            print(f"{position}/{len(scenes)} episodes, {store.steps} steps", file=sys.stderr)
    agreement = store.agreement()
    compared, agreed = agreement if agreement is not None else (None, None)
    return ExportOutcome(len(store.scene_ids), store.steps, added, compared, agreed, tuple(skipped))
