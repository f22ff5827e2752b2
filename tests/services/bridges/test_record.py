"""The MCAP recorder (services.record: the bag with --out, the Foxglove file with
--foxglove-out), the recording flags of services.up / services.evaluate (--record,
--record-foxglove) and the live Foxglove server. The bag must meet rosbag2's conditions for
`ros2 bag play` (tests/helpers/rosbag2_checks.py); more in
tests/mapex/interop/test_mcap_file.py (in-process) and tests/services/bridges/test_ros2.py
(services.up --record)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")

import argparse  # noqa: E402
import time  # noqa: E402

import zenoh  # noqa: E402
from foxglove_files import foxglove_channels, protobuf_messages_in  # noqa: E402
from mcap_files import mcap_counts, ros_messages_in  # noqa: E402
from rosbag2_checks import rosbag2_play_problems  # noqa: E402
from service_processes import ServiceProcesses, free_loopback_port  # noqa: E402

from mapex.config import ConfigError  # noqa: E402
from mapex.interop.ros_messages import MapFrame, grid_values_in_map_order  # noqa: E402
from mapex.interop.topics import RunTopics  # noqa: E402
from services.bridges import record  # noqa: E402
from services.bridges.outside_tools import (  # noqa: E402
    add_outside_tool_arguments,
    check_outside_tool_arguments,
)
from services.messages import MapMessage, PoseMessage, StatusMessage  # noqa: E402

RECORDER_DEADLINE_S = 60.0  # a cold interpreter on a shared 2-core machine


def same_messages(ros_counts: dict[str, int], foxglove_counts: dict[str, int]) -> bool:
    """Whether the Foxglove file holds each robot topic's messages, as many as the bag (the
    bag's other topics, /clock or /tf, need not have a Foxglove form)."""
    robots = {f"/foxglove{t}": n for t, n in ros_counts.items() if t.startswith("/mapex/")}
    return all(foxglove_counts.get(t) == n for t, n in robots.items()) and all(
        ros_counts.get(t.removeprefix("/foxglove")) == n for t, n in foxglove_counts.items()
    )


@pytest.mark.parametrize(
    ("argv", "text"),
    [
        (["--out", "{tmp}/old.mcap"], "exists"),
        (["--out", "{tmp}/nowhere/new.mcap"], "does not exist"),
        (["--out", "{tmp}/new.mcap", "--run", "Bad Run"], "--run"),
        (["--out", "{tmp}/new.mcap", "--timeout-s", "0"], "--timeout-s"),
        (["--foxglove-out", "{tmp}/old.mcap"], "--foxglove-out"),
        (["--out", "{tmp}/a.mcap", "--foxglove-out", "{tmp}/a.mcap"], "same file"),
        (["--run", "demo"], "--out"),
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
    assert not (tmp_path / "a.mcap").exists()


@pytest.mark.parametrize(
    ("argv", "text"),
    [
        (["--record", "{tmp}/old.mcap"], "--record '"),
        (["--record-foxglove", "{tmp}/old.mcap"], "--record-foxglove '"),
        (["--record", "{tmp}/a.mcap", "--record-foxglove", "{tmp}/a.mcap"], "same file"),
        (["--record-foxglove", "{tmp}/nowhere/a.mcap"], "does not exist"),
    ],
)
def test_the_recording_flags_of_up_and_evaluate_are_one_line_errors(tmp_path, argv, text):
    (tmp_path / "old.mcap").write_bytes(b"keep me")
    parser = argparse.ArgumentParser()
    add_outside_tool_arguments(parser)
    args = parser.parse_args([arg.format(tmp=tmp_path) for arg in argv])
    with pytest.raises(ConfigError, match=text):
        check_outside_tool_arguments(args)
    fine = parser.parse_args(["--record-foxglove", str(tmp_path / "new.mcap")])
    check_outside_tool_arguments(fine)  # either flag alone


def test_the_recorder_writes_a_bag_for_ros2_bag_play_and_a_foxglove_file(tmp_path):
    """RunRecorder on a Zenoh session where a run is published by hand: the bag meets
    rosbag2's conditions and holds the ROS topics alone, the Foxglove file the same
    messages as protobuf."""
    session = zenoh.open(
        zenoh.Config.from_json5('{mode: "peer", scouting: {multicast: {enabled: false}}}')
    )
    bag, fox = tmp_path / "run.mcap", tmp_path / "fox.mcap"
    recorder = record.RunRecorder(session, bag, "demo", foxglove_path=fox)
    codes = np.ones((6, 8), np.uint8)
    codes[2:4, 2:6] = 0
    try:
        deadline = time.monotonic() + RECORDER_DEADLINE_S
        while not recorder.finished(["demo"]) and time.monotonic() < deadline:
            session.put("mapex/@v1/demo/r0/observed_map", MapMessage(7, "observed", codes).encode())
            session.put("mapex/@v1/demo/r0/pose", PoseMessage(7, (2, 3)).encode())
            session.put("mapex/@v1/demo/r0/status", StatusMessage(7, "finished").encode())
            time.sleep(0.2)
        assert recorder.wait_finished(["demo"], RECORDER_DEADLINE_S)
    finally:
        written = recorder.close()
        session.close()
    assert f"-> {bag}" in written and f"-> {fox}" in written
    assert rosbag2_play_problems(bag) == []
    ros_counts = mcap_counts(bag)
    assert ros_counts["/mapex/demo/r0/map"] >= 1 and ros_counts["/mapex/demo/r0/pose"] >= 1
    assert not any(topic.startswith("/foxglove") for topic in ros_counts)
    assert same_messages(ros_counts, mcap_counts(fox))
    assert {channel[0] for channel in foxglove_channels(fox).values()} == {"protobuf"}
    grid = protobuf_messages_in(fox, "/foxglove/mapex/demo/r0/map")[-1]
    assert (grid.column_count, len(grid.data)) == (8, 6 * 8 * grid.cell_stride)


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
    out, fox = tmp_path / "run.mcap", tmp_path / "fox.mcap"
    try:
        recorder = processes.spawn(
            "record", "services.record", "--out", str(out), "--until-finished",
            "--timeout-s", str(RECORDER_DEADLINE_S), "--foxglove-out", str(fox),
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
    assert rosbag2_play_problems(out) == []
    assert same_messages(counts, mcap_counts(fox))
