"""ESRP-MAP's top-down map, built from egocentric views at known poses.

Each view's pixels are classified by colour (`goal.classify`, and the floor's own colour): a floor
pixel's ray meets the floor where `FloorProjection` says, so that floor point is free; a pixel that
is not floor, sitting right above a floor pixel in its column, is where an obstacle stands on the
floor (its base), so that floor point is occupied, by static structure (walls, doors, fixed
furniture) or by a movable object of its category. Pixels of an obstacle's sides and top project
beyond it and are not used. Points farther than `max_range` (3 m) are left out: a pixel row
covers (h² + d²) / h · 90°/R of floor at distance d (h: the camera's height), 10 cm at 3 m and
128 px, 17 cm at 4 m, and a base is placed up to a row beyond where it stands. Furniture on
legs shows the floor beneath it and then its top's front edge, which this takes for a base: that
edge's ray meets the floor beyond the object, by a factor h / (h − edge height). The static bases
are good for walls (what registration needs), the goal image, seen from above, gives the fixed
furniture's whole outline, and a movable object's bases lie on or behind it.

The map is a grid of square cells in a frame the caller chooses (the agent's start frame, or the
world's in tests), laid out as the goal image is: column = (x − min_x) / cell, row =
(z − min_z) / cell. Each cell counts the views that saw it free and the views that saw an
obstacle's base in it, by kind.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from .geometry import FloorProjection, Pose2D
from .goal import CATEGORIES, STATIC, TOP_SHADE, classify

__all__ = ["FLOOR_RGB", "TopDownMap", "floor_pixels"]

FLOOR_RGB = np.round(np.array([0.72, 0.66, 0.56]) * TOP_SHADE * 255)
"""The floor's colour in every view: esrp-render's floor colour under the shade of upward faces."""

_FLOOR_TOLERANCE = 3
"""Largest per-channel difference from `FLOOR_RGB` of a floor pixel (rounding, rasterisers)."""


def floor_pixels(rgb: npt.NDArray[np.uint8]) -> npt.NDArray[np.bool_]:
    """The pixels of `rgb` ((..., 3) uint8) that show the floor."""
    difference = np.abs(rgb.astype(np.int16) - FLOOR_RGB.astype(np.int16))
    return np.asarray((difference <= _FLOOR_TOLERANCE).all(axis=-1))


class TopDownMap:
    """Free space and obstacle bases seen from egocentric views, on a grid of `cell`-metre cells
    covering `size` metres square centred on (`centre_x`, `centre_z`).

    Attributes:
        free: (N, N) views that saw each cell's floor.
        static: (N, N) views that saw static structure stand in each cell.
        movable: (len(CATEGORIES), N, N) views that saw a movable object of each category there.
        instance: (len(tops), N, N) views that saw, of those bases, one whose object shows the top
            colour `tops[i]` above it in the view (the same column, one run of its category's
            pixels): which of several objects of a category a base belongs to.

    `tops`: (category index, RGB) per object to tell apart: the colour of its top faces, which a
    view shows exactly as the goal image does (upward faces are shaded alike).
    """

    def __init__(
        self,
        resolution: int = 128,
        *,
        cell: float = 0.05,
        size: float = 24.0,
        centre_x: float = 0.0,
        centre_z: float = 0.0,
        max_range: float = 3.0,
        tops: Sequence[tuple[int, tuple[int, int, int]]] = (),
    ) -> None:
        if cell <= 0 or size <= cell:
            raise ValueError(f"cell {cell} m and size {size} m: need 0 < cell < size")
        self.cell = cell
        self.cells = int(np.ceil(size / cell))
        self.min_x = centre_x - self.cells * cell / 2
        self.min_z = centre_z - self.cells * cell / 2
        self.max_range = max_range
        self.projection = FloorProjection(resolution)
        shape = (self.cells, self.cells)
        self.free = np.zeros(shape, dtype=np.int32)
        self.static = np.zeros(shape, dtype=np.int32)
        self.movable = np.zeros((len(CATEGORIES), *shape), dtype=np.int32)
        self.tops = list(tops)
        self.instance = np.zeros((len(self.tops), *shape), dtype=np.int32)
        below = self.projection.floor_mask()
        near = np.zeros_like(below)
        near[below] = np.hypot(self.projection.ahead[below], self.projection.right[below]) <= max_range
        self._usable = near
        # A pixel is a base candidate when the pixel below it (same column) is in the image.
        self._has_below = np.zeros_like(below)
        self._has_below[:-1, :] = True

    def cell_of(
        self, x: npt.ArrayLike, z: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
        """The (row, col) of the cells holding floor points (x, z) (outside the grid: −1)."""
        col = np.floor((np.asarray(x, dtype=np.float64) - self.min_x) / self.cell)
        row = np.floor((np.asarray(z, dtype=np.float64) - self.min_z) / self.cell)
        inside = (col >= 0) & (col < self.cells) & (row >= 0) & (row < self.cells)
        return np.where(inside, row, -1).astype(np.intp), np.where(inside, col, -1).astype(np.intp)

    def centre_of(
        self, row: npt.ArrayLike, col: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """The floor point (x, z) at the centre of cells (row, col)."""
        x = self.min_x + (np.asarray(col, dtype=np.float64) + 0.5) * self.cell
        z = self.min_z + (np.asarray(row, dtype=np.float64) + 0.5) * self.cell
        return x, z

    def integrate(self, ego_rgb: npt.NDArray[np.uint8], pose: Pose2D) -> None:
        """Adds what view `ego_rgb` ((R, R, 3) uint8), taken at `pose`, shows of the floor."""
        if ego_rgb.shape != (*self.projection.depth.shape, 3):
            raise ValueError(f"a {self.projection.resolution}-pixel view is expected, got {ego_rgb.shape}")
        floor = floor_pixels(ego_rgb)
        labels = classify(ego_rgb)
        x, z = self.projection.world(pose)
        seen_free = floor & self._usable
        self._add(self.free, x[seen_free], z[seen_free])
        floor_below = np.zeros_like(floor)
        floor_below[:-1, :] = floor[1:, :]
        base = ~floor & floor_below & self._usable & self._has_below
        self._add(self.static, x[base & (labels == STATIC)], z[base & (labels == STATIC)])
        for index in range(len(CATEGORIES)):
            mask = base & (labels == 2 + index)
            self._add(self.movable[index], x[mask], z[mask])
        if self.tops:
            runs = self._top_runs(ego_rgb, labels)
            for i, (category, _) in enumerate(self.tops):
                mask = base & (labels == 2 + category) & (runs == i)
                self._add(self.instance[i], x[mask], z[mask])

    def _top_runs(
        self, ego_rgb: npt.NDArray[np.uint8], labels: npt.NDArray[np.integer]
    ) -> npt.NDArray[np.intp]:
        """(R, R) for each pixel, the index of the `tops` colour seen in its column's run of
        same-label pixels above the segment it is in (a segment: pixels of one colour, one face),
        the brightest when several are, or −1.

        A top face is the brightest face of an object (the light comes from above), and it is never
        the segment an object's base pixel is in (that is the face standing on the floor). A side
        face of a brighter object of the category can have a darker one's top colour (the tints
        are brightnesses): such a match, in the base's own segment or below a brighter match, is
        not taken.
        """
        match = np.full(labels.shape, -1, dtype=np.intp)
        rgb = ego_rgb.astype(np.int16)
        brightness = np.array([sum(colour) for _, colour in self.tops] + [-1])  # [-1]: none
        for i, (category, colour) in enumerate(self.tops):
            hit = (labels == 2 + category) & np.all(
                np.abs(rgb - np.array(colour, dtype=np.int16)) <= 2, axis=-1
            )
            better = hit & (brightness[match] < brightness[i])
            match[better] = i
        above = np.full(labels.shape, -1, dtype=np.intp)
        # Top to bottom: the best match of the run so far, and of the run above this segment.
        run_best = match[0].copy()
        above_best = np.full(labels.shape[1], -1, dtype=np.intp)
        for row in range(1, labels.shape[0]):
            same_run = labels[row] == labels[row - 1]
            same_segment = same_run & np.all(np.abs(rgb[row] - rgb[row - 1]) <= 2, axis=-1)
            above_best = np.where(same_segment, above_best, np.where(same_run, run_best, -1))
            run_best = np.where(same_run, run_best, -1)
            run_best = np.where(brightness[match[row]] > brightness[run_best], match[row], run_best)
            above[row] = above_best
        return above

    def visit(self, pose: Pose2D, radius: float = 0.3) -> None:
        """Marks the floor under the robot at `pose` (a disc of `radius`) free: it stood there."""
        span = int(np.ceil(radius / self.cell)) + 1
        row0, col0 = self.cell_of(pose.x, pose.z)
        rows, cols = np.mgrid[-span : span + 1, -span : span + 1]
        rows, cols = rows + int(row0), cols + int(col0)
        x, z = self.centre_of(rows, cols)
        inside = np.hypot(x - pose.x, z - pose.z) <= radius
        self._add(self.free, x[inside], z[inside])

    def _add(
        self, counts: npt.NDArray[np.int32], x: npt.NDArray[np.float64], z: npt.NDArray[np.float64]
    ) -> None:
        """Counts one view in each cell that points (x, z) fall in (once per cell per view)."""
        row, col = self.cell_of(x, z)
        keep = row >= 0
        if not keep.any():
            return
        flat = np.unique(row[keep] * self.cells + col[keep])
        counts.reshape(-1)[flat] += 1
