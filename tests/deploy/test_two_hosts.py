"""The predictor pool across two hosts with real networking (issue 56): two Linux network
namespaces joined by a veth pair (tests/helpers/netns.py), each process told only the
other host's address.

Host A runs the router (`python -m deploy.router` with the shipped access-control file and
mutual TLS, listening on A's veth address only, its certificate naming that address) and
`services.up --members none` logged in as `runner`; host B runs one predictor worker per
member (as `worker`) under a supervisor that restarts them (tests/helpers/worker_host.py).
Checked: the run equals the in-process run and every member query was answered by B's
workers; a worker killed on B mid-run is replaced and the run completes; a client on B
without a certificate is refused, and so is the router when its certificate does not name
the address dialled. Where namespaces cannot be made the tests fail with one line (never
skip): `-m "not netns"` leaves them out on purpose.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from acl_router import LOOPBACK_NAMES, make_role_certificates, start_acl_router
from netns import ADDRESS_A, NamespaceError, TwoHosts, two_hosts
from service_processes import (
    REPO_ROOT,
    RouterProcess,
    kill_router,
    until,
    wait_router_ready,
)
from shard_runs import (
    any_degraded,
    comparable_tables,
    evaluate_command,
    pool_warnings,
    run_records,
    shard_commands,
)
from up_processes import RUN_DEADLINE_S, read_run

from mapex.config import ExplorationConfig
from mapex.episode import run_episode
from mapex.prediction.base import MEMBER_NAMES
from mapex.prediction.learned import LearnedEnsemble
from mapex.results import write_results
from mapex.worlds import load_world
from mapex.worlds.starts import eligible_start_cells

pytestmark = pytest.mark.netns

HELPERS = REPO_ROOT / "tests" / "helpers"
CLIENT_TLS = REPO_ROOT / "deploy" / "client-tls.json5"
ROUTER_TLS = REPO_ROOT / "deploy" / "zenohd-tls.json5"
WORLD = "generated:0"
STEPS = 100  # the run compared with the in-process one: several re-plans, G samples at 0, 50
KILL_STEPS = 300  # the run whose worker is killed, at step KILL_AT
KILL_AT = 40
KILLED = "g1"  # a member every `mapex` re-plan reads
HOST_B = "hostb"  # the worker-id prefix of host B's workers
RESTARTED = re.compile(rf"\[supervisor\] started predictor-{KILLED} \(pid (\d+)\)")
PROBE_DEADLINE_S = 60.0  # a probe's interpreter start and session on a loaded machine
UP_FLAGS = ("--no-progress", "--members", "none", "--method", "mapex", "--world", WORLD)


@dataclass
class Cluster:
    """The two hosts, the router on A and the worker host on B, and their files."""

    hosts: TwoHosts
    router: RouterProcess
    directory: Path
    workers_log: Path

    def client_file(self, cn: str, name: str, **changes: str) -> Path:
        """deploy/client-tls.json5 as a site edits it: this test's certificates (CN `cn`)
        and A's address as the router's host; `changes`: further text replacements."""
        text = CLIENT_TLS.read_text()
        text = text.replace("router.example.org:7447", self.router.endpoint.split("/", 1)[1])
        text = text.replace("/etc/mapex/tls/ca.pem", str(self.directory / "ca.pem"))
        text = text.replace("/etc/mapex/tls/worker.pem", str(self.directory / f"{cn}.pem"))
        text = text.replace("/etc/mapex/tls/worker-key.pem", str(self.directory / f"{cn}-key.pem"))
        for old, new in changes.items():
            assert text.count(old) == 1, old
            text = text.replace(old, new)
        path = self.directory / name
        path.write_text(text)
        return path

    def probe(self, host: str, command: str, config: Path) -> subprocess.CompletedProcess:
        """tests/helpers/netns_probe.py `command` on `host` with the client file `config`."""
        argv = ["python", str(HELPERS / "netns_probe.py"), command, str(config)]
        return self.hosts.run(host, argv, PROBE_DEADLINE_S)

    def up(self, name: str, *args: str) -> subprocess.Popen:
        """`services.up` on host A as `runner`, joined to the router by A's address only."""
        runner = self.client_file("mapex-runner", "runner.json5")
        argv = ["python", "-m", "services.up", "--config", str(runner), "--mode", "client",
                "--connect", self.router.endpoint, *UP_FLAGS, "--run-prefix", name,
                "--out", str(self.directory / "runs"), *args]  # fmt: skip
        return self.hosts.spawn("a", argv, self.directory / f"{name}.log")

    def log(self, name: str) -> str:
        return (self.directory / f"{name}.log").read_text(errors="replace")


