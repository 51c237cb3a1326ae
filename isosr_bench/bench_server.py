"""The server benchmark: `isosr serve` under 1, 4 and 16 concurrent view sessions per mode.

    python -m isosr_bench.bench_server --device cuda --volume bonsai            # 1920x1080
    python -m isosr_bench.bench_server --device cuda --volume bonsai --size 4k  # 3840x2160
    python -m isosr_bench.bench_server --smoke           # small, CPU, in the test suite

Results: ``OUT/bench_server_<size>_<device>.json``. Starts the server in a
subprocess (or uses ``--url``) and drives closed-loop view sessions
(:func:`isosr_client.drive.drive`: send a camera, wait for its frame, repeat; ``--drag-hz HZ``: cameras at HZ
and frames taken as they come, :func:`isosr_client.drive.drag`) for a bounded time per case. Per mode (``auto``;
each method mode the server offers at the AO rays its kind names, :attr:`~isosr_net.methods.FrameRunner.serve_bench_ao`: ``full`` with AO 0 and 8,
``atrous`` with 2, ``reconstruct`` with 1, ``upscale``, ``network``, ``buffers``; ``focus``) and
session count:

- frames/s (all sessions together, and per session) and latency p50/p99: a camera change's
  round trip as a client sees it; the methods the frames name (``auto``: what it chose);
- the server's milliseconds per stage (render, filter, network, shading, encode) from the
  frames' stage times, and the rest of the round trip (queueing behind other sessions on the
  one device thread, transfer, client-side receipt) as ``other_ms`` (mean latency minus mean
  server total; the total counts from a frame's first slice to its encoding);
- bytes per frame, and the frames/s a 50 Mbit/s and a 1 Gbit/s link carry at that size;
- over the timed span (:class:`isosr_bench.load.LoadSampler`), each GPU's busy fraction
  (``nvidia-smi``; None without), the CPU cores of the server's process (not with ``--url``) and
  its device thread's share of the span in jobs (``device_thread_busy``, from ``GET /metrics``).

Clients here only receive frames (``buffers`` frames are not upscaled here), so the numbers
are the server's. Then two studies. Matched quality: the ``buffers`` path (coded low-res
buffers, upscaled and shaded on the client with the same network) against ``full`` JPEG, at
the lowest JPEG quality (of 5, 10, ..., 95) whose PSNR against the lossless reference reaches
the buffers path's PSNR; the reference is the full-resolution frame the server sends for a
still camera (``full``, ``refine_ao_rays`` AO rays, PNG); the client side runs on ``--device``
of this machine. And the ``auto`` mode's quality, scored as in the Pareto study
(:mod:`isosr_bench.bench_pareto`): one auto session's frames (PNG) along the Pareto orbit
against the reference (4 rays per pixel, 512 AO rays; color PSNR on the reference's covered
region), beside the Pareto rows of the server's own candidates, run in this process with the
server's networks (:func:`isosr_server.engine.serving_network`): the best fixed method whose
frame time fits one session's budget (``1000 / target_fps`` ms).
"""

from __future__ import annotations

import ssl
from collections.abc import Callable

import numpy as np
import torch

from isosr_bench.bench_pareto import bench_cameras, pareto_rows
from isosr_bench.common import bench_parser, print_table, write_result
from isosr_bench.load import LoadSampler, metric_total, proc_status
from isosr_bench.sessions import add_drag_argument, choices_line, client_model, result_suffix, run_sessions
from isosr_client.drive import Orbit, summarize
from isosr_client.serve_process import ServeProcess
from isosr_client.view import connect
from isosr_net.budget import color_psnr, reference_frames
from isosr_net.inference import default_precision
from isosr_net.methods import RUNNERS, Networks
from isosr_net.metrics import masked_psnr
from isosr_net.reconstructor import RECON_X2_MODEL
from isosr_render import FrameBuffers, Renderer, open_volume
from isosr_render.catalog import SHARED_PREFIX, shared_volumes_dir
from isosr_server.auto import AutoPolicy
from isosr_server.core.config import default_volumes_dir
from isosr_server.engine import MODEL_NAMES, serving_network
from isosr_server.views import VIEWS
from isosr_server.volumes import UnknownVolume, VolumeCatalog

LINKS_BIT_S = {"50mbit": 50e6, "1gbit": 1e9}
STAGES = ("render", "filter", "network", "shading", "encode")
# The LoadSampler counter of a server's device thread: its seconds in jobs (its rate: the share of the span).
DEVICE_THREAD = "device_thread"
SIZES = {"1080p": (1920, 1080), "4k": (3840, 2160), "smoke": (64, 48)}
# (mode, AO rays) per case: auto, each method mode the server offers at the AO rays its kind
# names (FrameRunner.serve_bench_ao), and focus.
CASES = (("auto", 0), *((kind, ao) for kind in VIEWS if kind in RUNNERS for ao in RUNNERS[kind].serve_bench_ao),
         ("focus", 8))
