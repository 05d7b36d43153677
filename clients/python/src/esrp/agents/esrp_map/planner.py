"""ESRP-MAP's motion planning: A* over the action lattice (0.25 m moves along 16 headings, 22.5°
turns) in the agent's start frame, against an occupancy grid of the goal image's pixels.

The grid is the goal image's static structure (walls, doors, fixed furniture, seen from above)
plus what the agent marks (movable objects, surprises). The robot is a disc: the grid inflated by
its radius (`Occupancy`). A held object is its oriented rectangle, rigidly attached to the robot
(`HeldObject`): for each of its 32 orientations of the search (its yaw changes by 22.5° a turn,
and turns are checked at four intermediate angles) the grid is dilated by the rectangle
(`CarriedSpace`, a configuration space), so that its centre alone is checked. A motion is free
when every point of its sweep, sampled every half pixel or so, is free: the robot's centre along
a move, and the held object's centre (and angle) along a move or a turn's arc.
"""

from __future__ import annotations

import copy
import heapq
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..._values import Action
from .register import Registration

__all__ = [
    "KEY_CELL",
    "STEP",
    "Reach",
    "CarriedSpace",
    "HeldObject",
    "Occupancy",
    "State",
    "inflate",
    "plan",
    "reachable",
    "rectangle",
    "rectangle_iou",
]

Floats = npt.NDArray[np.float64]

STEP = 0.25
"""Metres a move covers."""
KEY_CELL = 0.10
"""Metres of the grid on which the search merges poses of one heading."""


@dataclass(frozen=True)
class State:
    """A pose on the lattice: position in the start frame (metres) and heading index (yaw = k · π/8)."""

    x: float
    z: float
    k: int

    @property
    def yaw(self) -> float:
        """The heading in radians."""
        return self.k * math.pi / 8

    def key(self) -> tuple[int, int, int]:
        """The state's cell for the search's closed set (10 cm, heading): lattice poses closer than
        that are one for the search, which keeps it to a few thousand states a room.
        """
        return (round(self.x / KEY_CELL), round(self.z / KEY_CELL), self.k % 16)

    def after(self, action: Action) -> State:
        """The pose an accepted `action` leads to (fetch and release leave it)."""
        if action == Action.LEFT:
            return State(self.x, self.z, (self.k + 1) % 16)
        if action == Action.RIGHT:
            return State(self.x, self.z, (self.k - 1) % 16)
        if action in (Action.FORWARD, Action.BACKWARD):
            sign = 1.0 if action == Action.FORWARD else -1.0
            return State(
                self.x + sign * STEP * math.cos(self.yaw), self.z - sign * STEP * math.sin(self.yaw), self.k
            )
        return self


def inflate(mask: npt.NDArray[np.bool_], radius: float) -> npt.NDArray[np.bool_]:
    """`mask` grown by a disc of `radius` pixels."""
    out: npt.NDArray[np.bool_] = mask.copy()
    reach = int(math.ceil(radius))
    rows, cols = mask.shape
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            if (dr, dc) == (0, 0) or dr * dr + dc * dc > radius * radius:
                continue
            shifted = np.zeros_like(mask)
            shifted[max(dr, 0) : rows + min(dr, 0), max(dc, 0) : cols + min(dc, 0)] = mask[
                max(-dr, 0) : rows + min(-dr, 0), max(-dc, 0) : cols + min(-dc, 0)
            ]
            out |= shifted
    return out


