"""The outside-tool flags of `services.up` and `services.evaluate`, and starting those tools.

* `--record FILE.mcap`: every run as a rosbag2 bag in one MCAP file, in-process
  (`services.record`: it writes a file and must see the end of the runs);
  `--record-foxglove FILE.mcap`: their Foxglove channels, a file of their own;
* `--ros2` (with `--ros-connect ENDPOINT`, `--ros-domain N`): the ROS 2 bridge as a child
  process (`services.ros2`), supervised like the others;
* `--web [PORT]`: the live browser view (`services.web`), a child process;
* `--foxglove [PORT]`: the Foxglove SDK's WebSocket server (`services.foxglove`), a child
  process.

The web view and the Foxglove server serve sockets to anyone on the machine, so they run
outside the supervisor, whose death ends the run: supervised children (`viewer_specs`) that
are restarted when they die and never end a run, joining the hub as the other children do.
Every flag's problem (a file that exists, a missing extra, a port already taken: probed
here) is one line before any process starts.
"""

from __future__ import annotations

import argparse
import logging
import socket
from collections.abc import Sequence
from pathlib import Path

import zenoh

from mapex.config import ConfigError
from mapex.interop.mcap_file import recording_flags_problem
from services.bridges.record import RunRecorder
from services.bridges.ros2 import ros_router_problem
from services.config import DEFAULT_FOXGLOVE, DEFAULT_WEB, FoxgloveConfig, WebConfig
from services.supervisor import ProcessSpec

log = logging.getLogger("services.outside_tools")

RECORD_FINISH_WAIT_S = 5.0  # after the planners exit: time for their last frames to arrive


def add_outside_tool_arguments(parser: argparse.ArgumentParser) -> None:
    """--record, --record-foxglove, --ros2, --ros-connect, --ros-domain, --web, --foxglove."""
    group = parser.add_argument_group("outside tools (docs/interop.md)")
    group.add_argument(
        "--record", type=Path, default=None, metavar="FILE.mcap",
        help="record every run as a rosbag2 bag in one MCAP file (ROS 2 topics, CDR: "
        "`ros2 bag play`, rosbags, Foxglove)",
    )  # fmt: skip
    group.add_argument(
        "--record-foxglove", type=Path, default=None, metavar="FILE.mcap",
        help="record every run's Foxglove channels (protobuf) as an MCAP file of their own",
    )  # fmt: skip
    group.add_argument(
        "--ros2", action="store_true",
        help="run the ROS 2 bridge (services.ros2): topics /mapex/<run>/<robot>/... over "
        "rmw_zenoh",
    )  # fmt: skip
    group.add_argument(
        "--ros-connect", default=None, metavar="ENDPOINT",
        help="with --ros2: publish through the ROS 2 router there (rmw_zenohd)",
    )  # fmt: skip
    group.add_argument("--ros-domain", type=int, default=None, help="with --ros2: ROS_DOMAIN_ID")
    group.add_argument(
        "--web", type=int, nargs="?", const=DEFAULT_WEB.port, default=None, metavar="PORT",
        help=f"serve the live browser view on http://127.0.0.1:PORT (default {DEFAULT_WEB.port})",
    )  # fmt: skip
    group.add_argument(
        "--foxglove", type=int, nargs="?", const=DEFAULT_FOXGLOVE.port, default=None,
        metavar="PORT", help="serve the run to the Foxglove app on ws://127.0.0.1:PORT "
        f"(default {DEFAULT_FOXGLOVE.port})",
    )  # fmt: skip


