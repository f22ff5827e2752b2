"""A run that joined another's hub with `--connect` ends when that hub goes (issue 53: in
the default peer mode its world and planner, linked to each other, carried on without the
hub's workers, although the refusal of a taken hub and the docs say it ends with it).

The hub here is `python -m deploy.router` (what a host `services.up` serves: a router on
loopback); the joined run is a real `services.up --connect` in its default peer mode.
`services.evaluate`'s loop ends the same way (`HubWatch.lost`).
"""

from __future__ import annotations

import argparse
import os
import signal
import threading
import time
from pathlib import Path

from service_processes import (
    STOP_DEADLINE_S,
    free_loopback_port,
    kill_router,
    spawn_router,
    until,
    wait_router_ready,
)
from up_processes import UpProcess

from mapex.exit_codes import EXIT_FAILED
from services.config import ServicesConfig
from services.evaluate import Episode, run_episodes
from services.keys import robot_key
from services.pool import HubWatch
from services.supervisor import endpoint_silence
from services.zenoh_config import open_session, zenoh_config

GRACE_S = 1.0  # services.hub_lost_grace_s of the joined run
STARTED_DEADLINE_S = 120.0  # a cold start of world and planner on a loaded machine
ENDED_DEADLINE_S = 30.0  # the grace, a supervision poll and stopping the children
RUN_STEPS = 5000  # far longer than the test: the run must end because the hub went


