"""The ROS 2 bridge (services.ros2) and the run translation it shares with the recorder.

No ROS install here: a router-mode Zenoh session on a loopback port stands in for
rmw_zenohd, and the test plays the parts of `ros2 topic list` (a liveliness query on
`@ros2_lv/0/**`), of a volatile subscriber and of RViz2's transient-local map subscriber
(a zenoh-ext advanced subscriber with rmw_zenoh's options), decoding with rosbags and
mcap_ros2.
"""

from __future__ import annotations

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
from service_processes import free_loopback_port, until  # noqa: E402
from up_processes import UpProcess  # noqa: E402
from zenoh.ext import HistoryConfig, declare_advanced_subscriber  # noqa: E402

from mapex.grid import FREE, OCCUPIED, UNKNOWN  # noqa: E402
from mapex.interop import rmw_zenoh as rmw  # noqa: E402
from mapex.interop import ros_messages as ros  # noqa: E402
from services.bridges import ros2  # noqa: E402
from services.bridges.follow import Update  # noqa: E402
from services.bridges.ros_translate import RunTranslator  # noqa: E402
from services.config import Ros2Config  # noqa: E402
from services.messages import (  # noqa: E402  # noqa: E402
    MapMessage,
    PathMessage,
    PoseMessage,
    StatusMessage,
    WorldInfo,
    decode_message,
)

GRID_HASH = "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"
TOPIC_NAMES = ("map", "prediction_mean", "pose", "plan", "trajectory")


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
        "/mapex/run_a/r0/map", "/mapex/run_a/r0/pose", "/mapex/run_a/r0/trajectory",
        "/mapex/run_a/r0/plan",
    ]  # fmt: skip
    grid = sent[0].message
    assert grid.info.resolution == pytest.approx(0.05) and sent[0].latched
    assert np.array_equal(ros.grid_values_in_map_order(grid), _expected_values(_codes()))
    assert sent[1].message.pose.position.x == pytest.approx(3.5 * 0.05)


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
    names = [o.topic.rsplit("/", 1)[1] for o in sent]
    assert names == ["map", "pose", "trajectory", "plan"][frame_from == "world_info" :]
    pose = next(o for o in sent if o.topic.endswith("/pose")).message
    resolution_m = 0.05 if frame_from == "world_info" else Ros2Config().default_resolution_m
    assert pose.pose.position.x == pytest.approx(3.5 * resolution_m)


def test_held_updates_are_kept_for_the_newest_runs_only():
    sent = []
    translate = RunTranslator(sent.append, Ros2Config(max_runs=2))
    for run in ("a", "b", "c"):
        translate(_update(run, "pose", PoseMessage(0, (2, 2))))
    translate(_update("a", "observed_map", MapMessage(0, "observed", _codes())))
    assert [o.topic for o in sent] == ["/mapex/a/r0/map"]  # a's pose went with the cap


def test_the_trajectory_goes_out_now_and_then_and_whole_at_the_end():
    sent = []
    translate = RunTranslator(sent.append, Ros2Config(trajectory_period_s=3600.0))
    translate(_update("r", "observed_map", MapMessage(0, "observed", _codes())))
    for t, cell in enumerate([(3, 3), (3, 4), (3, 5)], start=1):
        translate(_update("r", "pose", PoseMessage(t, cell)))
    translate(_update("r", "status", StatusMessage(3, "finished")))
    names = [o.topic.rsplit("/", 1)[1] for o in sent]
    assert names == ["map", "pose", "trajectory", "pose", "pose", "trajectory"]
    assert len(sent[-1].message.poses) == 3  # every pose, though sent once in between


def test_only_the_newest_runs_keep_their_topics():
    forgotten = []
    translate = RunTranslator(lambda _: None, Ros2Config(max_runs=2), forgotten.append)
    for run in ("a", "b", "c"):
        translate(_update(run, "observed_map", MapMessage(0, "observed", _codes())))
    assert list(translate.runs) == ["b", "c"] and forgotten == ["/mapex/a/"]


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
        graph = until(
            lambda: [t for t in _ros_graph(hub) if "%mapex%run_b%r0%map/" in t],
            "run-b's map topic in the ROS graph", 10.0,
        )  # fmt: skip
        assert graph and any("%mapex%run_a%r0%map/" in t for t in _ros_graph(hub))
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


