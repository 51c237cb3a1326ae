"""Renderer benchmark: first hit, AO and the low-res pass, with and without brick skipping.

    python -m isosr_bench.bench_render --device cuda          # full sizes, on a GPU
    python -m isosr_bench.bench_render --device cpu --smoke  # small sizes, CPU (CI)

Per volume, averaged over a 10-frame orbit: 1920x1080 first hit (mask, normal, depth) with
and without skipping, with two isosurfaces (the iso and one a quarter of the way to the top of
the range; opaque, and the outer one at 30%: two layers), 1080p with 128 AO rays, and the
480x270 low-res pass (mask, normal, depth, flow). Then the reconstruction's render (first hit, 1 AO ray, flow at 1080p) per call
three ways: a fresh ``Renderer.render`` (new buffers), a reused ``RenderPlan``, and on CUDA the
plan's launch replayed from a CUDA graph (``ms``: CUDA events around each call; ``kernel_ms``:
the render kernel alone). Prints a Markdown table and writes ``OUT/bench_render_*.json`` (``--out``).
"""

from __future__ import annotations

import os

import torch
import torch.nn.functional as F
import warp as wp

from isosr_render import Renderer, RenderRequest, Volume, kernels, open_volume, orbit_path, resolve_iso
from isosr_render.flow_fill import fill_flow
from isosr_render.sequence import sequence_requests
from isosr_render.surfaces import Surfaces
from isosr_render.voxels import ArraySource

from .common import bench_parser, kernel_ms, mean_ms, print_table, time_frames, write_result

FRAMES = 10
AO_RADIUS = 0.02  # world units: 20 voxels of a 1024^3 volume, 5 of a 256^3 one
LOWRES_OUTPUTS = ("mask", "normal", "depth", "flow")
RECON_OUTPUTS = ("mask", "normal", "depth", "ao", "flow")
FIRST_HIT_OUTPUTS = ("mask", "normal", "depth")


def upsampled(volume: Volume, factor: int, device: str) -> Volume:
    """``volume`` trilinearly upsampled by ``factor`` per axis (a stand-in for a big scan)."""
    x = torch.from_numpy(volume.data).to(device)[None, None]
    size = tuple((n - 1) * factor + 1 for n in volume.shape)
    big = F.interpolate(x, size=size, mode="trilinear", align_corners=True)[0, 0]
    lo, hi = volume.value_range
    return Volume.from_source(ArraySource(big.cpu().numpy(), volume.spacing, f"{volume.name} x{factor}", (hi - lo, lo)))


def volumes(smoke: bool, device: str) -> list[tuple[Volume, float]]:
    """``(volume, normalized iso)`` pairs: two real 256^3 scans and a 1024^3 one (smoke: small procedural)."""
    sources = ("proc:cloud:1@64", "proc:metaballs:2@64") if smoke else ("shared:bonsai", "shared:embryo")
    out = [(v, resolve_iso(source, v)) for source in sources for v in [open_volume(source)]]
    if not smoke:
        out.append((upsampled(out[0][0], 4, device), out[0][1]))
    return out


def two_surfaces(iso: float) -> dict[str, Surfaces]:
    """The first-hit cases of two isosurfaces: ``iso`` and one a quarter of the way from it to the top of the
    range, opaque and with ``iso``'s (the outer one of rising values) at 30%."""
    inner = iso + 0.25 * (1.0 - iso)
    return {"first hit, two surfaces": Surfaces.of([(iso, (0.9, 0.8, 0.7)), (inner, (0.9, 0.3, 0.2))]),
            "first hit, two surfaces, 30%": Surfaces.of([(iso, (0.9, 0.8, 0.7), 0.3), (inner, (0.9, 0.3, 0.2))])}


def count_samples(renderer: Renderer, camera, request: RenderRequest) -> dict:
    """Volume samples of one frame (a separate, counting render; a second layer's too): total, longest ray, hit
    fraction."""
    counted = RenderRequest(**{**request.__dict__, "outputs": request.outputs + ("samples",)})
    frame = renderer.render(camera, counted)
    samples = frame.samples if frame.behind is None else frame.samples + frame.behind.samples
    return {"samples": int(samples.sum()), "max samples/pixel": int(samples.max()),
            "coverage": float(frame.mask.float().mean())}


