"""Tests for scripts/bisect_frame.py: a commit's packages staged beside the working tree's models,
timed in fresh interpreters round after round, summarized as medians and ratios to a base tree."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "bisect_frame.py"
spec = importlib.util.spec_from_file_location("bisect_frame", SCRIPT)
bisect_frame = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bisect_frame)


def head() -> str:
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=7", "HEAD"], check=True,
                          capture_output=True, text=True).stdout.strip()


def test_a_staged_commit_is_timed_in_rounds_on_the_cpu(tmp_path):
    stage = tmp_path / "stage"
    [tree] = bisect_frame.stage(["HEAD"], stage)
    assert tree.name == head()
    models = [p for p in (tree / "isosr_net").iterdir() if p.is_symlink()]
    assert models and all((p / "config.json").is_file() for p in models)  # the working tree's, linked
    out = tmp_path / "r.json"
    done = subprocess.run([sys.executable, str(SCRIPT), "run", "--stage-dir", str(stage), "--device", "cpu",
                           "--rounds", "2", "--frames", "2", "--cases", "cloud:smoke:x1", "--base", tree.name,
                           "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    record = json.loads(out.read_text())
    assert record["errors"] == {} and record["device"] == "cpu"
    assert [(r["tree"], r["round"], r["case"]) for r in record["rows"]] == [
        (tree.name, 0, "cloud:smoke:x1"), (tree.name, 1, "cloud:smoke:x1")]
    assert all(math.isfinite(r[m]) and r[m] > 0 for r in record["rows"] for m in ("pareto_ms", "back_to_back_ms"))
    [line] = record["summary"]
    assert line["rounds"] == 2 and not any(k.startswith("ratio_") for k in line)  # the base itself


def test_the_summary_takes_medians_over_rounds_and_ratios_to_the_base():
    rows = [{"tree": t, "round": r, "case": "c", "pareto_ms": v, "idle_ms": v / 4}
            for t, values in (("old", (2.0, 2.4, 2.2)), ("new", (1.0, 1.2, 5.0))) for r, v in enumerate(values)]
    old, new = bisect_frame.summary(rows, "old")
    assert old["median_pareto_ms"] == 2.2 and "ratio_pareto_ms" not in old
    assert new["median_pareto_ms"] == 1.2 and new["ratio_pareto_ms"] == pytest.approx(1.2 / 2.2, abs=1e-4)
    assert new["ratio_idle_ms"] == pytest.approx(0.3 / 0.55, abs=1e-4)


def test_no_tree_runs_first_in_every_round():
    trees = ["a", "b", "c"]
    orders = [bisect_frame.round_order(trees, r) for r in range(4)]
    assert orders == [trees, trees[::-1], trees, trees[::-1]]


def test_an_unknown_base_or_no_rounds_is_refused(tmp_path):
    (tmp_path / "stage").mkdir()
    with pytest.raises(SystemExit, match="--base abc: not a staged tree"):
        bisect_frame.run(tmp_path / "r.json", "abc", 1, 1, "cloud:smoke:x1", "cpu", tmp_path / "stage")
    with pytest.raises(SystemExit):
        bisect_frame.main(["run", "--rounds", "0"])
