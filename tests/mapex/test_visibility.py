"""Visibility raycasts against the slab-method reference of test_raycast."""

from __future__ import annotations

import numpy as np
import pytest
from reference_rays import reference_walk

from mapex.raycast import ray_directions
from mapex.visibility import STOP_RULES, visibility_gain, visible_mask

N_RAYS = 61
RANGE_CELLS = 30


def random_opacity(seed: int) -> np.ndarray:
    """float32 20-60 cells a side: mostly clear, some walls near 1, a haze of small values."""
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(20, 61)), int(rng.integers(20, 61)))
    opacity = np.where(rng.random(shape) < 0.3, rng.random(shape) * 0.4, 0.0)
    opacity[rng.random(shape) < 0.05] = 0.95
    return opacity.astype(np.float32)


def random_viewpoints(shape: tuple[int, int], count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([rng.integers(0, shape[0], count), rng.integers(0, shape[1], count)], axis=1)


def reference_mask(opacity, viewpoint, n_rays, range_cells, stop_rule, epsilon) -> np.ndarray:
    """Union over rays of the reference walk cut after the cell where the stop rule fires."""
    mask = np.zeros(opacity.shape, dtype=bool)
    for direction in ray_directions(n_rays):
        cells = reference_walk(opacity.shape, tuple(viewpoint), direction, range_cells)
        values = opacity[cells[:, 0], cells[:, 1]].astype(np.float64)
        if stop_rule == "accumulate":
            values = np.cumsum(values)
        stops = np.flatnonzero(values >= epsilon)
        if len(stops):
            cells = cells[: stops[0] + 1]
        mask[cells[:, 0], cells[:, 1]] = True
    return mask


@pytest.mark.parametrize("stop_rule", STOP_RULES)
@pytest.mark.parametrize("seed", range(4))
def test_visible_mask_matches_reference(stop_rule: str, seed: int) -> None:
    opacity = random_opacity(seed)
    for viewpoint in random_viewpoints(opacity.shape, 3, seed):
        mask = visible_mask(opacity, tuple(viewpoint), N_RAYS, RANGE_CELLS, stop_rule, 0.8)
        expected = reference_mask(opacity, viewpoint, N_RAYS, RANGE_CELLS, stop_rule, 0.8)
        np.testing.assert_array_equal(mask, expected)


@pytest.mark.parametrize("stop_rule", STOP_RULES)
def test_unit_weight_gain_counts_each_visible_cell_once(stop_rule: str) -> None:
    opacity = random_opacity(10)
    viewpoints = random_viewpoints(opacity.shape, 6, 10)
    ones = np.ones(opacity.shape, dtype=np.float32)
    gains = visibility_gain(opacity, ones, viewpoints, N_RAYS, RANGE_CELLS, stop_rule, 0.8)
    for gain, viewpoint in zip(gains, viewpoints, strict=True):
        mask = visible_mask(opacity, tuple(viewpoint), N_RAYS, RANGE_CELLS, stop_rule, 0.8)
        assert gain == mask.sum()


@pytest.mark.parametrize("stop_rule", STOP_RULES)
def test_gain_is_the_weight_of_the_visible_set_and_additive(stop_rule: str) -> None:
    rng = np.random.default_rng(11)
    opacity = random_opacity(11)
    w1 = rng.random(opacity.shape).astype(np.float32)
    w2 = (rng.random(opacity.shape) < 0.5).astype(np.float32)
    viewpoints = random_viewpoints(opacity.shape, 5, 11)

    def gain(weights: np.ndarray) -> np.ndarray:
        return visibility_gain(opacity, weights, viewpoints, N_RAYS, RANGE_CELLS, stop_rule, 0.8)

    for g, viewpoint in zip(gain(w1), viewpoints, strict=True):
        mask = visible_mask(opacity, tuple(viewpoint), N_RAYS, RANGE_CELLS, stop_rule, 0.8)
        assert g == pytest.approx(w1[mask].astype(np.float64).sum(), rel=1e-9)
    np.testing.assert_allclose(gain(w1 + w2), gain(w1) + gain(w2), rtol=1e-6)
    np.testing.assert_allclose(gain(3 * w2), 3 * gain(w2), rtol=1e-6)


def test_gain_of_each_viewpoint_is_independent_of_the_others() -> None:
    """More than 255 viewpoints exercises the stamp reset; repeats must score the same."""
    opacity = random_opacity(12)
    weights = np.random.default_rng(12).random(opacity.shape).astype(np.float32)
    viewpoints = random_viewpoints(opacity.shape, 300, 12)
    viewpoints[105] = viewpoints[0]
    viewpoints[150:] = viewpoints[:150]  # so viewpoint 255, which reuses 0's stamp, equals 0
    together = visibility_gain(opacity, weights, viewpoints, 16, RANGE_CELLS, "threshold", 0.8)
    picked = [0, 1, 254, 255, 256, 299]
    alone = [
        visibility_gain(opacity, weights, viewpoints[i : i + 1], 16, RANGE_CELLS, "threshold", 0.8)
        for i in picked
    ]
    np.testing.assert_array_equal(together[picked], np.concatenate(alone))
    np.testing.assert_array_equal(together[:150], together[150:])
    assert together[255] == together[0] > 0


def test_the_256th_viewpoint_does_not_inherit_the_first_ones_cells() -> None:
    """Viewpoint 255 reuses viewpoint 0's stamp value: the stamp must have been cleared."""
    opacity = np.zeros((20, 40), dtype=np.float32)
    opacity[:, 20] = 1.0  # a wall between the two sides
    weights = np.ones(opacity.shape, dtype=np.float32)
    viewpoints = np.array([[10, 5]] + [[10, 30]] * 254 + [[10, 5], [10, 30]])
    gains = visibility_gain(opacity, weights, viewpoints, 32, 50, "threshold", 0.8)
    assert gains[255] == gains[0] > 0
    assert np.all(gains[1:255] == gains[256])


def test_accumulate_stops_in_a_haze_that_threshold_sees_through() -> None:
    opacity = np.zeros((21, 41), dtype=np.float32)
    opacity[:, 6:30] = 0.3  # a band of haze east of the viewpoint
    east = {rule: visible_mask(opacity, (10, 5), 1, 100, rule, 0.8) for rule in STOP_RULES}
    # accumulate: 0.3 + 0.3 + 0.3 >= 0.8 at the third haze cell, which is still visible
    np.testing.assert_array_equal(np.flatnonzero(east["accumulate"][10]), [5, 6, 7, 8])
    assert east["accumulate"].sum() == 4
    # threshold: no cell reaches 0.8, the ray walks to the map border
    np.testing.assert_array_equal(np.flatnonzero(east["threshold"][10]), np.arange(5, 41))


def test_reaching_epsilon_exactly_stops_the_ray() -> None:
    opacity = np.zeros((5, 20), dtype=np.float32)
    opacity[:, 8:] = 0.25
    opacity[:, 15] = 1.0
    accumulate = visible_mask(opacity, (2, 5), 1, 100, "accumulate", 0.5)  # 0.25 + 0.25
    np.testing.assert_array_equal(np.flatnonzero(accumulate[2]), [5, 6, 7, 8, 9])
    threshold = visible_mask(opacity, (2, 5), 1, 100, "threshold", 1.0)
    np.testing.assert_array_equal(np.flatnonzero(threshold[2]), np.arange(5, 16))


def test_threshold_on_a_binary_map_sees_the_wall_it_stops_on() -> None:
    opacity = np.zeros((21, 41), dtype=np.float32)
    opacity[:, 12] = 1.0
    mask = visible_mask(opacity, (10, 5), 4, 100, "threshold", 0.5)
    np.testing.assert_array_equal(np.flatnonzero(mask[10]), np.arange(0, 13))  # west + east
    assert not mask[:, 13:].any()


def test_an_open_map_is_seen_within_range_only() -> None:
    opacity = np.zeros((61, 61), dtype=np.float32)
    mask = visible_mask(opacity, (30, 30), 250, 20, "threshold", 0.8)
    rows, cols = np.nonzero(mask)
    assert np.hypot(rows + 0.5 - 30.5, cols + 0.5 - 30.5).max() <= 20 + np.sqrt(0.5) + 1e-9
    assert mask[30, 10] and mask[30, 50] and not mask[30, 9] and not mask[30, 51]


def test_bad_inputs_are_rejected() -> None:
    opacity = np.zeros((20, 20), dtype=np.float32)
    weights = np.ones((20, 20), dtype=np.float32)
    vp = np.array([[3, 3]])
    with pytest.raises(ValueError, match="stop_rule"):
        visibility_gain(opacity, weights, vp, 8, 10, "sum", 0.8)
    with pytest.raises(ValueError, match="epsilon"):
        visibility_gain(opacity, weights, vp, 8, 10, "threshold", 0.0)
    with pytest.raises(ValueError, match="n_rays"):
        visibility_gain(opacity, weights, vp, 0, 10, "threshold", 0.8)
    with pytest.raises(ValueError, match="outside"):
        visibility_gain(opacity, weights, np.array([[3, 3], [20, 0]]), 8, 10, "threshold", 0.8)
    with pytest.raises(ValueError, match="viewpoints"):
        visibility_gain(opacity, weights, np.array([[3.0, 3.0]]), 8, 10, "threshold", 0.8)
    with pytest.raises(ValueError, match="shape"):
        visibility_gain(opacity, weights[:, :5], vp, 8, 10, "threshold", 0.8)
    with pytest.raises(ValueError, match="outside"):
        visible_mask(opacity, (-1, 3), 8, 10, "accumulate", 0.8)