def bench_volume(volume: Volume, iso: float, device: str, smoke: bool) -> list[dict]:
    """All cases on one volume."""
    hi_w, hi_h = (320, 180) if smoke else (1920, 1080)
    lo_w, lo_h = hi_w // 4, hi_h // 4
    ao_samples = 16 if smoke else 128
    renderer = Renderer(volume, device)
    path = orbit_path(FRAMES + 1, yaw0=20.0, yaw_step=3.0, pitch=20.0, distance=1.8)

    def still(request: RenderRequest) -> list:
        return [(camera, request) for camera in path]

    # Per case, (camera, request) of each frame of the path; frame 0 is only the first previous camera.
    cases = {
        "first hit": still(RenderRequest(hi_w, hi_h, iso, FIRST_HIT_OUTPUTS)),
        "first hit, no skipping": still(RenderRequest(hi_w, hi_h, iso, FIRST_HIT_OUTPUTS, skip=False)),
        **{case: still(RenderRequest(hi_w, hi_h, iso, FIRST_HIT_OUTPUTS, surfaces=surfaces))
           for case, surfaces in two_surfaces(iso).items()},
        f"AO {ao_samples}": still(RenderRequest(hi_w, hi_h, iso, FIRST_HIT_OUTPUTS + ("ao",), ao_samples=ao_samples,
                                               ao_radius=AO_RADIUS)),
        "low-res": sequence_requests(path, lo_w, lo_h, iso, LOWRES_OUTPUTS),
    }
    rows = []
    for case, frames in cases.items():
        def frame(i, frames=frames):
            renderer.render(*frames[i % FRAMES + 1])
        t = time_frames(frame, FRAMES, device, warmup=1 if smoke else 3)
        if device.startswith("cuda"):
            t["kernel_ms"] = kernel_ms(frame, FRAMES, kernels.FRAME_KERNELS)
        request = frames[1][1]
        counts = count_samples(renderer, frames[1][0], request)
        ms = mean_ms(t)
        rays = request.width * request.height
        rows.append({"volume": volume.name, "voxels": "x".join(map(str, volume.shape)), "case": case,
                     "size": f"{request.width}x{request.height}", "ms": ms, **t, **counts,
                     "Mrays/s": rays / ms / 1e3, "Gsamples/s": counts["samples"] / ms / 1e6,
                     "samples/pixel": counts["samples"] / rays})
    first = {r["case"]: r["ms"] for r in rows}
    rows[0]["skip speedup"] = first["first hit, no skipping"] / first["first hit"]
    return rows


def bench_render_calls(volume: Volume, iso: float, device: str, smoke: bool) -> list[dict]:
    """The reconstruction's render per call: `Renderer.render`, a `RenderPlan`, the plan in a CUDA graph."""
    w, h = (320, 180) if smoke else (1920, 1080)
    renderer = Renderer(volume, device)
    path = orbit_path(FRAMES + 1, yaw0=20.0, yaw_step=3.0, pitch=20.0, distance=1.8)
    frames = sequence_requests(path, w, h, iso, RECON_OUTPUTS, ao_samples=1, ao_radius=AO_RADIUS)[1:]
    plan = renderer.plan(frames[0][1])
    calls = {"render()": lambda i: renderer.render(*frames[i % FRAMES]),
             "plan": lambda i: plan.render(*frames[i % FRAMES])}
    if device.startswith("cuda"):
        plan.render(*frames[0])
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            plan.launch()

        def replay(i: int) -> None:
            plan.stage(*frames[i % FRAMES])
            graph.replay()

        calls["plan, CUDA graph"] = replay
    rows = []
    for variant, call in calls.items():
        t = time_frames(call, FRAMES, device, warmup=1 if smoke else 3)
        if device.startswith("cuda") and variant != "plan, CUDA graph":  # Warp times its own launches only
            t["kernel_ms"] = kernel_ms(call, FRAMES, kernels.FRAME_KERNELS)
        rows.append({"volume": volume.name, "voxels": "x".join(map(str, volume.shape)),
                     "case": f"recon render, AO 1 + flow: {variant}", "size": f"{w}x{h}",
                     "ms": mean_ms(t), **t})
    return rows


def bench_flow_fill(volume: Volume, iso: float, device: str, smoke: bool) -> list[dict]:
    """Dense-flow fills at the low-res size: OpenCV Navier-Stokes (CPU) against push-pull."""
    w, h = (80, 45) if smoke else (480, 270)
    path = orbit_path(2, yaw0=20.0, yaw_step=3.0, pitch=20.0, distance=1.8)
    frame = Renderer(volume, device).render(*sequence_requests(path, w, h, iso, ("mask", "flow"))[1])
    rows = []
    for method in ("ns", "pushpull"):
        t = time_frames(lambda i: fill_flow(frame.flow, frame.mask, method), FRAMES, device)
        rows.append({"volume": volume.name, "case": f"flow fill {method}", "size": f"{w}x{h}",
                     "ms": mean_ms(t), **t})
    return rows


def bench_cpu_threads(volume: Volume, iso: float) -> list[dict]:
    """CPU row bands: one thread against all cores, measured in one run (a ratio)."""
    request = RenderRequest(256, 256, iso, FIRST_HIT_OUTPUTS)
    camera = orbit_path(1, yaw0=20.0, pitch=20.0, distance=1.8)[0]
    rows = []
    for threads in (1, os.cpu_count() or 1):
        renderer = Renderer(volume, "cpu", threads=threads)
        t = time_frames(lambda i: renderer.render(camera, request), 5, "cpu")
        rows.append({"volume": volume.name, "case": f"cpu first hit, {threads} thread(s)", "size": "256x256",
                     "ms": t["wall_ms"], **t})
    rows[-1]["thread speedup"] = rows[0]["ms"] / rows[-1]["ms"]
    return rows


def main(argv=None) -> None:
    parser = bench_parser(__doc__)
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    cases = volumes(args.smoke, args.device)
    rows = []
    for volume, iso in cases:
        with wp.ScopedTimer(f"{volume.name} {volume.shape}", print=True):
            rows += bench_volume(volume, iso, args.device, args.smoke)
            rows += bench_render_calls(volume, iso, args.device, args.smoke)
    rows += bench_flow_fill(*cases[0], args.device, args.smoke)
    if args.device == "cpu":
        rows += bench_cpu_threads(*volumes(True, "cpu")[0])
    print_table(rows, ["volume", "voxels", "case", "size", "ms", "kernel_ms", "wall_ms", "Mrays/s", "Gsamples/s",
                       "samples/pixel", "max samples/pixel", "coverage", "skip speedup", "thread speedup"])
    print(f"wrote {write_result('bench_render', args.device, rows, args.out)}")


if __name__ == "__main__":
    main()
