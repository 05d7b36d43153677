"""dm_env_rpc's own compliance suites, run against esrp-server.

Each suite is an abstract unittest class of the dm-env-rpc package; subclassing it as its docstring
says (a connection, a world, settings that must fail) runs every one of its checks. Each test gets
its own connection, so the worlds it creates end with it.
"""

from __future__ import annotations

import numpy as np
import pytest
from dm_env_rpc.v1 import connection as dm_connection
from dm_env_rpc.v1 import dm_env_rpc_pb2 as dm
from dm_env_rpc.v1 import tensor_utils
from dm_env_rpc.v1.compliance import create_destroy_world, join_leave_world, reset, reset_world, step

from harness import RunningServer, Session

# Small images: the suites step often and look at specs, not pixels.
WORLD_SETTINGS = {
    "resolution": tensor_utils.pack_tensor(32),
    "scene": tensor_utils.pack_tensor("esrp-bench-v2/00003"),
}
TURN_LEFT = 2


class Connected:
    """A dm_env_rpc connection per test (mixed in before a compliance suite)."""

    server: RunningServer
    session: Session

    def setUp(self) -> None:
        super().setUp()  # type: ignore[misc]
        self.session = self.server.connect()

    def tearDown(self) -> None:
        try:
            super().tearDown()  # type: ignore[misc]
        finally:
            self.session.close()

    @property
    def connection(self) -> dm_connection.Connection:
        return self.session.connection

    def new_world(self) -> str:
        response = self.connection.send(dm.CreateWorldRequest(settings=WORLD_SETTINGS))
        return str(response.world_name)


@pytest.mark.usefixtures("server_for_class")
class TestCreateDestroyWorld(Connected, create_destroy_world.CreateDestroyWorld):
    @property
    def required_world_settings(self) -> dict[str, dm.Tensor]:
        # Every setting has a default: an empty CreateWorld makes a world on the first test scene.
        return {}

    @property
    def invalid_world_settings(self) -> dict[str, dm.Tensor]:
        return {
            "scene": tensor_utils.pack_tensor("no-such-scene"),
            "split": tensor_utils.pack_tensor("validation"),
            "seed": tensor_utils.pack_tensor(-1),
            "horizon": tensor_utils.pack_tensor("long"),
            "resolution": tensor_utils.pack_tensor(7),
            "ego_depth": tensor_utils.pack_tensor(1.5),
            "colour": tensor_utils.pack_tensor(1),
        }

    @property
    def has_multiple_world_support(self) -> bool:
        return True


class WithWorld(Connected):
    """A fresh world for each test, named by `world_name` as the suites expect."""

    def setUp(self) -> None:
        super().setUp()
        self._world_name = self.new_world()

    @property
    def world_name(self) -> str:
        return self._world_name


@pytest.mark.usefixtures("server_for_class")
class TestJoinLeaveWorld(WithWorld, join_leave_world.JoinLeaveWorld):
    @property
    def invalid_join_settings(self) -> dict[str, dm.Tensor]:
        return {"colour": tensor_utils.pack_tensor(1), "resolution": tensor_utils.pack_tensor(64)}


@pytest.mark.usefixtures("server_for_class")
class TestReset(Connected, reset.Reset):
    def join_world(self) -> dm.ActionObservationSpecs:
        world_name = self.new_world()
        return self.connection.send(dm.JoinWorldRequest(world_name=world_name)).specs


@pytest.mark.usefixtures("server_for_class")
class TestResetWorld(WithWorld, reset_world.ResetWorld):
    pass


@pytest.mark.usefixtures("server_for_class")
class TestStep(Connected, step.Step):
    def setUp(self) -> None:
        super().setUp()
        world_name = self.new_world()
        self._specs = self.connection.send(dm.JoinWorldRequest(world_name=world_name)).specs

    @property
    def specs(self) -> dm.ActionObservationSpecs:
        return self._specs

    @property
    def required_actions(self) -> dict[int, dm.Tensor]:
        # ESRP has no "do nothing": a running step needs its action. Turning never leaves the spot.
        return {1: tensor_utils.pack_tensor(TURN_LEFT, dtype=np.int32)}
