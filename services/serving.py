"""What every service process does alike: answer queries on threads, stop on signals, log.

A service declares one queryable per key, answers its queries in arrival order on a
thread of its own (inside `with query:` so the querier stops waiting as soon as the
reply is sent), waits for SIGINT/SIGTERM and then undeclares and drains. Each answer is told
how long its query waited in the queue, so a worker can drop one its querier gave up on. An
answer that raises (a bug, or an input nobody foresaw) costs one warning and an `error`
reply, never the key's thread: the service answers the next query.
"""

from __future__ import annotations

import argparse
import ctypes
import logging
import math
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable

import zenoh

from services.codec import Payload
from services.config import MAX_PORT
from services.messages import ErrorReply, Message

Answer = Callable[[Payload | None, float], Message]
"""Turns a query's payload (None: none) into the reply, told how long (s) it waited queued."""
Signer = Callable[[str, bytes, bytes], bytes]
"""(key, query payload, reply payload) -> the MAC attached to the reply (a world's)."""
SUPERVISOR_PID_ENV = "MAPEX_SUPERVISOR_PID"  # set by services.supervisor for its children
# a run's secret: services.up sets it for its world and planners, which sign their steps with
# a key derived from it (services.messages.step_key); it never travels
RUN_TOKEN_ENV = "MAPEX_RUN_TOKEN"
STOP_POLL_S = 0.5  # how often the main thread looks up from waiting (signals run meanwhile)

log = logging.getLogger("services.serving")


class QueryServers:
    """One queryable and one answering thread per key, until `close`.

    Zenoh's threads only stamp each query with its arrival time and queue it; the key's
    thread answers the queue in arrival order. With a `signer`, every reply (an error too)
    is sent as a reply carrying its MAC as the attachment.
    """

    def __init__(
        self, session: zenoh.Session, answers: dict[str, Answer], signer: Signer | None = None
    ) -> None:
        self._queues: dict[str, queue.SimpleQueue] = {key: queue.SimpleQueue() for key in answers}
        self.queryables = [
            session.declare_queryable(key, self._enqueue(self._queues[key])) for key in answers
        ]
        self.threads = [
            threading.Thread(
                target=answer_queries,
                args=(self._queues[key], key, answer, signer),
                name=f"serve {key}",
                daemon=True,
            )
            for key, answer in answers.items()
        ]
        for thread in self.threads:
            thread.start()

    def queued(self, key: str) -> int:
        """Queries of `key` waiting for its thread (not counting the one being answered)."""
        return self._queues[key].qsize()

    def close(self, drain_s: float) -> None:
        """Undeclare every queryable, end each thread's loop and wait up to `drain_s` each."""
        for queryable in self.queryables:
            queryable.undeclare()
        for waiting in self._queues.values():
            waiting.put(None)
        for thread in self.threads:
            thread.join(drain_s)

    @staticmethod
    def _enqueue(waiting: queue.SimpleQueue) -> Callable[[zenoh.Query], None]:
        return lambda query: waiting.put((time.monotonic(), query))


def answer_queries(
    waiting: queue.SimpleQueue, key: str, answer: Answer, signer: Signer | None = None
) -> None:
    """Answer queued (arrival time, query) pairs in order until a None arrives; an answer
    that raises is one warning and an `error` reply, and the next query is answered."""
    while (item := waiting.get()) is not None:
        arrived, query = item
        with query:  # leaving the block finalises the query: the querier stops waiting
            payload = None
            try:
                payload = None if query.payload is None else query.payload.to_bytes()
                reply = answer(payload, time.monotonic() - arrived)
                encoded = reply.encode()
            except Exception as error:  # whatever it was (a bug, an unforeseen input): serve on
                why = " ".join(f"{type(error).__name__}: {error}".split())
                log.warning("%s: could not answer a query: %s", key, why)
                reply = ErrorReply(f"{key}: the query could not be answered")
                encoded = reply.encode()
            try:
                if signer is not None:
                    query.reply(key, encoded, attachment=signer(key, payload or b"", encoded))
                elif isinstance(reply, ErrorReply):
                    query.reply_err(encoded)
                else:
                    query.reply(key, encoded)
            except zenoh.ZError as error:  # e.g. the querier left; the next query is unaffected
                log.warning("could not send a reply: %s", " ".join(str(error).split()))