class Occupancy:
    """Blocked cells on the goal image's pixel grid, for a moving body of `radius` metres.

    `blocked`: (R, R) bool, the obstacles' own pixels (not yet inflated). Outside the image is
    blocked (the room lies inside it).
    """

    def __init__(self, blocked: npt.NDArray[np.bool_], registration: Registration, radius: float) -> None:
        self.registration = registration
        self.radius = radius
        self.obstacles = blocked
        # A pixel's centre is free when no obstacle pixel's centre lies within the radius plus half
        # a pixel's diagonal (so that the obstacle's whole pixel clears the body).
        self.inflated = inflate(blocked, radius * registration.scale + 0.71)
        self._pixel = _Pixels(registration, blocked.shape[0])
        self._moves: dict[tuple[int, int], tuple[Floats, Floats]] = {}

    def move_free(self, state: State, action: Action) -> bool:
        """Whether the body may make move `action` (forward or backward) from `state`: as
        `segment_free`, with the samples' offsets computed once per heading and direction.
        """
        key = (state.k % 16, int(action))
        offsets = self._moves.get(key)
        if offsets is None:
            child = state.after(action)
            steps = max(int(STEP / 0.025), 1)
            t = np.linspace(0.0, 1.0, steps + 1)
            offsets = (t * (child.x - state.x), t * (child.z - state.z))
            self._moves[key] = offsets
        cells = self._pixel.of(state.x + offsets[0], state.z + offsets[1])
        return cells is not None and not bool(self.inflated[cells].any())

    def free(self, x: npt.ArrayLike, z: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Whether the body's centre may be at start-frame points (x, z)."""
        col, row = self.registration.to_goal(x, z)
        c, r = np.floor(col).astype(np.intp), np.floor(row).astype(np.intp)
        size = self.inflated.shape[0]
        inside = (c >= 0) & (c < size) & (r >= 0) & (r < size)
        out = np.zeros(np.shape(c), dtype=np.bool_)
        out[inside] = ~self.inflated[r[inside], c[inside]]
        return out

    def segment_free(self, x0: float, z0: float, x1: float, z1: float) -> bool:
        """Whether the body may move straight from (x0, z0) to (x1, z1) (sampled every 2.5 cm)."""
        steps = max(int(math.hypot(x1 - x0, z1 - z0) / 0.025), 1)
        t = np.linspace(0.0, 1.0, steps + 1)
        return bool(self.free(x0 + t * (x1 - x0), z0 + t * (z1 - z0)).all())


@dataclass(frozen=True)
class HeldObject:
    """A held object's footprint relative to the robot: its centre `ahead` and `right` metres from
    the robot's centre, its yaw `rel_yaw` radians more than the robot's (esrp-core's footprint
    convention: its local x axis along (cos yaw, −sin yaw)), and its half sizes along its local x
    and z axes, metres.
    """

    ahead: float
    right: float
    rel_yaw: float
    half_x: float
    half_z: float

    def centre(self, state: State, extra: float = 0.0) -> tuple[float, float]:
        """Its centre in the start frame, held by a robot at `state` turned `extra` turns more."""
        return held_centre(state, (self.ahead, self.right), extra)

    def yaw(self, state: State, extra: float = 0.0) -> float:
        """Its yaw in the start frame, held by a robot at `state` turned `extra` turns more."""
        return state.yaw + extra * math.pi / 8 + self.rel_yaw

    def corners(self, state: State, extra: float = 0.0) -> npt.NDArray[np.float64]:
        """(4, 2) its footprint's corners in the start frame, in order around it."""
        cx, cz = self.centre(state, extra)
        return rectangle(cx, cz, self.half_x, self.half_z, self.yaw(state, extra))


def rectangle(cx: float, cz: float, half_x: float, half_z: float, yaw: float) -> npt.NDArray[np.float64]:
    """(4, 2) the corners, in order around it, of the footprint centred at (cx, cz) with half sizes
    `half_x`, `half_z` along its local axes and `yaw` (esrp-core's convention).
    """
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([(1, 1), (1, -1), (-1, -1), (-1, 1)], dtype=np.float64) * (half_x, half_z)
    x = cx + local[:, 0] * c + local[:, 1] * s
    z = cz - local[:, 0] * s + local[:, 1] * c
    return np.stack([x, z], axis=1)


def _clip(
    polygon: list[tuple[float, float]], a: tuple[float, float], b: tuple[float, float]
) -> list[tuple[float, float]]:
    """The part of convex `polygon` on the left of the line a → b (Sutherland–Hodgman)."""

    def side(p: tuple[float, float]) -> float:
        return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])

    out: list[tuple[float, float]] = []
    for i, p in enumerate(polygon):
        q = polygon[(i + 1) % len(polygon)]
        sp, sq = side(p), side(q)
        if sp >= 0:
            out.append(p)
        if (sp >= 0) != (sq >= 0):
            t = sp / (sp - sq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def _area(polygon: list[tuple[float, float]] | npt.NDArray[np.float64]) -> float:
    """The signed area of a polygon (positive when its corners go counter-clockwise in (x, z))."""
    total = 0.0
    for i in range(len(polygon)):
        x0, z0 = polygon[i]
        x1, z1 = polygon[(i + 1) % len(polygon)]
        total += x0 * z1 - x1 * z0
    return total / 2


def rectangle_iou(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> float:
    """The intersection over union of two rectangles given by their (4, 2) corners in order."""
    first = [(float(x), float(z)) for x, z in a]
    second = [(float(x), float(z)) for x, z in b]
    if _area(first) < 0:
        first.reverse()
    if _area(second) < 0:
        second.reverse()
    inside = first
    for i in range(4):
        inside = _clip(inside, second[i], second[(i + 1) % 4])
        if not inside:
            return 0.0
    meet = abs(_area(inside))
    union = abs(_area(first)) + abs(_area(second)) - meet
    return meet / union if union > 0 else 0.0


class CarriedSpace:
    """Where a held object's centre may be, on the goal image's pixel grid: `blocked` dilated by the
    object's rectangle at each of the 32 yaws `rel_yaw + m · π/32` (m mod 32: a rectangle is the
    same turned half a turn) that the search meets, computed when first asked for.

    `margin`: metres added to each half size (negative to shrink it: the goal image's pixels are
    coarse, and an object's target often touches a wall).
    """

    BINS = 32

    def __init__(
        self,
        blocked: npt.NDArray[np.bool_],
        registration: Registration,
        held: HeldObject,
        margin: float = 0.0,
    ) -> None:
        self.blocked = blocked
        self.registration = registration
        self.held = held
        self.margin = margin
        self._spaces: dict[int, npt.NDArray[np.bool_]] = {}
        size = blocked.shape[0]
        reach = (
            int(
                math.ceil(
                    math.hypot(held.half_x + max(margin, 0), held.half_z + max(margin, 0))
                    * registration.scale
                )
            )
            + 2
        )
        self._reach = reach
        self._fft_shape = (size + 2 * reach, size + 2 * reach)
        self._blocked_fft = np.fft.rfft2(blocked.astype(np.float64), self._fft_shape)
        self._offset = 0
        self._base_yaw = held.rel_yaw
        self._stack = np.zeros((self.BINS, size, size), dtype=np.bool_)
        self._pixel = _Pixels(registration, size)
        # (heading, action) → the held centre's samples relative to the robot's centre, and their
        # yaw bins, for this held object (reset by `holding`).
        self._sweeps: dict[tuple[int, int], tuple[Floats, Floats, npt.NDArray[np.intp]]] = {}

    def holding(self, held: HeldObject) -> CarriedSpace:
        """This space for `held`, the same object held another way (its rel_yaw differs from this
        one's by a multiple of a quarter turn), sharing the dilations computed.
        """
        other = copy.copy(self)
        other.held = held
        other._offset = round((held.rel_yaw - self._base_yaw) / (math.pi / self.BINS))
        other._sweeps = {}
        return other

    def _bin(self, state: State, extra: float) -> int:
        """The yaw bin of the object held at `state` turned `extra` turns more (extra in quarters)."""
        return (round((state.k + extra) * 4) + self._offset) % self.BINS

    def space(self, index: int) -> npt.NDArray[np.bool_]:
        """(R, R) the pixels the object's centre may not be in at yaw bin `index`."""
        found = self._spaces.get(index)
        if found is None:
            found = self._dilate(index)
            self._spaces[index] = found
            self._stack[index] = found
        return found

    def _dilate(self, index: int) -> npt.NDArray[np.bool_]:
        fit = self.registration
        reach = self._reach
        yaw = self._base_yaw + index * math.pi / self.BINS
        # Each kernel pixel's offset from the centre pixel, in start-frame metres.
        dr, dc = np.mgrid[-reach : reach + 1, -reach : reach + 1].astype(np.float64)
        x0, z0 = fit.from_goal(0.0, 0.0)
        x, z = fit.from_goal(dc, dr)
        dx, dz = x - x0, z - z0
        c, s = math.cos(yaw), math.sin(yaw)
        local_x = dx * c - dz * s
        local_z = dx * s + dz * c
        kernel = (np.abs(local_x) <= self.held.half_x + self.margin) & (
            np.abs(local_z) <= self.held.half_z + self.margin
        )
        full = np.fft.irfft2(
            self._blocked_fft * np.fft.rfft2(kernel.astype(np.float64), self._fft_shape), self._fft_shape
        )
        size = self.blocked.shape[0]
        return full[reach : reach + size, reach : reach + size] > 0.5

    def free(
        self, x: npt.ArrayLike, z: npt.ArrayLike, index: int | npt.NDArray[np.intp]
    ) -> npt.NDArray[np.bool_]:
        """Whether the object's centre may be at start-frame points (x, z) at yaw bins `index`."""
        col, row = self.registration.to_goal(x, z)
        c, r = np.floor(col).astype(np.intp), np.floor(row).astype(np.intp)
        size = self.blocked.shape[0]
        inside = (c >= 0) & (c < size) & (r >= 0) & (r < size)
        out = np.zeros(np.shape(c), dtype=np.bool_)
        bins = np.broadcast_to(np.asarray(index), np.shape(c))
        for b in np.unique(bins[inside]):
            here = inside & (bins == b)
            out[here] = ~self.space(int(b))[r[here], c[here]]
        return out

    def move_free(self, state: State, action: Action) -> bool:
        """Whether move `action` (forward or backward) from `state` keeps the object clear: its
        centre sampled about every half pixel.
        """
        key = (state.k % 16, int(action))
        sweep = self._sweeps.get(key)
        if sweep is None:
            child = state.after(action)
            x0, z0 = self.held.centre(State(0.0, 0.0, state.k))
            dx, dz = child.x - state.x, child.z - state.z
            pixels = math.hypot(dx, dz) * self.registration.scale
            t = np.linspace(0.0, 1.0, max(int(pixels * 2), 1) + 1)
            sweep = self._sweep(x0 + t * dx, z0 + t * dz, np.full(len(t), self._bin(state, 0)))
            self._sweeps[key] = sweep
        return self._clear(state, sweep)

    def turn_free(self, state: State, sign: int) -> bool:
        """Whether a turn (sign +1 left, −1 right) from `state` keeps the object clear along its
        arc: its centre sampled about every half pixel, its yaw in the nearest quarter turn bin.
        """
        key = (state.k % 16, 2 if sign > 0 else 3)
        sweep = self._sweeps.get(key)
        if sweep is None:
            arc = math.hypot(self.held.ahead, self.held.right) * math.pi / 8 * self.registration.scale
            count = max(int(arc * 2), 4)
            extras = sign * np.linspace(0.0, 1.0, count + 1)
            yaw = state.k * math.pi / 8 + extras * math.pi / 8
            ahead, right = self.held.ahead, self.held.right
            x = ahead * np.cos(yaw) + right * np.sin(yaw)
            z = -ahead * np.sin(yaw) + right * np.cos(yaw)
            bins = np.array([self._bin(state, float(e)) for e in extras], dtype=np.intp)
            sweep = self._sweep(x, z, bins)
            self._sweeps[key] = sweep
        return self._clear(state, sweep)

    def _sweep(
        self, x: Floats, z: Floats, bins: npt.NDArray[np.intp]
    ) -> tuple[Floats, Floats, npt.NDArray[np.intp]]:
        """A sweep's samples (relative to the robot), with every bin they need computed."""
        for index in np.unique(bins):
            self.space(int(index))
        return x, z, bins

    def _clear(self, state: State, sweep: tuple[Floats, Floats, npt.NDArray[np.intp]]) -> bool:
        x, z, bins = sweep
        cells = self._pixel.of(state.x + x, state.z + z)
        return cells is not None and not bool(self._stack[bins, cells[0], cells[1]].any())


class _Pixels:
    """Start-frame points → goal-image pixels (row, col), the registration's affine map inlined."""

    def __init__(self, registration: Registration, size: int) -> None:
        yaw = registration.heading * math.pi / 8
        c, s = math.cos(yaw), math.sin(yaw)
        self.a, self.b = registration.scale * c, registration.scale * s
        self.tx, self.tz = registration.tx, registration.tz
        self.size = size

    def of(self, x: Floats, z: Floats) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]] | None:
        """The pixels (row, col) of points (x, z), or None when one lies outside the image."""
        col = np.floor(self.a * x + self.b * z + self.tx).astype(np.intp)
        row = np.floor(-self.b * x + self.a * z + self.tz).astype(np.intp)
        if col.min() < 0 or row.min() < 0 or col.max() >= self.size or row.max() >= self.size:
            return None
        return row, col


