"""The predictor interface: ensemble statistics, region prediction, known-cell copy-through."""

from __future__ import annotations

import numpy as np
import pytest

from mapex.grid import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    dequantise_probability,
    observed_to_probability,
    quantise_probability,
)
from mapex.prediction.base import EnsemblePrediction, Predictor, known_region, with_context

HALF_LEVEL = 1 / 510  # quantisation error bound of a member output


class _ConstantMembers(Predictor):
    """Member i predicts (i + 1) / 10 everywhere; remembers the crops it was given."""

    name = "constant"

    def __init__(self, n_members: int = 3) -> None:
        self.n_members = n_members
        self.crops: list[np.ndarray] = []

    def predict_members(self, observed: np.ndarray, members) -> np.ndarray:
        self.crops.append(observed.copy())
        values = (np.asarray(members, dtype=np.float32) + 1) / 10
        return np.broadcast_to(values[:, None, None], (len(values), *observed.shape)).copy()


def _random_observed(shape: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.choice(np.array([FREE, UNKNOWN, OCCUPIED], dtype=np.uint8), size=shape)


@pytest.mark.parametrize(
    ("values", "mean", "variance"),
    [([0.0, 1.0], 0.5, 0.5), ([0.2, 0.4, 0.6], 0.4, 0.04), ([0.3, 0.3, 0.3, 0.3], 0.3, 0.0)],
)
def test_mean_and_unbiased_variance_over_the_members_but_not_g(
    values: list[float], mean: float, variance: float
) -> None:
    """G (row 0, here 0.9) is P_t; M_t and V_t are over G_1..G_n only (SPEC §4)."""
    rows = np.array([0.9, *values], dtype=np.float32)
    members = rows[:, None, None] * np.ones((1, 2, 3), np.float32)
    prediction = EnsemblePrediction(members)
    assert prediction.mean.dtype == np.float32 and prediction.variance.dtype == np.float32
    np.testing.assert_allclose(prediction.mean, mean, atol=1e-6)
    np.testing.assert_allclose(prediction.variance, variance, atol=1e-6)
    np.testing.assert_array_equal(prediction.main, members[0])


@pytest.mark.parametrize("rows", [1, 2])  # G alone; G and one member
def test_variance_of_fewer_than_two_members_is_zero(rows: int) -> None:
    prediction = EnsemblePrediction(np.full((rows, 4, 5), 0.7, dtype=np.float32))
    np.testing.assert_array_equal(prediction.variance, np.zeros((4, 5), np.float32))
    np.testing.assert_allclose(prediction.mean, 0.7)
    assert not prediction.has_variance


def test_variance_matches_numpy_ddof_one_per_cell() -> None:
    members = np.random.default_rng(3).random((4, 6, 7)).astype(np.float32)
    prediction = EnsemblePrediction(members)
    np.testing.assert_allclose(prediction.variance, np.var(members[1:], axis=0, ddof=1), rtol=1e-5)
    np.testing.assert_allclose(prediction.mean, members[1:].mean(axis=0), rtol=1e-6)


def test_predict_whole_map_copies_known_cells_and_fills_unknown_ones() -> None:
    observed = _random_observed((9, 13), seed=1)
    predictor = _ConstantMembers(n_members=3)
    prediction = predictor.predict(observed)
    assert prediction.members.shape == (3, 9, 13) and prediction.members.dtype == np.float32
    np.testing.assert_array_equal(predictor.crops[0], observed)
    known = observed != UNKNOWN
    for i in range(3):
        member = prediction.members[i]
        np.testing.assert_array_equal(member[known], observed[known] / 2)
        np.testing.assert_allclose(member[~known], (i + 1) / 10, atol=HALF_LEVEL)
    np.testing.assert_array_equal(prediction.variance[known], 0.0)
    np.testing.assert_allclose(prediction.variance[~known], 0.005, atol=1e-3)  # 0.2 and 0.3
    assert prediction.answered == (0, 1, 2)


def test_with_known_is_the_prediction_with_a_later_maps_known_cells() -> None:
    """Cells known since the prediction are copied through (certain: no variance); the
    cells still unknown keep what the members said; predicting the later map gives the
    same numbers where the prediction saw the same cells."""
    earlier = _random_observed((9, 13), seed=3)
    later = earlier.copy()
    later[earlier == UNKNOWN] = np.where(np.arange((earlier == UNKNOWN).sum()) % 2, FREE, UNKNOWN)
    predictor = _ConstantMembers(n_members=3)
    updated = predictor.predict(earlier).with_known(later)
    np.testing.assert_array_equal(updated.members, predictor.predict(later).members)
    assert np.all(updated.variance[later != UNKNOWN] == 0.0)
    assert updated.answered == (0, 1, 2)


def test_member_outputs_are_quantised_to_the_wire_levels() -> None:
    observed = _random_observed((6, 7), seed=5)
    prediction = _ConstantMembers(n_members=2).predict(observed)
    unknown = observed == UNKNOWN
    levels = prediction.members[:, unknown] * 255
    np.testing.assert_allclose(levels, np.rint(levels), atol=1e-4)
    np.testing.assert_array_equal(
        dequantise_probability(quantise_probability(prediction.members)), prediction.members
    )


def test_answered_names_the_requested_members_in_order() -> None:
    observed = _random_observed((4, 4), seed=6)
    prediction = _ConstantMembers(n_members=4).predict(observed, members=(2, 0))
    assert prediction.answered == (2, 0) and not prediction.has_variance  # one of G_1..G_n
    np.testing.assert_allclose(prediction.mean[observed == UNKNOWN], 0.3, atol=HALF_LEVEL)
    both = _ConstantMembers(n_members=4).predict(observed, members=(3, 0, 1))
    assert both.has_variance
    np.testing.assert_allclose(both.mean[observed == UNKNOWN], 0.3, atol=HALF_LEVEL)  # 0.4, 0.2


def test_predict_region_only_touches_the_region() -> None:
    observed = _random_observed((20, 30), seed=2)
    region = (3, 11, 5, 24)
    predictor = _ConstantMembers(n_members=2)
    prediction = predictor.predict(observed, region)
    np.testing.assert_array_equal(predictor.crops[0], observed[3:11, 5:24])
    inside = np.zeros(observed.shape, dtype=bool)
    inside[3:11, 5:24] = True
    expected_outside = observed_to_probability(observed)[~inside]
    for member in prediction.members:
        np.testing.assert_array_equal(member[~inside], expected_outside)  # unknown stays 0.5
    np.testing.assert_array_equal(prediction.variance[~inside], 0.0)
    unknown_inside = inside & (observed == UNKNOWN)
    np.testing.assert_allclose(prediction.members[1][unknown_inside], 0.2, atol=HALF_LEVEL)


class _EdgeMarkingMembers(Predictor):
    """Predicts wall (1) on the border cells of whatever crop it is given, free (0) inside:
    a network that mistakes a crop's edge for the map's border."""

    name = "edges"
    n_members = 2

    def __init__(self, context_cells: int) -> None:
        self.context_cells = context_cells

    def predict_members(self, observed: np.ndarray, members) -> np.ndarray:
        edges = np.ones(observed.shape, dtype=np.float32)
        edges[1:-1, 1:-1] = 0.0
        return np.repeat(edges[None], len(members), axis=0)


@pytest.mark.parametrize("context_cells", [0, 1, 5, 100])
def test_context_keeps_region_edges_inside_the_map_from_looking_like_the_border(
    context_cells: int,
) -> None:
    observed = np.full((30, 40), UNKNOWN, dtype=np.uint8)
    region = (0, 20, 10, 35)  # touches the map's top border only
    prediction = _EdgeMarkingMembers(context_cells).predict(observed, region).main
    inside = prediction[0:20, 10:35]
    assert (inside[0] == 1.0).all()  # the real border is seen as one
    interior_edges = np.concatenate([inside[-1], inside[1:, 0], inside[1:, -1]])
    assert (interior_edges == 1.0).all() == (context_cells == 0)


@pytest.mark.parametrize(
    ("context", "expected"), [(0, (3, 9, 4, 8)), (2, (1, 11, 2, 10)), (9, (0, 12, 0, 10))]
)
def test_with_context_grows_and_clips(context: int, expected: tuple[int, int, int, int]) -> None:
    assert with_context((3, 9, 4, 8), (12, 10), context) == expected


def test_predict_main_is_member_zero_of_the_whole_map() -> None:
    observed = _random_observed((5, 8), seed=4)
    predictor = _ConstantMembers(n_members=2)
    np.testing.assert_array_equal(
        predictor.predict_main(observed), predictor.predict(observed).main
    )


@pytest.mark.parametrize(
    ("margin", "expected"), [(0, (4, 7, 10, 16)), (2, (2, 9, 8, 18)), (50, (0, 20, 0, 30))]
)
def test_known_region_is_the_grown_and_clipped_bounding_box(
    margin: int, expected: tuple[int, int, int, int]
) -> None:
    observed = np.full((20, 30), UNKNOWN, dtype=np.uint8)
    observed[4, 12] = FREE
    observed[6, 10] = OCCUPIED
    observed[5, 15] = FREE
    assert known_region(observed, margin) == expected


def test_known_region_of_an_all_unknown_map_is_the_whole_map() -> None:
    assert known_region(np.full((7, 9), UNKNOWN, dtype=np.uint8), 3) == (0, 7, 0, 9)


def test_region_prediction_matches_whole_map_statistics_inside_the_region():
    observed = _random_observed((30, 40), seed=3)
    region = (5, 20, 10, 35)
    prediction = _ConstantMembers().predict(observed, region)
    reference = EnsemblePrediction(prediction.members)  # statistics over the whole map
    np.testing.assert_allclose(prediction.mean, reference.mean, atol=1e-6)
    np.testing.assert_allclose(prediction.variance, reference.variance, atol=1e-6)
    np.testing.assert_allclose(
        reference.variance, prediction.members[1:].var(axis=0, ddof=1), atol=1e-6
    )
