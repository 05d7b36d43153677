"""Conversions between the esrp.v1 messages and the package's values, at the edge.

Every answer is checked for what it must hold (an image's byte count against its shape, the
presence of required messages), so a malformed answer raises `ProtocolError`, never a numpy error.
Images become read-only numpy views of the message's bytes: `np.frombuffer(...).reshape(...)`.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import Any

import grpc
import numpy as np
import numpy.typing as npt

from ._errors import InvalidRequest, ProtocolError
from ._values import (
    Action,
    ArraySpec,
    Created,
    DatasetInfo,
    Difficulty,
    EpisodeMetrics,
    Footprint,
    Goal,
    ObjectState,
    Observation,
    ObservationSpec,
    Obstacle,
    PlanAnswer,
    PlanFailure,
    PlanStats,
    Pose2,
    PrivilegedState,
    Progress,
    RewardTerms,
    RewardWeights,
    SceneSummary,
    Sensors,
    ServerInfo,
    ServerLimits,
    Split,
    StaticObstacle,
    StepColumns,
    StepInfo,
    StepResult,
    TopDownFrame,
    action_value,
    observation_images,
    of_fields,
    unknown_action,
)
from .v1 import esrp_pb2 as pb

_SPLITS = {
    pb.SPLIT_TRAIN: Split.TRAIN,
    pb.SPLIT_TEST: Split.TEST,
    pb.SPLIT_CHALLENGE: Split.CHALLENGE,
    pb.SPLIT_MINIVAL: Split.MINIVAL,
}
_SPLIT_CODES = {value: code for code, value in _SPLITS.items()}
_DIFFICULTIES = {
    pb.DIFFICULTY_EASY: Difficulty.EASY,
    pb.DIFFICULTY_MEDIUM: Difficulty.MEDIUM,
    pb.DIFFICULTY_HARD: Difficulty.HARD,
}
_DIFFICULTY_CODES = {value: code for code, value in _DIFFICULTIES.items()}
_OBSTACLE_KINDS = {
    pb.Obstacle.KIND_WALL: "wall",
    pb.Obstacle.KIND_FIXED: "fixed",
    pb.Obstacle.KIND_MOVABLE: "movable",
}
_PLAN_FAILURES = {
    pb.PLAN_FAILURE_UNREACHABLE: PlanFailure.UNREACHABLE,
    pb.PLAN_FAILURE_NO_PLACEMENT: PlanFailure.NO_PLACEMENT,
    pb.PLAN_FAILURE_BUDGET_EXHAUSTED: PlanFailure.BUDGET_EXHAUSTED,
    pb.PLAN_FAILURE_TOO_LONG: PlanFailure.TOO_LONG,
}
_LITTLE_FLOAT32 = np.dtype("<f4")
_LITTLE_UINT32 = np.dtype("<u4")


# Requests.


def split_code(split: Split | str | None) -> pb.Split.ValueType:
    """The proto value of a split (`"train"`, `Split.TEST`, ...; None: unspecified)."""
    if split is None:
        return pb.SPLIT_UNSPECIFIED
    try:
        return _SPLIT_CODES[Split(split)]
    except ValueError:
        names = ", ".join(repr(s.value) for s in Split)
        raise InvalidRequest(f"unknown split {split!r}: use one of {names}") from None


def difficulty_code(difficulty: Difficulty | str | None) -> pb.Difficulty.ValueType:
    """The proto value of a difficulty (`"easy"`, `Difficulty.HARD`, ...; None: unspecified)."""
    if difficulty is None:
        return pb.DIFFICULTY_UNSPECIFIED
    try:
        return _DIFFICULTY_CODES[Difficulty(difficulty)]
    except ValueError:
        raise InvalidRequest(f"unknown difficulty {difficulty!r}: use 'easy', 'medium' or 'hard'") from None


def create_request(
    scene: str | None,
    *,
    scene_json: str | None,
    split: Split | str | None,
    seed: int,
    horizon: int,
    reward: RewardWeights | Mapping[str, Any] | None,
    sensors: Sensors | Mapping[str, Any] | None,
    privileged: bool,
    agent: str | None = None,
) -> pb.CreateEpisodeRequest:
    """The CreateEpisode request of `Client.create_episode`'s arguments, checked: `TypeError` or
    `ValueError` naming the argument for what the request cannot carry (an empty scene id, a
    negative seed...); `sensors` and `reward` may be mappings of their fields.
    """
    if scene is not None and scene_json is not None:
        raise InvalidRequest("give either scene (an id) or scene_json, not both")
    _check_scene(scene, "scene")
    _check_text(scene_json, "scene_json")
    _check_text(agent, "agent")
    _check_unsigned(seed, "seed", 64)
    _check_unsigned(horizon, "horizon", 32)
    sensors = of_fields(Sensors, sensors, "sensors") or Sensors()
    reward = of_fields(RewardWeights, reward, "reward")
    _check_unsigned(sensors.resolution, "sensors.resolution", 32)
    request = pb.CreateEpisodeRequest(
        split=split_code(split),
        seed=seed,
        horizon=horizon,
        sensors=pb.Sensors(
            ego_depth=sensors.depth,
            ego_segmentation=sensors.segmentation,
            current_top_down=sensors.current_top_down,
            resolution=sensors.resolution,
        ),
        privileged=privileged,
        agent=agent or "",
    )
    if scene is not None:
        request.scene_id = scene
    if scene_json is not None:
        request.scene_json = scene_json
    if reward is not None:
        weights: dict[str, Any] = {k: v for k, v in vars(reward).items() if v is not None}
        request.reward.CopyFrom(pb.RewardWeights(**weights))
    return request


def _check_scene(scene: object, what: str) -> None:
    """`scene` is None or a scene id: a string, not empty (`TypeError`, `ValueError`)."""
    if scene is None:
        return
    _check_text(scene, what)
    if not scene:
        raise ValueError(f"{what}: an empty scene id (leave it out, None, to pick one by split and seed)")


def _check_text(value: object, what: str) -> None:
    """`value` is None or a string (`TypeError`)."""
    if value is not None and not isinstance(value, str):
        raise TypeError(f"{what}: a string, got {value!r}")


def _check_unsigned(value: object, what: str, bits: int) -> None:
    """`value` is an integer from 0 to 2**bits - 1, as its field of the request (`TypeError`,
    `ValueError`).
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{what}: an integer, got {value!r}")
    if not 0 <= int(value) < 2**bits:
        raise ValueError(f"{what}: an integer from 0 to {2**bits - 1}, got {value}")


