"""Watch runs live in a browser: `python -m services.web`, a page fed by Server-Sent Events.

Follows every robot of one run (`--run`), or of every run, with
`services.bridges.follow.RunFollower`, and serves the page, a JSON snapshot (`GET /state`)
and an event stream (`GET /events`) with the standard library's HTTP server, on loopback
only unless `--allow-remote`, `WebConfig.max_connections` connections at once (a thread
each; one more is answered 503), each request's head within `request_timeout_s` and each
write within `send_timeout_s`, and each stream's queue bounded (`web_state.EventClient`).
`services.up --web` and `services.evaluate --web` run this command as a child process;
`WebView` is the server for use inside another process; the state and the events are
`services.bridges.web_state`. Routes, event formats, throttling and the page's hooks for
tests: docs/protocol.md#the-browser-view-http-routes-and-sse-events; what the page shows:
docs/interop.md#the-browser-view-servicesbridgesweb.
"""

from __future__ import annotations

import argparse
import io
import ipaddress
import json
import logging
import socket
import socketserver
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import urlsplit

import zenoh

from mapex.exit_codes import EXIT_USAGE
from services.bridges.follow import MAP_KIND_OF_TOPIC, RunFollower, Update
from services.bridges.gate import LISTEN_BACKLOG, ConnectionSlots, refuse
from services.bridges.web_state import (
    EventClient,
    MapThrottle,
    ViewState,
    encode_update,
    final_event,
    frame_key,
    sse_frame,
)
from services.config import DEFAULT_WEB, WebConfig
from services.keys import run_id_problem
from services.serving import (
    configure_logging,
    port_number,
    positive_number,
    stop_on_signals,
    wait_for,
)
from services.zenoh_config import (
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
    zenoh_config_from_args,
)

log = logging.getLogger("services.web")


LOCAL_HOST_NAMES = ("localhost",)  # host names accepted as loopback without --allow-remote
PAGE_PACKAGE, PAGE_FOLDER = "services.bridges", "web_page"
PAGE_FILES = {  # URL path -> (file of services/bridges/web_page, content type)
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/app.js": ("app.js", "text/javascript; charset=utf-8"),
    "/style.css": ("style.css", "text/css; charset=utf-8"),
}
JSON_TYPE = "application/json"
EVENT_STREAM_TYPE = "text/event-stream"


# ---------------------------------------------------------------------------- hosts


def is_loopback_host(host: str) -> bool:
    """Whether `host` (an IP address or a name) names this machine's loopback interface."""
    if host.lower() in LOCAL_HOST_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_host(host: str, allow_remote: bool) -> None:
    """ValueError (one line) for a host beyond loopback without `allow_remote`."""
    if not allow_remote and not is_loopback_host(host):
        raise ValueError(
            f"--host {host!r} is not a loopback address: the view has no authentication, "
            "add --allow-remote to serve it beyond this machine"
        )


def host_header_allowed(header: str | None, allow_remote: bool) -> bool:
    """Whether a request's Host header may be answered: a loopback one, or any with
    `allow_remote` (a loopback-only view refuses rebound DNS names)."""
    if allow_remote:
        return True
    if not header:
        return False
    name = urlsplit(f"//{header}").hostname
    return name is not None and is_loopback_host(name)


# ---------------------------------------------------------------------------- the view


def load_page_files() -> dict[str, tuple[bytes, str]]:
    """URL path -> (body, content type) of the page's files, read from the package data."""
    folder = resources.files(PAGE_PACKAGE).joinpath(PAGE_FOLDER)
    return {
        path: (folder.joinpath(name).read_bytes(), content_type)
        for path, (name, content_type) in PAGE_FILES.items()
    }


