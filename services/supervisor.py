"""Spawn `python -m module` children, forward their output, restart crashed servers, stop all.

services.up runs the world, the predictor workers and the planners as children of one
`Supervisor`. Each child gets a session (process group) of its own, so a terminal Ctrl-C
reaches only the supervisor, which then stops the children itself: SIGTERM, a grace period,
then SIGKILL of whatever is left and of its process group. Every output line of a child goes
to one log sink, prefixed with its name. The caller calls `poll()` in its own loop, which
restarts the servers that crashed; call a supervisor from one thread. `claim_hub` decides
whether services.up serves the well-known hub endpoint itself or joins the hub there;
`endpoint_silence` tells whether anything answers at a `--connect` endpoint.
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import errno
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import IO

from mapex.exit_codes import EXIT_USAGE
from services.codec import DEFAULT_SERVICES
from services.config import ServicesConfig
from services.serving import SUPERVISOR_PID_ENV

LogSink = Callable[[str], None]
_RECENT_LINES = 20  # lines kept per child for `last_words`


@dataclass(frozen=True)
class ProcessSpec:
    """A `python -m module *args` child.

    `restart=True` marks a long-lived server (the world, a predictor worker): the supervisor
    restarts it when it dies unexpectedly (a signal, or a non-zero exit other than 2: a usage
    error such as missing weights would only repeat). Planners finish and
    are not restarted. `cwd` (default: the supervisor's working directory) and `env`
    (variables added to the supervisor's environment) are there for children that need them.
    """

    name: str
    module: str
    args: tuple[str, ...] = ()
    restart: bool = False
    cwd: str | None = None
    env: Mapping[str, str] | None = field(default=None, hash=False)


@dataclass
class _Child:
    """One running (or exited) incarnation of a spec; `reported` once its exit was handled."""

    spec: ProcessSpec
    process: subprocess.Popen
    reported: bool = False


def write_to_stderr(line: str) -> None:
    """The default log sink: the line on the supervisor's stderr, flushed."""
    print(line, file=sys.stderr, flush=True)


class Supervisor:
    """The children of one machine: started by `start`, restarted by `poll`, ended by `stop`.

    `max_restarts` (default `services.supervisor_max_restarts`) caps the restarts of each
    name; `restarts` counts them. Used as a context manager, or not, every child is stopped
    at the latest when the interpreter exits (an `atexit` safety net).
    """

    def __init__(
        self,
        log_sink: LogSink | None = None,
        max_restarts: int | None = None,
        services: ServicesConfig = DEFAULT_SERVICES,
    ) -> None:
        self.log_sink = log_sink or write_to_stderr
        self.max_restarts = (
            services.supervisor_max_restarts if max_restarts is None else max_restarts
        )
        self.services = services
        self.restarts: dict[str, int] = {}
        self._recent: dict[str, collections.deque[str]] = {}  # each child's last lines
        self._children: dict[str, _Child] = {}
        self._forwarders: list[threading.Thread] = []
        self._sink_lock = threading.Lock()
        self._stopping = False
        self._guarded = False  # stop() registered with atexit

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def start(self, spec: ProcessSpec) -> subprocess.Popen:
        """Spawn `spec` in a new session, its merged stdout/stderr forwarded line by line."""
        current = self._children.get(spec.name)
        if current is not None and current.process.poll() is None:
            raise ValueError(f"a process named {spec.name!r} is already running")
        if not self._guarded:
            atexit.register(self.stop)
            self._guarded = True
        child = self._spawn(spec)
        self._children[spec.name] = child
        return child.process

    def poll(self) -> list[str]:
        """Handle every child that exited since the last call; return the names restarted.

        A `restart=True` child that died with a non-zero code or a signal is restarted until
        its name has used up `max_restarts`; every exit is logged once.
        """
        if self._stopping:
            return []
        restarted = []
        for name, child in list(self._children.items()):
            code = child.process.poll()
            if code is None or child.reported:
                continue
            child.reported = True
            if self._handle_exit(child, code):
                restarted.append(name)
        return restarted

    def process(self, name: str) -> subprocess.Popen:
        """The current process of `name` (a restart replaces it)."""
        child = self._children.get(name)
        if child is None:
            raise KeyError(f"no process named {name!r}")
        return child.process

    def last_words(self, name: str) -> str:
        """What `name` said last: its last recent line that reports an error, else its last
        line ("no output" when it printed nothing)."""
        recent = list(self._recent.get(name, ()))
        errors = [line for line in recent if "error" in line.lower()]
        return (errors or recent or ["no output"])[-1]

    def returncode(self, name: str) -> int | None:
        """The exit code of `name`'s current process (negative: killed by that signal), or None."""
        return self.process(name).poll()

    def is_running(self, name: str) -> bool:
        """Whether `name`'s current process has not exited yet."""
        return self.returncode(name) is None

    def wait(self, name: str, timeout_s: float | None) -> int | None:
        """Wait up to `timeout_s` for `name`'s current process; its exit code, or None."""
        try:
            return self.process(name).wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def kill(self, name: str, why: str) -> None:
        """SIGKILL `name`'s current process and its group, logging `why`; a server is then
        restarted by the next `poll` like any crashed one."""
        self._log(f"killing {name}: {why}")
        _signal_group(self.process(name), signal.SIGKILL)

    def stop(self, grace_s: float | None = None) -> None:
        """SIGTERM every child, wait up to `grace_s` (default `services.stop_grace_s`), then
        SIGKILL what is left and every child's process group. No child survives; idempotent."""
        grace_s = self.services.stop_grace_s if grace_s is None else grace_s
        self._stopping = True
        try:
            running = [c for c in self._children.values() if c.process.poll() is None]
            for child in running:
                _signal_group(child.process, signal.SIGTERM)
            deadline = time.monotonic() + grace_s
            for child in running:
                self._end(child, deadline, grace_s)
            for child in self._children.values():
                if not child.reported and child not in running:  # exited, poll() not told yet
                    self._log(
                        f"{child.spec.name} exited with {describe_exit(child.process.poll())}"
                    )
                child.reported = True
            for forwarder in self._forwarders:
                forwarder.join(grace_s)
            self._forwarders = [f for f in self._forwarders if f.is_alive()]
        finally:
            self._stopping = False
        if self._guarded:
            atexit.unregister(self.stop)
            self._guarded = False

    def _end(self, child: _Child, deadline: float, grace_s: float) -> None:
        """Wait for a SIGTERMed child until `deadline`, then SIGKILL it; kill its group."""
        name = child.spec.name
        try:
            code = child.process.wait(max(0.0, deadline - time.monotonic()))
            self._log(f"stopped {name} ({describe_exit(code)})")
        except subprocess.TimeoutExpired:
            child.process.kill()
            self._log(f"killed {name}: still running after the {grace_s:g} s grace period")
        _signal_group(child.process, signal.SIGKILL)  # any process it started and left behind
        try:
            child.process.wait(grace_s)
        except subprocess.TimeoutExpired:
            self._log(f"{name} (pid {child.process.pid}) did not die of SIGKILL")

    def _spawn(self, spec: ProcessSpec) -> _Child:
        env = {
            **os.environ,
            "PYTHONUNBUFFERED": "1",
            SUPERVISOR_PID_ENV: str(os.getpid()),  # children stop when orphaned
            **(spec.env or {}),
        }
        process = subprocess.Popen(
            [sys.executable, "-m", spec.module, *spec.args],
            cwd=spec.cwd,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        forwarder = threading.Thread(
            target=self._forward,
            args=(spec.name, process.stdout),
            name=f"forward {spec.name}",
            daemon=True,
        )
        forwarder.start()
        self._forwarders.append(forwarder)
        self._log(f"started {spec.name} (pid {process.pid})")
        return _Child(spec, process)

    def _handle_exit(self, child: _Child, code: int) -> bool:
        """Log an exit; restart the child when it is a crashed server with restarts left."""
        name = child.spec.name
        exit_text = f"{name} exited with {describe_exit(code)}"
        if not child.spec.restart or code == 0:
            self._log(exit_text)
            return False
        if code == EXIT_USAGE:
            self._log(f"{exit_text}; not restarted: a usage error would repeat")
            return False
        used = self.restarts.get(name, 0)
        if used >= self.max_restarts:
            self._log(f"{exit_text}; not restarted: gave up after {used} restarts")
            return False
        self.restarts[name] = used + 1
        try:
            self._children[name] = self._spawn(child.spec)
        except OSError as error:
            self._log(f"{exit_text}; could not restart it: {error}")
            return False
        self._log(f"{exit_text}; restarted ({used + 1}/{self.max_restarts})")
        return True

    def _forward(self, name: str, stream: IO[bytes]) -> None:
        """Send each output line of a child to the sink as it comes, until end of output."""
        with stream:
            for raw in stream:
                text = raw.decode(errors="replace").rstrip("\r\n")
                if text.strip():
                    self._recent.setdefault(name, collections.deque(maxlen=_RECENT_LINES))
                    self._recent[name].append(text.strip())
                self._emit(f"[{name}] {text}")

    def _log(self, message: str) -> None:
        self._emit(f"[supervisor] {message}")

    def _emit(self, line: str) -> None:
        # A closed or broken sink must not stop the draining: a child blocks on a full pipe.
        with self._sink_lock, contextlib.suppress(OSError, ValueError):
            self.log_sink(line)


def describe_exit(code: int) -> str:
    """`0`, `3`, or `-9 (SIGKILL)` for a child killed by a signal."""
    if code >= 0:
        return str(code)
    try:
        return f"{code} ({signal.Signals(-code).name})"
    except ValueError:
        return str(code)


def _signal_group(process: subprocess.Popen, signum: int) -> None:
    """Send `signum` to the process group a child leads (it was started in its own session)."""
    try:
        os.killpg(process.pid, signum)
    except (ProcessLookupError, PermissionError):  # the group is gone (or only a zombie left)
        if process.returncode is None:
            process.send_signal(signum)


def claim_hub(endpoint: str, services: ServicesConfig = DEFAULT_SERVICES) -> bool:
    """True when the TCP port of the `tcp/host:port` hub endpoint is free to listen on here
    (services.up then serves the hub itself); False when something already listens there or
    the address is not one of this machine's (services.up then connects to it).

    A bind probe with SO_REUSEADDR off decides; when it finds the port taken, a connect probe
    tells a listener from connections of a hub that just exited (TIME_WAIT), which do not
    keep a new hub from listening. ValueError for a non-tcp or malformed endpoint; OSError
    for other bind failures (e.g. a privileged port).
    """
    host, port = parse_tcp_endpoint(endpoint)
    try:
        family, _, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except socket.gaierror:
        raise ValueError(f"hub endpoint {endpoint!r}: cannot resolve host {host!r}") from None
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)
        try:
            probe.bind(address)
            return True
        except OSError as error:
            if error.errno == errno.EADDRNOTAVAIL:
                return False
            if error.errno != errno.EADDRINUSE:
                raise
    return _connect_refusal(family, address, services.hub_probe_timeout_s) is not None


def parse_tcp_endpoint(endpoint: str, protocols: tuple[str, ...] = ("tcp",)) -> tuple[str, int]:
    """(host, port) of a Zenoh `tcp/host:port` endpoint (IPv6 hosts in brackets), or of an
    endpoint of another of `protocols` written the same way (`tls/host:port`)."""
    protocol, slash, locator = endpoint.partition("/")
    address = locator.split("#", 1)[0].split("?", 1)[0]  # Zenoh config and metadata suffixes
    host, colon, port_text = address.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if protocol not in protocols or not slash:
        raise ValueError(f"hub endpoint {endpoint!r} is not a {protocols[0]}/host:port endpoint")
    if not colon or not host or not port_text.isdigit() or int(port_text) > 65535:
        raise ValueError(f"hub endpoint {endpoint!r} is not of the form {protocol}/host:port")
    return host, int(port_text)


TCP_PROTOCOLS = ("tcp", "tls")  # Zenoh link protocols over one TCP connection to host:port


def endpoint_silence(endpoint: str, timeout_s: float) -> str | None:
    """Why nothing answers at a Zenoh endpoint ("connection refused", "no answer within
    1.0 s", "cannot resolve host ..."), or None when something accepts a TCP connection
    at its host:port (the endpoint's protocol is one of `TCP_PROTOCOLS`) or the endpoint
    cannot be probed this way (udp/, quic/, unixsock-stream/, ...: Zenoh says it then).
    ValueError for a tcp/ or tls/ endpoint without a host:port."""
    if endpoint.partition("/")[0] not in TCP_PROTOCOLS:
        return None
    host, port = parse_tcp_endpoint(endpoint, TCP_PROTOCOLS)
    try:
        addresses = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror:
        return f"cannot resolve host {host!r}"
    reasons = []
    for family, _, _, _, address in addresses:
        reason = _connect_refusal(family, address, timeout_s)
        if reason is None:
            return None
        reasons.append(reason)
    return "; ".join(dict.fromkeys(reasons))


def _connect_refusal(family: int, address: tuple, timeout_s: float) -> str | None:
    """Why a TCP connect to `address` failed, or None when something accepted it."""
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.settimeout(timeout_s)
        try:
            probe.connect(address)
            return None
        except TimeoutError:
            return f"no answer within {timeout_s:g} s"
        except OSError as error:
            return (error.strerror or str(error)).lower()
