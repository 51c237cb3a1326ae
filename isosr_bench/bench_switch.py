"""What Python's interpreter lock costs a view session's frame coding, by switch interval.

    python -m isosr_bench.bench_switch --device cuda --volume shared:bonsai --size 1080p
    python -m isosr_bench.bench_switch --device cpu --smoke

A server codes its sessions' frames in threads (x264, libvpx, OpenCV's JPEG) beside its device thread and event
loop, which run Python. A coding thread lets go of the lock in each C call and, where a Python thread is busy, waits
up to the switch interval (``sys.setswitchinterval``; Python's 5 ms, the server's ``--switch-interval-ms``) to take
it back, a few times a frame. Per ``--intervals`` (ms) and encoding (the video ``--codecs`` at the server's threads
for the size and default quality, and JPEG): the mean coding ms of an orbit's frames alone and beside one thread of
busy Python (the device thread of a loaded server: 99.6 % busy in one process of 16 h264 sessions on an H200), and
that thread's work done meanwhile over its work alone (``busy_share``: what shorter intervals take from it). The
frames are ``--method``'s (``KIND:AO_RAYS``) along an orbit, made where the server makes them (``--device``).

Results: ``OUT/bench_switch_<size>_<device>.json``.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from contextlib import contextmanager

from isosr_bench.bench_video import (SESSION_FPS, SIZES, OrbitFrames, orbit_frames, parse_methods, run_jpeg,
                                     run_video, view_methods)
from isosr_bench.common import bench_parser, print_table, write_result
from isosr_client.drive import Orbit
from isosr_net.methods import Networks
from isosr_render import Renderer, open_volume, resolve_iso
from isosr_server.codecs import video
from isosr_server.core.config import MAX_SWITCH_INTERVAL_MS
from isosr_server.engine import serving_network
from isosr_server.protocol import Limits, ViewSettings
from isosr_server.video import video_threads

# Seconds the busy thread runs alone to set the rate its share is measured against.
ALONE_S = 0.5


def _busy(stop: threading.Event, done: list[int]) -> None:
    """Python work that holds the interpreter lock between bytecodes, counted in steps."""
    while not stop.is_set():
        sum(range(200))
        done[0] += 1


@contextmanager
def busy_python():
    """A thread of busy Python while the block runs; yields a function of its steps a second so far."""
    stop, done = threading.Event(), [0]
    thread = threading.Thread(target=_busy, args=(stop, done), daemon=True)
    start = time.perf_counter()
    thread.start()
    try:
        yield lambda: done[0] / (time.perf_counter() - start)
    finally:
        stop.set()
        thread.join()


def coding_ms(encoding: str, frames: OrbitFrames, threads: int) -> float:
    """Mean milliseconds a frame of the orbit takes to code in ``encoding``, as the server codes it."""
    if encoding == "jpeg":
        return run_jpeg(frames, ViewSettings().quality)["encode_ms"]
    return run_video(encoding, frames, ViewSettings().quality, Limits().max_bitrate_kbps, threads)["encode_ms"]


def switch_rows(frames: OrbitFrames, encodings: list[str], intervals_ms: list[float], threads: int) -> list[dict]:
    """The study (module docstring) of one orbit; Python's switch interval is restored after it."""
    before = sys.getswitchinterval()
    with busy_python() as rate:
        time.sleep(ALONE_S)
        alone_rate = rate()
    rows = []
    try:
        for ms in intervals_ms:
            sys.setswitchinterval(ms / 1e3)
            for encoding in encodings:
                alone = coding_ms(encoding, frames, threads)
                with busy_python() as rate:
                    beside = coding_ms(encoding, frames, threads)
                    share = rate() / alone_rate
                rows.append({"switch_interval_ms": ms, "encoding": encoding, "encoder_threads": threads,
                             "encode_ms_alone": alone, "encode_ms_beside": beside,
                             "beside_over_alone": beside / alone, "busy_share": share})
    finally:
        sys.setswitchinterval(before)
    return rows


def parse_intervals(text: str) -> list[float]:
    """``5,1,0.5`` as milliseconds, each one a server may take (ValueError naming the text otherwise)."""
    try:
        intervals = [float(t) for t in text.split(",") if t]
    except ValueError:
        intervals = []
    if not intervals or not all(0 < ms <= MAX_SWITCH_INTERVAL_MS for ms in intervals):
        raise ValueError(f"--intervals: milliseconds in (0, {MAX_SWITCH_INTERVAL_MS:g}], comma-separated, got {text!r}")
    return intervals


def main(argv: list[str] | None = None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--volume", default="proc:cloud:0@64", help="a volume (shared:NAME or a proc: spec)")
    parser.add_argument("--size", choices=[s for s in SIZES if s != "smoke"], default="1080p")
    parser.add_argument("--method", default="full:0", help="KIND:AO_RAYS of the frames")
    parser.add_argument("--frames", type=int, help="orbit frames (default 20; smoke 4)")
    parser.add_argument("--intervals", default="5,1,0.5", help="switch intervals, ms, comma-separated")
    parser.add_argument("--codecs", default=",".join(video.available()), help="video codecs (and jpeg always)")
    args = parser.parse_args(argv)
    size = "smoke" if args.smoke else args.size
    try:
        intervals, spec = parse_intervals(args.intervals), parse_methods(args.method)
        codecs = list(filter(None, args.codecs.split(",")))
        for codec in codecs:
            video.check_available(codec)
    except (ValueError, video.VideoUnavailable) as e:
        parser.error(str(e))
    volume = open_volume(args.volume)
    renderer, networks = Renderer(volume, args.device), Networks(serving_network)
    method = view_methods(spec, args.device, networks)[0]
    frames = orbit_frames(method, renderer, resolve_iso(args.volume, volume), SIZES[size], Orbit(),
                          args.frames or (4 if args.smoke else 20), networks)
    w, h = SIZES[size]
    rows = switch_rows(frames, codecs + ["jpeg"], intervals, video_threads(w, h, os.cpu_count() or 1))
    for row in rows:
        row.update(size=size, method=method.name, volume=args.volume, frames=len(frames.rgb),
                   cpu_cores=os.cpu_count(), session_fps=SESSION_FPS)
    print_table(rows, ["switch_interval_ms", "encoding", "encoder_threads", "encode_ms_alone", "encode_ms_beside",
                       "beside_over_alone", "busy_share"])
    print(f"wrote {write_result(f'bench_switch_{size}', args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
