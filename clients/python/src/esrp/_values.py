"""The values the client sends and receives: actions, observations (numpy views of the answer's
bytes, never copied), step results, metrics, scenes and server information.

Units and frames are those of the task's specification: metres, radians, a y-up world with plan
coordinates (x, z), headings as indices of 22.5°.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, TypeAlias, TypeVar

import numpy as np
import numpy.typing as npt

# Its public names are listed once, in esrp._EXPORTS (esrp/__init__.py), which exports them all.

RgbImage = npt.NDArray[np.uint8]
"""An RGB image, shape (H, W, 3), uint8, read-only."""


class Action(enum.IntEnum):
    """The six actions, with the integer codes of the API (SPEC §3)."""

    FORWARD = 0
    """Move 0.25 m forward (rejected whole on collision)."""
    BACKWARD = 1
    """Move 0.25 m backward."""
    LEFT = 2
    """Turn 22.5° left (counter-clockwise seen from above)."""
    RIGHT = 3
    """Turn 22.5° right."""
    FETCH = 4
    """Attach the nearest movable object within 1.0 m; a no-op when holding or none is in reach."""
    RELEASE = 5
    """Detach the held object where it is; a no-op when nothing is held."""

    @property
    def api_name(self) -> str:
        """The name the API uses (`move_forward`, ..., `release`), as in `ObservationSpec.actions`."""
        return _API_NAMES[self]


ActionLike: TypeAlias = Action | int | np.integer[Any] | npt.NDArray[np.integer[Any]]
"""What a step takes: an `Action`, its code 0..5, a numpy integer, or a numpy array of one (shape
`()` or `(1,)`). An integer-valued float (`2.0`) passes too; any other value (`2.7`) is refused
with `InvalidRequest`, in the server's words for a code outside 0..5."""


_API_NAMES = {
    Action.FORWARD: "move_forward",
    Action.BACKWARD: "move_backward",
    Action.LEFT: "turn_left",
    Action.RIGHT: "turn_right",
    Action.FETCH: "fetch",
    Action.RELEASE: "release",
}


def plain_action(action: object) -> object:
    """The Python value of an action given as a numpy scalar or a numpy array of one (shape `()` or
    `(1,)`); anything else as it is.
    """
    if isinstance(action, np.ndarray) and action.shape in ((), (1,)):
        return action.reshape(()).item()
    if isinstance(action, np.generic):
        return action.item()
    return action


ACTION_CODES_HELP = "use 0 move_forward, 1 move_backward, 2 turn_left, 3 turn_right, 4 fetch, 5 release"
"""The end of the server's message for an unknown action code."""


def unknown_action(action: object, at: str = "step") -> str:
    """The message for an action that is not a code 0..5 (`at` places it: `step`, `steps[3]`,
    `actions[1]`): the server's words for a code out of range, e.g. `step.action: unknown action
    code 7: use 0 move_forward, ...`, with the value as given (an array by its shape).
    """
    value = plain_action(action)
    shown = f"array of shape {value.shape}" if isinstance(value, np.ndarray) else repr(value)
    return f"{at}.action: unknown action code {shown}: {ACTION_CODES_HELP}"


def action_value(action: object) -> int | None:
    """The integer code of an `ActionLike` (an `Action` or int, a numpy integer, an integer-valued
    float, or a numpy array of one of these, shape `()` or `(1,)`), or None for anything else. The
    range 0..5 is not checked (that is the server's), only that the code fits the request's int32
    (None beyond: an unknown code all the same).
    """
    if type(action) is int or isinstance(action, Action):  # the common case, first
        code = int(action)
    else:
        value = plain_action(action)
        if isinstance(value, int) or isinstance(value, float) and value.is_integer():
            code = int(value)
        else:
            return None
    return code if -(2**31) <= code < 2**31 else None


_F = TypeVar("_F")


