"""The report's figures: mean metric curves with standard-error bands, and map snapshots.

curves.png / curves-<world>.png plot coverage, IoU and TU versus time step, one line per
method. snapshots.png shows the observed map and G's prediction at a few steps for one run
per method, all on the same world and start so the methods can be compared by eye.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mapex.grid import dequantise_probability, observed_to_probability  # noqa: E402
from mapex.plotting import occupancy_image  # noqa: E402
from mapex.report.config import ReportConfig  # noqa: E402
from mapex.report.runs import (  # noqa: E402
    METRIC_LABELS,
    METRICS,
    RunRecord,
    Snapshots,
    Warn,
    has_snapshots,
    warn_stderr,
)
from mapex.report.tables import order_methods  # noqa: E402

OBSERVED = "observed"
PREDICTED = "G prediction"
MAP_KINDS = (OBSERVED, PREDICTED)
_TITLE_INCHES = 0.4  # height of a panel title row
_SUPTITLE_INCHES = 0.6  # height of the figure title
_IMAGE_STYLE = dict(cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")


@dataclass(frozen=True)
class MeanCurve:
    """A method's curve of one metric: mean and standard error over runs at each step."""

    steps: np.ndarray
    mean: np.ndarray
    se: np.ndarray  # NaN where fewer than two runs have a sample


def mean_curve(runs: Sequence[RunRecord], metric: str) -> MeanCurve:
    """Mean +- SE over `runs` of `metric` at every step where at least one run sampled it."""
    steps = np.unique(np.concatenate([r.steps[np.isfinite(r.curve(metric))] for r in runs]))
    values = np.full((len(runs), steps.size), np.nan)
    for i, run in enumerate(runs):
        curve = run.curve(metric)
        ok = np.isfinite(curve)
        values[i, np.searchsorted(steps, run.steps[ok])] = curve[ok]
    n = np.isfinite(values).sum(axis=0)
    mean = np.nanmean(values, axis=0) if steps.size else np.zeros(0)
    se = np.full(steps.size, np.nan)
    many = n >= 2
    se[many] = np.nanstd(values[:, many], axis=0, ddof=1) / np.sqrt(n[many])
    return MeanCurve(steps, mean, se)


def plot_curves(
    path: Path, runs: Sequence[RunRecord], title: str, order: Sequence[str], config: ReportConfig
) -> None:
    """Coverage, IoU and TU versus time step: one line per method, SE bands."""
    size = config.curve_panel_inches
    fig, axes = plt.subplots(1, len(METRICS), figsize=(size * len(METRICS), size), squeeze=False)
    for ax, metric in zip(axes[0], METRICS, strict=True):
        for method in order_methods((r.method for r in runs), order):
            curve = mean_curve([r for r in runs if r.method == method], metric)
            (line,) = ax.plot(curve.steps, curve.mean, label=method, linewidth=1.5)
            ax.fill_between(
                curve.steps,
                curve.mean - curve.se,
                curve.mean + curve.se,
                color=line.get_color(),
                alpha=config.band_alpha,
                linewidth=0,
            )
        ax.set_xlabel("time step")
        ax.set_ylabel(METRIC_LABELS[metric])
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=config.dpi)
    plt.close(fig)


def world_file_name(world: str) -> str:
    """curves-<world>.png with the world name made file-system safe."""
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in world)
    return f"curves-{safe}.png"


# ---------------------------------------------------------------- snapshots


def choose_snapshot_runs(
    runs: Sequence[RunRecord],
    order: Sequence[str],
    pick: RunRecord | None = None,
    warn: Warn = warn_stderr,
) -> list[RunRecord]:
    """One run with snapshots per method, all on one world and start: `pick`'s, else the first
    (world, start) that every method has (else the one most methods have). Lowest seed wins."""
    with_snapshots = [r for r in runs if has_snapshots(r)]
    methods = order_methods((r.method for r in with_snapshots), order)
    if pick is not None:
        place = (pick.world, pick.start)
    else:
        places = sorted({(r.world, r.start) for r in with_snapshots})
        if not places:
            return []
        coverage = {
            p: {r.method for r in with_snapshots if (r.world, r.start) == p} for p in places
        }
        place = max(places, key=lambda p: len(coverage[p]))  # max keeps the first of ties
        if len(coverage[place]) < len(methods):
            warn(f"no world/start has snapshots of every method; using {place[0]} {place[1]}")
    chosen = []
    for method in methods:
        mine = [r for r in with_snapshots if (r.world, r.start, r.method) == (*place, method)]
        if mine:
            chosen.append(min(mine, key=lambda r: (r.seed, r.name)))
    return chosen


def snapshot_columns(
    wanted: Sequence[int], snapshots: Sequence[Snapshots | None]
) -> tuple[int, ...]:
    """The `wanted` steps that at least one run has a snapshot of (all of them if none has)."""
    present = {int(t) for s in snapshots if s is not None for t in s.steps}
    return tuple(t for t in wanted if t in present) or tuple(wanted)