def reset_request(episode_id: str, scene: str | None, scene_json: str | None) -> pb.ResetRequest:
    """The Reset request of `Episode.reset`'s arguments."""
    if scene is not None and scene_json is not None:
        raise InvalidRequest("give either scene (an id) or scene_json, not both")
    _check_scene(scene, "scene")
    _check_text(scene_json, "scene_json")
    request = pb.ResetRequest(episode_id=episode_id)
    if scene is not None:
        request.scene_id = scene
    if scene_json is not None:
        request.scene_json = scene_json
    return request


def action_code(action: object, at: str = "step") -> int:
    """The integer of an action as a step sends it (`action_value`). Anything else (`2.7`, a string,
    an array of several) raises `InvalidRequest` with the words the server uses for a code outside
    0..5 (`unknown_action`; `at` places it: `step`, `steps[3]`); the range itself is the server's
    to check.
    """
    code = action_value(action)
    if code is not None:
        return code
    raise InvalidRequest(unknown_action(action, at), code=grpc.StatusCode.INVALID_ARGUMENT)


def step_request(episode_id: str, action: object, include_goal: bool, at: str = "step") -> pb.StepRequest:
    """A Step request. Its action is `action_code(action)`; its range is the server's to check
    (INVALID_ARGUMENT).
    """
    return pb.StepRequest(episode_id=episode_id, action=action_code(action, at), include_goal=include_goal)


def plan_request(episode_id: str, max_actions: int, budget_ms: int | None) -> pb.PlanActionsRequest:
    """The PlanActions request of `Episode.plan_actions`'s arguments (checked here: the fields are
    unsigned 32-bit, and protobuf would raise a ValueError).
    """
    if not 0 <= max_actions < 2**32:
        raise InvalidRequest(f"max_actions must be 0 (the whole plan) or a positive count, not {max_actions}")
    if budget_ms is not None and not 0 < budget_ms < 2**32:
        raise InvalidRequest(f"budget_ms must be positive milliseconds (None: the server's), not {budget_ms}")
    return pb.PlanActionsRequest(episode_id=episode_id, max_actions=max_actions, budget_ms=budget_ms or 0)


