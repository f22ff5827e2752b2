"""The live viewer: pure rendering and decoding, then real watch processes on loopback.

The test process opens the hub session and plays the planner with a LatestPublisher; watch
processes are spawned (never forked) against it, some only after the frames were put (late
joiners), and all are killed at teardown whatever happens.
"""

from __future__ import annotations

import io
import logging
import signal
import subprocess
import sys

import msgpack
import numpy as np
import pytest
from PIL import Image
from service_processes import REPO_ROOT, STOP_DEADLINE_S, ServiceProcesses, until

from mapex.grid import FREE, OCCUPIED
from services.bridges.watch import (
    WATCHED_TOPICS,
    Inbox,
    WatchState,
    apply_payloads,
    apply_teammates,
    decode_topic,
    run_cli,
)
from services.bridges.watch_render import FrameReel, render_frame, write_atomic
from services.codec import ProtocolError
from services.config import WatchConfig
from services.keys import robot_key
from services.latest import LatestPublisher
from services.messages import (
    FrontiersMessage,
    GoalMessage,
    MapMessage,
    MetricsMessage,
    PathMessage,
    PoseMessage,
    StatusMessage,
)

SHAPE = (40, 50)
PURPLE_RGB = (148, 103, 189)  # matplotlib's tab:purple, the first teammate's colour
POSE_RGB = (31, 119, 180)  # tab:blue, the pose marker
START_DEADLINE_S = 60.0  # imports (matplotlib, zenoh) on a shared 2-core machine
EXIT_DEADLINE_S = 15.0
SMALL = WatchConfig(dpi=40, panel_inches=3.0)


def _frames(t: int, observed_code: int = FREE) -> dict[str, object]:
    """One message per watched topic, all about step `t`."""
    rng = np.random.default_rng(t)
    return {
        "observed_map": MapMessage(t, "observed", np.full(SHAPE, observed_code, np.uint8)),
        "prediction/mean": MapMessage.from_probabilities(t, "mean", rng.random(SHAPE)),
        "prediction/variance": MapMessage.from_probabilities(t, "variance", rng.random(SHAPE) / 4),
        "pose": PoseMessage(t, (20, 25)),
        "frontiers": FrontiersMessage(t, np.array([[5, 5], [6, 5]]), np.array([0.5, 0.7])),
        "goal": GoalMessage(t, (5, 5)),
        "path": PathMessage(t, np.array([[20, 25], [10, 15], [5, 5]])),
        "status": StatusMessage(t, "running"),
        "metrics": MetricsMessage(t, 0.25, 0.5, None, False),
    }


def _state(frames: dict[str, object]) -> WatchState:
    state = WatchState("demo", "r0")
    for topic, message in frames.items():
        state.apply(topic, message)
    return state


def _pixels(png: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(png)) as image:
        assert image.format == "PNG"
        return np.asarray(image.convert("RGB")).astype(int)


def _has_colour(pixels: np.ndarray, rgb: tuple[int, int, int], tolerance: int = 12) -> bool:
    return bool((np.abs(pixels - np.array(rgb)).max(axis=2) <= tolerance).any())


# ---------------------------------------------------------------------- pure: render, decode


def test_render_frame_draws_the_maps_and_the_overlays():
    plain = _frames(3)
    for topic in ("pose", "frontiers", "goal", "path"):
        del plain[topic]
    with_overlays = _pixels(render_frame(_state(_frames(3)), SMALL))
    without = _pixels(render_frame(_state(plain), SMALL))
    walls = _pixels(render_frame(_state(_frames(3, OCCUPIED)), SMALL))
    assert with_overlays.shape == without.shape == walls.shape
    assert _has_colour(with_overlays, POSE_RGB) and not _has_colour(without, POSE_RGB)
    assert walls.mean() < with_overlays.mean() - 20  # black walls instead of white free space


def test_teammates_are_drawn_in_their_own_colour_and_malformed_ones_dropped(caplog):
    state = _state(_frames(3))
    alone = _pixels(render_frame(state, SMALL))
    payloads = {
        ("r1", "pose"): PoseMessage(3, (30, 40)).encode(),
        ("r1", "path"): PathMessage(3, np.array([[30, 40], [35, 45]])).encode(),
        ("r1", "goal"): b"\x00junk",
    }
    assert apply_teammates(state, payloads)
    assert set(state.teammates["r1"]) == {"pose", "path"}
    assert "dropped a malformed message of r1 on goal" in caplog.text
    team = _pixels(render_frame(state, SMALL))
    assert _has_colour(team, PURPLE_RGB) and not _has_colour(alone, PURPLE_RGB)


def test_render_frame_copes_with_nothing_but_a_status():
    state = WatchState("demo", "r0", status=StatusMessage(0, "starting"))
    assert _pixels(render_frame(state, SMALL)).size > 0
    assert state.t == 0 and not state.finished


