"""services.planner pieces that need no process (its runs are tested in test_up.py)."""

from __future__ import annotations

from services.config import ServicesConfig
from services.planner import prediction_size_warning


def test_maps_too_large_to_predict_in_time_are_flagged_with_the_limit():
    services = ServicesConfig(predict_max_cells=1000, predict_timeout_s=10.0)
    assert prediction_size_warning((25, 40), services) is None  # exactly at the limit
    warning = prediction_size_warning((30, 40), services)
    assert warning is not None and "\n" not in warning
    assert "1,200 cells, above the 1,000" in warning and "within 10 s" in warning
    assert "marked degraded from the start" in warning


def test_the_default_limit_leaves_every_world_the_size_limit_allows_unflagged():
    from mapex.config import WorldConfig

    side = int(WorldConfig().max_cells ** 0.5)
    assert prediction_size_warning((side, side), ServicesConfig()) is None
