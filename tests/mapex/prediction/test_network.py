"""The LaMa-style generator: any map size, known cells copied through, determinism."""

import dataclasses

import numpy as np
import pytest
import torch
from tiny_training import SMALL

from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.prediction.config import NetworkConfig
from mapex.prediction.network import (
    OUTSIDE_MAP,
    LamaGenerator,
    emulated_bfloat16,
    encode_observed,
)


def random_observed(shape, seed=0):
    rng = np.random.default_rng(seed)
    return rng.choice(np.array([FREE, UNKNOWN, OCCUPIED], dtype=np.uint8), size=shape)


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (7, 2), (33, 65), (64, 64), (101, 37)])
def test_output_has_the_input_size(shape):
    torch.manual_seed(0)
    net = LamaGenerator(SMALL).eval()
    inputs = torch.from_numpy(encode_observed(random_observed(shape)))[None]
    with torch.inference_mode():
        assert net(inputs).shape == (1, 1, *shape)


def test_default_network_on_a_large_map():
    net = LamaGenerator(NetworkConfig()).eval()
    inputs = torch.from_numpy(encode_observed(random_observed((442, 1327))))[None]
    with torch.inference_mode():
        logits = net(inputs)
    assert logits.shape == (1, 1, 442, 1327) and torch.isfinite(logits).all()


def test_padding_is_treated_as_beyond_the_map_border():
    torch.manual_seed(0)
    net = LamaGenerator(SMALL).eval()
    observed = random_observed((10, 10))
    padded = np.full((12, 12), OUTSIDE_MAP, dtype=np.uint8)
    padded[:10, :10] = observed
    with torch.inference_mode():
        small = net(torch.from_numpy(encode_observed(observed))[None])
        large = net(torch.from_numpy(encode_observed(padded))[None])
    torch.testing.assert_close(small, large[..., :10, :10])


def test_encoding_is_one_hot_inside_the_map_and_zero_beyond_it():
    observed = random_observed((9, 11))
    observed[:, -2:] = OUTSIDE_MAP
    encoded = encode_observed(observed)
    assert encoded.shape == (3, 9, 11)
    np.testing.assert_array_equal(encoded[:, :, :-2].sum(axis=0), 1.0)
    np.testing.assert_array_equal(encoded[:, :, -2:], 0.0)


def test_inference_is_deterministic():
    torch.manual_seed(0)
    net = LamaGenerator(SMALL).eval()
    inputs = torch.from_numpy(encode_observed(random_observed((40, 52), seed=3)))[None]
    with torch.inference_mode():
        torch.testing.assert_close(net(inputs), net(inputs), rtol=0, atol=0)


def _half_turn(tensor: torch.Tensor) -> torch.Tensor:
    return torch.rot90(tensor, 2, (2, 3))


@pytest.mark.parametrize("shape", [(1, 1), (7, 2), (33, 65)])
def test_predict_logits_averages_the_map_and_the_map_turned_by_180_degrees(shape):
    torch.manual_seed(0)
    net = LamaGenerator(SMALL).eval()
    inputs = torch.from_numpy(encode_observed(random_observed(shape, seed=4)))[None]
    with torch.inference_mode():
        expected = (net(inputs) + _half_turn(net(_half_turn(inputs)))) / 2
        torch.testing.assert_close(net.predict_logits(inputs), expected)


def test_predict_logits_turn_with_the_map_unlike_one_pass():
    torch.manual_seed(0)
    net = LamaGenerator(SMALL).eval()
    inputs = torch.from_numpy(encode_observed(random_observed((30, 41), seed=5)))[None]
    with torch.inference_mode():
        averaged = net.predict_logits(inputs), net.predict_logits(_half_turn(inputs))
        one_pass = net(inputs), net(_half_turn(inputs))
    torch.testing.assert_close(_half_turn(averaged[0]), averaged[1])
    assert not torch.allclose(_half_turn(one_pass[0]), one_pass[1])


def test_without_the_turned_view_predict_logits_is_one_forward_pass():
    torch.manual_seed(0)
    net = LamaGenerator(dataclasses.replace(SMALL, average_turned_view=False)).eval()
    inputs = torch.from_numpy(encode_observed(random_observed((20, 24), seed=6)))[None]
    with torch.inference_mode():
        torch.testing.assert_close(net.predict_logits(inputs), net(inputs), rtol=0, atol=0)


def test_convolutions_are_channels_last_also_after_loading_weights():
    """The CPU speed of the full-resolution convolutions depends on it (docs/prediction.md)."""
    source = LamaGenerator(SMALL)
    net = LamaGenerator(SMALL)
    net.load_state_dict({k: v.clone().contiguous() for k, v in source.state_dict().items()})
    convolutions = [m.weight for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert convolutions
    assert all(w.is_contiguous(memory_format=torch.channels_last) for w in convolutions)


def test_the_input_memory_layout_does_not_change_the_output():
    torch.manual_seed(0)
    net = LamaGenerator(SMALL).eval()
    inputs = torch.from_numpy(encode_observed(random_observed((37, 45), seed=7)))[None]
    with torch.inference_mode():
        plain = net(inputs)
        nhwc = net(inputs.contiguous(memory_format=torch.channels_last))
    torch.testing.assert_close(plain, nhwc)


@pytest.mark.parametrize("native", [True, False])
def test_bfloat16_counts_as_emulated_only_on_a_cpu_without_it(native, monkeypatch):
    monkeypatch.setattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda: native)
    cpu = torch.device("cpu")
    assert emulated_bfloat16(cpu, "bfloat16") is not native
    assert not emulated_bfloat16(cpu, "float32")
    assert not emulated_bfloat16(torch.device("cuda"), "bfloat16")
