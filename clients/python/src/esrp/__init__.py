"""esrp: the Python client of esrp-server (Embodied Scene Rearrangement Planning).

- `Client` / `AsyncClient`: typed sync and asyncio clients of the native esrp.v1 API, with
  `Episode` / `AsyncEpisode` handles and the pipelined `EpisodeStream` / `AsyncEpisodeStream`.
- Values: `Action` (codes 0..5), `Observation` (numpy views of the answer's bytes, read-only, never
  copied), `StepResult`, `StepInfo`, `EpisodeMetrics`, `SceneSummary`, `ServerInfo`, ...
- Errors: `EsrpError` and one subclass per gRPC status kind (`EpisodeNotFound`, `InvalidRequest`,
  `EpisodeEnded`, `ServerBusy`, `Unauthenticated`, `PermissionDenied`, `ServerUnavailable`, ...).
- `LocalServer`: an esrp-server child process on a free port.
- With the `gym` extra: the Gymnasium env `esrp/Rearrange-v1` (registered on import) and its native
  vector env, in `esrp.gym`.

- The `esrp` command (`esrp.cli`): `esrp eval` (`esrp.evaluation`, agents in `esrp.agents`, the
  results schema in `esrp.results`), `esrp report` (`esrp.report`), `esrp replay` (`esrp.replay`).

The generated protobuf messages and gRPC stubs are in `esrp.v1`.
"""

from __future__ import annotations

import importlib.util

# First: grpcio reads its core settings when it is imported (see esrp._grpc_setup).
from . import _grpc_setup  # noqa: F401  # isort: skip
from . import _malloc_setup  # noqa: F401  # isort: skip  (malloc thresholds, see there)
from ._async_client import AsyncClient, AsyncEpisode, AsyncEpisodeStream
from ._client import Client, Episode, EpisodeStream
from ._common import RequestKind, StreamAnswer
from ._errors import (
    Cancelled,
    DeadlineExceeded,
    EpisodeEnded,
    EpisodeNotFound,
    EsrpError,
    InvalidRequest,
    LocalServerError,
    NotFound,
    PermissionDenied,
    ProtocolError,
    SceneNotFound,
    ServerBusy,
    ServerError,
    ServerUnavailable,
    Unauthenticated,
)
from ._local import LocalServer, find_server_binary
from ._values import (
    Action,
    ActionLike,
    ArraySpec,
    Created,
    DatasetInfo,
    Difficulty,
    EpisodeMetrics,
    Footprint,
    Goal,
    ObjectState,
    Observation,
    ObservationSpec,
    Obstacle,
    PlanAnswer,
    PlanFailure,
    PlanStats,
    Pose2,
    PrivilegedState,
    Progress,
    RewardTerms,
    RewardWeights,
    SceneSummary,
    Sensors,
    ServerInfo,
    ServerLimits,
    Split,
    StaticObstacle,
    StepInfo,
    StepResult,
    TopDownFrame,
)

__version__ = "0.1.0"

ENV_ID = "esrp/Rearrange-v1"
"""The Gymnasium id of the ESRP environment (`gymnasium.make` and `gymnasium.make_vec`)."""

__all__ = [
    "ENV_ID",
    "Action",
    "ActionLike",
    "ArraySpec",
    "AsyncClient",
    "AsyncEpisode",
    "AsyncEpisodeStream",
    "Cancelled",
    "Client",
    "Created",
    "DatasetInfo",
    "DeadlineExceeded",
    "Difficulty",
    "Episode",
    "EpisodeEnded",
    "EpisodeMetrics",
    "EpisodeNotFound",
    "EpisodeStream",
    "EsrpError",
    "Footprint",
    "Goal",
    "InvalidRequest",
    "LocalServer",
    "LocalServerError",
    "NotFound",
    "ObjectState",
    "Observation",
    "ObservationSpec",
    "Obstacle",
    "PermissionDenied",
    "PlanAnswer",
    "PlanFailure",
    "PlanStats",
    "Pose2",
    "PrivilegedState",
    "Progress",
    "ProtocolError",
    "RequestKind",
    "RewardTerms",
    "RewardWeights",
    "SceneNotFound",
    "SceneSummary",
    "Sensors",
    "ServerBusy",
    "ServerError",
    "ServerInfo",
    "ServerLimits",
    "ServerUnavailable",
    "Split",
    "StaticObstacle",
    "StepInfo",
    "StepResult",
    "StreamAnswer",
    "TopDownFrame",
    "Unauthenticated",
    "__version__",
    "find_server_binary",
]


def _register_gymnasium_envs() -> None:
    """Registers `esrp/Rearrange-v1` when gymnasium is installed (the `gym` extra). The entry points
    are strings, so `esrp.gym` is imported only when an env is made.
    """
    if importlib.util.find_spec("gymnasium") is None:
        return
    from gymnasium.envs.registration import register, registry

    if ENV_ID not in registry:
        register(
            id=ENV_ID,
            entry_point="esrp.gym:RearrangeEnv",
            vector_entry_point="esrp.gym:RearrangeVectorEnv",
        )


_register_gymnasium_envs()
