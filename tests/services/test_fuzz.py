"""A seeded fuzz of every service key during a real run: thousands of random and mutated
messages of every type, and the run still answers and ends with the in-process result.

Seeds are real messages (a world's world_info and ground truth, a worker's health and
prediction, a step request and reply, pose, scan, maps and metrics heard on the wire);
each is mutated at the msgpack level (a field dropped, retyped, made huge, negative, NaN,
an array header lying about its shape or dtype, another type or schema) or at the byte
level (flips, truncation, junk appended), and sent to a key a service listens on: a query
to every queryable, a put to every subscribed topic. Bounded in count and in time.
Meanwhile a rogue answers every step query of the run with forged replies (the team
finished, a teleport), and oversized but valid payloads (31 MiB of empty msgpack maps, a
claim larger than the world) go to the world and the workers, whose peak memory must not
grow by more than `PEAK_GROWTH_BYTES`.

The same episode in one process, which the run must equal, is computed beside the run (a
`python -m mapex run` child) rather than after it: tens of seconds of CPU on this floor.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
from service_processes import REPO_ROOT, free_loopback_port, until
from up_processes import RUN_DEADLINE_S, UpProcess, read_run

from mapex.grid import FREE, UNKNOWN
from services.keys import (
    ROBOT_TOPICS,
    alive_planner_key,
    alive_predictor_pattern,
    health_key,
    parse_key,
    predict_key,
    robot_key,
    run_key,
)
from services.messages import ErrorReply, PredictRequest, StepReply, StepRequest, WorldInfo
from services.zenoh_config import open_session, zenoh_config

FLOOR = "50015847"  # the largest KTH development floor: a run long enough to fuzz
RUN = "fuzz-0"
STEPS = 1000
METHOD = "mapex"  # predicts at every re-plan: the run lasts while the fuzz goes on
MESSAGES = 3000  # in all, spread over every key
TIME_BUDGET_S = 120.0  # the fuzzing stops here even if fewer were sent
SEED = 53
BIG_BYTES = 31 * 2**20  # under the 32 MiB message limit
PEAK_GROWTH_BYTES = 400 * 2**20  # of a process's peak memory (VmHWM) under big payloads


def real_messages(session) -> list[bytes]:
    """Encoded messages of every type the run's services exchange, heard or asked for."""
    seeds: list[bytes] = []
    for key in (run_key(RUN, "world_info"), run_key(RUN, "ground_truth")):
        seeds += [reply.ok.payload.to_bytes() for reply in session.get(key, timeout=5.0)]
    small = np.full((16, 16), UNKNOWN, dtype=np.uint8)
    small[4:12, 4:12] = FREE
    request = PredictRequest(1, small, 5.0).encode()
    seeds.append(request)
    for alive in session.liveliness().get(alive_predictor_pattern(), timeout=2.0):
        worker = parse_key(str(alive.ok.key_expr))
        for key, payload in (
            (health_key(worker.member, worker.worker_id), None),
            (predict_key(worker.member, worker.worker_id), request),
        ):
            for reply in session.get(key, payload=payload, timeout=10.0):
                sample = reply.ok if reply.ok is not None else reply.err
                seeds.append(sample.payload.to_bytes())
    cells = np.array([[1, 1]], dtype=np.int32)
    seeds.append(StepRequest(0, cells, False, False, None, None, None).encode())
    visible = np.zeros((8, 8), dtype=bool)
    seeds.append(StepRequest(3, cells, False, True, (2, 2), 1.5, visible).encode())
    seeds.append(ErrorReply("x").encode())
    heard: list[bytes] = []
    subscriber = session.declare_subscriber(
        f"mapex/@v1/{RUN}/**", lambda sample: heard.append(sample.payload.to_bytes())
    )
    time.sleep(3.0)
    subscriber.undeclare()
    by_type: dict[str, bytes] = {}
    for payload in heard:
        by_type.setdefault(msgpack.unpackb(payload, raw=False).get("type", ""), payload)
    return seeds + list(by_type.values())


ODD_VALUES = [
    None, -1, 0, 2**63 - 1, -(2**63), 1e308, float("nan"), float("inf"), "x" * 5000, "",
    [], {}, [1, 2, 3], True, b"\x00" * 64,
    {"dtype": "int32", "shape": [10**6, 10**6], "zlib": False, "data": b""},
    {"dtype": "float64", "shape": [2, 2], "zlib": True, "data": b"not zlib"},
    {"dtype": "object", "shape": [1], "zlib": False, "data": b"\x00" * 8},
    {"dtype": "uint8", "shape": [-1, 4], "zlib": False, "data": b""},
]  # fmt: skip


