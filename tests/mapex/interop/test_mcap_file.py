"""MCAP recordings (mapex.interop.mcap_file) and in-process episode recordings."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")
pytest.importorskip("mcap_ros2", reason="the ros extra is not installed")

from mcap_files import mcap_counts, ros_messages_in  # noqa: E402

from mapex.config import ExplorationConfig  # noqa: E402
from mapex.episode import run_episode  # noqa: E402
from mapex.interop.episode_recording import EpisodeRecording, RecordingConfig  # noqa: E402
from mapex.interop.mcap_file import McapRecording, offered_qos, record_path_problem  # noqa: E402
from mapex.interop.ros_messages import grid_values_in_map_order, observed_values  # noqa: E402
from mapex.prediction import make_predictor  # noqa: E402
from mapex.worlds import generate_floor_plan  # noqa: E402


def test_a_recording_is_a_valid_mcap_even_when_closed_at_once(tmp_path):
    recording = McapRecording(tmp_path / "empty.mcap")
    assert not (tmp_path / "empty.mcap").exists()  # hidden until complete
    recording.close()
    assert mcap_counts(tmp_path / "empty.mcap") == {}


def test_recordings_are_never_overwritten(tmp_path):
    (tmp_path / "old.mcap").write_bytes(b"x")
    assert "exists" in record_path_problem(tmp_path / "old.mcap")
    assert "does not exist" in record_path_problem(tmp_path / "nowhere" / "new.mcap")
    assert record_path_problem(tmp_path / "new.mcap") is None


def test_latched_topics_offer_transient_local_depth_one():
    assert "durability: 1" in offered_qos(True) and "depth: 1\n" in offered_qos(True)
    assert "durability: 2" in offered_qos(False) and "depth: 10" in offered_qos(False)


def test_a_100_step_run_reads_back_with_every_topic_and_the_final_map(tmp_path):
    world = generate_floor_plan(3)
    path = tmp_path / "run.mcap"
    recording = EpisodeRecording(path, "demo", world.shape, world.resolution_m, RecordingConfig(30))
    config = ExplorationConfig(steps=100)
    result = run_episode(
        world, "mapex", make_predictor("classical"), 0, 0, config,
        on_step=lambda t, explorers, _: recording.step(t, explorers),
    )  # fmt: skip
    written = recording.close()
    counts = mcap_counts(path)
    assert sum(counts.values()) == written
    assert counts["/mapex/demo/r0/pose"] == 100 == counts["/foxglove/mapex/demo/r0/pose"]
    assert counts["/mapex/demo/r0/map"] == 4  # t = 30, 60, 90 and the last step
    assert counts["/mapex/demo/r0/prediction_mean"] == result.stats.replans
    assert 0 < counts["/mapex/demo/r0/plan"] <= 100
    assert counts["/mapex/demo/r0/trajectory"] == 4  # with the maps: every 30 steps and the end
    maps = ros_messages_in(path, "/mapex/demo/r0/map")
    final = grid_values_in_map_order(maps[-1])
    assert np.array_equal(final, observed_values(result.final_observed))
    poses = ros_messages_in(path, "/mapex/demo/r0/pose")
    last = result.trajectory[-1]
    assert poses[-1].pose.position.x == pytest.approx((last[1] + 0.5) * world.resolution_m)
    xy = [(p.pose.position.x, p.pose.position.y) for p in poses]
    moves = [a for i, a in enumerate(xy) if i == 0 or a != xy[i - 1]]
    trajectory = ros_messages_in(path, "/mapex/demo/r0/trajectory")[-1].poses
    assert [(p.pose.position.x, p.pose.position.y) for p in trajectory] == moves
