"""What ESRP-MAP reads from the images alone: each pixel's kind by its colour, and the goal image's
objects and room.

The renderer's palette (esrp-render `mesh.rs`, SPEC §4): each movable category has a saturated
colour (blue cabinets/shelves/desks, red chairs, green sofas, yellow piers/stools, purple others),
scaled by a per-instance brightness tint; floor, walls, doors and fixed furniture are muted, and
what lies outside the room is dark slate. Shading is flat: a face's colour is its base colour times
`AMBIENT + DIFFUSE · max(n · light, 0)`, so every face of one object has the same chromaticity
(colour over its brightness), and the top faces that the goal image shows share one shade,
`TOP_SHADE`. Pixels are classified by chromaticity and saturation, which shading and tints leave
alone.

The goal image is an orthographic top-down render of the target layout that frames the room (its
floor and walls) with a margin of `TOP_DOWN_MARGIN` metres each side, square, centred (esrp-render
`TopDownFrame`): image right is +x and image down is +z.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "BACKGROUND",
    "CATEGORIES",
    "STATIC",
    "TOP_DOWN_MARGIN",
    "TOP_SHADE",
    "GoalImage",
    "GoalObject",
    "classify",
    "components",
    "parse_goal",
]

CATEGORIES = ("cabinet_shelf_desk", "chair", "sofa", "pier_stool", "others")
"""The movable categories, in the order of their labels (`classify` gives category i label 2 + i);
the names are the privileged state's."""

_CATEGORY_RGB = np.array(
    [[0.16, 0.42, 0.88], [0.88, 0.20, 0.16], [0.18, 0.70, 0.26], [0.98, 0.72, 0.08], [0.78, 0.22, 0.86]]
)
"""esrp-render's `category_colour`, in `CATEGORIES` order."""

_BACKGROUND_RGB = np.array([0.10, 0.11, 0.13])
"""esrp-render's `BACKGROUND_COLOUR`: outside the room and through windows."""

BACKGROUND = 0
"""Label of pixels outside the room (esrp-render's background colour)."""
STATIC = 1
"""Label of floor, wall, door and fixed-furniture pixels (the muted colours)."""

TOP_DOWN_MARGIN = 0.15
"""Metres of margin the goal image leaves around the room's floor and walls, each side."""
TOP_SHADE = 0.55 + 0.45 * 0.82130
"""The shade of an upward face (esrp-render's shader: ambient 0.55, diffuse 0.45, light y 0.8213)."""

_MIN_SATURATION = 0.45
"""(max − min) / max of a movable colour is 0.63 or more, of a muted one 0.31 or less."""
_DARK = 0.2
"""A pixel darker than this (its brightest channel, in [0, 1]) and unsaturated is background."""

Labels = npt.NDArray[np.uint8]


def classify(rgb: npt.NDArray[np.uint8]) -> Labels:
    """Each pixel's kind: `BACKGROUND`, `STATIC`, or 2 + i for movable category `CATEGORIES[i]`.

    `rgb`: (..., 3) uint8. A saturated pixel is movable, of the category whose chromaticity is
    nearest; an unsaturated one is background when it is about as dark as the background colour
    (shaded faces of muted objects stay brighter), else static.
    """
    colour = rgb.astype(np.float64) / 255.0
    top = colour.max(axis=-1)
    saturation = np.where(top > 0, (top - colour.min(axis=-1)) / np.maximum(top, 1e-9), 0.0)
    total = np.maximum(colour.sum(axis=-1, keepdims=True), 1e-9)
    chroma = colour / total
    references = _CATEGORY_RGB / _CATEGORY_RGB.sum(axis=-1, keepdims=True)
    distances = np.linalg.norm(chroma[..., None, :] - references, axis=-1)
    labels = np.where(saturation >= _MIN_SATURATION, 2 + distances.argmin(axis=-1), STATIC)
    background_top = float(_BACKGROUND_RGB.max())
    dark = (saturation < _MIN_SATURATION) & (top <= max(_DARK, background_top * 1.2))
    labels = np.where(dark, BACKGROUND, labels)
    return labels.astype(np.uint8)


def components(mask: npt.NDArray[np.bool_]) -> list[npt.NDArray[np.intp]]:
    """The 4-connected components of `mask` (2-D), each as an (n, 2) array of (row, col), largest
    first.
    """
    seen = np.zeros(mask.shape, dtype=np.bool_)
    rows, cols = mask.shape
    found: list[npt.NDArray[np.intp]] = []
    for start in zip(*np.nonzero(mask), strict=True):
        if seen[start]:
            continue
        seen[start] = True
        queue = deque([start])
        pixels = []
        while queue:
            r, c = queue.popleft()
            pixels.append((r, c))
            for nr, nc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
                if 0 <= nr < rows and 0 <= nc < cols and mask[nr, nc] and not seen[nr, nc]:
                    seen[nr, nc] = True
                    queue.append((nr, nc))
        found.append(np.array(pixels, dtype=np.intp))
    found.sort(key=len, reverse=True)
    return found


