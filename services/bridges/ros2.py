"""`python -m services.ros2`: a run's maps, poses, scans, paths and transforms as ROS 2
topics over rmw_zenoh, in simulated time.

    python -m services.ros2 [--run RUN] [--domain N] [--ros-connect ENDPOINT]
        [--bridge-keys] [--mode ...] [--connect ...]

Follows every robot of one run (`--run`), or of every run, and republishes the topics of
`mapex.interop.topics` as rmw_zenoh does, so `ros2 topic list/echo` and RViz2 see them;
`--ros-connect` publishes through a session connected to the ROS 2 router instead (nothing
answering there is a one-line error, exit 2). Needs the `ros` extra. Topics, wire format,
flags and exits:
docs/interop.md#the-ros-2-bridge-servicesbridgesros2.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import zenoh

from mapex.exit_codes import EXIT_USAGE
from mapex.interop import rmw_zenoh as rmw
from mapex.interop.ros_messages import MissingExtraError, serialize, type_hash
from mapex.interop.topics import Outgoing
from services.bridges.follow import RunFollower
from services.bridges.ros_translate import TRANSLATED_TOPICS, RunTranslator
from services.codec import DEFAULT_SERVICES
from services.config import Ros2Config
from services.keys import run_id_problem
from services.serving import configure_logging, stop_on_signals
from services.supervisor import endpoint_silence
from services.zenoh_config import (
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
    zenoh_config,
    zenoh_config_from_args,
)

log = logging.getLogger("services.ros2")


@dataclass
class _Publisher:
    """One ROS topic's Zenoh publisher(s), liveliness token, gid and sequence number."""

    publisher: Any  # a zenoh.Publisher, or a zenoh.ext.AdvancedPublisher for latched topics
    token: zenoh.LivelinessToken
    gid: bytes
    bridge_publisher: zenoh.Publisher | None
    sequence: int = 0

    def undeclare(self) -> None:
        for entity in (self.publisher, self.token, self.bridge_publisher):
            if entity is not None:
                entity.undeclare()


class RosNode:
    """One rmw_zenoh node on `session`: declares a publisher (with its token) the first time
    a topic is sent, and withdraws a run's publishers on `forget`."""

    def __init__(
        self, session: zenoh.Session, config: Ros2Config, bridge_keys: bool = False
    ) -> None:
        self.session, self.config, self.bridge_keys = session, config, bridge_keys
        self.zid = str(session.zid())
        self.node_id = 0
        token = rmw.node_token(config.domain_id, self.zid, self.node_id, config.node_name)
        self._node_token = session.liveliness().declare_token(token)
        self._publishers: dict[str, _Publisher] = {}
        self._next_entity_id = self.node_id + 1
        self.sent = 0

    def publish(self, outgoing: Outgoing) -> None:
        """Send one message on its topic (declared on first use)."""
        entry = self._publishers.get(outgoing.topic) or self._declare(outgoing)
        entry.sequence += 1
        payload = serialize(outgoing.message)
        attachment = rmw.attachment(entry.sequence, time.time_ns(), entry.gid)
        entry.publisher.put(payload, attachment=attachment)
        if entry.bridge_publisher is not None:
            entry.bridge_publisher.put(payload)
        self.sent += 1

    def forget(self, topic_prefix: str) -> None:
        """Undeclare the publishers (and tokens) of the topics under `topic_prefix`."""
        for topic in [t for t in self._publishers if t.startswith(topic_prefix)]:
            self._publishers.pop(topic).undeclare()

    def topics(self) -> list[str]:
        return sorted(self._publishers)

    def close(self) -> None:
        for entry in self._publishers.values():
            entry.undeclare()
        self._publishers.clear()
        self._node_token.undeclare()

    def _declare(self, outgoing: Outgoing) -> _Publisher:
        cfg = self.config
        digest = type_hash(outgoing.ros_type)
        depth = outgoing.depth or (cfg.latched_depth if outgoing.latched else cfg.volatile_depth)
        entity_id, self._next_entity_id = self._next_entity_id, self._next_entity_id + 1
        token = rmw.publisher_token(
            cfg.domain_id, self.zid, self.node_id, entity_id, cfg.node_name, outgoing.topic,
            outgoing.ros_type, digest, rmw.qos_text(outgoing.latched, depth, outgoing.reliable),
        )  # fmt: skip
        key = rmw.data_key(cfg.domain_id, outgoing.topic, outgoing.ros_type, digest)
        publisher = self._data_publisher(key, outgoing.latched, depth, outgoing.reliable)
        bridge = (
            self.session.declare_publisher(outgoing.topic.lstrip("/")) if self.bridge_keys else None
        )
        entry = _Publisher(
            publisher, self.session.liveliness().declare_token(token), rmw.publisher_gid(token),
            bridge,
        )  # fmt: skip
        self._publishers[outgoing.topic] = entry
        log.info("publishing %s (%s)", outgoing.topic, outgoing.ros_type)
        return entry

    def _data_publisher(self, key: str, latched: bool, depth: int, reliable: bool = True):
        """rmw_zenoh's publisher: latched topics keep their last `depth` samples for late
        transient-local subscribers (zenoh-ext advanced publisher, as rmw_zenoh declares,
        with sample-miss heartbeats when reliable); best-effort ones (/clock) put best
        effort."""
        reliability = zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT
        if not latched:
            return self.session.declare_publisher(
                key, reliability=reliability, congestion_control=zenoh.CongestionControl.DROP
            )
        from zenoh.ext import CacheConfig, MissDetectionConfig, declare_advanced_publisher

        heartbeat = MissDetectionConfig(sporadic_heartbeat=self.config.heartbeat_s)
        return declare_advanced_publisher(
            self.session, key, cache=CacheConfig(max_samples=depth),
            sample_miss_detection=heartbeat if reliable else None,
            publisher_detection=True, reliability=reliability,
            congestion_control=zenoh.CongestionControl.DROP,
        )  # fmt: skip


