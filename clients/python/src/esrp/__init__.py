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
training loops), `esrp.agents` (the agents `esrp eval` plays) and `esrp.cli` (the `esrp` command;
its `esrp.cli.bench` is `esrp bench`, also `python -m esrp.bench`). The client core at the top
imports none of them.

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

__version__ = "0.1.0"

# The public names, by the module each lives in: the one list of them that runs. `__getattr__`
# imports a name's module on first use, so that `import esrp` imports no grpc (whose core reads its
# settings once, when it is imported: see esrp._grpc_setup); `__all__` and `dir(esrp)` come from it.
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
        "AlreadyPlayed",
        "Cancelled",
        "DeadlineExceeded",
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

if TYPE_CHECKING:
    # The same names for type checkers and IDEs, which do not run `__getattr__`: imported with
    # redundant aliases (`X as X`), which they read as re-exports. tests/test_import.py checks that
    # this block and `_EXPORTS` name the same names from the same modules. One statement per module:
    # ruff's isort would give each alias a statement of its own.
    # isort: off
    from ._async_client import (
        AsyncClient as AsyncClient,
        AsyncEpisode as AsyncEpisode,
        AsyncEpisodeStream as AsyncEpisodeStream,
    )
    from ._client import (
        Client as Client,
        Episode as Episode,
        EpisodeStream as EpisodeStream,
    )
    from ._common import (
        RequestKind as RequestKind,
        StreamAnswer as StreamAnswer,
    )
    from ._errors import (
        AlreadyPlayed as AlreadyPlayed,
        Cancelled as Cancelled,
        DeadlineExceeded as DeadlineExceeded,
        EpisodeEnded as EpisodeEnded,
        EpisodeNotFound as EpisodeNotFound,
        EsrpError as EsrpError,
        InvalidRequest as InvalidRequest,
        LocalServerError as LocalServerError,
        NotFound as NotFound,
        PermissionDenied as PermissionDenied,
        ProtocolError as ProtocolError,
        SceneNotFound as SceneNotFound,
        ServerBusy as ServerBusy,
        ServerError as ServerError,
        ServerUnavailable as ServerUnavailable,
        Unauthenticated as Unauthenticated,
    )
    from ._local import (
        LocalServer as LocalServer,
        find_server_binary as find_server_binary,
        server_version as server_version,
    )
    from ._values import (
        Action as Action,
        ActionLike as ActionLike,
        ArraySpec as ArraySpec,
        Created as Created,
        DatasetInfo as DatasetInfo,
        Difficulty as Difficulty,
        EpisodeMetrics as EpisodeMetrics,
        Footprint as Footprint,
        Goal as Goal,
        ObjectState as ObjectState,
        Observation as Observation,
        ObservationSpec as ObservationSpec,
        Obstacle as Obstacle,
        PlanAnswer as PlanAnswer,
        PlanFailure as PlanFailure,
        PlanStats as PlanStats,
        Pose2 as Pose2,
        PrivilegedState as PrivilegedState,
        Progress as Progress,
        RewardTerms as RewardTerms,
        RewardWeights as RewardWeights,
        SceneSummary as SceneSummary,
        Sensors as Sensors,
        ServerInfo as ServerInfo,
        ServerLimits as ServerLimits,
        Split as Split,
        StaticObstacle as StaticObstacle,
        StepColumns as StepColumns,
        StepInfo as StepInfo,
        StepResult as StepResult,
        TopDownFrame as TopDownFrame,
    )
    # isort: on

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
