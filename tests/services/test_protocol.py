"""Keys, message round trips and the rejection of every kind of malformed payload."""

from __future__ import annotations

import dataclasses
import math
import zlib

import msgpack
import numpy as np
import pytest

from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.sensor import Scan
from mapex.worlds.base import World
from services.codec import (
    ProtocolError,
    count_objects,
    dequantise_probability,
    encode_array,
    quantise_probability,
)
from services.config import ServicesConfig
from services.messages import (
    CLAIM_FIELDS,
    STEP_REPLY_ARRAYS,
    StepReply,
    map_message_bytes,
    step_key,
)
from services.protocol import (
    ROBOT_TOPICS,
    AliveKey,
    ErrorReply,
    FrontiersMessage,
    GoalMessage,
    GroundTruth,
    HealthKey,
    MapMessage,
    Message,
    MetricsMessage,
    PathMessage,
    PoseMessage,
    PredictKey,
    PredictReply,
    PredictRequest,
    RobotKey,
    RunKey,
    ScanReply,
    StatusMessage,
    StepRequest,
    WorldInfo,
    alive_planner_key,
    alive_predictor_key,
    alive_predictor_pattern,
    alive_world_key,
    decode_message,
    health_key,
    parse_key,
    predict_key,
    robot_key,
    robot_key_pattern,
    run_key,
)

# ------------------------------------------------------------------------------------ keys


@pytest.mark.parametrize(
    "key, expected, parsed",
    [
        (
            robot_key("run_1", "r0", "observed_map"),
            "mapex/@v1/run_1/r0/observed_map",
            RobotKey("run_1", "r0", "observed_map"),
        ),
        (
            robot_key("run-2", "robot_a", "prediction/variance"),
            "mapex/@v1/run-2/robot_a/prediction/variance",
            RobotKey("run-2", "robot_a", "prediction/variance"),
        ),
        (
            run_key("run_1", "ground_truth"),
            "mapex/@v1/run_1/ground_truth",
            RunKey("run_1", "ground_truth"),
        ),
        (run_key("x", "world_info"), "mapex/@v1/x/world_info", RunKey("x", "world_info")),
        (predict_key("g2", "w-7"), "mapex/@v1/predict/g2/w-7", PredictKey("g2", "w-7")),
        (health_key("g1", "w-7"), "mapex/@v1/health/g1/w-7", HealthKey("g1", "w-7")),
        (
            alive_predictor_key("g", "host1_3"),
            "mapex/@v1/alive/predict/g/host1_3",
            AliveKey("predict", member="g", worker_id="host1_3"),
        ),
        (alive_world_key("r"), "mapex/@v1/alive/world/r", AliveKey("world", run="r")),
        (
            alive_planner_key("r", "r1"),
            "mapex/@v1/alive/planner/r/r1",
            AliveKey("planner", run="r", robot="r1"),
        ),
    ],
)
def test_keys_are_built_and_parsed_back(key, expected, parsed):
    assert key == expected
    assert parse_key(key) == parsed


@pytest.mark.parametrize("topic", ROBOT_TOPICS)
def test_every_robot_topic_round_trips(topic):
    assert parse_key(robot_key("run", "robot", topic)) == RobotKey("run", "robot", topic)


def test_wildcard_patterns():
    assert robot_key_pattern("observed_map", run="r1") == "mapex/@v1/r1/*/observed_map"
    assert robot_key_pattern("prediction/mean") == "mapex/@v1/*/*/prediction/mean"
    assert robot_key_pattern("goal", run="r", robot="b") == robot_key("r", "b", "goal")
    assert alive_predictor_pattern() == "mapex/@v1/alive/predict/*/*"
    assert alive_predictor_pattern("g3") == "mapex/@v1/alive/predict/g3/*"


@pytest.mark.parametrize(
    "bad_id",
    ["", "Run", "a/b", "a*", "$x", "@v1", "a b", "a.b", "x" * 65, 7, None],
)
@pytest.mark.parametrize(
    "build",
    [
        lambda i: robot_key(i, "r0", "pose"),
        lambda i: robot_key("run", i, "pose"),
        lambda i: run_key(i, "ground_truth"),
        lambda i: predict_key("g", i),
        lambda i: alive_predictor_key("g1", i),
        lambda i: alive_world_key(i),
    ],
)
def test_bad_ids_are_one_line_value_errors(bad_id, build):
    with pytest.raises(ValueError, match="id") as info:
        build(bad_id)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "build",
    [
        lambda: robot_key("predict", "r0", "pose"),
        lambda: run_key("alive", "world_info"),
        lambda: run_key("health", "world_info"),
        lambda: robot_key("run", "r0", "nonsense"),
        lambda: run_key("run", "pose"),
        lambda: predict_key("g4", "w"),
        lambda: alive_predictor_pattern("G"),
        lambda: robot_key_pattern("pose", run="a/b"),
        lambda: robot_key_pattern("pose", robot="*"),
    ],
)
def test_reserved_runs_unknown_topics_and_members_are_refused(build):
    with pytest.raises(ValueError):
        build()


