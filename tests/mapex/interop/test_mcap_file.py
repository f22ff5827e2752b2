"""MCAP recordings (mapex.interop.mcap_file) and in-process episode recordings: the bag
meets every condition of `ros2 bag play` reproduced from rosbag2's source
(tests/helpers/rosbag2_checks.py), reads back with rosbags' AnyReader and mcap_ros2, and the
Foxglove file holds the protobuf channels alone."""

from __future__ import annotations

import subprocess
import sys
from functools import partial
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")
pytest.importorskip("mcap_ros2", reason="the ros extra is not installed")

from foxglove_files import foxglove_channels, protobuf_messages_in  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap_files import mcap_counts, ros_messages_in  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from rosbag2_checks import decode_qos_text, rosbag2_play_problems  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402

from mapex.config import ExplorationConfig  # noqa: E402
from mapex.episode import run_episode  # noqa: E402
from mapex.interop import mcap_file  # noqa: E402
from mapex.interop import ros_messages as ros  # noqa: E402
from mapex.interop import topics as topics_module  # noqa: E402
from mapex.interop.episode_recording import EpisodeRecording, RecordingConfig  # noqa: E402
from mapex.interop.mcap_file import (  # noqa: E402
    McapRecording,
    RecordingProfile,
    Recordings,
    offered_qos,
    record_path_problem,
    recording_flags_problem,
    rosbag2_yaml,
)
from mapex.interop.ros_messages import (  # noqa: E402
    MapFrame,
    grid_values_in_map_order,
    observed_values,
)
from mapex.interop.sim_time import DEFAULT_SIM_CLOCK  # noqa: E402
from mapex.interop.topics import RunTopics  # noqa: E402
from mapex.prediction import make_predictor  # noqa: E402
from mapex.worlds import generate_floor_plan  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]
S = 1_000_000_000
# the channel metadata rosbag2_storage_mcap (Jazzy) writes for a latched topic:
# serialize_rclcpp_qos_vector -> YAML::Dump of a sequence of one version 9 profile
LATCHED_QOS_TEXT = """\
- history: keep_last
  depth: 1
  reliability: reliable
  durability: transient_local
  deadline:
    sec: 0
    nsec: 0
  lifespan:
    sec: 0
    nsec: 0
  liveliness: automatic
  liveliness_lease_duration:
    sec: 0
    nsec: 0
  avoid_ros_namespace_conventions: false"""
# yaml.hpp convert<BagMetadata>::encode, in its order
BAG_METADATA_KEYS = [
    "version", "storage_identifier", "duration", "starting_time", "message_count",
    "topics_with_message_count", "compression_format", "compression_mode",
    "relative_file_paths", "files", "custom_data", "ros_distro",
]  # fmt: skip


ROBOT_MAP = np.ones((6, 8), np.uint8)  # unknown, with a free room
ROBOT_MAP[2:4, 2:6] = 0


class KeepsEverything:
    """The recordings before issue #54: CDR and protobuf channels in one `ros2` file,
    without rosbag2's metadata record (a stand-in RecordingProfile)."""

    mcap_profile = "ros2"

    def keeps(self, message) -> bool:
        return True


def write_two_robots(recording, topics: RunTopics) -> None:
    """Real messages of two robots, every kind, stamps going back and forth between robots
    as a live recorder may see them."""
    for t in range(3):
        for k, robot in enumerate(("r0", "r1")):
            stamp_ns = t * S + (1 - k) * S // 2
            messages = topics.observed(robot, ROBOT_MAP, stamp_ns) + topics.pose(
                robot, (2 + t, 3 + k), stamp_ns
            )
            messages += topics.plan(robot, np.array([[2, 3], [3, 3], [3, 4]]), stamp_ns)
            messages += topics.mean(robot, np.full((6, 8), 0.25), stamp_ns)
            for outgoing in messages:
                recording.write(outgoing)


def any_reader_contents(path: Path) -> tuple[dict[str, str], dict[str, int]]:
    """rosbags' AnyReader on the file: topic -> type, and topic -> messages deserialized."""
    counts: dict[str, int] = {}
    with AnyReader([path]) as reader:
        types = {topic: info.msgtype for topic, info in reader.topics.items()}
        for connection, _, raw in reader.messages():
            message = reader.deserialize(raw, connection.msgtype)
            assert message.__msgtype__ == connection.msgtype
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
    return types, counts


