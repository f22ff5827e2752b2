"""The metric recorder's time-to-level record: the first step coverage and G's IoU reach each
level, to the step whatever the sampling interval, censored runs, and the IoU and coverage
stops."""

import dataclasses

import numpy as np
import pytest

from mapex.config import ExplorationConfig, MetricsConfig
from mapex.episode import COVERAGE_REACHED, IOU_REACHED, run_episode
from mapex.grid import FREE, UNKNOWN
from mapex.prediction import make_predictor
from mapex.recorder import MetricRecorder, StepTracker
from mapex.results import describe_end
from mapex.worlds import generate_floor_plan
from mapex.worlds.starts import start_cell

LEVELS = (0.3, 0.5, 0.99)


def episode(every: int, steps: int = 300, until_iou: float | None = None):
    config = ExplorationConfig(
        steps=steps,
        until_iou=until_iou,
        metrics=MetricsConfig(sample_every_steps=every, reach_levels=LEVELS),
    )
    world = generate_floor_plan(5)
    return run_episode(world, "nearest", make_predictor("classical"), 1, config=config)


@pytest.fixture(scope="module")
def every_step():
    return episode(every=1)


def test_levels_are_found_to_the_step_between_samples(every_step):
    sampled = episode(every=50)
    assert sampled.curves.reached == every_step.curves.reached
    iou = every_step.curves.iou
    first = next(t for t, value in zip(every_step.curves.steps, iou, strict=True) if value >= 0.3)
    assert every_step.curves.reached["iou"][0.3] == first
    assert first % 50 != 0  # found between two samples, not at one


def test_coverage_levels_match_the_every_step_curve(every_step):
    steps, coverage = every_step.curves.steps, every_step.curves.coverage
    for level, reached in every_step.curves.reached["coverage"].items():
        expected = next((t for t, c in zip(steps, coverage, strict=True) if c >= level), None)
        assert reached == expected


def test_a_level_never_reached_is_censored(every_step):
    assert every_step.curves.reached["iou"][0.99] is None
    assert every_step.curves.reached["coverage"][0.99] is None
    assert max(every_step.curves.iou) < 0.99


def test_until_iou_ends_the_run_at_the_first_sample_that_reaches_it():
    result = episode(every=50, until_iou=0.3)
    reached = result.curves.reached["iou"][0.3]
    assert result.end_reason == IOU_REACHED
    assert result.finished_at == 50 * -(-reached // 50)  # the first sample at or after it
    assert result.curves.steps[-1] == 300  # held to T, so AUCs compare
    held = result.curves.steps.index(result.finished_at)
    assert len(set(result.curves.iou[held:])) == 1


def test_until_coverage_ends_the_run_at_the_step_coverage_reaches_it(every_step):
    config = ExplorationConfig(
        steps=300, metrics=MetricsConfig(reach_levels=LEVELS, until_coverage=0.3)
    )
    world = generate_floor_plan(5)
    result = run_episode(world, "nearest", make_predictor("classical"), 1, config=config)
    reached = every_step.curves.reached["coverage"][0.3]
    assert result.end_reason == COVERAGE_REACHED and result.finished_at == reached
    assert result.curves.reached["coverage"][0.3] == reached and reached % 50 != 0
    assert len(result.trajectory) == reached + 1  # no step after it
    assert result.curves.steps[-1] == 300  # held to T, as with until_iou
    assert describe_end(result) == f"coverage reached 0.3 at step {reached}"


def test_the_tracker_rebuilds_every_step_between_samples():
    valid = np.ones((4, 5), dtype=bool)
    maps = [np.full((4, 5), UNKNOWN, dtype=np.uint8) for _ in range(4)]
    for t in range(1, 4):
        maps[t] = maps[t - 1].copy()
        maps[t][t, : t + 1] = FREE
    tracker = StepTracker(valid)
    coverages = [tracker.track(t, observed) for t, observed in enumerate(maps)]
    assert coverages == [np.count_nonzero(m != UNKNOWN) / 20 for m in maps]
    rebuilt = [(t, observed.copy()) for t, observed in tracker.window(until=3)]
    assert [t for t, _ in rebuilt] == [1, 2]
    for t, observed in rebuilt:
        np.testing.assert_array_equal(observed, maps[t])
    tracker.complete(2)
    assert [t for t, _ in tracker.window(until=4)] == [3]


def test_reach_levels_are_checked():
    with pytest.raises(ValueError, match="reach_levels must be in"):
        dataclasses.replace(MetricsConfig(), reach_levels=(0.5, 1.5))


def test_a_sample_is_completed_complete_after_steps_after_it_was_taken():
    """A live view trails the run by `metrics.complete_after_steps`, not by a sample period:
    the sample taken at t = 0 is in the curves from step 10 on, not only from step 50."""
    world = generate_floor_plan(1)
    config = MetricsConfig(sample_every_steps=50, complete_after_steps=10)
    recorder = MetricRecorder(world, start_cell(world, 0, 3), None, config)
    observed = np.full(world.shape, UNKNOWN, dtype=np.uint8)
    taken = []
    for t in range(61):
        observed[t, :] = FREE  # the map changes at every step
        recorder.at_step(t, observed)
        taken.append(list(recorder.curves.steps))
    assert taken[0] == taken[9] == []
    assert taken[10] == taken[59] == [0]
    assert taken[60] == [0, 50]
