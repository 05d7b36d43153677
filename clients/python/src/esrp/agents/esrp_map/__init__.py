"""ESRP-MAP: a non-privileged modular agent that maps the room and plans (docs/esrp-map.md).

It sees only what the paper's agents see (the egocentric view, the goal image and the grasp flag)
and maps the room from its egocentric views. Its parts:

- `geometry`: where each pixel of the egocentric view meets the floor, from the camera the server
  renders with (SPEC §2);
- `goal`: each pixel's kind by its colour (background, static, or a movable category), and the
  goal image's objects (centre, equivalent rectangle, colour) and room;
- `mapping`: a top-down map of free floor and obstacle bases (static, or movable by category)
  from egocentric views at known poses;
- `register`: the transform from the agent's start frame to the goal image (start heading among
  the 16, scale, start position), by correlating the map with the goal's static structure;
- `planner`: A* over the action lattice against the goal's static structure and the mapped
  objects, a held object's centre checked too;
- `agent`: `MapAgent`, `esrp eval --agent map`: look around, register, fetch, carry, release.
"""

from . import goal, mapping, planner, register
from .agent import MapAgent
from .geometry import CAMERA_HEIGHT, CAMERA_HORIZONTAL_FOV, CAMERA_PITCH, FloorProjection, Pose2D

__all__ = [
    "CAMERA_HEIGHT",
    "CAMERA_HORIZONTAL_FOV",
    "CAMERA_PITCH",
    "FloorProjection",
    "MapAgent",
    "Pose2D",
    "goal",
    "mapping",
    "planner",
    "register",
]
