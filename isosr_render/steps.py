"""Generators of slices: work that yields between bounded steps (a frame in row bands, a mesh in
slabs, a probe's units), so a scheduler may run other work between them; run to their end here."""

from __future__ import annotations

from collections.abc import Generator
from typing import TypeVar

T = TypeVar("T")


def finish_steps(steps: Generator[None, None, T]) -> T:
    """Run a generator of slices (a runner's, a network's or a mesh's ``steps``) to the end; its result."""
    return count_steps(steps)[1]


def count_steps(steps: Generator[None, None, T]) -> tuple[int, T]:
    """Run a generator of slices to the end: ``(how many times it yielded, its result)``."""
    yields = 0
    while True:
        try:
            next(steps)
            yields += 1
        except StopIteration as done:
            return yields, done.value
