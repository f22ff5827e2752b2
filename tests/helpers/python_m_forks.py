"""Run `python -m MODULE ARGS...` commands, each in a process of its own forked from this one
once it has imported the third-party libraries every command of the project imports (torch
above all): the seconds each interpreter spends on those imports are spent once. Used by
commands_at_once.run_python_m; run as a script, never imported by a test.

Input (stdin): JSON {"cases": [[module, arg, ...], ...], "at_once": N, "timeout_s": T,
"out_dir": DIR}. Each case runs as `python -m` runs it (`runpy` as `__main__`, sys.argv[0]
its file, the working directory first on sys.path), stdin from /dev/null, stdout and stderr
into DIR/<k>.out and DIR/<k>.err; its exit status is the interpreter's: SystemExit's code, 1
and the traceback on stderr for any other exception. A case still running after T seconds
is killed (SIGKILL). Output (stdout): JSON [returncode, ...] in the order of the cases.
"""

from __future__ import annotations

import contextlib
import json
import os
import runpy
import signal
import sys
import time
import traceback

# imported before any fork: no thread of theirs is running yet (numpy's BLAS threads are
# fork-safe); the project's modules and everything else are imported by each case itself
import numba  # noqa: F401
import numpy  # noqa: F401
import scipy.ndimage  # noqa: F401
import torch  # noqa: F401

POLL_S = 0.01


def run_case(case: list[str], out: str, err: str) -> int:
    """In the forked child: run `case` as `python -m` would; its exit status."""
    stdin = os.open(os.devnull, os.O_RDONLY)
    os.dup2(stdin, 0)
    for fd, path in ((1, out), (2, err)):
        os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), fd)
    module, *args = case
    sys.argv = [module, *args]
    sys.path[0] = os.getcwd()
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
        code = 0
    except SystemExit as done:
        if done.code is None or isinstance(done.code, int):
            code = done.code or 0
        else:
            print(done.code, file=sys.stderr)
            code = 1
    except BaseException:
        traceback.print_exc()
        code = 1
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a command may have closed it
            stream.flush()
    return code


def main() -> int:
    request = json.load(sys.stdin)
    cases, at_once = request["cases"], request["at_once"]
    timeout_s, out_dir = request["timeout_s"], request["out_dir"]
    codes: list[int | None] = [None] * len(cases)
    running: dict[int, tuple[int, float]] = {}  # pid -> (case, started)
    waiting = list(range(len(cases)))
    while waiting or running:
        while waiting and len(running) < at_once:
            k = waiting.pop(0)
            pid = os.fork()
            if pid == 0:
                os._exit(run_case(cases[k], f"{out_dir}/{k}.out", f"{out_dir}/{k}.err"))
            running[pid] = (k, time.monotonic())
        pid, status = os.waitpid(-1, os.WNOHANG)
        if pid:
            codes[running.pop(pid)[0]] = os.waitstatus_to_exitcode(status)
            continue
        for pid, (_, started) in running.items():
            if time.monotonic() - started > timeout_s:
                os.kill(pid, signal.SIGKILL)  # reaped by waitpid: returncode -9
        time.sleep(POLL_S)
    json.dump(codes, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
