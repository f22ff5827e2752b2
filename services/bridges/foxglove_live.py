"""A live Foxglove WebSocket server with a run's topics: `python -m services.foxglove`, the
child process `--foxglove` starts on services.up and services.evaluate, for users of the
Foxglove app (open a connection to ws://127.0.0.1:8765).

It serves the channels of both recordings (`mapex.interop.mcap_file`: `--record` and
`--record-foxglove`): each ROS 2 topic as CDR with its ros2msg schema, and beside it the
Foxglove-schema channel (`/foxglove/...`) where there is one, over the Foxglove SDK's
WebSocket protocol (subprotocol `SUBPROTOCOL`). Channels are made as topics first appear,
in a context of this server's own. Needs the Foxglove SDK (`pip install -e '.[foxglove]'`).

The SDK's server listens on a loopback port of its own; the port served is a
`services.bridges.gate.TcpRelay` in front of it, which bounds what clients may hold (the SDK
caps neither clients nor handshakes): `FoxgloveConfig.max_clients` at once (one more is
answered 503), each handshake within `handshake_timeout_s`, a client that takes nothing for
`send_timeout_s` closed, and `message_backlog` messages queued per client in the SDK, the
oldest dropped first.

Two things the SDK does not do by itself:

* A latched topic (transient local in ROS: the maps, the paths, /tf_static) is sent again,
  its last message, to a client that subscribes to it, so a client joining late gets the
  maps and frames a ROS subscriber would.
* The SDK advertises a channel made while a client is connected before it records the
  channel as advertised to that client (foxglove-sdk `ConnectedClient::advertise_channels`:
  send, then insert), so a client quick to subscribe can be refused ("attempted to
  subscribe to unknown channel"), and would get nothing of that topic all session. Each
  refusal the SDK logs is answered by making the channel again (a new id: every client is
  told unadvertise and advertise, and subscribes again).
"""

from __future__ import annotations

import argparse
import logging
import os
import queue
import re
import sys
import threading
from dataclasses import replace
from typing import Any

import zenoh

from mapex.exit_codes import EXIT_USAGE
from mapex.interop.ros_messages import MissingExtraError
from mapex.interop.topics import ChannelMessage, Outgoing, channel_messages
from services.bridges.follow import RunFollower
from services.bridges.gate import TcpRelay
from services.bridges.ros_translate import TRANSLATED_TOPICS, RunTranslator
from services.config import DEFAULT_FOXGLOVE, FoxgloveConfig, Ros2Config
from services.keys import run_id_problem
from services.serving import configure_logging, port_number, stop_on_signals, wait_for
from services.zenoh_config import (
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
    zenoh_config_from_args,
)

FOXGLOVE_DEFAULT_PORT = DEFAULT_FOXGLOVE.port  # the Foxglove app's default WebSocket port
SDK_HOST = "127.0.0.1"  # the SDK's own server listens here, on a free port, behind the relay
SUBPROTOCOL = "foxglove.sdk.v1"  # the WebSocket subprotocol the SDK's server speaks
# where and how the SDK (through Python logging) reports a subscription it refused
SDK_CLIENT_LOGGER = "foxglove.websocket.connected_client"
_REFUSED = re.compile(r"subscribe to unknown channel: (\d+)")
_OS_ERROR = re.compile(r"\(os error (\d+)\)")

log = logging.getLogger("services.foxglove_live")


