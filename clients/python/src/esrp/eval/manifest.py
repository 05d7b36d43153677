"""The challenge's scene list, `DIR/challenge-scenes.json`, which a server started with
`--challenge-seed` and `--records DIR` writes at its start (docs/evaluation.md, "The challenge's
scenes"): every challenge scene's id, difficulty, object count and horizon, the served dataset's
hash, and what each hidden split serves its clients.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from .results import DIFFICULTIES, OBSERVATIONS, ResultsError

__all__ = [
    "MANIFEST",
    "MANIFEST_SCHEMA",
    "ChallengeScenes",
    "ManifestError",
    "ManifestScene",
    "load_manifest",
]

MANIFEST = "challenge-scenes.json"
"""The file's name in the records folder."""

MANIFEST_SCHEMA = "esrp.challenge-scenes/v1"
"""Its `schema`."""


class ManifestError(ResultsError):
    """The scene list cannot be read, or is not `esrp.challenge-scenes/v1`."""


@dataclass(frozen=True)
class ManifestScene:
    """One challenge scene: its id (`challenge/00000`), difficulty, object count and horizon (0
    when the list does not give it: a reader then takes the scene's horizon from the server).
    """

    id: str
    difficulty: str
    objects: int
    horizon: int


@dataclass(frozen=True)
class ChallengeScenes:
    """The challenge's scene list.

    Attributes:
        path: The file it was read from.
        dataset_hash: The served dataset's hash (16 hex digits), as the records carry it.
        observations: What each hidden split serves tokens other than admins, by split
            (`{"challenge": "paper", "minival": "paper"}`).
        scenes: The challenge's scenes, in the file's order.
    """

    path: Path
    dataset_hash: str
    observations: Mapping[str, str]
    scenes: tuple[ManifestScene, ...]

    @cached_property
    def by_id(self) -> dict[str, ManifestScene]:
        """The scenes by id."""
        return {scene.id: scene for scene in self.scenes}

    def count(self, difficulty: str | None = None) -> int:
        """How many scenes there are (of one difficulty)."""
        return sum(1 for s in self.scenes if difficulty is None or s.difficulty == difficulty)


def _int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def load_manifest(path: str | os.PathLike[str]) -> ChallengeScenes:
    """Reads a scene list. Raises `ManifestError` naming the file and what is wrong: it cannot be
    read, is not JSON, or is not `esrp.challenge-scenes/v1` (a missing or mistyped member (a
    scene's `horizon` may be missing: 0, unknown), a
    difficulty other than easy, medium, hard, an observation policy other than paper or full, a
    scene listed twice).
    """
    where = Path(path)
    try:
        data = json.loads(where.read_bytes())
    except OSError as error:
        raise ManifestError(f"cannot read {where}: {error.strerror or error}") from None
    except ValueError as error:
        raise ManifestError(f"{where}: not JSON: {error}") from None

    def bad(what: str) -> ManifestError:
        return ManifestError(f"{where}: not an {MANIFEST_SCHEMA} scene list: {what}")

    if not isinstance(data, dict) or data.get("schema") != MANIFEST_SCHEMA:
        schema = data.get("schema") if isinstance(data, dict) else None
        raise bad(f"schema is {schema!r}")
    digest, observations, scenes = data.get("dataset_hash"), data.get("observations"), data.get("scenes")
    if not isinstance(digest, str):
        raise bad(f"dataset_hash is {digest!r}")
    if not isinstance(observations, dict) or not all(
        isinstance(k, str) and v in OBSERVATIONS for k, v in observations.items()
    ):
        raise bad(f"observations is {observations!r}, not an object of 'paper' or 'full' by split")
    if not isinstance(scenes, list):
        raise bad(f"scenes is {scenes!r}, not a list")
    listed: list[ManifestScene] = []
    for k, scene in enumerate(scenes):
        if not (
            isinstance(scene, dict)
            and isinstance(scene.get("id"), str)
            and scene.get("difficulty") in DIFFICULTIES
            and _int(scene.get("objects"))
            and _int(scene.get("horizon", 0))
        ):
            raise bad(f"scenes[{k}] is {scene!r}, not an id, difficulty, objects and horizon")
        horizon = scene.get("horizon", 0)
        listed.append(ManifestScene(scene["id"], scene["difficulty"], scene["objects"], horizon))
    if len({s.id for s in listed}) != len(listed):
        raise bad("a scene is listed twice")
    return ChallengeScenes(where, digest, dict(observations), tuple(listed))
