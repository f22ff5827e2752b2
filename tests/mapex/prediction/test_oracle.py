"""The oracle (mapex/prediction/oracle.py): the ground truth as the prediction, V_t = 1 on the
unknown cells, so that MapEx's gain is the exact count of unknown cells a frontier sees."""

from __future__ import annotations

import numpy as np
import pytest

from mapex.config import ExplorationConfig
from mapex.frontiers import extract_frontiers
from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.methods import make_method
from mapex.methods.base import PlanningContext
from mapex.navigation import cost_map, reachable_mask
from mapex.prediction import PREDICTORS, make_predictor
from mapex.prediction.oracle import OraclePrediction, OraclePredictor, oracle_prediction
from mapex.visibility import visible_mask


def two_rooms() -> tuple[np.ndarray, np.ndarray]:
    """(walls, observed): two rooms side by side joined by a door, the robot's room (left)
    known, the other unknown; the door's column is a frontier."""
    walls = np.zeros((40, 70), dtype=bool)
    walls[[0, -1], :] = walls[:, [0, -1]] = True
    walls[:, 30] = True
    walls[12:28, 30] = False  # a wide door (a frontier cluster of more than 10 cells)
    walls[15:25, 45:48] = True  # a pillar in the far room, hiding cells behind it
    observed = np.full(walls.shape, UNKNOWN, dtype=np.uint8)
    observed[:, :31] = np.where(walls[:, :31], OCCUPIED, FREE)
    return walls, observed


def test_the_truth_on_unknown_cells_and_a_variance_of_one_exactly_there():
    walls, observed = two_rooms()
    region = (0, 40, 20, 60)  # the pillar's right part and the last columns stay outside
    prediction = OraclePredictor(walls).predict(observed, region, (1, 2, 3))
    assert isinstance(prediction, OraclePrediction)
    assert prediction.answered == (1, 2, 3) and prediction.has_variance
    inside = np.zeros(walls.shape, dtype=bool)
    inside[0:40, 20:60] = True
    unknown = observed == UNKNOWN
    np.testing.assert_array_equal(prediction.mean[inside & unknown], walls[inside & unknown])
    np.testing.assert_array_equal(prediction.mean[~unknown], observed[~unknown] / 2)
    np.testing.assert_array_equal(prediction.mean[~inside & unknown], 0.5)  # not predicted
    np.testing.assert_array_equal(prediction.main, prediction.mean)
    assert prediction.variance.dtype == np.float32
    np.testing.assert_array_equal(prediction.variance, (inside & unknown).astype(np.float32))


def test_with_known_copies_new_cells_through_and_makes_them_certain():
    walls, observed = two_rooms()
    prediction = OraclePredictor(walls).predict(observed, None, (0, 1, 2, 3))
    later = observed.copy()
    later[10:30, 31:40] = np.where(walls[10:30, 31:40], OCCUPIED, FREE)
    later[25, 35] = OCCUPIED  # observed otherwise than the truth (a person standing there)
    updated = prediction.with_known(later)
    assert isinstance(updated, OraclePrediction) and updated.answered == (0, 1, 2, 3)
    np.testing.assert_array_equal(updated.variance, (later == UNKNOWN).astype(np.float32))
    assert updated.mean[25, 35] == 1.0 and prediction.mean[25, 35] == 0.0
    still = later == UNKNOWN
    np.testing.assert_array_equal(updated.mean[still], walls[still])


def test_the_oracle_is_registered_needs_the_walls_and_predicts_only_where_it_knows():
    walls, observed = two_rooms()
    assert PREDICTORS["oracle"] == "mapex.prediction.oracle:OraclePredictor"
    assert isinstance(make_predictor("oracle", walls), OraclePredictor)
    with pytest.raises(ValueError, match="needs the world's walls"):
        make_predictor("oracle")
    with pytest.raises(ValueError, match="knows a"):
        OraclePredictor(walls).predict(observed[:20])
    with pytest.raises(ValueError, match="not a crop"):
        OraclePredictor(walls).predict_members(observed[:20], (0,))
    whole = OraclePredictor(walls).predict_members(observed, (0, 2))
    assert whole.shape == (2, *walls.shape) and (whole == walls).all()
    with pytest.raises(ValueError, match="does not cover the region"):
        oracle_prediction(observed, walls[:10, :10], (0, 0), (0, 20, 0, 20), (0,))
    with pytest.raises(ValueError, match="no member"):
        oracle_prediction(observed, walls, (0, 0), None, ())


def test_a_truth_window_from_a_worker_gives_the_same_prediction():
    """The distributed oracle gets the truth of the region only, at its origin."""
    walls, observed = two_rooms()
    region = (5, 35, 25, 65)
    whole = oracle_prediction(observed, walls, (0, 0), region, (1, 2, 3))
    window = oracle_prediction(observed, walls[5:35, 25:65], (5, 25), region, (1, 2, 3), "w")
    np.testing.assert_array_equal(whole.members, window.members)
    np.testing.assert_array_equal(whole.variance, window.variance)
    assert window.served_by() == {"g": "w"} and whole.served_by() == {}


def test_mapex_under_the_oracle_scores_the_truly_visible_unknown_cells_per_distance():
    """MapEx's gain becomes the exact information gain: the unknown cells rays on the true
    walls reach from the frontier (the pillar hides what lies behind it)."""
    walls, observed = two_rooms()
    config = ExplorationConfig()
    pose = np.array([20, 10])
    cost = cost_map(observed, config.navigation)
    frontiers = extract_frontiers(observed, config.frontier)
    assert len(frontiers) >= 1
    context = PlanningContext(
        observed=observed,
        pose=pose,
        frontiers=frontiers,
        prediction=OraclePredictor(walls).predict(observed, None, (1, 2, 3)),
        cost=cost,
        reachable=reachable_mask(cost, (20, 10)),
        config=config,
        rng=np.random.default_rng(0),
    )
    scores = make_method("mapex", config).score(context)
    vis = config.visibility
    unknown = observed == UNKNOWN

    def seen_from(opacity: np.ndarray, cell: np.ndarray) -> int:
        mask = visible_mask(opacity.astype(np.float32), (int(cell[0]), int(cell[1])),
                            vis.n_rays, vis.range_cells, vis.stop_rule, vis.epsilon)  # fmt: skip
        return int(np.count_nonzero(mask & unknown))

    for frontier, score in zip(frontiers, scores, strict=True):
        count = seen_from(walls, frontier)
        distance = max(float(np.hypot(*(frontier - pose))), 1.0)
        assert count > 100 and score == pytest.approx(count / distance)
        assert count < seen_from(observed == OCCUPIED, frontier)  # the pillar hides cells
