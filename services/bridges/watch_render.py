"""The pure part of `services.watch`: one robot's latest messages drawn as a PNG, GIF frames.

No Zenoh here: `render_figure`/`render_frame` draw whatever state object carries the fields of
`WatchView` (`services.bridges.watch.WatchState` does), `FrameReel` keeps downscaled frames for the
animated GIF, and `write_atomic` writes a file readers never see half-written. Kept apart so
outside tools and tests can render a state without opening a session.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Protocol

from matplotlib.axes import Axes
from matplotlib.figure import Figure
from PIL import Image

from mapex.plotting import occupancy_image
from services.config import WatchConfig
from services.messages import (
    FrontiersMessage,
    GoalMessage,
    MapMessage,
    Message,
    MetricsMessage,
    PathMessage,
    PoseMessage,
    StatusMessage,
)

DEFAULT_WATCH = WatchConfig()
WIDE_ASPECT = 1.5  # layout, not tunables: maps wider than this stack their panels
WIDE_PANEL_SCALE = 2.0  # stacked panels of wide maps get twice the width
PANEL_TITLE_INCHES = 0.3
TITLE_INCHES = 0.6
TEAMMATE_COLOURS = ("tab:purple", "tab:green", "tab:brown", "tab:pink", "tab:olive")


class WatchView(Protocol):
    """What the renderer reads of a watch's state (None: not heard of yet)."""

    run: str
    robot: str
    observed: MapMessage | None
    mean: MapMessage | None
    variance: MapMessage | None
    pose: PoseMessage | None
    frontiers: FrontiersMessage | None
    goal: GoalMessage | None
    path: PathMessage | None
    status: StatusMessage | None
    metrics: MetricsMessage | None
    teammates: dict[str, dict[str, Message]]  # robot -> "pose" / "goal" / "path" -> message

    @property
    def t(self) -> int | None:
        """The latest step any received message is about."""
        ...


# ---------------------------------------------------------------------------- rendering


def render_figure(state: WatchView, config: WatchConfig = DEFAULT_WATCH) -> Figure:
    """A figure of the observed map (pose, path, frontiers, goal on top), mean and variance."""
    rows, cols = _map_shape(state)
    wide = cols > WIDE_ASPECT * rows  # wide maps stack their panels, others sit side by side
    panel_w = config.panel_inches * (WIDE_PANEL_SCALE if wide else 1.0)
    panel_h = panel_w * rows / cols + PANEL_TITLE_INCHES
    size = (panel_w, 3 * panel_h) if wide else (3 * panel_w, panel_h)
    figure = Figure(figsize=(size[0], size[1] + TITLE_INCHES))
    axes = figure.subplots(*((3, 1) if wide else (1, 3)), squeeze=False).ravel()
    _draw_observed(axes[0], state)
    _draw_map(axes[1], state.mean, "prediction mean", occupancy_image, "gray", 1.0)
    _draw_map(axes[2], state.variance, "variance", None, "magma", None)
    figure.suptitle(_title(state), fontsize=10)
    figure.tight_layout(rect=(0, 0, 1, 1 - TITLE_INCHES / figure.get_figheight()))
    return figure


def render_frame(state: WatchView, config: WatchConfig = DEFAULT_WATCH) -> bytes:
    """The PNG bytes of `render_figure(state)`."""
    buffer = io.BytesIO()
    render_figure(state, config).savefig(buffer, format="png", dpi=config.dpi)
    return buffer.getvalue()


def _map_shape(state: WatchView) -> tuple[int, int]:
    for message in (state.observed, state.mean, state.variance):
        if message is not None:
            return message.map_u8.shape
    return 1, 1


def _title(state: WatchView) -> str:
    """Two lines: run, robot and step; then metrics and status when known."""
    head = f"run {state.run} / {state.robot}   t = {'?' if state.t is None else state.t}"
    facts = []
    if state.metrics is not None:
        facts.append(f"coverage {state.metrics.coverage:.1%}   IoU {state.metrics.iou:.3f}")
        if state.metrics.degraded:
            facts.append("degraded")
    if state.status is not None:
        detail = f": {state.status.detail}" if state.status.detail else ""
        facts.append(state.status.state + detail)
    return head + "\n" + "   ".join(facts)