@pytest.mark.parametrize(
    "key",
    [
        "mapex/@v2/run/r0/pose",
        "other/@v1/run/r0/pose",
        "xmapex/@v1/run/r0/pose",
        "mapex/@v1/",
        "mapex/@v1/run",
        "mapex/@v1/run/r0/unknown",
        "mapex/@v1/run/r0/prediction/other",
        "mapex/@v1/run/*/pose",
        "mapex/@v1/Run/r0/pose",
        "mapex/@v1/predict/g9/w1",
        "mapex/@v1/predict/g/w1/extra",
        "mapex/@v1/alive/world/predict",
        "mapex/@v1/alive/predict/g/*",
        "mapex/@v1/alive/other/x",
        "mapex/@v1/alive/r0/pose",
    ],
)
def test_parse_key_rejects_foreign_keys(key):
    with pytest.raises(ProtocolError, match="not a MapEx v1 key") as info:
        parse_key(key)
    assert "\n" not in str(info.value)


# -------------------------------------------------------------------------------- messages


def step_request(seq, cells, done=False, claim=None, mac=None) -> StepRequest:
    """A step request that moves through `cells`, with a new claim (goal, score, claimed
    cells) when `claim` is given."""
    goal, score, visible = claim if claim is not None else (None, None, None)
    return StepRequest(seq, cells, done, claim is not None, goal, score, visible, mac)


def step_reply(seq, rng, robots=3, claims=(), shape=(6, 7), finished=False, rays=5) -> StepReply:
    """A step reply of `robots` robots (no scans when `finished`) whose robot i has claim
    state `claims[i]` (default none)."""
    scanned = 0 if finished else robots
    state = np.zeros(robots, np.uint8)
    state[: len(claims)] = claims
    made = int(np.count_nonzero(state == 1))
    return StepReply(
        seq, finished,
        rng.integers(0, 30, (scanned, 2)).astype(np.int32),
        rng.integers(1, 200, (scanned, rays)).astype(np.uint16),
        rng.random((scanned, rays)) < 0.5,
        np.arange(robots) % 2 == 1,
        state,
        rng.integers(0, 6, (robots, 2)).astype(np.int32),
        np.where(state == 1, rng.random(robots), 0.0),
        rng.random((made, *shape)) < 0.3,
        np.arange(robots) == robots - 1,
    )  # fmt: skip


def _sample_messages() -> list[Message]:
    rng = np.random.default_rng(7)
    observed = rng.integers(0, 3, size=(40, 50), dtype=np.uint8)
    cells = rng.integers(0, 200, size=(6, 2)).astype(np.int32)
    occupancy = rng.random((30, 20)) < 0.3
    claimed = rng.random((40, 50)) < 0.1
    return [
        step_request(4, cells[:3]),
        step_request(0, np.empty((0, 2), np.int32)),
        step_request(7, cells[:1], done=True).signed(step_key("s3cret", "run"), "run", 0),
        step_request(9, [], claim=((12, 30), 2.5, claimed), mac="0123456789abcdef" * 4),
        step_request(9, cells[:2], claim=((12, 30), -math.inf, claimed)),  # a last resort
        StepRequest(3, cells[:1], False, True, None, None, None),  # withdraws its claim
        step_reply(5, rng, claims=(0, 1, 2), shape=(40, 50)),
        step_reply(6, rng, robots=2, finished=True),
        ScanReply(
            (12, 34),
            rng.integers(1, 400, 2500).astype(np.uint16),
            rng.random(2500) < 0.5,
        ),
        PoseMessage(5, (3, 4)),
        PredictRequest(42, observed),
        PredictRequest(43, observed, 10.0, "ev-run_1", (120, 7), "oracle"),  # the oracle's
        PredictRequest(44, observed, None, None, None, "lama-v2"),
        PredictReply.from_probabilities(42, "g1", rng.random((40, 50)), "worker_0", 12.5),
        MapMessage(10, "observed", observed),
        MapMessage.from_probabilities(10, "variance", rng.random((40, 50)) * 0.3),
        FrontiersMessage(3, cells, rng.random(6) * 100),
        GoalMessage(3, (7, 8)),
        GoalMessage(4, None),
        PathMessage(3, cells),
        MetricsMessage(50, 0.25, 0.5, 0.75, False),
        MetricsMessage(150, 1.0, 0.0, None, True),
        StatusMessage(0, "running", "step 0 of 1000"),
        WorldInfo("generated_3", (30, 20), 0.1, cells[:2] % 20),
        WorldInfo("generated_3", (30, 20), 0.1, cells[:2] % 20, 2500, 200, 3),
        GroundTruth(occupancy, ~occupancy),
        ErrorReply("predictor busy"),
    ]