def plan_timeout(timeout: float | None, budget_ms: int | None, server_budget_ms: int = 0) -> float | None:
    """The gRPC deadline of a PlanActions call: the client's `timeout`, but never shorter than the
    planning budget plus 5 s, so that a short default deadline does not cancel (and stop) a
    planner the caller gave more time. Where the call names no budget, the budget is the server's,
    `server_budget_ms` (`ServerLimits.plan_budget_ms`; 0, from a server older than it: 60 s, the
    default cap).
    """
    if timeout is None:
        return None
    if budget_ms is None:
        budget_ms = server_budget_ms or 60_000
    return max(timeout, budget_ms / 1000 + 5.0)


def step_batch_request(episode_ids: Sequence[str], actions: Sequence[int]) -> pb.StepBatchRequest:
    """A StepBatch request: one step of each episode, the actions as given (the server checks them)."""
    return pb.StepBatchRequest(
        steps=[
            pb.StepRequest(episode_id=episode, action=action)
            for episode, action in zip(episode_ids, actions, strict=True)
        ]
    )


def step_batch_requests(
    episode_ids: Sequence[str],
    actions: Sequence[object],
    size: int,
    resets: Sequence[tuple[str, str | None]] = (),
) -> list[pb.StepBatchRequest]:
    """One step of each episode as StepBatch requests of at most `size` steps, in order, each action
    checked by `action_code` (an error names it `steps[k]` by its place in `actions`); then the
    `resets` (an episode, and its new scene or None for the same one) in the last request and
    more after it, a reset counting as two steps (its answer carries the goal image too).
    """
    if len(episode_ids) != len(actions):
        raise ValueError(f"{len(episode_ids)} episodes and {len(actions)} actions")
    codes = [action_code(action, f"steps[{k}]") for k, action in enumerate(actions)]
    requests = [
        step_batch_request(episode_ids[start : start + size], codes[start : start + size])
        for start in range(0, len(codes), size)
    ]
    if not resets:
        return requests
    last = requests[-1] if requests else None
    used = len(last.steps) if last is not None else 0
    for episode, scene in resets:
        # A new request when there is none, or when this reset does not fit beside what the
        # last one holds (a reset alone always goes, whatever `size`).
        if last is None or (used > 0 and used + 2 > size):
            last, used = pb.StepBatchRequest(), 0
            requests.append(last)
        last.resets.append(reset_request(episode, scene, None))
        used += 2
    return requests


# Answers.


def _checked(what: str, height: int, width: int, per_pixel: int, data: bytes) -> None:
    expected = height * width * per_pixel
    if height == 0 or width == 0 or len(data) != expected:
        raise ProtocolError(
            f"{what} is {width}x{height} with {per_pixel} bytes per pixel but holds {len(data)} bytes"
        )


def rgb_image(what: str, image: pb.Image) -> npt.NDArray[np.uint8]:
    """A read-only (H, W, C) uint8 view of an Image's bytes."""
    data = image.data
    _checked(what, image.height, image.width, image.channels, data)
    return np.frombuffer(data, dtype=np.uint8).reshape(image.height, image.width, image.channels)


def _depth_image(image: pb.FloatImage) -> npt.NDArray[np.float32]:
    data = image.data
    _checked("ego_depth", image.height, image.width, 4, data)
    array: npt.NDArray[np.float32] = np.frombuffer(data, dtype=_LITTLE_FLOAT32).reshape(
        image.height, image.width
    )
    return array


def _label_image(image: pb.LabelImage) -> npt.NDArray[np.uint32]:
    data = image.data
    _checked("ego_segmentation", image.height, image.width, 4, data)
    array: npt.NDArray[np.uint32] = np.frombuffer(data, dtype=_LITTLE_UINT32).reshape(
        image.height, image.width
    )
    return array


