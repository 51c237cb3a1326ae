"""The paper's timing table on our hardware, the whole interactive path, and how cost grows.

    python -m isosr_bench.bench_pipeline --device cuda
    python -m isosr_bench.bench_pipeline --device cpu --smoke

Per volume (CT head, CT chest, a simulation, a 1024^3 volume), averaged over a 10-frame
orbit at 1920x1080: the high-res render without AO and with 128 AO rays, the 480x270
low-res render, the network (`Upscaler.fastest`, on CUDA: bf16, channels-last, compiled with
CUDA graphs, fast layers), and the interactive path: low-res render + warp + network +
shading. Then time against output resolution (720p, 1080p, 4K) and against volume size
(64^3 to 1024^3).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from isosr_net.inference import surface_tensors
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_render import Renderer, RenderRequest, Volume, open_volume, orbit_path, resolve_iso
from isosr_render.conventions import AO_RADIUS, HIGHRES_BUFFERS, LOWRES_BUFFERS
from isosr_render.sequence import sequence_requests
from isosr_render.shading import shade_channels_first
from isosr_render.voxels import ArraySource

from .common import bench_parser, mean_ms, print_table, time_frames, write_result

FRAMES = 10
AO_SAMPLES = 128
LOWRES_OUTPUTS = LOWRES_BUFFERS + ("flow",)


def resampled(volume: Volume, size: int, device: str) -> Volume:
    """``volume`` trilinearly resampled to ``size`` voxels along its longest axis."""
    scale = (size - 1) / (max(volume.shape) - 1)
    shape = tuple(max(2, round((n - 1) * scale) + 1) for n in volume.shape)
    x = torch.from_numpy(volume.data).to(device)[None, None]
    data = F.interpolate(x, size=shape, mode="trilinear", align_corners=True)[0, 0].cpu().numpy()
    lo, hi = volume.value_range
    return Volume.from_source(ArraySource(data, volume.spacing, f"{volume.name} @{size}", (hi - lo, lo)))


def volumes(smoke: bool, device: str) -> list[tuple[str, Volume, float]]:
    """``(role, volume, normalized iso)``: the paper's roles, filled with our volumes."""
    roles = ((("procedural cloud", "proc:cloud:42@48"),) if smoke else
             (("CT head", "shared:ct_pitch"), ("CT chest", "shared:chest_lidc"), ("simulation", "shared:hydrogen")))
    out = [(role, v, resolve_iso(source, v)) for role, source in roles for v in [open_volume(source)]]
    if not smoke:
        bonsai = open_volume("shared:bonsai")
        out.append(("1024^3", resampled(bonsai, 1024, device), resolve_iso("shared:bonsai", bonsai)))
    return out


class Pipeline:
    """One volume's renderer and upscaler, timed stage by stage over a camera path."""

    def __init__(self, volume: Volume, iso: float, device: str, upscaler: Upscaler):
        self.renderer = Renderer(volume, device)
        self.iso, self.device, self.upscaler = iso, device, upscaler
        self.cameras = orbit_path(FRAMES + 1, yaw0=20.0, yaw_step=3.0, pitch=20.0, distance=1.6)

    def time(self, fn, smoke: bool) -> dict:
        """Mean time of ``fn(frame index)`` over the path."""
        return time_frames(fn, FRAMES, self.device, warmup=1 if smoke else 3)

    def highres(self, width: int, height: int, ao: bool):
        outputs = HIGHRES_BUFFERS if ao else LOWRES_BUFFERS
        request = RenderRequest(width, height, self.iso, outputs, ao_samples=AO_SAMPLES, ao_radius=AO_RADIUS)
        return lambda i: self.renderer.render(self.cameras[i % FRAMES + 1], request)

    def lowres(self, width: int, height: int):
        frames = sequence_requests(self.cameras, width, height, self.iso, LOWRES_OUTPUTS)
        return lambda i: self.renderer.render(*frames[i % FRAMES + 1])

    def network(self, width: int, height: int):
        lowres, flow = surface_tensors(self.lowres(width, height)(0))
        self.upscaler.reset()
        self.upscaler.step(lowres, None)
        return lambda i: self.upscaler.step(lowres, flow)

    def interactive(self, width: int, height: int):
        """Low-res render, warp + network, shading: what a viewer pays per frame."""
        render = self.lowres(width, height)
        self.upscaler.reset()

        def frame(i):
            lowres, flow = surface_tensors(render(i))
            return shade_channels_first(self.upscaler.step(lowres, flow))
        return frame


def main(argv=None) -> list[dict]:
    parser = bench_parser(__doc__)
    args = parser.parse_args(argv)
    s = 4
    hi = (192, 108) if args.smoke else (1920, 1080)
    upscaler = Upscaler.fastest(DEFAULT_MODEL, args.device)
    rows = []
    for role, volume, iso in volumes(args.smoke, args.device):
        pipe = Pipeline(volume, iso, args.device, upscaler)
        lo = (hi[0] // s, hi[1] // s)
        cases = {"high-res": pipe.highres(*hi, ao=False), f"high-res + AO {AO_SAMPLES}": pipe.highres(*hi, ao=True),
                 "low-res": pipe.lowres(*lo), "network": pipe.network(*lo), "interactive path": pipe.interactive(*lo)}
        times = {case: pipe.time(fn, args.smoke) for case, fn in cases.items()}
        for case, t in times.items():
            size = lo if case == "low-res" else hi
            rows.append({"part": "table", "role": role, "volume": volume.name,
                         "voxels": "x".join(map(str, volume.shape)), "case": case, "size": f"{size[0]}x{size[1]}",
                         "ms": mean_ms(t), **t})
        rows[-1]["speedup vs AO"] = rows[-4]["ms"] / rows[-1]["ms"]
    # How cost grows: output resolution on the CT head, volume size on resampled bonsai.
    role, volume, iso = volumes(args.smoke, args.device)[0]
    pipe = Pipeline(volume, iso, args.device, upscaler)
    sizes = [(96, 54), (192, 108)] if args.smoke else [(1280, 720), (1920, 1080), (3840, 2160)]
    for w, h in sizes:
        for case, fn in (("high-res + AO", pipe.highres(w, h, ao=True)), ("interactive path", pipe.interactive(w // s, h // s))):
            t = pipe.time(fn, args.smoke)
            rows.append({"part": "resolution", "volume": volume.name, "case": case, "size": f"{w}x{h}",
                         "ms": mean_ms(t), **t})
    base = volume if args.smoke else open_volume("shared:bonsai")
    for n in ([24, 48] if args.smoke else [64, 128, 256, 512, 1024]):
        pipe = Pipeline(resampled(base, n, args.device), iso, args.device, upscaler)
        for case, fn in (("high-res", pipe.highres(*hi, ao=False)), ("high-res + AO", pipe.highres(*hi, ao=True)),
                         ("interactive path", pipe.interactive(hi[0] // s, hi[1] // s))):
            t = pipe.time(fn, args.smoke)
            rows.append({"part": "volume size", "volume": f"{n}^3", "case": case, "size": f"{hi[0]}x{hi[1]}",
                         "ms": mean_ms(t), **t})
    print_table(rows, ["part", "role", "volume", "case", "size", "ms", "wall_ms", "speedup vs AO"])
    print(f"wrote {write_result('bench_pipeline', args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
