"""Where a reconstruction model's color error lives against the shipped model's, on one real frame (issue 49 item 3).

The first frame of the Pareto study's orbit (640x360 unless --size, 1 AO ray, 1 ray per pixel unless --spp, no
history; --frames N: its first N frames as one sequence, each frame's scores, the rest of the last) from the shipped
x1 model, each model named and the plain render; each model's mask, normals and AO scored against the reference, and
its color reshaded with the shipped model's mask, normals or AO in place of its own (scene-region dB, as the
study's)::

    python scripts/stem_geometry_gap.py ct_pitch stem=checkpoints/recon_stem/best [--size 1280x720 --spp 4 --frames 8]
"""

import argparse
from dataclasses import replace
from pathlib import Path

from isosr_bench.bench_pareto import SHIPPED_MODELS, bench_cameras, load, methods, scores
from isosr_net.budget import reference_frames
from isosr_net.methods import Networks, make_runner, run_sequence
from isosr_render import Renderer
from isosr_render.shading import shade


def main(volume_name: str, models: dict[str, Path], size: tuple[int, int] = (640, 360), spp: int = 1,
         count: int = 1) -> None:
    volume, iso = load(volume_name, "cpu")
    renderer = Renderer(volume, "cpu")
    cameras = bench_cameras(max(8, count))[:count]
    refs = reference_frames(renderer, iso, size, cameras, flow=True)
    ref = refs[-1]
    named = {"shipped": SHIPPED_MODELS["recon"], **models}
    chosen = [m for m in methods(False, "cpu", named) if m.kind in ("reconstruct", "full") and m.ao_rays == 1
              and m.spp == spp and m.factor == 1]
    networks = Networks()
    sequences = {m.name: run_sequence(make_runner(m, renderer, iso, *size, networks=networks), cameras)
                 for m in chosen}

    def scored(f, r=ref) -> dict:  # the Pareto study's scores of one frame (color: its scene region's dB)
        return scores([f], [r], ao_rays=1)

    if count > 1:
        for name, sequence in sequences.items():
            print(f"{name}, frame by frame: " + ", ".join(
                f"{scored(f, r)['color_psnr_scene']:.2f}" for f, r in zip(sequence, refs)) + " dB")
    frames = {name: sequence[-1] for name, sequence in sequences.items()}

    shipped = next(f for name, f in frames.items() if "shipped" in name)
    for name, f in frames.items():
        own = scored(f)
        mask_error = float((f.mask - ref.mask).abs().mean())
        normal_error = float((1 - (f.normal * ref.normal).sum(-1))[ref.mask > 0.01].mean())
        print(f"{name}: color {own['color_psnr_scene']:.2f} dB, mask MAE {mask_error:.5f}, normal 1 - cos "
              f"{normal_error:.5f}, AO RMSE {own['ao_rmse']:.4f}")
        if f is not shipped and any(n in name for n in models):
            for swap, parts in {"mask": (shipped.mask, f.normal, f.ao), "normals": (f.mask, shipped.normal, f.ao),
                                "AO": (f.mask, f.normal, shipped.ao),
                                "mask and normals": (shipped.mask, shipped.normal, f.ao)}.items():
                reshaded = scored(replace(f, color=shade(*parts)))
                print(f"  with the shipped model's {swap}: {reshaded['color_psnr_scene']:.2f} dB")

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("volume")
    parser.add_argument("models", nargs="+", help="NAME=FOLDER of a model folder")
    parser.add_argument("--size", default="640x360", help="WIDTHxHEIGHT (default: %(default)s)")
    parser.add_argument("--spp", type=int, default=1, help="rays per pixel (default: %(default)s)")
    parser.add_argument("--frames", type=int, default=1, help="the orbit's first frames, as one sequence")
    args = parser.parse_args()
    if args.frames < 1 or args.spp < 1:
        parser.error("--frames and --spp must be at least 1")
    try:
        width, height = (int(n) for n in args.size.split("x"))
    except ValueError:
        parser.error(f"--size must be WIDTHxHEIGHT, got {args.size!r}")
    main(args.volume, {name: Path(folder) for name, folder in (a.split("=", 1) for a in args.models)},
         (width, height), args.spp, args.frames)