def observation(message: pb.Observation) -> Observation:
    """An Observation of its message; images as read-only numpy views."""
    if not message.HasField("ego_rgb"):
        raise ProtocolError("an observation without ego_rgb")
    return Observation(
        ego_rgb=rgb_image("ego_rgb", message.ego_rgb),
        grasping=message.grasping,
        goal_rgb=rgb_image("goal_rgb", message.goal_rgb) if message.HasField("goal_rgb") else None,
        depth=_depth_image(message.ego_depth) if message.HasField("ego_depth") else None,
        segmentation=_label_image(message.ego_segmentation) if message.HasField("ego_segmentation") else None,
        current_top_down=(
            rgb_image("current_top_down", message.current_top_down)
            if message.HasField("current_top_down")
            else None
        ),
    )


def obstacle(message: pb.Obstacle) -> Obstacle:
    """An Obstacle of its message."""
    return Obstacle(kind=_OBSTACLE_KINDS.get(message.kind, "unknown"), index=message.index, name=message.name)


def metrics(message: pb.EpisodeMetrics) -> EpisodeMetrics:
    """EpisodeMetrics of its message."""
    return EpisodeMetrics(
        success=message.success,
        object_success_rate=message.object_success_rate,
        remaining_distance_ratio=message.remaining_distance_ratio,
        stage=message.stage,
        placed=message.placed,
        movable_objects=message.movable_objects,
        steps=message.steps,
        total_reward=message.total_reward,
    )


def step_result(message: pb.StepResponse) -> StepResult:
    """A StepResult of a StepResponse."""
    if not message.HasField("observation") or not message.HasField("info"):
        raise ProtocolError("a step answer without observation or info")
    info = message.info
    terms = info.reward_terms
    return StepResult(
        observation=observation(message.observation),
        reward=message.reward,
        terminated=message.terminated,
        truncated=message.truncated,
        info=StepInfo(
            accepted=info.accepted,
            collided_with=obstacle(info.collided_with) if info.HasField("collided_with") else None,
            no_op=info.no_op or None,
            fetched=info.fetched if info.HasField("fetched") else None,
            released=info.released if info.HasField("released") else None,
            placed_count=info.placed_count,
            step_index=info.step_index,
            reward_terms=RewardTerms(
                success=terms.success,
                placement=terms.placement,
                potential=terms.potential,
                holding=terms.holding,
                living=terms.living,
            ),
        ),
        metrics=metrics(message.metrics) if message.HasField("metrics") else None,
    )


# The message field of each image key of `observation_images`.
_IMAGE_FIELDS = {
    "ego_rgb": "ego_rgb",
    "depth": "ego_depth",
    "segmentation": "ego_segmentation",
    "current_top_down": "current_top_down",
}


@functools.cache
def image_layout(sensors: Sensors) -> tuple[tuple[str, str, int, np.dtype[Any]], ...]:
    """The images an observation of `sensors` holds besides the goal: (key, message field, bytes per
    pixel, dtype) each, `ego_rgb` first (`observation_images`, with the fields; kept per sensors,
    for the steps' hot path).
    """
    return tuple((key, _IMAGE_FIELDS[key], size, dtype) for key, size, dtype in observation_images(sensors))


def step_columns(
    messages: Sequence[pb.StepResponse],
    layout: Sequence[tuple[str, str, int, np.dtype[Any]]],
    resolution: int,
    into: StepColumns | None = None,
) -> StepColumns:
    """The StepResponses of a wave as `StepColumns` (appended to `into` if given), each image
    checked to be `resolution` square with the bytes of its `layout` entry. Reads only what the
    Gymnasium envs return: a fraction of `step_result`'s cost, and no per-step objects but the bytes.
    """
    columns = into if into is not None else StepColumns([entry[0] for entry in layout])
    images = [(columns.images[key], field, resolution * resolution * size) for key, field, size, _ in layout]
    offset = len(columns.rewards)
    for position, message in enumerate(messages, offset):
        if not message.HasField("info"):
            raise ProtocolError("a step answer without observation or info")
        observation = message.observation
        for column, field, size in images:
            image = getattr(observation, field)
            data = image.data
            if len(data) != size or image.width != resolution or image.height != resolution:
                raise ProtocolError(
                    f"{field} is {image.width}x{image.height} with {len(data)} bytes where a "
                    f"{resolution}x{resolution} image of {size} bytes was expected"
                )
            column.append(data)
        columns.grasping.append(observation.grasping)
        columns.rewards.append(message.reward)
        columns.terminated.append(message.terminated)
        columns.truncated.append(message.truncated)
        info = message.info
        columns.accepted.append(info.accepted)
        columns.collided.append(info.HasField("collided_with"))
        columns.placed_count.append(info.placed_count)
        columns.step_index.append(info.step_index)
        if message.HasField("metrics"):
            columns.metrics[position] = metrics(message.metrics)
    return columns


