"""`isosr demo`: the main job on the embedded default volume, side by side with the classic upscalers.

Renders a low-res sequence (mask, normal, depth, flow) and its ground truth (4x, with AO),
upscales the sequence with the shipped network and with nearest / bilinear / bicubic
interpolation, and writes per frame one image: nearest | bilinear | bicubic | network |
ground truth, each shaded and labelled with its color PSNR and time.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from isosr_render import Renderer, open_volume, orbit_path, resolve_iso
from isosr_render.atomic import atomic_write
from isosr_render.images import to_uint8
from isosr_render.shading import shade_channels_first
from isosr_cli.images import write_png

DEFAULT_VOLUME = "proc:cloud:42@96"  # a seed no training sequence used


def add_parser(subparsers) -> None:
    """Register ``demo``."""
    p = subparsers.add_parser("demo", help="render, upscale and compare on the embedded default volume",
                              description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--volume", default=DEFAULT_VOLUME, help="volume file, procedural spec or shared:NAME")
    p.add_argument("--iso", type=float, help="normalized iso (default: the volume's own)")
    p.add_argument("--frames", type=int, default=6)
    p.add_argument("--size", type=int, default=96, help="low-res side; ground truth is 4x")
    p.add_argument("--ao-samples", type=int, default=64, help="ground truth AO rays per hit")
    p.add_argument("--model", help="model folder (default: the shipped model)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default="demo_out")
    p.set_defaults(func=run)


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` (RGB uint8) with ``text`` written at its top left."""
    image = image.copy()
    cv2.putText(image, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return image


def _rgb(stack: torch.Tensor) -> np.ndarray:
    """The shaded color of a (1, 6, H, W) stack as an RGB uint8 image."""
    return to_uint8(shade_channels_first(stack.float().cpu())[0].permute(1, 2, 0))


def run(args: argparse.Namespace) -> int:
    from isosr_net.evaluate import COMPARED, compare_upscalers
    from isosr_net.upscaler import DEFAULT_MODEL, Upscaler

    volume = open_volume(args.volume)
    iso = resolve_iso(args.volume, volume, args.iso, normalized=True)
    upscaler = Upscaler(args.model or DEFAULT_MODEL, args.device)
    s = upscaler.upscale_factor
    cameras = orbit_path(args.frames, yaw0=30.0, yaw_step=2.0, pitch=20.0, distance=1.5)
    n = args.size
    times = {m: 0.0 for m in COMPARED + ("low-res render", "ground truth render")}
    psnr = {m: [] for m in COMPARED}
    out = Path(args.out)
    frames = compare_upscalers(Renderer(volume, args.device), cameras, iso, (n, n), upscaler, args.ao_samples)
    for t, frame in enumerate(frames):
        for stage, ms in frame.ms.items():
            times[stage] += ms
        panels = []
        for method in COMPARED:
            psnr[method].append(frame.color_psnr[method])
            panels.append(_label(_rgb(frame.outputs[method]), f"{method} {frame.color_psnr[method]:.1f} dB"))
        panels.append(_label(_rgb(frame.target), f"ground truth, AO {args.ao_samples}"))
        write_png(out / f"frame_{t:02d}.png", np.concatenate(panels, axis=1))
    summary = {"volume": volume.name, "frames": args.frames, "lowres": f"{n}x{n}", "highres": f"{n * s}x{n * s}",
               "device": args.device,
               "color_psnr_db": {m: float(np.mean(v)) for m, v in psnr.items()},
               "ms_per_frame": {m: v / args.frames for m, v in times.items()}}
    atomic_write(out / "summary.json", lambda f: f.write(json.dumps(summary, indent=1).encode()))
    print(f"{volume.name}, {args.frames} frames, {n}x{n} -> {n * s}x{n * s} on {args.device}")
    print("| method | color PSNR (dB) | ms per frame |\n|---|---|---|")
    for m in COMPARED:
        print(f"| {m} | {summary['color_psnr_db'][m]:.2f} | {summary['ms_per_frame'][m]:.1f} |")
    for m in ("low-res render", "ground truth render"):
        print(f"| {m} | | {summary['ms_per_frame'][m]:.1f} |")
    print(f"side-by-side frames (nearest | bilinear | bicubic | network | ground truth) in {out}/")
    return 0