def _assert_same(decoded: Message, original: Message) -> None:
    assert type(decoded) is type(original)
    for field in dataclasses.fields(original):
        got, want = getattr(decoded, field.name), getattr(original, field.name)
        if isinstance(want, np.ndarray):
            assert got.dtype == want.dtype and got.shape == want.shape, field.name
            np.testing.assert_array_equal(got, want)
        else:
            assert got == want, field.name


@pytest.mark.parametrize("message", _sample_messages(), ids=lambda m: m.TYPE)
def test_every_message_round_trips(message):
    payload = message.encode()
    assert isinstance(payload, bytes)
    _assert_same(type(message).decode(payload), message)
    _assert_same(decode_message(payload), message)
    _assert_same(decode_message(memoryview(payload)), message)


def test_scan_reply_converts_to_and_from_a_sensor_scan():
    scan = Scan((5, 6), np.array([1, 4, 9], np.uint16), np.array([True, False, True]))
    back = ScanReply.decode(ScanReply.from_scan(scan).encode()).to_scan()
    assert back.pose == scan.pose
    np.testing.assert_array_equal(back.n_cells, scan.n_cells)
    np.testing.assert_array_equal(back.hit, scan.hit)


def test_a_scan_reply_carries_its_step_and_one_without_it_still_decodes():
    scan = Scan((5, 6), np.array([1, 4], np.uint16), np.array([True, False]))
    assert ScanReply.decode(ScanReply.from_scan(scan, 7).encode()).t == 7
    assert ScanReply.decode(ScanReply.from_scan(scan).encode()).t is None  # an older world's
    with pytest.raises(ProtocolError, match="t"):
        ScanReply.from_scan(scan, -1)


def test_a_predict_request_names_run_origin_and_predictor_only_when_set():
    """Fields added later travel only when set, so a request of the default predictor is
    what workers older than them read, and a request without them (an older planner's)
    still decodes, naming none."""
    plain = PredictRequest(1, _OBSERVED, 5.0)
    assert set(msgpack.unpackb(plain.encode())) == {
        "schema", "type", "request_id", "observed", "budget_s",
    }  # fmt: skip
    oracle = PredictRequest(2, _OBSERVED, 5.0, "run-a", (3, 4), "oracle")
    assert {"run", "origin", "predictor"} <= set(msgpack.unpackb(oracle.encode()))
    old = {"schema": 1, "type": "predict_request", "request_id": 3,
           "observed": encode_array(_OBSERVED)}  # fmt: skip
    decoded = PredictRequest.decode(msgpack.packb(old, use_bin_type=True))
    assert (decoded.budget_s, decoded.run, decoded.origin, decoded.predictor) == (None,) * 4


def test_ground_truth_converts_to_and_from_a_world():
    occupancy = np.zeros((6, 7), bool)
    occupancy[0] = True
    world = World("tiny", occupancy, ~occupancy)
    back = GroundTruth.decode(GroundTruth.from_world(world).encode()).to_world("tiny", 0.1)
    np.testing.assert_array_equal(back.occupancy, world.occupancy)
    np.testing.assert_array_equal(back.valid_space, world.valid_space)


def test_a_claim_scored_minus_infinity_travels_nan_and_plus_infinity_do_not():
    """nearest_team rules out frontiers near a teammate's goal with -inf and still takes one
    when nothing else is left: that claim travels; NaN and +inf scores are refused."""
    visible = np.zeros((4, 5), dtype=bool)
    payload = step_request(1, [], claim=((2, 3), -math.inf, visible)).encode()
    assert StepRequest.decode(payload).claim_score == -math.inf
    for bad in (math.nan, math.inf):
        with pytest.raises(ProtocolError, match="claim_score"):
            step_request(1, [], claim=((2, 3), bad, visible))


def test_claimed_cells_travel_for_new_claims_only_in_robot_order():
    """A reply carries one claimed-cells map per new claim: the second robot's claim is the
    first row when the first robot made none (withdrawn claims carry none)."""
    reply = step_reply(3, np.random.default_rng(1), claims=(0, 1, 2), shape=(6, 7))
    decoded = StepReply.decode(reply.encode())
    assert decoded.claim_visible.shape == (1, 6, 7)
    np.testing.assert_array_equal(decoded.visible_of(1), reply.claim_visible[0])
    assert list(decoded.claim_state) == [0, 1, 2]


