"""A Zenoh router for MapEx on several machines: the stand-in for a user's `zenohd`.

    python -m deploy.router [--listen ENDPOINT ...] [--connect ENDPOINT ...] [--config FILE]

Opens one Zenoh session in router mode and keeps it open until SIGINT/SIGTERM; workers and
planners on other machines run with `--mode client --connect tcp/<this-host>:7447` and reach
each other through it. It listens on loopback only unless `--listen` says otherwise. Its
flags, logs and exits: deploy/README.md, section 2 (Machine A: the router).
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading

import zenoh

from mapex.exit_codes import EXIT_USAGE
from services.serving import configure_logging, stop_on_signals, wait_for
from services.zenoh_config import ZenohConfigError, open_session, zenoh_config

log = logging.getLogger("deploy.router")


def main(config: zenoh.Config, stop: threading.Event) -> None:
    """Run a router session with `config` until `stop` is set (zenoh-python example style).

    Raises ZenohConfigError (one line) when Zenoh refuses the config, e.g. a port in use.
    """
    endpoints = config.get_json("listen/endpoints")
    with open_session(config) as session:
        events = session.info.declare_transport_events_listener(_log_transport_event)
        log.info("router %s listening on %s", session.info.zid(), endpoints)
        try:
            wait_for(stop)
        finally:
            events.undeclare()
    log.info("router stopped")


def router_config(args: argparse.Namespace) -> zenoh.Config:
    """The router-mode config of the parsed flags; ZenohConfigError when it is unusable."""
    connect = args.connect
    if connect is None and args.config is None:
        connect = []  # a router links to other routers only when told to
    return zenoh_config("router", connect, args.listen, args.config)


def build_parser() -> argparse.ArgumentParser:
    """--listen, --connect and --config (the mode is fixed: router)."""
    parser = argparse.ArgumentParser(
        prog="python -m deploy.router",
        description=__doc__.split("\n\n")[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--listen",
        metavar="ENDPOINT",
        action="append",
        default=None,
        help="endpoint to listen on, repeatable (default: tcp/127.0.0.1:7447, loopback only; "
        "use tcp/0.0.0.0:7447 to serve other machines)",
    )
    parser.add_argument(
        "--connect",
        metavar="ENDPOINT",
        action="append",
        default=None,
        help="another router to link to, repeatable (default: none)",
    )
    parser.add_argument(
        "--config", metavar="FILE", default=None, help="Zenoh json5 config file (base config)"
    )
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    """Parse flags, route until SIGINT/SIGTERM; 0 on a clean stop, 2 on a one-line error."""
    args = build_parser().parse_args(argv)
    configure_logging("router")
    stop = stop_on_signals()
    try:
        main(router_config(args), stop)
    except ZenohConfigError as error:
        log.error("%s", error)
        return EXIT_USAGE
    return 0


def _log_transport_event(event: zenoh.TransportEvent) -> None:
    """One line per node joining or leaving (runs on a Zenoh thread: only logs)."""
    verb = "joined" if event.kind == zenoh.SampleKind.PUT else "left"
    log.info("%s %s %s", event.transport.whatami, event.transport.zid, verb)


if __name__ == "__main__":
    sys.exit(run_cli())
