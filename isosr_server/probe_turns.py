"""Replicas that share a GPU take turns at the auto mode's probe work: one probe unit on the GPU at a time.

A probe times its candidates between its sessions' frames. On a GPU that several replicas share, another
replica's probe work (its references at 512 AO rays, its dearest candidates) ran beside those timed frames and
made them look dearer by whatever it ran: on an H200 under four replicas, one replica's probe timed the
reconstruction at 1 AO ray and 4 a pixel at 41.7 ms and at 2 AO rays at 5.2, and the replicas probe together at
start and after each change of load. With turns, a timed frame meets the other replicas' frames only, the load the
policy measures in service (:meth:`isosr_server.auto.AutoPolicy.served`).

The turn is an exclusive ``flock`` on a file named for the GPU in the temporary directory, taken for one unit and
given back after it (a process that dies gives it back with its files). A unit waits for it :data:`TURN_WAIT_S`
at most, then runs anyway: a probe is never held off for good.
"""

from __future__ import annotations

import asyncio
import fcntl
import logging
import os
import tempfile
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import torch

log = logging.getLogger("isosr.server")

# How long a probe unit waits for its turn at most, and how often it looks (seconds). A unit is mostly under
# 0.25 s (engine.SLOW_PROBE_UNIT_S); four replicas' units in turn fit well within the wait.
TURN_WAIT_S = 2.0
TURN_POLL_S = 0.005


class ProbeTurns:
    """Turns at probe work on one GPU among the processes that open the same ``path``.

    The lock file stays open for the process's life (one a server).

    Attributes:
        path: the lock file.
        waited_out: units that ran without their turn (another process kept it past :data:`TURN_WAIT_S`).
    """

    def __init__(self, path: Path, wait_s: float = TURN_WAIT_S):
        if not wait_s >= 0:
            raise ValueError(f"ProbeTurns: wait_s must be >= 0, got {wait_s!r}")
        self.path, self.wait_s, self.waited_out = Path(path), float(wait_s), 0
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        self._local = asyncio.Lock()  # this process's probes, in turn too (a flock is the process's, not a task's)

    @classmethod
    def for_gpu(cls, device: torch.device) -> ProbeTurns | None:
        """The turns of ``device``'s GPU (named by its UUID, the same in every process whatever devices each sees),
        or None where its lock file cannot be opened (said once: probes then run without turns)."""
        gpu = str(torch.cuda.get_device_properties(device).uuid)
        path = Path(tempfile.gettempdir()) / f"isosr-probe-turns-{gpu}.lock"
        try:
            return cls(path)
        except OSError as e:
            log.warning("auto probes run without turns among the GPU's replicas: %s cannot be opened (%s)", path, e)
            return None

    def _try(self) -> bool:
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            return False

    @asynccontextmanager
    async def turn(self) -> AsyncIterator[bool]:
        """This process's turn for one unit (event loop): whether it was had (False: waited out, the unit runs)."""
        async with self._local:
            end = time.monotonic() + self.wait_s
            while not (had := self._try()) and time.monotonic() < end:
                await asyncio.sleep(TURN_POLL_S)
            self.waited_out += not had
            try:
                yield had
            finally:
                if had:
                    fcntl.flock(self._fd, fcntl.LOCK_UN)