def test_a_finished_reply_carries_no_scans_but_every_robot_s_flags():
    reply = StepReply.decode(step_reply(8, np.random.default_rng(2), finished=True).encode())
    assert reply.finished and reply.poses.shape == (0, 2) and reply.n_cells.shape == (0, 5)
    assert len(reply.lost) == len(reply.stood_still) == len(reply.claim_state) == 3
    assert {name for name, _, _ in STEP_REPLY_ARRAYS} >= set(CLAIM_FIELDS)


def test_world_info_says_the_world_s_settings_and_older_worlds_say_none():
    info = WorldInfo("w", (5, 5), 0.1, [[1, 1]], 90, 40, 2)
    assert WorldInfo.decode(info.encode()).settings() == {
        "n_rays": 90, "range_cells": 40, "cells_per_step": 2,
    }  # fmt: skip
    older = msgpack.unpackb(info.encode())
    for name in ("n_rays", "range_cells", "cells_per_step"):
        del older[name]  # a world from before the settings were shared
    assert set(WorldInfo.decode(msgpack.packb(older)).settings().values()) == {None}
    as_floats = msgpack.unpackb(info.encode())
    as_floats["n_rays"] = 90.0  # a whole number sent as a float is still that count
    assert WorldInfo.decode(msgpack.packb(as_floats)).n_rays == 90


def test_decode_message_honours_expected_types():
    payload = ErrorReply("no").encode()
    assert decode_message(payload, expected=(PredictReply, ErrorReply)) == ErrorReply("no")
    with pytest.raises(ProtocolError, match="expected a message of type predict_reply"):
        decode_message(payload, expected=(PredictReply,))


def test_error_reply_text_is_made_one_line():
    assert ErrorReply("bad\n  input\tshape").message == "bad input shape"


def test_cells_given_as_python_lists_become_int32():
    assert step_request(1, [[1, 2], [3, 4]]).cells.dtype == np.int32
    assert step_request(0, []).cells.shape == (0, 2)


def test_quantisation_error_is_at_most_half_a_level():
    rng = np.random.default_rng(0)
    edges = (np.arange(255, dtype=np.float32) + np.float32(0.5)) / np.float32(255)
    probability = np.concatenate([rng.random(10_000, dtype=np.float32), edges, [0.0, 1.0]])
    back = dequantise_probability(quantise_probability(probability))
    assert back.dtype == np.float32
    assert np.abs(back - probability).max() <= 1 / 510 + 1e-6  # float32 rounding of q / 255
    np.testing.assert_array_equal(quantise_probability(np.array([0.0, 1.0])), [0, 255])


@pytest.mark.parametrize("bad", [[-0.01], [1.01], [np.nan], [np.inf]])
def test_quantisation_refuses_values_outside_the_unit_interval(bad):
    with pytest.raises(ValueError, match="within"):
        quantise_probability(np.array(bad))


def test_arrays_are_compressed_only_above_the_threshold():
    config = ServicesConfig(compress_threshold_bytes=1000)
    assert not encode_array(np.zeros(1000, np.uint8), config)["zlib"]
    big = encode_array(np.zeros(1001, np.uint8), config)
    assert big["zlib"] and len(big["data"]) < 100
    noise = np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8)
    assert not encode_array(noise, config)["zlib"]  # incompressible: sent raw
    message = MapMessage(0, "observed", np.full((100, 100), UNKNOWN, np.uint8))
    payload = message.encode(config)
    assert len(payload) < 200
    _assert_same(MapMessage.decode(payload, config), message)


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "int16", "int32", "int64", "float32"])
def test_arrays_keep_their_dtype_and_byte_order(dtype):
    from services.codec import unpack_message

    values = np.arange(-3, 9).reshape(3, 4).astype(np.dtype(dtype).newbyteorder(">"))
    wire = {"a": encode_array(values)}
    payload = msgpack.packb({"schema": 1, "type": "t", **wire}, use_bin_type=True)
    decoded = unpack_message(payload).array("a", dtype, 2)
    assert decoded.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(decoded, values)


def test_unsendable_dtypes_are_refused_on_encoding():
    with pytest.raises(ProtocolError, match="not sendable"):
        encode_array(np.zeros(3, np.complex64))


# ------------------------------------------------------------------------ malformed inputs

_OBSERVED = np.array([[FREE, UNKNOWN], [OCCUPIED, UNKNOWN]], np.uint8)


def _map_document(**changes) -> dict:
    document = msgpack.unpackb(MapMessage(3, "observed", _OBSERVED).encode())
    document.update(changes)
    return {k: v for k, v in document.items() if v is not _DROP}