@pytest.mark.parametrize(
    "topic, payload, match",
    [
        ("observed_map", MapMessage.from_probabilities(1, "mean", np.zeros(SHAPE)), "kind"),
        ("prediction/variance", MapMessage(1, "observed", np.zeros(SHAPE, np.uint8)), "kind"),
        ("status", PoseMessage(1, (2, 3)), "expected a message of type status"),
        ("pose", b"\x92\x01\x02", "not a map"),
        ("goal", msgpack.packb({"schema": 2, "type": "goal"}), "schema version"),
    ],
)
def test_decode_topic_refuses_the_wrong_message(topic, payload, match):
    payload = payload if isinstance(payload, bytes) else payload.encode()
    with pytest.raises(ProtocolError, match=match):
        decode_topic(topic, payload)


def test_apply_payloads_logs_and_drops_malformed_ones_keeping_the_last_good(caplog):
    state = _state(_frames(4))
    keys = {topic: f"key/{topic}" for topic in WATCHED_TOPICS}
    payloads = {"pose": [b"junk"], "goal": [GoalMessage(5, None).encode()]}
    with caplog.at_level(logging.WARNING, logger="services.watch"):
        assert apply_payloads(state, payloads, keys)
    assert state.pose.t == 4 and state.goal.goal is None and state.t == 5
    assert "dropped a malformed message on key/pose" in caplog.text
    assert not apply_payloads(state, {"status": [b"junk"]}, keys)
    state.apply("status", StatusMessage(6, "failed"))
    assert state.finished


def test_a_malformed_payload_right_after_the_final_status_does_not_hide_it():
    state = _state(_frames(4))
    keys = {topic: f"key/{topic}" for topic in WATCHED_TOPICS}
    inbox = Inbox(depth=3)
    for payload in (b"old junk", StatusMessage(7, "finished").encode(), b"junk", b"more junk"):
        inbox.deliver("status", payload)
    assert apply_payloads(state, inbox.drain(), keys)
    assert state.finished and state.status.t == 7


def test_inbox_keeps_the_newest_in_order_and_prefers_live_samples_to_late_replies():
    inbox = Inbox()
    inbox.offer("goal", b"old reply")
    inbox.deliver("goal", b"live")
    inbox.offer("pose", b"reply")
    inbox.deliver("status", b"one")
    inbox.deliver("status", b"two")
    inbox.offer("status", b"stale reply")
    assert inbox.drain() == {
        "goal": [b"old reply", b"live"],
        "pose": [b"reply"],
        "status": [b"one", b"two"],
    }  # newest last; a reply after a live sample is stale
    assert inbox.drain() == {}
    assert set(inbox.unheard()) == set(WATCHED_TOPICS) - {"goal", "pose", "status"}


def _tiny_png(value: int) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (64, 32), (value, 255 - value, 0)).save(buffer, format="PNG")
    return buffer.getvalue()


def test_frame_reel_stays_bounded_keeps_the_last_frame_and_writes_a_gif(tmp_path):
    reel = FrameReel(max_frames=8, max_side_px=32)
    for value in range(100):
        reel.add(_tiny_png(value))
    reel.add(_tiny_png(255), force=True)
    assert 4 <= len(reel.frames) < 8 and reel.stride > 1
    assert max(reel.frames[0].size) <= 32
    path = tmp_path / "reel.gif"
    write_atomic(path, reel.gif_bytes(frame_ms=50))
    assert [p.name for p in tmp_path.iterdir()] == ["reel.gif"]  # no temporary file left
    with Image.open(path) as gif:
        assert gif.format == "GIF" and gif.n_frames == len(reel.frames)
        reds = []
        for index in range(gif.n_frames):
            gif.seek(index)
            reds.append(gif.convert("RGB").getpixel((0, 0))[0])
    assert reds[-1] > 250  # the forced last frame is the last one
    steps = np.diff(reds[:-1])
    assert (steps > 0).all() and steps.max() - steps.min() <= 2  # evenly thinned, in order


# ---------------------------------------------------------------------- real watch processes


@pytest.fixture
def processes(hub, tmp_path):
    spawned = ServiceProcesses(hub[1], tmp_path)
    try:
        yield spawned
    finally:
        spawned.kill_all()


def _keys(run: str) -> dict[str, str]:
    return {topic: robot_key(run, "r0", topic) for topic in WATCHED_TOPICS}


def _publish(latest: LatestPublisher, keys: dict[str, str], frames: dict[str, object]) -> None:
    for topic, message in frames.items():
        latest.put(keys[topic], message)


def _spawn_watch(processes: ServiceProcesses, run: str, *flags: str) -> subprocess.Popen:
    png = processes.log_dir / f"{run}.png"
    return processes.spawn(run, "services.watch", "--run", run, "--png", str(png), *flags)


def _png_pixels(processes: ServiceProcesses, run: str) -> np.ndarray | None:
    path = processes.log_dir / f"{run}.png"
    return _pixels(path.read_bytes()) if path.exists() else None


