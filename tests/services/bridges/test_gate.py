"""The connection bounds of the outside tools that serve sockets (services.bridges.gate): the
cap on connections at once, and the relay in front of the Foxglove SDK's server (its cap,
its handshake deadline, and a client that does not read: a bounded buffer, then closed),
against a plain TCP backend on loopback.
"""

from __future__ import annotations

import socket
import socketserver
import threading
import time

import pytest
from service_processes import read_until_closed, until

from services.bridges.gate import BUSY_RESPONSE, ConnectionSlots, TcpRelay

DEADLINE_S = 10.0  # one exchange on a shared 2-core machine
FLOOD_BYTES = 256 * 2**20  # what the backend would send a client that never reads
HELD_BYTES_AT_MOST = 64 * 2**20  # relay buffer + every kernel buffer on the way, generously
SMALL_RCVBUF = 4096  # the non-reading client's receive buffer (no autotuning)
CHUNK = 64 * 1024


class _Backend(socketserver.ThreadingTCPServer):
    """Reads a request head, answers `OK`, then echoes, or floods when the head says so."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _BackendHandler)
        self.sent = 0  # bytes flooded so far
        threading.Thread(target=self.serve_forever, daemon=True).start()

    @property
    def port(self) -> int:
        return int(self.server_address[1])


class _BackendHandler(socketserver.BaseRequestHandler):
    server: _Backend

    def handle(self) -> None:
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.request.recv(4096)
            if not chunk:
                return
            head += chunk
        self.request.sendall(b"OK\r\n")
        try:
            if b"flood" in head:
                block = bytes(CHUNK)
                while self.server.sent < FLOOD_BYTES:
                    self.request.sendall(block)
                    self.server.sent += len(block)
            else:
                while data := self.request.recv(4096):
                    self.request.sendall(data)
        except OSError:  # the relay closed the connection
            pass


@pytest.fixture
def backend():
    served = _Backend()
    yield served
    served.shutdown()
    served.server_close()


def _relay(backend: _Backend, **options) -> TcpRelay:
    settings = {"max_clients": 2, "handshake_timeout_s": DEADLINE_S, "send_timeout_s": DEADLINE_S,
                "buffer_bytes": CHUNK, **options}  # fmt: skip
    return TcpRelay("127.0.0.1", 0, ("127.0.0.1", backend.port), **settings)


def _client(relay: TcpRelay, head: bytes = b"GET / HTTP/1.1\r\n\r\n", **socket_options):
    connection = socket.socket()
    for option, value in socket_options.items():
        connection.setsockopt(socket.SOL_SOCKET, getattr(socket, option), value)
    connection.settimeout(DEADLINE_S)
    connection.connect(("127.0.0.1", relay.port))
    connection.sendall(head)
    return connection


def test_connection_slots_cap_what_is_held_at_once_and_count():
    slots = ConnectionSlots(2)
    assert slots.take() and slots.take() and not slots.take()
    assert (slots.in_use, slots.most, slots.refused) == (2, 2, 1)
    slots.give_back()
    assert slots.take() and slots.in_use == 2
    for _ in range(2):
        slots.give_back()
    with pytest.raises(RuntimeError):
        slots.give_back()
    with pytest.raises(ValueError):
        ConnectionSlots(0)


def test_the_relay_serves_max_clients_and_answers_one_more_503(backend):
    relay = _relay(backend)
    try:
        first, second = _client(relay), _client(relay)
        for client in (first, second):
            assert client.recv(4) == b"OK\r\n"
        second.sendall(b"ping")
        assert second.recv(4) == b"ping"  # relayed both ways
        until(lambda: relay.slots.in_use == 2, "both clients to be counted")
        with _client(relay) as third:
            assert read_until_closed(third) == BUSY_RESPONSE  # and closed at once
        assert relay.slots.refused == 1
        first.close()
        until(lambda: relay.slots.in_use == 1, "the closed client's slot to be free")
        with _client(relay) as fourth:
            assert fourth.recv(4) == b"OK\r\n"
        second.close()
    finally:
        relay.close()


def test_a_handshake_that_does_not_arrive_in_time_is_closed_and_frees_its_slot(backend):
    relay = _relay(backend, max_clients=1, handshake_timeout_s=0.5)
    try:
        began = time.monotonic()
        with _client(relay, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n") as slow:  # no blank line
            for _ in range(3):  # more of the head, slowly: the deadline is for all of it
                time.sleep(0.1)
                slow.sendall(b"X: y\r\n")
            assert read_until_closed(slow) == b""  # closed unanswered
        assert time.monotonic() - began < DEADLINE_S / 2
        assert relay.timed_out == 1
        until(lambda: relay.slots.in_use == 0, "the slot to be free")
        with _client(relay) as next_one:
            assert next_one.recv(4) == b"OK\r\n"
    finally:
        relay.close()


def test_a_client_that_does_not_read_holds_a_bounded_buffer_and_is_closed(backend):
    """The relay stops reading the backend for a client that takes nothing (so the backend
    sends a bounded amount, not its 256 MiB), and closes that client after the send
    timeout; another client is served meanwhile."""
    relay = _relay(backend, send_timeout_s=1.0)
    try:
        stalled = _client(relay, b"GET /flood HTTP/1.1\r\n\r\n", SO_RCVBUF=SMALL_RCVBUF)
        until(lambda: relay.stalled == 1, "the stalled client to be closed", DEADLINE_S)
        assert backend.sent < HELD_BYTES_AT_MOST, backend.sent
        until(lambda: relay.slots.in_use == 0, "its slot to be free")
        with _client(relay) as other:
            assert other.recv(4) == b"OK\r\n"
        stalled.close()
    finally:
        relay.close()


def test_a_taken_port_is_an_os_error_and_close_ends_every_connection(backend):
    relay = _relay(backend)
    with pytest.raises(OSError):
        TcpRelay("127.0.0.1", relay.port, ("127.0.0.1", backend.port), 1, 1.0, 1.0, CHUNK)
    client = _client(relay)
    assert client.recv(4) == b"OK\r\n"
    relay.close()
    assert read_until_closed(client) == b""
    client.close()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", relay.port), timeout=DEADLINE_S)