def hosts_or_fail(tag: str) -> TwoHosts:
    """The two hosts, or the test fails with one line saying why they cannot be made."""
    if shutil.which("openssl") is None:
        pytest.fail("the two-host test needs the openssl command", pytrace=False)
    try:
        return two_hosts(tag)
    except NamespaceError as error:
        pytest.fail(f"the two-host test cannot make network namespaces: {error}", pytrace=False)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    hosts = hosts_or_fail(str(os.getpid()))
    router = None
    try:
        directory = tmp_path_factory.mktemp("two-hosts")
        router = start_acl_router(directory, "mtls", host=ADDRESS_A, launcher=hosts.launcher("a"))
        cluster = Cluster(hosts, router, directory, directory / "workers.log")
        worker = cluster.client_file("mapex-worker", "worker.json5")
        hosts.spawn(
            "b",
            ["python", str(HELPERS / "worker_host.py"), "--members", ",".join(MEMBER_NAMES),
             "--id-prefix", HOST_B, "--", "--config", str(worker), "--mode", "client",
             "--connect", router.endpoint],
            cluster.workers_log,
        )  # fmt: skip
        yield cluster
    finally:
        if router is not None:
            kill_router(router)
        hosts.close()


def middle_start_cell() -> tuple[int, int]:
    """An eligible start cell of WORLD in the middle of the list (as tests/services/test_up)."""
    cells = np.argwhere(eligible_start_cells(load_world(WORLD), 3))
    return tuple(int(v) for v in cells[len(cells) // 2])


def in_process_run(steps: int, start: tuple[int, int], directory: Path):
    """The same `mapex` episode in one process, one torch thread like a worker, written out
    and read back as the distributed run is (tests/services/test_up.py compares alike)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        world = load_world(WORLD)
        config = ExplorationConfig(steps=steps)
        result = run_episode(world, "mapex", LearnedEnsemble(), start, 0, config)
    finally:
        torch.set_num_threads(threads)
    return read_run(write_results(result, world, directory / "in_process"))


def wait_for_exit(process: subprocess.Popen, log: str, timeout_s: float = RUN_DEADLINE_S) -> int:
    try:
        return process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        pytest.fail(f"still running after {timeout_s:g} s:\n{log}")


def test_the_router_listens_on_host_a_s_veth_address_only(cluster):
    endpoint = f"tls/{ADDRESS_A}:"
    assert cluster.router.endpoint.startswith(endpoint)
    said = re.search(r"listening on (\[.*\])", cluster.router.log()).group(1)
    assert said == f'["{cluster.router.endpoint}"]', cluster.router.log()
    assert cluster.router.process.pid in cluster.hosts.pids("a")
    san = subprocess.run(
        ["openssl", "x509", "-in", "router.pem", "-noout", "-ext", "subjectAltName"],
        cwd=cluster.directory, capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    assert f"IP Address:{ADDRESS_A}" in san and "127.0.0.1" not in san, san


def test_a_run_across_two_hosts_equals_the_in_process_run(cluster):
    start = middle_start_cell()
    up = cluster.up("same", "--steps", str(STEPS), "--start", f"{start[0]},{start[1]}")
    assert wait_for_exit(up, cluster.log("same")) == 0, cluster.log("same")
    metrics, trajectory, curves = read_run(cluster.directory / "runs" / "same-0-r0")
    expected_metrics, expected_trajectory, expected_curves = in_process_run(
        STEPS, start, cluster.directory
    )
    np.testing.assert_array_equal(trajectory, expected_trajectory)
    assert curves == expected_curves
    assert metrics["auc"] == expected_metrics["auc"] and metrics["replans"] > 1
    assert metrics["degraded_steps"] == [] and metrics["degraded_metric_samples"] == []
    audit = metrics["member_workers"]  # who answered every member query
    workers = {member: f"{HOST_B}-{member}-0" for member in MEMBER_NAMES}
    assert len(audit["replans"]) == metrics["replans"] and audit["metric_samples"]
    assert all(served == {m: workers[m] for m in ("g1", "g2", "g3")}
               for _, served in audit["replans"])  # fmt: skip
    assert all(served == {"g": workers["g"]} for _, served in audit["metric_samples"])
    started = dict(re.findall(r"\[supervisor\] started (\S+) \(pid (\d+)\)", _workers(cluster)))
    assert sorted(started) == sorted(f"predictor-{m}" for m in MEMBER_NAMES), started
    assert {int(pid) for pid in started.values()} <= set(cluster.hosts.pids("b"))


def test_a_worker_killed_on_host_b_mid_run_is_replaced_and_the_run_completes(cluster):
    follower = cluster.hosts.spawn(
        "a",
        ["python", str(HELPERS / "netns_probe.py"), "follow",
         str(cluster.client_file("mapex-viewer", "viewer.json5")), "kill-0"],
        cluster.directory / "follow.log",
    )  # fmt: skip
    up = cluster.up("kill", "--steps", str(KILL_STEPS))

    def reached() -> bool:
        if up.poll() is not None:
            pytest.fail(f"services.up exited before step {KILL_AT}:\n{cluster.log('kill')}")
        steps = [int(t) for t in re.findall(r"step (\d+)", cluster.log("follow"))]
        return bool(steps) and max(steps) >= KILL_AT

    until(reached, f"the run to reach step {KILL_AT}", RUN_DEADLINE_S)
    (killed,) = (int(pid) for pid in RESTARTED.findall(_workers(cluster)))
    os.kill(killed, signal.SIGKILL)
    killed_during = up.poll() is None
    assert wait_for_exit(up, cluster.log("kill")) == 0, cluster.log("kill")
    follower.kill()
    assert killed_during, "the run had ended before the kill"
    metrics, trajectory, curves = read_run(cluster.directory / "runs" / "kill-0-r0")
    assert int(curves[-1][0]) == KILL_STEPS
    assert len(trajectory) == KILL_STEPS + 1 or metrics["finished_at"] is not None
    assert f"predictor-{KILLED} exited with -9 (SIGKILL); restarted (1/" in _workers(cluster)
    replans = dict(map(tuple, metrics["member_workers"]["replans"]))
    assert all(t >= KILL_AT and KILLED not in replans[t] for t in metrics["degraded_steps"])

    def replaced() -> int | None:
        pids = [int(pid) for pid in RESTARTED.findall(_workers(cluster))]
        return pids[-1] if len(pids) == 2 else None

    replacement = until(replaced, "the worker's replacement", PROBE_DEADLINE_S)
    assert replacement != killed and replacement in cluster.hosts.pids("b")
    planner = cluster.client_file("mapex-planner", "planner.json5")
    key = f"mapex/@v1/alive/predict/{KILLED}/{HOST_B}-{KILLED}-0"

    def rejoined() -> bool:  # the replacement is back in the pool, seen from host A
        return key in cluster.probe("a", "workers", planner).stdout.split()

    until(rejoined, "the replacement to rejoin the pool", PROBE_DEADLINE_S)


def test_two_shards_on_two_hosts_share_host_b_s_pool_and_merge_to_the_whole(cluster):
    """A tiny campaign (tests/helpers/shard_runs.py) whole on A, and as 2 shards, one on
    each host into a folder of its own, all three at once on B's workers (`--members
    none`) through the router; `python -m mapex.report` merges the shards' folders into the
    whole's table."""
    runner = cluster.client_file("mapex-runner", "runner.json5")
    joined = ("--config", str(runner), "--mode", "client", "--connect", cluster.router.endpoint,
              "--members", "none")  # fmt: skip
    root = cluster.directory
    whole, shards = root / "whole", [root / "shard-a", root / "shard-b"]
    commands = [evaluate_command(whole, *joined), *shard_commands(shards, 2, *joined)]
    logs = [root / f"evaluate-{name}.log" for name in ("whole", "a", "b")]
    processes = [
        cluster.hosts.spawn(host, command, log)
        for host, command, log in zip("aab", commands, logs, strict=True)
    ]
    for process, log in zip(processes, logs, strict=True):
        text = log.read_text(errors="replace") if log.exists() else ""
        assert wait_for_exit(process, text) == 0, log.read_text(errors="replace")
    expected = run_records(whole)
    parts = [run_records(folder) for folder in shards]
    assert len(expected) == 4 and all(parts) and not set(parts[0]) & set(parts[1])
    merged = parts[0] | parts[1]
    sharded, unsharded = comparable_tables(merged, expected)
    assert sharded == unsharded, pool_warnings(*logs)
    for record in merged.values():  # G's metric samples: answered by B's worker only
        assert {served["g"] for _, served in record["member_workers"]["metric_samples"]} == {
            f"{HOST_B}-g-0"
        }, record["member_workers"]
    for args in ([*map(str, shards), "--out", str(root / "merged")], [str(whole)]):
        done = subprocess.run([sys.executable, "-m", "mapex.report", *args], cwd=REPO_ROOT,
                              capture_output=True, text=True, timeout=PROBE_DEADLINE_S)  # fmt: skip
        assert done.returncode == 0, done.stderr
    reports = (whole / "report" / "report.json", root / "merged" / "report.json")
    tables = [json.loads(path.read_text()) for path in reports]
    if any_degraded(expected, merged):  # only coverage is sure
        tables = [{m: row["auc"]["coverage"] for m, row in t["methods"].items()} for t in tables]
    assert tables[0] == tables[1], pool_warnings(*logs)


def test_a_client_on_host_b_without_a_certificate_is_refused(cluster):
    worker = cluster.client_file("mapex-worker", "worker-probe.json5")
    joined = cluster.probe("b", "join", worker)
    assert joined.returncode == 0 and joined.stdout.split() == ["joined", cluster.router.zid]
    bare = cluster.client_file(
        "mapex-worker", "no-certificate.json5",
        **{f'"{cluster.directory / "mapex-worker.pem"}"': "null",
           f'"{cluster.directory / "mapex-worker-key.pem"}"': "null"},
    )  # fmt: skip
    refused = cluster.probe("b", "join", bare)
    assert refused.returncode == 2 and "Unable to connect" in refused.stdout, refused.stdout


def test_a_router_whose_certificate_does_not_name_host_a_is_refused(cluster, tmp_path):
    """The same TLS router (deploy/zenohd-tls.json5) on A's address, with a certificate for
    localhost and 127.0.0.1 only: a client on B dialling A's address refuses it, and accepts
    it once told not to check the name (so the name is what it refused)."""
    make_role_certificates(tmp_path, ("worker",), LOOPBACK_NAMES)
    text = ROUTER_TLS.read_text().replace("/etc/mapex/tls/", f"{tmp_path}/")
    (tmp_path / "router.json5").write_text(text)
    listen = f"tls/{ADDRESS_A}:{_other_port(cluster)}"
    log = tmp_path / "misnamed-router.log"
    argv = ["python", "-m", "deploy.router", "--config", str(tmp_path / "router.json5"),
            "--listen", listen]  # fmt: skip
    misnamed = RouterProcess(cluster.hosts.spawn("a", argv, log), log, listen)
    try:
        wait_router_ready(misnamed)
        strict, lax = (
            _client_of(cluster, tmp_path, listen, name, verify)
            for name, verify in (("strict.json5", "true"), ("lax.json5", "false"))
        )
        refused = cluster.probe("b", "join", strict)
        assert refused.returncode == 2 and "Unable to connect" in refused.stdout, refused.stdout
        joined = cluster.probe("b", "join", lax)
        assert joined.returncode == 0 and joined.stdout.split() == ["joined", misnamed.zid]
    finally:
        kill_router(misnamed)


def _client_of(cluster: Cluster, directory: Path, endpoint: str, name: str, verify: str) -> Path:
    """deploy/client-tls.json5 for `directory`'s certificates, dialling `endpoint`."""
    text = CLIENT_TLS.read_text().replace("/etc/mapex/tls/", f"{directory}/")
    text = text.replace("tls/router.example.org:7447", endpoint)
    text = text.replace("verify_name_on_connect: true", f"verify_name_on_connect: {verify}")
    path = directory / name
    path.write_text(text)
    return path


def _other_port(cluster: Cluster) -> int:
    return int(cluster.router.endpoint.rsplit(":", 1)[1]) + 1


def _workers(cluster: Cluster) -> str:
    return cluster.workers_log.read_text(errors="replace")


def test_where_namespaces_cannot_be_made_the_test_fails_with_one_line(monkeypatch):
    """Never a silent skip or pass: no `ip`, not root, or `ip` refusing all fail the test."""
    import netns

    refused = "cannot make network namespaces: `ip netns add mapex-a/b-a` failed: Invalid netns"
    with pytest.raises(pytest.fail.Exception, match=refused):
        hosts_or_fail("a/b")  # `ip` itself refuses the name: nothing is made
    monkeypatch.setattr(netns.os, "geteuid", lambda: 1000)
    with pytest.raises(pytest.fail.Exception, match="need root; running as uid 1000$"):
        hosts_or_fail("x")
    which = shutil.which
    monkeypatch.setattr(netns.shutil, "which", lambda name: None if name == "ip" else which(name))
    with pytest.raises(pytest.fail.Exception, match=r"the `ip` command \(iproute2\) is missing$"):
        hosts_or_fail("x")
    monkeypatch.setattr(netns.shutil, "which", lambda name: None)
    with pytest.raises(pytest.fail.Exception, match="the two-host test needs the openssl command"):
        hosts_or_fail("x")