def _array_wire(**changes) -> dict:
    wire = {"dtype": "uint8", "shape": [2, 2], "zlib": False, "data": _OBSERVED.tobytes()}
    wire.update(changes)
    return {k: v for k, v in wire.items() if v is not _DROP}


def _zlib_wire(raw: bytes, shape: list[int], tail: bytes = b"") -> dict:
    return _array_wire(shape=shape, zlib=True, data=zlib.compress(raw) + tail)


_DROP = object()
_BOMB = _zlib_wire(bytes(16 * 2**20), [2, 2])  # 16 MiB of zeros behind a 4-byte shape
_CASES = {
    "not a map": (msgpack.packb([1, 2, 3]), "not a map"),
    "nil": (msgpack.packb(None), "not a map"),
    "no schema": (_map_document(schema=_DROP), "schema version"),
    "schema 2": (_map_document(schema=2), "schema version 2"),
    "schema as text": (_map_document(schema="1"), "schema version"),
    "schema as bool": (_map_document(schema=True), "schema version"),
    "no type": (_map_document(type=_DROP), "message type"),
    "type not a string": (_map_document(type=5), "message type"),
    "unknown type": (_map_document(type="teleport"), "unknown message type|got type 'teleport'"),
    "missing field": (_map_document(t=_DROP), "missing field 't'"),
    "extra field": (_map_document(colour="red"), "unexpected fields"),
    "t as text": (_map_document(t="3"), "'t' must be an integer"),
    "t as bool": (_map_document(t=True), "'t' must be an integer"),
    "t as float": (_map_document(t=3.0), "'t' must be an integer"),
    "negative t": (_map_document(t=-1), "non-negative"),
    "unknown kind": (_map_document(kind="heat"), "kind"),
    "array not a map": (_map_document(map_u8=b"\x00" * 4), "array map"),
    "array extra key": (_map_document(map_u8=_array_wire(order="C")), "array map"),
    "array missing key": (_map_document(map_u8=_array_wire(zlib=_DROP)), "array map"),
    "wrong dtype": (
        _map_document(map_u8=_array_wire(dtype="float64", data=bytes(32))),
        "must be uint8",
    ),
    "unknown dtype": (_map_document(map_u8=_array_wire(dtype="object")), "must be uint8"),
    "wrong rank": (_map_document(map_u8=_array_wire(shape=[4])), "shape of 2"),
    "negative shape": (_map_document(map_u8=_array_wire(shape=[-2, -2])), "shape of 2"),
    "shape of floats": (_map_document(map_u8=_array_wire(shape=[2.0, 2.0])), "shape of 2"),
    "data as text": (_map_document(map_u8=_array_wire(data="abcd")), "bytes 'data'"),
    "zlib flag as int": (_map_document(map_u8=_array_wire(zlib=0)), "boolean 'zlib'"),
    "short data": (_map_document(map_u8=_array_wire(data=b"\x00" * 3)), "need 4"),
    "long data": (_map_document(map_u8=_array_wire(data=b"\x00" * 5)), "need 4"),
    "short zlib data": (_map_document(map_u8=_zlib_wire(b"\x00" * 3, [2, 2])), "need 4"),
    "zlib bomb": (_map_document(map_u8=_BOMB), "decompresses to more"),
    "not zlib": (_map_document(map_u8=_array_wire(zlib=True, data=b"nonsense")), "zlib"),
    "truncated zlib": (
        _map_document(map_u8=_array_wire(zlib=True, data=zlib.compress(bytes(4))[:-3])),
        "truncated",
    ),
    "trailing zlib bytes": (
        _map_document(map_u8=_zlib_wire(bytes(4), [2, 2], tail=b"junk")),
        "trailing",
    ),
    "huge declared shape": (
        _map_document(map_u8=_zlib_wire(bytes(4), [2**20, 2**20])),
        "decoded-size limit",
    ),
    "bad observed code": (
        _map_document(map_u8=_array_wire(data=bytes([0, 1, 2, 3]))),
        "codes other than",
    ),
    "empty map": (_map_document(map_u8=_array_wire(shape=[0, 2], data=b"")), "empty"),
}


@pytest.mark.parametrize("document, message", list(_CASES.values()), ids=list(_CASES))
def test_malformed_payloads_raise_one_line_protocol_errors(document, message):
    payload = document if isinstance(document, bytes) else msgpack.packb(document)
    for decode in (MapMessage.decode, decode_message):
        with pytest.raises(ProtocolError, match=message) as info:
            decode(payload)
        assert "\n" not in str(info.value)


def _packed(message: Message, name: str, wire) -> bytes:
    document = msgpack.unpackb(message.encode())
    document[name] = wire
    return msgpack.packb(document)


def _renamed(message: Message, type_name: str) -> bytes:
    document = msgpack.unpackb(message.encode())
    document["type"] = type_name
    return msgpack.packb(document)


