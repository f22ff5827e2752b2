"""The report's time to a level on hand-made records: censored medians, ties, the share of
runs there by step t, paired differences, and records older than the field."""

import math
from pathlib import Path

import numpy as np
import pytest

from mapex.report import write_report
from mapex.report.reach import (
    ReachStat,
    censored_median,
    paired_rows,
    reach_table,
    share_reached,
)
from mapex.report.runs import RunRecord


def record(method, start, iou90, coverage_auc=0.5, steps=1000, world="w"):
    """A run that reached IoU 0.9 at step `iou90` (None: never) and coverage 0.9 at 100."""
    metrics = {
        "world": world,
        "method": method,
        "start_index": start,
        "start": [0, 0],
        "seed": 0,
        "steps": steps,
        "auc": {"coverage": coverage_auc, "iou": 0.5, "tu": 0.5},
        "reached": {"coverage": {"0.9": 100}, "iou": {"0.9": iou90}},
    }
    grid = np.arange(0, steps + 1, 50)
    flat = np.full(len(grid), 0.5)
    return RunRecord(Path(f"{world}-{method}-start{start}-seed0"), metrics, grid, flat, flat, flat)


@pytest.mark.parametrize(
    ("steps", "median"),
    [
        ([300, 100, 200], 200),
        ([100, 200], 150),
        ([100, None, 300], 300),  # a never counts as later than all
        ([100, None], math.inf),  # half never: the median is never
        ([None, None, 50], math.inf),
        ([70, 70, 70, None], 70),  # ties
    ],
)
def test_censored_median(steps, median):
    assert censored_median(steps) == median


def test_censored_median_of_no_runs_is_nan():
    assert math.isnan(censored_median([]))


def test_the_table_counts_runs_that_never_got_there():
    runs = [record("a", 0, 400), record("a", 1, None), record("a", 2, 600), record("b", 0, None)]
    table = reach_table(runs, ["b", "a"])
    assert list(table) == ["b", "a"]
    stat = table["a"][("iou", 0.9)]
    assert (stat.median, stat.reached, stat.never) == (600, 2, 1)
    assert table["b"][("iou", 0.9)].median == math.inf
    assert table["a"][("coverage", 0.9)].median == 100


def test_share_reached_by_step():
    runs = [record("a", 0, 2), record("a", 1, None), record("a", 2, 4), record("a", 3, 2)]
    share = share_reached(runs, ("iou", 0.9), horizon=5)
    np.testing.assert_allclose(share, [0, 0, 0.5, 0.5, 0.75, 0.75])


def test_paired_rows_match_episodes_and_order_by_first_step():
    runs = [record("a", s, step, coverage_auc=0.6) for s, step in enumerate([100, None, 300])]
    runs += [record("b", s, step, coverage_auc=0.5) for s, step in enumerate([200, None, 200])]
    runs.append(record("a", 9, 50))  # no partner: not paired
    (row,) = paired_rows(runs, [("a", "b"), ("a", "missing")], ("iou", 0.9))
    assert row.episodes == 3
    assert row.auc_difference["coverage"].mean == pytest.approx(0.1)
    assert (row.sooner, row.later, row.ties) == (1, 1, 1)  # both never: a tie


def test_report_writes_the_section_and_figure_and_skips_old_records(tmp_path):
    runs = [record("mapex", s, step) for s, step in enumerate([100, None])]
    old = record("nearest", 0, None)
    del old.metrics["reached"]  # written before the field existed
    files, summary = write_report(runs + [old], tmp_path, warn=lambda message: None)
    text = files.markdown.read_text()
    assert "## Time to a level" in text and "| mapex | 2 | 100 (0) | never (1) |" in text
    assert "| nearest |" not in text.split("## Time to a level")[1].split("##")[0]
    assert (tmp_path / "reach.png") in files.figures


def test_a_level_a_run_did_not_record_is_not_counted_as_never():
    custom = record("a", 1, None)
    custom.metrics["reached"] = {"iou": {"0.5": 300}}  # run with other reach levels
    runs = [record("a", 0, 400), custom]
    table = reach_table(runs, ["a"])
    assert table["a"][("iou", 0.9)] == ReachStat(400, 1, 0)
    assert table["a"][("iou", 0.5)] == ReachStat(300, 1, 0)
    np.testing.assert_allclose(share_reached(runs, ("iou", 0.9), horizon=500)[-1], 1.0)
