"""Where a reconstructed frame's time goes, and what compiling and CUDA graphs buy.

    python -m isosr_bench.bench_recon_path --device cuda --volumes ct_pitch,bonsai1024 --sizes 1080p,4k
    python -m isosr_bench.bench_recon_path --device cuda --model isosr_net/recon_x2_model   # x2: half-size render
    python -m isosr_bench.bench_recon_path --device cpu --smoke

Per volume, size, sampling (AO rays, rays per pixel) and `Reconstructor` variant, over the
Pareto benchmark's orbit (:func:`isosr_bench.bench_pareto.bench_cameras`), mean ms per frame:

- ``full``: the full-resolution frame with the same rays and no network (what the
  reconstruction adds to);
- ``path``: the whole reconstructed frame as its :class:`~isosr_net.methods.FrameRunner` makes it (render,
  reconstruction, shading), one synchronization at its end, as the Pareto benchmark times it;
  ``added``: ``path - full``;
- ``render``: its ray cast alone.

Variants on CUDA, all fp16 and NHWC: ``eager``; ``compiled`` (the frame's work after the render,
:func:`isosr_net.reconstructor.recon_frame`, through inductor); ``+ fast layers`` (channel counts
padded, :func:`isosr_net.fastpath.fast_reconnet`); ``+ CUDA graph`` (through the runner, the
render, the network and the shading replayed as one graph: :meth:`Reconstructor.render_reconstruct`);
where Triton imports, ``fused`` (the network as fused Triton kernels, :mod:`isosr_net.fused_recon`)
and ``fused + CUDA graph`` (:meth:`Reconstructor.fastest`). On CPUs: eager fp32. ``--variants``
picks some. Then the fastest variant without the runner: the render and then the network's graph,
against render, network and shading as one graph. The network's convolutions in GFLOP per frame
(:func:`isosr_net.reconnet.macs_per_pixel`) and the floor they imply at a bf16 matrix-multiply
rate measured in the same run (fp16's on Hopper) go beside them.

Fused rows also time each pass of the fused network alone on a rendered frame (CUDA events,
``kernels``: ``pack``, ``head``, ``down1``, ..., ``tail``, :meth:`FusedReconNet.passes`; small
passes alone time their launch too), all of them as one CUDA graph (``network``), and the ray
history's kernel before them (``history``, :mod:`isosr_net.ray_history`), with their
bytes (:func:`isosr_net.fused_recon.fused_traffic`), the floor they take at the copy bandwidth
measured in the same run, and ``of_floor``: floor over time (1 at the floor).
"""

from __future__ import annotations

from pathlib import Path

import torch

from isosr_render import Renderer
from isosr_render.shading import ShadingParams
from isosr_render.sequence import sequence_cameras
from isosr_net.methods import FrameMethod, Networks, make_runner
from isosr_net.methods.reconstruct import CANDIDATE_MODEL_NAME
from isosr_net.fused_recon import FusedReconNet, fused_runs_on, fused_traffic
from isosr_net.ray_history import accumulate_frames, history_traffic
from isosr_net.reconnet import macs_per_pixel
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, Reconstructor, sampled_rays

from .bench_network import copy_bandwidth, matmul_tflops
from .bench_pareto import FRAMES, SIZES, SMOKE_FRAMES, SMOKE_SIZES, WARMUP, bench_cameras, load
from .common import bench_parser, commit, mean_ms, print_table, time_frames, write_result

NAME = "bench_recon_path"
SAMPLINGS = ((1, 1), (1, 4))  # (AO rays, rays per pixel)
SMOKE_VOLUMES = ("sphere",)


def variants(device: str) -> dict[str, dict]:
    """Reconstructor options per variant (see the module docstring)."""
    cuda = device.startswith("cuda")
    base = {"precision": "fp16", "channels_last": True, "autotune": True}
    fast = {**base, "compile": "default", "fast_layers": True}
    out = {"eager": base, "compiled": {**base, "compile": "default"}, "compiled + fast layers": fast,
           "compiled + fast layers + CUDA graph": {**fast, "graphs": True}} if cuda else {
        "eager": {"precision": "fp32", "channels_last": True}}
    if fused_runs_on(device):  # on CPUs under Triton's interpreter only
        fused = {"precision": "fp16", "channels_last": True, "fused": True}
        out.update({"fused": fused, "fused + CUDA graph": {**fused, "graphs": True}} if cuda else {"fused": fused})
    return out


