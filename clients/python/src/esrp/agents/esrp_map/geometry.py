"""The egocentric camera's geometry (SPEC §2), as esrp-render draws it: where each pixel's ray
meets the floor (the plane y = 0), in the robot's frame and in the world's.

Conventions (esrp-core and esrp-render): the world's floor is the x-z plane, y is up; a heading
`yaw` looks along (cos yaw, −sin yaw) in (x, z), and the camera's right is (sin yaw, cos yaw).
The camera sits `CAMERA_HEIGHT` above the robot's centre, pitched `CAMERA_PITCH` down, with a
horizontal field of view of `CAMERA_HORIZONTAL_FOV` and square pixels. Pixel (col, row) covers
[col, col + 1) × [row, row + 1) from the top-left corner and is sampled at its centre.

In the robot's frame a floor point is (`ahead`, `right`): metres along the heading and to its
right. The view depth is the distance along the camera's axis, what the server's depth sensor
gives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["CAMERA_HEIGHT", "CAMERA_HORIZONTAL_FOV", "CAMERA_PITCH", "FloorProjection", "Pose2D"]

CAMERA_HEIGHT = 1.25
"""Height of the egocentric camera above the floor, metres."""
CAMERA_PITCH = math.radians(20.0)
"""Downward pitch of the egocentric camera, radians."""
CAMERA_HORIZONTAL_FOV = math.pi / 2
"""Horizontal field of view of the egocentric camera, radians."""

Floats = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Pose2D:
    """A robot pose on the floor: position (x, z) in metres and heading `yaw` in radians."""

    x: float
    z: float
    yaw: float


class FloorProjection:
    """Where each pixel of a `resolution` × `resolution` egocentric view meets the floor.

    Attributes:
        ahead, right: (R, R) metres in the robot's frame of each pixel's floor point; NaN for
            pixels at or above the horizon (their rays never reach the floor).
        depth: (R, R) the view depth of each pixel's floor point (NaN above the horizon).
    """

    def __init__(self, resolution: int) -> None:
        if resolution < 1:
            raise ValueError(f"resolution {resolution}: at least 1 pixel")
        self.resolution = resolution
        focal = 1.0 / math.tan(CAMERA_HORIZONTAL_FOV / 2)
        centres = (np.arange(resolution) + 0.5) / resolution
        ndc_x = centres * 2 - 1  # by column, right is +
        ndc_y = 1 - centres * 2  # by row, up is +
        lateral = np.broadcast_to(ndc_x[None, :] / focal, (resolution, resolution))
        vertical = np.broadcast_to(ndc_y[:, None] / focal, (resolution, resolution))
        # A ray of unit view depth: forward + lateral · right + vertical · up, in the camera's
        # basis; with the pitch, its drop per unit depth and its reach along the heading.
        sp, cp = math.sin(CAMERA_PITCH), math.cos(CAMERA_PITCH)
        drop = sp - vertical * cp  # metres down per metre of depth
        along = cp + vertical * sp  # metres along the heading per metre of depth
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(drop > 1e-12, CAMERA_HEIGHT / drop, np.nan)
        self.depth: Floats = depth
        self.ahead: Floats = depth * along
        self.right: Floats = depth * lateral

    def floor_mask(self) -> npt.NDArray[np.bool_]:
        """The pixels whose rays reach the floor (below the horizon)."""
        return np.isfinite(self.depth)

    def world(self, pose: Pose2D) -> tuple[Floats, Floats]:
        """Each pixel's floor point in the world's (x, z) for a robot at `pose` (NaN above the
        horizon).
        """
        sy, cy = math.sin(pose.yaw), math.cos(pose.yaw)
        x = pose.x + self.ahead * cy + self.right * sy
        z = pose.z - self.ahead * sy + self.right * cy
        return x, z