def test_a_run_joined_to_a_hub_ends_when_the_hub_goes(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    hub = spawn_router(tmp_path, endpoint)
    up = None
    try:
        wait_router_ready(hub)
        up = UpProcess(
            tmp_path / "joined.log", "--connect", endpoint, "--members", "none",
            "--method", "nearest", "--world", "generated:0", "--steps", str(RUN_STEPS),
            "--run-prefix", "joined", "--out", str(tmp_path / "runs"),
            "--set", f"services.hub_lost_grace_s={GRACE_S}",
            "--set", "services.workers_wait_s=0.5",  # nearest asks no worker
        )  # fmt: skip
        poses: list[bytes] = []
        with open_session(zenoh_config("client", [endpoint])) as follower:
            follower.declare_subscriber(
                robot_key("joined-0", "r0", "pose"), lambda s: poses.append(s)
            )

            def stepping() -> bool:
                if up.process.poll() is not None:
                    raise AssertionError(f"services.up exited early:\n{up.log()}")
                return len(poses) > 1

            until(stepping, "the joined run to step", STARTED_DEADLINE_S)
        hub.process.send_signal(signal.SIGINT)  # the host run ends, and its hub with it
        hub.process.wait(STOP_DEADLINE_S)
        gone = time.monotonic()
        assert up.wait(ENDED_DEADLINE_S) == EXIT_FAILED, up.log()
        assert time.monotonic() - gone < ENDED_DEADLINE_S
        errors = [line for line in up.log().splitlines() if " ERROR " in line]
        assert errors and f"the hub at --connect {endpoint} is gone" in errors[0], up.log()
        assert "Traceback" not in up.log()
    finally:
        if up is not None:
            up.kill()
        kill_router(hub)


def test_a_run_joined_by_its_config_file_uses_that_hub_listens_nowhere_and_ends_with_it(
    tmp_path,
):
    """`services.up --config FILE` alone, FILE in client mode connecting to a hub (the form
    deploy/README.md shows): the run joins that hub as `--mode client --connect` would, and
    ends when it goes. Nothing of the run listens on any port, neither the default hub's
    nor another (issue #64, item 8: the file's mode and endpoints were ignored and the run
    served a hub of its own, its world and planners clients of it)."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    default_hub = f"tcp/127.0.0.1:{free_loopback_port()}"  # where it served its own hub
    config = tmp_path / "runner.json5"
    config.write_text(
        f'{{ mode: "client", connect: {{ endpoints: ["{endpoint}"] }}, '
        "scouting: { multicast: { enabled: false } } }"
    )
    hub = spawn_router(tmp_path, endpoint)
    up = None
    try:
        wait_router_ready(hub)
        up = UpProcess(
            tmp_path / "joined.log", "--config", str(config), "--members", "none",
            "--method", "nearest", "--world", "generated:0", "--steps", str(RUN_STEPS),
            "--run-prefix", "joined", "--out", str(tmp_path / "runs"),
            "--set", f"services.hub_endpoint={default_hub}",
            "--set", f"services.hub_lost_grace_s={GRACE_S}",
            "--set", "services.workers_wait_s=0.5",  # nearest asks no worker
        )  # fmt: skip
        _until_stepping_through(endpoint, up)
        run = [up.process.pid] + [pid for pids in up.children().values() for pid in pids]
        assert len(run) >= 3, up.log()  # services.up, its world and its planner
        assert listening_ports(run) == set(), up.log()
        assert endpoint_silence(default_hub, 1.0) == "connection refused"
        hub.process.send_signal(signal.SIGINT)
        hub.process.wait(STOP_DEADLINE_S)
        assert up.wait(ENDED_DEADLINE_S) == EXIT_FAILED, up.log()
        errors = [line for line in up.log().splitlines() if " ERROR " in line]
        assert errors and f"the hub at --connect {endpoint} is gone" in errors[0], up.log()
        assert "Traceback" not in up.log()
    finally:
        if up is not None:
            up.kill()
        kill_router(hub)


def _until_stepping_through(endpoint: str, up: UpProcess) -> None:
    """Wait until the run's robot `joined-0/r0` steps, as a client of the hub at `endpoint`
    hears it."""
    poses: list[bytes] = []
    with open_session(zenoh_config("client", [endpoint])) as follower:
        follower.declare_subscriber(robot_key("joined-0", "r0", "pose"), lambda s: poses.append(s))

        def stepping() -> bool:
            if up.process.poll() is not None:
                raise AssertionError(f"services.up exited early:\n{up.log()}")
            return len(poses) > 1

        until(stepping, "the joined run to step", STARTED_DEADLINE_S)


def listening_ports(pids: list[int]) -> set[int]:
    """The TCP ports the processes `pids` listen on (their sockets in /proc/net/tcp{,6})."""
    sockets = set()
    for pid in pids:
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            try:
                target = os.readlink(fd)
            except FileNotFoundError:  # closed meanwhile
                continue
            if target.startswith("socket:["):
                sockets.add(target[len("socket:[") : -1])
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in sockets:  # 0A: LISTEN
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def test_hub_watch_ends_only_a_joined_run_that_lost_its_router(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    services = ServicesConfig(hub_lost_grace_s=GRACE_S)
    router = open_session(zenoh_config("router", [], [endpoint]))
    joined = open_session(zenoh_config("peer", [endpoint]))
    try:
        watch, serving_here = (
            HubWatch(joined, [endpoint], services),
            HubWatch(router, None, services),
        )
        until(lambda: any(True for _ in joined.info.routers_zid()), "the link to the router")
        assert watch.lost() is None and serving_here.lost() is None
        router.close()
        assert watch.lost() is None  # within the grace (a router restarting)
        line = until(watch.lost, "the watch to give the hub up", GRACE_S + 10.0)
        assert line.startswith(f"the hub at --connect {endpoint} is gone")
    finally:
        joined.close()
        router.close()


class _GoneHub:
    def lost(self) -> str:
        return "the hub at --connect tcp/127.0.0.1:1 is gone"


class _IdleSupervisor:
    """Starts nothing; its planners never exit."""

    services = ServicesConfig()

    def __init__(self) -> None:
        self.started: list[str] = []

    def start(self, spec) -> None:
        self.started.append(spec.name)

    def poll(self) -> None:
        pass

    def returncode(self, _name: str) -> None:
        return None


class _NoProgress:
    def of(self, _run_id: str) -> int:
        return 0


def test_an_evaluation_joined_to_a_hub_stops_when_it_goes(tmp_path):
    """services.evaluate's loop: a gone hub is a failure line and no episode starts after."""
    episode = Episode("generated:0", "generated:0", "nearest", 0, 0)
    supervisor = _IdleSupervisor()
    args = argparse.Namespace(jobs=1, out=tmp_path, no_progress=True)
    stop = threading.Event()
    done, failures = run_episodes(
        supervisor, [episode, episode], args, [], _NoProgress(), stop, hub=_GoneHub()
    )
    assert (done, failures) == (0, [_GoneHub().lost()]) and supervisor.started == []
