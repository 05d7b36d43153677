"""`esrp replay`: re-runs a recorded episode's actions on the server and draws it.

The simulator is deterministic, so a record's `actions` stepped from its scene's start reproduce the
episode exactly (docs/evaluation.md); `replay_record` checks that the final metrics equal the
record's and raises `ReplayError` when they do not (another dataset, another server version, an
edited file). Each frame shows, side by side: the egocentric view, the goal image, and the current
top-down view (the episode's `current_top_down` sensor) with the agent's path in red and each
carried object's path in blue, drawn from the privileged state (the replay's episode is created with
`privileged=True`) through the goal's pixel ↔ floor frame (`GetGoal`).

Needs Pillow (the `report` extra); MP4 output needs imageio-ffmpeg besides.
"""

from __future__ import annotations

import importlib
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from ._client import Client
from ._common import unreachable
from ._errors import EsrpError, ServerUnavailable
from ._local import LocalServer
from ._values import EpisodeMetrics, Observation, PrivilegedState, Sensors, TopDownFrame
from .results import EpisodeRecord, ResultsError, read_records

if TYPE_CHECKING:
    from PIL import Image

__all__ = [
    "AGENT_PATH",
    "OBJECT_PATH",
    "Replay",
    "ReplayError",
    "replay_record",
    "replay_to_file",
    "write_frames",
]

AGENT_PATH = (230, 25, 25)
"""The colour of the agent's path (red)."""
OBJECT_PATH = (20, 90, 255)
"""The colour of carried objects' paths (blue)."""

_HEADER = 14  # pixels of the caption strip above the panels
_GAP = 4  # pixels between panels

Frame = npt.NDArray[np.uint8]


class ReplayError(Exception):
    """A replay could not be made, or does not reproduce its record."""


@dataclass
class _Paths:
    """The agent's positions and each object's carried stretches, on the floor (x, z)."""

    agent: list[tuple[float, float]] = field(default_factory=list)
    carried: dict[int, list[list[tuple[float, float]]]] = field(default_factory=dict)
    _holding: int | None = None

    def add(self, state: PrivilegedState) -> None:
        self.agent.append((state.agent_x, state.agent_z))
        held = state.held
        if held is not None:
            footprint = state.objects[held].footprint
            point = (footprint.center_x, footprint.center_z)
            stretches = self.carried.setdefault(held, [])
            if self._holding != held:
                stretches.append([])
            stretches[-1].append(point)
        self._holding = held


@dataclass
class Replay:
    """A replayed episode.

    Attributes:
        record: The record replayed.
        frames: The composed frames (H, W, 3) uint8: the start, then one per action (only the last
            with `every_frame=False`).
        metrics: The replay's final metrics (they equal the record's).
    """

    record: EpisodeRecord
    frames: list[Frame]
    metrics: EpisodeMetrics


def _pil() -> Any:  # noqa: ANN401 - PIL's modules, imported lazily (the report extra).
    try:
        return importlib.import_module("PIL.Image"), importlib.import_module("PIL.ImageDraw")
    except ImportError:
        raise ReplayError("replays need Pillow: pip install 'esrp[report]'") from None


def _upscale(image: npt.NDArray[np.uint8], size: int) -> npt.NDArray[np.uint8]:
    """Nearest-neighbour resize of a square image to `size` pixels (integer factors stay exact)."""
    if size % image.shape[0] == 0 and image.shape[0] == image.shape[1]:
        factor = size // image.shape[0]
        repeated: npt.NDArray[np.uint8] = image.repeat(factor, axis=0).repeat(factor, axis=1)
        return repeated
    rows = (np.arange(size) * image.shape[0]) // size
    cols = (np.arange(size) * image.shape[1]) // size
    resized: npt.NDArray[np.uint8] = image[rows][:, cols]
    return resized


