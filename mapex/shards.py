"""Shards of an experiment: `--shard K/N` runs the K-th (0-based) of N slices of its episodes.

The slices depend only on the list of episodes in its canonical order (never on hashing,
the file system or the host), so every machine computes the same ones, and each episode is
in exactly one. The list is dealt round-robin after putting it group by group (the groups in
order of first appearance, each keeping its order): every shard gets as many episodes as any
other, plus or minus one, and so, of every group (a method) and every run of consecutive
items within it (a method's episodes on one world), as many as any other, plus or minus one.
Episodes of one method and world cost about the same, so the shards do too, whatever the
cost of each method. K is 0-based so that Slurm's `$SLURM_ARRAY_TASK_ID` and Kubernetes'
`$JOB_COMPLETION_INDEX` can be passed as they are.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import TypeVar

T = TypeVar("T")

# The most shards of one experiment: Kubernetes' limit on an Indexed Job's completions (and
# far above Slurm's default MaxArraySize of 1001); it also bounds the digits parsed.
MAX_SHARDS = 100_000
_DIGITS = len(str(MAX_SHARDS))
_SHARD = re.compile(rf"([0-9]{{1,{_DIGITS}}})/([0-9]{{1,{_DIGITS}}})")


@dataclass(frozen=True)
class Shard:
    """Shard `index` (0-based) of `count`."""

    index: int
    count: int

    def __post_init__(self) -> None:
        if not 1 <= self.count <= MAX_SHARDS:
            raise ValueError(f"--shard {self}: N must be from 1 to {MAX_SHARDS:,}")
        if not 0 <= self.index < self.count:
            raise ValueError(
                f"--shard {self}: K must be from 0 to N-1 = {self.count - 1} (K is 0-based)"
            )

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def parse_shard(text: str) -> Shard:
    """`K/N` (K from 0 to N-1) as a Shard; a one-line ValueError for anything else."""
    match = _SHARD.fullmatch(text)
    if match is None:
        raise ValueError(
            f"--shard must be K/N, shard K (0-based) of N, e.g. 0/4; got {text!r}"
            + (f" (at most {MAX_SHARDS:,} shards)" if re.fullmatch(r"[0-9]+/[0-9]+", text) else "")
        )
    return Shard(int(match[1]), int(match[2]))


def shard_indices(groups: Sequence[Hashable], shard: Shard) -> list[int]:
    """The positions of the items of `shard`, ascending, for items whose groups are
    `groups` (one per item, in the canonical order): see the module docstring."""
    rank: dict[Hashable, int] = {}
    for group in groups:
        rank.setdefault(group, len(rank))
    dealt = sorted(range(len(groups)), key=lambda i: rank[groups[i]])  # stable: keeps the order
    return sorted(dealt[shard.index :: shard.count])


def shard_items(
    items: Sequence[T], shard: Shard, group: Callable[[T], Hashable] = lambda _item: None
) -> list[T]:
    """The items of `shard`, in their canonical order (`group`: e.g. an episode's method)."""
    return [items[i] for i in shard_indices([group(item) for item in items], shard)]
