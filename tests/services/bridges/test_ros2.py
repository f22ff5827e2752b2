"""The ROS 2 bridge (services.ros2) and the run translation it shares with the recorder.

No ROS install here: a router-mode Zenoh session on a loopback port stands in for
rmw_zenohd, and the test plays the parts of `ros2 topic list` (a liveliness query on
`@ros2_lv/0/**`), of a volatile subscriber and of RViz2's transient-local map subscriber
(a zenoh-ext advanced subscriber with rmw_zenoh's options), decoding with rosbags and
mcap_ros2.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")
pytest.importorskip("mcap_ros2", reason="the ros extra is not installed")

import zenoh  # noqa: E402
from mcap.records import Schema  # noqa: E402
from mcap_files import mcap_counts, ros_messages_in  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from rosbag2_checks import rosbag2_play_problems  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from service_processes import free_loopback_port, until  # noqa: E402
from up_processes import UpProcess  # noqa: E402
from zenoh.ext import HistoryConfig, declare_advanced_subscriber  # noqa: E402

from mapex.config import SensorConfig  # noqa: E402
from mapex.grid import FREE, OCCUPIED, UNKNOWN  # noqa: E402
from mapex.interop import rmw_zenoh as rmw  # noqa: E402
from mapex.interop import ros_messages as ros  # noqa: E402
from mapex.interop.ros_messages import NS_PER_S, MapFrame  # noqa: E402
from mapex.interop.sim_time import SimClock  # noqa: E402
from mapex.interop.topics import GRAPH_TOPICS, ROBOT_TOPICS  # noqa: E402
from mapex.raycast import ray_directions, trace_ray  # noqa: E402
from mapex.sensor import cast_scan  # noqa: E402
from services import up  # noqa: E402
from services.bridges import ros2  # noqa: E402
from services.bridges.follow import Update  # noqa: E402
from services.bridges.ros_translate import RunTranslator  # noqa: E402
from services.config import Ros2Config  # noqa: E402
from services.messages import (  # noqa: E402
    FrontiersMessage,
    GoalMessage,
    MapMessage,
    PathMessage,
    PoseMessage,
    ScanReply,
    StatusMessage,
    WorldInfo,
    decode_message,
)

GRID_HASH = "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"
TEAM_STEPS = 40  # long enough for re-plans (frontiers, goal, predictions) of both robots


def _codes(shape=(8, 12), free_cols=6) -> np.ndarray:
    codes = np.full(shape, UNKNOWN, dtype=np.uint8)
    codes[2:6, 1:free_cols] = FREE
    codes[1, :] = OCCUPIED
    return codes


def _expected_values(codes: np.ndarray) -> np.ndarray:
    return np.where(codes == FREE, 0, np.where(codes == OCCUPIED, 100, -1)).astype(np.int8)


def _mcap_ros2_decode(data: bytes, ros_type: str):
    """Decode CDR with mcap_ros2 from the schema text alone (what Foxglove does)."""
    definition = ros.message_definition(ros_type).encode()
    schema = Schema(id=1, name=ros_type, encoding="ros2msg", data=definition)
    return DecoderFactory().decoder_for("cdr", schema)(data)


def _session(mode: str, listen: list[str], connect: list[str]) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("mode", f'"{mode}"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", str(listen).replace("'", '"'))
    config.insert_json5("connect/endpoints", str(connect).replace("'", '"'))
    config.insert_json5("timestamping/enabled", "true")
    return zenoh.open(config)


@pytest.fixture
def ros_router():
    """A router-mode session standing in for rmw_zenohd; yields its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router = _session("router", [endpoint], [])
    yield endpoint
    router.close()


def _ros_peer(endpoint: str) -> zenoh.Session:
    """A session configured like an rmw_zenoh node's: a peer of the router, listening."""
    return _session("peer", ["tcp/127.0.0.1:0"], [endpoint])


def _ros_graph(session: zenoh.Session) -> list[str]:
    """What `ros2 node list` / `ros2 topic list` read: the liveliness tokens of domain 0."""
    replies = session.liveliness().get("@ros2_lv/0/**", timeout=2.0)
    return sorted(str(reply.ok.key_expr) for reply in replies if reply.ok is not None)


# ----------------------------------------------------------------------------- translation


def _update(run, topic, message, robot="r0"):
    return Update(run, robot, topic, message)


def _names(sent) -> list[str]:
    """The per-robot topics of `sent`, by their last name (/clock and /tf left out)."""
    return [o.topic.rsplit("/", 1)[1] for o in sent if o.topic.startswith("/mapex/")]


def _stamp_ns(header) -> int:
    return header.stamp.sec * NS_PER_S + header.stamp.nanosec


def _yaw(quaternion) -> float:
    return 2.0 * math.atan2(quaternion.z, quaternion.w)


def _same_angle(a: float, b: float) -> bool:
    return abs(math.remainder(a - b, 2.0 * math.pi)) < 1e-6


