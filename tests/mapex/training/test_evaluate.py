"""The predictor evaluation: AUROC, near/far split, per-cell scores, tables, CLI errors."""

import numpy as np
import pytest

from mapex.grid import FREE, UNKNOWN
from mapex.prediction.base import EnsemblePrediction
from mapex.prediction.config import PredictorEvaluationConfig
from mapex.training.evaluate import (
    CellScores,
    SnapshotScore,
    auroc,
    far_variance_share,
    format_ceiling_table,
    format_map_table,
    format_split_table,
    format_table,
    local_ceiling_iou,
    main,
    near_known,
    outside_building,
    score_cells,
)
from mapex.worlds.base import World


@pytest.mark.parametrize(
    ("scores", "labels", "expected"),
    [
        ([0.1, 0.2, 0.8, 0.9], [False, False, True, True], 1.0),
        ([0.9, 0.8, 0.2, 0.1], [False, False, True, True], 0.0),
        ([0.5, 0.5, 0.5, 0.5], [False, True, False, True], 0.5),
        ([0.1, 0.4, 0.35, 0.8], [False, False, True, True], 0.75),
    ],
)
def test_auroc_counts_correctly_ordered_pairs(scores, labels, expected):
    assert auroc(np.array(scores), np.array(labels)) == pytest.approx(expected)


def test_auroc_without_both_classes_is_nan():
    assert np.isnan(auroc(np.array([0.1, 0.2]), np.array([True, True])))


def test_near_known_is_a_distance_band_around_known_cells():
    observed = np.full((1, 20), UNKNOWN, dtype=np.uint8)
    observed[0, 0] = FREE
    near = near_known(observed, 3)
    np.testing.assert_array_equal(np.flatnonzero(near[0]), [0, 1, 2, 3])
    assert not near_known(np.full((4, 4), UNKNOWN, dtype=np.uint8), 3).any()


def test_score_cells_judges_g_classical_and_unknown_free_on_the_same_cells():
    truth = np.array([[True, True, False, False]])
    cells = np.array([[True, True, True, False]])
    g = np.array([[0.9, 0.1, 0.1, 0.9]], dtype=np.float32)  # right, wrong, right, outside
    g1 = np.array([[0.9, 0.7, 0.1, 0.9]], dtype=np.float32)
    g2 = np.array([[0.9, 0.1, 0.1, 0.9]], dtype=np.float32)
    members = np.stack([g, g1, g2])
    classical = np.array([[0.9, 0.9, 0.9, 0.0]], dtype=np.float32)
    scores = score_cells(truth, cells, EnsemblePrediction(members), classical, 0.5)
    assert scores.iou_g == pytest.approx(1 / 2)
    assert scores.iou_classical == pytest.approx(2 / 3)
    assert scores.iou_unknown_free == 0.0
    assert scores.auroc == 1.0  # G_1 and G_2 disagree exactly where G is wrong


def test_score_cells_scores_the_reference_g_on_the_same_cells():
    truth = np.array([[True, True, False, False]])
    cells = np.array([[True, True, True, False]])
    members = np.stack([np.array([[0.9, 0.1, 0.1, 0.9]], dtype=np.float32)] * 3)
    reference = np.array([[0.9, 0.9, 0.9, 0.0]], dtype=np.float32)
    scores = score_cells(truth, cells, EnsemblePrediction(members), reference, 0.5, reference)
    assert scores.iou_reference == pytest.approx(2 / 3)
    assert np.isnan(
        score_cells(truth, cells, EnsemblePrediction(members), reference, 0.5).iou_reference
    )


def test_far_variance_share_counts_only_unknown_cells_beyond_the_distance():
    observed = np.full((1, 30), UNKNOWN, dtype=np.uint8)
    observed[0, 0] = FREE
    variance = np.zeros((1, 30), dtype=np.float32)
    variance[0, 5] = 3.0  # 5 cells from the known cell: near
    variance[0, 25] = 1.0  # 25 cells away: far
    assert far_variance_share(variance, observed, 20) == pytest.approx(0.25)
    assert np.isnan(far_variance_share(np.zeros_like(variance), observed, 20))