def check_outside_tool_arguments(args: argparse.Namespace) -> None:
    """ConfigError (one line) for a bad flag or a missing extra, before anything starts."""
    recordings = {"--record": args.record, "--record-foxglove": args.record_foxglove}
    if (problem := recording_flags_problem(recordings)) is not None:
        raise ConfigError(problem)
    if (args.ros_connect or args.ros_domain is not None) and not args.ros2:
        raise ConfigError("--ros-connect and --ros-domain go with --ros2")
    if args.ros_domain is not None and not 0 <= args.ros_domain <= 232:
        raise ConfigError(f"--ros-domain {args.ros_domain} is not a ROS 2 domain id (0-232)")
    if args.record is not None or args.record_foxglove is not None or args.ros2:
        _require(
            "rosbags", "--record, --record-foxglove and --ros2 need the ros extra: "
            "pip install -e '.[ros]'",
        )  # fmt: skip
    if args.foxglove is not None:
        _require("foxglove", "--foxglove needs the foxglove extra: pip install -e '.[foxglove]'")
    if args.ros2 and args.ros_connect and (problem := ros_router_problem(args.ros_connect)):
        raise ConfigError(problem)  # else the bridge would publish into nothing
    served = _served_addresses(args)
    if len(served) == 2 and len(set(served.values())) == 1 and args.web != 0:
        raise ConfigError(f"--web and --foxglove cannot both serve port {args.web}")
    for flag, address in served.items():  # taken now: one line, before any child starts
        if (problem := port_problem(*address)) is not None:
            raise ConfigError(f"{flag}: {problem}")


def _served_addresses(args: argparse.Namespace) -> dict[str, tuple[str, int]]:
    """(host, port) of the viewers asked for, by flag; ConfigError for a port out of range."""
    served = {}
    if args.web is not None:
        served["--web"] = (DEFAULT_WEB.host, WebConfig(port=args.web).port)
    if args.foxglove is not None:
        served["--foxglove"] = (DEFAULT_FOXGLOVE.host, FoxgloveConfig(port=args.foxglove).port)
    return served


def port_problem(host: str, port: int) -> str | None:
    """Why a server could not listen on `host`:`port` now ("cannot serve on 127.0.0.1 port
    8000: Address already in use"), or None: a bind probe, closed at once, with
    SO_REUSEADDR as the servers bind (a port held only by closed connections is free).
    Port 0 (any free one) is never a problem."""
    if port == 0:
        return None
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((host, port))
    except OSError as error:
        return f"cannot serve on {host} port {port}: {error.strerror or error}"
    return None


def bridge_spec(args: argparse.Namespace, zenoh_flags: Sequence[str]) -> list[ProcessSpec]:
    """The ROS 2 bridge child (`--ros2`), or none."""
    if not args.ros2:
        return []
    extra = ["--ros-connect", args.ros_connect] if args.ros_connect else []
    extra += ["--domain", str(args.ros_domain)] if args.ros_domain is not None else []
    return [ProcessSpec("ros2-bridge", "services.bridges.ros2", (*extra, *zenoh_flags))]


VIEWER_NAMES = ("web", "foxglove")  # the children of `viewer_specs`


def viewer_specs(args: argparse.Namespace, zenoh_flags: Sequence[str]) -> list[ProcessSpec]:
    """The browser view (`--web`) and the Foxglove server (`--foxglove`) children asked for,
    following every run: servers (`restart=True`) whose exit never ends a run."""
    specs = []
    if args.web is not None:
        web_args = ("--port", str(args.web), *zenoh_flags)
        specs.append(ProcessSpec("web", "services.bridges.web", web_args, restart=True))
    if args.foxglove is not None:
        fox_args = ("--port", str(args.foxglove), *zenoh_flags)
        specs.append(
            ProcessSpec("foxglove", "services.bridges.foxglove_live", fox_args, restart=True)
        )
    return specs


def tool_process_count(args: argparse.Namespace) -> int:
    """How many child processes the outside tools asked for start (the process caps)."""
    return len(bridge_spec(args, [])) + len(viewer_specs(args, []))


class OutsideTools:
    """The in-process tool asked for (the recording), started on `session`."""

    def __init__(self, session: zenoh.Session, args: argparse.Namespace) -> None:
        self.recorder = None
        if args.record is not None or args.record_foxglove is not None:
            self.recorder = RunRecorder(session, args.record, foxglove_path=args.record_foxglove)

    def close(self, runs: Sequence[str] = ()) -> None:
        """Stop the recording; it first waits a little for `runs` to say finished."""
        if self.recorder is not None:
            if runs and not self.recorder.wait_finished(runs, RECORD_FINISH_WAIT_S):
                log.warning("recording closed before every run said finished")
            self.recorder.close()


def _require(module: str, message: str) -> None:
    try:
        __import__(module)
    except ImportError:
        raise ConfigError(message) from None
