"""Time two ways of making a frame and score each against a high-effort reference (isosr_net).

    python examples/time_methods.py                                     # full, AO 8 against reconstruct, AO 1
    python examples/time_methods.py --methods full:32,svgf:2 --size 640x360 --device cuda

Every way to make a frame is a :class:`~isosr_net.methods.FrameMethod` (a registered kind and
its knobs) run by the runner :func:`~isosr_net.methods.make_runner` makes; here each is run
along the same short orbit (a new sequence: recurrent networks and temporal filters start empty)
and prints its mean milliseconds per frame and the color PSNR of its frames against the
reference (4 rays per pixel, 512 AO rays: :func:`isosr_net.budget.reference_frames`).
"""

from __future__ import annotations

import argparse
import time

import torch

from isosr_net.budget import color_psnr, reference_frames
from isosr_net.methods import FrameMethod, make_runner
from isosr_render import Renderer, open_volume, orbit_path, resolve_iso
from isosr_render.sequence import sequence_cameras


def main(argv: list[str] | None = None) -> list[tuple[str, float, float]]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--volume", default="proc:cloud:0@32", help="a volume file or a proc:NAME[:SEED][@N] spec")
    parser.add_argument("--methods", default="full:8,reconstruct:1", help="two or more KIND:AO_RAYS, comma-separated")
    parser.add_argument("--size", default="96x64", help="WxH in pixels")
    parser.add_argument("--frames", type=int, default=4, help="frames of the orbit, each timed")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    args = parser.parse_args(argv)

    width, height = (int(v) for v in args.size.lower().split("x"))
    volume = open_volume(args.volume)
    renderer, iso = Renderer(volume, args.device), resolve_iso(args.volume, volume)
    cameras = orbit_path(args.frames, yaw0=30.0, yaw_step=3.0)
    references = reference_frames(renderer, iso, (width, height), cameras)

    # Wall clock per frame; on a GPU after waiting for the frame's work (the CPU's is done on return).
    sync = torch.cuda.synchronize if args.device.startswith("cuda") else (lambda: None)
    rows = []
    for spec in args.methods.split(","):
        kind, ao_rays = spec.split(":")
        method = FrameMethod.of(kind, ao_rays=int(ao_rays))
        runner = make_runner(method, renderer, iso, width, height)
        runner.frame(cameras[0])  # warm-up: kernels, network weights, buffers
        sync()
        ms, psnr = [], []
        for (camera, prev), reference in zip(sequence_cameras(cameras), references):
            start = time.perf_counter()
            result = runner.frame(camera, prev)
            sync()
            ms.append((time.perf_counter() - start) * 1e3)
            psnr.append(color_psnr(result.buffers, reference))
        rows.append((method.name, sum(ms) / len(ms), sum(psnr) / len(psnr)))

    print(f"{args.volume} {width}x{height}, {args.frames} frames on {args.device}")
    print(f"{'method':<40}{'ms/frame':>10}{'PSNR dB':>10}")
    for name, ms_mean, db in rows:
        print(f"{name:<40}{ms_mean:>10.2f}{db:>10.2f}")
    return rows


if __name__ == "__main__":
    main()
