"""ESRP-MAP (issue 42, in progress): a non-privileged modular agent that maps the room from its
egocentric views and plans. What exists so far is its geometry (`geometry`): where each pixel of
the egocentric view meets the floor, from the camera the server renders with (SPEC §2).
"""

from .geometry import CAMERA_HEIGHT, CAMERA_HORIZONTAL_FOV, CAMERA_PITCH, FloorProjection, Pose2D

__all__ = ["CAMERA_HEIGHT", "CAMERA_HORIZONTAL_FOV", "CAMERA_PITCH", "FloorProjection", "Pose2D"]