def _old_step_request() -> bytes:
    document = msgpack.unpackb(step_request(1, [[1, 2]]).encode())
    return msgpack.packb({k: document[k] for k in ("schema", "type", "seq", "cells")})


@pytest.mark.parametrize(
    "payload, decode, match",
    [
        (  # cells must be (k, 2)
            _packed(
                step_request(1, [[1, 2]]),
                "cells",
                {"dtype": "int32", "shape": [1, 3], "zlib": False, "data": bytes(12)},
            ),
            StepRequest.decode,
            r"\(k, 2\)",
        ),
        (  # the step sequence number is a non-negative integer on the wire too
            _packed(step_request(1, [[1, 2]]), "seq", -3),
            StepRequest.decode,
            "seq must be a non-negative",
        ),
        (
            _packed(step_request(1, [[1, 2]]), "seq", "1"),
            StepRequest.decode,
            "field 'seq' must be an integer",
        ),
        (  # cells must be int32 on the wire even though int64 would hold them
            _packed(
                PathMessage(0, [[1, 2]]),
                "cells",
                {"dtype": "int64", "shape": [1, 2], "zlib": False, "data": bytes(16)},
            ),
            PathMessage.decode,
            "must be int32",
        ),
        (  # the observed crop is 2-D
            _packed(
                PredictRequest(1, _OBSERVED),
                "observed",
                {"dtype": "uint8", "shape": [4], "zlib": False, "data": bytes(4)},
            ),
            PredictRequest.decode,
            "shape of 2",
        ),
        (  # bool arrays hold only 0 and 1
            _packed(
                GroundTruth(np.zeros((1, 2), bool), np.zeros((1, 2), bool)),
                "occupancy",
                {"dtype": "bool", "shape": [1, 2], "zlib": False, "data": b"\x00\x02"},
            ),
            GroundTruth.decode,
            "other than 0 and 1",
        ),
        (  # ground-truth maps of different shapes
            _packed(
                GroundTruth(np.zeros((1, 2), bool), np.zeros((1, 2), bool)),
                "occupancy",
                {"dtype": "bool", "shape": [2, 1], "zlib": False, "data": bytes(2)},
            ),
            GroundTruth.decode,
            "differ in shape",
        ),
        (  # one hit flag per ray
            _packed(
                ScanReply((1, 1), np.ones(3, np.uint16), np.ones(3, bool)),
                "hit",
                {"dtype": "bool", "shape": [2], "zlib": False, "data": bytes(2)},
            ),
            ScanReply.decode,
            "one length",
        ),
        (  # one score per frontier
            _packed(
                FrontiersMessage(0, [[1, 2]], np.ones(1)),
                "scores",
                {"dtype": "float64", "shape": [2], "zlib": False, "data": bytes(16)},
            ),
            FrontiersMessage.decode,
            "one score per",
        ),
        (
            _packed(PredictReply(1, "g", _OBSERVED, "w", 1.0), "member", "g7"),
            PredictReply.decode,
            "member",
        ),
        (
            _packed(PredictReply(1, "g", _OBSERVED, "w", 1.0), "worker_id", "w/1"),
            PredictReply.decode,
            "worker_id",
        ),
        (
            _packed(MetricsMessage(0, 0.5, 0.5, None, False), "coverage", 1.5),
            MetricsMessage.decode,
            "outside",
        ),
        (
            _packed(MetricsMessage(0, 0.5, 0.5, None, False), "tu", float("nan")),
            MetricsMessage.decode,
            "outside",
        ),
        (
            _packed(PoseMessage(0, (1, 2)), "pose", [1, 2, 3]),
            PoseMessage.decode,
            r"\[row, col\]",
        ),
        (
            _packed(
                WorldInfo("w", (5, 5), 0.1, [[1, 1]]),
                "starts",
                encode_array(np.array([[9, 1]], np.int32)),
            ),
            WorldInfo.decode,
            "outside",
        ),
        (  # the world's settings are counts on the wire too
            _packed(WorldInfo("w", (5, 5), 0.1, [[1, 1]], 90, 40, 2), "n_rays", 2.5),
            WorldInfo.decode,
            "n_rays must be a non-negative integer",
        ),
        (
            _packed(WorldInfo("w", (5, 5), 0.1, [[1, 1]], 90, 40, 2), "cells_per_step", -2),
            WorldInfo.decode,
            "cells_per_step must be a non-negative integer",
        ),
        (
            _packed(WorldInfo("w", (5, 5), 0.1, [[1, 1]], 90, 40, 2), "range_cells", "40"),
            WorldInfo.decode,
            "field 'range_cells' must be a number",
        ),
        (  # a claim travels with its score
            _packed(
                step_request(2, [], claim=((1, 1), 1.0, np.zeros((2, 2), bool))),
                "claim_score",
                None,
            ),
            StepRequest.decode,
            "a claim needs a claim_score",
        ),  # fmt: skip
        (
            _packed(
                step_request(2, [], claim=((1, 1), 1.0, np.zeros((2, 2), bool))),
                "claim_goal",
                [1, -1],
            ),
            StepRequest.decode,
            "claim_goal",
        ),  # fmt: skip
        (
            _packed(step_request(2, []), "done", 1),
            StepRequest.decode,
            "field 'done' must be a boolean",
        ),
        (  # the single-robot step request of before teams: no done, no claim fields
            _old_step_request(),
            StepRequest.decode,
            "missing field 'done'",
        ),
        (  # the team messages of before: their types are gone
            _renamed(step_request(1, []), "team_step_request"),
            decode_message,
            "unknown message type",
        ),
        (
            _renamed(step_reply(1, np.random.default_rng(0)), "team_scan_reply"),
            decode_message,
            "unknown message type",
        ),
        (  # one row per robot in every per-robot array
            _packed(
                step_reply(1, np.random.default_rng(0)),
                "lost",
                encode_array(np.zeros(2, bool)),
            ),
            StepReply.decode,
            "every per-robot array needs 3 rows",
        ),
        (
            _packed(
                step_reply(1, np.random.default_rng(0)),
                "claim_state",
                encode_array(np.array([0, 3, 0], np.uint8)),
            ),
            StepReply.decode,
            "codes other than 0, 1, 2",
        ),
        (
            _packed(
                step_reply(1, np.random.default_rng(0), claims=(1, 1)),
                "claim_visible",
                encode_array(np.zeros((1, 6, 7), bool)),
            ),
            StepReply.decode,
            r"one row per new claim \(2\), got 1",
        ),
        (
            _packed(
                step_reply(1, np.random.default_rng(0)),
                "n_cells",
                encode_array(np.zeros((3, 5), np.int32)),
            ),
            StepReply.decode,
            "must be uint16",
        ),
        (ErrorReply("x").encode(), MapMessage.decode, "expected a map message"),
        ("not bytes", MapMessage.decode, "must be bytes"),
    ],
)
def test_per_message_rules_are_enforced(payload, decode, match):
    with pytest.raises(ProtocolError, match=match) as info:
        decode(payload)
    assert "\n" not in str(info.value)