def pass_times(net: FusedReconNet, renderer: Renderer, pairs: list, request, ao_rays: int, spp: int, frames: int,
               device: str, bandwidth: float) -> dict[str, dict]:
    """Each pass of the fused network timed alone on the second frame of ``pairs`` (the first's
    output warped in), as :meth:`FusedReconNet.frame` runs them (the pack reading the render's
    buffers, the tail writing output buffers and shading them), and on CUDA all of them replayed
    as one CUDA graph (``network``), with their bytes and floor at ``bandwidth`` (bytes/s)."""
    from isosr_net.fused_kernels import ReconSources  # imports Triton

    limits = net.config.limits
    constant = limits.channels(ao_rays, spp, torch.zeros(1, 1, 1, 1, device=device))
    first, frame = (renderer.render(camera, request(prev_camera)) for camera, prev_camera in pairs[:2])
    with torch.no_grad():  # each frame's AO and sampling as a Reconstructor reads them (the ray history's)
        first_ao, first_sampling, history = sampled_rays(first, ao_rays, spp, limits, None, constant)
        previous = net.frame(first.mask, first.normal, first.depth, first_ao, first_sampling, first.flow, None,
                             None)[0]
        ao, sampling, _ = sampled_rays(frame, ao_rays, spp, limits, history, constant)
    sources = ReconSources.of_buffers(frame.mask[None], frame.normal[None], frame.depth[None],
                                      None if ao is None else ao[None], sampling)  # a batch of one frame
    h, w = frame.mask.shape
    traffic = fused_traffic(h, w, net.config, frame=True)
    with torch.no_grad():
        _, passes = net.passes(sources, previous, frame.flow.permute(2, 0, 1)[None], as_buffers=True,
                               shading=ShadingParams())
        for _, run in passes:
            run()
        out = {}
        for name, run in passes:
            out[name] = {"ms": mean_ms(time_frames(lambda i: run(), frames, device))}
        if device.startswith("cuda"):  # without the launches' overhead, which the passes alone include
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                for _, run in passes:
                    run()
            out["network"] = {"ms": mean_ms(time_frames(lambda i: graph.replay(), frames, device))}
            traffic["network"] = sum(traffic.values())
        if history is not None:  # before the network: the ray history's kernel
            out["history"] = {"ms": mean_ms(time_frames(
                lambda i: accumulate_frames([frame], history, ao_rays * spp, limits.rays(spp)), frames, device))}
            traffic["history"] = history_traffic(h, w)
    for name, bytes_ in traffic.items():
        floor = bytes_ / bandwidth * 1e3
        out[name].update(bytes=bytes_, floor_ms=floor, of_floor=floor / out[name]["ms"])
    return out


def recon_method(model: str, ao_rays: int, spp: int, precision: str) -> FrameMethod:
    """The reconstruct method of ``model`` (the shipped one: named as the policy's candidates; else by its folder)."""
    named = ({"model_name": CANDIDATE_MODEL_NAME} if model == str(DEFAULT_RECON_MODEL)
             else {"model": model, "model_name": Path(model).name})
    return FrameMethod.of("reconstruct", ao_rays=ao_rays, spp=spp, precision=precision, **named)


def stage_row(renderer: Renderer, iso: float, volume: str, size: tuple[int, int], size_name: str, ao_rays: int,
              spp: int, variant: str, options: dict, frames: int, warmup: int, device: str, tflops: float,
              bandwidth: float, model: str) -> dict:
    """One row: the stages' mean times on one volume, size, sampling and variant."""
    pairs = sequence_cameras(bench_cameras(frames))
    method = recon_method(model, ao_rays, spp, options["precision"])
    recon = Reconstructor(model, device=device, **options)
    networks = Networks(lambda *_: recon)  # this variant's network
    runner = make_runner(method, renderer, iso, *size, networks=networks)
    full = make_runner(FrameMethod.of("full", ao_rays=ao_rays, spp=spp), renderer, iso, *size)
    row = {"volume": volume, "size": size_name, "pixels": f"{size[0]}x{size[1]}", "ao_rays": ao_rays, "spp": spp,
           "variant": variant, "method": method.name}
    row["full"] = mean_ms(time_frames(lambda i: full.frame(*pairs[i]), frames, device, warmup=warmup))
    row["path"] = mean_ms(time_frames(lambda i: runner.frame(*pairs[i]), frames, device, warmup=warmup))
    row["render"] = mean_ms(time_frames(lambda i: renderer.render(pairs[i][0], runner.render_request(pairs[i][1])),
                                   frames, device, warmup=0))
    row["added"] = row["path"] - row["full"]
    row["network_gflop"] = 2 * macs_per_pixel(recon.net.config) * size[0] * size[1] / 1e9
    row["floor_ms"] = row["network_gflop"] / tflops
    row["matmul_tflops"] = tflops
    if isinstance(recon.net, FusedReconNet):
        row["kernels"] = pass_times(recon.net, renderer, pairs, runner.render_request, ao_rays, spp, frames, device,
                                    bandwidth)
        row.update({f"{name}_ms": k["ms"] for name, k in row["kernels"].items()})
        row["bandwidth_gbs"] = bandwidth / 1e9
    row["commit"] = commit()
    return row


