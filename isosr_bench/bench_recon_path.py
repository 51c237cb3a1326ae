"""Where a reconstructed frame's time goes: the reconstruction path, stage by stage.

    python -m isosr_bench.bench_recon_path --device cuda --volumes ct_pitch,bonsai1024 --sizes 1080p,4k
    python -m isosr_bench.bench_recon_path --device cpu --smoke

Per volume, size and sampling (AO rays, rays per pixel), over the Pareto benchmark's orbit
(:func:`isosr_bench.bench_pareto.bench_cameras`), each stage alone, synchronized around it:

- ``render``: the ray cast of the buffers the reconstruction reads (mask, normal, depth, AO, flow);
- ``inputs``: those buffers laid out as the network's inputs (:func:`recon_inputs`), checks queued;
- ``step``: the recurrent step as `Reconstructor` runs it (warp, network, the checks read);
- ``shade``: the output as buffers (:func:`highres_frame`), then shading;
- ``stages``: their sum; ``path``: the whole frame as :class:`FrameRunner` makes it, one
  synchronization at its end, as the Pareto benchmark times it;
- ``full``: the full-resolution frame with the same rays and no network, the frame the
  reconstruction adds to, so ``path - full`` is what reconstructing costs.

The network's convolutions in GFLOP per frame (:func:`isosr_net.reconnet.macs_per_pixel`) and the
floor they imply at a matrix-multiply rate measured in the same run (fp16 on GPUs) go beside it.
"""

from __future__ import annotations

import torch

from isosr_render import Renderer
from isosr_render.sequence import sequence_cameras
from isosr_render.shading import shade
from isosr_net.frame_methods import FrameMethod, FrameRunner
from isosr_net.reconnet import macs_per_pixel
from isosr_net.reconstructor import recon_inputs
from isosr_net.upscaler import InputChecks, highres_frame

from .bench_pareto import FRAMES, SIZES, SMOKE_FRAMES, SMOKE_SIZES, WARMUP, bench_cameras, load
from .common import bench_parser, commit, print_table, time_frames, write_result

NAME = "bench_recon_path"
SAMPLINGS = ((1, 1), (2, 1), (1, 4))  # (AO rays, rays per pixel)
SMOKE_VOLUMES = ("sphere",)


def matmul_tflops(device: str, smoke: bool) -> float:
    """Measured matrix-multiply rate in TFLOP/s (fp16 on GPUs, as the path runs; fp32 on CPUs)."""
    cuda = device.startswith("cuda")
    n = 8192 if cuda and not smoke else 512
    a = torch.randn(n, n, device=device, dtype=torch.float16 if cuda else torch.float32)
    t = time_frames(lambda i: a @ a, 3 if smoke else 20, device)
    return 2 * n ** 3 / (t.get("gpu_ms", t["wall_ms"]) * 1e-3) / 1e12


def stage_rows(renderer: Renderer, iso: float, volume: str, size: tuple[int, int], size_name: str, ao_rays: int,
               spp: int, frames: int, warmup: int, device: str, upscalers: dict, tflops: float) -> dict:
    """One row: every stage's mean time on one volume, size and sampling."""
    ms = lambda t: t.get("gpu_ms", t["wall_ms"])  # noqa: E731
    pairs = sequence_cameras(bench_cameras(frames))
    method = FrameMethod("reconstruct", ao_rays=ao_rays, spp=spp, precision="fp16" if device.startswith("cuda")
                         else "fp32")
    runner = FrameRunner(method, renderer, iso, *size, upscalers=upscalers)
    recon = runner.upscaler
    full = FrameRunner(FrameMethod("full", ao_rays=ao_rays, spp=spp), renderer, iso, *size)
    row = {"volume": volume, "size": size_name, "pixels": f"{size[0]}x{size[1]}", "ao_rays": ao_rays, "spp": spp,
           "method": method.name}
    row["full"] = ms(time_frames(lambda i: full.frame(*pairs[i]), frames, device, warmup=warmup))
    row["path"] = ms(time_frames(lambda i: runner.frame(*pairs[i]), frames, device, warmup=warmup))

    rendered = [None] * frames
    row["render"] = ms(time_frames(
        lambda i: rendered.__setitem__(i, renderer.render(pairs[i][0], runner.render_request(pairs[i][1]))),
        frames, device, warmup=0))
    staged = [None] * frames

    def inputs(i):
        checks = InputChecks()
        staged[i] = (*recon_inputs(rendered[i], ao_rays, spp, checks), checks)

    row["inputs"] = ms(time_frames(inputs, frames, device, warmup=0))
    outputs = [None] * frames
    recon.reset()
    row["step"] = ms(time_frames(lambda i: outputs.__setitem__(i, recon.step(*staged[i])), frames, device, warmup=0))
    row["shade"] = ms(time_frames(lambda i: (lambda high: shade(high.mask, high.normal, high.ao, runner.shading))(
        highres_frame(outputs[i])), frames, device, warmup=0))
    row["stages"] = row["render"] + row["inputs"] + row["step"] + row["shade"]
    row["added_ms"] = row["path"] - row["full"]
    row["network_gflop"] = 2 * macs_per_pixel(recon.net.config) * size[0] * size[1] / 1e9
    row["floor_ms"] = row["network_gflop"] / tflops
    row["matmul_tflops"] = tflops
    row["commit"] = commit()
    return row


def main(argv=None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--volumes", default="", help="comma-separated volume names (default: ct_pitch)")
    parser.add_argument("--sizes", default="", help=f"comma-separated sizes of {','.join(SIZES)} (default: all)")
    args = parser.parse_args(argv)
    sizes = SMOKE_SIZES if args.smoke else SIZES
    size_names = [s.strip().lower() for s in args.sizes.split(",") if s.strip()] or list(sizes)
    unknown = [s for s in size_names if s not in sizes]
    if unknown:
        parser.error(f"unknown sizes {unknown}; choose from {', '.join(sizes)}")
    names = [s.strip() for s in args.volumes.split(",") if s.strip()] or list(
        SMOKE_VOLUMES if args.smoke else ("ct_pitch",))
    if args.device.startswith("cuda"):
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
    tflops = matmul_tflops(args.device, args.smoke)
    frames, warmup = (SMOKE_FRAMES, 1) if args.smoke else (FRAMES, WARMUP)
    upscalers: dict = {}
    rows = []
    for name in names:
        volume, iso = load(name, args.device)
        renderer = Renderer(volume, args.device)
        for size_name in size_names:
            for ao_rays, spp in SAMPLINGS:
                rows.append(stage_rows(renderer, iso, name, sizes[size_name], size_name, ao_rays, spp, frames,
                                       warmup, args.device, upscalers, tflops))
    print_table(rows, ["volume", "size", "ao_rays", "spp", "full", "path", "added_ms", "render", "inputs", "step",
                       "shade", "stages", "network_gflop", "floor_ms"])
    print(f"wrote {write_result(NAME, args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
