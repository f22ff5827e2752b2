"""Zenoh flags and defaults, one-line config errors, and a real loopback exchange."""

from __future__ import annotations

import argparse
import json
import threading

import numpy as np
import pytest
from service_processes import free_loopback_port, until

from services.config import ServicesConfig
from services.protocol import (
    MapMessage,
    PredictReply,
    PredictRequest,
    parse_key,
    predict_key,
    robot_key,
    robot_key_pattern,
)
from services.zenoh_config import (
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
    zenoh_config,
    zenoh_config_from_args,
)

HUB = ServicesConfig().hub_endpoint
EXCHANGE_DEADLINE_S = 5.0  # generous for a loaded machine; the exchange takes milliseconds


def _get(config, key: str):
    return json.loads(config.get_json(key))


def test_flags_are_parsed():
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    args = parser.parse_args(
        ["--mode", "client", "--connect", "tcp/10.0.0.1:7447", "--connect", "tcp/10.0.0.2:7447"]
    )
    assert args.mode == "client"
    assert args.connect == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    assert args.listen is None and args.config is None
    config = zenoh_config_from_args(args)
    assert _get(config, "connect/endpoints") == args.connect
    with pytest.raises(SystemExit):
        parser.parse_args(["--mode", "satellite"])


@pytest.mark.parametrize(
    "kwargs, mode, listen, connect",
    [
        ({}, "peer", ["tcp/127.0.0.1:0"], [HUB]),
        ({"listen": [HUB]}, "peer", [HUB], []),  # the hub itself
        ({"mode": "router"}, "router", [HUB], []),
        ({"mode": "client"}, "client", [], [HUB]),
        ({"connect": ["tcp/127.0.0.1:9000"]}, "peer", ["tcp/127.0.0.1:0"], ["tcp/127.0.0.1:9000"]),
    ],
)
def test_defaults_are_loopback_without_multicast(kwargs, mode, listen, connect):
    config = zenoh_config(**kwargs)
    assert _get(config, "mode") == mode
    assert _get(config, "listen/endpoints") == listen
    assert _get(config, "connect/endpoints") == connect
    assert _get(config, "scouting/multicast/enabled") is False
    assert _get(config, "scouting/gossip/multihop") is False


def test_a_config_file_is_the_base_and_flags_override_it(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "client", connect: { endpoints: ["tcp/10.1.1.1:7447"] } }')
    config = zenoh_config(config_file=path)
    assert _get(config, "mode") == "client"
    assert _get(config, "connect/endpoints") == ["tcp/10.1.1.1:7447"]
    config = zenoh_config(mode="peer", connect=["tcp/10.2.2.2:7447"], config_file=path)
    assert _get(config, "mode") == "peer"
    assert _get(config, "connect/endpoints") == ["tcp/10.2.2.2:7447"]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"listen": ["foo"]}, "bad --listen endpoint"),
        ({"connect": ["tcp127.0.0.1:7447"]}, "bad --connect endpoint"),
        ({"mode": "satellite"}, "not one of"),
        ({"config_file": "/nonexistent/zenoh.json5"}, "does not exist"),
        ("broken", "is invalid"),
        ("bad_mode", "is invalid"),
    ],
)
def test_bad_configs_are_one_line_errors(kwargs, match, tmp_path):
    files = {"broken": '{ mode: "peer", ', "bad_mode": '{ mode: "banana" }'}
    if isinstance(kwargs, str):
        path = tmp_path / "zenoh.json5"
        path.write_text(files[kwargs])
        kwargs = {"config_file": path}
    with pytest.raises(ZenohConfigError, match=match) as info:
        zenoh_config(**kwargs)
    assert "\n" not in str(info.value) and ".rs:" not in str(info.value)


@pytest.mark.parametrize("endpoint", ["tcp/127.0.0.1:99999", "tcp/no-such-host.invalid:7447"])
def test_unusable_endpoints_fail_to_open_with_one_line(endpoint):
    with pytest.raises(ZenohConfigError, match="cannot open a Zenoh session") as info:
        open_session(zenoh_config(listen=[endpoint], connect=[]))
    assert endpoint in str(info.value)
    assert "\n" not in str(info.value) and ".rs:" not in str(info.value)


def _until(condition, what: str):
    """Poll `condition` until it returns a truthy value (declarations propagate async)."""
    return until(condition, what, EXCHANGE_DEADLINE_S)


def test_two_loopback_sessions_exchange_a_put_and_a_query():
    hub_endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    hub = open_session(zenoh_config(listen=[hub_endpoint], connect=[]))
    try:
        peer = open_session(zenoh_config(connect=[hub_endpoint]))
        try:
            _exchange(hub, peer)
        finally:
            peer.close()
    finally:
        hub.close()


def _exchange(hub, peer) -> None:
    _until(lambda: list(peer.info.peers_zid()), "the peer to reach the hub")
    received: list = []
    got_one = threading.Event()

    def on_map(sample):
        received.append((parse_key(str(sample.key_expr)), sample.payload.to_bytes()))
        got_one.set()

    def on_predict(query):
        request = PredictRequest.decode(query.payload.to_bytes())
        reply = PredictReply.from_probabilities(
            request.request_id, "g", request.observed / 2.0, "w0", 1.5
        )
        query.reply(query.key_expr, reply.encode())

    observed = np.random.default_rng(5).integers(0, 3, (64, 64), np.uint8)
    subscriber = hub.declare_subscriber(robot_key_pattern("observed_map", run="r1"), on_map)
    queryable = hub.declare_queryable(predict_key("g", "w0"), on_predict)
    try:
        payload = MapMessage(7, "observed", observed).encode()

        def publish() -> bool:  # again until the subscriber's declaration has reached the peer
            peer.put(robot_key("r1", "bot", "observed_map"), payload)
            return got_one.wait(0.05)

        _until(publish, "the map to arrive")
        key, payload = received[0]
        assert key.robot == "bot" and key.topic == "observed_map"
        np.testing.assert_array_equal(MapMessage.decode(payload).map_u8, observed)

        def ask():
            request = PredictRequest(9, observed).encode()
            replies = list(peer.get(predict_key("g", "w0"), payload=request, timeout=1.0))
            return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]

        reply = PredictReply.decode(_until(ask, "the prediction reply")[0])
        assert reply.request_id == 9 and reply.worker_id == "w0"
        np.testing.assert_allclose(reply.probabilities(), observed / 2.0, atol=1 / 510 + 1e-6)
    finally:
        subscriber.undeclare()
        queryable.undeclare()
