"""Open a view session on a running `isosr serve` and save a few frames along an orbit (isosr_client).

    isosr serve --device cpu &                                     # in another shell: the server
    python examples/view_remote.py --url http://127.0.0.1:8000     # -> example-out/view/frame_000N.png
    python examples/view_remote.py --url URL --mode buffers --device cuda   # upscaled here, on the GPU

The server renders each frame (``--mode``: ``full`` ray casts at full size; ``network`` upscales a
low-res render with its network; ``buffers`` sends the low-res buffers and this side upscales them
on ``--device``); each camera update is answered by a frame that includes it, which arrives as an
encoded image (or buffers) with its costs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2

from isosr_client import connect


def main(argv: list[str] | None = None) -> list[Path]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the server, http(s)://HOST:PORT")
    parser.add_argument("--volume", default="proc:cloud:0@32", help="a name from GET /v1/volumes, or proc:...")
    parser.add_argument("--mode", default="full", help="view mode: full, network, buffers, reconstruct, auto, ...")
    parser.add_argument("--size", default="128x96", help="WxH (a multiple of the upscale factor in low-res modes)")
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--device", default="cpu", help="where buffers mode upscales: cpu, cuda or cuda:N")
    parser.add_argument("--out", type=Path, default=Path("example-out/view"))
    args = parser.parse_args(argv)

    width, height = (int(v) for v in args.size.lower().split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    with connect(args.url, args.volume, args.mode, (width, height), device=args.device,
                 settings={"encoding": "png", "refine": False}) as view:
        for i in range(args.frames):
            view.set_camera(yaw=30.0 + 10.0 * i, pitch=20.0, distance=1.8)
            frame = view.latest()  # the newest frame that includes this camera
            path = args.out / f"frame_{i:04d}.png"
            cv2.imwrite(str(path), cv2.cvtColor(frame.rgb(), cv2.COLOR_RGB2BGR))
            written.append(path)
            s = frame.stats
            print(f"frame {i}: {s.method}, {s.latency_ms:.0f} ms, {s.nbytes} bytes -> {path}")
    return written


if __name__ == "__main__":
    main()
