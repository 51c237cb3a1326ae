"""The video benchmark: h264, vp9 and av1 against JPEG at matched color PSNR on an orbit.

    python -m isosr_bench.bench_video --device cuda --volume bonsai            # 1080p and 4K
    python -m isosr_bench.bench_video --device cpu --smoke                     # small, CPU

Results: ``benchmarks/results/bench_video_<device>.json``. The frames are what a view session
encodes: ``full`` mode with ``--ao-rays`` AO rays, shaded, as uint8 RGB (the lossless frame),
along an orbit of ``--frames`` frames, ``--yaw-step`` degrees apart (1 degree: 30 degrees a
second at 30 frames/s). JPEG at ``--jpeg-quality`` sets the color PSNR to match (against the
lossless frame, on the covered pixels: mask > 0.5); per video codec the lowest ``quality``
whose stream's mean PSNR reaches it is found by bisection, its encoders in the server's
settings (:class:`isosr_server.codecs.video.VideoEncoder`: low latency, rate cap at
``max_bitrate_kbps`` so quality decides, the server's thread count for the size). Per size and
encoding:

- bytes per frame (mean; video also the keyframe's and the delta frames' mean), PSNR;
- encode milliseconds per frame (wall, on this machine's CPU; JPEG through OpenCV on the CPU as
  the server's CPU path), the CPU time per frame and the cores that makes (CPU time / wall);
  decode milliseconds per frame (the Python client's path: PyAV / OpenCV);
- frames/s that 10, 20 and 50 Mbit/s carry at that size, and how many sessions this machine's
  CPU cores encode at 30 frames/s (cores / (CPU seconds per frame * 30)).
"""

from __future__ import annotations

import os
import time

import cv2
import numpy as np

from isosr_bench.common import bench_parser, print_table, write_result
from isosr_client.drive import Orbit
from isosr_render import Renderer, RenderRequest, open_volume, orbit, resolve_iso, shade
from isosr_render.images import to_uint8
from isosr_server.codecs import video
from isosr_server.protocol import Limits
from isosr_server.video import video_threads

SIZES = {"1080p": (1920, 1080), "4k": (3840, 2160), "smoke": (160, 90)}
LINKS_BIT_S = {"10mbit": 10e6, "20mbit": 20e6, "50mbit": 50e6}
SESSION_FPS = 30.0


