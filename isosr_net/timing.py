"""Per-stage frame times without stalling the device.

    timer = StageTimer(device)
    with timer("render"):
        ...
    with timer("network"):
        ...
    timer.ms()        # {"render": 1.4, "network": 1.8}: reads the device once, at the end

On CUDA each stage is bracketed by CUDA events on the current stream, so a stage's time is the
device time between its first and last launch, and no stage waits for the one before it (the
host runs ahead; :meth:`StageTimer.ms` synchronizes once on the last event). On CPUs it is
wall time. A stage entered twice adds up.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from contextlib import contextmanager
from typing import TypeVar

import torch

T = TypeVar("T")


class StageTimer:
    """Milliseconds per named stage of one frame (see the module docstring); with ``share``, of work that
    ``share`` frames did together (one launch over a batch's views), each frame's share of it."""

    def __init__(self, device: torch.device | str, share: int = 1):
        self.cuda = torch.device(device).type == "cuda"
        self.share = share
        self._spans: list[tuple[str, object, object]] = []

    @contextmanager
    def __call__(self, stage: str):
        start = self._mark()
        yield
        self._spans.append((stage, start, self._mark()))

    def _mark(self):
        if self.cuda:
            event = torch.cuda.Event(enable_timing=True)
            event.record()
            return event
        return time.perf_counter()

    def ms(self) -> dict[str, float]:
        """Milliseconds per stage, in the order first entered (one device sync on CUDA)."""
        if self.cuda and self._spans:
            self._spans[-1][2].synchronize()
        out: dict[str, float] = {}
        for stage, start, end in self._spans:
            took = start.elapsed_time(end) if self.cuda else 1e3 * (end - start)
            out[stage] = out.get(stage, 0.0) + took / self.share
        return out


def timed_steps(steps: Generator[None, None, T], timer: StageTimer, stage: str) -> Generator[None, None, T]:
    """``steps`` (a generator of slices) with each of its own slices timed as ``stage``: the work
    a scheduler interleaves between the slices is not counted. Returns what ``steps`` returns."""
    while True:
        with timer(stage):
            try:
                next(steps)
            except StopIteration as done:
                return done.value
        yield