def test_oversized_payloads_are_refused_before_unpacking():
    config = ServicesConfig(max_message_bytes=1000)
    with pytest.raises(ProtocolError, match="exceeds the 1000-byte limit"):
        decode_message(b"\xc1" * 1001, config=config)  # invalid msgpack, never looked at
    big = MapMessage(0, "observed", np.random.default_rng(2).integers(0, 3, (40, 40), np.uint8))
    with pytest.raises(ProtocolError, match="exceeds"):
        big.encode(config)


def test_decoded_size_is_capped_per_message():
    config = ServicesConfig(max_decoded_bytes=10)
    message = GroundTruth(np.zeros((2, 3), bool), np.zeros((2, 3), bool))  # 12 bytes in all
    with pytest.raises(ProtocolError, match="decoded-size limit"):
        GroundTruth.decode(message.encode(), config)


@pytest.mark.parametrize("seed", range(4))
def test_random_bytes_raise_protocol_errors(seed):
    rng = np.random.default_rng(seed)
    for size in rng.integers(0, 300, 50):
        payload = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        with pytest.raises(ProtocolError):
            decode_message(payload)


@pytest.mark.parametrize("message", _sample_messages()[:8], ids=lambda m: m.TYPE)
def test_corrupted_payloads_decode_or_raise_protocol_errors_only(message):
    rng = np.random.default_rng(3)
    payload = np.frombuffer(message.encode(), np.uint8)
    for _ in range(100):
        corrupted = payload.copy()
        spots = rng.integers(0, len(payload), rng.integers(1, 4))
        corrupted[spots] = rng.integers(0, 256, len(spots))
        cut = rng.integers(len(payload) // 2, len(payload) + 1)
        try:
            decode_message(corrupted[:cut].tobytes())
        except ProtocolError as error:
            assert "\n" not in str(error)


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: step_request(0, np.zeros((2, 3), np.int32)), r"\(k, 2\)"),
        (lambda: step_request(0, np.array([[0.5, 1.0]])), "integer cells"),
        (lambda: step_request(0, [[-1, 2]]), "negative"),
        (lambda: step_request(-1, []), "seq"),
        (lambda: step_request(True, []), "seq"),
        (lambda: PredictRequest(-1, _OBSERVED), "request_id"),
        (lambda: PredictRequest(1, _OBSERVED.astype(np.float32)), "uint8"),
        (lambda: PredictRequest(1, _OBSERVED, None, "run-a"), "run and origin go together"),
        (lambda: PredictRequest(1, _OBSERVED, None, None, (0, 0)), "go together"),
        (lambda: PredictRequest(1, _OBSERVED, None, "Run A", (0, 0)), "not a valid run id"),
        (lambda: PredictRequest(1, _OBSERVED, None, "r", (-1, 0)), "origin"),
        (lambda: PredictRequest(1, _OBSERVED, None, None, None, "LaMa!"), "predictor"),
        (lambda: MapMessage(0, "observed", _OBSERVED + 1), "codes other than"),
        (lambda: MapMessage.from_probabilities(0, "observed", np.zeros((2, 2))), "codes"),
        (lambda: PoseMessage(0, (1,)), "two non-negative"),
        (lambda: MetricsMessage(0, 0.5, 0.5, None, 1), "degraded"),
        (lambda: StatusMessage(0, "sleeping"), "state"),
        (lambda: WorldInfo("", (5, 5), 0.1, []), "name"),
        (lambda: WorldInfo("w", (5, 5), 0.1, [], n_rays=-1), "n_rays"),
        (lambda: WorldInfo("w", (5, 5), 0.1, [], cells_per_step=1.5), "cells_per_step"),
        (lambda: step_request(1, [], claim=((1, 1), math.nan, np.zeros((2, 2), bool))), "score"),
        (lambda: step_request(1, [], claim=((1, 1), math.inf, np.zeros((2, 2), bool))), "score"),
        (lambda: step_request(1, [], claim=((1, 1), 0.5, np.zeros(4, bool))), "claim_visible"),
        (lambda: step_request(1, [], mac=7), "mac"),
        (lambda: step_request(1, [], mac="s3cret"), "mac must be 64 lowercase hex"),
        (lambda: step_request(1, [], mac="AB" * 32), "mac must be 64 lowercase hex"),
        (lambda: WorldInfo("w", (5, 5), 0.0, []), "resolution_m"),
    ],
)
def test_bad_messages_are_refused_when_built(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def _objects_in(value) -> int:
    """The msgpack objects of an unpacked value, counted the slow way."""
    if isinstance(value, dict):
        return 1 + sum(_objects_in(k) + _objects_in(v) for k, v in value.items())
    if isinstance(value, list):
        return 1 + sum(_objects_in(v) for v in value)
    return 1


@pytest.mark.parametrize("message", _sample_messages(), ids=lambda m: m.TYPE)
def test_objects_are_counted_from_their_headers_as_the_unpacker_sees_them(message):
    payload = message.encode()
    unpacked = msgpack.unpackb(payload, raw=False)
    assert count_objects(payload, 10**6) == _objects_in(unpacked)
    values = [1, -5, 2**40, -(2**40), 1.5, "x" * 300, b"y" * 70000, None, True,
              {"a": [{}, []]}, msgpack.ExtType(3, b"zz")]  # fmt: skip
    odd = msgpack.packb(values, use_bin_type=True)
    assert count_objects(odd, 10**6) == 1 + 11 + 4


def test_a_payload_of_millions_of_empty_maps_is_refused_before_unpacking():
    """31 MiB of empty maps in one valid message were 31 M Python objects (3 GB)."""
    count = 31 * 2**20
    payload = b"\x83" + msgpack.packb("schema") + b"\x01" + msgpack.packb("type")
    payload += msgpack.packb("step_request") + msgpack.packb("cells")
    payload += b"\xdd" + count.to_bytes(4, "big") + b"\x80" * count
    with pytest.raises(ProtocolError, match="more than 65536 msgpack objects"):
        decode_message(payload)


def test_a_receiver_s_own_limit_bounds_payload_and_decoded_arrays():
    """A map message cannot exceed what the receiver's run holds: the payload, and a
    compressed array claiming more cells than that, are refused before any array is made."""
    visible = np.ones((400, 400), dtype=bool)  # compresses to a few hundred bytes
    cells = np.array([[1, 1]], dtype=np.int32)
    payload = StepRequest(1, cells, False, True, (1, 1), 1.0, visible).encode()
    limit = map_message_bytes(100 * 100)  # a world of 10 000 cells
    assert len(payload) < limit
    with pytest.raises(ProtocolError, match="over the decoded-size limit"):
        StepRequest.decode(payload, max_bytes=limit)
    assert StepRequest.decode(payload, max_bytes=map_message_bytes(400 * 400)).claimed
    with pytest.raises(ProtocolError, match="exceeds the 100-byte limit"):
        StepRequest.decode(payload, max_bytes=100)
