"""The first look: how long a new view session waits for its first frame, what the background
probe of the ``auto`` mode costs the frames after it, and how long a shutdown takes mid-probe.

    python -m isosr_bench.bench_first_frame --device cpu --volume bonsai     # the 2-core CPU
    python -m isosr_bench.bench_first_frame --device cuda --volume bonsai
    python -m isosr_bench.bench_first_frame --smoke                          # small, CPU

Results: ``OUT/bench_first_frame_<device>.json``. One `isosr serve` process; per
case (mode and window size, each a scene and size no earlier case probed): the seconds from
connecting to the first frame (the first case also loads the volume; the server's start, to
ready, is the ``start`` row), its method, then
``--frames`` frames along an orbit: their latency (median, max: a frame that waited for a unit
of the probe) and the method of the last (``auto``: the probe's choice once it has run). Then a
shutdown: an ``auto`` session at a new size gets its first frame, the server is sent SIGTERM
while the probe runs, and the seconds until it has exited.
"""

from __future__ import annotations

import signal
import time

import numpy as np

from isosr_bench.bench_server import ServerProcess
from isosr_bench.common import bench_parser, print_table, write_result
from isosr_client.drive import Orbit
from isosr_client.view import connect

CASES = (("auto", (1280, 720)), ("full", (1280, 720)), ("reconstruct", (1280, 720)), ("auto", (1920, 1080)))
SMOKE_CASES = (("auto", (64, 48)), ("full", (64, 48)))


def first_look(url: str, volume: str, mode: str, size: tuple[int, int], frames: int) -> dict:
    """One case (module docstring)."""
    started = time.monotonic()
    with connect(url, volume, mode, size, settings={"refine": False}, local_upscale=False, timeout=600) as view:
        view.latest()
        row = {"mode": mode, "size": f"{size[0]}x{size[1]}", "first_frame_s": time.monotonic() - started,
               "first_method": view.stats.method}
        path, waits = Orbit(), []
        for i in range(frames):
            sent = time.monotonic()
            view.set_camera(**path.camera(i))
            view.latest()
            waits.append(time.monotonic() - sent)
        row.update(frames=frames, latency_p50_s=float(np.median(waits)), latency_max_s=max(waits),
                   last_method=view.stats.method)
    return row


def shutdown_mid_probe(server: ServerProcess, volume: str, size: tuple[int, int]) -> dict:
    """SIGTERM once an ``auto`` session at a new size has its first frame: seconds to exit."""
    with connect(server.url, volume, "auto", size, settings={"refine": False}, local_upscale=False, timeout=600) as v:
        v.latest()
        sent = time.monotonic()
        server.process.send_signal(signal.SIGTERM)
        server.process.wait(120)
        return {"study": "shutdown", "size": f"{size[0]}x{size[1]}", "exit_s": time.monotonic() - sent,
                "returncode": server.process.returncode}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--volume", default="bonsai", help="a volume the server offers")
    parser.add_argument("--frames", type=int, default=15, help="frames after the first, per case")
    args = parser.parse_args(argv)
    volume = "proc:cloud:0@32" if args.smoke else args.volume
    cases, frames = (SMOKE_CASES, 3) if args.smoke else (CASES, args.frames)
    rows = []
    with ServerProcess(args.device) as server:
        rows.append({"study": "start", "ready_s": server.ready_s})
        print(rows[-1], flush=True)
        for mode, size in cases:
            rows.append(first_look(server.url, volume, mode, size, frames))
            print(rows[-1], flush=True)
        rows.append(shutdown_mid_probe(server, volume, (size[0] + 16, size[1])))
    print_table([r for r in rows if "mode" in r], ["mode", "size", "first_frame_s", "first_method", "latency_p50_s",
                                                  "latency_max_s", "last_method"])
    print(rows[-1])
    print(f"wrote {write_result('bench_first_frame', args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
