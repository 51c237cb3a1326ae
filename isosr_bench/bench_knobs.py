"""What accuracy costs in time: each quality knob against a high-accuracy reference.

    python -m isosr_bench.bench_knobs --device cuda
    python -m isosr_bench.bench_knobs --device cpu --smoke

On one volume and camera path, each knob is swept with the others at their defaults and
timed; its error is measured against a reference rendered with far more effort:
- AO samples (8 to 512): RMS AO error on hit pixels against 2048 rays of another seed;
- ray step (2 to 0.25 voxels): mean hit-position error (voxels) against a 1/8-voxel step,
  and the fraction of pixels whose mask differs;
- refinement steps (0 to 8, secant): mean hit-position error against 16 bisection steps;
- supersampling (1 to 16 rays per pixel): RMS color error against 64 rays;
- sample lookup (the voxels, or their hardware-filtered texture at twice the memory): mean
  hit-position error and mask mismatch against the voxels' march (the texture's should be 0);
- upscaling (nearest, bilinear, bicubic at 2, 4, 8; each network at its own factor in fp32,
  bf16 and fp16 on GPUs): color PSNR of the shaded result against the high-res render with AO.
The networks are the shipped L1-normal model (x4) and those named by ``--models NAME=DIR,...``
(`scripts/train_scale_models.sh` trains x2 and x8 ones). ``--knobs`` picks sweeps (default: all).
"""

from __future__ import annotations


from pathlib import Path

import numpy as np
import torch

from isosr_render import Renderer, RenderRequest, open_volume, orbit_path, resolve_iso
from isosr_render.conventions import AO_RADIUS, HIGHRES_BUFFERS, LOWRES_BUFFERS
from isosr_render.sequence import sequence_requests
from isosr_net.metrics import frame_scores, upscale_baseline
from isosr_net.model import read_config
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_net.inference import surface_tensors

from .common import bench_parser, mean_ms, print_table, time_frames, write_result

FRAMES = 4


def stack(frame) -> torch.Tensor:
    """A rendered frame's mask, normal, depth, AO as a (1, 6, H, W) stack."""
    return frame.channels_first(HIGHRES_BUFFERS)[None]


