"""A worker machine of the two-host test: `python tests/helpers/worker_host.py FLAGS`.

One predictor worker per member (`services.pool.worker_specs`, ids `<id-prefix>-<member>-0`)
under a `services.supervisor.Supervisor` that restarts a worker that dies, as systemd's
`Restart=on-failure` or compose's restart policy do on a real worker machine
(deploy/README.md section 10); the Zenoh flags after `--` go to every worker. Logs
`[supervisor] started <name> (pid N)` lines like `services.up`; SIGTERM or SIGINT stops it
and its workers.
"""

from __future__ import annotations

import argparse
import sys
import time

from services.config import ServicesConfig
from services.pool import parse_member_list, worker_specs
from services.serving import stop_on_signals
from services.supervisor import Supervisor


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="worker_host")
    parser.add_argument("--members", type=parse_member_list, required=True)
    parser.add_argument("--id-prefix", required=True)
    parser.add_argument("zenoh_flags", nargs=argparse.REMAINDER, help="-- then Zenoh flags")
    args = parser.parse_args(argv)
    flags = args.zenoh_flags[1:] if args.zenoh_flags[:1] == ["--"] else args.zenoh_flags
    services = ServicesConfig()
    stop = stop_on_signals()
    threads = services.predictor_threads
    specs = worker_specs(args.members, 1, threads, flags, id_prefix=args.id_prefix)
    with Supervisor(services=services) as supervisor:
        for spec in specs:
            supervisor.start(spec)
        while not stop.is_set():
            supervisor.poll()
            time.sleep(services.supervision_poll_s)
    return 0


if __name__ == "__main__":
    sys.exit(main())
