"""ESRP-MAP's geometry against the real server's camera: every floor pixel's projected depth is
the depth the server renders there."""

from __future__ import annotations

import math

import numpy as np
import pytest

import esrp
from esrp.agents.esrp_map import FloorProjection, Pose2D


@pytest.mark.parametrize("turns", [0, 3])
def test_floor_pixels_project_to_the_depth_the_server_renders(
    client: esrp.Client, easy_scenes: list[str], turns: int
) -> None:
    sensors = esrp.Sensors(resolution=128, depth=True, segmentation=True)
    with client.create_episode(easy_scenes[0], sensors=sensors) as episode:
        observation = episode.observation
        for _ in range(turns):
            observation = episode.step(esrp.Action.LEFT).observation
    assert observation is not None
    assert observation.depth is not None
    assert observation.segmentation is not None
    floor = observation.segmentation == 1
    assert floor.sum() > 100, "the view sees some floor"
    projection = FloorProjection(128)
    assert projection.floor_mask()[floor].all(), "every floor pixel lies below the horizon"
    rendered = observation.depth[floor].astype(np.float64)
    projected = projection.depth[floor]
    assert np.allclose(projected, rendered, rtol=2e-4, atol=1e-4), np.abs(projected - rendered).max()


def test_the_horizon_and_the_frame() -> None:
    projection = FloorProjection(128)
    # Pitched 20° down with a 90° field of view: the horizon is above the image's middle row.
    horizon = math.tan(math.radians(20.0)) * 64  # rows above the centre
    top_floor_row = int(np.argmax(projection.floor_mask().any(axis=1)))
    assert abs(top_floor_row - (64 - horizon)) < 1.5
    # Symmetric left and right, and straight ahead at the middle columns.
    assert np.allclose(projection.right[100, :64], -projection.right[100, ::-1][:64])
    assert np.allclose(projection.ahead[100, :64], projection.ahead[100, ::-1][:64])
    # The bottom row is the nearest floor the camera sees: 1.25 m / tan(20° + 45°) down the axis.
    nearest = 1.25 / math.tan(math.radians(65.0))
    assert projection.ahead[127, 63] == pytest.approx(nearest, rel=0.02)
    # In the world: a robot at (1, 2) facing yaw 90° looks along −z, its right is +x.
    x, z = projection.world(Pose2D(1.0, 2.0, math.pi / 2))
    assert x[100, 64] == pytest.approx(1.0 + projection.right[100, 64], abs=1e-9)
    assert z[100, 64] == pytest.approx(2.0 - projection.ahead[100, 64], abs=1e-9)
    with pytest.raises(ValueError, match="resolution"):
        FloorProjection(0)
