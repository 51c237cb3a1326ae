"""A benchmark run without --out writes to the scratch folder, never over the committed results
(benchmarks/results): those change only with an explicit ``--out benchmarks/results``."""

from __future__ import annotations

from pathlib import Path

from isosr_bench.common import RESULTS_DIR, SCRATCH_DIR


def snapshot(folder: Path) -> dict[str, int]:
    """Every file name in ``folder`` with its modification time (ns)."""
    return {p.name: p.stat().st_mtime_ns for p in sorted(folder.iterdir())} if folder.is_dir() else {}


def test_a_smoke_benchmark_without_out_leaves_the_committed_results_alone(tmp_path, monkeypatch):
    # The cheapest smoke study: a few seconds on the CPU.
    from isosr_bench import bench_limits

    monkeypatch.chdir(tmp_path)  # the scratch default is relative to the working directory
    before = snapshot(RESULTS_DIR)
    rows = bench_limits.main(["--device", "cpu", "--smoke"])
    assert snapshot(RESULTS_DIR) == before
    assert rows and (tmp_path / SCRATCH_DIR / "bench_limits_cpu.json").is_file()


def test_isosr_bench_defaults_to_the_scratch_folder_and_says_so():
    from isosr_cli.main import build_parser

    parser = build_parser()
    assert parser.parse_args(["bench", "--smoke"]).out == SCRATCH_DIR
    assert parser.parse_args(["bench", "--out", "benchmarks/results"]).out == Path("benchmarks/results")
    assert not SCRATCH_DIR.is_absolute() and SCRATCH_DIR.resolve() != RESULTS_DIR.resolve()
    bench = parser._subparsers._group_actions[0].choices["bench"]
    assert f"./{SCRATCH_DIR}" in " ".join(bench.format_help().split())
