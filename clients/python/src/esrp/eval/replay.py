"""`esrp replay`: re-runs a recorded episode's actions on the server and draws it.

The simulator is deterministic, so a record's `actions` stepped from its scene's start reproduce the
episode exactly (docs/evaluation.md); `replay_record` checks the replay against the record as
`esrp verify` does (`esrp.eval.verify.compare`: the metrics compared exactly, since both are the
server's doubles and JSON carries them without loss, and the end) and raises `ReplayError` when
they differ (another dataset, another server version, an edited file). Each frame shows, side by
side and labelled: the egocentric view, the goal image, and the current top-down view (the
episode's `current_top_down` sensor) with the agent's path in red and each carried object's path
in blue, outlined in white, drawn from the privileged state (the replay's episode is created with
`privileged=True`) through the goal's pixel ↔ floor frame (`GetGoal`); a header says the step, the
action taken and whether it was accepted, collided or had no effect, the grasp flag and the reward.

Needs Pillow (the `report` extra); MP4 output needs imageio-ffmpeg besides.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from .._client import Client
from .._common import unreachable
from .._errors import EsrpError, ServerUnavailable
from .._local import LocalServer
from .._values import Action, EpisodeMetrics, Observation, PrivilegedState, Sensors, StepResult, TopDownFrame
from .results import EpisodeRecord, ResultsError, load_records, no_records
from .verify import compare

if TYPE_CHECKING:
    from PIL import Image

__all__ = [
    "AGENT_PATH",
    "LABEL",
    "OBJECT_PATH",
    "PANEL_TITLES",
    "Replay",
    "ReplayError",
    "StepNote",
    "header_height",
    "replay_record",
    "replay_to_file",
    "step_note",
    "write_frames",
]

AGENT_PATH = (230, 25, 25)
"""The colour of the agent's path (red)."""
OBJECT_PATH = (20, 90, 255)
"""The colour of carried objects' paths (blue)."""

