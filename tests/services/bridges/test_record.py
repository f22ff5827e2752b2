"""The MCAP recorder process (services.record) and the live Foxglove server: flags and
start-up; whole recordings are checked in tests/services/test_ros2.py (services.up
--record) and tests/mapex/interop/test_mcap_file.py (in-process)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")

import time  # noqa: E402

import zenoh  # noqa: E402
from mcap_files import mcap_counts, ros_messages_in  # noqa: E402
from service_processes import ServiceProcesses, free_loopback_port  # noqa: E402

from mapex.interop.ros_messages import MapFrame, grid_values_in_map_order  # noqa: E402
from mapex.interop.topics import RunTopics  # noqa: E402
from services.bridges import record  # noqa: E402
from services.messages import MapMessage, PoseMessage, StatusMessage  # noqa: E402

RECORDER_DEADLINE_S = 60.0  # a cold interpreter on a shared 2-core machine


@pytest.mark.parametrize(
    ("argv", "text"),
    [
        (["--out", "{tmp}/old.mcap"], "exists"),
        (["--out", "{tmp}/nowhere/new.mcap"], "does not exist"),
        (["--out", "{tmp}/new.mcap", "--run", "Bad Run"], "--run"),
        (["--out", "{tmp}/new.mcap", "--timeout-s", "0"], "--timeout-s"),
    ],
)
def test_bad_flags_are_one_line_and_exit_2(tmp_path, capsys, argv, text):
    (tmp_path / "old.mcap").write_bytes(b"keep me")
    with pytest.raises(SystemExit) as stopped:
        record.run_cli([arg.format(tmp=tmp_path) for arg in argv])
    assert stopped.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert text in error and error.startswith("usage:") is False
    assert (tmp_path / "old.mcap").read_bytes() == b"keep me"  # nothing lost


def test_the_foxglove_server_serves_the_ros_and_foxglove_channels():
    pytest.importorskip("foxglove", reason="the foxglove extra is not installed")
    from services.bridges.foxglove_live import FoxgloveServer

    server = FoxgloveServer(port=0)
    try:
        assert server.port > 0
        topics = RunTopics("demo", MapFrame(4, 5))
        for outgoing in topics.observed("r0", np.ones((4, 5), np.uint8), 1) + topics.pose(
            "r0", (1, 1), 2
        ):
            server.write(outgoing)
        assert server.topics() == [
            "/foxglove/mapex/demo/r0/map", "/foxglove/mapex/demo/r0/pose",
            "/foxglove/mapex/demo/r0/trajectory", "/mapex/demo/r0/map", "/mapex/demo/r0/pose",
            "/mapex/demo/r0/trajectory",
        ]  # fmt: skip
    finally:
        server.close()


@pytest.mark.slow  # a process of its own
def test_the_recorder_process_records_a_run_until_it_finishes(tmp_path):
    """services.record --until-finished on a hub where a run is published by hand: it exits
    0 once the run's robot says finished, and the file holds its map and pose."""
    hub = f"tcp/127.0.0.1:{free_loopback_port()}"
    config = zenoh.Config.from_json5(
        f'{{mode: "router", listen: {{endpoints: ["{hub}"]}}, '
        "scouting: {multicast: {enabled: false}}}"
    )
    session = zenoh.open(config)
    processes = ServiceProcesses(hub, tmp_path)
    out = tmp_path / "run.mcap"
    try:
        recorder = processes.spawn(
            "record", "services.record", "--out", str(out), "--until-finished",
            "--timeout-s", str(RECORDER_DEADLINE_S),
        )  # fmt: skip
        codes = np.ones((6, 8), np.uint8)
        codes[2:4, 2:6] = 0
        deadline = time.monotonic() + RECORDER_DEADLINE_S
        while recorder.poll() is None and time.monotonic() < deadline:
            session.put("mapex/@v1/demo/r0/observed_map", MapMessage(7, "observed", codes).encode())
            session.put("mapex/@v1/demo/r0/pose", PoseMessage(7, (2, 3)).encode())
            session.put("mapex/@v1/demo/r0/status", StatusMessage(7, "finished").encode())
            time.sleep(0.5)
        assert recorder.wait(RECORDER_DEADLINE_S) == 0, processes.log_of("record")
    finally:
        processes.kill_all()
        session.close()
    counts = mcap_counts(out)
    assert counts["/mapex/demo/r0/map"] >= 1 and counts["/mapex/demo/r0/pose"] >= 1
    grid = ros_messages_in(out, "/mapex/demo/r0/map")[-1]
    assert np.array_equal(grid_values_in_map_order(grid) == 0, codes == 0)