class TfTree:
    """The transforms heard on /tf_static (the newest message: it holds them all) and /tf
    (by stamp), composed in 2D as tf2 would look a frame up in `map`."""

    def __init__(self) -> None:
        self.static: dict[str, tuple] = {}
        self.dynamic: dict[tuple[str, int], tuple] = {}

    def add(self, topic: str, message) -> None:
        if topic == "/tf_static":
            self.static = {}
        for t in message.transforms:
            link = (t.header.frame_id, t.transform.translation.x, t.transform.translation.y,
                    _yaw(t.transform.rotation))  # fmt: skip
            if topic == "/tf_static":
                self.static[t.child_frame_id] = link
            else:
                self.dynamic[t.child_frame_id, _stamp_ns(t.header)] = link

    def in_map(self, frame: str, stamp_ns: int) -> tuple[float, float, float]:
        """(x, y, yaw) of `frame`'s origin in `map` at `stamp_ns` (KeyError: a link is missing)."""
        x, y, yaw = 0.0, 0.0, 0.0
        while frame != "map":
            parent, dx, dy, dyaw = self.static.get(frame) or self.dynamic[frame, stamp_ns]
            x, y = (
                dx + math.cos(dyaw) * x - math.sin(dyaw) * y,
                dy + math.sin(dyaw) * x + math.cos(dyaw) * y,
            )
            yaw, frame = yaw + dyaw, parent
        return x, y, yaw


def _check_scan(scan, tree: TfTree, reply: ScanReply, frame: MapFrame, range_cells: int) -> None:
    """Every range of a LaserScan, placed in `map` through the TF chain, ends within half a
    cell of the centre of the wall cell its ray hit (mapex.sensor: ray k leaves (row, col)
    along (sin, cos) of 2 pi k / n, i.e. at -2 pi k / n in the map frame); no return is +inf."""
    n = len(reply.n_cells)
    assert len(scan.ranges) == n and scan.angle_increment == pytest.approx(2 * math.pi / n)
    assert scan.range_max == pytest.approx(range_cells * frame.resolution_m)
    assert int(np.isfinite(scan.ranges).sum()) == int(reply.hit.sum())
    x0, y0, yaw0 = tree.in_map(scan.header.frame_id, _stamp_ns(scan.header))
    assert (x0, y0) == pytest.approx(tuple(frame.cell_xy_m(np.array(reply.pose))[0]))
    directions = ray_directions(n)
    for i, distance in enumerate(scan.ranges):
        angle = yaw0 + scan.angle_min + i * scan.angle_increment  # in the map frame
        k = round(-angle / scan.angle_increment) % n
        assert bool(reply.hit[k]) == bool(np.isfinite(distance)), k
        if not np.isfinite(distance):
            continue
        cells = trace_ray(frame.rows, frame.cols, *reply.pose, *directions[k], float(range_cells))
        wall = frame.cell_xy_m(cells[int(reply.n_cells[k]) - 1])[0]
        end = (x0 + distance * math.cos(angle), y0 + distance * math.sin(angle))
        assert np.abs(np.subtract(end, wall)).max() <= 0.5 * frame.resolution_m + 1e-5, k


def _room(shape=(30, 40)) -> np.ndarray:
    occupancy = np.zeros(shape, bool)
    occupancy[[0, -1], :] = occupancy[:, [0, -1]] = True
    occupancy[10:20, 25] = True
    return occupancy


def test_maps_poses_and_paths_become_their_topics_in_the_worlds_frame():
    sent = []
    translate = RunTranslator(sent.append, Ros2Config())
    info = WorldInfo("w", (8, 12), 0.05, np.zeros((1, 2), int))
    translate(Update("run-a", None, "world_info", info))
    translate(_update("run-a", "observed_map", MapMessage(1, "observed", _codes())))
    translate(_update("run-a", "pose", PoseMessage(1, (3, 3))))
    translate(_update("run-a", "path", PathMessage(1, np.array([[3, 3], [3, 4]]))))
    topics = [o.topic for o in sent]
    assert topics == [
        "/clock", "/mapex/run_a/r0/map", "/mapex/run_a/r0/pose", "/mapex/run_a/r0/trajectory",
        "/tf_static", "/tf", "/mapex/run_a/r0/plan",
    ]  # fmt: skip
    grid = sent[1].message
    assert grid.info.resolution == pytest.approx(0.05) and sent[1].latched
    assert np.array_equal(ros.grid_values_in_map_order(grid), _expected_values(_codes()))
    assert sent[2].message.pose.position.x == pytest.approx(3.5 * 0.05)
    assert all(o.stamp_ns == NS_PER_S for o in sent)  # step 1, 1 s of simulated time
    assert [o.latched for o in sent if o.topic.endswith(("/plan", "/trajectory"))] == [True] * 2