def batch_responses(message: pb.StepBatchResponse, sent: int) -> Sequence[pb.StepResponse]:
    """The StepResponses of a StepBatch answer to `sent` steps (checked to be as many)."""
    responses = message.responses
    if len(responses) != sent:
        raise ProtocolError(f"{len(responses)} answers to a batch of {sent} steps")
    return responses


def batch_columns(
    message: pb.StepBatchResponse,
    request: pb.StepBatchRequest,
    layout: Sequence[tuple[str, str, int, np.dtype[Any]]],
    resolution: int,
    into: StepColumns,
) -> StepColumns:
    """A StepBatch answer to `request` appended to `into`: its steps as `step_columns`, its resets
    as `(observation, scene)` to `into.resets` (each checked to be as many as were sent).
    """
    step_columns(batch_responses(message, len(request.steps)), layout, resolution, into=into)
    if len(message.resets) != len(request.resets):
        raise ProtocolError(f"{len(message.resets)} answers to a batch of {len(request.resets)} resets")
    for answer in message.resets:
        first, scene = reset_observation(answer)
        if scene is None:
            raise ProtocolError("a reset answer of a StepBatch names no scene")
        into.resets.append((first, scene))
    return into


def step_results(messages: Sequence[pb.StepResponse], sent: int) -> list[StepResult]:
    """The StepResults of a StepBatch answer to `sent` steps."""
    if len(messages) != sent:
        raise ProtocolError(f"{len(messages)} answers to a batch of {sent} steps")
    return [step_result(m) for m in messages]


def scene_summary(message: pb.SceneSummary) -> SceneSummary:
    """A SceneSummary of its message."""
    return SceneSummary(
        id=message.id,
        room_type=message.room_type,
        difficulty=_DIFFICULTIES.get(message.difficulty),
        split=_SPLITS.get(message.split),
        movable_objects=message.movable_objects,
        horizon=message.horizon,
        expert_length=message.expert_length,
    )


def observation_spec(message: pb.ObservationSpec) -> ObservationSpec:
    """An ObservationSpec of its message."""
    return ObservationSpec(
        arrays=tuple(ArraySpec(a.name, tuple(a.shape), a.dtype) for a in message.arrays),
        actions=tuple(message.actions),
    )


def created(message: pb.CreateEpisodeResponse) -> Created:
    """A Created of a CreateEpisode answer."""
    if not message.HasField("observation") or not message.HasField("scene"):
        raise ProtocolError("a create answer without observation or scene")
    return Created(
        episode_id=message.episode_id,
        scene=scene_summary(message.scene),
        spec=observation_spec(message.spec),
        observation=observation(message.observation),
    )


def reset_observation(message: pb.ResetResponse) -> tuple[Observation, SceneSummary | None]:
    """The first observation and the scene of a Reset answer."""
    if not message.HasField("observation"):
        raise ProtocolError("a reset answer without observation")
    scene = scene_summary(message.scene) if message.HasField("scene") else None
    return observation(message.observation), scene


def closed_metrics(message: pb.CloseEpisodeResponse) -> EpisodeMetrics:
    """The metrics of a CloseEpisode answer."""
    if not message.HasField("metrics"):
        raise ProtocolError("a close answer without metrics")
    return metrics(message.metrics)


def progress(message: pb.GetMetricsResponse) -> Progress:
    """The Progress of a GetMetrics answer: the metrics so far, and whether the episode ended."""
    return Progress(metrics(message.metrics), message.ended)


def goal(message: pb.GetGoalResponse) -> Goal:
    """A Goal of a GetGoal answer (its frame None where the answer has none: a hidden scene
    served with the paper's observation only, until the episode ends).
    """
    if not message.HasField("goal_rgb"):
        raise ProtocolError("a goal answer without image")
    frame = None
    if message.HasField("frame"):
        f = message.frame
        frame = TopDownFrame(f.min_x, f.min_z, f.metres_per_pixel, f.resolution)
    return Goal(image=rgb_image("goal_rgb", message.goal_rgb), frame=frame)


