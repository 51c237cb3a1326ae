"""Time series playback: steps per second through the series loader and the frame path, and the
quality of the played frames against per-step references.

    python -m isosr_bench.bench_series --device cuda --out benchmarks/results   # 256^3 float32, 512^3 uint16, 1080p
    python -m isosr_bench.bench_series --device cuda --cases 512u16 --steps 48
    python -m isosr_bench.bench_series --smoke                                  # small, CPU (the test suite)

The goals (issue 48; H100, 1080p, ``reconstruct`` at 1 AO ray): a 256^3 series plays at >= 30
steps/s, a 512^3 uint16 series at >= 10 (``goal_steps_per_s`` in the ``reconstruct`` rows).

Per case, a procedural series of ``--steps`` steps (a rippled ball that moves along x and grows) is
written as ``.npy`` files to a temporary folder and opened with :func:`isosr_render.series.open_series`
(its default memory bound), then played by each method as a view session plays it: per step the
step from the loader (:meth:`~isosr_render.series.VolumeSeries.step`, then ``prefetch`` of the next
ones on its thread), a :class:`~isosr_render.Renderer` of it (the upload, one per step as the
server's engine makes them) and one frame at a still camera through a
:class:`~isosr_net.methods.FrameStream` (each step a cut: nothing of one step in the next), with
the networks the service runs (:func:`isosr_server.engine.serving_network`: no CUDA graphs, which
would be captured anew for each step's renderer). The
first steps (compiling, capturing) are not timed; on CUDA each step ends in a synchronize. Rows,
per case and method:

- ``steps_per_s``: timed steps over their time; ``wait_ms``: the play thread's wait for a step (0
  where the prefetch had read it), ``upload_ms``: the renderer, ``frame_ms``: the frame (means per step);
- ``read_ms``: the loader's read of a step alone (file, min-max scan), timed before playing: the
  files were just written, so from the page cache;
- ``color_psnr``: the played frames' color PSNR on the covered region
  (:func:`isosr_net.budget.color_psnr`), mean over the timed steps, against references of each step
  (4 rays per pixel, 512 AO rays, :func:`isosr_net.budget.reference_frames`) from the same camera;
- ``flicker``, ``flicker_reference``: :func:`isosr_bench.bench_pareto.flicker` (the camera is still:
  the mean colour change from one step's frame to the next) of the played frames and of the
  references; ``flicker_ratio`` the first over the second (1: as steady as the references).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from isosr_bench.bench_pareto import finite, flicker
from isosr_bench.common import bench_parser, print_table, write_result
from isosr_net.budget import color_psnr, reference_frames
from isosr_net.inference import default_precision
from isosr_net.methods import FrameMethod, FrameStream, Networks, parse_method
from isosr_render import FrameBuffers, Renderer, orbit
from isosr_render.series import VolumeSeries, open_series
from isosr_server.engine import serving_network

NAME = "bench_series"
# name: (voxels a side, stored type)
CASES = {"256f32": (256, "float32"), "512u16": (512, "uint16")}
SMOKE_CASES = {"24f32": (24, "float32"), "32u16": (32, "uint16")}
GOALS = {"256f32": 30.0, "512u16": 10.0}  # steps/s of reconstruct at 1080p on an H100
SIZE, SMOKE_SIZE = (1920, 1080), (64, 48)
STEPS, SMOKE_STEPS = 24, 5
WARMUP, SMOKE_WARMUP = 3, 1  # untimed steps: a compiled network compiles, then captures, then replays
READS = 2  # steps read alone for read_ms
# The distance field's range stored by integer types ([lo, hi] over the type's range); the surface is at 0.
FIELD_RANGE = (-0.5, 1.0)
CAMERA = orbit(30.0, 20.0, 1.6)


def blob(n: int, t: int, steps: int, dtype: str, device: str) -> np.ndarray:
    """Step ``t`` of ``steps``: the signed distance (world units, box of side 1) to a rippled ball that
    moves along x from -0.15 to 0.15 while its radius grows from 0.2 to 0.28, indexed [x, y, z];
    integer types store it over :data:`FIELD_RANGE`."""
    s = t / max(steps - 1, 1)
    c = (torch.arange(n, device=device, dtype=torch.float32) + 0.5) / n - 0.5
    x, y, z = c[:, None, None], c[None, :, None], c[None, None, :]
    d = ((x - (-0.15 + 0.3 * s)) ** 2 + y ** 2 + z ** 2).sqrt() - (0.2 + 0.08 * s)
    d = d + 0.01 * torch.sin(40 * x) * torch.sin(40 * y) * torch.sin(40 * z)
    if dtype != "float32":
        lo, hi = FIELD_RANGE
        top = np.iinfo(dtype).max
        d = ((d.clamp(lo, hi) - lo) * (top / (hi - lo))).round().to(torch.int32)
    return d.cpu().numpy().astype(dtype)


def surface(dtype: str) -> float:
    """The stored value of the ball's surface (distance 0)."""
    if dtype == "float32":
        return 0.0
    lo, hi = FIELD_RANGE
    return float(round(-lo * np.iinfo(dtype).max / (hi - lo)))


def write_series(folder: Path, n: int, dtype: str, steps: int, device: str) -> None:
    """The case's steps as ``step_<t>.npy`` files."""
    for t in range(steps):
        np.save(folder / f"step_{t:03d}.npy", blob(n, t, steps, dtype, device))


def sync(device: str) -> None:
    """Wait for the device's queued work (CUDA; the CPU's is done on return)."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def read_ms(folder: Path) -> float:
    """Mean milliseconds of the loader's read of a step alone (no prefetch)."""
    series = open_series(folder)
    spent = []
    for i in range(READS):
        start = time.perf_counter()
        series.step(i)
        spent.append(1e3 * (time.perf_counter() - start))
    return sum(spent) / READS


