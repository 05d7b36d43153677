"""ESRP-MAP's motion planning: A* over the action lattice (0.25 m moves along 16 headings, 22.5°
turns) in the agent's start frame, against an occupancy grid of the goal image's pixels.

The grid is the goal image's static structure (walls, doors, fixed furniture, seen from above)
plus what the agent marks (movable objects, surprises), inflated by the moving body's radius: the
robot's 0.30 m, or with a held object the radius of the disc about the robot's centre that holds
both. A motion is free when every point of its sweep, sampled every few centimetres, is in free
cells; a turn in place sweeps nothing for the robot alone, and for a held object the arc its
centre travels is checked too (a disc that holds the object covers its rotation).
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..._values import Action
from .register import Registration

__all__ = ["KEY_CELL", "STEP", "Occupancy", "State", "inflate", "plan"]

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


def plan(
    start: State,
    occupancy: Occupancy,
    reached: Callable[[State], bool],
    heuristic: Callable[[State], float],
    *,
    carry: tuple[float, float] | None = None,
    carried: Occupancy | None = None,
    max_expansions: int = 20000,
) -> list[Action] | None:
    """The shortest action sequence from `start` to a state where `reached` holds, or None when
    none is found within `max_expansions` states. `heuristic` estimates the actions left (admissible
    for the shortest). With `carry`, a held object's centre at (ahead, right) metres from the robot:
    its centre must stay free in `carried` (an occupancy for the object's own radius) along every
    move and turn.
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
            child = state.after(action)
            if not _allowed(state, child, action, occupancy, carry, carried):
                continue
            child_key = child.key()
            if cost + 1 < costs.get(child_key, math.inf):
                costs[child_key] = cost + 1
                parents[child_key] = (key, action, child)
                states[child_key] = child
                pushed += 1
                heapq.heappush(frontier, (cost + 1 + heuristic(child), cost + 1, pushed, child))
    return None


def _allowed(
    state: State,
    child: State,
    action: Action,
    occupancy: Occupancy,
    carry: tuple[float, float] | None,
    carried: Occupancy | None,
) -> bool:
    moves = action in (Action.FORWARD, Action.BACKWARD)
    if moves and not occupancy.segment_free(state.x, state.z, child.x, child.z):
        return False
    if carry is None or carried is None:
        return True
    if action in (Action.FORWARD, Action.BACKWARD):
        x0, z0 = held_centre(state, carry)
        x1, z1 = held_centre(child, carry)
        return carried.segment_free(x0, z0, x1, z1)
    # A turn: the held object's centre travels an arc about the robot's centre.
    sign = 1 if action == Action.LEFT else -1
    points = [
        held_centre(State(state.x, state.z, state.k), carry, extra=sign * step / 8) for step in range(9)
    ]
    xs, zs = zip(*points, strict=True)
    return bool(carried.free(np.array(xs), np.array(zs)).all())


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
