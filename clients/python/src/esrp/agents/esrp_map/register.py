"""Registration: the transform from ESRP-MAP's own frame (the agent's start pose: origin at its
centre, yaw 0 along its heading) to the goal image's pixels.

The room's static structure (walls, doors, fixed furniture) is the same in the start layout and in
the target layout, so the map's static bases must fall on the goal image's static pixels. The
goal image is aligned with the world (image right +x, image down +z), and the agent starts at one
of the 16 lattice headings, so the rotation is one of 16; the scale is the goal image's pixels per
metre, within a quarter of what the margin implies (`GoalImage.metres_per_pixel`); the translation
is where the start pose is in the image. Each heading and scale is scored at every translation at
once, by correlation (FFT) of the map's points with two cost images of the goal: the distance to
the nearest static pixel (static bases) and a penalty where the goal shows no floor (free floor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .goal import BACKGROUND, STATIC, GoalImage
from .mapping import TopDownMap, floor_pixels

__all__ = ["Registration", "cost_of", "distance_to", "register"]

Floats = npt.NDArray[np.float64]

_COARSE = np.linspace(0.75, 1.30, 12)
"""Scales tried at every heading, as multiples of the margin's prior (within about ±25 %)."""
_FINE = np.linspace(-0.05, 0.05, 11)
"""Then around the best coarse scale of the two best headings, in steps of 1 %."""
_CAP = 6.0
"""Static bases farther than this from a goal static pixel (pixels) cost this much: an outlier
(furniture moved, or a base behind an edge) costs no more than a near miss."""
_OUTSIDE = _CAP
"""Cost of a free-floor point that lands outside the goal's room (on its background)."""
_ON_STATIC = 0.3 * _CAP
"""Cost of a free-floor point that lands on the goal's static pixels: less than outside, as the
floor under a table is seen free, but enough that a map shrunk onto furniture does not fit."""
_FREE_SHARE = 0.5
"""Weight of the free points' mean cost beside the static bases' mean cost (through a doorway the
floor goes on outside the room, so the term stays a minor one)."""


def distance_to(mask: npt.NDArray[np.bool_]) -> Floats:
    """The Euclidean distance (pixels, between centres) from each pixel to the nearest of `mask`'s
    (inf everywhere if it is empty).
    """
    rows, cols = np.nonzero(mask)
    out = np.full(mask.shape, np.inf)
    if len(rows) == 0:
        return out
    grid_r, grid_c = np.mgrid[0 : mask.shape[0], 0 : mask.shape[1]]
    for start in range(0, len(rows), 256):
        r = rows[start : start + 256, None, None]
        c = cols[start : start + 256, None, None]
        out = np.minimum(out, np.sqrt((grid_r - r) ** 2 + (grid_c - c) ** 2).min(axis=0))
    return out


@dataclass(frozen=True)
class Registration:
    """Start frame (metres) → goal image pixels: (col, row) = scale · R(heading) · (x, z) + (tx, tz).

    R(heading) turns the start frame's axes into the world's for a start yaw of heading · 22.5°
    (esrp-core's convention: a local (ahead, right) = (x, z) point is at world x = x cos + z sin,
    z = −x sin + z cos). `cost` is the best fit's (the static bases' mean distance to the goal's
    static pixels, capped, plus a share of the free points' outside the room), `runner_up` that of
    the best fit at another heading: their ratio says how sure the fit is.
    """

    heading: int
    scale: float
    tx: float
    tz: float
    cost: float
    runner_up: float

    def to_goal(self, x: npt.ArrayLike, z: npt.ArrayLike) -> tuple[Floats, Floats]:
        """Goal-image pixel coordinates (col, row) of start-frame points (x, z)."""
        wx, wz = _rotate(np.asarray(x, dtype=np.float64), np.asarray(z, dtype=np.float64), self.heading)
        return self.scale * wx + self.tx, self.scale * wz + self.tz

    def from_goal(self, col: npt.ArrayLike, row: npt.ArrayLike) -> tuple[Floats, Floats]:
        """Start-frame points (x, z) of goal-image pixel coordinates (col, row)."""
        wx = (np.asarray(col, dtype=np.float64) - self.tx) / self.scale
        wz = (np.asarray(row, dtype=np.float64) - self.tz) / self.scale
        return _rotate(wx, wz, -self.heading)


def _rotate(x: Floats, z: Floats, heading: int) -> tuple[Floats, Floats]:
    yaw = heading * math.pi / 8
    c, s = math.cos(yaw), math.sin(yaw)
    return x * c + z * s, -x * s + z * c


def register(world: TopDownMap, goal: GoalImage, goal_rgb: npt.NDArray[np.uint8]) -> Registration:
    """The best transform from `world` (a map in the start frame) to the goal image.

    Raises `ValueError` when the map has no static bases to register.
    """
    sx, sz, fx, fz = _points(world)
    resolution = goal.labels.shape[0]
    point_cost, free_cost = _cost_images(goal, goal_rgb)
    prior = 1.0 / goal.metres_per_pixel()
    rotated = {h: (_rotate(sx, sz, h), _rotate(fx, fz, h)) for h in range(16)}

    def fit(heading: int, scale: float) -> tuple[float, int, float, float, float]:
        (rsx, rsz), (rfx, rfz) = rotated[heading]
        cost, tx, tz = _best_translation(
            scale * rsx, scale * rsz, scale * rfx, scale * rfz, point_cost, free_cost, resolution
        )
        return cost, heading, scale, tx, tz

    # Per heading, its best fit over the coarse scales; then the two best headings refined.
    best = [min(fit(h, prior * factor) for factor in _COARSE) for h in range(16)]
    best.sort()
    for i in range(2):
        _, heading, scale, _, _ = best[i]
        best[i] = min([best[i], *(fit(heading, scale * (1 + step)) for step in _FINE)])
    best.sort()
    cost, heading, scale, tx, tz = best[0]
    return Registration(heading, scale, tx, tz, cost, best[1][0])


