"""ESRP-MAP, the agent: it looks around, maps, registers its map to the goal image, then for each
object of the goal image drives to it, fetches it, carries it to its target and releases it.

It sees what the paper's agents see and nothing more: the egocentric view, the goal image and the
grasp flag (no info field, no reward, no metrics). Its pose is dead reckoning over the actions it
took, in its start frame; a move or turn whose view is unchanged was rejected (a collision) and
leaves the pose, and the cell it would have entered is marked blocked (holding an object: that
motion from that pose is refused) before it plans again.

The phases:

1. **Look around**: 15 left turns, each view added to the map (`mapping.TopDownMap`).
2. **Register** the map to the goal image (`register.register`): the start heading, the scale and
   the start position in the goal's pixels.
3. For each goal object, largest first: **fit** its footprint to the map's bases of its category
   (its size from the goal image, its yaw its target's plus a multiple of 22.5°), **choose a fetch
   pose** among those the robot can reach from which a carry plan exists (the object keeps its
   pose relative to the robot), **drive** there (A* on the action lattice against the goal's
   static structure and the mapped objects, `planner.plan`), **fetch** (the grasp flag says
   whether it worked; if not it drives closer), then **carry** it, its rectangle checked along
   every move and turn (`planner.CarriedSpace`), until its believed footprint overlaps its target
   with an IoU of 0.6, and **release** it. With no carry plan left, it puts the object down and
   fetches it again from another pose. After a fetch it checks which object it holds (of several
   of one category: `_held_task`); objects it left somewhere are remembered there (`_released`).

Known limits: an object never seen from the start or from the way is searched for by a few
look-arounds only, and the held object's footprint is what the map's bases and the goal image say
(see docs/esrp-map.md for the measured errors).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..._values import Action, Observation
from .._config import check_agent_config
from .geometry import Pose2D
from .goal import CATEGORIES, STATIC, GoalImage, GoalObject, components, parse_goal
from .mapping import TopDownMap, floor_pixels
from .planner import (
    STEP,
    CarriedSpace,
    HeldObject,
    Occupancy,
    State,
    plan,
    reachable,
    rectangle,
    rectangle_iou,
)
from .register import Registration, cost_of, register

__all__ = ["MapAgent"]

ROBOT_RADIUS = 0.30
"""The robot's collision radius (SPEC §2)."""
_CLEARANCE = 0.04
"""Metres kept from obstacles beyond the body's radius (the map's error)."""
_FETCH_REACH = 0.85
"""The robot fetches when a base of the wanted object is this close to its centre (SPEC: a
footprint within 1.0 m; a base lies on or behind the object, so the object is at least as near)."""
_PLACE_IOU = 0.6
"""The IoU with its target that the held object's footprint, as the agent believes it, must reach
before it is released (the server's threshold is 0.3: the rest absorbs the belief's errors)."""
_OWN_BASES = 0.4
"""Metres from an object's believed footprint within which the map's bases of its category are
taken for its own (a base lies on or behind the face it belongs to)."""
_NEAR_BASES = 12
"""Bases of the held object in the view at the fetch from which its footprint is fitted alone."""
_NEARER = 0.15
"""Metres by which the wanted object must be nearer a fetch pose than any other object's base."""
_FETCH_CANDIDATES = 12
"""Fetch poses whose carry is planned before one is chosen, at most."""
_CHOOSE_MARGIN = -0.03
"""Metres added to the robot's radius when a fetch pose's carry is planned (`_choose_fetch`)."""
_CHOOSE_HELD_MARGIN = -0.015
"""Metres added to the held object's half sizes when a fetch pose's carry is planned."""
_REGRASPS = 2
"""Times an object is put down and fetched again from another pose when no carry plan is found."""
_FIT_INSET = 0.06
"""Metres inside a fitted footprint's edges where its points must not lie on structure (the goal
image's pixels and the registration are a few centimetres out)."""
_ON_STRUCTURE = 3.0
"""A fitted footprint's cost per point of it on the goal image's structure or outside the room."""
_ON_FREE = 0.15
"""A fitted footprint's cost per point of it on floor the map saw free (furniture on legs shows the
floor beneath it: a small cost, against the bases')."""
_REFIT_MARGIN = 1.1
"""A registration made after a later look-around replaces the last one only when the last one's
cost on the grown map is above the new one's by this factor."""
_LOOK_TURNS = 15
_EXPLORATIONS = 5
"""Look-arounds from new places at most, when a wanted object has not been seen."""
_MAX_REJECTED = 40
"""Rejected moves after which the agent gives up (its map is wrong somewhere it cannot tell)."""


@dataclass
class _Task:
    """A goal object to move: its target in the start frame and its size in metres."""

    target: GoalObject
    instance: int
    category: int
    x: float
    z: float
    half_long: float
    half_short: float


