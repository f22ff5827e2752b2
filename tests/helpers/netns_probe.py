"""A client of the two-host test, run inside one host's namespace:
`python tests/helpers/netns_probe.py COMMAND CONFIG_FILE [RUN]`.

The test process lives in neither namespace, so it cannot open a session on the router
itself; it runs this there instead. Each command opens a client session from the Zenoh
config file (its role is its certificate's CN), or prints why Zenoh refused it (one line)
and exits 2:

* `join`: print `joined <zid of each linked router>` and exit 0;
* `follow RUN`: print `step <t>` for every pose robot r0 of RUN publishes, until killed;
* `workers`: print the liveliness key of every predictor worker alive now, exit 0.
"""

from __future__ import annotations

import argparse
import sys
import threading

import zenoh

from services.keys import alive_predictor_pattern, robot_key
from services.messages import PoseMessage
from services.serving import stop_on_signals, wait_for
from services.zenoh_config import ZenohConfigError, open_session, zenoh_config

LIVELINESS_TIMEOUT_S = 5.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="netns_probe")
    parser.add_argument("command", choices=("join", "follow", "workers"))
    parser.add_argument("config")
    parser.add_argument("run", nargs="?")
    args = parser.parse_args(argv)
    stop = stop_on_signals()
    try:
        session = open_session(zenoh_config(config_file=args.config))
    except ZenohConfigError as error:
        print(error, flush=True)
        return 2
    try:
        if args.command == "join":
            print("joined", *(str(zid) for zid in session.info.routers_zid()), flush=True)
        elif args.command == "workers":
            for reply in session.liveliness().get(
                alive_predictor_pattern(), timeout=LIVELINESS_TIMEOUT_S
            ):
                if reply.ok is not None:
                    print(reply.ok.key_expr, flush=True)
        else:
            follow(session, args.run, stop)
    finally:
        session.close()
    return 0


def follow(session: zenoh.Session, run: str, stop: threading.Event) -> None:
    def on_pose(sample: zenoh.Sample) -> None:
        print("step", PoseMessage.decode(sample.payload.to_bytes()).t, flush=True)

    subscriber = session.declare_subscriber(robot_key(run, "r0", "pose"), on_pose)
    try:
        wait_for(stop)
    finally:
        subscriber.undeclare()


if __name__ == "__main__":
    sys.exit(main())
