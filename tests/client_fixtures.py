"""`isosr serve` in a subprocess on a free loopback port, for the client tests: a separate
process, as a real server is, so its memory (RSS) is its own and clients and server do not
share one interpreter's GIL."""

from __future__ import annotations

from contextlib import contextmanager

import pytest

from isosr_bench.bench_server import ServerProcess


@contextmanager
def serve(*args: str):
    """Yield a started `ServerProcess` (CPU, procedural volumes); stop it after."""
    with ServerProcess("cpu", extra_args=args) as server:
        yield server


@pytest.fixture(scope="module")
def server():
    with serve("--max-sessions-per-client", "16") as s:  # the load test's 16 sessions come from one address
        yield s
