"""services.planner: pieces that need no process, and a planner refusing a world whose
sensor or motion differ from its own (its whole runs are tested in test_up.py)."""

from __future__ import annotations

import pytest
from service_processes import ServiceProcesses

from mapex.config import WorldConfig
from services.config import ServicesConfig
from services.keys import alive_world_key
from services.planner import prediction_size_warning

RUN_DEADLINE_S = 120.0  # imports (torch) of a cold interpreter on a shared 2-core machine
RUN = "mismatch_test"


def test_maps_too_large_to_predict_in_time_are_flagged_with_the_limit():
    services = ServicesConfig(predict_max_cells=1000, predict_timeout_s=10.0)
    assert prediction_size_warning((25, 40), services) is None  # exactly at the limit
    warning = prediction_size_warning((30, 40), services)
    assert warning is not None and "\n" not in warning
    assert "1,200 cells, above the 1,000" in warning and "within 10 s" in warning
    assert "marked degraded from the start" in warning


def test_the_default_limit_leaves_every_world_the_size_limit_allows_unflagged():
    side = int(WorldConfig().max_cells ** 0.5)
    assert prediction_size_warning((side, side), ServicesConfig()) is None


@pytest.fixture(scope="module")
def world_process(hub, tmp_path_factory):
    """A world of the default settings serving RUN on the hub."""
    processes = ServiceProcesses(hub[1], tmp_path_factory.mktemp("logs"))
    try:
        processes.spawn("world", "services.world", "--run", RUN, "--world", "generated:0")

        def alive() -> bool:
            return bool(list(hub[0].liveliness().get(alive_world_key(RUN), timeout=1.0)))

        processes.wait_until_announced("world", alive, RUN_DEADLINE_S)
        yield processes
    finally:
        processes.kill_all()


@pytest.mark.parametrize(
    "settings, named",
    [
        (["sensor.n_rays=1000"], ["n_rays 2500 (here 1000)"]),
        (
            ["motion.cells_per_step=2", "sensor.range_cells=100", "services.step_retries=5"],
            ["range_cells 200 (here 100)", "cells_per_step 3 (here 2)"],
        ),
    ],
    ids=["sensor", "sensor-and-motion"],
)
def test_a_planner_with_other_settings_than_its_world_refuses_to_start(
    world_process, tmp_path, settings, named
):
    out = tmp_path / "runs" / "r0"
    name = f"planner-{len(settings)}"
    sets = [flag for item in settings for flag in ("--set", item)]
    process = world_process.spawn(
        name, "services.planner", "--run", RUN, "--method", "nearest", "--steps", "5",
        "--no-progress", "--out", str(out), *sets,
    )  # fmt: skip
    assert process.wait(RUN_DEADLINE_S) == 1, world_process.log_of(name)
    log = world_process.log_of(name)
    errors = [line for line in log.splitlines() if " ERROR " in line]
    assert len(errors) == 1 and "Traceback" not in log, log
    (error,) = errors
    assert f"the world of run {RUN} simulates " in error
    assert all(each in error for each in named), error
    assert "start the planner with the world's --set" in error
    assert not out.exists() and list(out.parent.iterdir()) == []  # nothing written
    assert world_process.processes["world"].poll() is None  # the world serves on
    (said,) = [line for line in log.splitlines() if " INFO settings: " in line]
    assert all(f" {item}" in said for item in ["steps=5", *settings]), said  # as it ran
