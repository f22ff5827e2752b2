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


@pytest.fixture(scope="module")
def hub():
    """A Zenoh session listening on a free loopback port: (session, endpoint) for services."""
    from service_processes import free_loopback_port

    from services.zenoh_config import open_session, zenoh_config

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    session = open_session(zenoh_config(listen=[endpoint], connect=[]))
    yield session, endpoint
    session.close()
