"""`isosr render`: one frame of an isosurface to a frame file (.npz) or an image (.png).

With --method NAME[:key=value,...], any registered frame method makes it
(:mod:`isosr_net.methods`; --list-methods lists them with their knobs and bounds): e.g.
``reconstruct:ao_rays=2`` renders few AO rays and reconstructs them with a trained network; the
file holds what the method makes.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, fields
from pathlib import Path

import torch

from isosr_cli.images import visualize, write_png
from isosr_cli.options import add_clip_options, clip_of, numbers
from isosr_net.budget import BudgetConfig, render_within_budget
from isosr_net.methods import (
    RUNNERS,
    FrameMethod,
    Networks,
    make_runner,
    parse_method,
    run_sequence,
    unavailable_kinds,
)
from isosr_render import (
    Camera,
    FrameBuffers,
    Renderer,
    RenderRequest,
    open_volume,
    orbit,
    resolve_iso,
)
from isosr_render.catalog import SHARED_PREFIX, check_iso
from isosr_render.color_field import ColorField
from isosr_render.coloring import COLORMAPS, GRADIENT, Coloring
from isosr_render.conventions import AO_RADIUS, BUFFER_NAMES
from isosr_render.formats import help_text
from isosr_render.picking import pick
from isosr_render.series import open_series
from isosr_render.shapes import frame_size
from isosr_render.surfaces import MAX_SURFACES, PALETTE, Surfaces

PNG_DEFAULT = "color"
# AO rays per hit of a plain render.
AO_SAMPLES = 64
# Render options a frame method sets itself (as a learned one was trained): RenderRequest's
# defaults. Option -> request field.
METHOD_FIXED = {"--step": "step", "--refine": "refine", "--refine-steps": "refine_steps", "--seed": "seed",
                "--flow-fill": "flow_fill", "--ao-samples": "ao_samples", "--spp": "spp"}


def _triple(text: str) -> tuple[float, float, float]:
    """Parse ``x,y,z``."""
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected x,y,z, got {text!r}")
    try:
        return tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three numbers x,y,z, got {text!r}") from None


def add_parser(subparsers) -> None:
    """Register ``render`` and its options."""
    p = subparsers.add_parser("render", help="render one frame of an isosurface",
                              description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("volume", nargs="?", help=f"a volume file or folder ({help_text()}), procedural spec (proc:sphere, "
                                  "proc:torus, proc:cloud:SEED, proc:metaballs:SEED, optional @SIZE) or shared volume "
                                  "(shared:NAME); an OME-Zarr level by name, scan.zarr#level=2, or by memory, "
                                  "scan.zarr#max-gb=8 (default: the finest); with --time-step, a time series")
    p.add_argument("--time-step", type=int, metavar="T",
                   help="render step T (from 0) of a time series: a glob ('run_*.nii.gz', quoted) or folder of "
                        "volume files in natural order, a 4D NIfTI, a (t, z, y, x) .npy, an OME-Zarr with a t axis "
                        "or FILE.h5#/DATASET")
    p.add_argument("--iso", type=float, action="append",
                   help="iso-value in data units, strictly inside the data's value range (default: the procedural "
                        f"volume's own, else Otsu's threshold); repeat it for up to {MAX_SURFACES} surfaces shown "
                        "together, each ray stopping at the nearest")
    p.add_argument("--normalized-iso", action="store_true", help="--iso is on the normalized [0, 1] scale")
    p.add_argument("--iso-color", type=numbers(3), action="append", default=[], metavar="R,G,B",
                   help="the colour (each in [0, 1]) of the --iso of the same place; none: a palette in turn")
    p.add_argument("--iso-opacity", type=float, action="append", default=[], metavar="A",
                   help="the opacity in [0, 1] of the --iso of the same place (default 1); below 1 the rays go on "
                        "to the next surface and the two layers are composited (any shaded --method: it runs on each layer)")
    p.add_argument("--size", type=frame_size, default=(640, 480), help="image size WxH")
    cam = p.add_argument_group("camera (world frame: box centered at 0, longest side 1)")
    cam.add_argument("--eye", type=_triple, help="camera position x,y,z")
    cam.add_argument("--target", type=_triple, default=(0.0, 0.0, 0.0), help="look-at point")
    cam.add_argument("--up", type=_triple, default=(0.0, 1.0, 0.0), help="up direction")
    cam.add_argument("--fov", type=float, default=40.0, help="vertical field of view, degrees")
    cam.add_argument("--orbit", type=_triple, help="YAW,PITCH,DIST around --target instead of --eye")
    cam.add_argument("--prev-eye", type=_triple, help="previous camera position, for flow")
    cam.add_argument("--prev-orbit", type=_triple, help="previous camera as YAW,PITCH,DIST, for flow")
    add_clip_options(p)
    paint = p.add_argument_group("colour by a field")
    paint.add_argument("--color-by", metavar="FIELD|gradient",
                       help="colour the surface by another volume of the same grid (a path or procedural spec) or by "
                            "the volume's gradient magnitude; the frame gets an albedo buffer")
    paint.add_argument("--colormap", choices=COLORMAPS, default="viridis", help="the colour map of --color-by")
    paint.add_argument("--color-range", type=numbers(2), metavar="LO,HI",
                       help="the values mapped to the colour map's ends (default: the field's range)")
    p.add_argument("--outputs", default="mask,normal,depth,color",
                   help=f"comma-separated buffers: {','.join(BUFFER_NAMES)},samples")
    p.add_argument("--ao-samples", type=int,
                   help=f"AO rays per hit of a plain render (default {AO_SAMPLES}, 0: none; a --method takes its "
                        "own, NAME:ao_rays=N)")
    p.add_argument("--ao-radius", type=float, default=AO_RADIUS, help="AO ray length (world units)")
    p.add_argument("--step", type=float, help="ray step (world units; default half the smallest voxel)")
    p.add_argument("--voxel-units", action="store_true", help="--step and --ao-radius are in voxels")
    p.add_argument("--refine", choices=("secant", "bisection"), default="secant", help="hit refinement")
    p.add_argument("--refine-steps", type=int, default=4, help="refinement steps")
    p.add_argument("--spp", type=int, default=1, help="rays per pixel (supersampling)")
    p.add_argument("--flow-fill", choices=("none", "ns", "pushpull"), default="none",
                   help="fill the flow of pixels without a hit")
    p.add_argument("--seed", type=int, default=0, help="AO ray seed")
    p.add_argument("--no-skip", action="store_true", help="march every brick (to measure skipping)")
    p.add_argument("--budget-ms", type=float,
                   help="quality auto: a short probe picks the way to make the frame (AO rays, rays per pixel, "
                        "upscaling, network) with the best expected quality within this frame time; the file then "
                        "holds what that method makes (color, mask, normal[, ao]); --outputs, --spp, --ao-samples "
                        "do not apply")
    methods = p.add_argument_group("frame methods")
    methods.add_argument("--method", metavar="NAME[:KEY=VALUE,...]",
                         help="make the frame with a registered frame method, NAME[:key=value,...] (e.g. "
                              "reconstruct:ao_rays=2, atrous:ao_rays=4,spp=2, network, "
                              "reconstruct:model=FOLDER,precision=bf16); with a previous camera its frame is made "
                              "first and carried over; --outputs from what the method makes")
    methods.add_argument("--list-methods", action="store_true",
                         help="list the registered frame methods with their knobs and bounds, and exit")
    p.add_argument("--pick", type=_pair, metavar="X,Y",
                   help="also print what lies under pixel X,Y (x right, y down): the isosurface point in world, "
                        "voxel and physical units, the volume's value there and, with several --iso, which of them "
                        "(surface: its index), as one JSON line (default: none)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--png-of", choices=BUFFER_NAMES, help="with a .png output: the buffer to show")
    p.add_argument("-o", "--output", help="FILE.npz (frame file) or FILE.png (required but with --list-methods)")
    p.set_defaults(func=run)


def _surfaces(args: argparse.Namespace, volume, label: str) -> tuple[float, Surfaces | None]:
    """The normalized iso of --iso (checked in the data's range), and with several of them, --iso-color or
    --iso-opacity their surfaces (None: one plain iso)."""
    given = args.iso or [None]
    isos = [check_iso(volume, resolve_iso(args.volume, volume, v, args.normalized_iso), label) for v in given]
    if len(isos) == 1 and not args.iso_color and not args.iso_opacity:
        return isos[0], None
    for name, given in (("--iso-color", args.iso_color), ("--iso-opacity", args.iso_opacity)):
        if given and len(given) != len(isos):
            raise ValueError(f"give one {name} per --iso ({len(isos)}), or none, not {len(given)}")
    if len(isos) > MAX_SURFACES:
        raise ValueError(f"--iso: at most {MAX_SURFACES} surfaces, got {len(isos)}")
    surfaces = Surfaces.of(zip(isos, args.iso_color or PALETTE, args.iso_opacity or [1.0] * len(isos)))
    return surfaces.iso, surfaces


def _series_step(spec: str, t: int):
    """Step ``t`` of the series ``spec``; `ValueError` naming the steps there are."""
    series = open_series(spec)
    if not 0 <= t < series.count:
        raise ValueError(f"{spec}: no time step {t}; the series has {series.count} (0 to {series.count - 1})")
    return series.step(t)


def _coloring(args: argparse.Namespace, volume, renderer: Renderer) -> ColorField | None:
    """The coloring of --color-by, --colormap and --color-range on the renderer's device (None: none)."""
    if args.color_by is None:
        return None
    coloring = Coloring(args.color_by, args.colormap, args.color_range)
    field = None if coloring.by == GRADIENT else open_volume(coloring.by)
    return ColorField.of(coloring, volume, field, renderer.torch_device)


def _pair(text: str) -> tuple[float, float]:
    """Parse ``x,y``."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers x,y, got {text!r}") from None
    return x, y


def _camera(orbit_arg, eye, target, up, fov) -> Camera:
    """A camera from --orbit or --eye (one of them given)."""
    if orbit_arg is not None:
        return orbit(*orbit_arg, target=target, fov_y=fov)
    return Camera(eye, target, up, fov)


def _check_method(args: argparse.Namespace) -> None:
    """Refuse render options a frame method sets itself, and --budget-ms beside one."""
    if args.method is None:
        return
    if args.budget_ms is not None:
        raise ValueError("--method and --budget-ms exclude each other: the budget picks its own method")
    defaults = RenderRequest(1, 1, 0.5)
    fixed = [option for option, name in METHOD_FIXED.items() if getattr(args, name) not in (None, getattr(defaults, name))]
    fixed += ["--no-skip"] if args.no_skip else []
    if fixed:
        raise ValueError(f"--method {args.method.kind} casts its own rays (its knobs, e.g. {args.method.kind}:ao_rays=2,"
                         f"spp=2), without {', '.join(fixed)}")


def list_methods() -> str:
    """The registered frame methods, one line each: kind, label, knobs with bounds, availability."""
    missing = unavailable_kinds()
    lines = []
    for kind, runner in RUNNERS.items():
        options = FrameMethod.of(kind).options
        bounds = options.bounds()
        knobs = [f"{f.name}={bounds[f.name][0]}..{bounds[f.name][1]}" if f.name in bounds else f.name
                 for f in fields(options)]
        note = f" (unavailable: {missing[kind]})" if kind in missing else ""
        lines.append(f"{kind:<12} {runner.label}; knobs: {', '.join(knobs) or 'none'}{note}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Render as the arguments say; print what was done and how long it took."""
    if args.list_methods:
        print(list_methods())
        return 0
    if args.volume is None or args.output is None:
        raise ValueError("give a volume and -o FILE (or --list-methods)")
    out = Path(args.output)
    if out.suffix not in (".npz", ".png"):
        raise ValueError(f"output must end in .npz or .png, got {out.name}")
    if (args.eye is None) == (args.orbit is None):
        if args.eye is None and args.orbit is None:
            args.orbit = (30.0, 20.0, 1.8)
        else:
            raise ValueError("give either --eye or --orbit, not both")
    if args.prev_eye is not None and args.prev_orbit is not None:
        raise ValueError("give either --prev-eye or --prev-orbit, not both")
    outputs = tuple(o.strip() for o in args.outputs.split(",") if o.strip())
    if out.suffix == ".png":
        shown = args.png_of or PNG_DEFAULT
        outputs = tuple(dict.fromkeys(outputs + (shown,)))
    args.method = None if args.method is None else parse_method(args.method)
    _check_method(args)
    if args.ao_samples is None:
        args.ao_samples = AO_SAMPLES
    clip = clip_of(args)

    volume = open_volume(args.volume) if args.time_step is None else _series_step(args.volume, args.time_step)
    iso, surfaces = _surfaces(args, volume, args.volume.removeprefix(SHARED_PREFIX))
    if surfaces is not None and args.budget_ms is not None:
        raise ValueError("--budget-ms takes one --iso")
    unit = volume.voxel_size_world() if args.voxel_units else 1.0
    camera = _camera(args.orbit, args.eye, args.target, args.up, args.fov)
    prev = None
    if args.prev_eye is not None or args.prev_orbit is not None:
        prev = _camera(args.prev_orbit, args.prev_eye, args.target, args.up, args.fov)
    renderer = Renderer(volume, args.device)
    coloring = _coloring(args, volume, renderer)
    if args.method is not None:
        # An eager network: for a frame or two, compiling it would take longer than it saves.
        runner = make_runner(args.method, renderer, iso, *args.size, ao_radius=args.ao_radius * unit,
                             networks=Networks.eager(), keep=tuple(o for o in outputs if o in BUFFER_NAMES),
                             clip=clip, coloring=coloring, surfaces=surfaces)
    else:
        request = RenderRequest(
            width=args.size[0], height=args.size[1], iso=iso, outputs=outputs,
            step=None if args.step is None else args.step * unit, refine=args.refine,
            refine_steps=args.refine_steps, spp=args.spp, ao_samples=args.ao_samples,
            ao_radius=args.ao_radius * unit, seed=args.seed, prev_camera=prev, flow_fill=args.flow_fill,
            skip=not args.no_skip, clip=clip, coloring=coloring, surfaces=surfaces)
    start = time.perf_counter()
    if args.method is not None:
        made = run_sequence(runner, [camera] if prev is None else [prev, camera])[-1]
        missing = [name for name in outputs if getattr(made, name, None) is None]
        if missing:
            raise ValueError(f"{args.method.name} makes {','.join(made.present())}, not {','.join(missing)}")
        frame = FrameBuffers(**{name: getattr(made, name) for name in outputs})
    elif args.budget_ms is None:
        frame = renderer.render(camera, request)
    else:
        frame, choice = render_within_budget(renderer, camera, iso, *args.size, args.budget_ms,
                                             BudgetConfig(ao_radius=args.ao_radius * unit, clip=clip))
        print(f"quality auto: {choice.summary()}")
        if out.suffix == ".png" and getattr(frame, shown) is None:
            raise ValueError(f"--png-of {shown}: the chosen method makes {', '.join(frame.present())}")
    if renderer.device.is_cuda:
        torch.cuda.synchronize()
    elapsed = time.perf_counter() - start
    picked = None if args.pick is None else pick(renderer, camera, iso, *args.size, *args.pick, clip=clip,
                                                 surfaces=surfaces)
    if out.suffix == ".npz":
        frame.save_npz(out)
    else:
        write_png(out, visualize(frame, shown))
    lo, hi = volume.value_range
    how = "rendered"
    if args.method is not None:
        how = f"made by {args.method.name}{' from the previous camera on' if prev else ''}:"
    isos = [iso] if surfaces is None else [s.iso for s in surfaces.items]
    print(f"{volume.name}: {volume.shape} voxels, iso {', '.join(f'{v:.4f}' for v in isos)} normalized "
          f"({', '.join(f'{lo + v * (hi - lo):g}' for v in isos)} in data units); "
          f"{how} {','.join(frame.present())} at {args.size[0]}x{args.size[1]} on {renderer.device} "
          f"in {elapsed * 1e3:.1f} ms{'' if args.budget_ms is None else ', the probe included'} -> {out}")
    if picked is not None:
        print(json.dumps({"pick": list(args.pick), **asdict(picked)}))
    return 0
