"""The supervisor's watch over its predictor workers: restart the ones that are stuck.

A worker can keep its Zenoh session and liveliness token while it is stuck in one
prediction (a deadlock, a stuck GPU): nothing exits, so the supervisor would never notice.
`PoolWatch` probes each worker's health key every `health_check_every_s` (the worker
answers at once, on Zenoh's thread, with how long its current prediction has run) and
SIGKILLs, for the supervisor to restart, a worker that has been busy on one prediction for
`unresponsive_after_s`, or that answered probes before and has answered none for that long
(its whole process is frozen). A worker still starting (no probe answered yet) is left to
the supervisor's exit handling. A reply counts only if it names the worker probed. What a
worker says of itself can keep it from being killed, never from being benched: the planners
bench a worker on what they measure (services/ensemble_client.py).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence

import zenoh

from services.codec import DEFAULT_SERVICES, ProtocolError
from services.config import ServicesConfig
from services.keys import health_key
from services.messages import HealthReply
from services.pool import WorkerSpec
from services.supervisor import Supervisor

log = logging.getLogger("services.health")


class PoolWatch:
    """Probes the workers of `specs` (children of `supervisor`) and kills the stuck ones."""

    def __init__(
        self,
        session: zenoh.Session,
        supervisor: Supervisor,
        specs: Sequence[WorkerSpec],
        services: ServicesConfig = DEFAULT_SERVICES,
    ) -> None:
        self.session = session
        self.supervisor = supervisor
        self.specs = {spec.name: spec for spec in specs}
        self.services = services
        self._lock = threading.Lock()
        self._last_answer: dict[str, float] = {}  # name -> monotonic time of the last reply
        self._busy_s: dict[str, float] = {}  # name -> busy_s of the last reply
        self._pids: dict[str, int] = {}  # name -> pid the state above belongs to
        self._next_check = 0.0

    def check(self) -> list[str]:
        """Kill the workers found stuck (restarted by the supervisor's next `poll`) and
        send the due probes; the names killed."""
        now = time.monotonic()
        if now < self._next_check:
            return []
        self._next_check = now + self.services.health_check_every_s
        killed = []
        for name, spec in self.specs.items():
            if not self._running(name):
                continue
            self._forget_if_restarted(name)
            why = self._stuck(name, now)
            if why is not None:
                self.supervisor.kill(name, f"unresponsive: {why}")
                killed.append(name)
                continue
            self.session.get(
                health_key(spec.member, spec.worker_id),
                self._on_reply(name),
                timeout=self.services.health_probe_timeout_s,
            )
        return killed

    def _running(self, name: str) -> bool:
        try:
            return self.supervisor.is_running(name)
        except KeyError:  # not started (yet)
            return False

    def _stuck(self, name: str, now: float) -> str | None:
        limit = self.services.unresponsive_after_s
        with self._lock:
            last, busy_s = self._last_answer.get(name), self._busy_s.get(name, 0.0)
        if last is None:
            return None  # still starting: never answered a probe
        if busy_s >= limit:
            return f"busy on one prediction for {busy_s:.0f} s"
        if now - last >= limit:
            return f"no answer to health probes for {now - last:.0f} s"
        return None

    def _forget_if_restarted(self, name: str) -> None:
        pid = self.supervisor.process(name).pid
        with self._lock:
            if self._pids.get(name) != pid:
                self._pids[name] = pid
                self._last_answer.pop(name, None)
                self._busy_s.pop(name, None)

    def _on_reply(self, name: str):
        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            try:
                health = HealthReply.decode(reply.ok.payload.to_bytes(), self.services)
            except ProtocolError as error:
                log.warning("%s: ignored a health reply: %s", name, error)
                return
            spec = self.specs[name]
            if (health.member, health.worker_id) != (spec.member, spec.worker_id):
                log.warning("%s: ignored a health reply signed %s/%s", name,
                            health.member, health.worker_id)  # fmt: skip
                return
            with self._lock:
                self._last_answer[name] = time.monotonic()
                self._busy_s[name] = health.busy_s

        return on_reply
