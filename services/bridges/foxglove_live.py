"""A live Foxglove WebSocket server with a run's topics (`--foxglove` on services.up and
services.ros2), for users of the Foxglove app (open a connection to ws://127.0.0.1:8765).

It serves the same channels as an MCAP recording (`mapex.interop.mcap_file`): each ROS 2
topic as CDR with its ros2msg schema, and beside it the Foxglove-schema channel
(`/foxglove/...`). Channels are made as topics first appear; the Foxglove SDK keeps them in
a context of this server's own. Needs the Foxglove SDK (`pip install -e '.[foxglove]'`).
"""

from __future__ import annotations

import logging
from typing import Any

import zenoh

from mapex.interop.ros_messages import MissingExtraError
from mapex.interop.topics import ChannelMessage, Outgoing, channel_messages
from services.bridges.follow import RunFollower
from services.bridges.ros_translate import RunTranslator
from services.config import Ros2Config

FOXGLOVE_DEFAULT_PORT = 8765  # the Foxglove app's default WebSocket port

log = logging.getLogger("services.foxglove_live")


class FoxgloveServer:
    """The WebSocket server and its channels; `write` logs one message on both channels."""

    def __init__(self, host: str = "127.0.0.1", port: int = FOXGLOVE_DEFAULT_PORT) -> None:
        try:
            import foxglove
        except ImportError as error:
            raise MissingExtraError(
                "--foxglove needs the foxglove extra: pip install -e '.[foxglove]'"
            ) from error
        self._foxglove = foxglove
        self.context = foxglove.Context()
        self.server = foxglove.start_server(
            name="mapex", host=host, port=port, context=self.context
        )
        self.port = self.server.port
        self._channels: dict[str, Any] = {}
        log.info("Foxglove WebSocket server on ws://%s:%d", host, self.port)

    def write(self, outgoing: Outgoing) -> None:
        """Log `outgoing` as CDR on its ROS topic and as protobuf on its Foxglove topic."""
        for message in channel_messages(outgoing):
            self._channel(message).log(message.data, log_time=outgoing.stamp_ns)

    def topics(self) -> list[str]:
        """The channels made so far, sorted."""
        return sorted(self._channels)

    def close(self) -> None:
        self.server.stop()

    def _channel(self, message: ChannelMessage) -> Any:
        if message.topic not in self._channels:
            name, encoding, data = message.schema()
            schema = self._foxglove.Schema(name=name, encoding=encoding, data=data)
            self._channels[message.topic] = self._foxglove.Channel(
                message.topic, schema=schema, message_encoding=message.message_encoding,
                context=self.context,
            )  # fmt: skip
        return self._channels[message.topic]


class FoxgloveLive:
    """A `FoxgloveServer` fed by a follower of `run` (None: every run) on `session`."""

    def __init__(
        self, session: zenoh.Session, run: str | None = None, host: str = "127.0.0.1",
        port: int = FOXGLOVE_DEFAULT_PORT, config: Ros2Config | None = None,
    ) -> None:  # fmt: skip
        self.server = FoxgloveServer(host, port)
        translate = RunTranslator(self.server.write, config or Ros2Config(), with_foxglove=True)
        self.follower = RunFollower(session, translate, run)

    def close(self) -> None:
        self.follower.close()
        self.server.close()
