"""The last few answers of a predictor, by crop digest: the same crop asked twice is
computed once (a re-plan and G's metric prediction on one map, a team's planners asking
for one epoch's map, planners on several machines sharing a worker).

An answer being computed is shared too: a second caller (another thread) waits for the
first's result instead of starting the same forward pass."""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from concurrent.futures import Future

import numpy as np

RECENT_ANSWERS = 8  # distinct (crop, member) answers kept (float32, a few MB each)


def crop_digest(observed: np.ndarray) -> bytes:
    """A digest of a crop's shape and codes (equal crops, equal digests)."""
    digest = hashlib.blake2b(str(observed.shape).encode(), digest_size=16)
    digest.update(np.ascontiguousarray(observed).data)
    return digest.digest()


class RecentAnswers:
    """A small thread-safe cache of computed answers, least recently used first out."""

    def __init__(self, size: int = RECENT_ANSWERS) -> None:
        if size < 1:
            raise ValueError(f"size must be >= 1, not {size}")
        self.size = size
        self.hits = 0  # answers served from the cache (or from a computation under way)
        self._answers: OrderedDict[Hashable, Future] = OrderedDict()
        self._lock = threading.Lock()

    def get_or_compute(self, key: Hashable, compute: Callable[[], np.ndarray]) -> np.ndarray:
        """The answer for `key`: kept, being computed by another caller, or `compute()`d now.
        A failed computation is not kept (the next caller tries again)."""
        with self._lock:
            future = self._answers.get(key)
            if future is not None:
                self._answers.move_to_end(key)
                self.hits += 1
                owner = False
            else:
                future = self._answers[key] = Future()
                owner = True
                while len(self._answers) > self.size:
                    self._answers.popitem(last=False)
        if not owner:
            return future.result()
        try:
            answer = compute()
        except BaseException as error:
            with self._lock:
                if self._answers.get(key) is future:
                    del self._answers[key]
            future.set_exception(error)
            raise
        future.set_result(answer)
        return answer
