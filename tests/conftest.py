"""Shared fixtures (the development KTH maps beside the checkout, skipped when absent; a
loopback Zenoh hub) and the `slow` marker: every test of tests/services and tests/deploy
starts real processes, so all of them are slow; `pytest -m "not slow"` is the fast loop."""

from __future__ import annotations

from pathlib import Path

import pytest

KTH_DEV_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kth_dev"


PROCESS_TEST_DIRS = ("services", "deploy")  # test folders whose tests start real processes


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark every test of the process-test folders `slow`."""
    tests_dir = Path(__file__).resolve().parent
    for item in items:
        parts = Path(item.fspath).resolve().relative_to(tests_dir).parts
        if parts[0] in PROCESS_TEST_DIRS:
            item.add_marker(pytest.mark.slow)


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
