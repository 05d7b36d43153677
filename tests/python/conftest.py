"""Session fixtures: one esrp-server for every test, and an expert scene."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from harness import ExpertScene, RunningServer, expert_scene, start_server


@pytest.fixture(scope="session")
def server() -> Iterator[RunningServer]:
    """esrp-server on the built-in benchmark, on an ephemeral port."""
    with start_server() as running:
        yield running


@pytest.fixture(scope="session")
def expert() -> ExpertScene:
    """esrp-bench-v2/00003 and its expert actions."""
    return expert_scene(3)


@pytest.fixture(scope="class")
def server_for_class(request: pytest.FixtureRequest, server: RunningServer) -> None:
    """Hands the server to a unittest-style class (the dm_env_rpc compliance suites)."""
    request.cls.server = server
