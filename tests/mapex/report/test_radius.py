"""The radius table (`python -m mapex.report.radius`) on hand-made records over a corridor:
the bound per world and team size, the ceiling min(N, one robot / bound), the speed-ups
measured beside it, and one-line refusals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mapex.report.config import ReportConfig
from mapex.report.radius import main, radius_markdown, radius_rows
from mapex.report.runs import ReportError, RunRecord
from mapex.worlds import World

CONFIG = {"sensor": {"range_cells": 10}, "motion": {"cells_per_step": 3}}


def corridor_world(name: str = "c") -> World:
    """A one-cell corridor of 100 cells between two walls; every cell valid."""
    occupancy = np.ones((3, 100), dtype=bool)
    occupancy[1] = False
    return World(name, occupancy, np.ones((3, 100), dtype=bool))


def record(method: str, robots: int, cov90: int | None, starts: list[list[int]]) -> RunRecord:
    metrics = {
        "world": "c", "method": method, "start_index": 0, "start": starts[0], "seed": 0,
        "steps": 1000, "auc": {"coverage": 0.5, "iou": 0.5, "tu": 0.5},
        "reached": {"coverage": {"0.9": cov90}}, "config": CONFIG,
    }  # fmt: skip
    if robots > 1:
        metrics["team"] = {"robots": robots, "starts": starts, "overlap": 0.5}
    grid = np.arange(0, 1001, 50)
    flat = np.full(len(grid), 0.5)
    name = f"c-{method}-start0-seed0-team{robots}"
    return RunRecord(Path(name), metrics, grid, flat, flat, flat)


def test_the_ceiling_is_the_smaller_of_n_and_one_robot_over_the_bound():
    # 90 % of 300 cells: the 270th nearest is 89 hops away from one end: ceil(78 / 3) = 26
    runs = [
        record("mapex", 1, 130, [[1, 0]]),
        record("mapex_assign", 2, 70, [[1, 0], [1, 1]]),
        record("mapex_assign", 8, 30, [[1, 0], [1, 1]]),
    ]
    rows = {
        (r.world, r.robots): r for r in radius_rows(runs, {"c": corridor_world()}, ReportConfig())
    }
    one, two, eight = rows[("c", 1)], rows[("c", 2)], rows[("c", 8)]
    assert one.bound_steps == 26 and two.bound_steps == 26  # the second start: no nearer end
    assert one.reference_steps.text() == "130"
    assert two.ceiling.text(2) == "2.00"  # k-fold binds
    assert eight.ceiling.text(2) == "5.00"  # the radius binds: 130 / 26
    assert two.measured["mapex_assign x2"].text(2) == "1.86"
    assert rows[("pooled", 8)].ceiling.text(2) == "5.00"
    table = radius_markdown(list(rows.values()), ReportConfig())
    assert "| c | 8 | 1 | 26 | 130 | 5.00 | mapex_assign x8 4.33 |" in table


def test_a_level_out_of_reach_has_an_infinite_bound():
    world = corridor_world()
    world.occupancy[1, 20] = True  # 80 % of the corridor out of sight
    rows = radius_rows([record("mapex", 1, None, [[1, 0]])], {"c": world}, ReportConfig())
    assert math.isinf(rows[0].bound_steps)


def test_a_world_without_its_map_is_refused():
    with pytest.raises(ReportError, match="no map given for world c"):
        radius_rows([record("mapex", 1, 130, [[1, 0]])], {}, ReportConfig())


def test_the_command_refuses_bad_input_in_one_line(tmp_path, capsys):
    assert main([str(tmp_path / "nowhere"), "--maps", "generated:0"]) == 2
    assert main([str(tmp_path), "--maps", "generated:0"]) == 2
    (tmp_path / "garbage").mkdir()
    (tmp_path / "garbage" / "metrics.json").write_bytes(b"\0" * 64)
    assert main([str(tmp_path), "--maps", "no_such_world_spec"]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert [line.startswith("mapex.report.radius: ") for line in errors[-1:]] == [True]
    assert not any("Traceback" in line for line in errors)