class FoxgloveServer:
    """The WebSocket server and its channels; `write` logs one message on both channels.

    `write` is called from one thread (the follower's); the SDK calls back on its own. The
    clients connect to `port`, the relay's (`config` bounds them).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = FOXGLOVE_DEFAULT_PORT,
        config: FoxgloveConfig = DEFAULT_FOXGLOVE,
    ) -> None:
        try:
            import foxglove
        except ImportError as error:
            raise MissingExtraError(
                "--foxglove needs the foxglove extra: pip install -e '.[foxglove]'"
            ) from error
        self._foxglove = foxglove
        self._channels: dict[str, Any] = {}  # topic -> its channel (the follower's thread)
        self._schemas: dict[str, tuple[str, str, bytes, str]] = {}  # topic -> to make it again
        self._topic_of: dict[int, str] = {}  # channel id -> topic, of every channel made
        self._latched: dict[str, tuple[bytes, int]] = {}  # topic -> last (data, log time ns)
        self._latched_lock = threading.Lock()  # held while logging a latched topic
        self._refused: queue.SimpleQueue[int] = queue.SimpleQueue()  # channel ids
        self._refusals = _RefusalWatch(self._refused)
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(
                name="mapex", host=SDK_HOST, port=0, context=self.context,
                server_listener=_listener(self), message_backlog_size=config.message_backlog,
            )  # fmt: skip
        except RuntimeError as error:  # the SDK's FoxgloveError
            reason = _reason(error)
            raise OSError(f"--foxglove: cannot start the Foxglove server: {reason}") from None
        try:
            self.relay = TcpRelay(
                host, port, (SDK_HOST, self.server.port), config.max_clients,
                config.handshake_timeout_s, config.send_timeout_s, config.client_buffer_bytes,
                name="foxglove",
            )  # fmt: skip
        except OSError as error:  # e.g. a port already taken
            self.server.stop()
            reason = error.strerror or str(error)
            raise OSError(f"--foxglove: cannot serve on {host} port {port}: {reason}") from None
        logging.getLogger(SDK_CLIENT_LOGGER).addHandler(self._refusals)
        self.port = self.relay.port
        log.info("Foxglove WebSocket server on ws://%s:%d", host, self.port)

    def write(self, outgoing: Outgoing) -> None:
        """Log `outgoing` as CDR on its ROS topic and as protobuf on its Foxglove topic."""
        self.remake_refused()
        for message in channel_messages(outgoing):
            channel = self._channel(message)
            if not outgoing.latched:
                channel.log(message.data, log_time=outgoing.stamp_ns)
                continue
            with self._latched_lock:  # a late subscriber's copy never overtakes a newer one
                self._latched[message.topic] = (message.data, outgoing.stamp_ns)
                channel.log(message.data, log_time=outgoing.stamp_ns)

    def topics(self) -> list[str]:
        """The channels made so far, sorted."""
        return sorted(self._channels)

    def channel_id(self, topic: str) -> int:
        """The id `topic`'s channel has now (a remade channel has a new one)."""
        return int(self._channels[topic].id())

    def remake_refused(self) -> list[str]:
        """Make again the channels a subscription to which the SDK refused; their topics."""
        remade = []
        while True:
            try:
                channel_id = self._refused.get_nowait()
            except queue.Empty:
                return remade
            topic = self._topic_of.get(channel_id)
            if topic is None or self.channel_id(topic) != channel_id:
                continue  # not ours, or remade already
            with self._latched_lock:  # no latched copy goes to the closed channel
                refused = self._channels.pop(topic)
            refused.close()  # unadvertised to every client
            self._make(topic)
            log.info("%s: a subscription was refused; channel made again", topic)
            remade.append(topic)

    def close(self) -> None:
        logging.getLogger(SDK_CLIENT_LOGGER).removeHandler(self._refusals)
        self.relay.close()
        self.server.stop()

    def send_latched(self, topic: str) -> None:
        """Log `topic`'s last message again, when it is latched and has one (SDK thread)."""
        with self._latched_lock:
            last = self._latched.get(topic)
            channel = self._channels.get(topic)
            if last is not None and channel is not None:
                channel.log(last[0], log_time=last[1])

    def _channel(self, message: ChannelMessage) -> Any:
        if message.topic not in self._channels:
            name, encoding, data = message.schema()
            self._schemas[message.topic] = (name, encoding, data, message.message_encoding)
            self._make(message.topic)
        return self._channels[message.topic]

    def _make(self, topic: str) -> None:
        name, encoding, data, message_encoding = self._schemas[topic]
        schema = self._foxglove.Schema(name=name, encoding=encoding, data=data)
        channel = self._foxglove.Channel(
            topic, schema=schema, message_encoding=message_encoding, context=self.context
        )
        self._topic_of[int(channel.id())] = topic
        self._channels[topic] = channel