def _score(world: str, t: int, g: float, classical: float) -> SnapshotScore:
    cells = CellScores(g, classical, 0.0, 0.6, g - 0.1)
    return SnapshotScore(
        world, 0, t, cells, cells, CellScores(g / 2, 0.0, 0.0, 0.5), 2 * g, g + 0.1, 0.25
    )


def test_the_map_table_has_a_row_per_map_and_an_overall_mean():
    scores = [_score("a", 100, 0.4, 0.2), _score("a", 300, 0.2, 0.2), _score("b", 300, 0.6, 0.3)]
    table = format_map_table(scores, PredictorEvaluationConfig()).splitlines()
    assert "variance > 2 m from known" in table[0]
    assert table[2] == "| a | 0.300 | 0.200 | 0.200 | 0.000 | +0.100 | 0.600 | 0.250 |"
    assert table[-1].startswith("| all | 0.400 | 0.300 | 0.233 |")


def test_tables_have_a_row_per_map_and_time_and_an_overall_mean():
    scores = [_score("a", 100, 0.4, 0.2), _score("a", 100, 0.2, 0.2), _score("b", 300, 0.6, 0.3)]
    table = format_table(scores).splitlines()
    assert table[2] == "| a | 100 | 0.300 | 0.200 | 0.000 | +0.100 | 0.600 |"
    assert table[-1].startswith("| all | - | 0.400 | 0.233 |")
    split = format_split_table(scores, 10).splitlines()
    assert "within 1 m" in split[0]
    assert split[5] == "| b | 300 | 0.600 / 0.300 | 0.300 / 0.000 | 0.600 / 0.500 |"
    ceiling = format_ceiling_table(scores, PredictorEvaluationConfig()).splitlines()
    assert "classical + 0.10" in ceiling[2]
    assert ceiling[4] == "| a | 100 | 0.200 | 0.300 | 0.600 | 0.300 | 0.400 |"


def test_outside_building_is_the_free_space_beyond_the_valid_space():
    occupancy = np.array([[False, True, False, False, True, False]])
    valid = np.array([[False, False, True, True, False, False]])
    world = World("strip", occupancy, valid)
    np.testing.assert_array_equal(outside_building(world)[0], [1, 0, 0, 0, 0, 1])


def test_local_ceiling_is_perfect_near_the_known_map_and_free_beyond():
    truth = np.array([[True, False, True, True, False, True]])
    cells = np.array([[True, True, True, True, True, False]])
    near = np.array([[True, True, True, False, False, False]])
    # found: the near wall at 0 and 2; missed: the far wall at 3; cell 5 is not scored
    assert local_ceiling_iou(truth, cells, near) == pytest.approx(2 / 3)
    assert local_ceiling_iou(truth, cells, np.ones_like(near)) == 1.0


def test_a_missing_map_is_a_one_line_error(tmp_path, capsys):
    assert main(["--maps", str(tmp_path / "nowhere")]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("mapex.training.evaluate: error:") and "\n" not in error


def test_a_weights_folder_without_weights_is_a_one_line_error(tmp_path, capsys):
    assert main(["--weights", str(tmp_path)]) == 2
    error = capsys.readouterr().err.strip()
    assert error == (
        f"mapex.training.evaluate: error: no weights file {tmp_path / 'g.pt'} "
        "(train with python -m mapex.prediction.train)"
    )


def test_the_map_table_shows_a_dash_without_a_reference():
    score = _score("a", 100, 0.4, 0.2)
    score.all.iou_reference = float("nan")
    row = format_map_table([score], PredictorEvaluationConfig()).splitlines()[2]
    assert row == "| a | 0.400 | - | 0.200 | 0.000 | - | 0.600 | 0.250 |"