def of_fields(kind: type[_F], value: object, what: str) -> _F | None:
    """`value` as a `kind` (a dataclass of this module, e.g. `Sensors`): itself, None, or a mapping
    of its fields (`kind(**value)`, so that settings can come as JSON); `ValueError` naming `what`
    and `kind`'s fields for unknown ones, `TypeError` for anything else.
    """
    if value is None or isinstance(value, kind):
        return value
    if not isinstance(value, Mapping):
        raise TypeError(f"{what}: a {kind.__name__} or a mapping of its fields, got {value!r}")
    try:
        return kind(**value)
    except TypeError:
        known = ", ".join(f.name for f in dataclasses.fields(kind))  # type: ignore[arg-type]
        raise ValueError(f"{what}: unknown fields in {dict(value)!r} ({kind.__name__} has {known})") from None


class Split(str, enum.Enum):
    """A split of the dataset."""

    TRAIN = "train"
    TEST = "test"
    CHALLENGE = "challenge"
    """The hidden challenge split (a server started with `--challenge-seed`): scenes listed by id,
    room type, difficulty and object count only; one counted attempt per scene and token."""
    MINIVAL = "minival"
    """The challenge's minival phase: more scenes of the same secret draw, played any number of
    times (for checking a setup)."""


class Difficulty(str, enum.Enum):
    """A difficulty level by number of movable objects: easy 1, medium 2-3, hard 4-6."""

    EASY = "easy"
    MEDIUM = "medium"
    HARD = "hard"


@dataclass(frozen=True)
class Sensors:
    """The optional sensors of an episode, and its image size (all images are square).

    Attributes:
        depth: Egocentric depth, float32 metres (+inf where nothing is seen).
        segmentation: Egocentric instance labels, uint32 (0 background, 1 floor, 2 wall, 3 door,
            0x10000 + i fixed object i, 0x20000 + i movable object i).
        current_top_down: A top-down RGB render of the current layout (framed like the goal).
        resolution: Side of every image in pixels, 16 to the server's `max_resolution`.
    """

    depth: bool = False
    segmentation: bool = False
    current_top_down: bool = False
    resolution: int = 128


@dataclass(frozen=True)
class RewardWeights:
    """Reward weights (SPEC §6); a field left None keeps the server's default.

    Attributes:
        success: Once, on success (default 10).
        place: When a release places an object (default 1).
        unplace: When a fetch takes a placed object off its goal (default -1).
        potential: Times the decrease of the held object's distance to its target (default 1).
        holding: Each step that ends holding an object (default 0.01).
        living: Each step (default 0).
    """

    success: float | None = None
    place: float | None = None
    unplace: float | None = None
    potential: float | None = None
    holding: float | None = None
    living: float | None = None


@dataclass(frozen=True, eq=False)
class Observation:
    """What the agent observes (SPEC §4). Arrays are read-only views of the answer's bytes.

    Attributes:
        ego_rgb: The egocentric view, (R, R, 3) uint8.
        grasping: Whether the agent holds an object.
        goal_rgb: The top-down image of the target layout, (R, R, 3) uint8: sent at creation and
            reset and on steps that ask for it (`include_goal`), else None. It never changes
            within an episode.
        depth: Egocentric depth, (R, R) float32 metres, when the sensor is on.
        segmentation: Egocentric instance labels, (R, R) uint32, when the sensor is on.
        current_top_down: The current layout from above, (R, R, 3) uint8, when the sensor is on.
    """

    ego_rgb: RgbImage
    grasping: bool
    goal_rgb: RgbImage | None = None
    depth: npt.NDArray[np.float32] | None = None
    segmentation: npt.NDArray[np.uint32] | None = None
    current_top_down: RgbImage | None = None


@dataclass(frozen=True)
class Obstacle:
    """What a rejected motion would have hit.

    Attributes:
        kind: `wall`, `fixed` (furniture) or `movable` (another movable object).
        index: The wall index, or the index among the fixed or movable objects.
        name: The object's id, or `wall N`.
    """

    kind: str
    index: int
    name: str


@dataclass(frozen=True)
class RewardTerms:
    """A step's reward term by term (SPEC §6); they add up to the reward."""

    success: float
    placement: float
    potential: float
    holding: float
    living: float


@dataclass(frozen=True)
class StepInfo:
    """What a step did, beside its observation and reward.

    Attributes:
        accepted: The action took effect (False for a rejected motion or a no-op).
        collided_with: What a rejected motion would have hit.
        no_op: Why a fetch or release did nothing.
        fetched: The movable object index this step fetched.
        released: The movable object index this step released.
        placed_count: Objects placed after the step.
        step_index: Steps taken so far, this one included.
        reward_terms: The reward, term by term.
    """

    accepted: bool
    collided_with: Obstacle | None
    no_op: str | None
    fetched: int | None
    released: int | None
    placed_count: int
    step_index: int
    reward_terms: RewardTerms


