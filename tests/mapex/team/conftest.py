"""The team tests' shared world (generated floor plan 5) and classical ensemble."""

import pytest

from mapex.prediction import make_predictor
from mapex.worlds import generate_floor_plan


@pytest.fixture(scope="module")
def world():
    return generate_floor_plan(5)


@pytest.fixture(scope="module")
def predictor():
    return make_predictor("classical")