def play(series: VolumeSeries, method: FrameMethod, size: tuple[int, int], iso: float, device: str,
         networks: Networks, warmup: int) -> tuple[dict, list[FrameBuffers]]:
    """Every step once at :data:`CAMERA`, as a view session plays it: the timed steps' mean times
    (module docstring) and frames."""
    stream, prev, times, frames = FrameStream(networks.fork()), None, {"wait": [], "upload": [], "frame": []}, []
    for t in range(series.count):
        marks = [time.perf_counter()]
        volume = series.step(t)
        series.prefetch(t)
        marks.append(time.perf_counter())
        renderer = Renderer(volume, device)
        sync(device)
        marks.append(time.perf_counter())
        result = stream.frame(method, renderer, volume.normalized_iso(iso), *size, CAMERA, prev)
        sync(device)
        marks.append(time.perf_counter())
        prev = CAMERA
        if t >= warmup:
            for name, a, b in zip(times, marks, marks[1:]):
                times[name].append(1e3 * (b - a))
            frames.append(FrameBuffers(mask=result.buffers.mask.clone(), color=result.buffers.color.clone()))
    ms = {f"{name}_ms": sum(v) / len(v) for name, v in times.items()}
    step_ms = sum(ms.values())
    return {**ms, "ms_per_step": step_ms, "steps_per_s": 1e3 / step_ms}, frames


def references(folder: Path, steps: range, size: tuple[int, int], iso: float, device: str) -> list[FrameBuffers]:
    """Each step's reference frame at :data:`CAMERA` (zero flow: the camera is still)."""
    series = open_series(folder)
    out = []
    for t in steps:
        volume = series.step(t)
        out += reference_frames(Renderer(volume, device), volume.normalized_iso(iso), size, [CAMERA], flow=True)
    return out


def case_rows(case: str, n: int, dtype: str, steps: int, methods: list[FrameMethod], size: tuple[int, int],
              device: str, warmup: int, networks: Networks, goal: float | None) -> list[dict]:
    """One row per method on one series (module docstring)."""
    iso = surface(dtype)
    with tempfile.TemporaryDirectory(prefix="isosr-series-") as tmp:
        folder = Path(tmp)
        write_series(folder, n, dtype, steps, device)
        base = {"case": case, "voxels": f"{n}^3", "dtype": dtype, "step_mb": n ** 3 * np.dtype(dtype).itemsize / 2**20,
                "steps": steps, "timed_steps": steps - warmup, "pixels": f"{size[0]}x{size[1]}",
                "read_ms": read_ms(folder)}
        played = []
        for method in methods:
            series = open_series(folder)
            try:
                played.append((method, *play(series, method, size, iso, device, networks, warmup)))
            finally:
                series.close()
            print(f"{case} {method.name}: {played[-1][1]['steps_per_s']:.1f} steps/s", flush=True)
        refs = references(folder, range(warmup, steps), size, iso, device)
    still = flicker(refs, refs)
    rows = []
    for method, timing, frames in played:
        psnr = torch.tensor([color_psnr(f, r) for f, r in zip(frames, refs)], dtype=torch.float64).nanmean().item()
        moving = flicker(frames, refs)
        rows.append({**base, "method": method.name, "kind": method.kind, "ao_rays": method.ao_rays, **timing,
                     "color_psnr": finite(psnr), "flicker": finite(moving), "flicker_reference": finite(still),
                     "flicker_ratio": finite(moving / still) if still > 0 else None,
                     "goal_steps_per_s": goal if method.kind == "reconstruct" else None})
    return rows


def main(argv: list[str] | None = None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--cases", default="", help=f"comma-separated cases of {', '.join(CASES)} (default: all)")
    parser.add_argument("--steps", type=int, help=f"steps per series (default: {STEPS}; smoke: {SMOKE_STEPS})")
    parser.add_argument("--methods", nargs="+", type=parse_method,
                        help="frame methods, NAME[:key=value,...] each (default: reconstruct and full at 1 AO ray)")
    args = parser.parse_args(argv)
    cases = SMOKE_CASES if args.smoke else CASES
    names = [c for c in args.cases.split(",") if c] or list(cases)
    if unknown := [c for c in names if c not in cases]:
        parser.error(f"--cases: unknown {', '.join(unknown)}; choose from {', '.join(cases)}")
    warmup = SMOKE_WARMUP if args.smoke else WARMUP
    steps = args.steps or (SMOKE_STEPS if args.smoke else STEPS)
    if steps < warmup + 2:
        parser.error(f"--steps: at least {warmup + 2} (the untimed first {warmup}, and two to compare)")
    if unshaded := [m.name for m in args.methods or () if not m.runner.shaded]:
        parser.error(f"--methods: {', '.join(unshaded)} make no color to score")
    methods = args.methods or [FrameMethod.of("reconstruct", ao_rays=1, precision=default_precision(args.device)),
                               FrameMethod.of("full", ao_rays=1)]
    size, networks, rows = SMOKE_SIZE if args.smoke else SIZE, Networks(serving_network), []
    for case in names:
        rows += case_rows(case, *cases[case], steps, methods, size, args.device, warmup, networks,
                          None if args.smoke else GOALS[case])
    print_table(rows, ["case", "method", "steps_per_s", "wait_ms", "upload_ms", "frame_ms", "read_ms", "color_psnr",
                       "flicker_ratio", "goal_steps_per_s"])
    print(f"wrote {write_result(NAME, args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
