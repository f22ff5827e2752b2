"""What every service process does alike: answer queries on threads, stop on signals, log.

A service declares one queryable per key, answers its queries in arrival order on a
thread of its own (inside `with query:` so the querier stops waiting as soon as the
reply is sent), waits for SIGINT/SIGTERM and then undeclares and drains. Each answer is told
how long its query waited in the queue, so a worker can drop one its querier gave up on.
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
from services.messages import ErrorReply, Message

Answer = Callable[[Payload | None, float], Message]
"""Turns a query's payload (None: none) into the reply, told how long (s) it waited queued."""
SUPERVISOR_PID_ENV = "MAPEX_SUPERVISOR_PID"  # set by services.supervisor for its children
RUN_TOKEN_ENV = "MAPEX_RUN_TOKEN"  # a run's secret: services.up sets it for its world and planners
STOP_POLL_S = 0.5  # how often the main thread looks up from waiting (signals run meanwhile)

log = logging.getLogger("services.serving")


class QueryServers:
    """One queryable and one answering thread per key, until `close`.

    Zenoh's threads only stamp each query with its arrival time and queue it; the key's
    thread answers the queue in arrival order.
    """

    def __init__(self, session: zenoh.Session, answers: dict[str, Answer]) -> None:
        self._queues: dict[str, queue.SimpleQueue] = {key: queue.SimpleQueue() for key in answers}
        self.queryables = [
            session.declare_queryable(key, self._enqueue(self._queues[key])) for key in answers
        ]
        self.threads = [
            threading.Thread(
                target=answer_queries,
                args=(self._queues[key], key, answer),
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


def answer_queries(waiting: queue.SimpleQueue, key: str, answer: Answer) -> None:
    """Answer queued (arrival time, query) pairs in order until a None arrives."""
    while (item := waiting.get()) is not None:
        arrived, query = item
        with query:  # leaving the block finalises the query: the querier stops waiting
            payload = None if query.payload is None else query.payload.to_bytes()
            reply = answer(payload, time.monotonic() - arrived)
            try:
                if isinstance(reply, ErrorReply):
                    query.reply_err(reply.encode())
                else:
                    query.reply(key, reply.encode())
            except zenoh.ZError as error:  # e.g. the querier left; the next query is unaffected
                log.warning("could not send a reply: %s", " ".join(str(error).split()))


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM (a clean stop instead of a KeyboardInterrupt)."""
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    return stop


def wait_for(stop: threading.Event) -> None:
    """Block until `stop` is set, waking regularly so signal handlers can run; also stop
    when the supervisor that started this process is gone (killed with SIGKILL)."""
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
