"""Two hosts on one machine: two Linux network namespaces joined by a veth pair.

Host A and host B each get a namespace of their own with its loopback up and one end of a
veth pair, addressed inside the namespace only (`ADDRESS_A`, `ADDRESS_B`, a /30 of the
private 10.231/16 block): nothing is added to, or changed in, the namespace the test runs
in, and a process in one namespace reaches the other only through the veth link, by the
other's address (each has a loopback of its own, so 127.0.0.1 never crosses). Processes are
started with `ip netns exec`; `close` SIGKILLs every process left in the two namespaces
(whoever started it: a supervisor's children too) and deletes them, links included.

Making namespaces needs root (CAP_SYS_ADMIN) and the `ip` command: where that fails,
`two_hosts` raises NamespaceError with one line saying why.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from service_processes import REPO_ROOT, STOP_DEADLINE_S
from up_processes import kill_quietly

PREFIX_BITS = 30  # a point-to-point link: two addresses
ADDRESS_A = "10.231.0.1"
ADDRESS_B = "10.231.0.2"
IP_TIMEOUT_S = 10.0  # one `ip` command
HOSTS = ("a", "b")

# `python -c JOIN_PROBE CONFIG_FILE`: open a client session from CONFIG_FILE, print the
# routers it is linked to and exit 0, or print why Zenoh refused it and exit 2.
JOIN_PROBE = """
import sys
from services.zenoh_config import ZenohConfigError, open_session, zenoh_config
try:
    session = open_session(zenoh_config(config_file=sys.argv[1]))
except ZenohConfigError as error:
    print(error)
    sys.exit(2)
print("joined", [str(zid) for zid in session.info.routers_zid()])
session.close()
"""


class NamespaceError(RuntimeError):
    """The namespaces could not be made (not root, no `ip`, EPERM): one line saying why."""


@dataclass
class TwoHosts:
    """Namespaces `a` and `b`, linked; processes started in them by `spawn`/`run`."""

    tag: str
    namespaces: dict[str, str] = field(default_factory=dict)  # host -> namespace name
    addresses: dict[str, str] = field(default_factory=lambda: {"a": ADDRESS_A, "b": ADDRESS_B})
    processes: list[subprocess.Popen] = field(default_factory=list)

    def launcher(self, host: str) -> list[str]:
        """The command prefix that runs a command on `host`."""
        return ["ip", "netns", "exec", self.namespaces[host]]

    def spawn(
        self,
        host: str,
        argv: Sequence[str],
        log_path: Path,
        env: dict[str, str] | None = None,
    ) -> subprocess.Popen:
        """Start `argv` (`python` = this interpreter) on `host` in a session of its own,
        logging stdout and stderr to `log_path`; `close` kills it if it is still running."""
        with open(log_path, "wb") as log:
            process = subprocess.Popen(
                [*self.launcher(host), *_python(argv)],
                cwd=REPO_ROOT,
                stdout=log,
                stderr=subprocess.STDOUT,
                env={**os.environ, **(env or {})},
                start_new_session=True,
            )
        self.processes.append(process)
        return process

    def run(self, host: str, argv: Sequence[str], timeout_s: float) -> subprocess.CompletedProcess:
        """Run `argv` on `host` to its end (stdout and stderr merged, text)."""
        return subprocess.run(
            [*self.launcher(host), *_python(argv)],
            cwd=REPO_ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=timeout_s,
        )

    def pids(self, host: str) -> list[int]:
        """Every process in `host`'s namespace now."""
        listed = _ip("netns", "pids", self.namespaces[host], check=False)
        return [int(pid) for pid in listed.split()]

    def close(self) -> None:
        """Kill every process in both namespaces, then delete the namespaces (idempotent)."""
        for process in self.processes:
            if process.poll() is None:
                _kill_group(process.pid)
        for host in list(self.namespaces):
            deadline = time.monotonic() + STOP_DEADLINE_S
            while (pids := self.pids(host)) and time.monotonic() < deadline:
                for pid in pids:
                    kill_quietly(pid)
                time.sleep(0.05)
        for process in self.processes:
            process.wait(STOP_DEADLINE_S)
        for host in list(self.namespaces):
            _ip("netns", "delete", self.namespaces.pop(host), check=False)


def two_hosts(tag: str) -> TwoHosts:
    """Make namespaces `mapex-<tag>-a` and `-b` linked by a veth pair (created in them
    directly, never in this namespace), addressed and up; NamespaceError if that fails.
    `tag` makes the names unique (e.g. the test process's pid)."""
    if shutil.which("ip") is None:
        raise NamespaceError("the `ip` command (iproute2) is missing")
    if os.geteuid() != 0:
        raise NamespaceError(f"network namespaces need root; running as uid {os.geteuid()}")
    hosts = TwoHosts(tag)
    try:
        for host in HOSTS:
            name = f"mapex-{tag}-{host}"
            _ip("netns", "add", name)
            hosts.namespaces[host] = name
        links = {host: f"veth-{host}" for host in HOSTS}
        _ip("link", "add", links["a"], "netns", hosts.namespaces["a"], "type", "veth",
            "peer", "name", links["b"], "netns", hosts.namespaces["b"])  # fmt: skip
        for host in HOSTS:
            inside = ("-n", hosts.namespaces[host])
            address = f"{hosts.addresses[host]}/{PREFIX_BITS}"
            _ip(*inside, "address", "add", address, "dev", links[host])
            _ip(*inside, "link", "set", links[host], "up")
            _ip(*inside, "link", "set", "lo", "up")
    except BaseException:
        hosts.close()
        raise
    return hosts


def _ip(*args: str, check: bool = True) -> str:
    """Run `ip *args`; its stdout, or NamespaceError with its one-line complaint."""
    try:
        done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=IP_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise NamespaceError(f"`ip {' '.join(args)}` failed: {error}") from None
    if check and done.returncode != 0:
        said = " ".join(done.stderr.split()) or f"exit {done.returncode}"
        raise NamespaceError(f"`ip {' '.join(args)}` failed: {said}")
    return done.stdout


def _python(argv: Sequence[str]) -> list[str]:
    """`argv` with a leading "python" replaced by this interpreter."""
    argv = list(argv)
    return [sys.executable, *argv[1:]] if argv[:1] == ["python"] else argv


def _kill_group(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        kill_quietly(pid)