def _draw_observed(ax: Axes, state: WatchView) -> None:
    _draw_map(ax, state.observed, "observed map", occupancy_image, "gray", 1.0)
    if state.observed is None:
        return
    if state.path is not None and len(state.path.cells):
        ax.plot(state.path.cells[:, 1], state.path.cells[:, 0], color="tab:red", linewidth=1.0)
    if state.frontiers is not None and len(state.frontiers.cells):
        cells = state.frontiers.cells
        ax.scatter(cells[:, 1], cells[:, 0], s=4, color="tab:cyan", linewidths=0)
    if state.goal is not None and state.goal.goal is not None:
        ax.plot(state.goal.goal[1], state.goal.goal[0], "*", color="tab:orange", markersize=10)
    if state.pose is not None:
        ax.plot(state.pose.pose[1], state.pose.pose[0], "o", color="tab:blue", markersize=6)
    for index, (_, messages) in enumerate(sorted(state.teammates.items())):
        _draw_teammate(ax, messages, TEAMMATE_COLOURS[index % len(TEAMMATE_COLOURS)])
    rows, cols = state.observed.map_u8.shape
    ax.set_xlim(-0.5, cols - 0.5)  # overlays never rescale the map
    ax.set_ylim(rows - 0.5, -0.5)


def _draw_teammate(ax: Axes, messages: dict[str, Message], colour: str) -> None:
    """Another robot of the team: its path, goal and pose in `colour`."""
    path, goal, pose = messages.get("path"), messages.get("goal"), messages.get("pose")
    if path is not None and len(path.cells):
        ax.plot(path.cells[:, 1], path.cells[:, 0], color=colour, linewidth=1.0)
    if goal is not None and goal.goal is not None:
        ax.plot(goal.goal[1], goal.goal[0], "*", color=colour, markersize=9)
    if pose is not None:
        ax.plot(pose.pose[1], pose.pose[0], "o", color=colour, markersize=5)


def _draw_map(ax: Axes, message, name: str, to_image, cmap: str, vmax: float | None) -> None:
    """A map panel, or a note that the map has not arrived yet."""
    ax.set_xticks([])
    ax.set_yticks([])
    if message is None:
        ax.set_title(f"{name}: waiting", fontsize=9)
        return
    values = message.probabilities()
    image = to_image(values) if to_image is not None else values
    top = vmax if vmax is not None else max(float(values.max()), 1e-6)
    ax.imshow(image, cmap=cmap, vmin=0.0, vmax=top, interpolation="nearest")
    scale = "" if vmax is not None else f", max {top:.3f}"
    ax.set_title(f"{name} (t = {message.t}{scale})", fontsize=9)


# ---------------------------------------------------------------------------- GIF frames and files


class FrameReel:
    """Downscaled GIF frames, fewer than `max_frames`: at the cap every other frame is dropped
    (the newest kept) and from then on only every other new one is kept (spacing doubles)."""

    def __init__(self, max_frames: int, max_side_px: int) -> None:
        self.max_frames = max(2, max_frames)
        self.max_side_px = max_side_px
        self.frames: list[Image.Image] = []
        self.stride = 1
        self._since_kept = 0

    def add(self, png: bytes, force: bool = False) -> None:
        """Offer a rendered PNG; `force` keeps it whatever the stride (e.g. the last frame)."""
        self._since_kept += 1
        if self._since_kept < self.stride and not force:
            return
        self._since_kept = 0
        self.frames.append(self._small(png))
        if len(self.frames) >= self.max_frames:
            self.frames = self.frames[::-2][::-1]
            self.stride *= 2

    def gif_bytes(self, frame_ms: int) -> bytes:
        """The frames as an endlessly looping animated GIF (sized like the first frame)."""
        if not self.frames:
            raise ValueError("no frames to write")
        first = self.frames[0]
        rest = [f if f.size == first.size else f.resize(first.size) for f in self.frames[1:]]
        buffer = io.BytesIO()
        first.save(
            buffer, format="GIF", save_all=True, append_images=rest, duration=frame_ms, loop=0
        )
        return buffer.getvalue()

    def _small(self, png: bytes) -> Image.Image:
        with Image.open(io.BytesIO(png)) as image:
            frame = image.convert("RGB")
        frame.thumbnail((self.max_side_px, self.max_side_px))
        return frame.convert("P", palette=Image.Palette.ADAPTIVE)


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` to `path` through a temporary file and os.replace (readers never see half)."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        temporary.write_bytes(data)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
