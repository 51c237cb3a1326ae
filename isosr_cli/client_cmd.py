"""`isosr client`: a view session on `isosr serve` along an orbit, frames written as PNG.

Prints frames/s, latency p50/p99 and bytes per frame, next to what ``full`` mode sent for the
same frames (measured: a second session replays the path in ``full`` mode with the same size,
AO, encoding and quality). In ``buffers`` mode the frames are upscaled and shaded here, on
``--device``, with the same network and shading as the server.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from isosr_render.shapes import frame_size
from isosr_server.core.config import TOKEN_ENV
from isosr_server.protocol import ENCODINGS, INTERPOLATIONS


def add_parser(subparsers) -> None:
    """Register ``client``."""
    p = subparsers.add_parser("client", help="view a volume on an isosr server, write the frames, report costs",
                              description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("url", help="the server, http(s)://HOST:PORT")
    p.add_argument("--volume", required=True, help="a name from GET /v1/volumes, or proc:cloud:0 and the like")
    p.add_argument("--mode", default="auto",
                   help="the view mode (auto: the server chooses the method; GET /v1/modes lists the server's)")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--orbit", default="30,20,1.8,2", help="YAW,PITCH,DIST[,YAWSTEP], degrees and world units")
    p.add_argument("--size", type=frame_size, default="640x480", help="output WxH")
    p.add_argument("--focus", help="focus mode's circle CX,CY,R in output pixels (default: centered, radius H/4)")
    p.add_argument("--iso", type=float, help="iso-value in data units (default: the volume's suggested one)")
    p.add_argument("--ao-rays", type=int, default=0, help="AO rays per hit of full-resolution renders "
                                                          "(reconstruct mode: 0-8 with the shipped model)")
    p.add_argument("--interpolation", default="bilinear", choices=INTERPOLATIONS, help="upscale mode's interpolation")
    p.add_argument("--encoding", default="jpeg", choices=ENCODINGS)
    p.add_argument("--quality", type=int, default=85)
    p.add_argument("--out", type=Path, help="folder for frame_NNNN.png and summary.json (default: none written)")
    p.add_argument("--device", default="cpu", help="where buffers mode upscales: cpu, cuda, cuda:N")
    p.add_argument("--token", help=f"the server's token (default: ${TOKEN_ENV})")
    p.add_argument("--cafile", type=Path, help="PEM certificates to trust for an https server (e.g. its "
                                               "self-signed one; default: the system's)")
    p.add_argument("--no-compare", action="store_true", help="skip the full-mode replay")
    p.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for a frame")
    p.set_defaults(func=run)


def _focus(text: str | None, size: tuple[int, int]) -> tuple[float, float, float]:
    if text is None:
        return size[0] / 2, size[1] / 2, size[1] / 4
    try:
        cx, cy, r = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--focus must be CX,CY,R, got {text!r}") from None
    return cx, cy, r


def run(args: argparse.Namespace) -> int:
    from isosr_client.drive import Orbit, drive, summarize
    from isosr_client.view import connect
    from isosr_cli.images import write_png
    from isosr_render.atomic import atomic_write

    if args.frames < 1:
        raise ValueError(f"--frames must be at least 1, got {args.frames}")
    path, size = Orbit.parse(args.orbit), args.size
    if args.mode == "buffers":  # before a session is opened, not at its first frame
        from isosr_client.local import check_device

        check_device(args.device)
    token = args.token or os.environ.get(TOKEN_ENV) or None
    settings = {"ao_rays": args.ao_rays, "interpolation": args.interpolation, "encoding": args.encoding,
                "quality": args.quality, "refine": False}

    focus = _focus(args.focus, size)

    def session(mode: str):
        view = connect(args.url, args.volume, mode, size, token=token, settings=settings, iso=args.iso,
                       device=args.device, timeout=args.timeout, cafile=args.cafile)
        if mode == "focus":
            view.set_focus("circle", focus[:2], focus[2])
        return view

    def write(i: int, frame) -> None:
        write_png(args.out / f"frame_{i:04d}.png", frame.rgb())

    try:
        with session(args.mode) as view:
            stats, seconds = drive(view, path, args.frames, on_frame=write if args.out else None)
        summary = {"mode": args.mode, **summarize(stats, seconds)}
        rows = [summary]
        if not args.no_compare and args.mode != "full":
            with session("full") as view:
                full_stats, full_seconds = drive(view, path, args.frames)
            rows.append({"mode": "full", **summarize(full_stats, full_seconds)})
            summary["full_bytes_per_frame"] = rows[1]["bytes_per_frame"]
    except (ConnectionError, TimeoutError) as e:  # the command line reports RuntimeErrors in one line
        raise RuntimeError(str(e)) from None
    print(f"{args.volume} {size[0]}x{size[1]}, {len(stats)} frames, {args.encoding} q{args.quality}, "
          f"AO {args.ao_rays}")
    print(f"{'mode':<9}{'fps':>8}{'p50 ms':>10}{'p99 ms':>10}{'bytes/frame':>14}")
    for r in rows:
        print(f"{r['mode']:<9}{r['fps']:>8.1f}{r['latency_p50_ms']:>10.1f}{r['latency_p99_ms']:>10.1f}"
              f"{r['bytes_per_frame']:>14.0f}")
    if len(rows) == 2:
        print(f"{args.mode} sends {summary['bytes_per_frame'] / rows[1]['bytes_per_frame']:.2f}x the bytes of full")
    if args.out:
        record = {"volume": args.volume, "size": list(size), "orbit": vars(path), "settings": settings, "runs": rows}
        atomic_write(args.out / "summary.json", lambda f: f.write(json.dumps(record, indent=1).encode()))
        print(f"wrote {len(stats)} frames and summary.json to {args.out}")
    return 0
