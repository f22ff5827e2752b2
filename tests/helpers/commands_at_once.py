"""Short `python -m` commands run side by side, without each paying for the imports.

The one-line-error and `--help` checks each start a command that only parses its flags,
perhaps reads a file, and exits: 1-2 s of CPU, nearly all of it importing torch, numpy,
scipy and numba. `run_python_m` runs a test module's cases at once (a module-scoped
fixture; each case then checks its own result), each in a process of its own forked from
one interpreter that has imported those libraries (tests/helpers/python_m_forks.py): the
command's own modules are imported by the case, and it runs as `python -m` runs it. What
each case checks is unchanged: its exit status, its stdout and its stderr. A `--help`
asked for by two test modules (tests/test_docs.py, tests/test_imports.py) runs once.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

from service_processes import REPO_ROOT

AT_ONCE = 4  # commands running at once (a 2-core machine is kept busy, its memory is not)
COMMAND_TIMEOUT_S = 120  # one command on a loaded machine; one that hangs is killed then
FORKS = Path(__file__).resolve().parent / "python_m_forks.py"
_HELPS: dict[tuple[str, ...], subprocess.CompletedProcess] = {}


def run_python_m(
    cases: Sequence[Sequence[str]],
    cwd: Path = REPO_ROOT,
    timeout_s: float = COMMAND_TIMEOUT_S,
    env: Mapping[str, str] | None = None,
) -> list[subprocess.CompletedProcess]:
    """`python -m MODULE ARGS...` of each case ([MODULE, *ARGS]), AT_ONCE at a time, in
    `cwd`: their results in order (args: the case; text stdout and stderr). A case still
    running after `timeout_s` is killed (returncode -9)."""
    if not cases:
        return []
    with tempfile.TemporaryDirectory(prefix="python-m-") as out_dir:
        request = {"cases": [list(case) for case in cases], "at_once": AT_ONCE,
                   "timeout_s": timeout_s, "out_dir": out_dir}  # fmt: skip
        done = subprocess.run(
            [sys.executable, str(FORKS)], input=json.dumps(request), cwd=cwd, env=env,
            capture_output=True, text=True, timeout=timeout_s * len(cases) + 60,
        )  # fmt: skip
        assert done.returncode == 0, f"python_m_forks.py failed:\n{done.stderr[-3000:]}"
        codes = json.loads(done.stdout)
        return [
            subprocess.CompletedProcess(
                list(case),
                code,
                Path(out_dir, f"{k}.out").read_text(errors="replace"),
                Path(out_dir, f"{k}.err").read_text(errors="replace"),
            )
            for k, (case, code) in enumerate(zip(cases, codes, strict=True))
        ]


def helps_at_once(commands: Sequence[Sequence[str]]) -> list[subprocess.CompletedProcess]:
    """`python -m COMMAND --help` of each command, once per test session."""
    missing = sorted({tuple(c) for c in commands} - set(_HELPS))
    answers = run_python_m([[*command, "--help"] for command in missing])
    _HELPS.update(zip(missing, answers, strict=True))
    return [_HELPS[tuple(command)] for command in commands]