def graph_rows(renderer: Renderer, iso: float, volume: str, size: tuple[int, int], size_name: str, ao_rays: int,
               spp: int, frames: int, warmup: int, device: str, model: str) -> list[dict]:
    """CUDA: the frame without the runner, mean ms per frame (CUDA events): the render then the
    network's graph (``Reconstructor.reconstruct``), against render, network and shading as one
    graph (``Reconstructor.render_reconstruct``)."""
    pairs = sequence_cameras(bench_cameras(frames))
    method = recon_method(model, ao_rays, spp, "fp16")
    recon = Reconstructor.fastest(model, device=device)
    runner = make_runner(method, renderer, iso, *size, networks=Networks(lambda *_: recon))
    shading = runner.shading

    def network_graph(i: int) -> None:
        camera, prev = pairs[i]
        recon.reconstruct(renderer.render(camera, runner.render_request(prev)), ao_rays, spp, shading)

    def one_graph(i: int) -> None:
        camera, prev = pairs[i]
        recon.render_reconstruct(renderer, camera, runner.render_request(prev), ao_rays, spp, shading)

    rows = []
    for variant, call in (("render + network graph", network_graph), ("one graph", one_graph)):
        recon.reset()
        t = time_frames(call, frames, device, warmup=warmup)
        rows.append({"volume": volume, "size": size_name, "pixels": f"{size[0]}x{size[1]}", "ao_rays": ao_rays,
                     "spp": spp, "variant": variant, "method": method.name, "path": t["gpu_ms"],
                     "wall_ms": t["wall_ms"], "commit": commit()})
    return rows


def main(argv=None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--volumes", default="", help="comma-separated volume names (default: ct_pitch)")
    parser.add_argument("--sizes", default="", help=f"comma-separated sizes of {','.join(SIZES)} (default: all)")
    parser.add_argument("--variants", default="", help="semicolon-separated variants (default: all of the device's)")
    parser.add_argument("--model", default=str(DEFAULT_RECON_MODEL),
                        help="the reconstruction model's folder (default: the shipped one); an x2 model renders "
                             "at half the sides")
    args = parser.parse_args(argv)
    offered = variants(args.device)
    chosen = [v.strip() for v in args.variants.split(";") if v.strip()] or list(offered)
    if any(v not in offered for v in chosen):
        parser.error(f"unknown variants {[v for v in chosen if v not in offered]}; choose from {'; '.join(offered)}")
    sizes = SMOKE_SIZES if args.smoke else SIZES
    size_names = [s.strip().lower() for s in args.sizes.split(",") if s.strip()] or list(sizes)
    unknown = [s for s in size_names if s not in sizes]
    if unknown:
        parser.error(f"unknown sizes {unknown}; choose from {', '.join(sizes)}")
    names = [s.strip() for s in args.volumes.split(",") if s.strip()] or list(
        SMOKE_VOLUMES if args.smoke else ("ct_pitch",))
    if args.device.startswith("cuda"):
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
    tflops = matmul_tflops(args.device, args.smoke)
    bandwidth = copy_bandwidth(args.device, args.smoke)
    frames, warmup = (SMOKE_FRAMES, 1) if args.smoke else (FRAMES, WARMUP)
    rows = []
    for name in names:
        volume, iso = load(name, args.device)
        renderer = Renderer(volume, args.device)
        for size_name in size_names:
            for ao_rays, spp in SAMPLINGS:
                for variant in chosen:
                    options = offered[variant]
                    rows.append(stage_row(renderer, iso, name, sizes[size_name], size_name, ao_rays, spp, variant,
                                          options, frames, warmup, args.device, tflops, bandwidth, args.model))
                if args.device.startswith("cuda"):
                    rows += graph_rows(renderer, iso, name, sizes[size_name], size_name, ao_rays, spp, frames, warmup,
                                       args.device, args.model)
    print_table(rows, ["volume", "size", "ao_rays", "spp", "variant", "full", "path", "added", "render",
                       "network_gflop", "floor_ms"])
    fused = [r for r in rows if "kernels" in r]
    if fused:
        print(f"fused passes alone, ms (floor ms at {bandwidth / 1e9:.0f} GB/s copy bandwidth):")
        print_table([{**r, **{name: f"{k['ms']:.3g}" + (f" ({k['floor_ms']:.3g})" if "floor_ms" in k else "")
                              for name, k in r["kernels"].items()}} for r in fused],
                    ["volume", "size", "ao_rays", "spp", "variant", *fused[0]["kernels"]])
    print(f"wrote {write_result(NAME, args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