class Knobs:
    """Sweeps on one volume: time per frame and error against a reference."""

    def __init__(self, volume, iso: float, size: tuple[int, int], device: str, smoke: bool,
                 models: dict[str, Path] | None = None):
        self.models = models or {"L1-normal": DEFAULT_MODEL}
        self.volume, self.renderer = volume, Renderer(volume, device)
        self.voxel = volume.voxel_size_world()
        self.iso, self.size, self.device, self.smoke = iso, size, device, smoke
        self.cameras = orbit_path(FRAMES, yaw0=25.0, yaw_step=3.0, pitch=20.0, distance=1.6)

    def render(self, i: int, renderer: Renderer | None = None, **options):
        w, h = options.pop("size", self.size)
        return (renderer or self.renderer).render(self.cameras[i % FRAMES], RenderRequest(w, h, self.iso, **options))

    def timed(self, renderer: Renderer | None = None, **options) -> float:
        t = time_frames(lambda i: self.render(i, renderer, **options), FRAMES, self.device, warmup=1)
        return mean_ms(t)

    def row(self, knob: str, setting, ms: float, error: float, unit: str) -> dict:
        return {"knob": knob, "setting": str(setting), "ms": ms, "error": error, "error unit": unit,
                "size": f"{self.size[0]}x{self.size[1]}"}

    def ao_samples(self) -> list[dict]:
        outputs = ("mask", "normal", "ao")
        ref = [self.render(i, outputs=outputs, ao_samples=512 if self.smoke else 2048, ao_radius=AO_RADIUS, seed=7)
               for i in range(FRAMES)]
        rows = []
        for n in ([8, 32, 128] if self.smoke else [8, 16, 32, 64, 128, 256, 512]):
            opts = dict(outputs=outputs, ao_samples=n, ao_radius=AO_RADIUS)
            err = np.mean([_rms(self.render(i, **opts).ao, ref[i].ao, ref[i].mask > 0) for i in range(FRAMES)])
            rows.append(self.row("AO samples", n, self.timed(**opts), float(err), "RMS AO"))
        return rows

    def _position_error(self, ref, frame) -> float:
        both = (ref.mask > 0) & (frame.mask > 0)
        return float((frame.position[both] - ref.position[both]).norm(dim=-1).mean()) / self.voxel

    def _hit_errors(self, refs: list, frames: list) -> tuple[float, float]:
        """Mean hit-position error (voxels, where both hit) and fraction of pixels whose mask differs."""
        err = np.mean([self._position_error(r, f) for r, f in zip(refs, frames)])
        return float(err), float(np.mean([float((r.mask != f.mask).float().mean()) for r, f in zip(refs, frames)]))

    def step(self) -> list[dict]:
        outputs = ("mask", "position")
        ref = [self.render(i, outputs=outputs, step=self.voxel / 8, refine_steps=8) for i in range(FRAMES)]
        rows = []
        for voxels in (2.0, 1.0, 0.5, 0.25):
            opts = dict(outputs=outputs, step=self.voxel * voxels)
            err, mismatch = self._hit_errors(ref, [self.render(i, **opts) for i in range(FRAMES)])
            row = self.row("ray step (voxels)", voxels, self.timed(**opts), err, "mean hit error (voxels)")
            rows.append({**row, "mask mismatch": mismatch})
        return rows

    def refinement(self) -> list[dict]:
        outputs = ("mask", "position")
        ref = [self.render(i, outputs=outputs, refine="bisection", refine_steps=16) for i in range(FRAMES)]
        rows = []
        for n in (0, 1, 2, 4, 8):
            opts = dict(outputs=outputs, refine_steps=n)
            err = np.mean([self._position_error(ref[i], self.render(i, **opts)) for i in range(FRAMES)])
            rows.append(self.row("refinement steps (secant)", n, self.timed(**opts), float(err),
                                 "mean hit error (voxels)"))
        return rows

    def supersampling(self) -> list[dict]:
        outputs = ("mask", "normal", "color")
        ref = [self.render(i, outputs=outputs, spp=16 if self.smoke else 64) for i in range(FRAMES)]
        rows = []
        for spp in ([1, 4] if self.smoke else [1, 2, 4, 8, 16]):
            opts = dict(outputs=outputs, spp=spp)
            err = np.mean([_rms(self.render(i, **opts).color, ref[i].color) for i in range(FRAMES)])
            rows.append(self.row("supersampling (rays/pixel)", spp, self.timed(**opts), float(err), "RMS color"))
        return rows

    def _renderer(self, filtered: bool) -> Renderer:
        """The knobs' renderer where its lookup is the one asked for (the device's default), else a new one."""
        if self.renderer.filtered == filtered:
            return self.renderer
        return Renderer(self.volume, self.device, filtered=filtered)

    def sample_lookup(self) -> list[dict]:
        outputs = ("mask", "position")
        renderers = {"voxels": self._renderer(filtered=False)}
        try:
            renderers["filtered texture (2x memory)"] = self._renderer(filtered=True)
        except ValueError as e:  # the device cannot make the texture or hold it: the voxels' row alone
            print(f"sample lookup: no texture row: {e}")
        ref = [self.render(i, renderers["voxels"], outputs=outputs) for i in range(FRAMES)]
        rows = []
        for setting, renderer in renderers.items():
            err, mismatch = self._hit_errors(ref, [self.render(i, renderer, outputs=outputs) for i in range(FRAMES)])
            row = self.row("sample lookup", setting, self.timed(renderer, outputs=outputs), err,
                           "mean hit error (voxels)")
            rows.append({**row, "mask mismatch": mismatch})
        return rows

    def upscaling(self) -> list[dict]:
        w, h = self.size
        truth = [stack(self.render(i, size=(w, h), outputs=HIGHRES_BUFFERS, spp=4,
                                   ao_samples=64 if self.smoke else 256, ao_radius=AO_RADIUS))
                 for i in range(FRAMES)]
        rows = []
        for factor in (2, 4, 8):
            sequence = sequence_requests(self.cameras, w // factor, h // factor, self.iso,
                                         LOWRES_BUFFERS + ("flow",))
            lows = [surface_tensors(self.renderer.render(*frame)) for frame in sequence]
            methods = {mode: (lambda low, mode=mode: upscale_baseline(low[0], factor, mode))
                       for mode in ("nearest", "bilinear", "bicubic")}
            for model, folder in self.models.items():
                if read_config(folder)["model"]["upscale"] != factor:
                    continue
                for precision in ("fp32", "bf16", "fp16") if self.device.startswith("cuda") else ("fp32",):
                    up = Upscaler(folder, self.device, precision)
                    methods[f"{model} {precision}"] = lambda low, up=up: up.step(low[0], low[1])
            for name, fn in methods.items():
                outs = [fn(low) for low in lows]  # in sequence: the network carries its state
                psnr = np.mean([float(frame_scores(o.float().cpu(), t.cpu())["color_psnr"][0])
                                for o, t in zip(outs, truth)])
                t = time_frames(lambda i: fn(lows[1 + i % (FRAMES - 1)]), FRAMES - 1, self.device, warmup=1)
                rows.append(self.row(f"upscale x{factor}", name, mean_ms(t), float(psnr),
                                     "color PSNR dB (higher is better)"))
        return rows