def plan(
    start: State,
    occupancy: Occupancy,
    reached: Callable[[State], bool],
    heuristic: Callable[[State], float],
    *,
    carried: CarriedSpace | None = None,
    refused: set[tuple[tuple[int, int, int], Action]] | None = None,
    max_expansions: int = 20000,
) -> list[Action] | None:
    """The shortest action sequence from `start` to a state where `reached` holds, or None when
    none is found within `max_expansions` states. `heuristic` estimates the actions left (admissible
    for the shortest). With `carried`, the robot holds an object that must stay clear in it along
    every move and turn. `refused`: (state key, action) pairs known to be rejected (tried before).
    """
    opened = pushed = 0
    # (estimate, cost, push order, state): the order breaks ties, states are never compared.
    frontier: list[tuple[float, int, int, State]] = [(heuristic(start), 0, 0, start)]
    costs = {start.key(): 0}
    parents: dict[tuple[int, int, int], tuple[tuple[int, int, int], Action, State]] = {}
    states = {start.key(): start}
    while frontier:
        _, cost, _, state = heapq.heappop(frontier)
        key = state.key()
        if cost > costs.get(key, math.inf):
            continue
        if reached(state):
            return _path(parents, key)
        opened += 1
        if opened > max_expansions:
            return None
        for action in (Action.FORWARD, Action.BACKWARD, Action.LEFT, Action.RIGHT):
            if refused and (key, action) in refused:
                continue
            child = state.after(action)
            if not _allowed(state, action, occupancy, carried):
                continue
            child_key = child.key()
            if cost + 1 < costs.get(child_key, math.inf):
                costs[child_key] = cost + 1
                parents[child_key] = (key, action, child)
                states[child_key] = child
                pushed += 1
                heapq.heappush(frontier, (cost + 1 + heuristic(child), cost + 1, pushed, child))
    return None