TARGET_FPS = 30.0


def rss_bytes(pid: int) -> int:
    """A process's resident set size (Linux ``/proc``)."""
    rss = proc_status(pid).get("VmRSS")
    if rss is None:
        raise RuntimeError(f"no VmRSS for process {pid}")
    return int(rss.split()[0]) * 1024


def server_load(load: dict) -> dict:
    """A case row's GPU busy fractions, server cores and the share of the span its device thread spent in jobs
    from a `LoadSampler` result (rounded: they are read, not computed on; nothing where the span did not run, no
    cores without the server's process, no device thread's share without its counter)."""
    if not load:
        return {}
    server, busy = load["cpu_cores"]["server"], load["counters"].get(DEVICE_THREAD)
    return {"gpu_busy": load["gpu_busy"] and [round(b, 3) for b in load["gpu_busy"]],
            "server_cores": round(server["cores"], 2) if server["processes"] else None,
            "device_thread_busy": None if busy is None else round(busy, 3)}


def device_thread(url: str) -> dict[str, Callable[[], float | None]]:
    """The `LoadSampler` counter of a single server's device thread (its seconds in jobs, ``GET /metrics``)."""
    return {DEVICE_THREAD: metric_total(url, "isosr_device_busy_seconds_total")}


def room_options(sessions: int) -> tuple[str, ...]:
    """`isosr serve` options that let in a benchmark's ``sessions`` view sessions, all from this
    address, while the previous case's close, with no frame-rate cap."""
    room = str(2 * sessions + 4)
    return ("--max-sessions", room, "--max-sessions-per-client", room, "--max-connections-per-client", room,
            "--max-fps", "1000")


def check_offered(volume: str) -> None:
    """ValueError unless a server started here (:class:`ServerProcess`: the default volumes folder, procedural specs)
    offers ``volume``: a bench says so at once, not after its servers' start-up."""
    root = default_volumes_dir()
    try:
        VolumeCatalog(root).info(volume)
    except UnknownVolume as e:
        where = f"the volumes folder {root}" if root else f"no volumes folder ({shared_volumes_dir()} is absent)"
        raise ValueError(f"{e}; a server started here reads {where}") from None


class ServerProcess(ServeProcess):
    """`isosr serve` on ``device`` in a subprocess on a free loopback port (a context manager:
    :class:`isosr_client.serve_process.ServeProcess`), with its resident memory.

    Args:
        device: the server's device.
        extra_args: more `isosr serve` options.
        startup_s, tls: as :class:`~isosr_client.serve_process.ServeProcess` takes them.
    """

    def __init__(self, device: str, extra_args: tuple[str, ...] = (), startup_s: float = 420.0,
                 tls: ssl.SSLContext | None = None):
        super().__init__(("--device", device, *extra_args), startup_s=startup_s, tls=tls)

    def rss(self) -> int:
        return rss_bytes(self.pid)