class MapAgent:
    """ESRP-MAP (see the module). `config`: `max_expansions` (A*'s budget per plan, default
    20,000); another key, or a budget that is not an integer of at least 1 (None included),
    raises `ValueError`.
    """

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        check_agent_config(config or {}, "map", {"max_expansions": "positive"})
        self.config = dict(config or {})
        budget = self.config.get("max_expansions", 20000)
        if budget is None:
            # `check_agent_config` passes None over; a JSON null is no budget.
            raise ValueError("the map agent's max_expansions must be an integer of at least 1, not None")
        self.max_expansions = int(budget)
        self._stats: dict[str, Any] = {}

    def reset(self, observation: Observation, info: Mapping[str, Any]) -> None:
        """Starts an episode from its first observation (`info` is not read: an ESRP agent sees
        only its observations).
        """
        if observation.goal_rgb is None:
            raise ValueError("ESRP-MAP needs the goal image in the first observation")
        self.goal_rgb = np.asarray(observation.goal_rgb)
        self.goal: GoalImage = parse_goal(self.goal_rgb)
        # The goal pixels of static structure (walls, doors, fixed furniture) and outside the room.
        self._structure_pixels: npt.NDArray[np.bool_] = (
            (self.goal.labels == STATIC) & ~floor_pixels(self.goal_rgb)
        ) | ~self.goal.room
        side = observation.ego_rgb.shape[0]
        # Objects of a category seen more than once in the goal are told apart by their tops.
        counts = [sum(o.category == g.category for o in self.goal.objects) for g in self.goal.objects]
        tops = [(CATEGORIES.index(g.category), g.colour) for g in self.goal.objects]
        self._told_apart = [n > 1 for n in counts]
        self.map = TopDownMap(side, tops=tops)
        self.state = State(0.0, 0.0, 0)
        self.map.integrate(np.asarray(observation.ego_rgb), self._pose())
        self.map.visit(self._pose())
        self._last_view = np.asarray(observation.ego_rgb).copy()
        self._last_action: Action | None = None
        self._looks_left = _LOOK_TURNS
        self.registration: Registration | None = None
        self._tasks: list[_Task] = []
        self._placed: list[_Task] = []
        self._plan: list[Action] = []
        self._phase = "look"
        self._held: HeldObject | None = None
        self._refused: set[tuple[tuple[int, int, int], Action]] = set()
        self._approach: State | None = None
        self._approach_tried = False
        self._released: dict[int, npt.NDArray[np.float64]] = {}
        self._regrasps = 0
        self._skipped: set[int] = set()
        self._blocked_extra: list[tuple[float, float]] = []
        self._fetch_tries = 0
        self._explorations = 0
        self._waypoint: tuple[float, float] | None = None
        self._wander: list[Action] = []
        self._stats = {"plans": 0, "rejected": 0, "fetches": 0, "releases": 0, "explorations": 0}
        self._decisions: list[float] = []

    def stats(self) -> dict[str, Any]:
        """What the agent did: plans made, moves rejected, fetches and releases tried, the
        registration's fit, and its decision time per step (milliseconds, median and largest).
        """
        out = dict(self._stats)
        if self._decisions:
            out["decision_ms_median"] = round(1000 * float(np.median(self._decisions)), 2)
            out["decision_ms_max"] = round(1000 * max(self._decisions), 1)
        if self.registration is not None:
            out.update(
                heading=self.registration.heading,
                scale=round(self.registration.scale, 3),
                fit_cost=round(self.registration.cost, 3),
            )
        out["phase"] = self._phase
        return out

    def act(self, observation: Observation) -> Action | None:
        """The next action, or None when it gives up (nothing left it knows how to do)."""
        started = time.perf_counter()
        try:
            return self._act(observation)
        finally:
            self._decisions.append(time.perf_counter() - started)

    def _act(self, observation: Observation) -> Action | None:
        view = np.asarray(observation.ego_rgb)
        self._update_pose(view)
        carrying = bool(observation.grasping)
        self._observe(view, carrying)
        if self._stats["rejected"] > _MAX_REJECTED:
            return None
        if self._phase == "look":
            if self._looks_left > 0:
                self._looks_left -= 1
                return self._do(Action.LEFT)
            # Registered again after every look around: the map has grown. A new fit replaces the
            # last only where it scores better on the grown map (a partial view can fit better
            # elsewhere than the room the robot has been driving in).
            fit = register(self.map, self.goal, self.goal_rgb)
            if self.registration is not None:
                kept = cost_of(self.registration, self.map, self.goal, self.goal_rgb)
                if kept <= fit.cost * _REFIT_MARGIN:
                    fit = self.registration
                else:
                    self._stats["refits"] = self._stats.get("refits", 0) + 1
            self.registration = fit
            made = {task.instance: task for task in self._make_tasks()}
            if self._tasks or self._placed:
                # The same tasks in the same order (skips and swaps reorder them), in the new fit.
                self._tasks = [made[task.instance] for task in self._tasks]
                self._placed = [made[task.instance] for task in self._placed]
            else:
                self._tasks = list(made.values())
            self._phase = "carry" if carrying else "fetch"
        return self._next(carrying)

    # The phases after the look around.

    def _next(self, carrying: bool) -> Action | None:
        if self._phase == "skip":
            # Put down where its carry went nowhere: the other objects first (moving them may
            # clear its way), then it again.
            self._skipped.add(self._tasks[0].instance)
            self._tasks.append(self._tasks.pop(0))
            self._phase = "fetch"
            self._held = None
            self._refused = set()
            self._approach, self._approach_tried = None, False
            self._regrasps, self._fetch_tries = 0, 0
        if self._phase == "regrasp":
            # Put down where no carry plan went on: fetch it again from a better pose, its
            # footprint known from the belief it was carried with (`_released`).
            self._phase = "fetch"
            self._held = None
            self._refused = set()
            self._approach, self._approach_tried = None, False
            self._fetch_tries = 0
        if self._phase == "released":
            self._placed.append(self._tasks.pop(0))
            self._phase = "fetch"
            self._held = None
            self._refused = set()
            self._approach, self._approach_tried = None, False
            self._regrasps = 0
        if self._phase == "fetching":
            self._stats["fetches"] += 1
            if carrying:
                self._start_carry()
            else:
                self._fetch_tries += 1
                self._phase = "fetch"
                self._approach = None
                if self._fetch_tries >= 3:
                    return None
        if not self._tasks:
            return None
        if self._phase == "wander":
            if self._wander:
                return self._do(self._wander.pop(0))
            self._phase = "look"
            self._looks_left = _LOOK_TURNS - 1
            return self._do(Action.LEFT)
        if self._phase == "explore":
            return self._drive_then(Action.LEFT, "look", self._explore_goal())
        if self._phase == "fetch":
            if not self._approach_tried and self._fetch_tries == 0:
                chosen = self._choose_fetch(self._tasks[0])
                if chosen is not None:
                    self._approach, self._plan = chosen
            goal = self._approach_goal() if self._approach is not None else self._fetch_goal()
            if goal is None:
                return self._explore()
            return self._drive_then(Action.FETCH, "fetching", goal)
        if self._phase == "carry":
            return self._drive_then(Action.RELEASE, "released", self._carry_goal())
        return None

    def _drive_then(self, final: Action, phase: str, goal: tuple[Any, Any] | None) -> Action | None:
        """The next move of the plan towards `goal` (reached, heuristic), replanned when it is
        empty; `final` once it is reached.
        """
        if goal is None:
            return None
        reached, heuristic = goal
        if reached(self.state):
            self._plan = []
            self._phase = phase
            if final == Action.RELEASE:
                self._stats["releases"] += 1
            if phase == "look":
                self._looks_left = _LOOK_TURNS - 1
            return self._do(final)
        if not self._plan:
            found = self._replan(reached, heuristic)
            if not found and self._phase == "carry" and self._regrasps < _REGRASPS:
                self._regrasps += 1
                self._stats["regrasps"] = self._stats.get("regrasps", 0) + 1
                self._phase = "regrasp"
                return self._do(Action.RELEASE)
            if (
                not found
                and self._phase == "carry"
                and len(self._tasks) > 1
                and self._tasks[0].instance not in self._skipped
            ):
                self._stats["skips"] = self._stats.get("skips", 0) + 1
                self._phase = "skip"
                return self._do(Action.RELEASE)
            if not found and self._approach is not None and self._phase == "fetch":
                self._approach = None  # the chosen pose is out of reach now: any within reach
                return self._next(False)
            if not found:
                return self._explore() if self._phase in ("fetch", "explore") else None
            self._plan = found
        return self._do(self._plan.pop(0))

    def _replan(self, reached: Any, heuristic: Any) -> list[Action] | None:  # noqa: ANN401
        assert self.registration is not None
        self._stats["plans"] += 1
        blocked = self._blocked()
        for margin, held_margin in zip((_CLEARANCE, 0.0, -0.05), (0.02, 0.0, -0.03), strict=True):
            robot = Occupancy(blocked, self.registration, ROBOT_RADIUS + margin)
            carried = None
            if self._held is not None:
                room = self._room_for_held(blocked, self._held.corners(self.state))
                carried = CarriedSpace(room, self.registration, self._held, held_margin)
            found = plan(
                self.state,
                robot,
                reached,
                heuristic,
                carried=carried,
                refused=self._refused,
                # Carrying, the goal is a small region of a larger space: a larger budget.
                max_expansions=self.max_expansions * (3 if self._held is not None else 1),
            )
            if found:
                return found
        return None

    def _put_down(self) -> tuple[float, float, float] | None:
        """The current object's footprint (centre x, z, yaw) where it was put down, as believed,
        or None when it has not been held.
        """
        corners = self._released.get(self._tasks[0].instance)
        if corners is None:
            return None
        cx, cz, yaw, _, _ = _pose_of(corners)
        return cx, cz, yaw

    def _fetch_goal(self) -> tuple[Any, Any] | None:
        task = self._tasks[0]
        points = self._object_points(task)
        corners = self._released.get(task.instance)
        if corners is not None:
            points = np.concatenate([points.reshape(-1, 2), corners])
        if len(points) == 0:
            return None
        reach = _FETCH_REACH if self._fetch_tries == 0 else _FETCH_REACH - 0.25 * self._fetch_tries

        def distance(state: State) -> float:
            return float(np.min(np.hypot(points[:, 0] - state.x, points[:, 1] - state.z)))

        return (lambda s: distance(s) <= reach), (lambda s: max(distance(s) - reach, 0.0) / STEP)

    def _approach_goal(self) -> tuple[Any, Any]:
        """Reached at the fetch pose chosen (`_choose_fetch`)."""
        assert self._approach is not None
        want = self._approach
        key = want.key()

        def estimate(state: State) -> float:
            turns = abs(state.k - want.k) % 16
            return math.hypot(state.x - want.x, state.z - want.z) / STEP + min(turns, 16 - turns)

        return (lambda s: s.key() == key), estimate

    def _carry_goal(self) -> tuple[Any, Any] | None:
        """Reached where the held object's footprint, as the agent believes it, overlaps its
        target's with an IoU of `_PLACE_IOU` or more.
        """
        assert self._held is not None
        return self._carry_goal_for(self._held)

    def _carry_goal_for(self, held: HeldObject) -> tuple[Any, Any]:
        target = self._target_rectangle(self._tasks[0])
        tx, tz = target.mean(axis=0)
        near = 0.75 * max(held.half_x, held.half_z, 0.1)

        def distance(state: State) -> float:
            x, z = held.centre(state)
            return math.hypot(x - tx, z - tz)

        def reached(state: State) -> bool:
            if distance(state) > near:
                return False
            return rectangle_iou(held.corners(state), target) >= _PLACE_IOU

        return reached, (lambda s: max(distance(s) - 0.1, 0.0) / STEP)

    def _target_rectangle(self, task: _Task) -> npt.NDArray[np.float64]:
        """(4, 2) the corners of `task`'s target footprint in the start frame."""
        assert self.registration is not None
        target = task.target
        x0, z0 = self.registration.from_goal(target.col, target.row)
        x1, z1 = self.registration.from_goal(
            target.col + math.cos(target.angle), target.row + math.sin(target.angle)
        )
        yaw = math.atan2(-(float(z1) - float(z0)), float(x1) - float(x0))
        return rectangle(float(x0), float(z0), task.half_long, task.half_short, yaw)

    def _explore(self) -> Action | None:
        """Heads for floor of the goal's room that the map has not seen, to look around there."""
        if self._explorations >= _EXPLORATIONS:
            return None
        self._explorations += 1
        self._stats["explorations"] += 1
        self._phase = "explore"
        self._plan = []
        self._waypoint = self._unseen_point()
        if self._waypoint is None:
            # Nowhere the map can plan to (a wrong registration may wall the robot in): wander a
            # few moves along free floor it sees, then look around and register again.
            self._phase = "wander"
            self._wander = [Action.FORWARD] * 4
        return self._next(False)

    def _unseen_point(self) -> tuple[float, float] | None:
        """The nearest point, 1.5 m away or more, that the robot can reach (in the free space
        connected to where it stands) and the map has not seen.
        """
        assert self.registration is not None
        free = ~Occupancy(self._blocked(), self.registration, ROBOT_RADIUS).inflated
        col, row = self.registration.to_goal(self.state.x, self.state.z)
        here = (int(np.floor(row)), int(np.floor(col)))
        size = free.shape[0]
        if not (0 <= here[0] < size and 0 <= here[1] < size):
            return None
        free[here] = True  # the robot stands there, whatever the map says
        region = next((c for c in components(free) if (c == here).all(axis=1).any()), None)
        if region is None:
            return None
        x, z = self.registration.from_goal(region[:, 1] + 0.5, region[:, 0] + 0.5)
        r, c = self.map.cell_of(x, z)
        inside = r >= 0
        seen = np.zeros(len(x), dtype=bool)
        seen[inside] = (self.map.free[r[inside], c[inside]] > 0) | (self.map.static[r[inside], c[inside]] > 0)
        d = np.hypot(x - self.state.x, z - self.state.z)
        candidates = np.flatnonzero(~seen & (d >= 1.5))
        if len(candidates) == 0:
            return None
        best = candidates[int(np.argmin(d[candidates]))]
        return float(x[best]), float(z[best])

    def _explore_goal(self) -> tuple[Any, Any] | None:
        if self._waypoint is None:
            return None
        wx, wz = self._waypoint

        def distance(state: State) -> float:
            return math.hypot(state.x - wx, state.z - wz)

        return (lambda s: distance(s) <= 1.0), (lambda s: max(distance(s) - 1.0, 0.0) / STEP)

    def _choose_fetch(self, task: _Task) -> tuple[State, list[Action]] | None:
        """A fetch pose from which the object can be carried to its target, and the way there.

        The object's footprint is fitted to the map (`_fit_footprint`); the poses the robot can
        reach (breadth first) from which that footprint is within fetch reach are ranked by the
        drive there plus the object's distance to its target, with a penalty where the robot's
        heading is across the way the object must go (moves go along the heading). For the best
        few, the carry is planned as if fetched there (the object keeps its pose relative to the
        robot); the first whose carry plan exists is chosen. None when the map has no fit, or no
        candidate's carry plan is found: any pose within reach will do then.
        """
        assert self.registration is not None
        fit = self._put_down() or self._fit_footprint(task, None)
        if fit is None:
            return None
        self._approach_tried = True  # once per object: its fit only improves while it is fetched
        cx, cz, yaw = fit
        hx, hz = task.half_long, task.half_short
        corners = rectangle(cx, cz, hx, hz, yaw)
        target = self._target_rectangle(task)
        tx, tz = target.mean(axis=0)
        blocked = self._blocked()
        robot = Occupancy(blocked, self.registration, ROBOT_RADIUS + _CLEARANCE)
        reach = reachable(self.state, robot)
        blocked = self._blocked(ignore=(task.category, corners))
        # The carry is planned with margins between `_replan`'s last two rungs (the first is often
        # too strict next to the walls that targets stand against, and in the narrow ways the
        # layouts were made through: the goal image's pixels make structure a little wider).
        tight = Occupancy(blocked, self.registration, ROBOT_RADIUS + _CHOOSE_MARGIN)
        keys = list(reach.states)
        xs = np.array([reach.states[k].x for k in keys])
        zs = np.array([reach.states[k].z for k in keys])
        ks = np.array([reach.states[k].k for k in keys])
        gap = _gap_to_rectangle(xs, zs, cx, cz, yaw, hx, hz)
        usable = (gap >= ROBOT_RADIUS + 0.03) & (gap <= 0.9)
        # The server fetches the nearest object in reach: the others' bases must be farther (and
        # the outlines of those the robot left somewhere).
        others = self._movable_bases((task.category, corners), solid=False)
        left = [_outline(c) for i, c in self._released.items() if i != task.instance]
        others = np.concatenate([others, *left])
        if len(others):
            nearest_other = np.full(len(keys), np.inf)
            for start in range(0, len(others), 256):
                chunk = others[start : start + 256]
                d = np.hypot(xs[:, None] - chunk[None, :, 0], zs[:, None] - chunk[None, :, 1]).min(axis=1)
                nearest_other = np.minimum(nearest_other, d)
            usable &= nearest_other > gap + _NEARER
        if not usable.any():
            return None
        way = math.atan2(-(tz - cz), tx - cx)  # the heading that points from the object to its target
        across = np.abs(np.sin(ks * math.pi / 8 - way))
        # Behind the object as seen from its target: the robot follows it, instead of being
        # dragged round it.
        behind = 1 - np.cos(np.arctan2(-(cz - zs), cx - xs) - way)
        far = math.hypot(tx - cx, tz - cz) / STEP
        drive = np.array([reach.costs[k] for k in keys], dtype=np.float64)
        score = np.where(usable, drive + far + 6 * across + 6 * behind, np.inf)
        room = self._room_for_held(blocked, corners)
        space: CarriedSpace | None = None
        tried: list[State] = []
        for index in np.argsort(score):
            if not math.isfinite(score[index]) or len(tried) >= _FETCH_CANDIDATES:
                break
            state = reach.states[keys[index]]
            # Candidates unlike those tried: another heading, or 30 cm away.
            if any(t.k == state.k and math.hypot(t.x - state.x, t.z - state.z) < 0.3 for t in tried):
                continue
            tried.append(state)
            held = _relative(cx, cz, yaw, hx, hz, state)
            if space is None:
                space = CarriedSpace(room, self.registration, held, _CHOOSE_HELD_MARGIN)
            reached, heuristic = self._carry_goal_for(held)
            found = plan(
                state,
                tight,
                reached,
                heuristic,
                carried=space.holding(held),
                max_expansions=self.max_expansions // 10,
            )
            if found is not None:
                self._stats.setdefault("fetch_choices", []).append(len(tried))
                return state, reach.path_to(keys[index])
        self._stats.setdefault("fetch_choices", []).append(-len(tried))
        return None

    def _movable_bases(
        self, ignore: tuple[int, npt.NDArray[np.float64]] | None, *, solid: bool
    ) -> npt.NDArray[np.float64]:
        """(n, 2) start-frame points of the map's movable bases of every category (only the
        `_solid` ones with `solid`), less, with `ignore` = (category, corners), those of that
        category within `_OWN_BASES` of footprint `corners` (that object's own).
        """
        points = []
        for index in range(len(CATEGORIES)):
            cells = self._solid(index) if solid else self.map.movable[index] > 0
            x, z = self.map.centre_of(*np.nonzero(cells))
            if ignore is not None and ignore[0] == index:
                keep = _gap_to_corners(x, z, ignore[1]) > _OWN_BASES
                x, z = x[keep], z[keep]
            points.append(np.stack([x, z], axis=1))
        return np.concatenate(points)

    def _fit_footprint(
        self, task: _Task, robot: State | None, points: npt.NDArray[np.float64] | None = None
    ) -> tuple[float, float, float] | None:
        """The object's footprint (centre x, z and yaw in the start frame) fitted to the bases the
        map saw of it (near the robot, when it is given), or None when the map has none.

        Its size is its target's in the goal image. Its yaw differs from its target's by a
        multiple of 22.5° (the layouts are made by carrying objects on the lattice), so the fit
        tries those 8 yaws (a rectangle is the same turned half a turn); for each, the centres on a
        2 cm grid about the bases. A fit costs the bases' distances outside the rectangle and a
        third of their depths inside it (a base lies on the visible boundary, or behind it for
        furniture on legs). With `robot` (it holds the object), fits nearer its centre than its
        radius or farther than fetch reach (1 m) are ruled out: the fetch worked. `points`: the
        bases to fit (default: the map's, `_object_points`).
        """
        if points is None:
            points = self._object_points(task)
        target = self._target_rectangle(task)
        target_yaw = _pose_of(target)[2]
        hx, hz = task.half_long, task.half_short
        if len(points) and robot is not None:
            d = np.hypot(points[:, 0] - robot.x, points[:, 1] - robot.z)
            points = points[d <= 1.0 + 2 * max(hx, hz)]
        elif len(points):
            # The cluster of bases nearest the robot: another object of the category may be far.
            d = np.hypot(points[:, 0] - self.state.x, points[:, 1] - self.state.z)
            nearest = points[int(np.argmin(d))]
            points = points[np.hypot(*(points - nearest).T) <= 2.2 * max(hx, hz)]
        if len(points) == 0:
            return None
        best: tuple[float, float, float, float] | None = None
        lo = points.min(axis=0) - max(hx, hz)
        hi = points.max(axis=0) + max(hx, hz)
        gx, gz = np.meshgrid(np.arange(lo[0], hi[0], 0.02), np.arange(lo[1], hi[1], 0.02))
        cx, cz = gx.ravel(), gz.ravel()
        structure = self._structure()
        free = self._seen_free()
        # Points of the footprint, _FIT_INSET inside its edges, that must not lie on structure.
        u = np.linspace(-1.0, 1.0, 5)
        ux, uz = (a.ravel() for a in np.meshgrid(u * max(hx - _FIT_INSET, 0), u * max(hz - _FIT_INSET, 0)))
        for turn in range(8):
            yaw = target_yaw + turn * math.pi / 8
            c, s = math.cos(yaw), math.sin(yaw)
            # Each base in each candidate's local frame: (centres, bases).
            dx = points[None, :, 0] - cx[:, None]
            dz = points[None, :, 1] - cz[:, None]
            lx, lz = np.abs(dx * c - dz * s), np.abs(dx * s + dz * c)
            outside = np.hypot(np.maximum(lx - hx, 0), np.maximum(lz - hz, 0))
            depth = np.minimum(hx - lx, hz - lz).clip(min=0)
            cost = np.minimum(outside, 0.3).sum(axis=1) + np.minimum(depth, 0.3).sum(axis=1) / 3
            # A footprint through a wall or fixed furniture is not where the object stands (a
            # tall object's top edges, taken for bases, lie behind it, beyond the wall it backs
            # onto): each of its points on structure costs as much as 3 bases a metre out.
            px = cx[:, None] + ux[None, :] * c + uz[None, :] * s
            pz = cz[:, None] - ux[None, :] * s + uz[None, :] * c
            cost = cost + _ON_STRUCTURE * structure(px, pz).sum(axis=1)
            # Nor is one over floor the views saw free: a face is seen from the side it is not on.
            cost = cost + _ON_FREE * free(px, pz).sum(axis=1)
            if robot is not None:
                gap = _gap_to_rectangle(np.array([robot.x]), np.array([robot.z]), cx, cz, yaw, hx, hz)
                cost = np.where((gap < ROBOT_RADIUS - 0.02) | (gap > 1.0), np.inf, cost)
            index = int(np.argmin(cost))
            if best is None or cost[index] < best[0]:
                best = (float(cost[index]), float(cx[index]), float(cz[index]), yaw)
        assert best is not None
        if not math.isfinite(best[0]):
            return None
        return best[1], best[2], best[3]

    def _start_carry(self) -> None:
        """Finds out which object it holds (`_held_task`) and estimates where its footprint is
        relative to the robot.
        """
        held = self._held_task()
        if held:
            # Another object of the category than the one it went for: carry that one to its own
            # target (the one it went for is still where the map saw it).
            self._tasks.insert(0, self._tasks.pop(held))
            self._regrasps = 0
            self._stats["reassigned"] = self._stats.get("reassigned", 0) + 1
        task = self._tasks[0]
        self._phase = "carry"
        self._plan = []
        self._refused = set()
        self._held = self._estimate_held(task)
        self._released.pop(task.instance, None)
        # Its bases move with it from now on: forget them (those of its category near it; another
        # object of the category stays).
        layer = self.map.movable[task.category]
        rows, cols = np.nonzero(layer)
        x, z = self.map.centre_of(rows, cols)
        near = _gap_to_corners(x, z, self._held.corners(self.state)) <= _OWN_BASES
        layer[rows[near], cols[near]] = 0
        self.map.instance[:, rows[near], cols[near]] = 0

    def _held_task(self) -> int:
        """The index in the tasks of the object just fetched: the server fetches the object
        nearest the robot, which, of several objects of a category, need not be the one it went
        for. Each candidate is placed by the map's bases that are its own by their top colour;
        one whose bases are nearer the robot than the wanted one's by `_NEARER` is the one held.
        0 (the wanted one) when the objects of its category are not told apart, or the map saw
        no top of another one near.
        """
        task = self._tasks[0]
        if not self._told_apart[task.instance]:
            return 0
        rows, cols = np.nonzero(self.map.movable[task.category])
        x, z = self.map.centre_of(rows, cols)
        distance = np.hypot(x - self.state.x, z - self.state.z)
        nearest = {}
        robot = np.array([self.state.x]), np.array([self.state.z])
        for index, other in enumerate(self._tasks):
            if other.category != task.category:
                continue
            mine, theirs = _mine_theirs(self.map, other.instance, rows, cols)
            own = (mine > 0) & (mine > theirs)
            nearest[index] = float(distance[own].min()) if own.any() else math.inf
            left = self._released.get(other.instance)
            if left is not None:
                # Put down: where it was left, as believed.
                nearest[index] = min(nearest[index], float(_gap_to_corners(*robot, left)[0]))
        best = min(nearest, key=lambda i: nearest[i])
        if best != 0 and nearest[best] <= 1.0 and nearest[best] + _NEARER < nearest[0]:
            return best
        return 0

    def _estimate_held(self, task: _Task) -> HeldObject:
        """The held object's footprint relative to the robot (`_fit_footprint` with the robot's
        constraint), or, when the map saw none of it, its target's yaw straight ahead of it.
        """
        hx, hz = task.half_long, task.half_short
        fit = self._put_down()
        if fit is None:
            # The view at the fetch sees the object near, where a pixel row covers a few
            # centimetres, and with no drift of the pose: its bases alone when there are enough.
            near = self._view_bases(task)
            if len(near) >= _NEAR_BASES:
                fit = self._fit_footprint(task, self.state, near)
                self._stats["fits_from_view"] = self._stats.get("fits_from_view", 0) + 1
        fit = fit or self._fit_footprint(task, self.state)
        if fit is None:
            yaw = _pose_of(self._target_rectangle(task))[2]
            return HeldObject(ROBOT_RADIUS + hz + 0.05, 0.0, yaw - self.state.yaw, hx, hz)
        return _relative(*fit, hx, hz, self.state)

    def _view_bases(self, task: _Task) -> npt.NDArray[np.float64]:
        """(n, 2) start-frame points of the bases of `task`'s category in the current view alone,
        less those under another object's top colour (of several objects of the category).
        """
        view = TopDownMap(self._last_view.shape[0], tops=self.map.tops)
        view.integrate(self._last_view, self._pose())
        rows, cols = np.nonzero(view.movable[task.category])
        if self._told_apart[task.instance]:
            mine, theirs = _mine_theirs(view, task.instance, rows, cols)
            keep = theirs <= mine
            rows, cols = rows[keep], cols[keep]
        x, z = view.centre_of(rows, cols)
        return np.stack([x, z], axis=1)

    def debug_image(self, scale: int = 4) -> npt.NDArray[np.uint8]:
        """What the agent believes, drawn over its goal image magnified `scale` times: the map's
        free floor (light green), static bases (blue) and movable bases (magenta) where the
        registration puts them, the plan ahead (yellow), each task's target (white), the held
        object's footprint as the agent believes it (red outline) and the robot (black, with a
        tick along its heading). Before registration: the goal image alone.
        """
        image: npt.NDArray[np.uint8] = np.repeat(np.repeat(self.goal_rgb, scale, axis=0), scale, axis=1)
        fit = self.registration
        if fit is None:
            return image
        side = image.shape[0]

        def put(x: npt.ArrayLike, z: npt.ArrayLike, colour: tuple[int, int, int], size: int = 1) -> None:
            col, row = fit.to_goal(x, z)
            c = np.floor(np.atleast_1d(col) * scale).astype(np.intp)
            r = np.floor(np.atleast_1d(row) * scale).astype(np.intp)
            for dr in range(-size + 1, size):
                for dc in range(-size + 1, size):
                    rr, cc = r + dr, c + dc
                    ok = (rr >= 0) & (rr < side) & (cc >= 0) & (cc < side)
                    image[rr[ok], cc[ok]] = colour

        for counts, colour in ((self.map.free, (190, 240, 190)), (self.map.static, (40, 80, 220))):
            rows, cols = np.nonzero(counts)
            put(*self.map.centre_of(rows, cols), colour)
        for index in range(len(CATEGORIES)):
            rows, cols = np.nonzero(self.map.movable[index])
            put(*self.map.centre_of(rows, cols), (230, 40, 230))
        # The last action is taken but not yet seen: the plan goes on from where it leads.
        state = self.state if self._last_action is None else self.state.after(self._last_action)
        for action in self._plan:
            state = state.after(action)
            put(state.x, state.z, (250, 220, 0), 2)
        for task in self._tasks:
            put(task.x, task.z, (255, 255, 255), 3)
        if self._held is not None:
            corners = self._held.corners(self.state)
            t = np.linspace(0.0, 1.0, 40)[:, None]
            for i in range(4):
                a, b = corners[i], corners[(i + 1) % 4]
                edge = a + t * (b - a)
                put(edge[:, 0], edge[:, 1], (220, 30, 30))
        put(self.state.x, self.state.z, (0, 0, 0), 3)
        tick = self.state.after(Action.FORWARD)
        put((self.state.x + tick.x) / 2, (self.state.z + tick.z) / 2, (0, 0, 0), 2)
        return image

    # Seeing and moving.

    def _do(self, action: Action) -> Action:
        if action == Action.RELEASE and self._held is not None:
            # Where it is left, as believed: an obstacle, and another object's footprint when
            # choosing where to fetch from, until it is fetched again.
            self._released[self._tasks[0].instance] = self._held.corners(self.state)
        self._last_action = action
        return action

    def _pose(self) -> Pose2D:
        return Pose2D(self.state.x, self.state.z, self.state.yaw)

    def _update_pose(self, view: npt.NDArray[np.uint8]) -> None:
        action = self._last_action
        if action is not None and action in (Action.FORWARD, Action.BACKWARD, Action.LEFT, Action.RIGHT):
            if np.array_equal(view, self._last_view):
                self._stats["rejected"] += 1
                self._plan = []
                if self._phase == "wander" and self._wander:
                    self._wander[0] = Action.LEFT  # blocked ahead: turn, then go on
                moved = self.state.after(action)
                if self._held is not None:
                    # The held object (or the robot) hit something the map does not show: that
                    # motion from this pose is refused from now on.
                    self._refused.add((self.state.key(), action))
                elif action in (Action.FORWARD, Action.BACKWARD):
                    self._blocked_extra.append((2 * moved.x - self.state.x, 2 * moved.z - self.state.z))
            else:
                self.state = self.state.after(action)
        self._last_view = view.copy()

    def _observe(self, view: npt.NDArray[np.uint8], carrying: bool) -> None:
        pose = self._pose()
        if carrying and self._tasks:
            # The held object sits in front of the camera: keep its category out of the map.
            category = self._tasks[0].category
            kept = self.map.movable[category].copy()
            kept_instances = self.map.instance.copy()
            self.map.integrate(view, pose)
            self.map.movable[category] = kept
            self.map.instance[:] = kept_instances
        else:
            self.map.integrate(view, pose)
        self.map.visit(pose)

    # What the map and the goal say.

    def _make_tasks(self) -> list[_Task]:
        assert self.registration is not None
        tasks = []
        for instance, target in enumerate(self.goal.objects):
            x, z = self.registration.from_goal(target.col, target.row)
            tasks.append(
                _Task(
                    target,
                    instance,
                    CATEGORIES.index(target.category),
                    float(x),
                    float(z),
                    target.half_long / self.registration.scale,
                    target.half_short / self.registration.scale,
                )
            )
        return tasks

    def _solid(self, category: int) -> npt.NDArray[np.bool_]:
        """The map's cells of `category`'s bases seen as bases at least as often as free: a
        tall object's top edge, taken for a base, lands on the floor behind it, which other
        views see free.
        """
        counts = self.map.movable[category]
        solid: npt.NDArray[np.bool_] = (counts > 0) & (counts >= self.map.free)
        return solid

    def _object_points(self, task: _Task) -> npt.NDArray[np.float64]:
        """Start-frame points of the map's bases of `task`'s category, less those on a target
        already filled. All of them: a near face's bases share their cells with floor seen free,
        so `_solid` would drop the very bases a footprint is fitted to.
        """
        rows, cols = np.nonzero(self.map.movable[task.category])
        if self._told_apart[task.instance]:
            # Of several objects of its category: its own bases (seen under its top colour more
            # than under another's) and those near them no top was seen above (a top is seen
            # above a few of an object's bases only), else all those no top was seen above.
            mine, theirs = _mine_theirs(self.map, task.instance, rows, cols)
            own = (mine > 0) & (mine > theirs)
            pick = (mine == 0) & (theirs == 0)
            if own.any():
                x, z = self.map.centre_of(rows, cols)
                near = np.zeros(len(x), dtype=bool)
                reach = 2 * max(task.half_long, task.half_short)
                for i in np.nonzero(own)[0]:
                    near |= np.hypot(x - x[i], z - z[i]) <= reach
                pick = own | (pick & near)
            rows, cols = rows[pick], cols[pick]
        x, z = self.map.centre_of(rows, cols)
        keep = np.ones(len(x), dtype=bool)
        for done in self._placed:
            if done.category == task.category:
                keep &= np.hypot(x - done.x, z - done.z) > max(done.half_long, 0.3) + 0.2
        return np.stack([x[keep], z[keep]], axis=1)

    def _structure(
        self,
    ) -> Callable[[npt.NDArray[np.float64], npt.NDArray[np.float64]], npt.NDArray[np.bool_]]:
        """Whether start-frame points (x, z) lie on the goal image's static structure or outside
        its room (outside the image counts as outside).
        """
        solid = self._structure_pixels

        def on(x: npt.NDArray[np.float64], z: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
            r, c, inside = self._goal_pixels(x, z)
            hit = np.ones(inside.shape, dtype=bool)
            hit[inside] = solid[r[inside], c[inside]]
            return hit

        return on

    def _seen_free(
        self,
    ) -> Callable[[npt.NDArray[np.float64], npt.NDArray[np.float64]], npt.NDArray[np.bool_]]:
        """Whether start-frame points (x, z) lie on cells the map saw free more often than it saw
        any base there.
        """
        bases = self.map.static + self.map.movable.sum(axis=0)
        seen: npt.NDArray[np.bool_] = self.map.free > bases

        def on(x: npt.NDArray[np.float64], z: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
            row, col = self.map.cell_of(x, z)
            hit: npt.NDArray[np.bool_] = seen[row, col] & (row >= 0)
            return hit

        return on

    def _blocked(self, ignore: tuple[int, npt.NDArray[np.float64]] | None = None) -> npt.NDArray[np.bool_]:
        """The goal pixels a body may not cover: outside the room, static structure, the mapped
        movable objects, and where moves were rejected. `ignore`: (category, corners) an object
        about to be fetched, whose bases (those of its category within `_OWN_BASES` of its
        footprint `corners`) are left out: it moves with the robot.
        """
        assert self.registration is not None
        blocked: npt.NDArray[np.bool_] = self._structure_pixels.copy()
        size = blocked.shape[0]
        bases = self._movable_bases(ignore, solid=True)
        self._mark(blocked, bases[:, 0], bases[:, 1])
        if self._blocked_extra:
            xs, zs = zip(*self._blocked_extra, strict=True)
            self._mark(blocked, np.array(xs), np.array(zs))
        for instance, corners in self._released.items():
            # Objects left somewhere, where the agent believes they are (not the one about to be
            # fetched: it moves with the robot).
            if ignore is None or instance != self._tasks[0].instance:
                blocked |= self._rectangle_pixels(corners, size)
        return blocked

    def _room_for_held(
        self, blocked: npt.NDArray[np.bool_], corners: npt.NDArray[np.float64]
    ) -> npt.NDArray[np.bool_]:
        """`blocked` for the held object: not where it stands now (its footprint `corners`, as believed, may
        overlap what the map shows by its errors; it is there), nor on its target (the goal image
        shows it fits there, often against a wall or furniture).
        """
        assert self.registration is not None
        here = self._rectangle_pixels(corners, blocked.shape[0], grow=0.05)
        there = self._rectangle_pixels(self._target_rectangle(self._tasks[0]), blocked.shape[0], grow=0.05)
        return blocked & ~here & ~there

    def _rectangle_pixels(
        self, corners: npt.NDArray[np.float64], size: int, grow: float = 0.0
    ) -> npt.NDArray[np.bool_]:
        """(size, size) the goal pixels whose centres lie in the start-frame rectangle `corners`
        ((4, 2), in order) grown by `grow` metres each side.
        """
        assert self.registration is not None
        cx, cz, yaw, half_x, half_z = _pose_of(corners)
        rows, cols = np.mgrid[0:size, 0:size]
        x, z = self.registration.from_goal(cols + 0.5, rows + 0.5)
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dz = x - cx, z - cz
        lx, lz = np.abs(dx * c - dz * s), np.abs(dx * s + dz * c)
        inside: npt.NDArray[np.bool_] = (lx <= half_x + grow) & (lz <= half_z + grow)
        return inside

    def _mark(
        self, blocked: npt.NDArray[np.bool_], x: npt.NDArray[np.float64], z: npt.NDArray[np.float64]
    ) -> None:
        """Sets the goal pixels of start-frame points (x, z) in `blocked` (those inside it)."""
        r, c, inside = self._goal_pixels(x, z)
        blocked[r[inside], c[inside]] = True

    def _goal_pixels(
        self, x: npt.NDArray[np.float64], z: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], npt.NDArray[np.bool_]]:
        """The goal-image pixels (row, col) of start-frame points (x, z), and which are inside it."""
        assert self.registration is not None
        size = self.goal_rgb.shape[0]
        col, row = self.registration.to_goal(x, z)
        c, r = np.floor(col).astype(np.intp), np.floor(row).astype(np.intp)
        inside: npt.NDArray[np.bool_] = (c >= 0) & (c < size) & (r >= 0) & (r < size)
        return r, c, inside


def _mine_theirs(
    seen: TopDownMap, instance: int, rows: npt.NDArray[np.intp], cols: npt.NDArray[np.intp]
) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int32]]:
    """At cells (rows, cols) of map `seen`: the views that saw `instance`'s top above a base there,
    and the most that saw the top of any other object of its category.
    """
    category = seen.tops[instance][0]
    others = [i for i, t in enumerate(seen.tops) if t[0] == category and i != instance]
    mine = seen.instance[instance][rows, cols]
    theirs = seen.instance[others][:, rows, cols].max(axis=0, initial=0)
    return mine, theirs