def cost_of(fit: Registration, world: TopDownMap, goal: GoalImage, goal_rgb: npt.NDArray[np.uint8]) -> float:
    """What `register` would score transform `fit` on `world` (its cost at that heading, scale
    and translation): to compare an earlier registration with a new one on the map as it is now.
    """
    sx, sz, fx, fz = _points(world)
    point_cost, free_cost = _cost_images(goal, goal_rgb)
    size = point_cost.shape[0]

    def mean(x: Floats, z: Floats, image: Floats, outside: float) -> float:
        if len(x) == 0:
            return 0.0
        col, row = fit.to_goal(x, z)
        c, r = np.floor(col).astype(np.intp), np.floor(row).astype(np.intp)
        inside = (c >= 0) & (c < size) & (r >= 0) & (r < size)
        values = np.full(len(c), outside)
        values[inside] = image[r[inside], c[inside]]
        return float(values.mean())

    return mean(sx, sz, point_cost, _CAP) + _FREE_SHARE * mean(fx, fz, free_cost, _OUTSIDE)


def _points(world: TopDownMap) -> tuple[Floats, Floats, Floats, Floats]:
    """The map's static bases and (a sample of) its free floor, as start-frame points."""
    static_rows, static_cols = np.nonzero(world.static)
    if len(static_rows) == 0:
        raise ValueError("the map has no static bases yet: look around first")
    sx, sz = world.centre_of(static_rows, static_cols)
    free_rows, free_cols = np.nonzero(world.free)
    fx, fz = world.centre_of(free_rows, free_cols)
    # Free floor is dense; a sample of it is as informative and keeps the rasters light.
    if len(fx) > 4000:
        keep = np.linspace(0, len(fx) - 1, 4000).astype(np.intp)
        fx, fz = fx[keep], fz[keep]
    return sx, sz, fx, fz


def _cost_images(goal: GoalImage, goal_rgb: npt.NDArray[np.uint8]) -> tuple[Floats, Floats]:
    """The goal's cost of a static base (its distance to the goal's static pixels, capped) and of
    a free point (outside the room, on static structure, or nothing) at each pixel.
    """
    static = (goal.labels == STATIC) & ~floor_pixels(goal_rgb)
    point_cost = np.minimum(distance_to(static), _CAP)
    free_cost = np.where(goal.labels == BACKGROUND, _OUTSIDE, np.where(static, _ON_STATIC, 0.0))
    return point_cost, free_cost


def _best_translation(
    sc: Floats,
    sr: Floats,
    fc: Floats,
    fr: Floats,
    point_cost: Floats,
    free_cost: Floats,
    resolution: int,
) -> tuple[float, float, float]:
    """The translation (tx, tz) minimising the summed costs of the points (static: point_cost,
    free: free_cost) placed at their (col, row) + (tx, tz), over whole-pixel translations that keep
    the start pose inside the image; (cost, tx, tz). A point off the image costs the most.
    """
    # Points rounded to pixels, relative to the origin (the start pose): a point at continuous
    # (col, row) c lands on the image at c + T, in pixel floor(c) + T for a whole-pixel T.
    s_c, s_r = np.floor(sc).astype(np.intp), np.floor(sr).astype(np.intp)
    f_c, f_r = np.floor(fc).astype(np.intp), np.floor(fr).astype(np.intp)
    lo_c = int(min(s_c.min(), f_c.min(initial=0), 0))
    lo_r = int(min(s_r.min(), f_r.min(initial=0), 0))
    hi_c = int(max(s_c.max(), f_c.max(initial=0), 0))
    hi_r = int(max(s_r.max(), f_r.max(initial=0), 0))
    span = max(hi_c - lo_c, hi_r - lo_r) + 1
    # The image sits at offset (-lo_r, -lo_c) in a canvas of at least span + resolution pixels, so
    # that a raster pixel q = p - lo placed with shift t lands on canvas pixel q + t, which is
    # image pixel p + t: the shift is the translation T itself, and for T on the image no
    # placement wraps around. Off the image a static base costs _CAP and a free point the penalty.
    size = 1 << int(math.ceil(math.log2(span + resolution)))
    canvas_point = np.full((size, size), _CAP)
    canvas_free = np.full((size, size), _OUTSIDE)
    canvas_point[-lo_r : -lo_r + resolution, -lo_c : -lo_c + resolution] = point_cost
    canvas_free[-lo_r : -lo_r + resolution, -lo_c : -lo_c + resolution] = free_cost
    # Weighted so that the sum is the static bases' mean cost plus a share of the free points'.
    points = np.zeros((size, size))
    np.add.at(points, (s_r - lo_r, s_c - lo_c), 1.0 / len(s_c))
    frees = np.zeros((size, size))
    if len(f_c):
        np.add.at(frees, (f_r - lo_r, f_c - lo_c), _FREE_SHARE / len(f_c))
    # total[t] = Σ_q raster[q] · cost[q + t], the circular cross-correlation.
    spectrum = np.fft.rfft2(canvas_point) * np.conj(np.fft.rfft2(points))
    spectrum += np.fft.rfft2(canvas_free) * np.conj(np.fft.rfft2(frees))
    total = np.fft.irfft2(spectrum, s=(size, size))[:resolution, :resolution]  # the start pose on the image
    index = int(np.argmin(total))
    row, col = divmod(index, resolution)
    return float(total[row, col]), float(col), float(row)
