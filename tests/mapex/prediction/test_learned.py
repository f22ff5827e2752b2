"""The learned ensemble as a predictor: weights on disk, copy-through, determinism."""

import numpy as np
import pytest
import torch
from tiny_training import SMALL

from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.prediction import make_predictor
from mapex.prediction.learned import LearnedEnsemble
from mapex.prediction.network import LamaGenerator
from mapex.prediction.weights import (
    MEMBER_NAMES,
    WEIGHTS_DIR,
    WeightsError,
    read_metadata,
    save_weights,
)


@pytest.fixture
def random_weights(tmp_path):
    for index, name in enumerate(MEMBER_NAMES):
        torch.manual_seed(index)
        save_weights(tmp_path / f"{name}.pt", LamaGenerator(SMALL), {"member": name})
    return tmp_path


def partly_observed(shape=(45, 61)):
    observed = np.full(shape, UNKNOWN, dtype=np.uint8)
    observed[5:30, 5:40] = FREE
    observed[5:30, 4] = OCCUPIED
    observed[4, 4:41] = OCCUPIED
    return observed


def test_known_cells_are_copied_through(random_weights):
    predictor = LearnedEnsemble(random_weights)
    observed = partly_observed()
    prediction = predictor.predict(observed)
    assert prediction.members.shape == (4, *observed.shape)
    known = observed != UNKNOWN
    for member in prediction.members:
        np.testing.assert_array_equal(member[known], observed[known] / 2.0)
    unknown = prediction.members[:, ~known]
    assert ((unknown >= 0) & (unknown <= 1)).all()
    assert prediction.variance[~known].max() > 0  # members differ


def test_region_and_member_selection(random_weights):
    predictor = LearnedEnsemble(random_weights)
    observed = partly_observed()
    whole = predictor.predict(observed)
    main = predictor.predict_main(observed)
    np.testing.assert_allclose(main, whole.main, atol=1e-6)
    part = predictor.predict(observed, region=(0, 35, 0, 50))
    assert (part.variance[35:, :] == 0).all() and (part.variance[:, 50:] == 0).all()


def test_prediction_is_deterministic(random_weights):
    predictor = LearnedEnsemble(random_weights)
    observed = partly_observed()
    np.testing.assert_array_equal(
        predictor.predict(observed).members, predictor.predict(observed).members
    )


def test_bfloat16_is_close_to_float32_deterministic_and_copies_known_cells(random_weights):
    observed = partly_observed()
    exact = LearnedEnsemble(random_weights).predict(observed).members
    mixed = LearnedEnsemble(random_weights, precision="bfloat16")
    fast = mixed.predict(observed).members
    assert fast.dtype == np.float32 and fast.shape == exact.shape
    known = observed != UNKNOWN
    np.testing.assert_array_equal(fast[:, known], exact[:, known])
    difference = np.abs(fast - exact)[:, ~known]
    assert 0 < difference.max() < 0.05  # another precision, not another network
    np.testing.assert_array_equal(fast, mixed.predict(observed).members)


def test_the_same_crop_asked_again_is_answered_from_the_recent_ones(random_weights):
    """G's metric prediction and a re-plan's on the same map, or a team's planners asking
    for one crop: one forward pass."""
    predictor = LearnedEnsemble(random_weights)
    observed = partly_observed()
    first = predictor.predict(observed).members
    again = predictor.predict(observed.copy(), members=(0,)).main
    assert predictor.recent.hits == 1
    np.testing.assert_array_equal(again, first[0])
    predictor.predict(partly_observed((40, 61)), members=(0,))
    assert predictor.recent.hits == 1
    uncached = LearnedEnsemble(random_weights, recent_answers=0)
    assert uncached.recent is None
    np.testing.assert_array_equal(uncached.predict(observed).members, first)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"inference": "onnx"}, "inference 'onnx'.*fused, plain"),
        ({"views": 3}, "views 3"),
    ],
)
def test_an_unknown_inference_setting_is_refused(random_weights, options, message):
    with pytest.raises(ValueError, match=message):
        LearnedEnsemble(random_weights, **options)


def test_the_plain_path_and_two_views_are_there_on_request(random_weights):
    observed = partly_observed()
    fused = LearnedEnsemble(random_weights).predict(observed).members
    plain = LearnedEnsemble(random_weights, inference="plain").predict(observed).members
    np.testing.assert_allclose(fused, plain, atol=1e-2)  # the wire's uint8 levels apart at most
    one = LearnedEnsemble(random_weights, views=1)
    assert not any(model.config.average_turned_view for model in one.models)
    assert all(m.config.average_turned_view for m in LearnedEnsemble(random_weights).models)


def test_an_unknown_precision_is_refused(random_weights):
    with pytest.raises(ValueError, match="float16.*float32, bfloat16"):
        LearnedEnsemble(random_weights, precision="float16")


def test_missing_or_broken_weights_are_one_line_errors(tmp_path):
    with pytest.raises(WeightsError, match="no weights file"):
        LearnedEnsemble(tmp_path)
    for name in MEMBER_NAMES:
        (tmp_path / f"{name}.pt").write_bytes(b"garbage")
    with pytest.raises(WeightsError, match="not a weights file") as info:
        LearnedEnsemble(tmp_path)
    assert "\n" not in str(info.value)


def test_shipped_weights_load_on_cpu_and_say_how_they_were_trained():
    predictor = make_predictor("lama")
    assert predictor.n_members == 4
    assert all(next(m.parameters()).device.type == "cpu" for m in predictor.models)
    metadata = read_metadata(WEIGHTS_DIR / "g.pt")
    assert metadata["steps"] > 0 and metadata["training_wall_time_s"] > 0
    assert not {"50037764_PLAN1", "50052748"} & set(metadata["worlds"])  # never trained on


def test_lama_v2_reads_the_v2_folder_whatever_the_default_folder_holds(monkeypatch, tmp_path):
    """`lama` means the default folder (new weights land there); `lama-v2` keeps its own."""
    read = []
    monkeypatch.setattr(
        "mapex.prediction.learned.load_member_with_bias",
        lambda path, device: read.append(path) or (LamaGenerator(SMALL).eval(), 0.0),
    )
    assert make_predictor("lama-v2", members=("g", "g2")).name == "lama-v2"
    assert make_predictor("lama", members=("g",)).name == "lama"
    make_predictor("lama-v2", weights_dir=tmp_path, members=("g1",))
    assert read == [
        WEIGHTS_DIR / "v2" / "g.pt",
        WEIGHTS_DIR / "v2" / "g2.pt",
        WEIGHTS_DIR / "g.pt",
        tmp_path / "g1.pt",
    ]
    assert all((WEIGHTS_DIR / "v2" / f"{name}.pt").is_file() for name in MEMBER_NAMES)
