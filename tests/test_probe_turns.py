"""Replicas sharing a GPU take turns at probe work: the lock's semantics, and the engine's probe units in turn."""

from __future__ import annotations

import asyncio

import pytest

from isosr_server.probe_turns import ProbeTurns
from server_fixtures import server_settings


def test_a_turn_is_one_holders_at_a_time_and_a_long_wait_runs_the_unit_anyway(tmp_path):
    """Two openers of one lock file (two replicas): while one holds its turn the other's waits, and has it once it
    is given back; past its wait it runs without (counted), and holds nothing it must give back."""
    path = tmp_path / "gpu.lock"
    mine, theirs = ProbeTurns(path), ProbeTurns(path, wait_s=0.05)
    order = []

    async def hold_then_give():
        async with mine.turn() as had:
            assert had
            order.append("held")
            await asyncio.sleep(0.02)
            order.append("given back")

    async def wait_for_turn():
        await asyncio.sleep(0)  # mine first
        async with ProbeTurns(path, wait_s=5.0).turn() as had:
            order.append(f"had {had}")

    async def both():
        await asyncio.gather(hold_then_give(), wait_for_turn())

    asyncio.run(both())
    assert order == ["held", "given back", "had True"]

    async def waited_out():
        async with mine.turn():
            async with theirs.turn() as had:
                assert not had
        async with theirs.turn() as had:
            assert had, "a waited-out unit gave back nothing it did not have; the turn is free again"

    asyncio.run(waited_out())
    assert theirs.waited_out == 1 and mine.waited_out == 0
    with pytest.raises(ValueError, match="wait_s must be >= 0"):
        ProbeTurns(path, wait_s=-1.0)


def test_the_engines_probe_units_run_in_its_turn(tmp_path):
    """An engine with turns (a replica on a shared GPU) runs no unit of a probe while another replica holds the
    turn: each unit once it is given back."""
    from isosr_server.engine import Engine

    engine, order = Engine(server_settings()), []
    engine._turns = ProbeTurns(tmp_path / "gpu.lock")
    other = ProbeTurns(tmp_path / "gpu.lock")

    def probe(name: str):
        for unit in range(2):
            yield
            order.append(f"{name} {unit}")

    async def replica_holds_for_a_while():
        async with other.turn():
            await asyncio.sleep(0.05)
            order.append("given back")

    async def run():
        held = asyncio.create_task(replica_holds_for_a_while())
        await asyncio.sleep(0.01)
        await asyncio.gather(engine._run_probe(probe("a")), engine._run_probe(probe("b")))
        await held

    try:
        asyncio.run(run())
    finally:
        engine.shutdown()
    assert order[0] == "given back" and sorted(order[1:]) == ["a 0", "a 1", "b 0", "b 1"]
