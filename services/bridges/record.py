"""`python -m services.record --out run.mcap`: record runs on the Zenoh network as MCAP files.

    python -m services.record [--out FILE.mcap] [--foxglove-out FILE.mcap] [--run RUN]
        [--until-finished] [--timeout-s N] [--mode ...] [--connect ...]

Follows every robot of one run (`--run`) or of every run and writes what it hears as the
topics of `mapex.interop.topics`: the ROS 2 topics as a rosbag2 bag in one MCAP file
(`--out`), the Foxglove channels in a file of their own (`--foxglove-out`); one of them or
both (`mapex.interop.mcap_file`). Needs the `ros` extra. What the files hold and the exits:
docs/interop.md#recording-mcap.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections.abc import Collection
from pathlib import Path

import zenoh

from mapex.exit_codes import EXIT_USAGE
from mapex.interop.mcap_file import Recordings, recording_flags_problem
from mapex.interop.ros_messages import MissingExtraError
from services.bridges.follow import FINAL_STATES, RunFollower, Update
from services.bridges.ros_translate import TRANSLATED_TOPICS, RunTranslator
from services.config import Ros2Config
from services.keys import run_id_problem
from services.serving import configure_logging, positive_number, stop_on_signals
from services.zenoh_config import (
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
    zenoh_config_from_args,
)

EXIT_NOT_FINISHED = 1

log = logging.getLogger("services.record")


class RunRecorder:
    """Records the followed runs until `close`, the bag into `path` and the Foxglove channels
    into `foxglove_path` (either may be None); knows which runs finished."""

    def __init__(
        self, session: zenoh.Session, path: Path | None, run: str | None = None,
        config: Ros2Config | None = None, foxglove_path: Path | None = None,
    ) -> None:  # fmt: skip
        self.config = config or Ros2Config()
        self.recordings = Recordings(path, foxglove_path)
        self._translate = RunTranslator(
            self.recordings.write, self.config, with_foxglove=self.recordings.with_foxglove
        )
        self._states: dict[str, dict[str, str]] = {}  # run -> robot -> latest status state
        self._changed = threading.Condition()
        self.follower = RunFollower(session, self._on_update, run, TRANSLATED_TOPICS)

    def _on_update(self, update: Update) -> None:
        self._translate(update)
        if update.topic == "status":
            with self._changed:
                self._states.setdefault(update.run, {})[update.robot] = update.message.state
                self._changed.notify_all()

    def finished(self, runs: Collection[str] | None = None) -> bool:
        """Whether every robot of `runs` (None: of every run heard of, at least one) said
        finished or failed."""
        with self._changed:
            return self._finished(runs)

    def wait_finished(self, runs: Collection[str] | None, timeout_s: float) -> bool:
        """Wait until `finished(runs)`, at most `timeout_s`, then `settle_s` for the last
        samples of other keys; whether it is."""
        with self._changed:
            done = self._changed.wait_for(lambda: self._finished(runs), timeout_s)
        if done:
            time.sleep(self.config.settle_s)
        return done

    def close(self) -> str:
        """Stop following, write what is queued, finish the files; what was written."""
        self.follower.close()
        written = self.recordings.close()
        log.info("wrote %s", written)
        return written

    def _finished(self, runs: Collection[str] | None) -> bool:
        wanted = list(self._states) if runs is None else list(runs)
        return bool(wanted) and all(
            run in self._states
            and all(state in FINAL_STATES for state in self._states[run].values())
            for run in wanted
        )


def main(
    config: zenoh.Config,
    out: Path | None,
    run: str | None = None,
    until_finished: bool = False,
    timeout_s: float | None = None,
    stop: threading.Event | None = None,
    foxglove_out: Path | None = None,
) -> bool:
    """Record until `stop`, the runs' end (`until_finished`) or `timeout_s`; whether the
    followed runs finished."""
    stop = stop or threading.Event()
    deadline_s = None if timeout_s is None else time.monotonic() + timeout_s
    session = open_session(config)
    try:
        recorder = RunRecorder(session, out, run, foxglove_path=foxglove_out)
        try:
            while not stop.is_set():
                if until_finished and recorder.finished([run] if run else None):
                    stop.wait(recorder.config.settle_s)  # the other keys' last samples
                    break
                if deadline_s is not None and time.monotonic() >= deadline_s:
                    break
                stop.wait(0.2)
        finally:
            done = recorder.finished([run] if run else None)
            recorder.close()
    finally:
        session.close()
    return done


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m services.record",
        description=__doc__.split("\n\n")[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--out", type=Path, default=None, metavar="FILE.mcap",
        help="the rosbag2 bag to write, one MCAP file (ROS 2 topics, CDR)",
    )  # fmt: skip
    parser.add_argument(
        "--foxglove-out", type=Path, default=None, metavar="FILE.mcap",
        help="the MCAP file of the Foxglove channels (protobuf) to write",
    )  # fmt: skip
    parser.add_argument("--run", default=None, help="run id to record (default: every run)")
    parser.add_argument(
        "--until-finished", action="store_true",
        help="stop once the followed runs' robots said finished or failed",
    )  # fmt: skip
    parser.add_argument(
        "--timeout-s", type=positive_number("of seconds"), default=None,
        help="stop after this many seconds",
    )  # fmt: skip
    add_zenoh_arguments(parser)
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.run is not None and (problem := run_id_problem(args.run)) is not None:
        parser.error(problem)
    if args.out is None and args.foxglove_out is None:
        parser.error("give --out FILE.mcap, --foxglove-out FILE.mcap or both")
    paths = {"--out": args.out, "--foxglove-out": args.foxglove_out}
    if (problem := recording_flags_problem(paths)) is not None:
        parser.error(problem)
    configure_logging(f"record[{args.run or '*'}]")
    stop = stop_on_signals()
    try:
        done = main(zenoh_config_from_args(args), args.out, args.run, args.until_finished,
                    args.timeout_s, stop, args.foxglove_out)  # fmt: skip
    except (ZenohConfigError, MissingExtraError, OSError) as error:
        log.error("%s", error)
        return EXIT_USAGE
    if args.until_finished and not done and not stop.is_set():
        log.error("timed out before the run finished (the file holds what was heard)")
        return EXIT_NOT_FINISHED
    return 0


if __name__ == "__main__":
    sys.exit(run_cli())