def plot_snapshots(
    path: Path,
    chosen: Sequence[tuple[RunRecord, Snapshots | None]],
    config: ReportConfig,
) -> tuple[int, ...]:
    """Observed map and G's prediction of each chosen run at each snapshot step that some run
    reached; returns those steps. Square-ish maps: one row per method, a column pair (observed,
    prediction) per step. Maps wider than `config.snapshot_wide_aspect`: one row per method and
    map kind, one column per step, so each panel stays wide enough to read."""
    steps = snapshot_columns(config.snapshot_steps, [s for _, s in chosen])
    rows_cells, cols_cells = _map_shape([s for _, s in chosen])
    top = 1.0  # fraction of the figure height below the figure title
    if cols_cells / rows_cells > config.snapshot_wide_aspect:
        fig = _wide_layout(chosen, steps, rows_cells / cols_cells, config)
        top -= _SUPTITLE_INCHES / fig.get_figheight()  # keep it off the top row's titles
    else:
        fig = _grid_layout(chosen, steps, rows_cells / cols_cells, config)
    first = chosen[0][0]
    fig.suptitle(f"{first.world} | {first.start}", fontsize=10)
    fig.tight_layout(rect=(0.0, 0.0, 1.0, top))
    fig.savefig(path, dpi=config.dpi)
    plt.close(fig)
    return steps


def _map_shape(snapshots: Sequence[Snapshots | None]) -> tuple[int, int]:
    """(rows, cols) in cells of the first run's maps; (1, 1) when no run has any."""
    shapes = [s.observed.shape[1:] for s in snapshots if s is not None and s.observed.size]
    return shapes[0] if shapes else (1, 1)


def _grid_layout(
    chosen: Sequence[tuple[RunRecord, Snapshots | None]],
    steps: Sequence[int],
    aspect: float,
    config: ReportConfig,
) -> plt.Figure:
    """Rows = methods, columns = (observed, prediction) per step; `aspect` = rows / cols."""
    width = config.snapshot_panel_inches
    height = width * aspect
    fig, axes = plt.subplots(
        len(chosen),
        2 * len(steps),
        figsize=(width * 2 * len(steps), (height + _TITLE_INCHES) * len(chosen) + _SUPTITLE_INCHES),
        squeeze=False,
    )
    for axes_row, (run, snaps) in zip(axes, chosen, strict=True):
        for j, step in enumerate(steps):
            for k, kind in enumerate(MAP_KINDS):
                ax = axes_row[2 * j + k]
                ax.set_title(f"{kind} t={step}", fontsize=8)
                _draw_map(ax, snaps, step, kind)
        axes_row[0].set_ylabel(run.method, fontsize=9)
    return fig


def _wide_layout(
    chosen: Sequence[tuple[RunRecord, Snapshots | None]],
    steps: Sequence[int],
    aspect: float,
    config: ReportConfig,
) -> plt.Figure:
    """Rows = (method, map kind), columns = steps (titled on the top row); `aspect` = rows /
    cols."""
    width = config.snapshot_wide_panel_inches
    row_inches = width * aspect + config.snapshot_wide_row_gap_inches
    n_rows = len(MAP_KINDS) * len(chosen)
    fig, axes = plt.subplots(
        n_rows,
        len(steps),
        figsize=(width * len(steps), row_inches * n_rows + _TITLE_INCHES + _SUPTITLE_INCHES),
        squeeze=False,
    )
    for i, (run, snaps) in enumerate(chosen):
        for k, kind in enumerate(MAP_KINDS):
            axes_row = axes[len(MAP_KINDS) * i + k]
            for ax, step in zip(axes_row, steps, strict=True):
                _draw_map(ax, snaps, step, kind)
            axes_row[0].set_ylabel(f"{run.method}\n{kind}", fontsize=10)
    for ax, step in zip(axes[0], steps, strict=True):
        ax.set_title(f"t={step}", fontsize=10)
    return fig


def _draw_map(ax: plt.Axes, snaps: Snapshots | None, step: int, kind: str) -> None:
    """One panel: the run's observed map or G's prediction at `step`, or why there is none."""
    ax.set_xticks([])
    ax.set_yticks([])
    maps = None if snaps is None else snaps.at(step)
    if maps is None:
        _blank(ax, "not reached")
        return
    observed, prediction = maps
    if kind == OBSERVED:
        ax.imshow(occupancy_image(observed_to_probability(observed)), **_IMAGE_STYLE)
    elif prediction is None:
        _blank(ax, "no predictor")
    else:
        ax.imshow(occupancy_image(dequantise_probability(prediction)), **_IMAGE_STYLE)


def _blank(ax: plt.Axes, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", fontsize=8, transform=ax.transAxes)
