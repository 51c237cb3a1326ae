"""The network's fast path: time per 1080p frame for each inference variant, its deviation, FLOPs.

    python -m isosr_bench.bench_network --device cuda
    python -m isosr_bench.bench_network --device cpu --smoke

Variants, each adding to the one before: fp32; bf16 autocast; + channels-last; + torch.compile
of the network (static shapes; the warp stays eager); + CUDA graphs (compile's
"reduce-overhead"); + cuDNN autotuning; + fast layers (`isosr_net.fastpath`: channels padded to
multiples of 8, subpixel upsampling); fp16 in place of bf16; and compile's "max-autotune",
which also times Triton kernel templates. cuDNN autotuning is process-wide, so every variant
after the first that asks for it runs with it. Each runs the recurrent step of `Upscaler`
(flow upscaling, warping, network) on a rendered low-res sequence; its deviation is the
largest difference from the fp32 output over the sequence. The FLOP count (torch's FlopCounterMode) over a measured
bf16 matrix-multiply rate gives the floor the card could reach.
"""

from __future__ import annotations

import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from isosr_render import Renderer, open_volume, orbit_path, resolve_iso
from isosr_render.sequence import sequence_requests
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_net.inference import surface_tensors

from .common import bench_parser, mean_ms, print_table, time_frames, write_result

VOLUME = "proc:cloud:42@128"


def variants(device: str) -> dict[str, dict]:
    """Upscaler options per variant. On CPUs only fp32 ones: bf16 ran 70x slower than fp32 on
    our 2-core CI machine, and compiling takes minutes there."""
    if not device.startswith("cuda"):
        return {"fp32": {}, "fp32 + channels-last": {"channels_last": True}}
    out = {"fp32": {}, "bf16": {"precision": "bf16"},
           "bf16 + channels-last": {"precision": "bf16", "channels_last": True}}
    out["bf16 + channels-last + compile"] = {"precision": "bf16", "channels_last": True, "compile": "default"}
    graphs = {"precision": "bf16", "channels_last": True, "compile": "reduce-overhead"}
    out["bf16 + channels-last + compile + CUDA graphs"] = graphs
    out["... + cuDNN autotune"] = {**graphs, "autotune": True}
    out["... + cuDNN autotune + fast layers"] = {**graphs, "autotune": True, "fast_layers": True}
    out["fp16 + channels-last + compile + CUDA graphs + cuDNN autotune + fast layers"] = {
        **graphs, "precision": "fp16", "autotune": True, "fast_layers": True}
    out["bf16 ... fast layers, compile max-autotune (Triton templates, CUDA graphs)"] = {
        **graphs, "compile": "max-autotune", "autotune": True, "fast_layers": True}
    return out


def lowres_sequence(width: int, height: int, frames: int, device: str) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Network inputs ``(lowres, flow)`` of a rendered orbit (flow None on the first frame)."""
    volume = open_volume(VOLUME)
    renderer = Renderer(volume, device)
    cameras = orbit_path(frames, yaw_step=2.0, distance=1.4)
    out = []
    for camera, request in sequence_requests(cameras, width, height, resolve_iso(VOLUME, volume),
                                             ("mask", "normal", "depth", "flow")):
        lowres, flow = surface_tensors(renderer.render(camera, request))
        out.append((lowres.to(device), None if flow is None else flow.to(device)))
    return out


def matmul_tflops(device: str, smoke: bool) -> float:
    """Measured matrix-multiply rate (TFLOP/s; bf16 on GPUs, fp32 on CPUs), the floor's yardstick."""
    cuda = device.startswith("cuda")
    n = 8192 if cuda and not smoke else 1024
    a = torch.randn(n, n, device=device, dtype=torch.bfloat16 if cuda else torch.float32)
    t = time_frames(lambda i: a @ a, 5 if smoke else 20, device)
    return 2 * n ** 3 / (mean_ms(t) * 1e-3) / 1e12


def copy_bandwidth(device: str, smoke: bool) -> float:
    """Measured memory bandwidth (bytes/s: read plus written by a large device copy), the memory floor's yardstick."""
    n = 2 ** 28 if device.startswith("cuda") and not smoke else 2 ** 22  # bytes
    a = torch.empty(n, dtype=torch.uint8, device=device)
    b = torch.empty_like(a)
    t = time_frames(lambda i: b.copy_(a), 5 if smoke else 20, device)
    return 2 * n / (mean_ms(t) * 1e-3)


def frame_flops(upscaler: Upscaler, lowres: torch.Tensor) -> int:
    """FLOPs of one network forward on this frame size (convolutions and matmuls, as torch counts)."""
    warped = upscaler.net.first_previous(lowres)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        upscaler.net(lowres, warped)
    return counter.get_total_flops()


def main(argv=None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--model", default=str(DEFAULT_MODEL))
    args = parser.parse_args(argv)
    width, height = (96, 54) if args.smoke else (480, 270)
    frames = 4 if args.smoke else 12
    sequence = lowres_sequence(width, height, frames, args.device)
    reference = None
    rows = []
    flops = None
    rate = matmul_tflops(args.device, args.smoke)
    for name, options in variants(args.device).items():
        upscaler = Upscaler(args.model, args.device, **options)
        flops = flops or frame_flops(upscaler, sequence[0][0])
        start = time.perf_counter()
        outputs = [upscaler.step(*inputs) for inputs in sequence]  # first pass: compiles where asked
        warmup_s = time.perf_counter() - start
        reference = reference or outputs
        deviation = max(float((o - r).abs().max()) for o, r in zip(outputs, reference))
        upscaler.reset()
        upscaler.step(*sequence[0])
        t = time_frames(lambda i: upscaler.step(*sequence[1 + i % (frames - 1)]), frames - 1, args.device, warmup=0)
        ms = mean_ms(t)
        rows.append({"variant": name, "size": f"{width}x{height} -> {width * 4}x{height * 4}", "ms": ms, **t,
                     "max |diff| vs fp32": deviation, "first pass s": warmup_s,
                     "GFLOP/frame": flops / 1e9, "floor ms": flops / (rate * 1e12) * 1e3,
                     "matmul TFLOP/s": rate})
    print_table(rows, ["variant", "size", "ms", "wall_ms", "max |diff| vs fp32", "first pass s", "GFLOP/frame",
                       "floor ms"])
    print(f"wrote {write_result('bench_network', args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