def mcap_ros2_contents(path: Path) -> dict[str, int]:
    """mcap_ros2's decoder on every message: topic -> messages decoded."""
    counts: dict[str, int] = {}
    with open(path, "rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages():
            assert decoded is not None
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def serialized_metadata(path: Path) -> list[dict]:
    from ruamel.yaml import YAML

    with open(path, "rb") as handle:
        records = [m.metadata for m in make_reader(handle).iter_metadata() if m.name == "rosbag2"]
    return [YAML(typ="safe").load(r["serialized_metadata"]) for r in records]


def log_times(path: Path) -> list[int]:
    with open(path, "rb") as handle:
        return [m.log_time for _, _, m in make_reader(handle).iter_messages(log_time_order=False)]


def test_a_recording_is_a_valid_mcap_even_when_closed_at_once(tmp_path):
    recording = McapRecording(tmp_path / "empty.mcap")
    assert not (tmp_path / "empty.mcap").exists()  # hidden until complete
    recording.close()
    assert mcap_counts(tmp_path / "empty.mcap") == {}
    (bag,) = serialized_metadata(tmp_path / "empty.mcap")
    assert bag["message_count"] == 0 and bag["topics_with_message_count"] == []
    assert bag["starting_time"]["nanoseconds_since_epoch"] == 2**63 - 1  # rosbag2's "none"


def test_recordings_are_never_overwritten(tmp_path):
    (tmp_path / "old.mcap").write_bytes(b"x")
    assert "exists" in record_path_problem(tmp_path / "old.mcap")
    assert "does not exist" in record_path_problem(tmp_path / "nowhere" / "new.mcap")
    assert record_path_problem(tmp_path / "new.mcap") is None


def test_the_recording_flags_are_checked_together(tmp_path):
    (tmp_path / "old.mcap").write_bytes(b"x")
    new, old = tmp_path / "new.mcap", tmp_path / "old.mcap"
    problem = recording_flags_problem({"--record": new, "--record-foxglove": old})
    assert problem.startswith("--record-foxglove ") and "exists" in problem
    problem = recording_flags_problem({"--record": new, "--record-foxglove": tmp_path / "."})
    assert problem is not None  # a directory exists too
    same = recording_flags_problem({"--record": new, "--record-foxglove": tmp_path / "new.mcap"})
    assert "same file" in same and "--record and --record-foxglove" in same
    assert recording_flags_problem({"--record": new, "--record-foxglove": None}) is None
    assert recording_flags_problem({"--record": None, "--record-foxglove": new}) is None


def test_latched_topics_offer_transient_local_depth_one_as_rosbag2_writes_it():
    assert rosbag2_yaml(offered_qos(True)) == LATCHED_QOS_TEXT
    (latched,) = decode_qos_text(rosbag2_yaml(offered_qos(True)))
    (volatile,) = decode_qos_text(rosbag2_yaml(offered_qos(False)))
    assert (latched["durability"], latched["depth"]) == ("transient_local", 1)
    assert (volatile["durability"], volatile["depth"]) == ("volatile", 10)
    assert latched["reliability"] == volatile["reliability"] == "reliable"


def test_a_bag_meets_every_condition_of_ros2_bag_play(tmp_path):
    path = tmp_path / "bag.mcap"
    recording = McapRecording(path)
    write_two_robots(recording, RunTopics("demo", MapFrame(6, 8), with_foxglove=True))
    recording.close()
    assert rosbag2_play_problems(path) == []
    with open(path, "rb") as handle:
        reader = make_reader(handle)
        header, summary = reader.get_header(), reader.get_summary()
    assert header.profile == "ros2"
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert not any(c.topic.startswith("/foxglove") for c in summary.channels.values())
    (bag,) = serialized_metadata(path)
    assert list(bag) == BAG_METADATA_KEYS
    assert (bag["version"], bag["ros_distro"], bag["storage_identifier"]) == (9, "jazzy", "mcap")
    assert bag["message_count"] == recording.messages == sum(mcap_counts(path).values())
    assert bag["starting_time"]["nanoseconds_since_epoch"] == 0  # the earliest, robot r1's
    assert bag["duration"]["nanoseconds"] == 2 * S + S // 2
    latched = [
        t["topic_metadata"]["offered_qos_profiles"][0]["durability"]
        for t in bag["topics_with_message_count"]
        if t["topic_metadata"]["type"] == ros.GRID_TYPE
    ]
    assert latched == ["transient_local"] * 4  # map and prediction_mean of two robots


def test_a_bag_reads_back_with_rosbags_and_mcap_ros2_message_for_message(tmp_path):
    path = tmp_path / "bag.mcap"
    recording = McapRecording(path)
    write_two_robots(recording, RunTopics("demo", MapFrame(6, 8), with_foxglove=True))
    recording.close()
    counts = mcap_counts(path)
    types, deserialized = any_reader_contents(path)
    assert deserialized == counts == mcap_ros2_contents(path)
    assert types == {
        f"/mapex/demo/{robot}/{name}": ros_type
        for robot in ("r0", "r1")
        for name, ros_type in (
            ("map", ros.GRID_TYPE), ("prediction_mean", ros.GRID_TYPE),
            ("pose", ros.POSE_TYPE), ("plan", ros.PATH_TYPE), ("trajectory", ros.PATH_TYPE),
        )
    }  # fmt: skip
    grid = ros_messages_in(path, "/mapex/demo/r1/map")[-1]
    assert np.array_equal(grid_values_in_map_order(grid), observed_values(ROBOT_MAP))


def test_every_ros_topic_goes_into_the_bag_with_the_qos_it_is_offered_with(tmp_path):
    """Graph topics (/clock best effort, /tf, /tf_static), the scan and markers, which have no
    Foxglove form: in the bag, each with its own QoS, read back by rosbags and mcap_ros2."""
    path = tmp_path / "bag.mcap"
    recording = McapRecording(path)
    topics = RunTopics("demo", MapFrame(6, 8), with_foxglove=True)
    n_rays = 8
    messages = [topics_module.clock(S), *topics.transforms("r0", (2, 3), S)]
    messages += topics.variance("r0", np.full((6, 8), 0.1), S)
    messages += topics.frontiers("r0", np.array([[2, 2], [3, 5]]), np.array([0.2, 0.9]), S)
    messages += topics.goal("r0", (3, 5), S)
    messages += topics.scan(
        "r0", (2, 3), np.full(n_rays, 3, np.uint16), np.ones(n_rays, bool), 10, S
    )
    for outgoing in messages:
        recording.write(outgoing)
    recording.close()
    assert rosbag2_play_problems(path) == []
    types, deserialized = any_reader_contents(path)
    assert deserialized == mcap_counts(path) == mcap_ros2_contents(path)
    assert set(types) == {outgoing.topic for outgoing in messages}
    with open(path, "rb") as handle:
        channels = make_reader(handle).get_summary().channels.values()
        qos = {c.topic: decode_qos_text(c.metadata["offered_qos_profiles"])[0] for c in channels}
    for outgoing in messages:
        profile = qos[outgoing.topic]
        assert profile["reliability"] == ("reliable" if outgoing.reliable else "best_effort")
        assert profile["durability"] == ("transient_local" if outgoing.latched else "volatile")
        assert outgoing.depth is None or profile["depth"] == outgoing.depth
    assert qos["/clock"]["reliability"] == "best_effort"


def test_the_checks_catch_the_recordings_of_before(tmp_path):
    """What a user met: one file with CDR and protobuf channels is refused by rosbag2's
    SequentialReader and breaks rosbags' AnyReader on the binary schemas."""
    path = tmp_path / "mixed.mcap"
    recording = McapRecording(path, KeepsEverything())
    write_two_robots(recording, RunTopics("demo", MapFrame(6, 8), with_foxglove=True))
    recording.close()
    problems = rosbag2_play_problems(path)
    assert any("different rmw serialization format" in p for p in problems), problems
    assert any("'rosbag2' metadata record" in p for p in problems), problems
    with pytest.raises(UnicodeDecodeError):
        any_reader_contents(path)


def _no_statistics(monkeypatch) -> None:
    import mcap.writer

    monkeypatch.setattr(mcap.writer, "Writer", partial(mcap.writer.Writer, use_statistics=False))


def _no_chunks(monkeypatch) -> None:
    import mcap.writer

    monkeypatch.setattr(mcap.writer, "Writer", partial(mcap.writer.Writer, use_chunking=False))


def _unknown_history(monkeypatch) -> None:
    bad = [{**offered_qos(False)[0], "history": "keep_newest"}]
    monkeypatch.setattr(mcap_file, "offered_qos", lambda *_qos: bad)


def _root_definition_only(monkeypatch) -> None:
    full = ros.message_definition
    monkeypatch.setattr(ros, "message_definition", lambda t: full(t).split("=" * 80)[0])


def _miscounted(monkeypatch) -> None:
    bag_metadata = McapRecording.bag_metadata
    monkeypatch.setattr(
        McapRecording, "bag_metadata", lambda self: {**bag_metadata(self), "message_count": 1}
    )


def _digit_token(monkeypatch) -> None:
    monkeypatch.setattr(topics_module, "ros_token", lambda text: f"{text}_1x".replace("_1", "/1"))


@pytest.mark.parametrize(
    ("breach", "problem"),
    [
        (_no_statistics, "no Statistics record"),
        (_no_chunks, "message_indexes_present"),
        (_unknown_history, "to_rclcpp_qos_vector"),
        (_root_definition_only, "has no MSG: section"),
        (_miscounted, "message_count"),
        (_digit_token, "create_generic_publisher"),
    ],
)
def test_each_rosbag2_condition_catches_its_breach(tmp_path, monkeypatch, breach, problem):
    breach(monkeypatch)
    path = tmp_path / "bag.mcap"
    recording = McapRecording(path)
    write_two_robots(recording, RunTopics("demo", MapFrame(6, 8), with_foxglove=False))
    recording.close()
    problems = rosbag2_play_problems(path)
    assert any(problem in p for p in problems), problems


def test_a_foxglove_file_holds_the_protobuf_channels_alone(tmp_path):
    path = tmp_path / "foxglove.mcap"
    recording = McapRecording(path, RecordingProfile.FOXGLOVE)
    write_two_robots(recording, RunTopics("demo", MapFrame(6, 8), with_foxglove=True))
    recording.close()
    channels = foxglove_channels(path)
    assert channels and all(c[:2] == ("protobuf", "protobuf") for c in channels.values())
    assert channels["/foxglove/mapex/demo/r0/map"][2] == "foxglove.Grid"
    assert serialized_metadata(path) == []
    with open(path, "rb") as handle:
        assert make_reader(handle).get_header().profile == ""
    grid = protobuf_messages_in(path, "/foxglove/mapex/demo/r0/map")[-1]
    assert (grid.column_count, grid.frame_id) == (8, "map")
    assert len(grid.data) == 6 * 8 * grid.cell_stride


def test_both_files_get_the_same_messages_and_a_failed_open_leaves_none(tmp_path):
    bag, fox = tmp_path / "bag.mcap", tmp_path / "fox.mcap"
    recordings = Recordings(bag, fox)
    assert recordings.with_foxglove
    write_two_robots(recordings, RunTopics("demo", MapFrame(6, 8), with_foxglove=True))
    assert recordings.close() == f"{recordings.files[0].messages} messages -> {bag}, " + (
        f"{recordings.files[1].messages} messages -> {fox}"
    )
    ros_counts, fox_counts = mcap_counts(bag), mcap_counts(fox)
    assert fox_counts == {f"/foxglove{topic}": n for topic, n in ros_counts.items()}
    bag_only = Recordings(tmp_path / "bag_only.mcap")
    assert not bag_only.with_foxglove
    bag_only.close()
    with pytest.raises(OSError):
        Recordings(tmp_path / "discarded.mcap", tmp_path / "nowhere" / "fox.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag.mcap", "bag_only.mcap", "fox.mcap"]


def test_a_100_step_run_reads_back_with_every_topic_and_the_final_map(tmp_path):
    world = generate_floor_plan(3)
    path, fox = tmp_path / "run.mcap", tmp_path / "fox.mcap"
    recording = EpisodeRecording(
        path, "demo", world.shape, world.resolution_m, RecordingConfig(30), foxglove_path=fox
    )
    config = ExplorationConfig(steps=100)
    result = run_episode(
        world, "mapex", make_predictor("classical"), 0, 0, config,
        on_step=lambda t, explorers, _: recording.step(t, explorers),
    )  # fmt: skip
    written = recording.close()
    counts = mcap_counts(path)
    assert f"{sum(counts.values())} messages -> {path}" in written
    assert counts["/mapex/demo/r0/pose"] == 100 == mcap_counts(fox)["/foxglove/mapex/demo/r0/pose"]
    assert counts["/mapex/demo/r0/map"] == 4  # t = 30, 60, 90 and the last step
    assert counts["/mapex/demo/r0/prediction_mean"] == result.stats.replans
    assert 0 < counts["/mapex/demo/r0/plan"] <= 100
    assert counts["/mapex/demo/r0/trajectory"] == 4  # with the maps: every 30 steps and the end
    assert rosbag2_play_problems(path) == []
    times = log_times(path)
    assert times == sorted(times)  # written in log-time order
    poses = ros_messages_in(path, "/mapex/demo/r0/pose")
    stamps = [p.header.stamp.sec * S + p.header.stamp.nanosec for p in poses]
    assert stamps == [DEFAULT_SIM_CLOCK.stamp_ns(t) for t in range(1, 101)]  # simulation time
    maps = ros_messages_in(path, "/mapex/demo/r0/map")
    final = grid_values_in_map_order(maps[-1])
    assert np.array_equal(final, observed_values(result.final_observed))
    last = result.trajectory[-1]
    assert poses[-1].pose.position.x == pytest.approx((last[1] + 0.5) * world.resolution_m)
    xy = [(p.pose.position.x, p.pose.position.y) for p in poses]
    moves = [a for i, a in enumerate(xy) if i == 0 or a != xy[i - 1]]
    trajectory = ros_messages_in(path, "/mapex/demo/r0/trajectory")[-1].poses
    assert [(p.pose.position.x, p.pose.position.y) for p in trajectory] == moves


def mapex_run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mapex", "run", "--no-progress", *args],
        capture_output=True, text=True, cwd=ROOT, timeout=600,
    )  # fmt: skip


