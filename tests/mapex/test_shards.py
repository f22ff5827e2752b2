"""Shard arithmetic: every episode in exactly one shard, the same shards everywhere, balanced
in all and per method, and `K/N` parsed strictly."""

from __future__ import annotations

import itertools
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from mapex.shards import MAX_SHARDS, Shard, parse_shard, shard_indices, shard_items

ROOT = Path(__file__).resolve().parents[2]


def campaign(worlds: int, methods: int, starts: int, seeds: int = 1) -> list[tuple]:
    """(world, method, start, seed) in services.evaluate's canonical order: worlds outermost."""
    return [
        (f"w{w}", f"m{m}", s, seed)
        for w in range(worlds)
        for m, s, seed in itertools.product(range(methods), range(starts), range(seeds))
    ]


CAMPAIGNS = [campaign(1, 1, 1), campaign(1, 2, 2), campaign(2, 3, 4), campaign(6, 8, 1, 2)]


def method(episode: tuple) -> str:
    return episode[1]


@pytest.mark.parametrize("count", range(1, 8))
@pytest.mark.parametrize("episodes", CAMPAIGNS, ids=lambda e: f"{len(e)}-episodes")
def test_every_episode_is_in_exactly_one_shard_and_the_shards_are_balanced(episodes, count):
    shards = [shard_items(episodes, Shard(k, count), method) for k in range(count)]
    assert Counter(e for shard in shards for e in shard) == Counter(episodes)  # each once
    sizes = [len(shard) for shard in shards]
    assert max(sizes) - min(sizes) <= 1  # also with fewer episodes than shards: some empty
    for name in {method(e) for e in episodes}:  # every method spread over the shards
        per_shard = [sum(method(e) == name for e in shard) for shard in shards]
        assert max(per_shard) - min(per_shard) <= 1, (name, per_shard)
    for shard in shards:  # each shard keeps the canonical order
        assert shard == sorted(shard, key=episodes.index)


def test_a_method_per_shard_is_not_what_round_robin_over_the_methods_gives():
    # 8 methods, one start, 6 worlds, 8 shards: dealing the canonical order as it is would
    # give shard k method k on every world (the slow methods all in one shard)
    episodes = campaign(6, 8, 1)
    shard = shard_items(episodes, Shard(0, 8), method)
    assert len({method(e) for e in shard}) == 6


def test_the_shards_depend_only_on_the_order_and_the_groups():
    episodes = campaign(2, 3, 4)
    first = shard_indices([method(e) for e in episodes], Shard(1, 3))
    assert first == shard_indices([method(e) for e in episodes], Shard(1, 3))
    renamed = [f"other-{method(e)}" for e in episodes]  # other names, same grouping
    assert shard_indices(renamed, Shard(1, 3)) == first
    assert shard_indices([None] * 5, Shard(1, 2)) == [1, 3]  # no groups: plain round-robin


def test_the_shards_are_the_same_in_another_interpreter():
    # hash randomisation differs per process: the slices must not depend on it
    code = (
        "from mapex.shards import Shard, shard_indices; "
        "print(shard_indices([f'method{i % 5}' for i in range(40)], Shard(2, 7)))"
    )
    outputs = {
        subprocess.run(
            [sys.executable, "-c", code],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
            env={"PYTHONHASHSEED": seed, "PATH": ""},
            timeout=60,
        ).stdout
        for seed in ("1", "2", "3")
    }
    assert len(outputs) == 1
    expected = shard_indices([f"method{i % 5}" for i in range(40)], Shard(2, 7))
    assert outputs == {f"{expected}\n"}


@pytest.mark.parametrize(
    ("text", "shard"), [("0/1", Shard(0, 1)), ("2/3", Shard(2, 3)), ("07/10", Shard(7, 10))]
)
def test_good_shards_parse(text, shard):
    assert parse_shard(text) == shard


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("3/3", "K must be from 0 to N-1 = 2"),
        ("2/1", "K must be from 0 to N-1 = 0"),
        ("0/0", "N must be from 1 to"),
        ("-1/2", "must be K/N"),
        ("a/b", "must be K/N"),
        ("1", "must be K/N"),
        ("", "must be K/N"),
        (" 1/2", "must be K/N"),
        ("1/2/3", "must be K/N"),
        ("1.0/2", "must be K/N"),
        ("٣/٤", "must be K/N"),  # other scripts' digits
        (f"0/{MAX_SHARDS + 1}", f"N must be from 1 to {MAX_SHARDS:,}"),
        ("1/" + "9" * 5000, f"at most {MAX_SHARDS:,} shards"),
    ],
)
def test_bad_shards_are_one_line_value_errors(text, message):
    with pytest.raises(ValueError, match="--shard") as raised:
        parse_shard(text)
    assert message in str(raised.value) and "\n" not in str(raised.value)