@dataclass(frozen=True)
class GoalObject:
    """A movable object in the goal image: a connected region of one category's colour.

    Attributes:
        category: Its category, one of `CATEGORIES`.
        pixels: (n, 2) its pixels' (row, col).
        col, row: The centre of its pixels (pixel units, from the image's top-left corner).
        half_long, half_short: Half sizes of the rectangle with the same second moments, pixels.
        angle: The long side's direction, radians from image right (+x) towards image down (+z),
            in [0, π).
        colour: Its most common RGB colour (the top faces: category colour × tint × `TOP_SHADE`).
    """

    category: str
    pixels: npt.NDArray[np.intp]
    col: float
    row: float
    half_long: float
    half_short: float
    angle: float
    colour: tuple[int, int, int]

    @property
    def area(self) -> int:
        """Its pixel count."""
        return len(self.pixels)


@dataclass(frozen=True)
class GoalImage:
    """What the goal image shows.

    Attributes:
        labels: (R, R) each pixel's kind (`classify`).
        objects: The movable objects, largest first (regions of fewer than `min_pixels` are left
            out as edge noise).
        room: (R, R) the pixels inside the room (every pixel that is not background).
        bounds: (col_min, row_min, col_max, row_max) of the room's pixels, inclusive.
    """

    labels: Labels
    objects: tuple[GoalObject, ...]
    room: npt.NDArray[np.bool_]
    bounds: tuple[int, int, int, int]

    def metres_per_pixel(self) -> float:
        """The scale the margin implies: the room's larger side spans the image less the margins.
        Its error is about ±1 pixel of the margin over the margins' width in pixels: a prior for
        registration, not a measurement.
        """
        resolution = self.labels.shape[0]
        col_min, row_min, col_max, row_max = self.bounds
        span = max(col_max - col_min + 1, row_max - row_min + 1)
        margin_pixels = max(resolution - span, 1)
        return float(2 * TOP_DOWN_MARGIN / margin_pixels)


def parse_goal(goal_rgb: npt.NDArray[np.uint8], min_pixels: int = 3) -> GoalImage:
    """The objects and the room of goal image `goal_rgb` ((R, R, 3) uint8)."""
    if goal_rgb.ndim != 3 or goal_rgb.shape[2] != 3 or goal_rgb.shape[0] != goal_rgb.shape[1]:
        raise ValueError(f"a goal image is (R, R, 3), got {goal_rgb.shape}")
    labels = classify(goal_rgb)
    objects = []
    for index, category in enumerate(CATEGORIES):
        for pixels in components(labels == 2 + index):
            if len(pixels) >= min_pixels:
                objects.append(_describe(category, pixels, goal_rgb))
    objects.sort(key=lambda o: o.area, reverse=True)
    room = labels != BACKGROUND
    rows, cols = np.nonzero(room)
    if len(rows) == 0:
        raise ValueError("the goal image shows no room (every pixel is background)")
    bounds = (int(cols.min()), int(rows.min()), int(cols.max()), int(rows.max()))
    return GoalImage(labels, tuple(objects), room, bounds)


def _describe(category: str, pixels: npt.NDArray[np.intp], rgb: npt.NDArray[np.uint8]) -> GoalObject:
    """A region's centre, equivalent rectangle and dominant colour (pixel centres at +0.5)."""
    rows = pixels[:, 0] + 0.5
    cols = pixels[:, 1] + 0.5
    col, row = float(cols.mean()), float(rows.mean())
    dc, dr = cols - col, rows - row
    # A uniform rectangle of sides a and b has variances a²/12 and b²/12 along its axes; each
    # pixel adds 1/12 of its own width.
    cov = np.array([[np.mean(dc * dc), np.mean(dc * dr)], [np.mean(dc * dr), np.mean(dr * dr)]])
    values, vectors = np.linalg.eigh(cov)
    long_axis = vectors[:, 1]
    angle = float(np.arctan2(long_axis[1], long_axis[0]) % np.pi)
    half_long = float(np.sqrt(3 * max(values[1] + 1 / 12, 0.0)))
    half_short = float(np.sqrt(3 * max(values[0] + 1 / 12, 0.0)))
    colours, counts = np.unique(rgb[pixels[:, 0], pixels[:, 1]], axis=0, return_counts=True)
    r, g, b = (int(v) for v in colours[counts.argmax()])
    return GoalObject(category, pixels, col, row, half_long, half_short, angle, (r, g, b))
