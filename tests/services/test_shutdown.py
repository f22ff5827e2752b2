"""The end of a `services.up` run: every child stops of the SIGTERM it is sent, none is
killed after the grace period (issue #54, item 6).

Workers were killed in most short runs on a loaded machine: a stopped worker went through
the interpreter's teardown of torch (seconds), and one stopped while it loaded its weights
finished loading first. A worker now exits without the teardown (`services.predictor.
exit_now`) and ends at once when stopped before it serves (`exit_on_signals`,
tests/services/test_early_signals.py). The checks read exit codes and log lines, not
times: the runs get a long grace period, so a slow machine cannot fail them, and a mark
printed at interpreter teardown tells whether a worker went through it.
"""

from __future__ import annotations

import os
import re

from service_processes import free_loopback_port
from up_processes import UpProcess

RUNS = 3
STEPS = 30
GRACE_S = 30  # far more than a stop takes: a slow machine cannot fail the check
TEARDOWN_MARK = "interpreter teardown"
# a sitecustomize for every child: print the mark when the interpreter tears down
SITECUSTOMIZE = (
    "import atexit, sys\n"
    f"atexit.register(lambda: print({TEARDOWN_MARK!r}, file=sys.stderr, flush=True))\n"
)
EXITED = re.compile(r"\[supervisor\] (?:stopped (\S+) \((-?\d+)|(\S+) exited with (-?\d+))")


def test_short_runs_end_with_every_child_stopping_on_its_own(tmp_path, monkeypatch):
    marker = tmp_path / "site"
    marker.mkdir()
    (marker / "sitecustomize.py").write_text(SITECUSTOMIZE)
    paths = [str(marker), *filter(None, [os.environ.get("PYTHONPATH")])]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(paths))  # up and every child it starts
    ups = []  # the runs go side by side: each stops on a machine loaded by the others
    try:
        for run in range(RUNS):
            up = UpProcess(
                tmp_path / f"up{run}.log", "--steps", str(STEPS), "--run-prefix", f"end{run}",
                "--listen", f"tcp/127.0.0.1:{free_loopback_port()}",
                "--out", str(tmp_path / "runs"), "--set", f"services.stop_grace_s={GRACE_S}",
            )  # fmt: skip
            ups.append(up)
        for up in ups:
            assert up.wait() == 0, up.log()
    finally:
        for up in ups:
            up.kill()
    for run, up in enumerate(ups):
        log = up.log()
        assert "killed" not in log and "SIGKILL" not in log, log
        codes = {stopped or exited: int(a or b) for stopped, a, exited, b in EXITED.findall(log)}
        started = set(up.children())
        assert codes.keys() == started and len(started) == 6, log  # 4 workers, world, planner
        assert set(codes.values()) == {0}, codes  # each exited by itself, cleanly
        workers = [name for name in started if name.startswith("predictor-")]
        for name in workers:  # a worker skips the seconds of torch's teardown
            assert f"[{name}] {TEARDOWN_MARK}" not in log, log
        assert f"[world-end{run}-0] {TEARDOWN_MARK}" in log  # the mark does show teardowns