@pytest.mark.slow  # a run in a process of its own
def test_mapex_run_records_a_bag_for_ros2_bag_play_and_a_foxglove_file(tmp_path):
    bag, fox = tmp_path / "run.mcap", tmp_path / "fox.mcap"
    done = mapex_run(
        "--steps", "8", "--out", str(tmp_path / "results"), "--record", str(bag),
        "--record-foxglove", str(fox),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"-> {bag}" in done.stderr and f"-> {fox}" in done.stderr
    assert rosbag2_play_problems(bag) == []
    types, deserialized = any_reader_contents(bag)
    assert deserialized == mcap_counts(bag) == mcap_ros2_contents(bag)
    robot_topics = {topic for topic in types if topic.startswith("/mapex/")}
    assert {topic.removeprefix("/foxglove") for topic in foxglove_channels(fox)} == robot_topics
    assert {c[0] for c in foxglove_channels(fox).values()} == {"protobuf"}


@pytest.mark.slow  # runs the command in a process of its own
@pytest.mark.parametrize(
    ("flags", "text"),
    [
        (["--record-foxglove", "{tmp}/old.mcap"], "--record-foxglove"),
        (["--record", "{tmp}/a.mcap", "--record-foxglove", "{tmp}/a.mcap"], "same file"),
    ],
)
def test_mapex_run_refuses_bad_recording_flags_in_one_line(tmp_path, flags, text):
    (tmp_path / "old.mcap").write_bytes(b"an older recording")
    done = mapex_run("--steps", "2", *[flag.format(tmp=tmp_path) for flag in flags])
    assert done.returncode == 2 and "Traceback" not in done.stderr
    (error,) = [line for line in done.stderr.splitlines() if "error" in line]
    assert text in error
    assert (tmp_path / "old.mcap").read_bytes() == b"an older recording"
    assert not (tmp_path / "a.mcap").exists()
