"""What every benchmark shares: timing, the record of where and how it ran, the result file."""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import torch

from isosr_render.atomic import atomic_write

# The committed results live outside the package: benchmarks/results of the checkout (where an
# editable install or `python -m` from the repository runs), else of the working directory. The
# report reads them by default; a benchmark writes there only when told (`--out benchmarks/results`).
_CHECKOUT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ((_CHECKOUT if (_CHECKOUT / "pyproject.toml").is_file() else Path.cwd()) / "benchmarks" / "results")
# Where a benchmark writes without --out: a scratch folder of the working directory (relative, so
# resolved where the run starts; ignored by git at the repository's root), never the committed results.
SCRATCH_DIR = Path("bench-out")
# (%(default)s: argparse fills in the parser's default, SCRATCH_DIR.)
OUT_HELP = ("folder for the results (default: ./%(default)s, a scratch folder of the working directory; "
            "--out benchmarks/results updates the committed results)")


def bench_parser(doc: str) -> argparse.ArgumentParser:
    """The options every study takes: --device, --smoke, --out (default :data:`SCRATCH_DIR`)."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--smoke", action="store_true", help="small sizes on the CPU (CI)")
    parser.add_argument("--out", type=Path, default=SCRATCH_DIR, help=OUT_HELP)
    return parser


def device_name(device: str) -> str:
    """A human name for the device: the GPU's, or the CPU model and core count."""
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model} ({os.cpu_count()} cores)"


def commit() -> str:
    """``$ISOSR_COMMIT`` (set where the checkout travels without .git), else git's HEAD, with
    ``-dirty`` appended when the working tree has uncommitted changes."""
    if os.environ.get("ISOSR_COMMIT"):
        return os.environ["ISOSR_COMMIT"]
    try:
        return subprocess.run(["git", "describe", "--always", "--dirty", "--abbrev=7"], capture_output=True, text=True,
                              check=True, cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def time_frames(fn, frames: int, device: str, warmup: int = 2, keep=None) -> dict:
    """Mean wall and device time of ``fn(i)`` over ``frames`` calls, in milliseconds.

    On CUDA the device time comes from events around each call (what the GPU spent);
    wall time includes Python and launch overhead, synchronized after each call. ``keep(i,
    result)``, where given, gets what each timed call returned, after its timing (to copy what
    the next call may overwrite without timing the copy).
    """
    cuda = device.startswith("cuda")
    for i in range(warmup):
        fn(i)
    if cuda:
        torch.cuda.synchronize()
    wall, gpu = [], []
    for i in range(frames):
        start = time.perf_counter()
        if cuda:
            e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            e0.record()
        made = fn(i)
        if cuda:
            e1.record()
            torch.cuda.synchronize()
            gpu.append(e0.elapsed_time(e1))
        wall.append((time.perf_counter() - start) * 1e3)
        if keep is not None:
            keep(i, made)
    result = {"wall_ms": sum(wall) / frames, "wall_ms_min": min(wall)}
    if cuda:
        result.update(gpu_ms=sum(gpu) / frames, gpu_ms_min=min(gpu))
    return result


def mean_ms(times: dict) -> float:
    """The mean ms per call of a :func:`time_frames` result: the device's where CUDA events timed
    it, else the wall clock's."""
    return times.get("gpu_ms", times["wall_ms"])


def kernel_ms(fn, frames: int, kernels: tuple[str, ...]) -> float:
    """Mean CUDA time per call of ``fn(i)`` spent in Warp kernels whose name contains one of ``kernels``.

    This is the GPU's own time, without launch overhead or idle gaps between launches.
    """
    import warp as wp

    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    for i in range(frames):
        fn(i)
    results = wp.timing_end()
    return sum(r.elapsed for r in results if any(k in r.name for k in kernels)) / frames


def write_result(name: str, device: str, rows: list[dict], out_dir: Path = SCRATCH_DIR) -> Path:
    """Write ``OUT_DIR/NAME_<device kind>.json`` with device, commit and command."""
    out_dir.mkdir(parents=True, exist_ok=True)
    kind = "cuda" if device.startswith("cuda") else "cpu"
    path = out_dir / f"{name}_{kind}.json"
    record = {"benchmark": name, "device": device_name(device), "commit": commit(),
              "command": " ".join(sys.orig_argv),
              "torch": torch.__version__, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "rows": rows}
    atomic_write(path, lambda f: f.write(json.dumps(record, indent=1).encode()))
    return path


def kept_rows(path: Path, keep: Callable[[dict], bool], stamp: tuple[str, ...] = ("device",)) -> list[dict]:
    """The rows of the result file at ``path`` that ``keep`` accepts (none if there is no file),
    each given the file's ``stamp`` fields (those it has) where it has none of its own: the rows a later run of a
    study keeps beside those it measured."""
    if not path.is_file():
        return []
    record = json.loads(path.read_text())
    return [{**{key: record[key] for key in stamp if key in record}, **r} for r in record["rows"] if keep(r)]


def print_table(rows: list[dict], columns: list[str]) -> None:
    """A Markdown table of ``rows`` restricted to ``columns``."""
    def fmt(v):
        return f"{v:.3g}" if isinstance(v, float) else str(v)
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))
    for r in rows:
        print("| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |")