def test_a_late_joiner_renders_the_latest_frames_and_stops_on_sigint(hub, processes):
    run = "watch_late"
    keys = _keys(run)
    with LatestPublisher(hub[0], list(keys.values())) as latest:
        _publish(latest, keys, _frames(1))
        _publish(latest, keys, _frames(2))  # before the watch exists
        process = _spawn_watch(processes, run, "--every-s", "0.2")

        def pose_drawn() -> bool:
            pixels = _png_pixels(processes, run)
            return pixels is not None and _has_colour(pixels, POSE_RGB)

        processes.wait_until_announced(run, pose_drawn, START_DEADLINE_S)
        process.send_signal(signal.SIGINT)
        assert process.wait(STOP_DEADLINE_S) == 0
    log = processes.log_of(run)
    assert "stopped (stopped)" in log
    assert "WARNING" not in log and "Traceback" not in log


def test_until_finished_writes_a_gif_after_the_status_says_finished(hub, processes):
    run = "watch_gif"
    keys = _keys(run)
    gif = processes.log_dir / "run.gif"
    with LatestPublisher(hub[0], list(keys.values())) as latest:
        _publish(latest, keys, _frames(1))
        process = _spawn_watch(
            processes, run, "--gif", str(gif), "--until-finished", "--every-s", "0.1"
        )
        processes.wait_until_announced(
            run, lambda: _png_pixels(processes, run) is not None, START_DEADLINE_S
        )
        assert not gif.exists()
        for t in (2, 3):
            latest.put(keys["observed_map"], _frames(t)["observed_map"])
        latest.put(keys["status"], StatusMessage(4, "finished"))
        assert process.wait(EXIT_DEADLINE_S) == 0
    with Image.open(gif) as image:
        assert image.format == "GIF" and image.n_frames >= 2
    log = processes.log_of(run)
    assert "stopped (finished)" in log and "Traceback" not in log


def test_malformed_payloads_are_dropped_and_the_watch_renders_on(hub, processes):
    run = "watch_bad"
    keys = _keys(run)
    session = hub[0]
    png = processes.log_dir / f"{run}.png"
    with LatestPublisher(session, list(keys.values())) as latest:
        latest.put(keys["observed_map"], _frames(1)["observed_map"])
        process = _spawn_watch(processes, run, "--every-s", "0.1")
        processes.wait_until_announced(run, png.exists, START_DEADLINE_S)
        rng = np.random.default_rng(0)
        for key in keys.values():
            session.put(key, rng.bytes(64))
        until(lambda: _dropped(processes, run) >= len(keys), "random bytes to be dropped")
        session.put(keys["observed_map"], PoseMessage(3, (1, 1)).encode())
        session.put(keys["status"], msgpack.packb({"schema": 9, "type": "status"}))
        until(lambda: _dropped(processes, run) >= len(keys) + 2, "wrong schemas to be dropped")
        assert process.poll() is None
        before = png.stat().st_ino
        latest.put(keys["observed_map"], _frames(5, OCCUPIED)["observed_map"])
        until(lambda: png.stat().st_ino != before, "a new frame after the good map")
        assert process.poll() is None
    log = processes.log_of(run)
    for key in keys.values():
        assert f"dropped a malformed message on {key}:" in log
    assert "Traceback" not in log


def _dropped(processes: ServiceProcesses, run: str) -> int:
    return processes.log_of(run).count("dropped a malformed message on")


def test_until_finished_times_out_with_exit_1(tmp_path, hub):
    result = subprocess.run(
        [sys.executable, "-m", "services.watch", "--run", "watch_never", "--until-finished",
         "--timeout-s", "0.5", "--png", str(tmp_path / "w.png"), "--connect", hub[1]],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=START_DEADLINE_S,
    )  # fmt: skip
    assert result.returncode == 1, result.stderr
    assert "before run watch_never finished" in result.stderr
    assert "Traceback" not in result.stderr


# ---------------------------------------------------------------------- flags


@pytest.mark.parametrize(
    "flags, message",
    [
        ([], "the following arguments are required: --run"),
        (["--run", "Bad Run"], "--run 'Bad Run' must match"),
        (["--run", "predict"], "--run 'predict' must match"),
        (["--run", "ok", "--robot", "R0"], "--robot 'R0' must match"),
        (["--run", "ok", "--every-s", "0"], "'0' is not a positive number of seconds"),
        (["--run", "ok", "--timeout-s", "nan"], "'nan' is not a positive number of seconds"),
        (["--run", "ok", "--png", "{missing}/w.png"], "does not exist"),
        (["--run", "ok", "--gif", "{tmp}"], "is a directory"),
    ],
)
def test_bad_flags_are_one_line_errors(flags, message, tmp_path, capsys):
    flags = [f.format(missing=tmp_path / "none", tmp=tmp_path) for f in flags]
    with pytest.raises(SystemExit) as exit_info:
        run_cli(flags)
    assert exit_info.value.code == 2
    errors = capsys.readouterr().err.splitlines()
    assert sum(message in line for line in errors) == 1 and "Traceback" not in "\n".join(errors)


def test_bad_flags_exit_2_as_a_process(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "services.watch", "--run", "ok", "--every-s", "-1"],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=START_DEADLINE_S,
    )  # fmt: skip
    assert result.returncode == 2
    assert result.stderr.splitlines()[-1].endswith("'-1' is not a positive number of seconds")
    assert "Traceback" not in result.stderr
