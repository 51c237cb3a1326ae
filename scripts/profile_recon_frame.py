"""Where a reconstructed frame's time goes after the render: the GPU's kernels, grouped.

    python scripts/profile_recon_frame.py --device cuda --sizes 1080p,4k [--variant served]

`Reconstructor.fastest` (the network as fused Triton kernels, the frame's work after the render
in one CUDA graph: inputs laid out and checked, the network, the output buffers, shading) on a
synthetic frame (random surface, 1 AO ray, a flow), so no Warp is needed. Per size: the first
frame's wall ms (compiling and autotuning what the size's class has not had: the stall a viewer
of a new window size waits), the mean ms of ``reconstruct`` (graph replay, checks read, outputs
copied), and one frame under the torch profiler with its kernels' GPU time summed by name
(Triton kernels by their function name). ``--variant served``: the service's way (no graphs).
"""

from __future__ import annotations

import argparse
import json
import time

import torch
import torch.nn.functional as F
from torch.profiler import ProfilerActivity, profile

from isosr_render.buffers import FrameBuffers
from isosr_render.shading import ShadingParams
from isosr_net.inference import default_precision
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, Reconstructor

SIZES = {"1080p": (1080, 1920), "4k": (2160, 3840), "smoke": (64, 96)}
# fastest: Reconstructor.fastest (one CUDA graph a frame); served: as the service runs it
# (Reconstructor.served: on GPUs the fused kernels launched one by one, no graphs).
VARIANTS = {"fastest": lambda device: Reconstructor.fastest(device=device),
            "served": lambda device: Reconstructor.served(DEFAULT_RECON_MODEL, device, default_precision(device))}


def synthetic_frame(h: int, w: int, device: str, seed: int) -> FrameBuffers:
    """A frame as a render gives it: a mask with holes, unit normals and depths where covered, AO, flow."""
    gen = torch.Generator(device=device).manual_seed(seed)
    mask = (torch.rand(h, w, device=device, generator=gen) > 0.3).float()
    normal = F.normalize(torch.randn(h, w, 3, device=device, generator=gen), dim=-1) * mask[..., None]
    return FrameBuffers(mask=mask, normal=normal, depth=torch.rand(h, w, device=device, generator=gen) * mask,
                        ao=torch.rand(h, w, device=device, generator=gen).round(),
                        flow=torch.randn(h, w, 2, device=device, generator=gen))


def sync(device: str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def profile_size(recon: Reconstructor, h: int, w: int, device: str, frames: int) -> dict:
    """Wall ms of the first ``reconstruct`` of this size (compiling and tuning whatever this size
    class has not had yet), the mean over ``frames`` frames after warm-up, and one frame's kernels
    (GPU ms by name)."""
    frames_ = [synthetic_frame(h, w, device, seed) for seed in range(2)]
    shading = ShadingParams()
    sync(device)
    start = time.perf_counter()
    recon.reconstruct(frames_[0], 1, 1, shading)
    sync(device)
    first_ms = (time.perf_counter() - start) * 1e3
    for i in range(1, 4):  # a carried frame, then its captured graph
        recon.reconstruct(frames_[i % 2], 1, 1, shading)
    sync(device)
    start = time.perf_counter()
    for i in range(frames):
        recon.reconstruct(frames_[i % 2], 1, 1, shading)
    sync(device)
    wall_ms = (time.perf_counter() - start) / frames * 1e3
    with profile(activities=[ProfilerActivity.CUDA, ProfilerActivity.CPU]) as prof:
        recon.reconstruct(frames_[0], 1, 1, shading)
        sync(device)
    kernels: dict[str, float] = {}
    for event in prof.events():
        if event.device_type == torch.autograd.DeviceType.CUDA:
            kernels[event.name] = kernels.get(event.name, 0.0) + event.time_range.elapsed_us() / 1e3
    top = dict(sorted(kernels.items(), key=lambda kv: -kv[1]))
    return {"pixels": f"{w}x{h}", "first_frame_ms": first_ms, "reconstruct_wall_ms": wall_ms,
            "gpu_ms": sum(top.values()), "kernels_ms": top}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--sizes", default="1080p,4k")
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--variant", choices=VARIANTS, default="fastest")
    args = parser.parse_args()
    recon = VARIANTS[args.variant](args.device)
    out = {}
    for name in args.sizes.split(","):
        out[name] = profile_size(recon, *SIZES[name], args.device, args.frames)
        row = out[name]
        print(f"{name}: first frame {row['first_frame_ms']:.0f} ms, then reconstruct {row['reconstruct_wall_ms']:.3f} "
              f"ms (wall), kernels {row['gpu_ms']:.3f} ms")
        for kernel, ms in list(row["kernels_ms"].items())[:30]:
            print(f"  {ms:7.3f}  {kernel[:110]}")
    device = torch.cuda.get_device_name(args.device) if torch.device(args.device).type == "cuda" else "cpu"
    print(json.dumps({"device": device, "variant": args.variant, "rows": out}))


if __name__ == "__main__":
    main()
