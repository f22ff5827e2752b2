"""deploy/throughput_model.py: the sizing model on fixed inputs, and its figure."""

from __future__ import annotations

import dataclasses

import matplotlib.image
import pytest

from deploy.throughput_model import (
    FIGURE,
    MEASURED,
    MEASURED_POINTS,
    EpisodeDemand,
    MeasuredPoint,
    bounds_per_hour,
    draw,
    episodes_per_hour,
    main,
)

# 1000 steps of 10 ms, 40 re-plans asking g1..g3 200 ms each (10 ms more on the wire), and
# 20 whole-map samples of G at 300 ms: a planner is busy 10 + 40 x 0.21 = 18.4 s per
# episode, g1..g3 8 s each and g 6 s, the CPU 10 + 24 + 6 = 40 s.
DEMAND = EpisodeDemand(
    steps=1000,
    step_s=0.01,
    replans=40,
    replan_members=("g1", "g2", "g3"),
    replan_query_s=0.2,
    metric_samples=20,
    metric_query_s=0.3,
    round_trip_s=0.01,
)


def test_the_bounds_are_the_planners_the_busiest_member_and_the_cores():
    assert DEMAND.planner_s() == pytest.approx(18.4)
    assert DEMAND.member_s() == pytest.approx({"g1": 8.0, "g2": 8.0, "g3": 8.0, "g": 6.0})
    assert DEMAND.cpu_s() == pytest.approx(40.0)
    assert bounds_per_hour(DEMAND, 2, 3, cores=16) == pytest.approx(
        {"planners": 3600 * 2 / 18.4, "workers": 3600 * 3 / 8.0, "cores": 3600 * 16 / 40.0}
    )
    assert episodes_per_hour(DEMAND, 1, 1) == pytest.approx(3600 / 18.4)  # planner-bound
    assert episodes_per_hour(DEMAND, 4, 1) == pytest.approx(450.0)  # g1..g3 saturate
    assert episodes_per_hour(DEMAND, 4, 1, cores=2) == pytest.approx(180.0)  # one machine


def test_more_planners_or_workers_never_lower_the_throughput_and_each_saturates():
    for planners in (1, 2, 8, 64):
        rates = [episodes_per_hour(DEMAND, planners, w) for w in range(1, 65)]
        assert rates == sorted(rates)
        assert rates[-1] == pytest.approx(3600 * planners / DEMAND.planner_s())  # planners bind
    rates = [episodes_per_hour(DEMAND, p, 2) for p in range(1, 65)]
    assert rates == sorted(rates) and rates[-1] == pytest.approx(900.0)  # workers bind


def test_a_method_that_reads_g_at_re_plans_loads_g_with_both():
    g_only = dataclasses.replace(DEMAND, replan_members=("g",))
    assert g_only.member_s() == pytest.approx({"g": 8.0 + 6.0})
    assert episodes_per_hour(g_only, 100, 1) == pytest.approx(3600 / 14.0)


def test_the_figure_is_drawn_from_fixed_inputs(tmp_path):
    path = tmp_path / "model.png"
    draw(DEMAND, [MeasuredPoint(1, 1, 150.0, 1.5), MeasuredPoint(2, 2, 300.0, 2.0)], path)
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 500
    assert main(["--figure", str(tmp_path / "shipped.png")]) == 0  # the measured figures
    assert (tmp_path / "shipped.png").stat().st_size > 0


def test_the_shipped_figures_are_complete_and_the_figure_is_in_the_docs():
    fields = [MEASURED.step_s, MEASURED.replans, MEASURED.replan_query_s]
    fields += [MEASURED.metric_samples, MEASURED.metric_query_s, MEASURED.round_trip_s]
    assert all(value > 0 for value in fields)
    assert {(p.planners, p.workers) for p in MEASURED_POINTS} == {(1, 1), (2, 1), (2, 2)}
    assert FIGURE.is_file()


def test_a_missing_figure_folder_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["--figure", str(tmp_path / "no" / "model.png")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