@pytest.mark.slow
def test_a_run_through_up_appears_in_the_ros_graph_and_its_maps_decode(ros_router, tmp_path):
    """services.up --ros2 with its own hub, the bridge publishing through the stand-in
    rmw_zenohd: the node and every topic are in the graph, map samples carry the 33-byte
    attachment and decode (rosbags and mcap_ros2) to the run's final observed map cell for
    cell, a transient-local subscriber joining mid-run gets the current map at once (the
    bridge of services.up ends with the run; the test above joins after the last put), and
    the --record file holds every topic and the same final map."""
    hub = f"tcp/127.0.0.1:{free_loopback_port()}"
    record = tmp_path / "run.mcap"
    up = UpProcess(
        tmp_path / "up.log", "--steps", "100", "--run-prefix", "rostest", "--ros2",
        "--ros-connect", ros_router, "--record", str(record), "--listen", hub,
        "--out", str(tmp_path / "results"),
    )  # fmt: skip
    ros_peer, hub_peer = _ros_peer(ros_router), _session("peer", [], [hub])
    observed, samples = {}, []
    key = rmw.data_key(0, "/mapex/rostest_0/r0/map", ros.GRID_TYPE, GRID_HASH)
    try:
        hub_peer.declare_subscriber(
            "mapex/@v1/rostest-0/r0/observed_map",
            lambda s: observed.update(
                {"last": decode_message(s.payload.to_bytes(), (MapMessage,))}
            ),
        )
        ros_peer.declare_subscriber(
            key, lambda s: samples.append((s.payload.to_bytes(), s.attachment.to_bytes()))
        )
        until(lambda: len(samples) >= 2, "the bridge's first maps", 300.0)
        graph = until(  # while the run goes on: the bridge ends with it
            lambda: _bridge_tokens(_ros_graph(ros_peer)), "the node and its 5 topics", 20.0
        )
        late = []
        subscriber = declare_advanced_subscriber(
            ros_peer, key, lambda s: late.append(s.payload.to_bytes()),
            history=HistoryConfig(detect_late_publishers=True, max_samples=1),
            subscriber_detection=True,
        )  # fmt: skip
        until(lambda: late, "the latched map for a subscriber joining mid-run", 10.0)
        subscriber.undeclare()
        assert up.wait() == 0, up.log()[-3000:]
        final = observed[max(observed)].map_u8
    finally:
        up.kill()
        ros_peer.close()
        hub_peer.close()
    assert any(t.endswith("/NN/%/%/mapex_bridge") for t in graph), graph
    for name in TOPIC_NAMES:
        assert any(f"/MP/%/%/mapex_bridge/%mapex%rostest_0%r0%{name}/" in t for t in graph), name
    assert samples and all(len(attachment) == 33 for _, attachment in samples)
    sequences = [rmw.parse_attachment(attachment)[0] for _, attachment in samples]
    assert sequences == sorted(sequences) and sequences[0] >= 1
    expected = _expected_values(final)
    grid = ros.deserialize(samples[-1][0], ros.GRID_TYPE)
    assert np.array_equal(ros.grid_values_in_map_order(grid), expected)
    decoded = _mcap_ros2_decode(samples[-1][0], ros.GRID_TYPE)
    values = np.flipud(np.asarray(decoded.data, np.int8).reshape(decoded.info.height, -1))
    assert np.array_equal(values, expected)
    assert ros.deserialize(late[0], ros.GRID_TYPE).info.width == expected.shape[1]
    _check_recording(record, "rostest_0", expected)


def _bridge_tokens(graph: list[str]) -> list[str]:
    """The bridge's tokens once its node and all five topics of robot r0 are there."""
    mine = [t for t in graph if "/mapex_bridge" in t]
    return mine if len(mine) == 1 + len(TOPIC_NAMES) else []


def _keep_by_step(maps: dict[int, MapMessage], message: MapMessage) -> None:
    maps[message.t] = message


def _check_recording(path, run: str, final_values: np.ndarray) -> None:
    counts = mcap_counts(path)
    for name in TOPIC_NAMES:
        assert counts[f"/mapex/{run}/r0/{name}"] > 0, name
        assert counts[f"/foxglove/mapex/{run}/r0/{name}"] == counts[f"/mapex/{run}/r0/{name}"]
    maps = ros_messages_in(path, f"/mapex/{run}/r0/map")
    assert len(maps) == counts[f"/mapex/{run}/r0/map"]
    values = np.flipud(np.asarray(maps[-1].data, np.int8).reshape(maps[-1].info.height, -1))
    assert np.array_equal(values, final_values)


def test_cli_errors_are_one_line(capsys):
    for argv, text in ((["--run", "Bad Run"], "--run"), (["--domain", "300"], "--domain")):
        with pytest.raises(SystemExit) as stopped:
            ros2.run_cli(argv)
        assert stopped.value.code == 2
        assert text in capsys.readouterr().err
