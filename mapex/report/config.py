"""Settings of the evaluation report `python -m mapex.report`."""

from __future__ import annotations

from dataclasses import dataclass

from mapex.config import Checked, positive, ranged, share
from mapex.methods import ABLATIONS, BEYOND_PAPER, FOLLOW_UP, MAIN_COMPARISON


@dataclass(frozen=True)
class ReportConfig(Checked):
    """The evaluation report `python -m mapex.report`: figure settings and snapshot steps."""

    snapshot_steps: tuple[int, ...] = ranged((200, 500, 1000), 0)  # columns of snapshots.png
    dpi: int = ranged(120, 1, 2400)
    # width (and height) of one metric panel of curves.png
    curve_panel_inches: float = ranged(4.0, 0, 100, low_open=True)
    # width of one map panel of snapshots.png
    snapshot_panel_inches: float = ranged(2.2, 0, 100, low_open=True)
    # maps wider than this (cols / rows) get one snapshots.png row per (method, map kind)
    snapshot_wide_aspect: float = positive(2.0)
    # width of one map panel in that wide layout
    snapshot_wide_panel_inches: float = ranged(6.0, 0, 100, low_open=True)
    # space between the rows of that wide layout
    snapshot_wide_row_gap_inches: float = ranged(0.2, 0, 100)
    band_alpha: float = share(0.2)  # opacity of the standard-error bands
    # paired differences (first - second on the same episodes) the report lists when both ran
    paired_comparisons: tuple[tuple[str, str], ...] = (
        ("pipe", "pw_nbv"),
        ("mapex_plus", "pw_nbv"),
        ("mapex_plus", "mapex_plus_observed"),
        ("mapex_plus", "pipe"),
        ("mapex", "observed_map"),
    )
    paired_level: tuple[str, float] = share(("iou", 0.9))  # whose first step the pairs compare
    # teams' speed-up (speedup.png): the single-robot method N robots are compared with, on
    # the same episodes, and the coverage level whose median first step they compare
    speedup_reference: str = "mapex"
    speedup_level: float = ranged(0.9, 0, 1, low_open=True)

    @property
    def method_order(self) -> tuple[str, ...]:
        """Rows of every table and figure: the main comparison, the ablations, the methods
        beyond the paper, then the authors' follow-up."""
        return MAIN_COMPARISON + ABLATIONS + BEYOND_PAPER + FOLLOW_UP
