"""The report's team part: what the robots of team runs did, as a table and a figure.

Team runs (metrics.json has a `team` entry) get, besides the AUC tables every run has, a
table of overlap (share of the seen cells that more than one robot saw) and path length per
robot, and teams.png: for one world and start, each team method's last snapshot of the
merged observed map with every robot's trajectory in a colour of its own
(docs/algorithms.md#teams). Team coverage against time for 1, 2 and 4 robots is curves.png:
teams are labelled by size (`mapex_team x2`), so they are curves of their own; how much
sooner they reach a coverage level than one robot is `mapex.report.speedup`.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from mapex.grid import observed_to_probability
from mapex.plotting import ROBOT_COLOURS, occupancy_image
from mapex.report.config import ReportConfig
from mapex.report.runs import RunRecord, Snapshots, Warn
from mapex.report.tables import mean_se, order_methods
from mapex.results import TEAM_TRAJECTORIES_FILE

TEAMS_FIGURE = "teams.png"


def team_runs(runs: Sequence[RunRecord]) -> list[RunRecord]:
    """The runs of teams (of any size, a team of one included)."""
    return [r for r in runs if r.metrics.get("team")]


def team_summary(runs: Sequence[RunRecord], order: Sequence[str]) -> dict[str, dict]:
    """Per team method: runs, overlap (mean, se), mean path length per robot in metres,
    and the robots lost (run name -> robots), for report.json and the table."""
    summary = {}
    for method in order_methods((r.method for r in runs), order):
        mine = [r for r in runs if r.method == method]
        overlap = mean_se([float(r.metrics["team"].get("overlap", np.nan)) for r in mine])
        lengths = [v for r in mine for v in r.metrics["team"].get("path_length_m", [])]
        totals = [r.metrics["path_length_m"] for r in mine if "path_length_m" in r.metrics]
        idle = [v for r in mine for v in r.metrics.get("idle_steps") or []]
        lost = {r.name: r.metrics["team"].get("lost_at") for r in mine}
        summary[method] = {
            "runs": len(mine),
            "overlap": {"mean": overlap.mean, "se": overlap.se},
            "path_length_m_per_robot": float(np.mean(lengths)) if lengths else None,
            "path_length_m_team": float(np.mean(totals)) if totals else None,
            "idle_steps_per_robot": float(np.mean(idle)) if idle else None,
            "lost": {name: at for name, at in lost.items() if at},
        }
    return summary


def team_markdown(summary: dict[str, dict]) -> str:
    """The report.md section of the team table."""
    lines = [
        "## Teams",
        "",
        "Overlap: share of the cells seen by the team that more than one robot saw "
        "(lower: the robots spread out more). Path length: mean over robots and runs; team "
        "path: every robot's summed, mean over runs. Idle steps: the steps a robot stood "
        "still while the run went on, mean over robots and runs.",
        "",
        "| method | runs | overlap | path length per robot (m) | runs with a lost robot "
        "| team path (m) | idle steps per robot |",
        "|---|---|---|---|---|---|---|",
    ]
    for method, row in summary.items():
        overlap = row["overlap"]
        se = "" if np.isnan(overlap["se"]) else f" ± {overlap['se']:.3f}"
        length, team = row["path_length_m_per_robot"], row.get("path_length_m_team")
        idle = row.get("idle_steps_per_robot")
        lines.append(
            f"| {method} | {row['runs']} | {overlap['mean']:.3f}{se} | {_whole(length)} | "
            f"{len(row['lost'])} | {_whole(team)} | {_whole(idle)} |"
        )
    return "\n".join(lines)


def _whole(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def load_trajectories(run: RunRecord, until_step: int) -> list[np.ndarray] | None:
    """Every robot's trajectory up to `until_step`, int (n, 2) (row, col), from
    trajectories.csv; None when the file is missing or unreadable."""
    try:
        with open(run.path / TEAM_TRAJECTORIES_FILE, newline="") as handle:
            rows = [
                (int(r["robot"]), int(r["row"]), int(r["col"]))
                for r in csv.DictReader(handle)
                if int(r["step"]) <= until_step
            ]
    except (OSError, ValueError, KeyError):
        return None
    robots = sorted({robot for robot, _, _ in rows})
    return [np.array([(r, c) for k, r, c in rows if k == robot]) for robot in robots] or None


def plot_teams(
    path: Path,
    chosen: Sequence[tuple[RunRecord, Snapshots | None, list[np.ndarray] | None]],
    config: ReportConfig,
    warn: Warn,
) -> None:
    """teams.png: one panel per chosen run, its last snapshot of the observed map with every
    robot's trajectory (circle: start, square: end)."""
    rows, cols = _map_shape([snaps for _, snaps, _ in chosen])
    wide = cols / rows > config.snapshot_wide_aspect
    layout = (len(chosen), 1) if wide else (1, len(chosen))
    width = config.snapshot_wide_panel_inches if wide else config.curve_panel_inches
    panel_height = width * rows / cols + 0.5
    figsize = (width * layout[1], panel_height * layout[0])
    fig, axes = plt.subplots(*layout, figsize=figsize, squeeze=False)
    for ax, (run, snaps, trajectories) in zip(axes.ravel(), chosen, strict=True):
        ax.set_xticks([])
        ax.set_yticks([])
        if snaps is None or not len(snaps.steps) or trajectories is None:
            warn(f"{run.name}: no snapshots or trajectories: its teams.png panel is empty")
            ax.set_title(f"{run.method}: no data", fontsize=8)
            continue
        ax.imshow(occupancy_image(observed_to_probability(snaps.observed[-1])), cmap="gray",
                  vmin=0.0, vmax=1.0, interpolation="nearest")  # fmt: skip
        _draw_trajectories(ax, trajectories)
        team = run.metrics["team"]
        lengths = ", ".join(f"{m:.0f}" for m in team.get("path_length_m", []))
        ax.set_title(
            f"{run.method} | t = {int(snaps.steps[-1])} | "
            f"overlap {team.get('overlap', np.nan):.2f} | {lengths} m",
            fontsize=8,
        )
    fig.suptitle(f"{chosen[0][0].world} | {chosen[0][0].start}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=config.dpi)
    plt.close(fig)


def _map_shape(snapshots: Sequence[Snapshots | None]) -> tuple[int, int]:
    """(rows, cols) of the first run with a snapshot; (1, 1) when none has one (runs
    shorter than the first snapshot step)."""
    for snaps in snapshots:
        if snaps is not None and len(snaps.steps):
            return tuple(snaps.observed.shape[1:])
    return (1, 1)


def _draw_trajectories(ax: plt.Axes, trajectories: list[np.ndarray]) -> None:
    for robot, shown in enumerate(trajectories):
        colour = ROBOT_COLOURS[robot % len(ROBOT_COLOURS)]
        ax.plot(shown[:, 1], shown[:, 0], color=colour, linewidth=1.0, label=f"robot {robot}")
        ax.plot(shown[0, 1], shown[0, 0], "o", color=colour, markersize=4)
        ax.plot(shown[-1, 1], shown[-1, 0], "s", color=colour, markersize=4)
    ax.legend(loc="lower right", fontsize=6, framealpha=0.7)