class WebView:
    """The browser view of `run` (None: every run) over an open Zenoh session.

    The constructor binds the HTTP port (OSError, one line naming host and port, when it is
    taken; ValueError for a host beyond loopback without `allow_remote`); `start` follows
    the run(s) and serves on threads of its own; `close` stops both (the session stays open:
    it is the caller's).
    Usable as a context manager (`with WebView(...) as view:` starts and closes it).
    """

    def __init__(
        self,
        session: zenoh.Session,
        run: str | None = None,
        config: WebConfig = DEFAULT_WEB,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        check_host(config.host, config.allow_remote)
        self.session, self.run, self.config, self.clock = session, run, config, clock
        self.page_files = load_page_files()
        self.state = ViewState(config, run)
        self.throttle = MapThrottle(1.0 / config.map_events_per_s)
        self.events_sent = 0
        self._clients: set[EventClient] = set()
        self._lock = threading.Lock()
        self._streams_changed = threading.Condition(self._lock)
        self._closing = threading.Event()
        self._follower: RunFollower | None = None
        self._threads: list[threading.Thread] = []
        try:
            self.server = _ViewServer((config.host, config.port), _Handler, self)
        except OSError as error:  # one line naming the address, e.g. a port already taken
            reason = error.strerror or str(error)
            raise OSError(f"cannot serve on {config.host} port {config.port}: {reason}") from None

    @property
    def port(self) -> int:
        """The port served (the one picked when the config asked for port 0)."""
        return int(self.server.server_address[1])

    @property
    def url(self) -> str:
        """The page's URL."""
        host = self.config.host
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/"

    @property
    def clients(self) -> int:
        """How many `/events` streams are open."""
        with self._lock:
            return len(self._clients)

    @property
    def connections(self) -> ConnectionSlots:
        """The HTTP connections served now (`in_use`), at most, and refused at the cap."""
        return self.server.slots

    def start(self) -> WebView:
        """Follow the run(s) and serve, on threads of their own; returns self."""
        self._follower = RunFollower(self.session, self.on_update, self.run)
        for target, name in ((self.server.serve_forever, "web http"), (self._flush, "web flush")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def close(self) -> None:
        """Stop following, end every stream once what is queued for it is sent (at most
        `close_timeout_s`), stop serving and free the port."""
        self._closing.set()
        if self._follower is not None:
            self._follower.close()
        if self._threads:
            self.server.shutdown()
        with self._lock:
            for client in self._clients:
                client.close(drain=True)
            self._streams_changed.wait_for(lambda: not self._clients, self.config.close_timeout_s)
            self._clients.clear()
        for thread in self._threads:
            thread.join(self.config.close_timeout_s)
        self.server.server_close()
        dropped = 0 if self._follower is None else self._follower.dropped
        slots = self.server.slots
        log.info(
            "stopped: %d events sent, %d malformed messages dropped, %d connections at most, "
            "%d refused",
            self.events_sent, dropped, slots.most, slots.refused,
        )  # fmt: skip

    def __enter__(self) -> WebView:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def subscribe(self) -> tuple[EventClient, bytes]:
        """A new stream's client and its first frame, the snapshot, taken atomically with
        the subscription (so every later update reaches the client, none is missed)."""
        client = EventClient(
            self.config.client_max_queued_events, self.config.client_max_queued_bytes
        )
        with self._lock:
            snapshot = sse_frame("snapshot", self.state.snapshot())
            if not self._closing.is_set():
                self._clients.add(client)
            else:
                client.close()
        return client, snapshot

    def unsubscribe(self, client: EventClient) -> None:
        """Forget a stream's client (its browser went away)."""
        client.close()
        with self._lock:
            self._clients.discard(client)
            self._streams_changed.notify_all()

    def snapshot_json(self) -> bytes:
        """The `/state` document as JSON bytes."""
        with self._lock:
            snapshot = self.state.snapshot()
        return json.dumps(snapshot, separators=(",", ":"), allow_nan=False).encode()

    def on_update(self, update: Update) -> None:
        """Take one update in (the follower's sink, on its one thread; callable directly to
        feed updates from elsewhere): remember it, then send it now or hold a map back; then
        a `final` event when it changed how its run ended."""
        run = update.run
        with self._lock:
            final_before = self.state.final(run)
            if not self.state.apply(update):
                return
            if update.topic in MAP_KIND_OF_TOPIC:
                update = self.throttle.offer(update, self.clock())
            if update is not None:
                self._broadcast(update)
            if (final := self.state.final(run)) != final_before:
                self._send(sse_frame("final", final_event(run, final)))

    def _flush(self) -> None:
        """Send held-back maps as their turn comes, until `close`."""
        while not self._closing.wait(self.config.flush_poll_s):
            with self._lock:
                for update in self.throttle.due(self.clock()):
                    self._broadcast(update)

    def _broadcast(self, update: Update) -> None:
        """Queue `update`'s event for every client (the lock is held)."""
        self._send(sse_frame("update", encode_update(update)), frame_key(update))

    def _send(self, frame: bytes, key: tuple | None = None) -> None:
        """Queue `frame` for every client, in place of its queued frame of `key` (the lock
        is held); drop clients too far behind."""
        self.events_sent += 1
        for client in list(self._clients):
            if not client.push(frame, key) and not self._closing.is_set():  # closing: it drains
                self._clients.discard(client)
                log.info(
                    "dropped a stream %d events or %d bytes behind (its browser reconnects)",
                    self.config.client_max_queued_events,
                    self.config.client_max_queued_bytes,
                )


# ---------------------------------------------------------------------------- HTTP


class _ViewServer(ThreadingHTTPServer):
    """A threading HTTP server that knows its view; IPv6 when the host is an IPv6 address.

    It serves at most `max_connections` connections at once, a thread each: one more is
    answered 503 and closed at once, on the accepting thread.
    """

    daemon_threads = True  # open streams never hold the process
    request_queue_size = LISTEN_BACKLOG

    def __init__(self, address: tuple[str, int], handler: type, view: WebView) -> None:
        self.view = view
        self.slots = ConnectionSlots(view.config.max_connections)
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        super().__init__(address, handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        """Serve the connection on a thread of its own while a slot is free, else refuse it."""
        if not self.slots.take():
            refuse(request)
            log.debug("refused %s: %d connections served", client_address, self.slots.limit)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.give_back()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.give_back()

    def server_bind(self) -> None:
        """Bind without HTTPServer's reverse DNS lookup of the host (it can stall offline)."""
        socketserver.TCPServer.server_bind(self)
        self.server_name, self.server_port = str(self.server_address[0]), self.server_address[1]

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A browser that went away is not an error; anything else is logged with its trace."""
        error = sys.exc_info()[1]
        if isinstance(error, ConnectionError):
            log.debug("client %s went away: %s", client_address, error)
        else:
            log.exception("failed to answer %s", client_address)


class _DeadlineReader(io.RawIOBase):
    """A connection's bytes, read until `deadline` (time.monotonic) at the latest: a read
    past it raises TimeoutError; None: no deadline (the socket's own timeout)."""

    def __init__(self, connection: socket.socket, deadline: float | None) -> None:
        super().__init__()
        self.connection, self.deadline = connection, deadline

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        if self.deadline is not None:
            left = self.deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("the request's head did not arrive in time")
            self.connection.settimeout(left)
        return self.connection.recv_into(buffer)


class _Handler(BaseHTTPRequestHandler):
    """GET the page's files, /state and /events; everything else is 404.

    The request's line and headers must arrive within `request_timeout_s` of the
    connection's start, and every write is given `send_timeout_s`: a timeout ends the
    connection (BaseHTTPRequestHandler logs it and closes)."""

    server: _ViewServer
    server_version = "mapex-web"

    def setup(self) -> None:
        super().setup()
        config = self.server.view.config
        self.rfile.close()  # the buffered file of the socket, replaced by one with a deadline
        self._head_reader = _DeadlineReader(
            self.connection, time.monotonic() + config.request_timeout_s
        )
        self.rfile = io.BufferedReader(self._head_reader)

    def parse_request(self) -> bool:
        """Read the headers (within the deadline), then give writes their own timeout."""
        parsed = super().parse_request()
        self._head_reader.deadline = None
        self.connection.settimeout(self.server.view.config.send_timeout_s)
        return parsed

    def do_GET(self) -> None:  # noqa: N802 (the name http.server dispatches to)
        view = self.server.view
        if not host_header_allowed(self.headers.get("Host"), view.config.allow_remote):
            self._send(HTTPStatus.FORBIDDEN, b"not a loopback Host\n", "text/plain")
            return
        path = urlsplit(self.path).path
        try:
            if path in view.page_files:
                self._send(HTTPStatus.OK, *view.page_files[path])
            elif path == "/state":
                self._send(HTTPStatus.OK, view.snapshot_json(), JSON_TYPE)
            elif path == "/events":
                self._stream(view)
            else:
                self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")
        except ConnectionError as error:  # the browser closed the tab or reloaded
            log.debug("client went away during %s: %s", path, error)

    def _send(self, status: HTTPStatus, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _stream(self, view: WebView) -> None:
        """The `/events` stream: the snapshot, then updates and keep-alives until closed."""
        client, snapshot = view.subscribe()
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", EVENT_STREAM_TYPE)
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(f"retry: {view.config.retry_ms}\n\n".encode() + snapshot)
            while (frame := client.next_frame(view.config.keepalive_s)) is not None:
                self.wfile.write(frame)
        finally:
            view.unsubscribe(client)

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (the base's name)
        log.debug("%s %s", self.address_string(), format % args)


# ---------------------------------------------------------------------------- entry points


def main(
    config: zenoh.Config,
    run: str | None = None,
    host: str | None = None,
    port: int | None = None,
    stop: threading.Event | None = None,
    web: WebConfig = DEFAULT_WEB,
    on_ready: Callable[[str], None] | None = None,
) -> None:
    """Serve the view of `run` (None: every run) on `host`:`port` (None: `web`'s) until `stop`.

    `on_ready` is told the URL once serving. Raises ZenohConfigError when the session is
    refused, OSError when the port cannot be bound, ValueError for a host beyond loopback
    without `web.allow_remote`.
    """
    web = replace(
        web, host=web.host if host is None else host, port=web.port if port is None else port
    )
    check_host(web.host, web.allow_remote)
    session = open_session(config)
    try:
        with WebView(session, run, web) as view:
            log.info("serving %s (following %s)", view.url, f"run {run}" if run else "every run")
            if on_ready is not None:
                on_ready(view.url)
            wait_for(stop or threading.Event())
    finally:
        session.close()


def build_parser() -> argparse.ArgumentParser:
    """The command-line flags: run, where to serve, map rate and Zenoh's."""
    parser = argparse.ArgumentParser(
        prog="python -m services.web", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--run", default=None, help="run id to follow (default: every run)")
    parser.add_argument(
        "--host",
        default=DEFAULT_WEB.host,
        help="address to serve on, loopback unless --allow-remote (default: %(default)s)",
    )
    parser.add_argument(
        "--port",
        type=port_number,
        default=DEFAULT_WEB.port,
        help="port to serve on, 0 for any free one (default: %(default)s)",
    )
    parser.add_argument(
        "--allow-remote",
        action="store_true",
        help="serve a non-loopback --host (the view has no authentication)",
    )
    parser.add_argument(
        "--map-events-per-s",
        type=positive_number("per second"),
        default=DEFAULT_WEB.map_events_per_s,
        help="maps sent per second per robot and map kind, at most (default: %(default)s)",
    )
    add_zenoh_arguments(parser)
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    """Parse flags, serve until SIGINT/SIGTERM; 0 on a clean stop, 2 on bad flags or a port
    or Zenoh config that cannot be used."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _check_flags(parser, args)
    configure_logging(f"web[{args.run or 'all'}]")
    stop = stop_on_signals()
    web = replace(
        DEFAULT_WEB, allow_remote=args.allow_remote, map_events_per_s=args.map_events_per_s
    )
    try:
        main(zenoh_config_from_args(args), args.run, args.host, args.port, stop, web)
    except (ZenohConfigError, OSError) as error:
        log.error("%s", error)
        return EXIT_USAGE
    return 0


def _check_flags(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """argparse-style one-line errors (exit 2) for flag values argparse cannot check itself."""
    if args.run is not None and (problem := run_id_problem(args.run)) is not None:
        parser.error(problem)
    try:
        check_host(args.host, args.allow_remote)
    except ValueError as error:
        parser.error(str(error))


if __name__ == "__main__":
    sys.exit(run_cli())