@dataclass(frozen=True)
class EpisodeMetrics:
    """An episode's metrics (SPEC §5).

    Attributes:
        success: Every object placed.
        object_success_rate: OSR, the share of objects placed.
        remaining_distance_ratio: RDR, the remaining over the initial distance to the targets.
        stage: 1 never in fetch reach, 2 never fetched, 3 fetched without success, 4 success.
        placed: Objects placed.
        movable_objects: Movable objects of the scene.
        steps: Steps taken.
        total_reward: The sum of the rewards.
    """

    success: bool
    object_success_rate: float
    remaining_distance_ratio: float
    stage: int
    placed: int
    movable_objects: int
    steps: int
    total_reward: float


class Progress(NamedTuple):
    """`Episode.metrics()`: the metrics so far, and whether the episode has ended."""

    metrics: EpisodeMetrics
    ended: bool


@dataclass(frozen=True, eq=False)
class StepResult:
    """The answer to a step.

    Attributes:
        observation: The observation after the step.
        reward: The step's reward (the sum of `info.reward_terms`).
        terminated: Success: every object is placed and the episode has ended.
        truncated: The horizon was reached without success (never both).
        info: What the step did.
        metrics: The episode's final metrics, on the step that ends it; else None.
    """

    observation: Observation
    reward: float
    terminated: bool
    truncated: bool
    info: StepInfo
    metrics: EpisodeMetrics | None

    @property
    def ended(self) -> bool:
        """Whether the episode has ended (terminated or truncated)."""
        return self.terminated or self.truncated


@dataclass(frozen=True)
class SceneSummary:
    """A summary of one scene.

    Attributes:
        id: The scene id, e.g. `esrp-bench-v2/00042`.
        room_type: The 3D-FRONT room type, e.g. `MasterBedroom`.
        difficulty: Easy, medium or hard (None if the server sent an unknown value).
        split: Train or test (None if the server sent an unknown value).
        movable_objects: Objects to rearrange, 1 to 6.
        horizon: The step limit; 0 in listings of the built-in benchmark until the scene is built.
        expert_length: Steps of the expert trajectory; 0 where the listing does not hold it.
    """

    id: str
    room_type: str
    difficulty: Difficulty | None
    split: Split | None
    movable_objects: int
    horizon: int
    expert_length: int


@dataclass(frozen=True)
class ArraySpec:
    """Name, shape and dtype (`uint8`, `float32`, `uint32`, `bool`) of one observation array."""

    name: str
    shape: tuple[int, ...]
    dtype: str


@dataclass(frozen=True)
class ObservationSpec:
    """The arrays an episode's observations hold, and the action names in code order."""

    arrays: tuple[ArraySpec, ...]
    actions: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class Created:
    """A newly created episode: its id, scene, observation spec and first observation (with goal)."""

    episode_id: str
    scene: SceneSummary
    spec: ObservationSpec
    observation: Observation


@dataclass(frozen=True)
class TopDownFrame:
    """The pixel ↔ floor mapping of top-down images.

    Pixel (col, row) covers [col, col+1) × [row, row+1), with `x = min_x + col * metres_per_pixel`
    and `z = min_z + row * metres_per_pixel` (image right is +x, image up is -z).
    """

    min_x: float
    min_z: float
    metres_per_pixel: float
    resolution: int


@dataclass(frozen=True, eq=False)
class Goal:
    """The goal image, (R, R, 3) uint8 read-only, and its frame on the floor.

    `frame` is None on a hidden scene (challenge, minival) served with the paper's observation
    only, until the episode has ended: it gives the room's size in metres, which the paper's
    agent is not told.
    """

    image: RgbImage
    frame: TopDownFrame | None


@dataclass(frozen=True)
class Pose2:
    """A pose on the floor: position (x, z) in metres and yaw in radians."""

    x: float
    z: float
    yaw: float