def compose_frame(
    observation: Observation,
    goal: npt.NDArray[np.uint8],
    frame: TopDownFrame,
    paths: _Paths,
    *,
    scale: int,
    caption: str,
) -> Frame:
    """One frame: ego | goal | current top-down with the paths, each panel `128 * scale` pixels
    (the ego view's resolution times `scale`), under a caption strip.
    """
    image_module, draw_module = _pil()
    side = observation.ego_rgb.shape[0] * scale
    top_down = observation.current_top_down
    if top_down is None:
        raise ReplayError("the replay's episode answered no current_top_down view")
    panels = [_upscale(observation.ego_rgb, side), _upscale(goal, side), _upscale(top_down, side)]
    width = 3 * side + 2 * _GAP
    canvas: Image.Image = image_module.new("RGB", (width, side + _HEADER), (255, 255, 255))
    for k, panel in enumerate(panels):
        canvas.paste(image_module.fromarray(panel), (k * (side + _GAP), _HEADER))
    draw = draw_module.Draw(canvas)
    draw.text((2, 1), caption, fill=(0, 0, 0))
    # Floor (x, z) to the top-down panel's pixels: col = (x - min_x) / m, row = (z - min_z) / m in
    # the frame's resolution, scaled to the panel.
    per_metre = side / (frame.resolution * frame.metres_per_pixel)
    left = 2 * (side + _GAP)

    def pixel(point: tuple[float, float]) -> tuple[float, float]:
        return (left + (point[0] - frame.min_x) * per_metre, _HEADER + (point[1] - frame.min_z) * per_metre)

    line = max(1, scale)
    for stretches in paths.carried.values():
        for stretch in stretches:
            if len(stretch) > 1:
                draw.line([pixel(p) for p in stretch], fill=OBJECT_PATH, width=line)
    if len(paths.agent) > 1:
        draw.line([pixel(p) for p in paths.agent], fill=AGENT_PATH, width=line)
    if paths.agent:
        x, y = pixel(paths.agent[-1])
        r = 1.5 * line
        draw.ellipse((x - r, y - r, x + r, y + r), fill=AGENT_PATH)
    composed: Frame = np.asarray(canvas, dtype=np.uint8)
    return composed


def _metrics_differences(record: EpisodeRecord, m: EpisodeMetrics) -> list[str]:
    pairs: list[tuple[str, object, object]] = [
        ("success", record.success, m.success),
        ("stage", record.stage, m.stage),
        ("placed", record.placed, m.placed),
        ("steps", record.steps, m.steps),
    ]
    different = [f"{name} {want!r} (replay {got!r})" for name, want, got in pairs if want != got]
    for name, want_f, got_f in (
        ("osr", record.osr, m.object_success_rate),
        ("rdr", record.rdr, m.remaining_distance_ratio),
        ("total_reward", record.total_reward, m.total_reward),
    ):
        if not math.isclose(want_f, got_f, rel_tol=1e-9, abs_tol=1e-12):
            different.append(f"{name} {want_f!r} (replay {got_f!r})")
    return different


def replay_record(
    client: Client,
    record: EpisodeRecord,
    *,
    scale: int = 2,
    every_frame: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> Replay:
    """Steps `record.actions` in a new privileged episode of `record.scene_id` (its horizon) on
    `client`'s server, drawing a frame after each; checks the final metrics against the record.
    With `every_frame=False` only the final frame is composed (a still).
    """
    info = client.server_info()
    if info.dataset != record.dataset:
        raise ReplayError(
            f"the record is of dataset {record.dataset!r} but the server serves {info.dataset!r}: "
            "start a server of that dataset"
        )
    sensors = Sensors(current_top_down=True)
    frames: list[Frame] = []
    paths = _Paths()
    try:
        episode = client.create_episode(
            record.scene_id, privileged=True, sensors=sensors, horizon=record.horizon
        )
    except EsrpError as error:
        raise ReplayError(f"cannot create an episode of {record.scene_id!r}: {error}") from error
    with episode:
        goal = episode.goal()
        observation = episode.observation
        assert observation is not None
        paths.add(episode.privileged_state())
        total = len(record.actions)

        def draw(observation: Observation, step: int) -> None:
            caption = f"{record.scene_id}  {record.agent}  step {step}/{total}"
            frames.append(
                compose_frame(observation, goal.image, goal.frame, paths, scale=scale, caption=caption)
            )

        if every_frame or total == 0:
            draw(observation, 0)
        metrics: EpisodeMetrics | None = None
        for k, action in enumerate(record.actions, start=1):
            if metrics is not None:
                raise ReplayError(
                    f"the replay of {record.scene_id} ended after {k - 1} of the record's {total} actions "
                    f"({metrics}): the record does not replay on this server"
                )
            try:
                result = episode.step(action)
            except EsrpError as error:
                raise ReplayError(f"step {k} of {record.scene_id} failed: {error}") from error
            paths.add(episode.privileged_state())
            if every_frame or k == total:
                draw(result.observation, k)
            if result.ended:
                metrics = result.metrics
            if progress is not None:
                progress(k, total)
        if metrics is None:
            metrics = episode.metrics().metrics
    different = _metrics_differences(record, metrics)
    if different:
        raise ReplayError(
            f"the replay of {record.scene_id} does not reproduce the record: " + "; ".join(different)
        )
    return Replay(record, frames, metrics)


def _even(frame: Frame, multiple: int = 16) -> Frame:
    """`frame` padded with white to sides that are multiples of `multiple` (video encoders)."""
    height, width = frame.shape[:2]
    pad_h, pad_w = -height % multiple, -width % multiple
    if not pad_h and not pad_w:
        return frame
    padded: Frame = np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)), constant_values=255)
    return padded