def test_stamps_are_simulated_time_and_the_clock_only_moves_forward():
    sent = []
    translate = RunTranslator(sent.append, Ros2Config(), sim_clock=SimClock(seconds_per_step=0.5))
    translate(_update("r", "observed_map", MapMessage(4, "observed", _codes())))
    for t in (5, 3, 7):  # a late path of an older step does not turn the clock back
        translate(_update("r", "path", PathMessage(t, np.array([[3, 3]]))))
    clocks = [o.message.clock for o in sent if o.topic == "/clock"]
    assert [c.sec * NS_PER_S + c.nanosec for c in clocks] == [
        2 * NS_PER_S,
        2_500_000_000,
        3_500_000_000,
    ]
    plans = [o for o in sent if o.topic.endswith("/plan")]
    assert [_stamp_ns(o.message.header) for o in plans] == [o.stamp_ns for o in plans]
    assert [o.stamp_ns for o in plans] == [2_500_000_000, 1_500_000_000, 3_500_000_000]
    clock = next(o for o in sent if o.topic == "/clock")
    assert not clock.reliable and clock.depth == 1  # rclcpp's ClockQoS


@pytest.mark.parametrize("frame_from", ["observed_map", "world_info"])
def test_a_pose_before_the_runs_first_frame_is_held_until_there_is_one(frame_from):
    """Zenoh orders samples per key only: a pose and a path that beat the run's first map
    (or world info) are sent, the newest of each, once the run can be placed."""
    sent = []
    translate = RunTranslator(sent.append, Ros2Config())
    translate(_update("run-a", "pose", PoseMessage(0, (2, 2))))
    translate(_update("run-a", "pose", PoseMessage(1, (3, 3))))
    translate(_update("run-a", "path", PathMessage(1, np.array([[3, 3], [3, 4]]))))
    assert sent == []
    if frame_from == "observed_map":
        translate(_update("run-a", "observed_map", MapMessage(1, "observed", _codes())))
    else:
        info = WorldInfo("w", (8, 12), 0.05, np.zeros((1, 2), int))
        translate(Update("run-a", None, "world_info", info))
    assert _names(sent) == ["map", "pose", "trajectory", "plan"][frame_from == "world_info" :]
    pose = next(o for o in sent if o.topic.endswith("/pose")).message
    resolution_m = 0.05 if frame_from == "world_info" else Ros2Config().default_resolution_m
    assert pose.pose.position.x == pytest.approx(3.5 * resolution_m)


def test_held_updates_are_kept_for_the_newest_runs_only():
    sent = []
    translate = RunTranslator(sent.append, Ros2Config(max_runs=2))
    for run in ("a", "b", "c"):
        translate(_update(run, "pose", PoseMessage(0, (2, 2))))
    translate(_update("a", "observed_map", MapMessage(0, "observed", _codes())))
    assert [o.topic for o in sent] == ["/clock", "/mapex/a/r0/map"]  # a's pose went with the cap


def test_the_trajectory_goes_out_now_and_then_and_whole_at_the_end():
    sent = []
    translate = RunTranslator(sent.append, Ros2Config(trajectory_period_s=3600.0))
    translate(_update("r", "observed_map", MapMessage(0, "observed", _codes())))
    for t, cell in enumerate([(3, 3), (3, 4), (3, 5)], start=1):
        translate(_update("r", "pose", PoseMessage(t, cell)))
    translate(_update("r", "status", StatusMessage(3, "finished")))
    assert _names(sent) == ["map", "pose", "trajectory", "pose", "pose", "trajectory"]
    assert len(sent[-1].message.poses) == 3  # every pose, though sent once in between


def test_only_the_newest_runs_keep_their_topics_and_frames():
    forgotten, sent = [], []
    translate = RunTranslator(sent.append, Ros2Config(max_runs=2), forgotten.append)
    for run in ("a", "b", "c"):
        translate(_update(run, "observed_map", MapMessage(0, "observed", _codes())))
        translate(_update(run, "pose", PoseMessage(0, (3, 3))))
    assert list(translate.runs) == ["b", "c"] and forgotten == ["/mapex/a/"]
    statics = [o.message for o in sent if o.topic == "/tf_static"]
    assert [len(m.transforms) for m in statics] == [2, 4, 2, 4]  # a; a, b; b; b, c
    assert {t.child_frame_id for t in statics[-1].transforms} == {
        "b/r0/odom", "b/r0/base_scan", "c/r0/odom", "c/r0/base_scan",
    }  # fmt: skip


def test_the_heading_is_the_last_move_in_the_pose_and_the_transform():
    sent = []
    translate = RunTranslator(sent.append, Ros2Config())
    translate(_update("r", "observed_map", MapMessage(0, "observed", _codes())))
    cells = [(5, 5), (5, 5), (5, 7), (5, 7), (3, 7), (4, 6)]
    for t, cell in enumerate(cells):
        translate(_update("r", "pose", PoseMessage(t, cell)))
    expected = [0.0, 0.0, 0.0, 0.0, math.pi / 2, -3 * math.pi / 4]  # still, right, up, down-left
    poses = [o.message for o in sent if o.topic.endswith("/pose")]
    tfs = [o.message.transforms[0] for o in sent if o.topic == "/tf"]
    for pose, tf, yaw, cell in zip(poses, tfs, expected, cells, strict=True):
        assert _same_angle(_yaw(pose.pose.orientation), yaw)
        assert _same_angle(_yaw(tf.transform.rotation), yaw)
        assert (tf.header.frame_id, tf.child_frame_id) == ("r/r0/odom", "r/r0/base_link")
        centre = MapFrame(8, 12, Ros2Config().default_resolution_m).cell_xy_m(np.array(cell))[0]
        assert (tf.transform.translation.x, tf.transform.translation.y) == pytest.approx(
            tuple(centre)
        )