@dataclass(frozen=True)
class Footprint:
    """An oriented rectangle on the plan: centre, half sizes along its local axes, yaw."""

    center_x: float
    center_z: float
    half_x: float
    half_z: float
    yaw: float


@dataclass(frozen=True)
class ObjectState:
    """One movable object's current and target pose and footprint, IoU, and whether placed/held."""

    id: str
    category: str
    pose: Pose2
    target: Pose2
    footprint: Footprint
    target_footprint: Footprint
    iou: float
    placed: bool
    held: bool


@dataclass(frozen=True)
class StaticObstacle:
    """A wall piece or a fixed object, and its footprint."""

    obstacle: Obstacle
    footprint: Footprint


@dataclass(frozen=True)
class PrivilegedState:
    """The full state of a privileged episode, for planners and debugging (not for ESRP agents).

    Attributes:
        agent_x: Agent position x, metres.
        agent_z: Agent position z, metres.
        agent_heading: Heading index 0..15; yaw = index × 22.5°.
        held: The index of the held movable object, or None.
        objects: Every movable object, in scene order.
        static_obstacles: Wall pieces, then fixed objects.
        floor: The floor polygon as (x, z) points.
        scene_json: The scene as `esrp.scene/v1` JSON, expert trajectory included.
    """

    agent_x: float
    agent_z: float
    agent_heading: int
    held: int | None
    objects: tuple[ObjectState, ...]
    static_obstacles: tuple[StaticObstacle, ...]
    floor: tuple[tuple[float, float], ...]
    scene_json: str

    @property
    def agent_yaw(self) -> float:
        """The agent's yaw in radians."""
        return self.agent_heading * math.pi / 8


@dataclass(frozen=True)
class ServerLimits:
    """The server's limits (its flags).

    Attributes:
        plan_budget_ms: The planning time of a PlanActions call that names none (`--plan-budget-ms`,
            capped by `max_plan_ms`); 0 from a server older than this field.
        max_plan_ms: The most planning time a call may ask for (`--max-plan-ms`); 0 from an older
            server.
    """

    max_episodes: int
    max_batch: int
    max_message_bytes: int
    idle_timeout_seconds: int
    max_resolution: int
    plan_budget_ms: int = 0
    max_plan_ms: int = 0


@dataclass(frozen=True)
class ServerInfo:
    """The server's version, renderer, limits, live episode count and dataset name, and who it
    takes the caller for.

    Attributes:
        caller: The name of the caller's token (`"admin"` with the server's `--token`,
            `"anonymous"` on a server without tokens; empty from a server older than token roles).
        role: The token's role: `"agent"`, `"trainer"` or `"admin"` (empty from an older server).
        challenge: Whether the server serves a challenge split (`Split.CHALLENGE`, `Split.MINIVAL`).
        recording: Which episodes the server records: `"challenge"`, `"all"`, or `""` (none).
        renderer_rasterizer: What draws the triangles: `"pipeline"` (the graphics pipeline) or
            `"compute"` (compute shaders); empty from a server older than the compute rasteriser.
    """

    version: str
    renderer_adapter: str
    renderer_backend: str
    software_renderer: bool
    limits: ServerLimits
    live_episodes: int
    dataset: str
    caller: str = ""
    role: str = ""
    challenge: bool = False
    recording: str = ""
    renderer_rasterizer: str = ""


@dataclass(frozen=True)
class DatasetInfo:
    """The served dataset: its name, scene count, counts by split, difficulty and room type (each
    sorted by name, so that the same dataset gives the same values in the same order everywhere).
    """

    name: str
    scenes: int
    by_split: Mapping[str, int]
    by_difficulty: Mapping[str, int]
    by_room_type: Mapping[str, int]
    source: str


class PlanFailure(str, enum.Enum):
    """Why the server's planner found no plan (`PlanAnswer.failure`)."""

    UNREACHABLE = "unreachable"
    """No pose from which `fetch` takes an object (`PlanAnswer.failure_object`)."""
    NO_PLACEMENT = "no_placement"
    """No release pose places an object (`PlanAnswer.failure_object`)."""
    BUDGET_EXHAUSTED = "budget_exhausted"
    """The search's node budget ran out."""
    TOO_LONG = "too_long"
    """A plan exists but does not fit the steps left before the horizon."""


