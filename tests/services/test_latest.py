"""LatestPublisher on real Zenoh sessions over loopback: live puts and late-joiner gets.

The hub session publishes; a second session connected to it plays the outside tool.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
import zenoh
from service_processes import until

from mapex.recorder import MetricCurves
from services.keys import robot_key
from services.latest import LatestPublisher
from services.messages import MapMessage, StatusMessage, decode_message
from services.publishing import RunPublisher
from services.zenoh_config import open_session, zenoh_config

QUERY_TIMEOUT_S = 2.0


@pytest.fixture(scope="module")
def viewer(hub):
    """A session connected to the hub, as an outside tool would be."""
    session = open_session(zenoh_config(connect=[hub[1]]))
    yield session
    session.close()


def _map(t: int) -> MapMessage:
    return MapMessage(t, "observed", np.full((4, 6), t % 3, dtype=np.uint8))


def _replies(session, selector: str) -> list:
    return [reply.ok for reply in session.get(selector, timeout=QUERY_TIMEOUT_S)]


def _routed_replies(session, selector: str) -> list:
    """The replies once the queryables' declarations have reached `session` (asynchronous)."""
    return until(lambda: _replies(session, selector), f"a reply on {selector}")


def test_a_late_get_gets_the_last_of_several_puts_and_nothing_before(hub, viewer):
    observed, status = (
        robot_key("latest_a", "r0", "observed_map"),
        robot_key("latest_a", "r0", "status"),
    )
    with LatestPublisher(hub[0], [observed, status]) as latest:
        assert _replies(viewer, observed) == []
        assert latest.latest(observed) is None
        for t in (1, 2, 3):
            latest.put(observed, _map(t))
        replies = _routed_replies(viewer, observed)
        assert len(replies) == 1 and str(replies[0].key_expr) == observed
        message = decode_message(replies[0].payload.to_bytes())
        assert isinstance(message, MapMessage) and message.t == 3
        np.testing.assert_array_equal(message.map_u8, _map(3).map_u8)
        assert latest.latest(observed) == _map(3).encode()
        assert _replies(viewer, status) == []  # a key nothing was put on stays silent


def test_subscribers_receive_the_puts_in_order(hub, viewer):
    key = robot_key("latest_b", "r0", "status")
    received: list[int] = []
    subscriber = viewer.declare_subscriber(
        key, lambda sample: received.append(decode_message(sample.payload.to_bytes()).t)
    )
    try:
        with LatestPublisher(hub[0], [key]) as latest:

            def warmed_up() -> bool:  # the subscription needs a moment to reach the hub
                latest.put(key, StatusMessage(0, "starting"))
                return bool(received)

            until(warmed_up, "the subscription to reach the publisher")
            for t in range(1, 6):
                latest.put(key, StatusMessage(t, "running"))
            until(lambda: received[-1:] == [5], "the last put")
            assert [t for t in received if t] == [1, 2, 3, 4, 5]
    finally:
        subscriber.undeclare()


def test_queryables_answer_only_their_own_exact_keys(hub, viewer):
    observed, goal = (
        robot_key("latest_c", "r0", "observed_map"),
        robot_key("latest_c", "r0", "goal"),
    )
    status = robot_key("latest_c", "r0", "status")
    with LatestPublisher(hub[0], [observed, status]) as latest:
        latest.put(observed, _map(7))
        latest.put(status, StatusMessage(7, "running"))
        assert _replies(viewer, goal) == []  # not one of its keys: no wildcard queryable
        until(lambda: len(_replies(viewer, "mapex/@v1/latest_c/r0/**")) == 2, "both keys")
        replies = _replies(viewer, "mapex/@v1/latest_c/r0/**")
        by_key = {str(r.key_expr): decode_message(r.payload.to_bytes()) for r in replies}
        assert set(by_key) == {observed, status}
        assert by_key[observed].t == 7 and by_key[status].state == "running"
        assert _replies(viewer, "mapex/@v1/latest_other/r0/**") == []


def test_close_undeclares_everything(hub, viewer):
    key = robot_key("latest_d", "r0", "observed_map")
    with LatestPublisher(hub[0], [key]) as latest:
        latest.put(key, _map(1))
        assert len(_routed_replies(viewer, key)) == 1
    until(lambda: _replies(viewer, key) == [], "the undeclaration to reach the viewer")
    with pytest.raises(KeyError):
        latest.put(key, _map(2))
    latest.close()  # idempotent


