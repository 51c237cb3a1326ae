"""The series playback benchmark in its smoke mode: a complete record, finite numbers, and what the
played frames score; its options refused before any work."""

from __future__ import annotations

import json
import math

import pytest

from isosr_bench import bench_series

TIMES = ("steps_per_s", "ms_per_step", "wait_ms", "upload_ms", "frame_ms", "read_ms")
SCORES = ("color_psnr", "flicker", "flicker_reference", "flicker_ratio")


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    rows = bench_series.main(["--device", "cpu", "--smoke", "--out", str(out)])
    record = json.loads((out / "bench_series_cpu.json").read_text())
    assert record["rows"] == rows
    return record


def test_the_record_says_where_how_and_what(record):
    assert record["benchmark"] == "bench_series"
    assert record["device"] and record["commit"] and record["command"] and record["date"]
    rows = record["rows"]
    assert [(r["case"], r["kind"]) for r in rows] == [(case, kind) for case in bench_series.SMOKE_CASES
                                                     for kind in ("reconstruct", "full")]
    for r in rows:
        assert r["ao_rays"] == 1 and r["pixels"] == "64x48" and r["goal_steps_per_s"] is None
        assert r["steps"] == bench_series.SMOKE_STEPS and r["timed_steps"] == r["steps"] - bench_series.SMOKE_WARMUP


def test_the_numbers_are_finite_and_add_up(record):
    for r in record["rows"]:
        values = [r[k] for k in TIMES + SCORES]
        assert all(isinstance(v, float) and math.isfinite(v) for v in values), r
        assert r["steps_per_s"] > 0 and r["frame_ms"] > 0 and r["upload_ms"] > 0 and r["read_ms"] > 0
        assert r["wait_ms"] >= 0
        assert r["ms_per_step"] == pytest.approx(r["wait_ms"] + r["upload_ms"] + r["frame_ms"])
        assert r["steps_per_s"] == pytest.approx(1e3 / r["ms_per_step"])
        assert r["flicker"] > 0 and r["flicker_reference"] > 0  # the ball moves and grows
        assert r["flicker_ratio"] == pytest.approx(r["flicker"] / r["flicker_reference"])


def test_reconstruction_scores_above_its_raw_rays(record):
    """The same AO ray per hit, reconstructed or shaded as it is: closer to the references, steadier."""
    for case in bench_series.SMOKE_CASES:
        recon, raw = (next(r for r in record["rows"] if r["case"] == case and r["kind"] == kind)
                      for kind in ("reconstruct", "full"))
        assert recon["color_psnr"] > raw["color_psnr"] + 1.0
        assert recon["flicker_ratio"] < raw["flicker_ratio"]


@pytest.mark.parametrize("argv, words", [
    (["--cases", "24f32,bogus"], "--cases: unknown bogus; choose from 24f32, 32u16"),
    (["--steps", "2"], "--steps: at least 3"),
    (["--methods", "buffers"], "--methods: x2 buffers make no color to score"),
])
def test_bad_options_are_refused_naming_them(argv, words, capsys, tmp_path):
    with pytest.raises(SystemExit):
        bench_series.main(["--device", "cpu", "--smoke", "--out", str(tmp_path), *argv])
    assert words in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
