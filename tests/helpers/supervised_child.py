"""A tiny child for tests/services/test_supervisor.py: `python -m supervised_child [options]`.

Prints the `--say` lines (and `--raw` bytes) at once, says `ready` once its signal handling
is set up, then exits with `--exit` code or, with `--sleep`, sleeps until SIGTERM (exit 0).
`--ignore-term` makes it ignore SIGTERM (only SIGKILL ends it); `--grandchild` first starts
a second copy of itself that ignores SIGTERM and prints `grandchild <pid>`.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time

SLEEP_STEP_S = 0.05


def main() -> None:
    args = parse_args()
    if args.ignore_term:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    else:
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    for line in args.say:
        print(line, flush=True)
    if args.raw:
        sys.stdout.buffer.write(bytes.fromhex(args.raw) + b"\n")
        sys.stdout.flush()
    if args.grandchild:
        command = [sys.executable, "-m", "supervised_child", "--sleep", "--ignore-term"]
        grandchild = subprocess.Popen(command, stdout=subprocess.DEVNULL)
        print(f"grandchild {grandchild.pid}", flush=True)
    print("ready", flush=True)
    while args.sleep:
        time.sleep(SLEEP_STEP_S)
    sys.exit(args.exit)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="supervised_child", description=__doc__)
    parser.add_argument("--say", action="append", default=[], help="a line to print")
    parser.add_argument("--raw", default="", help="hex bytes to print as one line")
    parser.add_argument("--exit", type=int, default=0, help="exit code when not sleeping")
    parser.add_argument("--sleep", action="store_true", help="sleep until SIGTERM")
    parser.add_argument("--ignore-term", action="store_true", help="ignore SIGTERM")
    parser.add_argument("--grandchild", action="store_true", help="start a stubborn grandchild")
    return parser.parse_args()


if __name__ == "__main__":
    main()
