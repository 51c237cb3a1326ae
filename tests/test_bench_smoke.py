"""The renderer benchmark in its smoke mode, so that its code cannot rot."""

from __future__ import annotations

import json

from isosr_bench.bench_render import main


def test_bench_render_smoke_writes_a_complete_record(tmp_path, capsys):
    main(["--device", "cpu", "--smoke", "--out", str(tmp_path)])
    record = json.loads((tmp_path / "bench_render_cpu.json").read_text())
    assert record["device"] and record["commit"] and record["command"]
    cases = {r["case"] for r in record["rows"]}
    assert {"first hit", "first hit, no skipping", "low-res", "flow fill ns", "flow fill pushpull"} <= cases
    first = next(r for r in record["rows"] if r["case"] == "first hit")
    assert first["ms"] > 0 and first["skip speedup"] > 0 and 0 < first["coverage"] <= 1
    assert "| first hit |" in capsys.readouterr().out
