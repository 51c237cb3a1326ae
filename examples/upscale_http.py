"""Upscale a frame through the service's HTTP API (``POST /v1/upscale``).

    isosr serve --device cpu &                                     # in another shell: the server
    python examples/upscale_http.py --url http://127.0.0.1:8000    # -> example-out/upscaled.png

The service upscales a frame's low-res buffers, not its pixels: this side ray casts a small frame
(mask, normal, depth) on ``--device``, sends it, and the server's network answers with the
shaded image ``factor`` times as wide and as high (or with the high-res buffers:
``output="buffers"``). :func:`isosr_client.upscale_remote` is the route's Python client.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from isosr_client import decode_image, upscale_remote
from isosr_render import Renderer, RenderRequest, open_volume, orbit, resolve_iso


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the server, http(s)://HOST:PORT")
    parser.add_argument("--volume", default="proc:cloud:0@32", help="a volume file or a proc:NAME[:SEED][@N] spec")
    parser.add_argument("--size", default="48x32", help="the low-res WxH sent")
    parser.add_argument("--device", default="cpu", help="where the low-res frame is ray cast: cpu, cuda or cuda:N")
    parser.add_argument("--out", type=Path, default=Path("example-out/upscaled.png"))
    args = parser.parse_args(argv)

    width, height = (int(v) for v in args.size.lower().split("x"))
    volume = open_volume(args.volume)
    renderer = Renderer(volume, args.device)
    low = renderer.render(orbit(30, 20, 1.8), RenderRequest(width, height, resolve_iso(args.volume, volume),
                                                            outputs=("mask", "normal", "depth")))

    result = upscale_remote(args.url, low, output="png")  # the frame's buffers as msgpack, a PNG back
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_bytes(result.image)
    high_h, high_w = decode_image(result.image).shape[:2]
    times = ", ".join(f"{stage} {ms:.0f} ms" for stage, ms in result.times.items())
    print(f"upscaled {width}x{height} -> {high_w}x{high_h} (x{high_w // width}) on the server ({times}) -> {args.out}")
    return args.out


if __name__ == "__main__":
    main()
