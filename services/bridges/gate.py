"""Bounds on what the outside tools that serve sockets (the browser view, the Foxglove server)
give a client: a cap on the connections served at once (one more is answered 503 and
closed at once), and `TcpRelay`, the capped front of a server of another library (the
Foxglove SDK's WebSocket server, which caps neither its clients nor its handshakes).

The relay serves the public address. A client beyond the cap gets `BUSY_RESPONSE`; one
whose handshake (an HTTP request head, up to its blank line) has not arrived within the
handshake timeout is closed; every other is relayed to the backend both ways through
bounded buffers: while a client takes nothing, the relay stops reading the backend for it
(so the backend's own per-client queue is the one that fills, and drops), and a client that
has taken nothing for the send timeout is closed. docs/design.md#trust.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading

BUSY_RESPONSE = (
    b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\n"
    b"Content-Length: 5\r\nConnection: close\r\n\r\nbusy\n"
)
HEAD_END = b"\r\n\r\n"  # the end of an HTTP request head
MAX_HEAD_BYTES = 16 * 1024  # a WebSocket handshake is well under 2 KiB
RELAY_CHUNK_BYTES = 64 * 1024  # read at most this much at once from either side
LISTEN_BACKLOG = 128  # connections the kernel queues before they are accepted
STOP_TIMEOUT_S = 5.0  # how long `TcpRelay.close` waits for its thread
BUSY_READ_S = 0.05  # how long a client refused at the cap is given to send its request

# how reading a request head or relaying can end, besides a timeout
_HEAD_ERRORS = (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError)

log = logging.getLogger("services.gate")


class ConnectionSlots:
    """At most `limit` connections at once: `take` one (False at the cap: refuse the
    connection), `give_back` it when the connection ends. Thread-safe; counts what it saw."""

    def __init__(self, limit: int) -> None:
        if limit < 1:
            raise ValueError(f"a cap of {limit} connections serves nobody")
        self.limit = limit
        self.most = 0  # the most connections held at once
        self.refused = 0  # connections refused at the cap
        self._in_use = 0
        self._lock = threading.Lock()

    @property
    def in_use(self) -> int:
        with self._lock:
            return self._in_use

    def take(self) -> bool:
        with self._lock:
            if self._in_use >= self.limit:
                self.refused += 1
                return False
            self._in_use += 1
            self.most = max(self.most, self._in_use)
            return True

    def give_back(self) -> None:
        with self._lock:
            if self._in_use <= 0:
                raise RuntimeError("a connection slot given back that was not taken")
            self._in_use -= 1


def refuse(connection: socket.socket) -> None:
    """Answer `BUSY_RESPONSE` on an accepted connection and close it, never waiting."""
    try:
        connection.setblocking(False)
        with contextlib.suppress(OSError):  # what the client sent so far: a close with unread
            connection.recv(MAX_HEAD_BYTES)  # data would reset the connection, losing the 503
        connection.send(BUSY_RESPONSE)
    except OSError:  # gone already, or its buffer full: it is closed all the same
        pass
    finally:
        connection.close()


class TcpRelay:
    """Serves `host`:`port` (bound by the constructor: OSError when taken) and relays each
    client to `backend` (host, port), `max_clients` at once, on a thread of its own.

    `port` is the one bound (the one picked for port 0); `close` stops serving and ends
    every relayed connection.
    """

    def __init__(
        self,
        host: str,
        port: int,
        backend: tuple[str, int],
        max_clients: int,
        handshake_timeout_s: float,
        send_timeout_s: float,
        buffer_bytes: int,
        name: str = "relay",
    ) -> None:
        self.backend, self.slots = backend, ConnectionSlots(max_clients)
        self.handshake_timeout_s, self.send_timeout_s = handshake_timeout_s, send_timeout_s
        self.buffer_bytes = buffer_bytes
        self.timed_out = 0  # handshakes that did not arrive in time
        self.stalled = 0  # clients closed for taking nothing for the send timeout
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._listener = socket.create_server((host, port), family=family, backlog=LISTEN_BACKLOG)
        self.port = int(self._listener.getsockname()[1])
        self._open: dict[asyncio.Task, list[asyncio.StreamWriter]] = {}  # each client's sides
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.base_events.Server | None = None
        started = threading.Event()
        failure: list[BaseException] = []
        self._thread = threading.Thread(
            target=self._run, args=(started, failure), name=f"{name} relay", daemon=True
        )
        self._thread.start()
        started.wait()
        if failure:
            self._listener.close()
            raise failure[0]

    def close(self) -> None:
        """Stop accepting, end every relayed connection and stop the thread."""
        if not self._thread.is_alive():
            return
        with contextlib.suppress(RuntimeError, TimeoutError, asyncio.TimeoutError):
            asyncio.run_coroutine_threadsafe(self._stop(), self._loop).result(STOP_TIMEOUT_S)
        with contextlib.suppress(RuntimeError):  # the loop closed already
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(STOP_TIMEOUT_S)

    def _run(self, started: threading.Event, failure: list[BaseException]) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._server = self._loop.run_until_complete(
                asyncio.start_server(self._serve, sock=self._listener, limit=MAX_HEAD_BYTES)
            )
        except BaseException as error:  # noqa: BLE001 (handed to the constructor's thread)
            failure.append(error)
            started.set()
            self._loop.close()
            return
        started.set()
        try:
            self._loop.run_forever()
        finally:
            self._loop.close()

    async def _stop(self) -> None:
        """Stop accepting and end every connection by closing its sockets (no task is
        cancelled: Python 3.11's `wait_for` can swallow a cancellation)."""
        if self._server is not None:
            self._server.close()
        for sides in self._open.values():
            for side in sides:
                side.transport.abort()
        if self._open:
            await asyncio.wait(list(self._open), timeout=STOP_TIMEOUT_S)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One client: refused at the cap, else its head read in time, then relayed."""
        if not self.slots.take():
            # its request first, if it comes at once: closing a socket with unread data
            # resets the connection, and the client may lose the answer
            with contextlib.suppress(asyncio.TimeoutError, *_HEAD_ERRORS):
                await asyncio.wait_for(reader.readuntil(HEAD_END), BUSY_READ_S)
            writer.write(BUSY_RESPONSE)
            writer.close()
            return
        task = asyncio.current_task()
        sides = [writer]
        if task is not None:
            self._open[task] = sides
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(HEAD_END), self.handshake_timeout_s)
            except asyncio.TimeoutError:
                self.timed_out += 1
                return
            backend_reader, upstream = await asyncio.open_connection(
                *self.backend, limit=RELAY_CHUNK_BYTES
            )
            sides.append(upstream)
            for side in sides:
                side.transport.set_write_buffer_limits(high=self.buffer_bytes)
            upstream.write(head)
            await self._relay(reader, writer, backend_reader, upstream)
        except _HEAD_ERRORS as error:
            log.debug("relayed client ended: %s", error)
        finally:
            for side in sides:
                side.close()
            self.slots.give_back()
            if task is not None:
                self._open.pop(task, None)

    async def _relay(
        self,
        client_reader: asyncio.StreamReader,
        client: asyncio.StreamWriter,
        backend_reader: asyncio.StreamReader,
        backend: asyncio.StreamWriter,
    ) -> None:
        """Both directions until either ends (EOF, an error, or a stalled client); then
        both sockets are closed, which ends the other direction too: after what is buffered
        is sent, or at once for a stalled client (and for anyone after the send timeout)."""
        directions = [
            asyncio.ensure_future(self._pipe(backend_reader, client, to_client=True)),
            asyncio.ensure_future(self._pipe(client_reader, backend, to_client=False)),
        ]
        done, _ = await asyncio.wait(directions, return_when=asyncio.FIRST_COMPLETED)
        stalled = any(isinstance(d.exception(), asyncio.TimeoutError) for d in done)
        for side in (client, backend):
            if stalled:
                side.transport.abort()
            else:
                side.close()
        _, pending = await asyncio.wait(directions, timeout=self.send_timeout_s)
        if pending:
            for side in (client, backend):
                side.transport.abort()
        for ended in await asyncio.gather(*directions, return_exceptions=True):
            if isinstance(ended, BaseException):
                log.debug("relay direction ended: %s", ended)

    async def _pipe(
        self, source: asyncio.StreamReader, sink: asyncio.StreamWriter, to_client: bool
    ) -> None:
        while chunk := await source.read(RELAY_CHUNK_BYTES):
            sink.write(chunk)
            try:
                await asyncio.wait_for(sink.drain(), self.send_timeout_s)
            except asyncio.TimeoutError:
                if to_client:
                    self.stalled += 1
                    log.info("closed a client that took nothing for %g s", self.send_timeout_s)
                raise
