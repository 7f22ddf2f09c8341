"""``qr-cl features --shard I/N``: one of N runs that split a scene's frames with no coordination.

Shard I (1-based) takes the frames whose position p in cameras.json's order has p % N == I - 1,
so N runs (a SLURM or Ray array job, several machines on a shared folder) write every frame
exactly once between them, each a fixed set known from I, N and the cameras alone. Round robin
rather than blocks: neighbouring frames look alike and cost alike, so the shards' loads even out.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Sequence, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class Shard:
    """Shard ``index`` (1-based) of ``count``."""

    index: int = 1
    count: int = 1

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"

    @property
    def whole(self) -> bool:
        """Whether this shard is the whole scene (1/1)."""
        return self.count == 1

    def holds(self, position: int) -> bool:
        """Whether the frame at ``position`` (0-based, cameras.json's order) is this shard's."""
        return position % self.count == self.index - 1

    def select(self, items: Sequence[T]) -> list[T]:
        """This shard's ``items`` (one per frame, cameras.json's order), in order."""
        return [item for position, item in enumerate(items) if self.holds(position)]


def shard_spec(text: str) -> Shard:
    """``I/N`` with integers 1 <= I <= N (argparse ``type=``: a one-line error otherwise)."""
    expected = f"expected I/N with integers 1 <= I <= N (e.g. 2/8), got {text!r}"
    index, slash, count = text.strip().partition("/")
    try:
        shard = Shard(int(index), int(count))
    except ValueError:
        raise argparse.ArgumentTypeError(expected) from None
    if not slash or not 1 <= shard.index <= shard.count:
        raise argparse.ArgumentTypeError(expected)
    return shard
