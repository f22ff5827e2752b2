"""A small Foxglove WebSocket protocol client for tests (foxglove/ws-protocol docs/spec.md).

It reads the server's JSON text operations (`serverInfo`, `advertise`, `unadvertise`,
`status`) and binary `messageData` frames (opcode 0x01, uint32 subscription id, uint64 log
time in ns, little-endian, then the payload), and can subscribe to every channel advertised,
also those advertised later, as a Foxglove app subscribing to all topics would.
"""

from __future__ import annotations

import json
import re
import struct
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import websocket

SUBPROTOCOL = "foxglove.sdk.v1"  # what the Foxglove SDK's server accepts
MESSAGE_DATA_OPCODE = 0x01
_MESSAGE_DATA_HEADER = struct.Struct("<BIQ")  # opcode, subscription id, log time (ns)
READ_TIMEOUT_S = 0.2  # one wait for a frame; `pump` loops until its deadline
_UNKNOWN_CHANNEL = re.compile(r"unknown channel id: (\d+)", re.IGNORECASE)


@dataclass
class Channel:
    """One advertised channel, as the server described it."""

    channel_id: int
    topic: str
    encoding: str
    schema_name: str


@dataclass
class FoxgloveClient:
    """One connection to a Foxglove WebSocket server; `pump` reads what it sends."""

    url: str
    subscribe_all: bool = True
    subprotocol: str = SUBPROTOCOL
    server_info: dict | None = None
    channels: dict[int, Channel] = field(default_factory=dict)  # advertised, not unadvertised
    unadvertised: list[int] = field(default_factory=list)  # channel ids, in order
    topic_of: dict[int, str] = field(default_factory=dict)  # every channel ever advertised
    statuses: list[dict] = field(default_factory=list)  # status operations, in order
    received: Counter = field(default_factory=Counter)  # messages by channel id
    received_by_topic: Counter = field(default_factory=Counter)  # messages by topic
    closed_by_server: bool = False
    _subscriptions: dict[int, int] = field(default_factory=dict)  # subscription id -> channel
    _socket: websocket.WebSocket | None = None

    def __post_init__(self) -> None:
        self._socket = websocket.create_connection(
            self.url, subprotocols=[self.subprotocol], timeout=READ_TIMEOUT_S
        )

    def subscribe(self, channel_ids: list[int]) -> None:
        """Subscribe to `channel_ids` (one new subscription id each) in one operation."""
        subscriptions = []
        for channel_id in channel_ids:
            subscription_id = len(self._subscriptions) + 1
            self._subscriptions[subscription_id] = channel_id
            subscriptions.append({"id": subscription_id, "channelId": channel_id})
        if subscriptions:
            self._send({"op": "subscribe", "subscriptions": subscriptions})

    def subscribed(self) -> set[int]:
        """The channel ids subscribed to."""
        return set(self._subscriptions.values())

    def pump(self, until: Callable[[FoxgloveClient], bool], deadline_s: float) -> bool:
        """Read frames until `until(self)` holds (True) or `deadline_s` passes or the server
        closes the connection (False)."""
        deadline = time.monotonic() + deadline_s
        while not until(self):
            if time.monotonic() > deadline or self.closed_by_server:
                return False
            self._read_one()
        return True

    def refused_channels(self) -> list[int]:
        """The channel ids of the server's 'Unknown channel ID: N' statuses (a subscription
        refused), in order."""
        found = (_UNKNOWN_CHANNEL.search(s["message"]) for s in self.statuses)
        return [int(match.group(1)) for match in found if match is not None]

    def silent_topics(self) -> list[str]:
        """Topics of the advertised channels that delivered no message yet (on any of their
        channels: a channel made again is the same topic)."""
        topics = {channel.topic for channel in self.channels.values()}
        return sorted(topic for topic in topics if not self.received_by_topic[topic])

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _send(self, operation: dict) -> None:
        assert self._socket is not None, "the client is closed"
        self._socket.send(json.dumps(operation))

    def _read_one(self) -> None:
        assert self._socket is not None, "the client is closed"
        try:
            opcode, data = self._socket.recv_data()
        except websocket.WebSocketTimeoutException:
            return
        except websocket.WebSocketConnectionClosedException:
            self.closed_by_server = True
            return
        if opcode == websocket.ABNF.OPCODE_TEXT:
            self._on_text(json.loads(data))
        elif opcode == websocket.ABNF.OPCODE_BINARY and data[0] == MESSAGE_DATA_OPCODE:
            _, subscription_id, _log_time_ns = _MESSAGE_DATA_HEADER.unpack_from(data)
            channel_id = self._subscriptions[subscription_id]
            self.received[channel_id] += 1
            self.received_by_topic[self.topic_of[channel_id]] += 1

    def _on_text(self, operation: dict) -> None:
        op = operation.get("op")
        if op == "serverInfo":
            self.server_info = operation
        elif op == "status":
            self.statuses.append(operation)
        elif op == "advertise":
            new = []
            for channel in operation["channels"]:
                self.channels[channel["id"]] = Channel(
                    channel["id"], channel["topic"], channel["encoding"], channel["schemaName"]
                )
                self.topic_of[channel["id"]] = channel["topic"]
                new.append(channel["id"])
            if self.subscribe_all:
                self.subscribe([c for c in new if c not in self.subscribed()])
        elif op == "unadvertise":
            for channel_id in operation["channelIds"]:
                self.channels.pop(channel_id, None)
                self.unadvertised.append(channel_id)