def _outline(corners: npt.NDArray[np.float64], spacing: float = 0.05) -> npt.NDArray[np.float64]:
    """(n, 2) points every `spacing` metres or less along the edges of rectangle `corners`."""
    points = []
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        count = max(int(math.ceil(math.hypot(*(b - a)) / spacing)), 1)
        t = np.arange(count)[:, None] / count
        points.append(a + t * (b - a))
    return np.concatenate(points)


def _gap_to_rectangle(
    x: npt.NDArray[np.float64],
    z: npt.NDArray[np.float64],
    cx: npt.NDArray[np.float64] | float,
    cz: npt.NDArray[np.float64] | float,
    yaw: float,
    half_x: float,
    half_z: float,
) -> npt.NDArray[np.float64]:
    """The distance from points (x, z) to the rectangle(s) centred at (cx, cz) (0 inside)."""
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dz = x - cx, z - cz
    lx, lz = np.abs(dx * c - dz * s), np.abs(dx * s + dz * c)
    gap: npt.NDArray[np.float64] = np.hypot(np.maximum(lx - half_x, 0), np.maximum(lz - half_z, 0))
    return gap


def _relative(cx: float, cz: float, yaw: float, half_x: float, half_z: float, robot: State) -> HeldObject:
    """The footprint centred at (cx, cz) with `yaw` (start frame), as held by a robot at `robot`."""
    c, s = math.cos(robot.yaw), math.sin(robot.yaw)
    ahead = (cx - robot.x) * c - (cz - robot.z) * s
    right = (cx - robot.x) * s + (cz - robot.z) * c
    return HeldObject(ahead, right, yaw - robot.yaw, half_x, half_z)


def _pose_of(corners: npt.NDArray[np.float64]) -> tuple[float, float, float, float, float]:
    """The centre x, z, yaw and half sizes of the rectangle of (4, 2) `corners` in
    `planner.rectangle`'s order (the inverse of `planner.rectangle`).
    """
    centre = corners.mean(axis=0)
    axis_x = (corners[0] - corners[3]) / 2  # half the local x side, as a vector
    axis_z = (corners[0] - corners[1]) / 2
    yaw = math.atan2(-float(axis_x[1]), float(axis_x[0]))
    return float(centre[0]), float(centre[1]), yaw, float(np.hypot(*axis_x)), float(np.hypot(*axis_z))


def _gap_to_corners(
    x: npt.NDArray[np.float64], z: npt.NDArray[np.float64], corners: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """The distance from points (x, z) to the rectangle of (4, 2) `corners` in order (0 inside)."""
    return _gap_to_rectangle(x, z, *_pose_of(corners))