def _listener(server: FoxgloveServer) -> Any:
    """The SDK's server listener: a subscription to a latched topic gets its last message
    (the SDK's `ServerListener` answers every other callback with nothing)."""
    from foxglove.websocket import ServerListener

    class Listener(ServerListener):
        def on_subscribe(self, client: Any, channel: Any) -> None:
            server.send_latched(channel.topic)

    return Listener()


class _RefusalWatch(logging.Handler):
    """Queues the id of each channel the SDK logs a refused subscription to.

    Called on the SDK's thread while it holds the client's channel table: it only queues
    (making a channel there would wait for that table for ever)."""

    def __init__(self, refused: queue.SimpleQueue[int]) -> None:
        super().__init__(logging.ERROR)
        self._refused = refused

    def emit(self, record: logging.LogRecord) -> None:
        if (match := _REFUSED.search(record.getMessage())) is not None:
            self._refused.put(int(match.group(1)))


def _reason(error: RuntimeError) -> str:
    """'Address already in use' of the SDK's 'FoxgloveError: Failed to bind port: Address
    already in use (os error 98)'; its whole text, on one line, when it names no OS error."""
    found = _OS_ERROR.search(str(error))
    return os.strerror(int(found.group(1))) if found else " ".join(str(error).split())


class FoxgloveLive:
    """A `FoxgloveServer` fed by a follower of `run` (None: every run) on `session`."""

    def __init__(
        self, session: zenoh.Session, run: str | None = None, host: str = "127.0.0.1",
        port: int = FOXGLOVE_DEFAULT_PORT, config: Ros2Config | None = None,
        foxglove: FoxgloveConfig = DEFAULT_FOXGLOVE,
    ) -> None:  # fmt: skip
        self.server = FoxgloveServer(host, port, foxglove)
        translate = RunTranslator(self.server.write, config or Ros2Config(), with_foxglove=True)
        self.follower = RunFollower(session, translate, run, TRANSLATED_TOPICS)

    def close(self) -> None:
        self.follower.close()
        self.server.close()


# ---------------------------------------------------------------------------- entry points


def main(
    config: zenoh.Config,
    run: str | None = None,
    foxglove: FoxgloveConfig = DEFAULT_FOXGLOVE,
    stop: threading.Event | None = None,
) -> None:
    """Serve `run` (None: every run) on `foxglove.host`:`foxglove.port` until `stop`.

    Raises ZenohConfigError when the session is refused, OSError when the port cannot be
    bound, MissingExtraError without the foxglove extra.
    """
    session = open_session(config)
    try:
        live = FoxgloveLive(session, run, foxglove.host, foxglove.port, foxglove=foxglove)
        try:
            log.info("following %s", f"run {run}" if run else "every run")
            wait_for(stop or threading.Event())
        finally:
            live.close()
            log.info(
                "stopped: %d clients at most, %d refused, %d handshakes too slow, "
                "%d clients closed for not reading",
                live.server.relay.slots.most, live.server.relay.slots.refused,
                live.server.relay.timed_out, live.server.relay.stalled,
            )  # fmt: skip
    finally:
        session.close()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m services.foxglove",
        description="Serve the runs to the Foxglove app over the Foxglove SDK's WebSocket "
        "protocol (docs/interop.md).",
    )
    parser.add_argument("--run", default=None, help="run id to follow (default: every run)")
    parser.add_argument(
        "--port", type=port_number, default=DEFAULT_FOXGLOVE.port,
        help=f"port to serve on {DEFAULT_FOXGLOVE.host}, 0 for any free one (default: "
        "%(default)s)",
    )  # fmt: skip
    add_zenoh_arguments(parser)
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    """Parse flags, serve until SIGINT/SIGTERM; 0 on a clean stop, 2 on bad flags, a port
    or Zenoh config that cannot be used, or no foxglove extra."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.run is not None and (problem := run_id_problem(args.run)) is not None:
        parser.error(problem)
    configure_logging(f"foxglove[{args.run or 'all'}]")
    stop = stop_on_signals()
    foxglove = replace(DEFAULT_FOXGLOVE, port=args.port)
    try:
        main(zenoh_config_from_args(args), args.run, foxglove, stop)
    except (ZenohConfigError, OSError, MissingExtraError) as error:
        log.error("%s", error)
        return EXIT_USAGE
    return 0


if __name__ == "__main__":
    sys.exit(run_cli())
