"""Teams' speed-up over one robot on hand-made records: censored medians as intervals (odd
and even counts, ties, all censored), their ratios, the rows per world and pooled, the
report's section and speedup.png."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mapex.report import write_report
from mapex.report.config import ReportConfig
from mapex.report.runs import RunRecord, load_runs
from mapex.report.speedup import (
    NO_DATA,
    Interval,
    censored_median,
    ratio,
    speedup_rows,
    team_speedup_rows,
)

INF = math.inf


@pytest.mark.parametrize(
    ("steps", "budgets", "low", "high", "text"),
    [
        ([300, 100, 200], [1000] * 3, 200, 200, "200"),  # odd: the middle run
        ([400, 100, 200, 300], [1000] * 4, 250, 250, "250"),  # even: the two middle runs
        ([100, 100, 300], [1000] * 3, 100, 100, "100"),  # ties
        ([100, None, None], [1000] * 3, 1000, INF, "> 1000"),  # the middle run never got there
        ([100, 200, None], [1000] * 3, 200, 200, "200"),  # a censored run above the middle
        ([100, None], [1000] * 2, 550, INF, "> 550"),  # even: the upper middle never did
        ([100, 200, None, None], [1000] * 4, 600, INF, "> 600"),
        ([None, None], [800, 1000], 900, INF, "> 900"),  # all censored: above the budgets
        ([100, None, 300], [1000, 200, 1000], 200, 300, "200–300"),  # mixed budgets
    ],
)
def test_a_median_of_censored_steps_is_an_interval(steps, budgets, low, high, text):
    median = censored_median(steps, budgets)
    assert (median.low, median.high) == (low, high) and median.text() == text


def test_no_runs_no_median():
    assert censored_median([], []) is NO_DATA and NO_DATA.text() == "–"


@pytest.mark.parametrize(
    ("one", "team", "text"),
    [
        ((800, 800), (400, 400), "2.00"),  # both known
        ((1000, INF), (400, 400), "> 2.50"),  # one robot never got there: at least
        ((800, 800), (1000, INF), "< 0.80"),  # the team never did: at most
        ((1000, INF), (1000, INF), "?"),  # neither: nothing known
        ((0, 0), (0, 0), "–"),  # both at the start: undefined
    ],
)
def test_a_speedup_of_bounded_medians_is_bounded(one, team, text):
    assert ratio(Interval(*one), Interval(*team)).text(2) == text


def record(world, start, method, robots, cov90, steps=1000, path=100.0):
    """A run whose coverage reached 0.8 / 0.9 / 0.95 at cov90 / 2, cov90 and never."""
    metrics = {
        "world": world,
        "method": method,
        "start_index": start,
        "start": [0, 0],
        "seed": 0,
        "steps": steps,
        "auc": {"coverage": 0.5, "iou": 0.5, "tu": 0.5},
        "reached": {"coverage": {"0.8": None if cov90 is None else cov90 // 2, "0.9": cov90,
                                 "0.95": None}},
        "path_length_m": path * robots,
        "idle_steps": [10 * k for k in range(robots)],
    }  # fmt: skip
    if method != "mapex" or robots > 1:
        metrics["team"] = {"robots": robots, "overlap": 0.5}
    grid = np.arange(0, steps + 1, 50)
    flat = np.full(len(grid), 0.5)
    name = f"{world}-{method}-start{start}-seed0-team{robots}"
    return RunRecord(Path(name), metrics, grid, flat, flat, flat)


def campaign():
    """Two worlds x two starts: one mapex robot, mapex_team of 2 and of 4 (start 1 of world
    b: the single robot never got to 90 %)."""
    one = {("a", 0): 800, ("a", 1): 600, ("b", 0): 900, ("b", 1): None}
    two = {("a", 0): 400, ("a", 1): 300, ("b", 0): 500, ("b", 1): 700}
    four = {("a", 0): 200, ("a", 1): 200, ("b", 0): 300}  # b 1 not run: not compared
    runs = [record(w, s, "mapex", 1, v) for (w, s), v in one.items()]
    runs += [record(w, s, "mapex_team", 2, v) for (w, s), v in two.items()]
    runs += [record(w, s, "mapex_team", 4, v) for (w, s), v in four.items()]
    return runs


def test_speedup_rows_per_world_and_pooled_on_the_shared_episodes():
    rows = {(r.method, r.robots): r for r in speedup_rows(campaign(), ReportConfig())}
    alone, two, four = rows[("mapex", 1)], rows[("mapex_team", 2)], rows[("mapex_team", 4)]
    assert alone.speedup.text(2) == "1.00" and two.episodes == 4 and four.episodes == 3
    # one robot: 600, 800, 900, never -> (800 + 900) / 2; two: 300, 400, 500, 700 -> 450
    assert two.reference_steps[0.9] == Interval(850, 850) and two.median_steps[0.9].low == 450
    assert two.speedup.text(2) == f"{850 / 450:.2f}"
    assert two.by_world["a"].text(2) == "2.00"  # 700 / 350
    assert two.by_world["b"].text(2) == "> 1.58"  # (900 + 1000) / 2 / 600: a bound
    assert four.reference_steps[0.9].text() == "800" and four.speedup.text(2) == "4.00"
    assert two.median_steps[0.95].text() == "> 1000"  # nobody got there
    assert two.path_length_m == 200 and two.idle_steps == 5 and two.overlap == 0.5
    assert math.isnan(alone.overlap)


def test_the_median_per_episode_speedup_does_not_mix_building_sizes():
    # episodes a0 a1 b0 b1: 2, 2, 1.8 and 1000 / 700 to infinity (one robot never got there)
    two = {(r.method, r.robots): r for r in speedup_rows(campaign(), ReportConfig())}
    assert two[("mapex_team", 2)].episode_speedup == Interval((1.8 + 2) / 2, 2.0)
    assert two[("mapex", 1)].episode_speedup.text(2) == "1.00"
    # the pooled medians pair one robot's episode b with the team's episode c
    one = {"a": 100, "b": 1000, "c": 1100}
    team = {"a": 50, "b": 600, "c": 300}  # 2, 1.67 and 3.67 times faster
    runs = [record(w, 0, "mapex", 1, v) for w, v in one.items()]
    runs += [record(w, 0, "mapex_team", 2, v) for w, v in team.items()]
    row = {(r.method, r.robots): r for r in speedup_rows(runs, ReportConfig())}[("mapex_team", 2)]
    assert row.speedup.text(2) == "3.33" and row.episode_speedup.text(2) == "2.00"


def test_one_robot_against_itself_is_one_even_when_it_never_got_there():
    never = [record("a", 0, "mapex", 1, None), record("a", 0, "mapex_team", 2, 500)]
    rows = speedup_rows(never, ReportConfig())
    assert [row.speedup.text(2) for row in rows] == ["1.00", "> 2.00"]
    assert rows[0].by_world["a"].text(2) == "1.00"


def test_no_speedup_without_the_reference_robot_or_a_team():
    only_teams = [r for r in campaign() if r.metrics["method"] != "mapex"]
    assert speedup_rows(only_teams, ReportConfig()) == []
    alone = [r for r in campaign() if r.metrics["method"] == "mapex"]
    assert len(speedup_rows(alone, ReportConfig())) == 1
    assert team_speedup_rows(alone, ReportConfig()) == []


def write_folder(run: RunRecord, root: Path) -> None:
    folder = root / run.name
    folder.mkdir(parents=True)
    (folder / "metrics.json").write_text(json.dumps(run.metrics))
    lines = ["step,coverage,iou,tu"] + [f"{t},0.5,0.5,0.5" for t in run.steps]
    (folder / "curves.csv").write_text("\n".join(lines) + "\n")


def test_the_report_has_the_speedup_section_and_figure(tmp_path):
    for run in campaign():
        write_folder(run, tmp_path / "runs")
    runs = load_runs(tmp_path / "runs")
    files, _ = write_report(runs, tmp_path / "out", warn=lambda _: None, missing=["x"])
    text = (tmp_path / "out" / "report.md").read_text()
    assert "### Speed-up over one robot" in text
    row = "| mapex_team | 2 | 4 | 225 | 450 | > 1000 | 1.89 | 1.90–2.00 | 200 | 5 | 0.500 |"
    assert row in text
    assert "| b | > 1.58 | 3.00 |" in text  # per world: 900 / 300 for four robots
    data = json.loads((tmp_path / "out" / "report.json").read_text())
    pooled = {(r["method"], r["robots"]): r["speedup"] for r in data["speedup"]["rows"]}
    assert pooled[("mapex_team", 4)] == {"low": 4.0, "high": 4.0}
    figure = tmp_path / "out" / "speedup.png"
    assert figure in files.figures and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
