"""`isosr mesh`: the isosurface of a volume as a triangle mesh file (.ply, .obj, .stl, .vtu)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from isosr_cli.options import add_clip_options, clip_of
from isosr_render import open_volume, resolve_iso
from isosr_render.catalog import SHARED_PREFIX, check_iso
from isosr_render.formats import help_text
from isosr_render.mesh import (
    MAX_MESH_TRIANGLES,
    MAX_MESH_VOXELS,
    MESH_FORMATS,
    extract_mesh,
    write_mesh,
)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("mesh", help="the isosurface as a triangle mesh (marching cubes), for ParaView or "
                                           "Blender", description=__doc__)
    p.add_argument("volume", help=f"a volume file or folder ({help_text()}), procedural spec or shared:NAME")
    p.add_argument("--iso", type=float, help="iso-value in data units (default: the volume's suggested one)")
    p.add_argument("--normalized-iso", action="store_true", help="--iso is on the normalized [0, 1] scale")
    p.add_argument("--device", default="cpu", help="where marching cubes runs: cpu, cuda or cuda:N")
    p.add_argument("--max-triangles", type=int, default=MAX_MESH_TRIANGLES, help="refuse larger surfaces")
    p.add_argument("--max-voxels", type=int, default=MAX_MESH_VOXELS, help="refuse larger volumes")
    add_clip_options(p)
    p.add_argument("-o", "--output", required=True,
                   help=f"the mesh file, {', '.join(MESH_FORMATS)} (physical units, vertex normals)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Extract and write the mesh; print its size and how long it took."""
    out = Path(args.output)
    if out.suffix.lower() not in MESH_FORMATS:
        raise ValueError(f"output must end in one of {', '.join(MESH_FORMATS)}, got {out.name}")
    volume = open_volume(args.volume)
    iso = check_iso(volume, resolve_iso(args.volume, volume, args.iso, args.normalized_iso),
                    args.volume.removeprefix(SHARED_PREFIX))
    start = time.perf_counter()
    clip = clip_of(args)
    mesh = extract_mesh(volume, iso, args.device, args.max_voxels, args.max_triangles, clip)
    if len(mesh.faces) == 0:
        kept = " in the clip's kept region" if clip.active else ""
        raise ValueError(f"the iso {iso:.4f} (normalized) has no surface{kept} in {volume.name}")
    write_mesh(mesh, out)
    lo, hi = volume.value_range
    print(f"{volume.name}: iso {lo + iso * (hi - lo):g}, {len(mesh.vertices):,} vertices, {len(mesh.faces):,} "
          f"triangles on {args.device} in {(time.perf_counter() - start) * 1e3:.0f} ms -> {out}")
    return 0