def mutate(seed: bytes, rng: np.random.Generator, types: list[str]) -> bytes:
    """One mutation of an encoded message (module doc)."""
    choice = rng.integers(8)
    if choice == 0:  # byte flips
        data = bytearray(seed)
        for _ in range(rng.integers(1, 8)):
            data[rng.integers(len(data))] = int(rng.integers(256))
        return bytes(data)
    if choice == 1:  # truncated
        return seed[: rng.integers(len(seed))]
    if choice == 2:  # random bytes of random length
        return rng.bytes(int(rng.integers(0, 2048)))
    fields = msgpack.unpackb(seed, raw=False)
    names = [name for name in fields if name != "schema"]
    if choice == 3 and names:  # a field dropped
        fields.pop(names[rng.integers(len(names))])
    elif choice == 4:  # another type, or another schema
        if rng.random() < 0.5:
            fields["type"] = types[rng.integers(len(types))]
        else:
            fields["schema"] = ODD_VALUES[rng.integers(len(ODD_VALUES))]
    elif choice == 5:  # a field added
        fields[f"extra{rng.integers(9)}"] = ODD_VALUES[rng.integers(len(ODD_VALUES))]
    elif names:  # a field retyped or made absurd
        fields[names[rng.integers(len(names))]] = ODD_VALUES[rng.integers(len(ODD_VALUES))]
    return msgpack.packb(fields, use_bin_type=True)


def fuzz(session, seeds: list[bytes], worker_keys: list[str]) -> int:
    """Send mutated seeds to every key until MESSAGES are sent or the time is up."""
    rng = np.random.default_rng(SEED)
    types = sorted({msgpack.unpackb(s, raw=False).get("type", "") for s in seeds})
    queried = [run_key(RUN, "world_info"), run_key(RUN, "ground_truth")]
    queried += [robot_key(RUN, "r0", "step"), *worker_keys]
    queried += [robot_key(RUN, "r0", topic) for topic in ROBOT_TOPICS]  # latest-value queryables
    put = [robot_key(RUN, "r0", topic) for topic in ROBOT_TOPICS]
    put += [run_key(RUN, "world_info"), run_key(RUN, "ground_truth")]
    keys = [(key, True) for key in queried] + [(key, False) for key in put]
    began, sent = time.monotonic(), 0
    while sent < MESSAGES and time.monotonic() - began < TIME_BUDGET_S:
        key, query = keys[sent % len(keys)]
        payload = mutate(seeds[rng.integers(len(seeds))], rng, types)
        if query:
            session.get(key, payload=payload, timeout=1.0)  # replies are not awaited
        else:
            session.put(key, payload)
        sent += 1
        if sent % 50 == 0:
            time.sleep(0.05)  # a flood, not a denial of service of the test machine
    return sent


def answering(session) -> bool:
    """Whether the world and every worker still answer a well-formed query."""
    if not list(session.get(run_key(RUN, "world_info"), timeout=5.0)):
        return False
    workers = list(session.liveliness().get(alive_predictor_pattern(), timeout=2.0))
    for alive in workers:
        worker = parse_key(str(alive.ok.key_expr))
        if not list(session.get(health_key(worker.member, worker.worker_id), timeout=5.0)):
            return False
    return len(workers) == 4


def message_type(payload: bytes) -> str:
    """The `type` of an encoded message."""
    return msgpack.unpackb(payload, raw=False).get("type", "")


def empty_maps(size_bytes: int, type_name: str) -> bytes:
    """A valid msgpack message of `type_name` whose one field is a list of empty maps."""
    head = msgpack.packb({"schema": 1, "type": type_name}, use_bin_type=True)
    count = size_bytes - len(head) - 16
    field = msgpack.packb("cells") + b"\xdd" + count.to_bytes(4, "big") + b"\x80" * count
    return bytes([head[0] + 1]) + head[1:] + field  # one more field in the map


def big_claim(shape: tuple[int, int]) -> bytes:
    """A well-formed step request claiming cells of a map 16 times the world's."""
    visible = np.ones((shape[0] * 4, shape[1] * 4), dtype=bool)
    cells = np.array([[1, 1]], dtype=np.int32)
    return StepRequest(1, cells, False, True, (1, 1), 1.0, visible).encode()