def write_frames(frames: Sequence[Frame], path: str | os.PathLike[str], *, fps: float = 10.0) -> Path:
    """Writes frames by `path`'s extension: `.gif` (every frame, looping), `.mp4` (needs
    imageio-ffmpeg), `.png` (the last frame).
    """
    out = Path(path)
    if not frames:
        raise ReplayError("no frames to write")
    image_module, _ = _pil()
    suffix = out.suffix.lower()
    out.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".png":
        image_module.fromarray(frames[-1]).save(out, format="PNG")
    elif suffix == ".gif":
        images = [image_module.fromarray(f) for f in frames]
        duration = max(int(round(1000 / fps)), 20)
        images[0].save(out, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)
    elif suffix == ".mp4":
        try:
            ffmpeg: Any = importlib.import_module("imageio_ffmpeg")
        except ImportError:
            raise ReplayError(
                "MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg); or write .gif"
            ) from None
        first = _even(frames[0])
        writer = ffmpeg.write_frames(
            str(out), (first.shape[1], first.shape[0]), fps=fps, macro_block_size=1, pix_fmt_out="yuv420p"
        )
        writer.send(None)
        for frame in frames:
            writer.send(np.ascontiguousarray(_even(frame)).tobytes())
        writer.close()
    else:
        raise ReplayError(f"unknown output format {out.suffix!r}: use .gif, .mp4 or .png")
    return out


def find_record(results: str | os.PathLike[str], scene_id: str) -> EpisodeRecord:
    """The record of `scene_id` in a results file (the last one, if the file holds several)."""
    try:
        records = read_records(results).records
    except OSError as error:
        raise ReplayError(f"cannot read {results}: {error.strerror or error}") from None
    except ResultsError as error:
        raise ReplayError(str(error)) from None
    found = [r for r in records if r.scene_id == scene_id]
    if not found:
        ends = sorted({r.scene_id for r in records if r.scene_id.endswith("/" + scene_id)})
        hint = f" (did you mean {ends[0]!r}?)" if len(ends) == 1 else ""
        raise ReplayError(f"{results} has no record of scene {scene_id!r}{hint}")
    return found[-1]


def replay_to_file(
    results: str | os.PathLike[str],
    scene_id: str,
    out: str | os.PathLike[str],
    *,
    fps: float = 10.0,
    scale: int = 2,
    server: str | None = None,
    token: str | None = None,
    server_args: Sequence[str] = (),
) -> Replay:
    """`esrp replay`: the record of `scene_id` in `results`, replayed on `server` (or a
    `LocalServer` started for it) and written to `out` (.gif, .mp4 or .png).
    """
    record = find_record(results, scene_id)
    every_frame = Path(out).suffix.lower() != ".png"

    def run(address: str) -> Replay:
        with Client(address, token=token, timeout=120) as client:
            if server is not None:
                try:
                    client.server_info()  # fails at once when nothing answers there
                except ServerUnavailable as error:
                    raise ReplayError(unreachable(server, error)) from None
            client.wait_healthy(30)
            return replay_record(client, record, scale=scale, every_frame=every_frame)

    if server is not None:
        replay = run(server)
    else:
        with LocalServer(*server_args) as local:
            replay = run(local.address)
    write_frames(replay.frames, out, fps=fps)
    return replay