def ros_router_problem(
    endpoint: str, timeout_s: float = DEFAULT_SERVICES.hub_probe_timeout_s
) -> str | None:
    """Why `--ros-connect ENDPOINT` cannot be used, in one line (nothing accepts a TCP
    connection there within `timeout_s`, or the endpoint is malformed), or None. Without
    this the bridge would open a session anyway and publish into nothing."""
    try:
        silence = endpoint_silence(endpoint, timeout_s)
    except ValueError as error:
        return f"bad --ros-connect endpoint: {error}"
    if silence is None:
        return None
    return (
        f"nothing answers at --ros-connect {endpoint} ({silence}): start the ROS 2 router "
        "there first (ros2 run rmw_zenoh_cpp rmw_zenohd)"
    )


def ros_session_config(endpoint: str) -> zenoh.Config:
    """A peer session connected to a ROS 2 router, listening on a free loopback port (peers
    of one router talk directly) and with timestamping on, as rmw_zenoh's own session
    config."""
    config = zenoh_config("peer", [endpoint], [DEFAULT_SERVICES.ephemeral_listen_endpoint])
    config.insert_json5("timestamping/enabled", "true")
    return config


def main(
    config: zenoh.Config,
    run: str | None = None,
    ros_connect: str | None = None,
    bridge_keys: bool = False,
    stop: threading.Event | None = None,
    ros2: Ros2Config | None = None,
) -> int:
    """Bridge until `stop`; returns the number of ROS messages sent."""
    ros2 = ros2 or Ros2Config()
    config.insert_json5("timestamping/enabled", "true")
    session = open_session(config)
    ros_session = open_session(ros_session_config(ros_connect)) if ros_connect else session
    node = RosNode(ros_session, ros2, bridge_keys)
    translate = RunTranslator(node.publish, ros2, node.forget)
    follower = RunFollower(session, translate, run, TRANSLATED_TOPICS)
    log.info("bridging %s to ROS 2 domain %d as node %s",
             f"run {run}" if run else "every run", ros2.domain_id, ros2.node_name)  # fmt: skip
    try:
        (stop or threading.Event()).wait()
    finally:
        follower.close()
        node.close()
        if ros_session is not session:
            ros_session.close()
        session.close()
    log.info("stopped after %d ROS messages (%d dropped updates)", node.sent, follower.dropped)
    return node.sent


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m services.ros2",
        description=__doc__.split("\n\n")[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--run", default=None, help="run id to bridge (default: every run)")
    parser.add_argument(
        "--domain", type=int, default=int(os.environ.get("ROS_DOMAIN_ID", 0)),
        help="ROS 2 domain id (default: $ROS_DOMAIN_ID or 0)",
    )  # fmt: skip
    parser.add_argument(
        "--ros-connect", default=None, metavar="ENDPOINT",
        help="publish through a session connected to this ROS 2 router (rmw_zenohd) "
        "instead of the followed session",
    )  # fmt: skip
    parser.add_argument(
        "--bridge-keys", action="store_true",
        help="also put raw CDR on <topic> keys (zenoh-bridge-ros2dds users)",
    )  # fmt: skip
    add_zenoh_arguments(parser)
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.run is not None and (problem := run_id_problem(args.run)) is not None:
        parser.error(problem)
    if not 0 <= args.domain <= 232:
        parser.error(f"--domain {args.domain} is not a ROS 2 domain id (0-232)")
    if args.ros_connect and (problem := ros_router_problem(args.ros_connect)) is not None:
        print(f"{parser.prog}: error: {problem}", file=sys.stderr)
        return EXIT_USAGE
    configure_logging(f"ros2[{args.run or '*'}]")
    stop = stop_on_signals()
    try:
        config = zenoh_config_from_args(args)
        main(config, args.run, args.ros_connect, args.bridge_keys, stop,
             replace(Ros2Config(), domain_id=args.domain))  # fmt: skip
    except (ZenohConfigError, MissingExtraError) as error:
        log.error("%s", error)
        return EXIT_USAGE
    return 0


if __name__ == "__main__":
    sys.exit(run_cli())