def peak_bytes(pid: int) -> int:
    """The peak resident memory (VmHWM) of process `pid`."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no VmHWM for {pid}")


def service_pids(endpoint: str, modules: tuple[str, ...]) -> list[int]:
    """The processes of `modules` (python -m) connected to `endpoint`."""
    pids = []
    for status in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            argv = status.read_bytes().split(b"\0")
        except OSError:
            continue
        words = [a.decode(errors="replace") for a in argv]
        if endpoint in words and any(m in words for m in modules):
            pids.append(int(status.parent.name))
    return pids


def send_big_payloads(session, shape: tuple[int, int], worker_keys: list[str]) -> None:
    """Oversized but valid payloads to the world's step key and every worker's predict key."""
    step = robot_key(RUN, "r0", "step")
    for key, payload in [
        (step, empty_maps(BIG_BYTES, "step_request")),
        (step, big_claim(shape)),
        *[(key, empty_maps(BIG_BYTES, "predict_request")) for key in worker_keys],
    ]:
        list(session.get(key, payload=payload, timeout=20.0))


def forge_step_replies(session, shape: tuple[int, int]):
    """A rogue queryable answering every step query of the run with forged replies: the
    team finished, and the robot at the other end of the map. Undeclare when done."""
    lost = np.zeros(1, bool)
    none = {"stood_still": lost, "claim_state": np.zeros(1, np.uint8),
            "claim_goals": np.zeros((1, 2), np.int32), "claim_scores": np.zeros(1),
            "claim_visible": np.zeros((0, *shape), bool), "lost": lost}  # fmt: skip
    rays = 2500

    def forge(query) -> None:
        try:
            seq = StepRequest.decode(query.payload.to_bytes()).seq
        except Exception:  # noqa: BLE001 (the fuzz's own garbage)
            return
        finished = StepReply(seq, True, np.zeros((0, 2), np.int32), np.zeros((0, rays), np.uint16),
                             np.zeros((0, rays), bool), **none)  # fmt: skip
        corner = np.array([[shape[0] - 2, shape[1] - 2]], np.int32)
        far = StepReply(seq, False, corner, np.ones((1, rays), np.uint16),
                        np.zeros((1, rays), bool), **none)  # fmt: skip
        for reply in (finished, far):
            query.reply(query.key_expr, reply.encode())

    return session.declare_queryable(robot_key(RUN, "r0", "step"), forge)


def start_alone(world_spec: str, out: Path, log_path: Path) -> subprocess.Popen:
    """The episode in one process (`python -m mapex run`: corner 0, seed 0, the default
    settings and ensemble, as the run's) with one torch thread, as a worker computes."""
    command = [sys.executable, "-m", "mapex", "run", "--world", world_spec, "--method", METHOD,
               "--steps", str(STEPS), "--out", str(out), "--no-progress"]  # fmt: skip
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}  # torch's threads
    with open(log_path, "wb") as log:
        return subprocess.Popen(
            command, cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT, env=environment
        )


def test_thousands_of_mutated_messages_on_every_key_harm_no_process_and_no_result(
    tmp_path, kth_dev_dir
):
    world_spec = str(kth_dev_dir / FLOOR)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    up = UpProcess(
        tmp_path / "up.log", "--world", world_spec, "--listen", endpoint, "--run-prefix", "fuzz",
        "--out", str(tmp_path / "runs"), "--method", METHOD, "--steps", str(STEPS),
    )  # fmt: skip
    alone = start_alone(world_spec, tmp_path / "in_process", tmp_path / "in_process.log")
    session = open_session(zenoh_config(connect=[endpoint], listen=[]))
    try:
        until(
            lambda: list(session.liveliness().get(alive_planner_key(RUN, "r0"), timeout=1.0)),
            "the planner to start",
            120,
        )
        until(lambda: answering(session), "the world and four workers to answer", 120)
        workers = [parse_key(str(a.ok.key_expr)) for a in session.liveliness().get(
            alive_predictor_pattern(), timeout=2.0)]  # fmt: skip
        worker_keys = [predict_key(w.member, w.worker_id) for w in workers]
        worker_keys += [health_key(w.member, w.worker_id) for w in workers]
        seeds = real_messages(session)
        types = {msgpack.unpackb(s, raw=False).get("type") for s in seeds}
        assert {"world_info", "ground_truth", "health", "predict_reply", "step_request"} <= types
        (info,) = [WorldInfo.decode(s) for s in seeds if message_type(s) == "world_info"][:1]
        rogue = forge_step_replies(session, info.shape)
        sent = fuzz(session, seeds, worker_keys)
        assert sent >= 1000, sent
        pids = service_pids(endpoint, ("services.world", "services.predictor"))
        assert len(pids) == 5, pids  # the world and four workers
        peaks = {pid: peak_bytes(pid) for pid in pids}
        send_big_payloads(session, info.shape, worker_keys[:4])
        grown = {pid: peak_bytes(pid) - peaks[pid] for pid in pids}
        assert max(grown.values()) < PEAK_GROWTH_BYTES, grown
        rogue.undeclare()
        assert up.process.poll() is None, "the run ended before the fuzz did: make it longer"
        assert answering(session), up.log()
        assert up.wait() == 0, up.log()
        assert alone.wait(RUN_DEADLINE_S) == 0, (tmp_path / "in_process.log").read_text()
    finally:
        session.close()
        up.kill()
        if alone.poll() is None:
            alone.kill()
            alone.wait()
    log = up.log()
    assert "restarted" not in log and "Traceback" not in log, log[-5000:]
    metrics, trajectory, curves = read_run(tmp_path / "runs" / f"{RUN}-r0")
    expected = read_run(tmp_path / "in_process")
    np.testing.assert_array_equal(trajectory, expected[1])
    assert metrics["auc"]["coverage"] == expected[0]["auc"]["coverage"]