LABEL = "esrp replay"
"""The agent label of the episodes a replay creates (a recording server's records name them so)."""

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
        notes: What each frame's header says (its step, action, outcome, grasp flag and reward).
    """

    record: EpisodeRecord
    frames: list[Frame]
    metrics: EpisodeMetrics
    notes: list[StepNote] = field(default_factory=list)


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


PANEL_TITLES = ("ego view", "goal", "now, from above")
"""The labels above the three panels."""

_ACCEPTED = (0, 110, 0)
_REFUSED = (200, 0, 0)
_NO_EFFECT = (170, 95, 0)
_OUTLINE = (255, 255, 255)


@dataclass(frozen=True)
class StepNote:
    """What a frame says about its step: the caption (scene, agent, step), the action and what
    became of it, and the grasp flag and reward.

    Attributes:
        caption: `scene  agent  step k/n`.
        action: `turn_left (2): accepted`, `move_forward (0): rejected, collided with wall 3`,
            `fetch (4): no effect (...)`, or `start` before the first action.
        state: `grasping: yes  reward +0.050  total +1.230`.
        outcome: `accepted`, `collided`, `no effect` or `start` (the action line's colour).
    """

    caption: str
    action: str
    state: str
    outcome: str

    @property
    def lines(self) -> tuple[str, str, str]:
        """The header's three lines."""
        return self.caption, self.action, self.state


def step_note(
    caption: str, action: int | None, result: StepResult | None, grasping: bool, total_reward: float
) -> StepNote:
    """The note of a frame: `action` and its `result` (None for the start), the grasp flag after
    it, and the episode's reward so far.
    """
    if action is None or result is None:
        text, outcome, reward = "start (no action yet)", "start", 0.0
    else:
        try:
            name = f"{Action(action).api_name} ({action})"
        except ValueError:
            name = f"action {action}"
        info = result.info
        reward = result.reward
        if info.collided_with is not None:
            text, outcome = f"{name}: rejected, collided with {info.collided_with.name}", "collided"
        elif not info.accepted:
            why = f" ({info.no_op})" if info.no_op else ""
            text, outcome = f"{name}: no effect{why}", "no effect"
        else:
            text, outcome = f"{name}: accepted", "accepted"
            if info.fetched is not None:
                text += f", fetched object {info.fetched}"
            if info.released is not None:
                text += f", released object {info.released}"
    state = f"grasping: {'yes' if grasping else 'no'}  reward {reward:+.3f}  total {total_reward:+.3f}"
    return StepNote(caption, text, state, outcome)


def _font(scale: int) -> Any:  # noqa: ANN401 - a PIL font
    font_module = importlib.import_module("PIL.ImageFont")
    try:
        return font_module.load_default(size=5 * scale + 6)
    except TypeError:  # Pillow without FreeType: the fixed bitmap font
        return font_module.load_default()


def header_height(scale: int) -> int:
    """Pixels of the header above the panels: three lines of text and the panels' labels."""
    return 4 * _line_height(scale) + 4


def _line_height(scale: int) -> int:
    return 5 * scale + 10


def compose_frame(
    observation: Observation,
    goal: npt.NDArray[np.uint8],
    frame: TopDownFrame,
    paths: _Paths,
    *,
    scale: int,
    note: StepNote | str,
) -> Frame:
    """One frame: ego | goal | current top-down with the paths, each panel `128 * scale` pixels
    (the ego view's resolution times `scale`), each under its label, under a header of three lines
    (`note`: the caption, the action and what became of it, the grasp flag and reward; a plain
    caption alone where `note` is a string). The paths are outlined in white, so a blue path shows
    over a blue object.
    """
    image_module, draw_module = _pil()
    side = observation.ego_rgb.shape[0] * scale
    top_down = observation.current_top_down
    if top_down is None:
        raise ReplayError("the replay's episode answered no current_top_down view")
    header = header_height(scale)
    line_height = _line_height(scale)
    panels = [_upscale(observation.ego_rgb, side), _upscale(goal, side), _upscale(top_down, side)]
    width = 3 * side + 2 * _GAP
    canvas: Image.Image = image_module.new("RGB", (width, side + header), (255, 255, 255))
    for k, panel in enumerate(panels):
        canvas.paste(image_module.fromarray(panel), (k * (side + _GAP), header))
    draw = draw_module.Draw(canvas)
    font = _font(scale)
    lines = note.lines if isinstance(note, StepNote) else (note, "", "")
    colours = {"accepted": _ACCEPTED, "collided": _REFUSED, "no effect": _NO_EFFECT}
    action_colour = colours.get(note.outcome, (0, 0, 0)) if isinstance(note, StepNote) else (0, 0, 0)
    for row, (text, colour) in enumerate(zip(lines, ((0, 0, 0), action_colour, (0, 0, 0)), strict=True)):
        draw.text((3, 2 + row * line_height), text, fill=colour, font=font)
    for k, title in enumerate(PANEL_TITLES):
        draw.text((k * (side + _GAP) + 3, 2 + 3 * line_height), title, fill=(60, 60, 60), font=font)
    # The paths' colours, at the right of the caption line where there is room.
    key = [("paths: ", (60, 60, 60)), ("agent", AGENT_PATH), (", ", (60, 60, 60)), ("carried", OBJECT_PATH)]
    x = width - 3 - sum(draw.textlength(text, font=font) for text, _ in key)
    if x > 3 + draw.textlength(lines[0], font=font) + 10:
        for text, colour in key:
            draw.text((x, 2), text, fill=colour, font=font)
            x += draw.textlength(text, font=font)
    # Floor (x, z) to the top-down panel's pixels: col = (x - min_x) / m, row = (z - min_z) / m in
    # the frame's resolution, scaled to the panel.
    per_metre = side / (frame.resolution * frame.metres_per_pixel)
    left = 2 * (side + _GAP)

    def pixel(point: tuple[float, float]) -> tuple[float, float]:
        return (left + (point[0] - frame.min_x) * per_metre, header + (point[1] - frame.min_z) * per_metre)

    line = max(1, scale)
    outline = line + 2 * max(1, (scale + 1) // 2)

    def path(points: list[tuple[float, float]], colour: tuple[int, int, int]) -> None:
        xy = [pixel(p) for p in points]
        draw.line(xy, fill=_OUTLINE, width=outline, joint="curve")
        draw.line(xy, fill=colour, width=line, joint="curve")

    for stretches in paths.carried.values():
        for stretch in stretches:
            if len(stretch) > 1:
                path(stretch, OBJECT_PATH)
    if len(paths.agent) > 1:
        path(paths.agent, AGENT_PATH)
    if paths.agent:
        x, y = pixel(paths.agent[-1])
        r = 1.5 * line
        draw.ellipse((x - r, y - r, x + r, y + r), fill=AGENT_PATH, outline=_OUTLINE)
    composed: Frame = np.asarray(canvas, dtype=np.uint8)
    return composed


def replay_record(
    client: Client,
    record: EpisodeRecord,
    *,
    scale: int = 2,
    every_frame: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> Replay:
    """Steps `record.actions` in a new privileged episode of `record.scene_id` (its horizon, and
    the reward weights a server record says it played with) on `client`'s server, drawing a frame
    after each; checks the replay against the record exactly, as `esrp verify` does (`compare`:
    success, OSR, RDR, stage, placed, steps, total reward and the end), raising `ReplayError` on
    any difference. With `every_frame=False` only the final frame is composed (a still).
    """
    info = client.server_info()
    if info.dataset != record.dataset:
        raise ReplayError(
            f"the record is of dataset {record.dataset!r} but the server serves {info.dataset!r}: "
            "start a server of that dataset"
        )
    sensors = Sensors(current_top_down=True)
    frames: list[Frame] = []
    notes: list[StepNote] = []
    paths = _Paths()
    try:
        # With the reward weights it played with (a server record's), as `esrp verify` replays it.
        episode = client.create_episode(
            record.scene_id,
            privileged=True,
            sensors=sensors,
            horizon=record.horizon,
            reward=record.played_weights(),
            agent=LABEL,
        )
    except EsrpError as error:
        raise ReplayError(f"cannot create an episode of {record.scene_id!r}: {error}") from error
    with episode:
        goal = episode.goal()
        # A privileged episode is never one served with the paper's observation only.
        frame = goal.frame
        if frame is None:
            raise ReplayError(f"the server gave the goal of {record.scene_id!r} no frame on the floor")
        observation = episode.observation
        assert observation is not None
        paths.add(episode.privileged_state())
        total = len(record.actions)
        reward = 0.0

        def draw(observation: Observation, step: int, result: StepResult | None) -> None:
            caption = f"{record.scene_id}  {record.agent}  step {step}/{total}"
            action = record.actions[step - 1] if step else None
            note = step_note(caption, action, result, observation.grasping, reward)
            notes.append(note)
            frames.append(compose_frame(observation, goal.image, frame, paths, scale=scale, note=note))

        if every_frame or total == 0:
            draw(observation, 0, None)
        metrics: EpisodeMetrics | None = None
        ended_after: int | None = None
        for k, action in enumerate(record.actions, start=1):
            try:
                result = episode.step(action)
            except EsrpError as error:
                raise ReplayError(f"step {k} of {record.scene_id} failed: {error}") from error
            reward += result.reward
            paths.add(episode.privileged_state())
            if every_frame or k == total:
                draw(result.observation, k, result)
            if progress is not None:
                progress(k, total)
            if result.ended:
                # An episode that ends before the record's last action does not reproduce it:
                # `compare` says so, with the metrics it ended with.
                metrics, ended_after = result.metrics, k
                break
        if metrics is None:
            metrics = episode.metrics().metrics
    # `esrp verify`'s comparison: exact (both sides are the server's doubles, which JSON carries
    # without loss), and the end too.
    different = compare(record, metrics, ended_after)
    if different:
        raise ReplayError(
            f"the replay of {record.scene_id} does not reproduce the record: " + "; ".join(different)
        )
    return Replay(record, frames, metrics, notes)


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
        read = load_records(results, "esrp replay")
    except ResultsError as error:
        raise ReplayError(str(error)) from None
    records = read.records
    found = [r for r in records if r.scene_id == scene_id]
    if not found:
        if not records:
            raise ReplayError(no_records([results], [read]))
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
        with LocalServer(*server_args, unix_socket="auto") as local:
            replay = run(local.address)
    write_frames(replay.frames, out, fps=fps)
    return replay