@pytest.mark.parametrize(
    "keys, match",
    [
        ([], "at least one key"),
        (["mapex/@v1/x/r0/*"], "no wildcard"),
        (["mapex/@v1/x/**"], "no wildcard"),
        (["mapex/@v1/x/r0/goal", "mapex/@v1/x/r0/goal"], "duplicate"),
        ("mapex/@v1/x/r0/goal", "not one string"),
    ],
)
def test_keys_must_be_exact_and_distinct(hub, keys, match):
    with pytest.raises(ValueError, match=match):
        LatestPublisher(hub[0], keys)


def test_put_on_a_key_it_does_not_serve_is_refused(hub):
    latest = LatestPublisher(hub[0], [robot_key("latest_e", "r0", "goal")])
    try:
        with pytest.raises(KeyError, match="not one of"):
            latest.put(robot_key("latest_e", "r0", "path"), _map(1))
    finally:
        latest.close()


def test_concurrent_puts_leave_each_key_with_its_last_put(hub, viewer):
    keys = [robot_key("latest_f", f"r{i}", "observed_map") for i in range(4)]
    with LatestPublisher(hub[0], keys) as latest:

        def put_all(key: str) -> None:
            for t in range(40):
                latest.put(key, _map(t))

        threads = [threading.Thread(target=put_all, args=(key,)) for key in keys]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        for key in keys:
            (reply,) = _replies(viewer, key)
            assert decode_message(reply.payload.to_bytes()).t == 39


def test_blocking_keys_wait_for_room_and_the_others_drop_under_congestion(hub):
    frames, status = (
        robot_key("latest_d", "r0", "observed_map"),
        robot_key("latest_d", "r0", "status"),
    )
    with LatestPublisher(hub[0], [frames, status], blocking_keys=[status]) as latest:
        congestion = {key: p.congestion_control for key, p in latest._publishers.items()}
    assert congestion == {
        frames: zenoh.CongestionControl.DROP,
        status: zenoh.CongestionControl.BLOCK,
    }


def test_a_blocking_key_must_be_one_of_the_keys(hub):
    key = robot_key("latest_e", "r0", "status")
    with pytest.raises(ValueError, match="not among the keys"):
        LatestPublisher(hub[0], [key], blocking_keys=[robot_key("latest_e", "r0", "goal")])


def test_a_runs_status_and_metrics_are_never_dropped(hub):
    publisher = RunPublisher(hub[0], "latest_f", "r0")
    try:
        blocking = {
            topic
            for topic, key in publisher.keys.items()
            if publisher.latest._publishers[key].congestion_control == zenoh.CongestionControl.BLOCK
        }
    finally:
        publisher.close()
    assert blocking == {"status", "metrics"}  # maps, path, goal: a newer one follows


def test_every_metric_sample_and_status_arrives_in_order(hub, viewer):
    """Samples completed together (a run's end completes its last ones at once) and
    statuses in one publishing period all reach a subscriber, none replaced by a newer one
    (the browser view's curves have no gaps)."""
    got: list[tuple[str, int]] = []
    done = threading.Event()

    def heard(sample: zenoh.Sample) -> None:
        message = decode_message(sample.payload.to_bytes())
        got.append((message.TYPE, message.t))
        if message.TYPE == "status" and message.state == "finished":
            done.set()

    subscribers = [
        viewer.declare_subscriber(robot_key("latest_m", "r0", topic), heard)
        for topic in ("metrics", "status")
    ]
    publisher = RunPublisher(hub[0], "latest_m", "r0")
    try:
        until(lambda: publisher.latest._publishers[publisher.keys["metrics"]].matching_status
              .matching, "the subscriber's route")  # fmt: skip
        curves = MetricCurves()
        for t in range(0, 300, 50):  # six samples handed over in one go
            curves.steps.append(t)
            curves.coverage.append(t / 1000)
            curves.iou.append(t / 2000)
            curves.tu.append(float("nan"))
        publisher.status(0, "running")
        publisher._publish_metrics(curves, degraded=False)
        publisher.status(300, "finished")
        assert done.wait(10.0)
    finally:
        publisher.close()
        for subscriber in subscribers:
            subscriber.undeclare()
    metrics = [t for kind, t in got if kind == "metrics"]
    assert metrics == [0, 50, 100, 150, 200, 250]
    assert [t for kind, t in got if kind == "status"] == [0, 300]
