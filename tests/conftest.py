"""Shared fixtures: the development KTH maps beside the checkout (skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

KTH_DEV_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kth_dev"


@pytest.fixture
def kth_dev_dir() -> Path:
    """../shared/data/kth_dev, or skip the test when the development data is not there."""
    if not KTH_DEV_DIR.is_dir():
        pytest.skip("development maps ../shared/data/kth_dev are not present")
    return KTH_DEV_DIR