def _pose(message: pb.Pose2) -> Pose2:
    return Pose2(message.x, message.z, message.yaw)


def _footprint(message: pb.Footprint) -> Footprint:
    return Footprint(message.center_x, message.center_z, message.half_x, message.half_z, message.yaw)


def privileged_state(message: pb.GetPrivilegedStateResponse) -> PrivilegedState:
    """A PrivilegedState of its message."""
    floor = list(message.floor)
    if len(floor) % 2:
        raise ProtocolError(f"a floor polygon of {len(floor)} coordinates (x, z pairs expected)")
    return PrivilegedState(
        agent_x=message.agent_x,
        agent_z=message.agent_z,
        agent_heading=message.agent_heading,
        held=message.held if message.HasField("held") else None,
        objects=tuple(
            ObjectState(
                id=o.id,
                category=o.category,
                pose=_pose(o.pose),
                target=_pose(o.target),
                footprint=_footprint(o.footprint),
                target_footprint=_footprint(o.target_footprint),
                iou=o.iou,
                placed=o.placed,
                held=o.held,
            )
            for o in message.objects
        ),
        static_obstacles=tuple(
            StaticObstacle(obstacle(s.obstacle), _footprint(s.footprint)) for s in message.static_obstacles
        ),
        floor=tuple(zip(floor[0::2], floor[1::2], strict=True)),
        scene_json=message.scene_json,
    )


def server_info(message: pb.ServerInfoResponse) -> ServerInfo:
    """A ServerInfo of its message."""
    limits = message.limits
    return ServerInfo(
        version=message.version,
        renderer_adapter=message.renderer_adapter,
        renderer_backend=message.renderer_backend,
        software_renderer=message.software_renderer,
        limits=ServerLimits(
            max_episodes=limits.max_episodes,
            max_batch=limits.max_batch,
            max_message_bytes=limits.max_message_bytes,
            idle_timeout_seconds=limits.idle_timeout_seconds,
            max_resolution=limits.max_resolution,
            plan_budget_ms=limits.plan_budget_ms,
            max_plan_ms=limits.max_plan_ms,
        ),
        live_episodes=message.live_episodes,
        dataset=message.dataset,
        caller=message.caller,
        role=message.role,
        challenge=message.challenge,
        recording=message.recording,
        renderer_rasterizer=message.renderer_rasterizer,
    )


def dataset_info(message: pb.DescribeDatasetResponse) -> DatasetInfo:
    """A DatasetInfo of its message, its counts sorted by name: a protobuf map comes in no set order
    (the server's encoder and upb's hash table, seeded per process, each order it their own way), and
    the same dataset should give the same values, printed alike, everywhere.
    """
    return DatasetInfo(
        name=message.name,
        scenes=message.scenes,
        by_split=dict(sorted(message.by_split.items())),
        by_difficulty=dict(sorted(message.by_difficulty.items())),
        by_room_type=dict(sorted(message.by_room_type.items())),
        source=message.source,
    )


def plan_answer(message: pb.PlanActionsResponse) -> PlanAnswer:
    """A PlanAnswer of a PlanActions answer; an action code outside 0..5 is a `ProtocolError`."""
    try:
        actions = tuple(Action(code) for code in message.actions)
    except ValueError:
        codes = list(message.actions)[:16]
        raise ProtocolError(f"a plan with an action code outside 0..5: {codes}") from None
    stats = message.stats
    failure = _PLAN_FAILURES.get(message.failure)
    if message.failure and failure is None:
        raise ProtocolError(f"a plan failure this client does not know: {message.failure}")
    return PlanAnswer(
        actions=actions,
        reaches_success=message.reaches_success,
        plan_length=message.plan_length,
        cached=message.cached,
        stats=PlanStats(
            nodes_expanded=stats.nodes_expanded,
            searches=stats.searches,
            planning_seconds=stats.planning_seconds,
            objects_relocated=stats.objects_relocated,
        ),
        failure=failure,
        failure_message=message.failure_message,
        failure_object=message.failure_object,
    )
