"""The video benchmark: h264, vp9 and av1 against JPEG on the frames users see, under the
server's rate control, and over a throttled link (issue 21).

    python -m isosr_bench.bench_video --device cuda --volume shared:bonsai --sizes 1080p
    python -m isosr_bench.bench_video --device cuda --volume shared:bonsai --sizes 4k --frames 30 \\
        --methods reconstruct:1,full:8 --rates 20000,50000 --link-encodings h264,jpeg --link-caps 0 \\
        --link-mbit 50 --link-seconds 8
    python -m isosr_bench.bench_video --device cpu --smoke

Results: ``OUT/bench_video_<sizes>_<device>.json`` (``bench_video_1080p_cuda.json``),
one row per study and case (``study``).
The frames are what a view session encodes: per ``--methods`` entry (``KIND:AO_RAYS``, a
registered frame method; default ``reconstruct:1``, what ``auto`` picks at 1080p on an H100,
denoised; ``full:0``; ``full:8``, noisy AO) an orbit of ``--frames`` frames ``--yaw-step``
degrees apart (1: 30 degrees a second at 30 frames/s), made through the frame contract as a
session makes them (:func:`isosr_server.views.method_for` with the server's precision and
shipped models, :func:`isosr_server.engine.serving_network`; recurrent methods continue from
frame to frame), quantized to uint8 RGB: the lossless frame. PSNR is color PSNR against it on
the covered pixels (mask > 0.5). Per size and method:

- ``matched``: JPEG at ``--jpeg-quality`` (OpenCV, the server's CPU path) sets the PSNR; per video
  codec the lowest ``quality`` whose stream's mean PSNR reaches it (bisection), its encoder in
  the server's settings (:class:`isosr_server.codecs.video.VideoEncoder`: low latency, the rate
  cap at ``max_bitrate_kbps`` so quality decides, the server's thread count for the size, or each
  of ``--encoder-threads``), the frames coded where they are as the server codes them (on a GPU
  converted to 4:2:0 there: :func:`isosr_server.video.encode_frame`): bytes
  per frame (keyframe, delta frames), bytes over JPEG's, encode ms per frame (wall, this
  machine's CPU), its CPU ms and the cores that makes, decode ms (the Python client's path),
  frames/s 10, 20 and 50 Mbit/s carry, and sessions this CPU encodes at 30 frames/s.
- ``rate``: the server's own coder (:class:`isosr_server.video.SessionCoder`) of a session with
  ``bitrate_kbps`` set, per codec at each of ``--rates`` (kbit/s) and 30 frames/s, at the
  session's default quality: bytes per frame, PSNR, keyframe bytes, the largest and p99 frame
  against the per-frame budget (rate / 30 frames/s), the keyframe's milliseconds on a link of
  that rate, and whether the frames fit (p99 within the budget). JPEG beside it: frames/s the
  link carries at ``--jpeg-quality``, and the highest JPEG quality whose frames (every fourth of
  the orbit) fit the budget, with its PSNR.
- ``link`` (per size): a real server (:class:`isosr_bench.bench_server.ServerProcess`, its default
  limits) and one view session in ``--link-mode`` through a loopback link of ``--link-mbit``
  Mbit/s (:mod:`isosr_bench.video_link`: paced, bounded buffers, no propagation delay) for
  ``--link-seconds``, a new camera ``--link-input-hz`` times a second, per ``--link-encodings``
  and, for video, each of ``--link-caps`` (``bitrate_kbps``; 0: the server estimates the link):
  frames/s, latency p50/p99 (camera update to arrival; display: plus decode), bytes per frame,
  kbit/s, the server's targets, keyframes, the server's ms per stage; ``--link-max-unacked``
  sets the server's credit window (frames in flight: render, encode and link time together
  over the frame interval).

At the end the issue's goals, as measured: video at most a third of JPEG's bytes per frame at
matched PSNR, and 30 frames/s over 10 Mbit/s with latency p99 under 100 ms.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from isosr_bench.bench_server import ServerProcess
from isosr_bench.common import bench_parser, print_table, write_result
from isosr_bench.video_link import link_run
from isosr_client.drive import Orbit
from isosr_net.methods import RUNNERS, FrameMethod, Networks, make_runner
from isosr_net.inference import default_precision
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_render import Renderer, open_volume, orbit, resolve_iso
from isosr_render.catalog import SHARED_PREFIX
from isosr_render.images import quantize
from isosr_server.codecs import video
from isosr_server.engine import MODEL_NAMES, serving_network
from isosr_server.protocol import Limits, ViewSettings
from isosr_server.video import CodePlan, SessionCoder, encode_frame, video_threads
from isosr_server.views import ViewContext, method_for

SIZES = {"1080p": (1920, 1080), "4k": (3840, 2160), "smoke": (160, 90)}
LINKS_BIT_S = {"10mbit": 10e6, "20mbit": 20e6, "50mbit": 50e6}
SESSION_FPS = 30.0
# The goals: bytes per frame over JPEG's at matched PSNR; frames/s and latency p99 over a 10 Mbit/s link.
GOAL_BYTES_RATIO, GOAL_FPS, GOAL_LATENCY_MS, GOAL_LINK_KBPS = 1 / 3, 30.0, 100.0, 10_000
# JPEG's quality at a link's budget is searched on every JPEG_STRIDE-th frame (JPEG codes frames alone).
JPEG_STRIDE = 4
DEFAULTS = {"methods": "reconstruct:1,full:0,full:8", "rates": "10000,20000,50000", "link_caps": "0,8000"}
SMOKE = {"methods": "reconstruct:1,full:0", "rates": "100,300", "link_caps": "0", "link_encodings": "h264,jpeg",
         "frames": 6, "link_mbit": 1.0, "link_seconds": 1.5, "link_mode": "full", "volume": "proc:cloud:0@32"}


@dataclass
class OrbitFrames:
    """An orbit's lossless frames: as uint8 RGB numpy (what encoders take), on the device (for
    PSNR), and their covered pixels.

    Shape:
        rgb, ref: (H, W, 3) uint8 each. covered: (H, W) bool each.
    """

    rgb: list[np.ndarray]
    ref: list[torch.Tensor]
    covered: list[torch.Tensor]

    def every(self, stride: int) -> "OrbitFrames":
        return OrbitFrames(self.rgb[::stride], self.ref[::stride], self.covered[::stride])


def view_methods(specs: list[tuple[str, int]], device: str, networks: Networks) -> list[FrameMethod]:
    """The frame methods of ``(kind, AO rays)`` as a view session makes them on this device
    (the server's precision, shipped models and upscale factor)."""
    precision = default_precision(device)
    factor = (networks.get(Upscaler, DEFAULT_MODEL, device, precision).upscale_factor
              if any(RUNNERS[kind].low_res for kind, _ in specs) else 1)
    ctx = ViewContext(factor, precision, {cls: (None, name) for cls, name in MODEL_NAMES.items()})
    return [method_for(kind, ViewSettings(ao_rays=ao), ctx) for kind, ao in specs]


def orbit_frames(method: FrameMethod, renderer: Renderer, iso: float, size: tuple[int, int], path: Orbit,
                 frames: int, networks: Networks) -> OrbitFrames:
    """The orbit's frames of ``method``, one stream from the first frame on."""
    runner = make_runner(method, renderer, iso, *size, networks=networks)
    out, prev = OrbitFrames([], [], []), None
    for i in range(frames):
        camera = orbit(**path.camera(i))
        buffers = runner.frame(camera, prev).buffers
        prev = camera
        rgb = quantize(buffers.color)
        out.ref.append(rgb)
        out.rgb.append(rgb.cpu().numpy())
        out.covered.append(buffers.mask > 0.5)
    return out


def psnr(got: np.ndarray, ref: torch.Tensor, covered: torch.Tensor) -> float:
    """Color PSNR (dB) of ``got`` on the covered pixels (the whole frame where none are)."""
    region = covered if bool(covered.any()) else torch.ones_like(covered)
    diff = torch.from_numpy(got).to(ref.device)[region].double() - ref[region].double()
    mse = float(diff.square().mean())
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def timed(fn) -> tuple[object, float, float]:
    """``(fn(), wall ms, CPU ms of the whole process)``."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, 1e3 * (time.perf_counter() - wall), 1e3 * (time.process_time() - cpu)


def run_jpeg(frames: OrbitFrames, quality: int) -> dict:
    sizes, scores, enc_ms, cpu_ms, dec_ms = [], [], 0.0, 0.0, 0.0
    for rgb, ref, cov in zip(frames.rgb, frames.ref, frames.covered):
        (ok, data), wall, cpu = timed(lambda: cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]),
                                                           [cv2.IMWRITE_JPEG_QUALITY, quality]))
        enc_ms, cpu_ms = enc_ms + wall, cpu_ms + cpu
        got, wall, _ = timed(lambda: np.ascontiguousarray(cv2.imdecode(data, cv2.IMREAD_COLOR)[..., ::-1]))
        dec_ms += wall
        sizes.append(len(data))
        scores.append(psnr(got, ref, cov))
    n = len(frames.rgb)
    return {"encoding": "jpeg", "quality": quality, "psnr_db": float(np.mean(scores)),
            "bytes_per_frame": float(np.mean(sizes)), "encode_ms": enc_ms / n, "encode_cpu_ms": cpu_ms / n,
            "decode_ms": dec_ms / n}


def run_video(encoding: str, frames: OrbitFrames, quality: int, ceiling_kbps: int, threads: int) -> dict:
    """One stream of the orbit at ``quality`` by an encoder of ``threads``, coded as the server codes the frames
    where they are (:func:`isosr_server.video.encode_frame`): its bytes, PSNR and times."""
    h, w = frames.rgb[0].shape[:2]
    encoder = video.VideoEncoder(encoding, w, h, quality, ceiling_kbps, SESSION_FPS, threads)
    decoder = video.VideoDecoder(encoding)
    sizes, scores, keys, enc_ms, cpu_ms, dec_ms = [], [], [], 0.0, 0.0, 0.0
    for i, (ref, cov) in enumerate(zip(frames.ref, frames.covered)):
        (data, key), wall, cpu = timed(lambda: encode_frame(encoder, ref, round(1e6 * (i + 1) / SESSION_FPS)))
        enc_ms, cpu_ms = enc_ms + wall, cpu_ms + cpu
        got, wall, _ = timed(lambda: decoder.decode(data, w, h))
        dec_ms += wall
        sizes.append(len(data))
        keys.append(key)
        scores.append(psnr(got, ref, cov))
    codec = encoder.codec
    encoder.close()
    n = len(frames.rgb)
    deltas = [s for s, k in zip(sizes, keys) if not k]
    return {"encoding": encoding, "quality": quality, "codec": codec, "psnr_db": float(np.mean(scores)),
            "psnr_min_db": float(np.min(scores)), "bytes_per_frame": float(np.mean(sizes)),
            "keyframe_bytes": sizes[0], "delta_bytes_per_frame": float(np.mean(deltas)) if deltas else None,
            "encode_ms": enc_ms / n, "encode_cpu_ms": cpu_ms / n, "decode_ms": dec_ms / n, "encoder_threads": threads}


def matched(encoding: str, frames: OrbitFrames, target_db: float, ceiling_kbps: int, threads: int) -> dict:
    """The stream at the lowest quality whose mean PSNR reaches ``target_db`` (100 if none does)."""
    lo, hi, best = 1, 100, None
    while lo <= hi:
        q = (lo + hi) // 2
        row = run_video(encoding, frames, q, ceiling_kbps, threads)
        if row["psnr_db"] >= target_db:
            best, hi = row, q - 1
        else:
            lo = q + 1
    return best or run_video(encoding, frames, 100, ceiling_kbps, threads)


def derived(row: dict, cores: int) -> dict:
    """Frames/s per link, cores used, sessions at 30 frames/s."""
    out = {f"fps_{name}": bits / (8 * row["bytes_per_frame"]) for name, bits in LINKS_BIT_S.items()}
    out["cores_used"] = row["encode_cpu_ms"] / row["encode_ms"]
    out["sessions_at_30fps"] = cores / (row["encode_cpu_ms"] / 1e3 * SESSION_FPS)
    return out


def matched_rows(frames: OrbitFrames, codecs: list[str], jpeg_quality: int, cores: int,
                 threads: list[int] | None = None) -> list[dict]:
    """The ``matched`` study of one orbit (module docstring) for encoders of each of ``threads`` (None: the server's
    for the size); JPEG's row first."""
    h, w = frames.rgb[0].shape[:2]
    jpeg = run_jpeg(frames, jpeg_quality)
    rows = [jpeg] + [matched(c, frames, jpeg["psnr_db"], Limits().max_bitrate_kbps, n) for c in codecs
                     for n in threads or [video_threads(w, h, cores)]]
    for row in rows:
        row.update(study="matched", bytes_vs_jpeg=row["bytes_per_frame"] / jpeg["bytes_per_frame"],
                   **derived(row, cores))
    return rows


def run_rate(encoding: str, frames: OrbitFrames, bitrate_kbps: int, quality: int) -> dict:
    """The orbit through a session's coder at ``bitrate_kbps`` and 30 frames/s (module docstring)."""
    h, w = frames.rgb[0].shape[:2]
    coder, decoder = SessionCoder(os.cpu_count() or 1), None
    sizes, keys, scores, enc_ms = [], [], [], 0.0
    for i, (ref, cov) in enumerate(zip(frames.ref, frames.covered)):
        plan = CodePlan(encoding, quality, bitrate_kbps, SESSION_FPS, round(1e6 * (i + 1) / SESSION_FPS))
        coded, wall, _ = timed(lambda: coder.code(ref, plan))
        if coded.encoding != encoding:
            raise RuntimeError(f"the {encoding} session coder sent {coded.encoding}: {coded.notice}")
        if coded.keyframe:
            decoder = video.VideoDecoder(encoding)
        enc_ms += wall
        sizes.append(len(coded.data))
        keys.append(coded.keyframe)
        scores.append(psnr(decoder.decode(coded.data, w, h), ref, cov))
    coder.close()
    budget = 1e3 * bitrate_kbps / 8 / SESSION_FPS
    p99 = float(np.percentile(sizes, 99))
    deltas = [s for s, k in zip(sizes, keys) if not k]
    return {"study": "rate", "encoding": encoding, "quality": quality, "bitrate_kbps": bitrate_kbps,
            "session_fps": SESSION_FPS,
            "budget_bytes": budget, "bytes_per_frame": float(np.mean(sizes)),
            "delta_bytes_per_frame": float(np.mean(deltas)) if deltas else None, "keyframe_bytes": sizes[0],
            "keyframes": sum(keys), "max_bytes": max(sizes), "p99_bytes": p99, "max_over_budget": max(sizes) / budget,
            "p99_over_budget": p99 / budget, "keyframe_link_ms": 8 * sizes[0] / bitrate_kbps,
            "fits_30fps": p99 <= budget, "psnr_db": float(np.mean(scores)), "psnr_min_db": float(np.min(scores)),
            "encode_ms": enc_ms / len(sizes)}


def jpeg_at_budget(frames: OrbitFrames, budget_bytes: float) -> dict | None:
    """JPEG at the highest quality whose mean bytes per frame fit ``budget_bytes`` (None: not even quality 1)."""
    lo, hi, best = 1, 100, None
    while lo <= hi:
        q = (lo + hi) // 2
        row = run_jpeg(frames, q)
        if row["bytes_per_frame"] <= budget_bytes:
            best, lo = row, q + 1
        else:
            hi = q - 1
    return best


def rate_rows(frames: OrbitFrames, codecs: list[str], rates: list[int], jpeg: dict) -> list[dict]:
    """The ``rate`` study of one orbit (module docstring); ``jpeg``: its ``matched`` JPEG row."""
    quality, every = ViewSettings().quality, frames.every(JPEG_STRIDE)
    rows = []
    for rate in rates:
        at_budget = jpeg_at_budget(every, 1e3 * rate / 8 / SESSION_FPS)
        beside = {"jpeg_fps": 1e3 * rate / 8 / jpeg["bytes_per_frame"], "jpeg_psnr_db": jpeg["psnr_db"],
                  "jpeg_quality_at_budget": at_budget and at_budget["quality"],
                  "jpeg_psnr_at_budget_db": at_budget and at_budget["psnr_db"]}
        rows += [dict(run_rate(c, frames, rate, quality), **beside) for c in codecs]
    return rows


def link_rows(args, size: tuple[int, int], encodings: list[str], caps: list[int]) -> list[dict]:
    """The ``link`` study at one size: a server of its own, one throttled session per case."""
    volume = args.volume.removeprefix(SHARED_PREFIX)
    cases = [(e, cap) for e in encodings for cap in (caps if e in video.CODECS else [0])]
    rows = []
    extra = () if args.link_max_unacked is None else ("--max-unacked-frames", str(args.link_max_unacked))
    with ServerProcess(args.device, extra) as server:
        for encoding, cap in cases:
            result = link_run(server.url, 1e6 * args.link_mbit, volume, args.link_mode, size,
                              {"encoding": encoding, "bitrate_kbps": cap, "ao_rays": args.link_ao_rays},
                              args.link_seconds, args.link_input_hz, Orbit(yaw_step=args.yaw_step))
            rows.append({"study": "link", "encoding": encoding, "bitrate_cap_kbps": cap, "link_mbit": args.link_mbit,
                         "max_unacked_frames": args.link_max_unacked or Limits().max_unacked_frames,
                         "mode": args.link_mode, "ao_rays": args.link_ao_rays, "input_hz": args.link_input_hz,
                         "seconds": args.link_seconds, **result})
            r = rows[-1]
            print(f"link {encoding:<4} cap {cap:>6} kbit/s: {r.get('fps', 0):5.1f} fps, latency p50 "
                  f"{r.get('latency_p50_ms', 0):6.1f} p99 {r.get('latency_p99_ms', 0):6.1f} ms, "
                  f"{r.get('bytes_per_frame', 0):8.0f} B, {r.get('link_kbps', 0):7.0f} kbit/s on the link", flush=True)
    return rows


def goals(rows: list[dict]) -> list[str]:
    """The issue's goals against the rows, one line each (what is met and what is not)."""
    lines = []
    for r in rows:
        if r["study"] == "matched" and r["encoding"] != "jpeg" and r["size"] == "1080p":
            ok = r["bytes_vs_jpeg"] <= GOAL_BYTES_RATIO
            lines.append(f"{'MET' if ok else 'NOT MET'}: {r['method']}, {r['encoding']}: {r['bytes_vs_jpeg']:.2f} of "
                         f"JPEG's bytes at {r['psnr_db']:.1f} dB (goal <= {GOAL_BYTES_RATIO:.2f})")
        if r["study"] == "rate" and r["size"] == "1080p" and r["bitrate_kbps"] == GOAL_LINK_KBPS:
            lines.append(f"info: {r['method']}, {r['encoding']} at {r['bitrate_kbps']} kbit/s, 30 frames/s: "
                         f"{r['psnr_db']:.1f} dB, p99 frame {r['p99_over_budget']:.2f} of its budget, keyframe "
                         f"{r['keyframe_link_ms']:.0f} ms on the link; JPEG {r['jpeg_psnr_db']:.1f} dB at "
                         f"{r['jpeg_fps']:.1f} frames/s, or {r['jpeg_psnr_at_budget_db'] or float('nan'):.1f} dB at 30")
        if r["study"] == "link" and r["size"] == "1080p" and r.get("frames") and 1e3 * r["link_mbit"] <= GOAL_LINK_KBPS:
            ok = r["fps"] >= GOAL_FPS - 1 and r["latency_p99_ms"] < GOAL_LATENCY_MS
            lines.append(f"{'MET' if ok else 'NOT MET'}: {r['encoding']} (cap {r['bitrate_cap_kbps']}) over "
                         f"{r['link_mbit']:g} Mbit/s: {r['fps']:.1f} frames/s, latency p99 {r['latency_p99_ms']:.0f} ms "
                         f"(goal {GOAL_FPS:g} frames/s, p99 < {GOAL_LATENCY_MS:g} ms)")
    return lines


def parse_methods(text: str) -> list[tuple[str, int]]:
    """``KIND:AO_RAYS,...`` -> ``[(kind, rays)]``; ValueError naming the bad entry."""
    out = []
    for spec in filter(None, text.split(",")):
        kind, _, rays = spec.partition(":")
        if kind not in RUNNERS or not rays.isdigit():
            raise ValueError(f"--methods: {spec!r} is not KIND:AO_RAYS with KIND one of {', '.join(RUNNERS)}")
        out.append((kind, int(rays)))
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--volume", default="proc:cloud:0@64", help="a volume (shared:NAME or a proc: spec)")
    parser.add_argument("--sizes", default="1080p,4k", help=f"comma-separated of {', '.join(SIZES)}")
    parser.add_argument("--frames", type=int, help="orbit frames (default 60; smoke 6)")
    parser.add_argument("--yaw-step", type=float, default=1.0)
    parser.add_argument("--methods", help=f"KIND:AO_RAYS,... (default {DEFAULTS['methods']})")
    parser.add_argument("--jpeg-quality", type=int, default=85)
    parser.add_argument("--codecs", default=",".join(video.available()), help="video codecs to run")
    parser.add_argument("--encoder-threads", help="the matched study's encoder threads, comma-separated (default: "
                                                  "the server's for the size; more cut a frame's latency for bytes)")
    parser.add_argument("--rates", help=f"rate study bitrates, kbit/s (default {DEFAULTS['rates']})")
    parser.add_argument("--link-encodings", help="link run encodings (default: the codecs and jpeg; '' skips it)")
    parser.add_argument("--link-caps", help=f"link run bitrate_kbps per video encoding (default {DEFAULTS['link_caps']}; "
                                            "0: the server estimates the link)")
    parser.add_argument("--link-mbit", type=float, help="the link's Mbit/s (default 10)")
    parser.add_argument("--link-seconds", type=float, help="timed seconds per link case (default 10)")
    parser.add_argument("--link-input-hz", type=float, default=30.0, help="camera updates a second")
    parser.add_argument("--link-mode", help="the link session's view mode (default auto; smoke full)")
    parser.add_argument("--link-ao-rays", type=int, default=0, help="the link session's ao_rays")
    parser.add_argument("--link-max-unacked", type=int, help="the link server's --max-unacked-frames (default: its own)")
    args = parser.parse_args(argv)
    preset = SMOKE if args.smoke else {}
    for name, default in (("frames", 60), ("link_mbit", 10.0), ("link_seconds", 10.0), ("link_mode", "auto"),
                          ("link_encodings", ",".join([*args.codecs.split(","), "jpeg"])), *DEFAULTS.items()):
        if getattr(args, name) is None:
            setattr(args, name, preset.get(name, default))
    if args.smoke and args.volume == parser.get_default("volume"):
        args.volume = SMOKE["volume"]
    sizes = ["smoke"] if args.smoke else args.sizes.split(",")
    if unknown := [s for s in sizes if s not in SIZES]:
        parser.error(f"--sizes: {unknown[0]!r} is not one of {', '.join(SIZES)}")
    codecs = list(filter(None, args.codecs.split(",")))
    link_encodings = list(filter(None, args.link_encodings.split(",")))
    try:
        specs = parse_methods(args.methods)
        rates = [int(r) for r in filter(None, args.rates.split(","))]
        threads = [int(n) for n in filter(None, (args.encoder_threads or "").split(","))] or None
        if threads and min(threads) < 1:
            raise ValueError(f"--encoder-threads: counts of 1 or more, got {args.encoder_threads!r}")
        caps = [int(c) for c in filter(None, args.link_caps.split(","))]
        for codec in codecs + [e for e in link_encodings if e != "jpeg"]:
            video.check_available(codec)
    except (ValueError, video.VideoUnavailable) as e:
        parser.error(str(e))
    start = time.perf_counter()
    volume = open_volume(args.volume)
    renderer, iso = Renderer(volume, args.device), resolve_iso(args.volume, volume)
    networks = Networks(serving_network)
    methods, cores, rows = view_methods(specs, args.device, networks), os.cpu_count() or 1, []
    for size in sizes:
        for method in methods:
            frames = orbit_frames(method, renderer, iso, SIZES[size], Orbit(yaw_step=args.yaw_step), args.frames,
                                  networks)
            found = matched_rows(frames, codecs, args.jpeg_quality, cores, threads)
            found += rate_rows(frames, codecs, rates, found[0])
            for row in found:
                row.update(size=size, method=method.name, frames=args.frames)
            rows += found
            del frames
            print(f"{size} {method.name}: {time.perf_counter() - start:.0f} s", flush=True)
        if link_encodings:
            rows += [dict(r, size=size) for r in link_rows(args, SIZES[size], link_encodings, caps)]
    av = video._av()
    for row in rows:
        row.update(volume=args.volume, yaw_step=args.yaw_step, cpu_cores=cores, pyav=None if av is None else av.__version__)
    report(rows)
    path = write_result(f"bench_video_{'_'.join(sizes)}", args.device, rows, args.out)
    print(f"{time.perf_counter() - start:.0f} s; wrote {path}")
    return rows


def report(rows: list[dict]) -> None:
    """The tables and the goals' lines."""
    print_table([r for r in rows if r["study"] == "matched"],
                ["size", "method", "encoding", "quality", "psnr_db", "bytes_per_frame", "bytes_vs_jpeg",
                 "keyframe_bytes", "encode_ms", "cores_used", "decode_ms", "fps_10mbit", "fps_20mbit", "fps_50mbit",
                 "sessions_at_30fps"])
    print_table([r for r in rows if r["study"] == "rate"],
                ["size", "method", "encoding", "bitrate_kbps", "bytes_per_frame", "budget_bytes", "keyframe_bytes",
                 "max_over_budget", "p99_over_budget", "keyframe_link_ms", "fits_30fps", "psnr_db", "psnr_min_db",
                 "jpeg_fps", "jpeg_quality_at_budget", "jpeg_psnr_at_budget_db"])
    print_table([r for r in rows if r["study"] == "link"],
                ["size", "encoding", "bitrate_cap_kbps", "fps", "latency_p50_ms", "latency_p99_ms",
                 "display_latency_p99_ms", "bytes_per_frame", "payload_kbps", "link_kbps", "target_kbps_median",
                 "keyframes", "methods"])
    for line in goals(rows):
        print(line)


if __name__ == "__main__":
    main()
