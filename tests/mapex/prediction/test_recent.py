"""The recent-answers cache: one computation per key, least recently used out, failures
not kept, and a second caller waits for a computation under way instead of repeating it."""

import threading

import numpy as np
import pytest

from mapex.prediction.recent import RecentAnswers, crop_digest


def test_a_key_is_computed_once_and_the_oldest_goes_first():
    cache, calls = RecentAnswers(size=2), []

    def compute(value):
        return lambda: calls.append(value) or np.full(3, value)

    for key in ("a", "b", "a", "c", "a", "b"):
        cache.get_or_compute(key, compute(key))
    # "b" went when "c" came ("a" had been used since), so it is computed again
    assert calls == ["a", "b", "c", "b"]
    assert cache.hits == 2


def test_a_failed_computation_is_not_kept():
    cache = RecentAnswers()

    def fail():
        raise RuntimeError("out of memory")

    with pytest.raises(RuntimeError, match="out of memory"):
        cache.get_or_compute("k", fail)
    assert cache.get_or_compute("k", lambda: np.ones(1))[0] == 1


def test_a_second_caller_waits_for_the_computation_under_way():
    cache, started, release, calls = RecentAnswers(), threading.Event(), threading.Event(), []

    def slow():
        calls.append(1)
        started.set()
        release.wait(5.0)
        return np.arange(4)

    results = []
    first = threading.Thread(target=lambda: results.append(cache.get_or_compute("k", slow)))
    first.start()
    assert started.wait(5.0)
    second = threading.Thread(target=lambda: results.append(cache.get_or_compute("k", slow)))
    second.start()
    release.set()
    first.join(5.0)
    second.join(5.0)
    assert len(calls) == 1 and len(results) == 2
    np.testing.assert_array_equal(results[0], results[1])


def test_digests_tell_crops_apart_by_codes_and_shape():
    crop = np.zeros((4, 6), dtype=np.uint8)
    assert crop_digest(crop) == crop_digest(crop.copy())
    assert crop_digest(crop) != crop_digest(crop.reshape(6, 4))
    changed = crop.copy()
    changed[2, 3] = 1
    assert crop_digest(crop) != crop_digest(changed)
    assert crop_digest(crop[:, ::2]) == crop_digest(np.ascontiguousarray(crop[:, ::2]))


def test_an_empty_cache_is_refused():
    with pytest.raises(ValueError, match="size"):
        RecentAnswers(size=0)
