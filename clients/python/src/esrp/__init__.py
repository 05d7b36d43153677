"""esrp: the Python client of esrp-server (Embodied Scene Rearrangement Planning).

- `Client` / `AsyncClient`: typed sync and asyncio clients of the native esrp.v1 API, with
  `Episode` / `AsyncEpisode` handles and the pipelined `EpisodeStream` / `AsyncEpisodeStream`.
- Values: `Action` (codes 0..5), `Observation` (numpy views of the answer's bytes, read-only, never
  copied), `StepResult`, `StepColumns` (a wave of step answers as columns), `StepInfo`,
  `EpisodeMetrics`, `SceneSummary`, `ServerInfo`, ...
- Errors: `EsrpError` and one subclass per gRPC status kind (`EpisodeNotFound`, `InvalidRequest`,
  `EpisodeEnded`, `ServerBusy`, `Unauthenticated`, `PermissionDenied`, `ServerUnavailable`, ...).
- `LocalServer`: an esrp-server child process on a free port.
- With the `gym` extra: the Gymnasium env `esrp/Rearrange-v1` and its native vector env, in
  `esrp.envs` (importing it registers the id; `import esrp` registers it too when gymnasium is
  imported already).

The rest of the package is laid out by audience: `esrp.envs` (the Gymnasium envs), `esrp.eval`
(`esrp eval`, `report`, `replay` and the results schema), `esrp.train` (demonstrations and the
training loops), `esrp.agents` (the agents `esrp eval` plays), `esrp.cli` (the `esrp` command) and
`esrp.bench` (`python -m esrp.bench`). The client core at the top imports none of them.

The generated protobuf messages and gRPC stubs are in `esrp.v1`.

`import esrp` leaves the process as it was: it sets no environment variable, changes no malloc
setting and imports neither grpc nor gymnasium; each name below is imported on first use. The
process-wide tunings (`esrp._grpc_setup`, `esrp._malloc_setup`) are opt-in: the `esrp` command,
`python -m esrp.bench`, the vector env and the training loops apply those that pay there.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from ._registration import ENV_ID, register_if_gymnasium_is_loaded

if TYPE_CHECKING:
    from ._async_client import (
        AsyncClient as AsyncClient,
    )
    from ._async_client import (
        AsyncEpisode as AsyncEpisode,
    )
    from ._async_client import (
        AsyncEpisodeStream as AsyncEpisodeStream,
    )
    from ._client import (
        Client as Client,
    )
    from ._client import (
        Episode as Episode,
    )
    from ._client import (
        EpisodeStream as EpisodeStream,
    )
    from ._common import (
        RequestKind as RequestKind,
    )
    from ._common import (
        StreamAnswer as StreamAnswer,
    )
    from ._errors import (
        AlreadyPlayed as AlreadyPlayed,
    )
    from ._errors import (
        Cancelled as Cancelled,
    )
    from ._errors import (
        DeadlineExceeded as DeadlineExceeded,
    )
    from ._errors import (
        EpisodeEnded as EpisodeEnded,
    )
    from ._errors import (
        EpisodeNotFound as EpisodeNotFound,
    )
    from ._errors import (
        EsrpError as EsrpError,
    )
    from ._errors import (
        InvalidRequest as InvalidRequest,
    )
    from ._errors import (
        LocalServerError as LocalServerError,
    )
    from ._errors import (
        NotFound as NotFound,
    )
    from ._errors import (
        PermissionDenied as PermissionDenied,
    )
    from ._errors import (
        ProtocolError as ProtocolError,
    )
    from ._errors import (
        SceneNotFound as SceneNotFound,
    )
    from ._errors import (
        ServerBusy as ServerBusy,
    )
    from ._errors import (
        ServerError as ServerError,
    )
    from ._errors import (
        ServerUnavailable as ServerUnavailable,
    )
    from ._errors import (
        Unauthenticated as Unauthenticated,
    )
    from ._local import (
        LocalServer as LocalServer,
    )
    from ._local import (
        find_server_binary as find_server_binary,
    )
    from ._local import (
        server_version as server_version,
    )
    from ._values import (
        Action as Action,
    )
    from ._values import (
        ActionLike as ActionLike,
    )
    from ._values import (
        ArraySpec as ArraySpec,
    )
    from ._values import (
        Created as Created,
    )
    from ._values import (
        DatasetInfo as DatasetInfo,
    )
    from ._values import (
        Difficulty as Difficulty,
    )
    from ._values import (
        EpisodeMetrics as EpisodeMetrics,
    )
    from ._values import (
        Footprint as Footprint,
    )
    from ._values import (
        Goal as Goal,
    )
    from ._values import (
        ObjectState as ObjectState,
    )
    from ._values import (
        Observation as Observation,
    )
    from ._values import (
        ObservationSpec as ObservationSpec,
    )
    from ._values import (
        Obstacle as Obstacle,
    )
    from ._values import (
        PlanAnswer as PlanAnswer,
    )
    from ._values import (
        PlanFailure as PlanFailure,
    )
    from ._values import (
        PlanStats as PlanStats,
    )
    from ._values import (
        Pose2 as Pose2,
    )
    from ._values import (
        PrivilegedState as PrivilegedState,
    )
    from ._values import (
        Progress as Progress,
    )
    from ._values import (
        RewardTerms as RewardTerms,
    )
    from ._values import (
        RewardWeights as RewardWeights,
    )
    from ._values import (
        SceneSummary as SceneSummary,
    )
    from ._values import (
        Sensors as Sensors,
    )
    from ._values import (
        ServerInfo as ServerInfo,
    )
    from ._values import (
        ServerLimits as ServerLimits,
    )
    from ._values import (
        Split as Split,
    )
    from ._values import (
        StaticObstacle as StaticObstacle,
    )
    from ._values import (
        StepColumns as StepColumns,
    )
    from ._values import (
        StepInfo as StepInfo,
    )
    from ._values import (
        StepResult as StepResult,
    )
    from ._values import (
        TopDownFrame as TopDownFrame,
    )

__version__ = "0.1.0"

# Where each public name lives; imported by `__getattr__` on first use, so that `import esrp`
# imports no grpc (whose core reads its settings once, when it is imported: see esrp._grpc_setup).
_EXPORTS: dict[str, tuple[str, ...]] = {
    "._async_client": (
        "AsyncClient",
        "AsyncEpisode",
        "AsyncEpisodeStream",
    ),
    "._client": (
        "Client",
        "Episode",
        "EpisodeStream",
    ),
    "._common": (
        "RequestKind",
        "StreamAnswer",
    ),
    "._errors": (
        "Cancelled",
        "DeadlineExceeded",
        "AlreadyPlayed",
        "EpisodeEnded",
        "EpisodeNotFound",
        "EsrpError",
        "InvalidRequest",
        "LocalServerError",
        "NotFound",
        "PermissionDenied",
        "ProtocolError",
        "SceneNotFound",
        "ServerBusy",
        "ServerError",
        "ServerUnavailable",
        "Unauthenticated",
    ),
    "._local": (
        "LocalServer",
        "find_server_binary",
        "server_version",
    ),
    "._values": (
        "Action",
        "ActionLike",
        "ArraySpec",
        "Created",
        "DatasetInfo",
        "Difficulty",
        "EpisodeMetrics",
        "Footprint",
        "Goal",
        "ObjectState",
        "Observation",
        "ObservationSpec",
        "Obstacle",
        "PlanAnswer",
        "PlanFailure",
        "PlanStats",
        "Pose2",
        "PrivilegedState",
        "Progress",
        "RewardTerms",
        "RewardWeights",
        "SceneSummary",
        "Sensors",
        "ServerInfo",
        "ServerLimits",
        "Split",
        "StaticObstacle",
        "StepColumns",
        "StepInfo",
        "StepResult",
        "TopDownFrame",
    ),
}

_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = ["ENV_ID", "__version__", *sorted(_MODULE_OF)]


def __getattr__(name: str) -> object:
    """Imports a public name's module on first use (PEP 562) and keeps the name here."""
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module 'esrp' has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_MODULE_OF})


register_if_gymnasium_is_loaded()
