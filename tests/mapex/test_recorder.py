"""The metric recorder's time-to-level record: the first step coverage and G's IoU reach each
level, to the step whatever the sampling interval, censored runs, and the IoU stop."""

import dataclasses

import numpy as np
import pytest

from mapex.config import ExplorationConfig, MetricsConfig
from mapex.episode import IOU_REACHED, run_episode
from mapex.grid import FREE, UNKNOWN
from mapex.prediction import make_predictor
from mapex.recorder import StepTracker
from mapex.worlds import generate_floor_plan

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
