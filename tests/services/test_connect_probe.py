"""`--connect` to a hub that is not there: `services.up` and `services.evaluate` say so at
once, in one line with exit 2, before any child starts (issue 53: in the default peer mode
the run waited 72 s and then blamed the world; in client mode Zenoh gave up after 8 s).
And the refusal of a taken hub port suggests a way to join it that works.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time

import pytest
from service_processes import REPO_ROOT, free_loopback_port

from mapex.exit_codes import EXIT_USAGE
from services.config import ServicesConfig
from services.pool import check_hub_answers, hub_session_config
from services.supervisor import endpoint_silence
from services.up import build_parser
from services.zenoh_config import ZenohConfigError

# a cold interpreter importing torch on a loaded shared machine; the old code waited 72 s
ANSWER_DEADLINE_S = 45.0
PROBE = ServicesConfig().hub_probe_timeout_s


def _listening() -> tuple[socket.socket, str]:
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen()
    return server, f"127.0.0.1:{server.getsockname()[1]}"


def test_endpoint_silence_tells_a_listener_from_nothing():
    server, address = _listening()
    with server:
        assert endpoint_silence(f"tcp/{address}", PROBE) is None
        assert endpoint_silence(f"tls/{address}#iface=lo", PROBE) is None
    assert endpoint_silence(f"tcp/{address}", PROBE) == "connection refused"
    assert endpoint_silence("tls/no-such-host.invalid:7447", PROBE).startswith(
        "cannot resolve host 'no-such-host.invalid'"
    )
    assert endpoint_silence(f"udp/{address}", PROBE) is None  # not probed: Zenoh says it
    with pytest.raises(ValueError, match="tcp/host:port"):
        endpoint_silence("tcp/127.0.0.1", PROBE)


def test_check_hub_answers_names_the_silent_endpoint():
    server, address = _listening()
    silent = f"tcp/127.0.0.1:{free_loopback_port()}"
    with server:
        check_hub_answers([f"tcp/{address}"], ServicesConfig())
        check_hub_answers(None, ServicesConfig())  # serving the hub here: nothing to probe
        with pytest.raises(ZenohConfigError, match=f"nothing answers at --connect {silent} "):
            check_hub_answers([f"tcp/{address}", silent], ServicesConfig())


@pytest.mark.parametrize(
    ("command", "mode"),
    [
        ("services.up", None),
        ("services.up", "client"),
        ("services.evaluate", None),
        ("services.evaluate", "client"),
    ],
)
def test_connect_to_nothing_fails_at_once_before_any_child(command, mode, tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    args = [sys.executable, "-m", command, "--connect", endpoint, "--steps", "5"]
    args += ["--out", str(tmp_path / "out"), "--no-progress"]
    args += ["--mode", mode] if mode else []
    args += ["--maps", "generated:0"] if command == "services.evaluate" else []
    last = _refused_at_once(args)
    assert f"nothing answers at --connect {endpoint} (connection refused)" in last


@pytest.mark.parametrize("command", ["services.up", "services.evaluate"])
def test_a_config_file_naming_a_hub_that_is_not_there_fails_at_once(command, tmp_path):
    """`--config FILE` alone, FILE in client mode connecting to where nothing listens: the
    run joins what the file names, so it is probed as `--connect` is (issue #64, item 8: the
    file's endpoints were ignored and the run served a hub of its own)."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    config = tmp_path / "client.json5"
    config.write_text(f'{{ mode: "client", connect: {{ endpoints: ["{endpoint}"] }} }}')
    args = [sys.executable, "-m", command, "--config", str(config), "--steps", "5"]
    args += ["--out", str(tmp_path / "out"), "--no-progress", "--members", "none"]
    # were the file ignored, the default hub served here must not be the machine's 7447
    args += ["--set", f"services.hub_endpoint=tcp/127.0.0.1:{free_loopback_port()}"]
    args += (
        ["--maps", "generated:0", "--methods", "nearest"] if command == "services.evaluate" else []
    )
    last = _refused_at_once(args)
    assert (
        f"nothing answers at --connect {endpoint} (connection refused) (named in {config})" in last
    )


def test_the_taken_hub_refusal_suggests_a_join_that_works():
    """The suggested flags parse and name an endpoint that answers; in client mode, so
    every child is a client of that hub and the run cannot go on without it."""
    server, address = _listening()
    with server:
        services = ServicesConfig(hub_endpoint=f"tcp/{address}")
        no_flags = build_parser().parse_args([])
        with pytest.raises(ZenohConfigError) as refused:
            hub_session_config(no_flags, services)
        message = str(refused.value)
        suggestion = f"--mode client --connect tcp/{address}"
        assert suggestion in message and "--listen tcp/127.0.0.1:<free port>" in message
        joined = build_parser().parse_args(suggestion.split())
        check_hub_answers(joined.connect, services)
        _, flags = hub_session_config(joined, services)
        assert flags == ["--mode", "client", "--connect", f"tcp/{address}"]


def _refused_at_once(args: list[str]) -> str:
    """Run `args`: it must end with exit 2 before any child starts, within
    ANSWER_DEADLINE_S, no traceback; its last line."""
    began = time.monotonic()
    completed = subprocess.run(
        args, cwd=REPO_ROOT, capture_output=True, text=True, timeout=ANSWER_DEADLINE_S + 60
    )
    took_s = time.monotonic() - began
    assert completed.returncode == EXIT_USAGE, completed.stderr
    assert "Traceback" not in completed.stderr and "started" not in completed.stderr
    assert took_s < ANSWER_DEADLINE_S
    return completed.stderr.strip().splitlines()[-1]
