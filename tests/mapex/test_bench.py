"""The benchmark's arithmetic: the network's operation count and the core's peak."""

import numpy as np

from mapex.bench import core_peak_gflops, network_flops
from mapex.grid import UNKNOWN


def test_the_networks_flops_grow_with_the_map_area():
    small = network_flops(np.full((64, 64), UNKNOWN, dtype=np.uint8))
    large = network_flops(np.full((128, 128), UNKNOWN, dtype=np.uint8))
    assert small > 0
    assert 3.5 < large / small < 4.5  # convolutions everywhere: four times the cells


def test_the_core_peak_is_a_positive_rate():
    assert core_peak_gflops(size=256, repeats=1) > 0