def case_row(mode: str, ao: int, result: dict) -> dict:
    """One table row: throughput, latency, server stages, bytes and what links carry."""
    row = {"mode": mode, "ao": ao, "sessions": result["sessions"], "errors": len(result["errors"])}
    if result["errors"]:
        row["first_error"] = str(result["errors"][0])[:300]
    if "frames" not in result:
        return row
    row["methods"], row["batch_mean"] = result["methods"], result["batch_mean"]
    if result.get("choices"):  # auto: what it expected of each method it chose
        row["choices"] = result["choices"]
    server = result["server_ms"]
    row.update(frames=result["frames"], fps=result["fps"], fps_per_session=result["fps_per_session"],
               latency_p50_ms=result["latency_p50_ms"], latency_p99_ms=result["latency_p99_ms"],
               **{f"{s}_ms": server.get(s, 0.0) for s in STAGES}, server_total_ms=server.get("total", 0.0),
               bytes_per_frame=result["bytes_per_frame"])
    row["other_ms"] = result["latency_mean_ms"] - row["server_total_ms"]
    for link, bits in LINKS_BIT_S.items():
        row[f"link_fps_{link}"] = bits / (8.0 * row["bytes_per_frame"])
    return row


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two uint8 RGB images over all pixels."""
    x, y = (torch.from_numpy(v).permute(2, 0, 1)[None].float() / 255.0 for v in (a, b))
    return float(masked_psnr(x, y, torch.ones_like(x[:, :1])))


def matched_quality(url: str, volume: str, size: tuple[int, int], device: str, frames: int, measured: int,
                    qualities: tuple[int, ...]) -> dict:
    """The buffers path against full JPEG at matched quality (module docstring), over the last
    ``measured`` of ``frames`` orbit frames (the first ones build up the recurrent state)."""
    path = Orbit()
    with connect(url, volume, "full", size, settings={"encoding": "png", "refine": False}, timeout=300) as ref_view:
        ao = ref_view.settings.refine_ao_rays
        ref_view.set_settings(ao_rays=ao)
        with connect(url, volume, "buffers", size, settings={"refine": False}, device=device, timeout=300) as buf:
            buf_stats, buf_rgb, refs = [], [], []
            for i in range(frames):
                buf.set_camera(**path.camera(i))
                buf_rgb.append(buf.frame())
                buf_stats.append(buf.stats)
                ref_view.set_camera(**path.camera(i))
                refs.append(ref_view.frame())
        with connect(url, volume, "full", size, settings={"ao_rays": ao, "refine": False}, timeout=300) as jpg:
            by_quality = {}
            for q in qualities:
                jpg.set_settings(quality=q)
                sizes, scores = [], []
                for i in range(frames - measured, frames):
                    jpg.set_camera(**path.camera(i))
                    scores.append(psnr(jpg.frame(), refs[i]))
                    sizes.append(jpg.stats.nbytes)
                by_quality[q] = (float(np.mean(sizes)), float(np.mean(scores)))
    last = range(frames - measured, frames)
    buffers_psnr = float(np.mean([psnr(buf_rgb[i], refs[i]) for i in last]))
    buffers_bytes = float(np.mean([buf_stats[i].nbytes for i in last]))
    client = summarize([buf_stats[i] for i in last], 1.0)["client_ms"]
    matched = next((q for q in qualities if by_quality[q][1] >= buffers_psnr), None)
    row = {"study": "matched_quality", "reference": f"full PNG, AO {ao}", "buffers_psnr_db": buffers_psnr,
           "buffers_bytes": buffers_bytes, "client_device": device,
           **{f"client_{k}_ms": v for k, v in client.items()},
           "jpeg": [{"quality": q, "bytes": b, "psnr_db": p} for q, (b, p) in by_quality.items()],
           "matched_jpeg_quality": matched}
    if matched is not None:
        row["matched_jpeg_bytes"] = by_quality[matched][0]
        row["buffers_over_jpeg_bytes"] = buffers_bytes / by_quality[matched][0]
    return row


def auto_quality(url: str, volume: str, size: tuple[int, int], size_name: str, device: str, frames: int,
                 warmup: int) -> dict:
    """The auto mode's color PSNR along the Pareto orbit against the best fixed method that fits
    one session's budget (module docstring)."""
    cameras = bench_cameras(frames)
    with connect(url, volume, "auto", size, settings={"encoding": "png", "refine": False}, timeout=600) as view:
        iso = view.ready.volume.iso_normalized
        shown = []
        for i in range(frames):
            view.set_camera(yaw=20.0 + 3.0 * i, pitch=20.0, distance=1.6)  # bench_cameras' orbit
            shown.append((view.frame(), view.stats.method))
    renderer = Renderer(open_volume(volume if volume.startswith("proc:") else SHARED_PREFIX + volume), device)
    refs = reference_frames(renderer, iso, size, cameras)
    torch_device = torch.device(device)
    scores = [color_psnr(FrameBuffers(mask=ref.mask, color=torch.from_numpy(rgb).to(torch_device).float() / 255),
                         ref) for (rgb, _), ref in zip(shown, refs)]
    networks = Networks(serving_network)
    models = {cls: (None, name) for cls, name in MODEL_NAMES.items()}  # the shipped models, the server's names
    candidates = AutoPolicy.for_server(device, default_precision(device), 4, models, TARGET_FPS, networks,
                                       RECON_X2_MODEL).candidates
    rows = pareto_rows(renderer, iso, volume, size, size_name, list(candidates), frames, warmup, device, networks)
    budget = 1000.0 / TARGET_FPS
    fits = [r for r in rows if r["ms"] <= budget and r["color_psnr"] is not None]
    best = max(fits, key=lambda r: r["color_psnr"]) if fits else None
    auto_psnr = float(np.nanmean(scores))
    return {"study": "auto_quality", "budget_ms": budget, "auto_psnr_db": auto_psnr,
            "auto_methods": sorted({m for _, m in shown}), "best_fixed": best and best["method"],
            "best_fixed_psnr_db": best and best["color_psnr"], "best_fixed_ms": best and best["ms"],
            "shortfall_db": best and best["color_psnr"] - auto_psnr,
            "fixed": [{k: r[k] for k in ("method", "ms", "color_psnr")} for r in rows]}


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__)
    parser.add_argument("--url", help="a running server (default: start one on --device)")
    parser.add_argument("--volume", default="proc:cloud:0@128", help="a volume the server offers")
    parser.add_argument("--size", choices=("1080p", "4k"), default="1080p", help="the view sessions' frame size")
    parser.add_argument("--seconds", type=float, help="timed seconds per case (default 5; smoke 0.5)")
    parser.add_argument("--sessions", help="concurrent sessions per case, comma-separated (default 1,4,16; smoke 1,2)")
    parser.add_argument("--modes", help="the cases' modes, comma-separated (default: every mode)")
    add_drag_argument(parser)
    args = parser.parse_args(argv)
    smoke = args.smoke
    size_name = "smoke" if smoke else args.size
    size = SIZES[size_name]
    seconds = args.seconds or (0.5 if smoke else 5.0)
    warmup = 1 if smoke else 2
    counts = [int(n) for n in (args.sessions or ("1,2" if smoke else "1,4,16")).split(",")]
    volume = "proc:cloud:0@32" if smoke and args.volume == parser.get_default("volume") else args.volume
    if not args.url:
        try:
            check_offered(volume)
        except ValueError as e:
            parser.error(f"--volume: {e}")
    focus_radius = size[1] / 4
    modes = args.modes.split(",") if args.modes else [m for m, _ in CASES]
    cases = [(m, ao) for m, ao in CASES if m in modes]

    def run(url: str, pid: int | None = None) -> list[dict]:
        rows = []
        for mode, ao in cases:
            for n in counts:
                settings = {"ao_rays": ao}
                load = LoadSampler({"server": lambda: [] if pid is None else [pid]}, gpus=args.device.startswith("cuda"),
                                   counters=device_thread(url))
                result = run_sessions(url, volume, n, seconds, mode, size, settings,
                                      focus=(size[0] / 2, size[1] / 2, focus_radius) if mode == "focus" else None,
                                      warmup_frames=warmup, on_start=lambda: load.start(seconds),
                                      drag_hz=args.drag_hz)
                rows.append(case_row(mode, ao, result) | server_load(load.result())
                            | {"client": client_model(args.drag_hz)})
                r = rows[-1]
                print(f"{mode:<11} AO {ao:<2} x{n:<3} {r.get('fps', 0):7.1f} fps  p50 {r.get('latency_p50_ms', 0):7.1f} "
                      f"p99 {r.get('latency_p99_ms', 0):7.1f} ms {r.get('bytes_per_frame', 0):10.0f} B  errors "
                      f"{r['errors']}  {', '.join(r.get('methods', []))}", flush=True)
                if r.get("choices"):
                    print(f"            auto expected: {choices_line(r['choices'])}", flush=True)
        rows.append(matched_quality(url, volume, size, args.device, 4 if smoke else 8, 2 if smoke else 4,
                                    (10, 50, 90) if smoke else tuple(range(5, 100, 5))))
        rows.append(auto_quality(url, volume, size, size_name, args.device, 2 if smoke else 8, 0 if smoke else 2))
        return rows

    if args.url:
        rows = run(args.url)
    else:
        with ServerProcess(args.device, room_options(max(counts)) + ("--target-fps", str(TARGET_FPS))) as server:
            rows = run(server.url, server.pid)
    table = [r for r in rows if "mode" in r]
    print_table(table, ["mode", "ao", "sessions", "fps", "fps_per_session", "latency_p50_ms", "latency_p99_ms",
                        "render_ms", "filter_ms", "network_ms", "shading_ms", "encode_ms", "other_ms",
                        "bytes_per_frame", "link_fps_50mbit", "link_fps_1gbit", "errors"])
    study, auto = rows[-2], rows[-1]
    print(f"buffers path: {study['buffers_psnr_db']:.2f} dB at {study['buffers_bytes']:.0f} B/frame; full JPEG "
          f"reaches it at quality {study['matched_jpeg_quality']} "
          f"({study.get('matched_jpeg_bytes', float('nan')):.0f} B/frame)")
    print(f"auto: {auto['auto_psnr_db']:.2f} dB ({', '.join(auto['auto_methods'])}); best fixed within "
          f"{auto['budget_ms']:.1f} ms: {auto['best_fixed']} {auto['best_fixed_psnr_db']} dB at {auto['best_fixed_ms']} ms")
    print(f"wrote {write_result(f'bench_server_{size_name}{result_suffix(args.drag_hz)}', args.device, rows, args.out)}")


if __name__ == "__main__":
    main()