def parse_models(text: str) -> dict[str, Path]:
    """``NAME=DIR,NAME=DIR`` as a dict; each DIR must be a model folder.

    Raises:
        ValueError: an item is not ``NAME=DIR`` with a readable ``config.json`` in DIR.
    """
    models = {}
    for item in filter(None, text.split(",")):
        name, sep, folder = item.partition("=")
        if not sep or not name or not (Path(folder) / "config.json").is_file():
            raise ValueError(f"--models: {item!r} is not NAME=MODEL_FOLDER (a folder with config.json)")
        read_config(folder)
        models[name] = Path(folder)
    return models


def _rms(a: torch.Tensor, b: torch.Tensor, where: torch.Tensor | None = None) -> float:
    """RMS difference, over ``where`` if given."""
    d = (a - b).float()
    if where is not None:
        d = d[where]
    return float(d.pow(2).mean().sqrt()) if d.numel() else float("nan")


SWEEPS = {"ao": Knobs.ao_samples, "step": Knobs.step, "refinement": Knobs.refinement,
          "supersampling": Knobs.supersampling, "lookup": Knobs.sample_lookup, "upscaling": Knobs.upscaling}


def main(argv=None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--models", default="", help="more networks to sweep: NAME=MODEL_FOLDER,...")
    parser.add_argument("--knobs", default=",".join(SWEEPS), help=f"sweeps to run, of {','.join(SWEEPS)}")
    args = parser.parse_args(argv)
    try:
        models = {"L1-normal": DEFAULT_MODEL, **parse_models(args.models)}
    except ValueError as e:
        parser.error(str(e))
    sweeps = args.knobs.split(",")
    if unknown := [k for k in sweeps if k not in SWEEPS]:
        parser.error(f"--knobs: unknown {', '.join(unknown)}; choose from {', '.join(SWEEPS)}")
    source, size = ("proc:cloud:42@48", (64, 48)) if args.smoke else ("shared:ct_pitch", (960, 544))
    volume = open_volume(source)
    iso = resolve_iso(source, volume)
    knobs = Knobs(volume, iso, size, args.device, args.smoke, models)
    rows = [row for sweep in sweeps for row in SWEEPS[sweep](knobs)]
    for r in rows:
        r["volume"] = volume.name
    print_table(rows, ["knob", "setting", "size", "ms", "error", "error unit", "mask mismatch"])
    print(f"wrote {write_result('bench_knobs', args.device, rows, args.out)}")
    return rows


if __name__ == "__main__":
    main()
