"""Publish frames so that late joiners get the latest one: a publisher and a queryable per key.

Every `put` of a `LatestPublisher` goes out on the key's Zenoh publisher and is remembered
as the key's latest payload; a queryable on exactly that key answers a `get` with it, so a
viewer started mid-run shows the current frame at once (docs/protocol.md). Queryables are
never declared on wildcards: they would catch other services' queries. A put is dropped at
a congested hop by default, which suits map frames (a newer one follows); a key in
`blocking_keys` waits for room instead, for small messages no later put replaces, such as a
run's final status.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Collection, Sequence

import zenoh

from services.messages import Message

log = logging.getLogger("services.latest")


class LatestPublisher:
    """One Zenoh publisher and one queryable (serving the latest payload) per key, until `close`.

    `put` may be called from several threads; queries are answered on Zenoh's threads from
    memory (a dictionary look-up, never blocking on the publishing side).
    """

    def __init__(
        self, session: zenoh.Session, keys: Sequence[str], blocking_keys: Collection[str] = ()
    ) -> None:
        self._keys = _checked_keys(keys)
        unknown = set(blocking_keys) - set(self._keys)
        if unknown:
            raise ValueError(f"blocking keys {sorted(unknown)} are not among the keys")
        self._latest: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._queryables: list[zenoh.Queryable] = []
        try:
            for key in self._keys:
                congestion = (
                    zenoh.CongestionControl.BLOCK
                    if key in blocking_keys
                    else zenoh.CongestionControl.DROP
                )
                self._publishers[key] = session.declare_publisher(
                    key, congestion_control=congestion
                )
                self._queryables.append(session.declare_queryable(key, self._answerer(key)))
        except BaseException:
            self.close()
            raise

    @property
    def keys(self) -> tuple[str, ...]:
        """The keys served, in declaration order."""
        return self._keys

    def put(self, key: str, message: Message) -> None:
        """Publish `message` on `key` and remember it as the latest for late joiners."""
        publisher = self._publishers.get(key)
        if publisher is None:
            raise KeyError(f"key {key!r} is not one of this publisher's keys (or it is closed)")
        payload = message.encode()
        with self._lock:
            self._latest[key] = payload
        publisher.put(payload)

    def latest(self, key: str) -> bytes | None:
        """The payload a `get` on `key` is answered with now (None before the first put)."""
        with self._lock:
            return self._latest.get(key)

    def close(self) -> None:
        """Undeclare every queryable and publisher (idempotent)."""
        queryables, self._queryables = self._queryables, []
        publishers, self._publishers = self._publishers, {}
        for entity in [*queryables, *publishers.values()]:
            try:
                entity.undeclare()
            except zenoh.ZError as error:  # e.g. the session was closed first
                log.debug("undeclare failed: %s", error)

    def __enter__(self) -> LatestPublisher:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _answerer(self, key: str):
        """The queryable callback of `key`: reply with its latest payload, if any."""

        def answer(query: zenoh.Query) -> None:
            with query:  # leaving the block finalises the query: the querier stops waiting
                payload = self.latest(key)
                if payload is None:
                    return
                try:
                    query.reply(key, payload)
                except zenoh.ZError as error:  # e.g. the querier left meanwhile
                    log.warning("could not answer a query on %s: %s", key, _one_line(error))

        return answer


def _checked_keys(keys: Sequence[str]) -> tuple[str, ...]:
    """The keys as a tuple; ValueError for none, duplicates, or wildcards."""
    if isinstance(keys, str):
        raise ValueError("keys must be a sequence of key strings, not one string")
    checked = tuple(keys)
    if not checked:
        raise ValueError("a LatestPublisher needs at least one key")
    if len(set(checked)) != len(checked):
        raise ValueError(f"duplicate keys in {list(checked)}")
    for key in checked:
        if not isinstance(key, str) or not key or "*" in key:
            raise ValueError(f"key {key!r} must be one exact key expression (no wildcard)")
    return checked


def _one_line(error: Exception) -> str:
    return " ".join(str(error).split())
