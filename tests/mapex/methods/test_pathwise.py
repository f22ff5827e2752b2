"""pipe, pw_nbv and mapex_plus_observed on hand-made scenes: open doors along the way beat a
dead end, agreed cells earn pipe nothing, and the authors' path samples."""

import dataclasses

import numpy as np
import pytest

from mapex.config import ConfigError, ExplorationConfig, apply_overrides
from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.methods import make_method
from mapex.methods.pathwise import pipe_samples
from tests.mapex.methods.test_path_gain import DISAGREEING, context_for

LEFT_END, RIGHT_END = (30, 10), (30, 70)  # the corridor's two frontiers, 30 cells from the robot
ROBOT = (30, 40)


def corridor(doors_on_the_left: bool) -> np.ndarray:
    """An east-west corridor (rows 28-32, cols 10-70) open to unknown space at both ends,
    robot in the middle. With doors: two 4-cell openings in its north wall on the left half
    (cols 16-19 and 24-27) look into unknown rooms; the right half is walled throughout."""
    observed = np.full((61, 81), UNKNOWN, dtype=np.uint8)
    observed[28:33, 10:71] = FREE
    observed[27, 10:71] = OCCUPIED
    observed[33, 10:71] = OCCUPIED
    if doors_on_the_left:
        observed[27, 16:20] = UNKNOWN
        observed[27, 24:28] = UNKNOWN
    return observed


def short_sight() -> ExplorationConfig:
    """Rays of 12 cells: each end sees only the unknown space next to it."""
    config = ExplorationConfig()
    return dataclasses.replace(
        config, visibility=dataclasses.replace(config.visibility, range_cells=12)
    )


def end_scores(name: str, observed: np.ndarray, config: ExplorationConfig, members=None):
    """(left end's score, right end's score) under method `name`."""
    context = context_for(observed, ROBOT, [LEFT_END, RIGHT_END], config)
    if members is not None:
        context.prediction.members[...] = members
    return tuple(make_method(name, config).score(context))


@pytest.mark.parametrize("name", ["pipe", "pw_nbv", "mapex_plus_observed"])
def test_a_path_past_open_doors_outranks_a_dead_end(name):
    left, right = end_scores(name, corridor(doors_on_the_left=True), short_sight())
    assert left > right > 0


@pytest.mark.parametrize("name", ["pipe", "pw_nbv"])
def test_without_doors_the_two_ends_tie(name):
    left, right = end_scores(name, corridor(doors_on_the_left=False), short_sight())
    assert left == pytest.approx(right, rel=0.05)


def test_pipe_gives_no_credit_to_cells_the_ensemble_agrees_on():
    observed = corridor(doors_on_the_left=False)
    members = np.repeat((observed.astype(np.float32) / 2)[None], 4, axis=0)
    unknown = observed == UNKNOWN
    members[:, unknown] = DISAGREEING[:, None]
    members[:, :, :40] = np.where(unknown[:, :40], np.float32(0.3), members[:, :, :40])  # agree
    pipe_left, pipe_right = end_scores("pipe", observed, short_sight(), members)
    nbv_left, nbv_right = end_scores("pw_nbv", observed, short_sight(), members)
    assert pipe_left == 0.0 and pipe_right > 0
    assert nbv_left == pytest.approx(nbv_right, rel=0.05)  # no prediction: area only


def test_unreachable_frontiers_score_minus_infinity():
    observed = corridor(doors_on_the_left=False)
    observed[28:33, 20] = OCCUPIED  # the left end is cut off
    for name in ("pipe", "pw_nbv"):
        left, right = end_scores(name, observed, short_sight())
        assert left == -np.inf and np.isfinite(right)


def test_pipe_samples_every_nth_cell_after_the_robots_own():
    path = np.stack([np.full(10, 5), np.arange(10)], axis=1)
    np.testing.assert_array_equal(pipe_samples(path, 3)[:, 1], [2, 5, 8])  # path[n-1::n]
    np.testing.assert_array_equal(pipe_samples(path[:2], 3), [[5, 1]])  # too short: its end


def test_pipe_reads_only_the_members_and_pw_nbv_no_prediction():
    config = ExplorationConfig()
    assert make_method("pipe", config).prediction_members(4) == (1, 2, 3)
    assert not make_method("pw_nbv", config).uses_prediction
    assert not make_method("mapex_plus_observed", config).uses_prediction


def test_pipe_sample_spacing_is_validated():
    assert (
        apply_overrides(ExplorationConfig(), ["pipe.path_sample_cells=5"]).pipe.path_sample_cells
        == 5
    )
    with pytest.raises(ConfigError, match="pipe.path_sample_cells must be >= 1"):
        apply_overrides(ExplorationConfig(), ["pipe.path_sample_cells=0"])
