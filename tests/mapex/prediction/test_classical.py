"""The classical inpainting ensemble and the predictor registry."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import ndimage

from mapex.grid import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    dequantise_probability,
    observed_to_probability,
    quantise_probability,
)
from mapex.prediction import PREDICTORS, make_predictor
from mapex.prediction.classical import ClassicalInpaintingEnsemble, inpaint_member
from mapex.prediction.config import ClassicalPredictorConfig, InpaintMemberConfig


@pytest.fixture(scope="module")
def predictor() -> ClassicalInpaintingEnsemble:
    return ClassicalInpaintingEnsemble()


def _random_observed(shape: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    codes = np.array([FREE, UNKNOWN, OCCUPIED], dtype=np.uint8)
    return rng.choice(codes, size=shape, p=[0.45, 0.45, 0.1])


def _floor_plan(shape: tuple[int, int] = (120, 200), room_cells: int = 30) -> np.ndarray:
    """Ground-truth walls (bool): a grid of square rooms, a 6-cell door in every inner wall."""
    walls = np.zeros(shape, dtype=bool)
    walls[::room_cells] = True
    walls[:, ::room_cells] = True
    walls[-1] = walls[:, -1] = True
    door = np.arange(room_cells // 2 - 3, room_cells // 2 + 3)
    inner = [np.arange(room_cells, size - 1, room_cells) for size in shape]
    doors = [(np.arange(0, size, room_cells)[:, None] + door).ravel() for size in shape]
    doors = [cells[cells < size - 1] for cells, size in zip(doors, shape, strict=True)]
    walls[np.ix_(inner[0], doors[1])] = False
    walls[np.ix_(doors[0], inner[1])] = False
    return walls


def _reveal_disc(walls: np.ndarray, centre: tuple[int, int], radius_cells: int) -> np.ndarray:
    """Observed map knowing the ground truth inside a disc, unknown elsewhere."""
    rows, cols = np.indices(walls.shape)
    inside = (rows - centre[0]) ** 2 + (cols - centre[1]) ** 2 <= radius_cells**2
    observed = np.full(walls.shape, UNKNOWN, dtype=np.uint8)
    observed[inside] = np.where(walls[inside], OCCUPIED, FREE)
    return observed


def test_is_a_four_member_ensemble_named_classical(predictor: ClassicalInpaintingEnsemble) -> None:
    assert predictor.name == "classical"
    assert predictor.n_members == 4 == len(ClassicalPredictorConfig().members)


@pytest.mark.parametrize(
    "shape", [(1, 1), (3, 5), (7, 2), (2, 7), (5, 1), (33, 17), (61, 129), (301, 757)]
)
def test_members_have_the_map_shape_and_stay_in_unit_range(
    predictor: ClassicalInpaintingEnsemble, shape: tuple[int, int]
) -> None:
    observed = _random_observed(shape, seed=sum(shape))
    members = predictor.predict_members(observed, range(4))
    assert members.shape == (4, *shape) and members.dtype == np.float32
    assert np.isfinite(members).all()
    assert members.min() >= 0.0 and members.max() <= 1.0


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (7, 2), (64, 96)])
def test_predict_copies_known_cells_exactly(
    predictor: ClassicalInpaintingEnsemble, shape: tuple[int, int]
) -> None:
    observed = _random_observed(shape, seed=11)
    observed.flat[0] = FREE
    prediction = predictor.predict(observed)
    known = observed != UNKNOWN
    expected = observed_to_probability(observed)[known]
    for member in prediction.members:
        np.testing.assert_array_equal(member[known], expected)
    assert prediction.members.min() >= 0.0 and prediction.members.max() <= 1.0


def test_predict_is_deterministic(predictor: ClassicalInpaintingEnsemble) -> None:
    observed = _reveal_disc(_floor_plan(), (60, 100), 40)
    first = predictor.predict(observed).members
    second = ClassicalInpaintingEnsemble().predict(observed.copy()).members
    np.testing.assert_array_equal(first, second)


def test_region_prediction_leaves_the_outside_at_the_observed_map(
    predictor: ClassicalInpaintingEnsemble,
) -> None:
    observed = _reveal_disc(_floor_plan(), (60, 100), 35)
    region = (20, 100, 50, 150)
    prediction = predictor.predict(observed, region)
    outside = np.ones(observed.shape, dtype=bool)
    outside[20:100, 50:150] = False
    assert (observed[outside] == UNKNOWN).any()
    for member in prediction.members:
        np.testing.assert_array_equal(member[outside], observed_to_probability(observed)[outside])
    np.testing.assert_array_equal(prediction.variance[outside], 0.0)
    crop_members = predictor.predict_members(observed[20:100, 50:150], range(4))
    unknown_crop = observed[20:100, 50:150] == UNKNOWN
    np.testing.assert_array_equal(  # the raw outputs at the wire's uint8 precision
        prediction.members[:, 20:100, 50:150][:, unknown_crop],
        dequantise_probability(quantise_probability(crop_members[:, unknown_crop])),
    )


def test_variance_is_informative_on_a_partly_observed_floor_plan(
    predictor: ClassicalInpaintingEnsemble,
) -> None:
    observed = _reveal_disc(_floor_plan(), (45, 75), 40)
    variance = predictor.predict(observed).variance
    unknown = observed == UNKNOWN
    assert (variance[~unknown] == 0).all()
    assert variance[unknown].max() > 0.05  # members disagree about structure somewhere
    assert np.median(variance[unknown]) < variance[unknown].max() / 5  # ... but not everywhere


@pytest.mark.parametrize("gap_cells", [4, 10, 16])
def test_a_corridor_wall_cut_by_unknown_space_continues(
    predictor: ClassicalInpaintingEnsemble, gap_cells: int
) -> None:
    observed = np.full((21, 80), UNKNOWN, dtype=np.uint8)
    observed[5] = observed[15] = OCCUPIED
    observed[6:15] = FREE
    gap = slice(30, 30 + gap_cells)
    observed[:, gap] = UNKNOWN
    main = predictor.predict(observed).main
    assert (main[5, gap] >= 0.5).all() and (main[15, gap] >= 0.5).all()
    assert (main[7:14, gap] < 0.5).all()  # the corridor between the walls stays free


def test_an_all_unknown_crop_gets_each_members_prior(
    predictor: ClassicalInpaintingEnsemble,
) -> None:
    members = predictor.predict_members(np.full((9, 14), UNKNOWN, dtype=np.uint8), range(4))
    for member, config in zip(members, predictor.config.members, strict=True):
        np.testing.assert_allclose(member, config.prior, atol=1e-6)


def test_each_member_is_the_configured_inpainting(predictor: ClassicalInpaintingEnsemble) -> None:
    observed = _reveal_disc(_floor_plan(), (60, 100), 30)
    members = predictor.predict_members(observed, range(4))
    for member, config in zip(members, predictor.config.members, strict=True):
        np.testing.assert_array_equal(member, inpaint_member(observed, config))
    assert not np.array_equal(members[0], members[1])


def _reveal_by_rays(walls: np.ndarray, pose: tuple[int, int], range_cells: int = 120) -> np.ndarray:
    """Observed map after one LiDAR-like scan from `pose`: free up to the first wall, seen."""
    angles = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    steps = np.arange(0.0, range_cells, 0.5)
    rows = np.rint(pose[0] + np.outer(np.sin(angles), steps)).astype(int)
    cols = np.rint(pose[1] + np.outer(np.cos(angles), steps)).astype(int)
    rows, cols = rows.clip(0, walls.shape[0] - 1), cols.clip(0, walls.shape[1] - 1)
    seen = np.cumsum(np.cumsum(walls[rows, cols], axis=1), axis=1) <= 1  # through the first wall
    observed = np.full(walls.shape, UNKNOWN, dtype=np.uint8)
    observed[rows[seen], cols[seen]] = np.where(walls[rows[seen], cols[seen]], OCCUPIED, FREE)
    return observed


@pytest.mark.parametrize("pose", [(174, 354), (129, 418)])
def test_main_member_predicts_walls_near_the_seen_part_of_a_kth_map(
    predictor: ClassicalInpaintingEnsemble, kth_dev_dir: Path, pose: tuple[int, int]
) -> None:
    occupancy = np.load(kth_dev_dir / "50052748" / "occ_map.npy") == 0
    rows, cols = (occupancy.shape[0] + 1) // 2 * 2, (occupancy.shape[1] + 1) // 2 * 2
    padded = np.ones((rows, cols), dtype=bool)
    padded[: occupancy.shape[0], : occupancy.shape[1]] = occupancy
    walls = padded.reshape(rows // 2, 2, cols // 2, 2).any(axis=(1, 3))  # 0.1 m, block-min
    observed = _reveal_by_rays(walls, pose)
    prediction = predictor.predict(observed)
    near = (observed == UNKNOWN) & (ndimage.distance_transform_edt(observed == UNKNOWN) <= 30)
    predicted, truth = prediction.main[near] >= 0.5, walls[near]
    iou = (predicted & truth).sum() / (predicted | truth).sum()
    assert iou > 2 * truth.mean()  # clearly better than calling every unknown cell a wall
    assert prediction.variance[near].max() > 0.05


def test_registry_makes_the_classical_predictor() -> None:
    assert "classical" in PREDICTORS
    made = make_predictor("classical")
    assert isinstance(made, ClassicalInpaintingEnsemble)
    config = ClassicalPredictorConfig(members=(InpaintMemberConfig(), InpaintMemberConfig()))
    assert make_predictor("classical", config=config).n_members == 2


def test_registry_rejects_unknown_names() -> None:
    choices = "classical, lama, lama-v2, oracle"
    with pytest.raises(ValueError, match=rf"unknown predictor 'magic' \(choose from: {choices}\)"):
        make_predictor("magic")


@pytest.mark.parametrize(
    "settings",
    [
        {"method": "fast"},
        {"scale": 0},
        {"radius_cells": 0},
        {"prior": 1.5},
        {"wall_level": 1.0},
    ],
)
def test_bad_member_settings_are_rejected(settings: dict) -> None:
    with pytest.raises(ValueError):  # the configuration itself refuses them (ConfigError)
        ClassicalInpaintingEnsemble(
            ClassicalPredictorConfig(members=(InpaintMemberConfig(**settings),))
        )


def test_no_members_and_bad_maps_are_rejected(predictor: ClassicalInpaintingEnsemble) -> None:
    with pytest.raises(ValueError, match="at least one member"):
        ClassicalInpaintingEnsemble(ClassicalPredictorConfig(members=()))
    with pytest.raises(ValueError, match="2-D uint8"):
        predictor.predict_members(np.zeros((4, 4), dtype=np.float64), range(4))


def test_a_non_finite_inpainting_falls_back_to_the_prior(monkeypatch: pytest.MonkeyPatch) -> None:
    """OpenCV's inpaint once returned NaN on a tiny map; such cells must take the prior."""
    member = ClassicalPredictorConfig().members[0]
    observed = _reveal_disc(_floor_plan((40, 40), room_cells=12), (20, 20), 8)
    monkeypatch.setattr(
        cv2, "inpaint", lambda image, *_: np.full_like(image, np.nan, dtype=np.float32)
    )
    probability = inpaint_member(observed, member)
    assert np.isfinite(probability).all()
    prior_in_band = np.interp(member.prior, (0.0, member.wall_level, 1.0), (0, 0.5, 1))
    unknown = probability[observed == UNKNOWN]
    assert np.isclose(unknown, member.prior).any()
    assert (np.isclose(unknown, member.prior) | np.isclose(unknown, prior_in_band)).all()