def lossless_frames(renderer: Renderer, iso: float, size: tuple[int, int], path: Orbit, frames: int,
                    ao_rays: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The orbit's shaded frames as uint8 RGB, and their covered pixels (mask > 0.5)."""
    rgb, covered = [], []
    for i in range(frames):
        f = renderer.render(orbit(**path.camera(i)), RenderRequest(*size, iso, ("mask", "normal", "ao"),
                                                                   ao_samples=max(ao_rays, 1)))
        rgb.append(to_uint8(shade(f.mask, f.normal, f.ao if ao_rays else None)))
        covered.append(f.mask.cpu().numpy() > 0.5)
    return rgb, covered


def psnr(got: np.ndarray, ref: np.ndarray, covered: np.ndarray) -> float:
    """Color PSNR (dB) on the covered pixels (the whole frame where none are)."""
    region = covered if covered.any() else np.ones_like(covered)
    mse = np.mean((got[region].astype(np.float64) - ref[region]) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def timed(fn) -> tuple[object, float, float]:
    """``(fn(), wall ms, CPU ms of the whole process)``."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, 1e3 * (time.perf_counter() - wall), 1e3 * (time.process_time() - cpu)


def run_jpeg(frames, covered, quality: int) -> dict:
    sizes, scores, enc_ms, cpu_ms, dec_ms = [], [], 0.0, 0.0, 0.0
    for rgb, cov in zip(frames, covered):
        (ok, data), wall, cpu = timed(lambda: cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]),
                                                           [cv2.IMWRITE_JPEG_QUALITY, quality]))
        enc_ms, cpu_ms = enc_ms + wall, cpu_ms + cpu
        got, wall, _ = timed(lambda: cv2.imdecode(data, cv2.IMREAD_COLOR)[..., ::-1])
        dec_ms += wall
        sizes.append(len(data))
        scores.append(psnr(got, rgb, cov))
    n = len(frames)
    return {"encoding": "jpeg", "quality": quality, "psnr_db": float(np.mean(scores)),
            "bytes_per_frame": float(np.mean(sizes)), "encode_ms": enc_ms / n, "encode_cpu_ms": cpu_ms / n,
            "decode_ms": dec_ms / n}


def run_video(encoding: str, frames, covered, quality: int, ceiling_kbps: int) -> dict:
    """One stream of the orbit at ``quality``: its bytes, PSNR and times."""
    h, w = frames[0].shape[:2]
    encoder = video.VideoEncoder(encoding, w, h, quality, ceiling_kbps, SESSION_FPS,
                                 video_threads(w, h, os.cpu_count() or 1))
    decoder = video.VideoDecoder(encoding)
    sizes, scores, keys, enc_ms, cpu_ms, dec_ms = [], [], [], 0.0, 0.0, 0.0
    for i, (rgb, cov) in enumerate(zip(frames, covered)):
        (data, key), wall, cpu = timed(lambda: encoder.encode(rgb, round(1e6 * (i + 1) / SESSION_FPS)))
        enc_ms, cpu_ms = enc_ms + wall, cpu_ms + cpu
        got, wall, _ = timed(lambda: decoder.decode(data, w, h))
        dec_ms += wall
        sizes.append(len(data))
        keys.append(key)
        scores.append(psnr(got, rgb, cov))
    codec = encoder.codec
    encoder.close()
    n = len(frames)
    deltas = [s for s, k in zip(sizes, keys) if not k]
    return {"encoding": encoding, "quality": quality, "codec": codec, "psnr_db": float(np.mean(scores)),
            "psnr_min_db": float(np.min(scores)), "bytes_per_frame": float(np.mean(sizes)),
            "keyframe_bytes": sizes[0], "delta_bytes_per_frame": float(np.mean(deltas)) if deltas else None,
            "encode_ms": enc_ms / n, "encode_cpu_ms": cpu_ms / n, "decode_ms": dec_ms / n,
            "encoder_threads": video_threads(w, h, os.cpu_count() or 1)}


def matched(encoding: str, frames, covered, target_db: float, ceiling_kbps: int) -> dict:
    """The stream at the lowest quality whose mean PSNR reaches ``target_db`` (100 if none does)."""
    lo, hi, best = 1, 100, None
    while lo <= hi:
        q = (lo + hi) // 2
        row = run_video(encoding, frames, covered, q, ceiling_kbps)
        if row["psnr_db"] >= target_db:
            best, hi = row, q - 1
        else:
            lo = q + 1
    return best or run_video(encoding, frames, covered, 100, ceiling_kbps)


def derived(row: dict, cores: int) -> dict:
    """Frames/s per link, cores used, sessions at 30 frames/s."""
    out = {f"fps_{name}": bits / (8 * row["bytes_per_frame"]) for name, bits in LINKS_BIT_S.items()}
    out["cores_used"] = row["encode_cpu_ms"] / row["encode_ms"]
    out["sessions_at_30fps"] = cores / (row["encode_cpu_ms"] / 1e3 * SESSION_FPS)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__)
    parser.add_argument("--volume", default="proc:cloud:0@64", help="a volume name or proc: spec")
    parser.add_argument("--sizes", default="1080p,4k", help=f"comma-separated of {', '.join(SIZES)}")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--yaw-step", type=float, default=1.0)
    parser.add_argument("--ao-rays", type=int, default=8)
    parser.add_argument("--jpeg-quality", type=int, default=85)
    parser.add_argument("--codecs", default=",".join(video.available()), help="video codecs to run")
    args = parser.parse_args(argv)
    sizes = ["smoke"] if args.smoke else args.sizes.split(",")
    frames_n = 6 if args.smoke else args.frames
    if unknown := [s for s in sizes if s not in SIZES]:
        parser.error(f"--sizes: {unknown[0]!r} is not one of {', '.join(SIZES)}")
    for codec in filter(None, args.codecs.split(",")):
        video.check_available(codec)
    volume = open_volume(args.volume)
    renderer, iso = Renderer(volume, args.device), resolve_iso(args.volume, volume)
    cores, ceiling = os.cpu_count() or 1, Limits().max_bitrate_kbps
    rows = []
    for size in sizes:
        frames, covered = lossless_frames(renderer, iso, SIZES[size], Orbit(yaw_step=args.yaw_step), frames_n,
                                          args.ao_rays)
        jpeg = run_jpeg(frames, covered, args.jpeg_quality)
        found = [jpeg] + [matched(c, frames, covered, jpeg["psnr_db"], ceiling)
                          for c in filter(None, args.codecs.split(","))]
        for row in found:
            row.update(size=size, width=SIZES[size][0], height=SIZES[size][1], frames=frames_n,
                       bytes_vs_jpeg=row["bytes_per_frame"] / jpeg["bytes_per_frame"], **derived(row, cores))
            rows.append(row)
    print_table(rows, ["size", "encoding", "quality", "psnr_db", "bytes_per_frame", "bytes_vs_jpeg", "encode_ms",
                       "cores_used", "decode_ms", "fps_10mbit", "fps_20mbit", "fps_50mbit", "sessions_at_30fps"])
    av = video._av()
    for row in rows:
        row.update(volume=args.volume, ao_rays=args.ao_rays, yaw_step=args.yaw_step, cpu_cores=cores,
                   pyav=None if av is None else av.__version__)
    print(write_result("bench_video", args.device, rows, args.out))


if __name__ == "__main__":
    main()