@dataclass
class Reach:
    """The states a breadth-first search reached: each one's cost (actions from the start) and how
    it was reached, by state key.
    """

    states: dict[tuple[int, int, int], State]
    costs: dict[tuple[int, int, int], int]
    parents: dict[tuple[int, int, int], tuple[tuple[int, int, int], Action, State]]

    def path_to(self, key: tuple[int, int, int]) -> list[Action]:
        """The actions from the start to the state of `key`."""
        return _path(self.parents, key)


def reachable(
    start: State,
    occupancy: Occupancy,
    *,
    max_states: int = 12000,
    refused: set[tuple[tuple[int, int, int], Action]] | None = None,
) -> Reach:
    """Every state the robot alone can reach from `start` in `occupancy`, nearest first, up to
    `max_states` of them.
    """
    reach = Reach({start.key(): start}, {start.key(): 0}, {})
    queue = deque([start])
    while queue and len(reach.states) < max_states:
        state = queue.popleft()
        key = state.key()
        cost = reach.costs[key]
        for action in (Action.FORWARD, Action.BACKWARD, Action.LEFT, Action.RIGHT):
            if refused and (key, action) in refused:
                continue
            child = state.after(action)
            child_key = child.key()
            if child_key in reach.costs or not _allowed(state, action, occupancy, None):
                continue
            reach.states[child_key] = child
            reach.costs[child_key] = cost + 1
            reach.parents[child_key] = (key, action, child)
            queue.append(child)
    return reach


def _allowed(
    state: State,
    action: Action,
    occupancy: Occupancy,
    carried: CarriedSpace | None,
) -> bool:
    moves = action in (Action.FORWARD, Action.BACKWARD)
    if moves and not occupancy.move_free(state, action):
        return False
    if carried is None:
        return True
    if moves:
        return carried.move_free(state, action)
    return carried.turn_free(state, 1 if action == Action.LEFT else -1)


def held_centre(state: State, carry: tuple[float, float], extra: float = 0.0) -> tuple[float, float]:
    """The start-frame point `carry` = (ahead, right) metres from a robot at `state` (its yaw plus
    `extra` turns of 22.5°).
    """
    yaw = state.yaw + extra * math.pi / 8
    ahead, right = carry
    return state.x + ahead * math.cos(yaw) + right * math.sin(yaw), state.z - ahead * math.sin(
        yaw
    ) + right * math.cos(yaw)


def _path(
    parents: dict[tuple[int, int, int], tuple[tuple[int, int, int], Action, State]], key: tuple[int, int, int]
) -> list[Action]:
    actions: list[Action] = []
    while key in parents:
        key, action, _ = parents[key]
        actions.append(action)
    actions.reverse()
    return actions