def test_scans_land_on_their_hit_cells_through_the_tf_chain_whatever_comes_first():
    """A robot's pose and scan of one step come on two keys, in either order: the scan is
    turned by the same heading as the transform of that step."""
    occupancy, config = _room(), SensorConfig(n_rays=360, range_cells=15)
    frame = MapFrame(*occupancy.shape, 0.05)
    sent = []
    translate = RunTranslator(sent.append, Ros2Config())
    info = WorldInfo("w", occupancy.shape, 0.05, np.array([[15, 12]]), 360, 15, 3)
    translate(Update("r", None, "world_info", info))
    replies = {}
    for t, cell in enumerate([(15, 12), (15, 12), (13, 14), (13, 14), (16, 11)]):
        replies[t] = ScanReply.from_scan(cast_scan(occupancy, cell, config), t)
        updates = [_update("r", "pose", PoseMessage(t, cell)), _update("r", "scan", replies[t])]
        for update in updates[:: 1 if t % 2 else -1]:
            translate(update)
    tree = TfTree()
    for outgoing in sent:
        if outgoing.topic.startswith("/tf"):
            tree.add(outgoing.topic, outgoing.message)
    scans = [o for o in sent if o.topic == "/mapex/r/r0/scan"]
    assert len(scans) == 5 and all(o.ros_type == ros.SCAN_TYPE for o in scans)
    for outgoing in scans:
        scan = ros.deserialize(ros.serialize(outgoing.message), ros.SCAN_TYPE)
        assert scan.header.frame_id == "r/r0/base_scan"
        _check_scan(scan, tree, replies[_stamp_ns(scan.header) // NS_PER_S], frame, 15)
    headings = [tree.in_map("r/r0/base_scan", t * NS_PER_S)[2] for t in range(5)]
    for heading, yaw in zip(
        headings, [0, 0, math.pi / 4, math.pi / 4, -3 * math.pi / 4], strict=True
    ):
        assert _same_angle(heading, yaw)


def test_frontiers_and_the_goal_become_markers_and_the_variance_a_grid():
    sent = []
    translate = RunTranslator(sent.append, Ros2Config())
    translate(_update("r", "observed_map", MapMessage(2, "observed", _codes())))
    cells, scores = np.array([[3, 3], [4, 5], [2, 6]], np.int32), np.array([0.5, np.nan, 2.0])
    translate(_update("r", "frontiers", FrontiersMessage(2, cells, scores)))
    translate(
        _update("r", "frontiers", FrontiersMessage(3, np.zeros((0, 2), np.int32), np.zeros(0)))
    )
    translate(_update("r", "goal", GoalMessage(2, (4, 5))))
    translate(_update("r", "goal", GoalMessage(3, None)))
    variance = np.full((8, 12), 0.125)
    variance[0, 0] = 0.25
    translate(
        _update("r", "prediction/variance", MapMessage.from_probabilities(2, "variance", variance))
    )
    by_name = {}
    for outgoing in sent:
        by_name.setdefault(outgoing.topic.rsplit("/", 1)[1], []).append(outgoing)
    full, empty = (
        ros.deserialize(ros.serialize(o.message), ros.MARKERS_TYPE) for o in by_name["frontiers"]
    )
    (spheres,) = full.markers
    assert spheres.type == spheres.SPHERE_LIST and len(spheres.points) == len(cells)
    rgb = [(c.r, c.g, c.b) for c in spheres.colors]
    assert rgb[1] == pytest.approx(tuple(ros.SCORE_COLORMAP[0]), abs=1e-6)  # nan: lowest
    assert rgb[2] == pytest.approx(tuple(ros.SCORE_COLORMAP[-1]), abs=1e-6)  # highest
    assert [m.action for m in empty.markers] == [spheres.DELETE]
    goal, gone = (o.message.markers[0] for o in by_name["goal"])
    centre = MapFrame(8, 12, 0.1).cell_xy_m(np.array([4, 5]))[0]
    assert (goal.type, goal.pose.position.x, goal.pose.position.y) == (goal.SPHERE, *centre)
    assert gone.action == gone.DELETE
    (grid,) = by_name["prediction_variance"]
    values = ros.grid_values_in_map_order(grid.message)
    assert grid.latched and values[0, 0] == 100 and values[1, 1] == 50  # of 0.25


# ----------------------------------------------------------------------------- the bridge


def test_the_bridge_survives_malformed_keys_and_follows_a_new_run(ros_router, caplog):
    """A bridge thread follows runs published by hand: a run id that is not one and a
    payload that is not a map are dropped with a log line; a run after the first one gets
    its own topics; --bridge-keys puts the same CDR on the topic's own key."""
    hub = _ros_peer(ros_router)
    stop = threading.Event()
    config = zenoh.Config.from_json5(
        f'{{mode: "peer", connect: {{endpoints: ["{ros_router}"]}}, '
        'listen: {endpoints: ["tcp/127.0.0.1:0"]}, scouting: {multicast: {enabled: false}}}'
    )
    raw = []  # --bridge-keys: plain CDR on the topic's own key (zenoh-bridge-ros2dds)
    hub.declare_subscriber("mapex/run_b/r0/map", lambda s: raw.append(s.payload.to_bytes()))
    bridge = threading.Thread(
        target=ros2.main, args=(config,), kwargs={"stop": stop, "bridge_keys": True}
    )
    bridge.start()
    try:
        time.sleep(1.0)  # the bridge's subscribers reach the router
        hub.put("mapex/@v1/Not!A-Run/r0/observed_map", MapMessage(0, "observed", _codes()).encode())
        hub.put("mapex/@v1/run-a/r0/observed_map", b"not a map")
        for run, cols in (("run-a", 4), ("run-b", 9)):
            hub.put(f"mapex/@v1/{run}/r0/observed_map",
                    MapMessage(5, "observed", _codes(free_cols=cols)).encode())  # fmt: skip
            hub.put(f"mapex/@v1/{run}/r0/status", StatusMessage(5, "finished").encode())
        until(  # Zenoh orders samples per key only: either run's map may come first
            lambda: all(any(f"%mapex%{run}%r0%map/" in t for t in _ros_graph(hub))
                        for run in ("run_a", "run_b")),
            "both runs' map topics in the ROS graph", 10.0,
        )  # fmt: skip
        latest = []
        key = rmw.data_key(0, "/mapex/run_b/r0/map", ros.GRID_TYPE, GRID_HASH)
        late = declare_advanced_subscriber(
            hub, key, lambda s: latest.append(s.payload.to_bytes()),
            history=HistoryConfig(detect_late_publishers=True, max_samples=1),
        )  # fmt: skip
        until(lambda: latest, "run-b's latched map", 10.0)
        grid = ros.deserialize(latest[-1], ros.GRID_TYPE)
        expected = _expected_values(_codes(free_cols=9))
        assert np.array_equal(ros.grid_values_in_map_order(grid), expected)
        late.undeclare()
        assert raw and raw[-1] == latest[-1]  # the same CDR bytes on the bridge key
    finally:
        stop.set()
        bridge.join(20)
        hub.close()
    said = caplog.text
    assert "Not!A-Run" in said and "dropped" in said  # the bad run id, one line
    assert "run-a/r0/observed_map" in said  # the payload that is not a map


def _peer_config(endpoint: str) -> zenoh.Config:
    return zenoh.Config.from_json5(
        f'{{mode: "peer", connect: {{endpoints: ["{endpoint}"]}}, '
        'listen: {endpoints: ["tcp/127.0.0.1:0"]}, scouting: {multicast: {enabled: false}}}'
    )


def _topic_of_key(key: str) -> tuple[str, str] | None:
    """(ROS topic, ROS type) of an rmw_zenoh data key; None for any other key."""
    parts = key.split("/")
    if len(parts) < 4 or "::dds_::" not in parts[-2] or not parts[-1].startswith("RIHS01_"):
        return None
    package, kind, _, name = parts[-2].split("::")
    return "/" + "/".join(parts[1:-2]), f"{package}/{kind}/{name[:-1]}"


def _graph_of(session: zenoh.Session, domain: int, at_least: int = 0) -> dict[str, str] | None:
    """ROS topic -> its publisher's liveliness token, in one domain (None: fewer than
    `at_least` topics)."""
    replies = session.liveliness().get(f"@ros2_lv/{domain}/**", timeout=2.0)
    tokens = [str(reply.ok.key_expr) for reply in replies if reply.ok is not None]
    graph = {t.split("/")[9].replace("%", "/"): t for t in tokens if "/MP/" in t}
    return graph if len(graph) >= at_least else None


def _expected_token_tail(topic: str, spec, config: Ros2Config) -> str:
    depth = spec.depth or (config.latched_depth if spec.latched else config.volatile_depth)
    qos = rmw.qos_text(spec.latched, depth, spec.reliable)
    return f"/{rmw.dds_type_name(spec.ros_type)}/{ros.type_hash(spec.ros_type)}/{qos}"


def _latched_sample(session: zenoh.Session, domain: int, topic: str, ros_type: str):
    """What a transient-local subscriber joining now gets on `topic` (RViz2 joining late)."""
    got = []
    key = rmw.data_key(domain, topic, ros_type, ros.type_hash(ros_type))
    subscriber = declare_advanced_subscriber(
        session, key, lambda s: got.append(s.payload.to_bytes()),
        history=HistoryConfig(detect_late_publishers=True, max_samples=1),
        subscriber_detection=True,
    )  # fmt: skip
    try:
        until(lambda: got, f"the latched {topic}", 10.0)
    finally:
        subscriber.undeclare()
    return ros.deserialize(got[-1], ros_type)


class HubLog:
    """The run's own messages on the hub, by (robot, topic) and step."""

    def __init__(self) -> None:
        self.by_step: dict[tuple[str, str], dict[int, object]] = {}

    def __call__(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        message = decode_message(sample.payload.to_bytes())
        self.by_step.setdefault((parts[3], "/".join(parts[4:])), {})[message.t] = message

    def of(self, robot: str, topic: str) -> dict[int, object]:
        return self.by_step.get((robot, topic), {})


HUB_TOPICS = ("pose", "scan", "frontiers", "goal", "path", "observed_map", "prediction/variance")
SOURCE_OF = {  # ROS topic name -> the run's topic its messages come from
    "map": "observed_map", "prediction_variance": "prediction/variance", "pose": "pose",
    "scan": "scan", "plan": "path", "frontiers": "frontiers", "goal": "goal",
}  # fmt: skip


@pytest.mark.slow
def test_a_team_run_through_up_in_ros_2(ros_router, tmp_path):
    """services.up --ros2 runs a team of two through the stand-in rmw_zenohd (domain 0,
    the bridge ends with the run) while a standalone bridge follows the same run in domain
    1. Every topic of both robots is published with its type, samples carry the 33-byte
    attachment with rmw_zenoh's gid of their publisher, every stamp is the simulated time
    of its step, /clock only moves forward, the TF tree map -> odom -> base_link ->
    base_scan of each robot puts base_link on the pose's cell centre heading the way the
    robot last moved, every LaserScan range ends on its hit cell, a marker per frontier,
    the variance grid on its 0.25 scale, a map subscriber joining mid-run gets the map at
    once, and after the run a late subscriber gets the latched plan, trajectory and
    /tf_static from the standalone bridge; the --record file holds the same topics."""
    run, hub = "rosteam-0", f"tcp/127.0.0.1:{free_loopback_port()}"
    record = tmp_path / "run.mcap"
    ros_peer = _ros_peer(ros_router)
    samples = []  # domain 0, as they come: (key, payload, attachment)
    ros_peer.declare_subscriber(
        "0/**", lambda s: samples.append((str(s.key_expr), s.payload.to_bytes(),
                                          s.attachment.to_bytes() if s.attachment else b""))
    )  # fmt: skip
    stop = threading.Event()
    standalone = threading.Thread(
        target=ros2.main, args=(_peer_config(hub), run, ros_router),
        kwargs={"stop": stop, "ros2": Ros2Config(domain_id=1)},
    )  # fmt: skip
    standalone.start()
    up_process = UpProcess(
        tmp_path / "up.log", "--robots", "2", "--method", "mapex_team", "--steps",
        str(TEAM_STEPS), "--run-prefix", "rosteam", "--ros2", "--ros-connect", ros_router,
        "--record", str(record), "--listen", hub, "--out", str(tmp_path / "results"),
    )  # fmt: skip
    hub_peer, hub_log = _session("peer", [], [hub]), HubLog()
    try:
        for topic in HUB_TOPICS:
            hub_peer.declare_subscriber(f"mapex/@v1/{run}/*/{topic}", hub_log)
        info = until(lambda: [r.ok for r in hub_peer.get(f"mapex/@v1/{run}/world_info", timeout=2.0)
                              if r.ok is not None], "the run's world info", 300.0)  # fmt: skip
        info = decode_message(info[0].payload.to_bytes(), (WorldInfo,))
        graph = until(  # while the run goes on: the bridge of up ends with it
            lambda: _graph_of(ros_peer, 0, at_least=2 * len(ROBOT_TOPICS)), "the topics", 300.0
        )
        mid_run = _latched_sample(ros_peer, 0, "/mapex/rosteam_0/r0/map", ros.GRID_TYPE)
        assert up_process.wait() == 0, up_process.log()[-3000:]
        graph_1 = until(  # the standalone bridge may still be declaring on a loaded machine
            lambda: _graph_of(ros_peer, 1, at_least=2 * len(ROBOT_TOPICS)), "its topics", 60.0
        )
        late = {
            (robot, name): _latched_sample(ros_peer, 1, f"/mapex/rosteam_0/{robot}/{name}",
                                           ros.PATH_TYPE)
            for robot in ("r0", "r1") for name in ("plan", "trajectory")
        }  # fmt: skip
        late_static = _latched_sample(ros_peer, 1, "/tf_static", ros.TF_TYPE)
    finally:
        stop.set()
        standalone.join(20)
        up_process.kill()
        ros_peer.close()
        hub_peer.close()
    frame = MapFrame(*info.shape, info.resolution_m)
    config = Ros2Config()
    for robot in ("r0", "r1"):  # the graph: every topic with its type and QoS
        for name, spec in ROBOT_TOPICS.items():
            topic = f"/mapex/rosteam_0/{robot}/{name}"
            assert graph_1[topic].endswith(_expected_token_tail(topic, spec, config)), topic
    for topic, spec in GRAPH_TOPICS.items():
        assert graph_1[topic].endswith(_expected_token_tail(topic, spec, config)), topic
    received = _received(samples, graph)
    _check_stamps_and_clock(received, hub_log)
    tree = TfTree()
    for topic in ("/tf_static", "/tf"):
        for message in received[topic]:
            tree.add(topic, message)
    for robot in ("r0", "r1"):
        ns = f"rosteam_0/{robot}"
        _check_poses_and_transforms(
            received[f"/mapex/{ns}/pose"], tree, ns, hub_log.of(robot, "pose"), frame
        )
        scans = received[f"/mapex/{ns}/scan"]
        assert scans and all(s.header.frame_id == f"{ns}/base_scan" for s in scans)
        for scan in scans[:: max(1, len(scans) // 4)]:  # a few whole scans, ray by ray
            reply = hub_log.of(robot, "scan")[_stamp_ns(scan.header) // NS_PER_S]
            _check_scan(scan, tree, reply, frame, info.range_cells)
        _check_markers(received, ns, hub_log, robot, frame)
        variance = received[f"/mapex/{ns}/prediction_variance"][-1]
        source = hub_log.of(robot, "prediction/variance")[_stamp_ns(variance.header) // NS_PER_S]
        expected = np.clip(np.rint(source.map_u8 / 255 / 0.25 * 100), 0, 100)
        assert np.array_equal(ros.grid_values_in_map_order(variance), expected)
        final = hub_log.of(robot, "observed_map")[max(hub_log.of(robot, "observed_map"))].map_u8
        maps = received[f"/mapex/{ns}/map"]
        assert np.array_equal(ros.grid_values_in_map_order(maps[-1]), _expected_values(final))
        poses = hub_log.of(robot, "pose")
        cells = [tuple(poses[t].pose) for t in sorted(poses)]
        cells = [c for i, c in enumerate(cells) if i == 0 or c != cells[i - 1]]
        trajectory = [tuple(p) for p in _path_cells(late[robot, "trajectory"], frame)]
        # the hub log may join after the first steps, the latched trajectory lag the last ones
        shared = min(len(cells), len(trajectory))
        assert shared > 1 and (
            _contiguous_in(trajectory[-shared:], cells)
            or _contiguous_in(cells[-shared:], trajectory)
        )
        path = hub_log.of(robot, "path")
        assert np.array_equal(_path_cells(late[robot, "plan"], frame), path[max(path)].cells)
    assert {t.child_frame_id for t in late_static.transforms} == {
        f"rosteam_0/{r}/{name}" for r in ("r0", "r1") for name in ("odom", "base_scan")
    }
    assert mid_run.info.width == frame.cols
    _check_team_recording(record, hub_log)


def _contiguous_in(part: list, whole: list) -> bool:
    """Whether `part` is a run of consecutive items of `whole`."""
    return any(whole[i : i + len(part)] == part for i in range(len(whole) - len(part) + 1))


def _check_team_recording(record, hub_log: HubLog) -> None:
    """The --record bag of the team run passes rosbag2's checks and reads back whole with
    rosbags' AnyReader and with mcap_ros2: every topic of both robots and the graph's with
    its type, each message's log time its header stamp, t * 1 s of a step its source
    message carried."""
    assert rosbag2_play_problems(record) == []
    expected = {
        f"/mapex/rosteam_0/{robot}/{name}": spec.ros_type
        for robot in ("r0", "r1") for name, spec in ROBOT_TOPICS.items()
    }  # fmt: skip
    expected |= {topic: spec.ros_type for topic, spec in GRAPH_TOPICS.items()}
    with AnyReader([record]) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == expected
        decoded = [
            (c.topic, log_ns, reader.deserialize(data, c.msgtype))
            for c, log_ns, data in reader.messages()
        ]  # fmt: skip
    assert len(decoded) == sum(mcap_counts(record).values())
    for topic, log_ns, message in decoded:
        name = topic.rsplit("/", 1)[1]
        assert log_ns % NS_PER_S == 0, topic
        stamp = _recorded_stamp_ns(name, message)
        assert stamp in (None, log_ns), (topic, stamp, log_ns)
        if name in SOURCE_OF:
            assert log_ns // NS_PER_S in hub_log.of(topic.split("/")[3], SOURCE_OF[name]), topic
    for topic in expected:  # the same bytes through mcap_ros2's own decoder
        assert len(ros_messages_in(record, topic)) == sum(1 for d in decoded if d[0] == topic)


def _recorded_stamp_ns(name: str, message) -> int | None:
    """The sim-time stamp a recorded message carries (None: an empty marker array)."""
    if name == "clock":
        return message.clock.sec * NS_PER_S + message.clock.nanosec
    if name in ("tf", "tf_static"):
        return _stamp_ns(message.transforms[0].header)
    if name in ("frontiers", "goal"):
        return _stamp_ns(message.markers[0].header) if message.markers else None
    return _stamp_ns(message.header)


def _received(samples, graph: dict[str, str]) -> dict[str, list]:
    """The decoded messages of each topic, in order; every sample carries the attachment
    with its publisher's gid as rmw_zenoh makes it, and the type its key names."""
    received: dict[str, list] = {}
    specs = {**GRAPH_TOPICS, **{f"/{n}": s for n, s in ROBOT_TOPICS.items()}}
    for key, payload, attachment in samples:
        if (parsed := _topic_of_key(key)) is None:
            continue
        topic, ros_type = parsed
        spec = specs.get(topic) or specs[f"/{topic.rsplit('/', 1)[1]}"]
        assert ros_type == spec.ros_type, topic
        sequence, _, gid = rmw.parse_attachment(attachment)
        assert sequence >= 1
        if topic in graph:
            assert gid == rmw.publisher_gid(graph[topic]), topic
        received.setdefault(topic, []).append(ros.deserialize(payload, ros_type))
    for robot in ("r0", "r1"):
        for name in ROBOT_TOPICS:
            assert received.get(f"/mapex/rosteam_0/{robot}/{name}"), (robot, name)
    return received


def _check_stamps_and_clock(received: dict[str, list], hub_log: HubLog) -> None:
    """Every stamp is t * 1 s of a step its source message carried; /clock only goes up,
    to the newest stamp."""
    newest = 0
    for topic, messages in received.items():
        name = topic.rsplit("/", 1)[1]
        for message in messages:
            header = (
                message.markers[0].header
                if name in ("frontiers", "goal")
                else getattr(message, "header", None)
            )
            if header is None:
                continue
            stamp = _stamp_ns(header)
            assert stamp % NS_PER_S == 0, topic
            newest = max(newest, stamp)
            if name in SOURCE_OF:
                robot = topic.split("/")[3]
                assert stamp // NS_PER_S in hub_log.of(robot, SOURCE_OF[name]), (topic, stamp)
    clocks = [c.clock.sec * NS_PER_S + c.clock.nanosec for c in received["/clock"]]
    assert clocks == sorted(set(clocks)) and clocks[-1] == newest


def _check_poses_and_transforms(poses, tree: TfTree, ns: str, world_poses, frame: MapFrame) -> None:
    """base_link sits on the world's pose of that step, heading the way the robot last
    moved (0 before it moved); the PoseStamped says the same."""
    yaw, previous, expected = 0.0, None, {}
    for t in sorted(world_poses):
        cell = tuple(world_poses[t].pose)
        if previous is not None and cell != previous:
            yaw = math.atan2(-(cell[0] - previous[0]), cell[1] - previous[1])
        expected[t], previous = (cell, yaw), cell
    for pose in poses:
        t = _stamp_ns(pose.header) // NS_PER_S
        cell, yaw = expected[t]
        centre = tuple(frame.cell_xy_m(np.array(cell))[0])
        assert (pose.pose.position.x, pose.pose.position.y) == pytest.approx(centre)
        assert _same_angle(_yaw(pose.pose.orientation), yaw)
        x, y, heading = tree.in_map(f"{ns}/base_link", t * NS_PER_S)
        assert (x, y) == pytest.approx(centre) and _same_angle(heading, yaw)


def _check_markers(received, ns: str, hub_log: HubLog, robot: str, frame: MapFrame) -> None:
    """A sphere per frontier of that step; the goal's sphere on its cell."""
    for array in received[f"/mapex/{ns}/frontiers"]:
        (marker,) = array.markers
        frontiers = hub_log.of(robot, "frontiers")[_stamp_ns(marker.header) // NS_PER_S]
        assert len(marker.points) == len(frontiers.cells)
        if len(frontiers.cells):
            xy = [(p.x, p.y) for p in marker.points]
            assert np.allclose(xy, frame.cell_xy_m(frontiers.cells))
    for array in received[f"/mapex/{ns}/goal"]:
        (marker,) = array.markers
        goal = hub_log.of(robot, "goal")[_stamp_ns(marker.header) // NS_PER_S].goal
        if goal is not None:
            centre = frame.cell_xy_m(np.array(goal))[0]
            assert (marker.pose.position.x, marker.pose.position.y) == pytest.approx(tuple(centre))


def _path_cells(path, frame: MapFrame) -> np.ndarray:
    """int (n, 2) (row, col) of a Path's cell centres."""
    xy = np.array([(p.pose.position.x, p.pose.position.y) for p in path.poses]).reshape(-1, 2)
    cols = np.floor(xy[:, 0] / frame.resolution_m)
    rows = frame.rows - 1 - np.floor(xy[:, 1] / frame.resolution_m)
    return np.stack([rows, cols], axis=1).astype(np.int64)


def test_a_ros_router_that_is_not_there_is_one_line_and_exit_2(capsys, tmp_path):
    """--ros-connect to an endpoint where nothing listens: one line before anything starts
    (services.ros2, and services.up --ros2 before any child)."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    assert ros2.run_cli(["--ros-connect", endpoint]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"nothing answers at --ros-connect {endpoint}" in line and "rmw_zenohd" in line
    argv = ["--ros2", "--ros-connect", endpoint, "--steps", "1", "--out", str(tmp_path)]
    assert up.run_cli(["--no-progress", *argv]) == 2
    said = capsys.readouterr().err.strip().splitlines()
    assert said[-1].startswith("services.up: error: nothing answers at --ros-connect")
    assert not any("started" in line for line in said)  # no child started


def test_cli_errors_are_one_line(capsys):
    for argv, text in ((["--run", "Bad Run"], "--run"), (["--domain", "300"], "--domain")):
        with pytest.raises(SystemExit) as stopped:
            ros2.run_cli(argv)
        assert stopped.value.code == 2
        assert text in capsys.readouterr().err