@dataclass(frozen=True)
class PlanStats:
    """What the planning that made a plan cost.

    Attributes:
        nodes_expanded: Search nodes expanded.
        searches: Searches run (one per object attempt).
        planning_seconds: Wall time of the planning, seconds.
        objects_relocated: Blockers moved aside to buffer poses.
    """

    nodes_expanded: int
    searches: int
    planning_seconds: float
    objects_relocated: int


@dataclass(frozen=True)
class PlanAnswer:
    """The answer of `Episode.plan_actions`: the next actions of a plan from the current state.

    Attributes:
        actions: The next actions, at most `max_actions`. With a `failure`: the next of the actions
            the planner took before it failed (they place what they can, possibly none: step them
            and ask again from there).
        reaches_success: The plan ends in success (False only with a `failure`).
        plan_length: Length of the whole plan from the current state.
        cached: Answered from the plan cached with the episode (no planning; `stats` are the
            planning that made it).
        stats: The planning's cost.
        failure: Why there is no plan, or None when a plan was found.
        failure_message: The failure in words ("" without one).
        failure_object: The id of the object a failure is about ("" if none).
    """

    actions: tuple[Action, ...]
    reaches_success: bool
    plan_length: int
    cached: bool
    stats: PlanStats
    failure: PlanFailure | None
    failure_message: str
    failure_object: str


_LITTLE_FLOAT32 = np.dtype("<f4")
_LITTLE_UINT32 = np.dtype("<u4")

# Every image an observation can hold besides the goal, as the Gymnasium envs name them, in their
# order: (observation key, bytes per pixel, dtype).
_SENSOR_IMAGES: tuple[tuple[str, int, np.dtype[Any]], ...] = (
    ("ego_rgb", 3, np.dtype(np.uint8)),
    ("depth", 4, _LITTLE_FLOAT32),
    ("segmentation", 4, _LITTLE_UINT32),
    ("current_top_down", 3, np.dtype(np.uint8)),
)


def observation_images(sensors: Sensors) -> tuple[tuple[str, int, np.dtype[Any]], ...]:
    """The images an observation of `sensors` holds besides the goal: (key, bytes per pixel, dtype)
    each, `ego_rgb` first; each is `sensors.resolution` square (RGB images (R, R, 3), the others
    (R, R)).
    """
    wanted = {
        "ego_rgb": True,
        "depth": sensors.depth,
        "segmentation": sensors.segmentation,
        "current_top_down": sensors.current_top_down,
    }
    return tuple(entry for entry in _SENSOR_IMAGES if wanted[entry[0]])


class StepColumns:
    """The answers to a wave of steps as columns (`Client.step_columns`, `Episode.step_columns`):
    one list per field in request order, the images as the answers' bytes (not yet arrays; each
    checked to hold the expected size), and the metrics of the steps that ended an episode, by
    position. What the Gymnasium envs read, without per-step values.

    Attributes:
        rewards, terminated, truncated, grasping: A step's reward and flags.
        accepted, collided, placed_count, step_index: Its `StepInfo` fields (`collided`: whether it
            names an obstacle hit).
        images: Each image key of `observation_images` (the sensors' images) to its bytes per step.
        metrics: The final metrics of the steps that ended their episode, by position.
        resets: The first observation (with the goal image) and the scene of each reset of the
            call (`Client.step_columns(..., resets=...)`), in request order.
    """

    __slots__ = (
        "accepted",
        "collided",
        "grasping",
        "images",
        "metrics",
        "placed_count",
        "resets",
        "rewards",
        "step_index",
        "terminated",
        "truncated",
    )

    def __init__(self, keys: Sequence[str]) -> None:
        self.rewards: list[float] = []
        self.terminated: list[bool] = []
        self.truncated: list[bool] = []
        self.grasping: list[bool] = []
        self.accepted: list[bool] = []
        self.collided: list[bool] = []
        self.placed_count: list[int] = []
        self.step_index: list[int] = []
        self.images: dict[str, list[bytes]] = {key: [] for key in keys}
        self.metrics: dict[int, EpisodeMetrics] = {}
        self.resets: list[tuple[Observation, SceneSummary]] = []
