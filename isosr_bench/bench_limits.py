"""The heaviest work the service's default limits allow: its time and peak memory.

    python -m isosr_bench.bench_limits --device cpu     # OUT/bench_limits_cpu.json (--out)
    python -m isosr_bench.bench_limits --smoke          # small sizes (CI)

Two requests, each as the server runs it (the engine's networks, frames in slices) in a fresh
process, one after the other: the largest view frame (``full`` at ``max_pixels``, 3840x2160,
with ``max_ao_rays`` AO rays per hit, cut into slices of the device's ``slice_ms``) and the
largest upscale (the network from 960x540 to 3840x2160; on CPUs in tiles). Per request: wall
time, slices, and the process's peak memory above what it held before (``ru_maxrss`` on CPUs,
``torch.cuda.max_memory_allocated`` on GPUs).
"""

from __future__ import annotations

import resource
import time

import torch

from isosr_bench.common import bench_parser, print_table, write_result
from isosr_net.methods import FrameMethod, Networks, make_runner
from isosr_net.inference import default_precision
from isosr_render.steps import count_steps
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_render import FrameBuffers, Renderer, RenderRequest, open_volume, orbit, resolve_iso
from isosr_server.engine import serving_network
from isosr_server.protocol import Limits

SLICE_MS = {"cpu": 100.0, "cuda": 8.0}


def peak_bytes(device: str) -> int:
    """The process's peak memory so far: device memory on GPUs, resident memory on CPUs."""
    if device.startswith("cuda"):
        return torch.cuda.max_memory_allocated(torch.device(device))
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def run(steps, device: str) -> dict:
    """Run a generator of slices to its end: wall seconds, slices, peak memory growth."""
    before, start = peak_bytes(device), time.perf_counter()
    yields, _ = count_steps(steps)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return {"seconds": time.perf_counter() - start, "slices": yields + 1,
            "peak_growth_mib": (peak_bytes(device) - before) / 2**20}


def main(argv: list[str] | None = None) -> list[dict]:
    args = bench_parser(__doc__).parse_args(argv)
    limits = Limits()
    size, ao_rays = ((64, 48), 8) if args.smoke else ((3840, 2160), limits.max_ao_rays)
    limits.check_size(*size)
    volume = open_volume("proc:cloud:0@32" if args.smoke else "proc:cloud:0@128")
    renderer, iso = Renderer(volume, args.device), resolve_iso("proc:cloud", volume)
    kind = "cuda" if args.device.startswith("cuda") else "cpu"
    view = make_runner(FrameMethod.of("full", ao_rays=ao_rays), renderer, iso, *size)
    rows = [{"request": f"view frame, full {size[0]}x{size[1]}, AO {ao_rays}", "slice_ms": SLICE_MS[kind],
             **run(view.steps(orbit(30, 20, 1.8), None, SLICE_MS[kind]), args.device)}]
    upscaler = Networks(serving_network).get(Upscaler, DEFAULT_MODEL, args.device, default_precision(args.device))
    low = (size[0] // upscaler.upscale_factor, size[1] // upscaler.upscale_factor)
    frame: FrameBuffers = renderer.render(orbit(30, 20, 1.8), RenderRequest(*low, iso))
    rows.append({"request": f"upscale {low[0]}x{low[1]} to {size[0]}x{size[1]}", "tile": upscaler.tile,
                 **run(upscaler.upscale_steps(frame), args.device)})
    print_table(rows, ["request", "seconds", "slices", "peak_growth_mib"])
    print(f"wrote {write_result('bench_limits', args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
