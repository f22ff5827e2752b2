"""The MCAP recorder process (services.record) and the live Foxglove server: flags and
start-up; whole recordings are checked in tests/services/test_ros2.py (services.up
--record) and tests/mapex/interop/test_mcap_file.py (in-process)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")

from mapex.interop.ros_messages import MapFrame  # noqa: E402
from mapex.interop.topics import RunTopics  # noqa: E402
from services import record  # noqa: E402


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
    from services.foxglove_live import FoxgloveServer

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