_signals_exit_until_serving = False  # set by exit_on_signals(until_serving=True)
_serving = False  # set when wait_for begins: the process serves


def exit_on_signals(until_serving: bool = False) -> None:
    """The first thing a service's `__main__` does: from here SIGINT and SIGTERM end the
    process at once (exit 128 + the signal number) while it loads a world or weights and
    sets up, so a process stopped then never lingers (an orphaned world setting up a huge
    team once ignored SIGTERM for minutes). `stop_on_signals` installs the graceful stop
    later; with `until_serving` its handler too exits at once until `wait_for` begins."""
    global _signals_exit_until_serving
    _signals_exit_until_serving = until_serving
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _exit_at_once)


def _exit_at_once(signum: int, _frame: object) -> None:
    os._exit(128 + signum)  # nothing to undeclare or flush yet: no cleanup to wait for


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM (a clean stop instead of a KeyboardInterrupt);
    after `exit_on_signals(until_serving=True)` a signal before `wait_for` exits at once."""
    stop = threading.Event()

    def handle(signum: int, frame: object) -> None:
        if _signals_exit_until_serving and not _serving:
            _exit_at_once(signum, frame)
        stop.set()

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, handle)
    return stop


def wait_for(stop: threading.Event) -> None:
    """Block until `stop` is set, waking regularly so signal handlers can run; also stop
    when the supervisor that started this process is gone (killed with SIGKILL). From here
    a signal stops the process gracefully (`exit_on_signals`)."""
    global _serving
    _serving = True
    while not stop.wait(STOP_POLL_S):
        if supervisor_gone():
            log.warning("the supervisor is gone: stopping")
            stop.set()


def supervisor_gone() -> bool:
    """Whether a supervisor started this process and has died since (it was orphaned)."""
    supervisor = os.environ.get(SUPERVISOR_PID_ENV)
    return supervisor is not None and str(os.getppid()) != supervisor


def run_token_from_env() -> str | None:
    """The run token of this process's run (`MAPEX_RUN_TOKEN`), or None when unset or empty."""
    return os.environ.get(RUN_TOKEN_ENV) or None


def configure_logging(process_name: str) -> None:
    """Log lines to stderr carrying the process name (services.up forwards them)."""
    logging.basicConfig(
        level=logging.INFO,
        format=f"%(asctime)s {process_name} %(levelname)s %(message)s",
        stream=sys.stderr,
    )


_M_TRIM_THRESHOLD = -1  # mallopt parameters of glibc's malloc.h
_M_MMAP_THRESHOLD = -3


def return_freed_memory(threshold_bytes: int = 4 * 2**20) -> bool:
    """Make glibc serve large blocks with mmap and trim the heap eagerly (True if applied).

    Torch frees its large activation tensors after every prediction, but glibc's default
    adaptive thresholds keep such blocks in the heap, so a worker's resident memory creeps
    up to twice what one prediction needs. With fixed thresholds freed blocks go back to the
    system. No-op where libc is not glibc.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(
            libc.mallopt(_M_MMAP_THRESHOLD, threshold_bytes)
            and libc.mallopt(_M_TRIM_THRESHOLD, threshold_bytes)
        )
    except (OSError, AttributeError):
        return False


def positive_number(unit: str) -> Callable[[str], float]:
    """An argparse type: a finite number above 0, `unit` naming it in the error
    ("'0' is not a positive number of seconds")."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise argparse.ArgumentTypeError(f"{text!r} is not a positive number {unit}")
        return value

    return parse


def port_number(text: str) -> int:
    """An argparse type: a TCP port, 0 (any free one) to `MAX_PORT`."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_PORT:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port (0 to {MAX_PORT})")
    return value
