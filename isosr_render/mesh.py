"""The isosurface as a triangle mesh, to take on to ParaView or Blender: marching cubes where Warp
runs it (``warp.MarchingCubes``, on CUDA and on the CPU), in the volume's physical units (voxel
coordinates times the spacing, from the centre of voxel (0, 0, 0)), with outward vertex normals,
written through meshio.

    mesh = extract_mesh(volume, volume.normalized_iso(300.0), "cuda")
    write_mesh(mesh, "surface.ply")                          # .ply, .obj, .stl or .vtu
    half = extract_mesh(volume, iso, clip=Clip(planes=(((0, 0, 0), (0, 0, 1)),)))

The values above the iso are inside: normals point to lower values.

A clip (:mod:`isosr_render.clip`, world units) cuts the mesh as it cuts the renders. Without caps the
triangles are cut at its planes and box faces (those wholly outside dropped, those across split on
the plane, their new vertices shared along the cut): the cut is exact and the surface open there,
as the render shows it. With caps (``cap="above"`` or ``"below"``) marching cubes runs on the field
with the kept region's signed distance scaled to the field's slope across the iso (``min(value - iso,
slope * distance)`` for "above", the CSG intersection of two distance-like fields), which closes the
surface with the cut face: never beyond the planes, on them where a field's slope is even (a
distance field's exactly), the rim where cut face meets surface within a cell.

The mesh is made in z slabs of a bounded size (:func:`mesh_steps`, a step each: the server runs
each as its own device-thread job) and welded on the planes they share by voxel edge: the same
vertices, faces and normals as the whole volume's at once.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Generator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from isosr_render.clip import Clip
from isosr_render.steps import finish_steps
from isosr_render.volume import Volume

# What one mesh may take: the voxels marching cubes reads at once (float32 on the device), and the
# triangles, estimated before it is built from the cells the surface crosses (each gives one or more).
MAX_MESH_VOXELS = 512**3
MAX_MESH_TRIANGLES = 20_000_000
# Voxels of one slab, a step of a mesh (:func:`mesh_steps`; the server's device-thread job): on 2 CPU
# cores 36 ms at most (77 ms with the cores shared; proc:cloud:0@128: 19 slabs of 8 planes), within a frame
# slice (100 ms there).
MESH_SLAB_VOXELS = 2**17
MESH_FORMATS = {".ply": "ply", ".obj": "obj", ".stl": "stl", ".vtu": "vtu"}  # VTU: ParaView's XML (meshio has no VTP)
# The Warp module of Warp's marching cubes kernels (compiled at first use, as the project's own).
MESH_MODULE = wp.MarchingCubes.__module__


class MeshTooLarge(ValueError):
    """A mesh over a limit (voxels or triangles), refused before it is built, naming the limit."""


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh.

    Shape:
        vertices (V, 3) float32, physical units; faces (F, 3) int32 vertex indices; normals (V, 3)
        float32, unit, outward.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray


def extract_mesh(volume: Volume, iso: float, device: str = "cpu", max_voxels: int = MAX_MESH_VOXELS,
                 max_triangles: int = MAX_MESH_TRIANGLES, clip: Clip = Clip()) -> Mesh:
    """The isosurface of normalized ``iso`` of ``volume`` by marching cubes on ``device``, cut by
    ``clip`` (module docstring; empty where it keeps nothing): :func:`mesh_steps` run to its end.

    Raises:
        MeshTooLarge: the volume has more than ``max_voxels`` voxels, or the surface would take more
            than ``max_triangles`` triangles (each refused before the mesh is built, naming the limit).
        ValueError: a crop box of zero volume.
    """
    return finish_steps(mesh_steps(volume, iso, device, max_voxels, max_triangles, clip))


def mesh_steps(volume: Volume, iso: float, device: str = "cpu", max_voxels: int = MAX_MESH_VOXELS,
               max_triangles: int = MAX_MESH_TRIANGLES, clip: Clip = Clip(),
               slab_voxels: int = MESH_SLAB_VOXELS) -> Generator[None, None, Mesh]:
    """:func:`extract_mesh` as a generator of steps, each bounded by a slab of about ``slab_voxels``
    voxels (z planes, neighbours sharing one), so a scheduler may run other work between them:
    the capped field's slope (capped clips), the cells the surface crosses (the triangle limit,
    checked before anything is built), then each slab's mesh, cut by ``clip``; the last step
    welds the slabs' meshes on their shared planes (by edge, :func:`_stitch`) and returns the mesh,
    the same as the whole volume's. Raises as :func:`extract_mesh`, at its first step."""
    voxels = int(np.prod(volume.shape, dtype=np.int64))
    if voxels > max_voxels:
        raise MeshTooLarge(f"mesh: the volume has {voxels:,} voxels, over the limit of {max_voxels:,} "
                           f"(a coarser level or a crop of it fits)")
    if clip.box is not None and any(a == b for a, b in zip(*clip.box)):
        raise ValueError(f"mesh: clip.box {clip.box} has zero volume (lo equals hi on an axis): it keeps no surface")
    slabs = _slabs(volume.shape, slab_voxels)
    slope = (yield from _slope(volume, iso, slabs)) if clip.capped else None
    crossed = []
    for z0, z1 in slabs:
        crossed.append(_crossed_cells(_field(volume, iso, clip, slope, z0, z1), iso))
        yield
    if sum(crossed) > max_triangles:
        raise MeshTooLarge(f"mesh: the surface crosses {sum(crossed):,} cells, more triangles than the limit of "
                           f"{max_triangles:,}")
    pieces, made = [], {}
    for (z0, z1), cells in zip(slabs, crossed):
        if cells:
            pieces.append(_slab_mesh(volume, iso, clip, slope, z0, z1, device, made))
            yield
    return _stitch(pieces)


def _slabs(shape: tuple[int, int, int], slab_voxels: int) -> list[tuple[int, int]]:
    """The z planes ``[z0, z1)`` of each slab: at least two planes, at most about ``slab_voxels``
    voxels, each slab's last plane the next one's first (the cells split among them, none lost)."""
    planes = max(2, slab_voxels // (shape[0] * shape[1]))
    return [(z0, min(z0 + planes, shape[2])) for z0 in range(0, shape[2] - 1, planes - 1)]


def _field(volume: Volume, iso: float, clip: Clip, slope: float | None, z0: int, z1: int) -> np.ndarray:
    """Planes ``z0..z1-1`` of the field marching cubes runs on: the volume's, or with caps
    (``slope`` given) the field intersected with the region ``clip`` keeps (its signed distance at
    ``slope``), solid on the ``clip.cap`` side of ``iso``: marching cubes of it closes the cut."""
    field = _planes(volume, z0, z1)
    if slope is None:
        return field
    scale, offset = volume.world_transform()
    index = (np.arange(volume.shape[0]), np.arange(volume.shape[1]), np.arange(z0, z1))
    axes = [(i * s + o).reshape([-1 if a == axis else 1 for a in range(3)])
            for axis, (i, s, o) in enumerate(zip(index, scale, offset))]
    inside = np.full(field.shape, np.inf, np.float32)  # world units into the kept region (< 0: removed)
    for row in clip.half_spaces():
        np.minimum(inside, sum(c * x for c, x in zip(row[:3], axes)) + row[3], out=inside)
    inside *= slope
    cut = np.minimum(field - iso, inside) if clip.cap == "above" else np.maximum(field - iso, -inside)
    return (cut + iso).astype(np.float32)


def _planes(volume: Volume, z0: int, z1: int) -> np.ndarray:
    """The volume's z planes ``z0..z1-1``, normalized (:meth:`Volume.read_normalized`)."""
    return volume.read_normalized(slice(0, volume.shape[0]), slice(0, volume.shape[1]), slice(z0, z1))


def _slope(volume: Volume, iso: float, slabs: list[tuple[int, int]]) -> Generator[None, None, float]:
    """The field's median slope (per world unit) along the voxel edges the iso crosses (1 where
    none), a step per slab: its edges along z, and along x and y on its planes but the last (the
    next slab's first; the volume's last in the last slab): each edge counted once."""
    scale, slopes = volume.world_transform()[0], []
    for z0, z1 in slabs:
        field = _planes(volume, z0, z1)
        own = slice(0, None if z1 == volume.shape[2] else -1)
        for axis in range(3):
            along = np.moveaxis(field if axis == 2 else field[:, :, own], axis, 0)
            step = along[1:] - along[:-1]
            slopes.append(np.abs(step[(along[1:] >= iso) != (along[:-1] >= iso)]) / scale[axis])
        yield
    slopes = np.concatenate([np.zeros(0), *slopes])
    return float(np.median(slopes)) if len(slopes) else 1.0


def _slab_mesh(volume: Volume, iso: float, clip: Clip, slope: float | None, z0: int, z1: int, device: str,
               made: dict[tuple[int, int, int], int]) -> tuple[Mesh, np.ndarray]:
    """Marching cubes of planes ``z0..z1-1`` in the volume's physical units, cut by ``clip`` (no
    caps), and its vertices' keys (:func:`_edge_keys`; ``made``: the cut's, :func:`_cut`). Its
    vertices are the whole volume's: Warp places the slab at ``z0``, so a shared edge's vertex is
    computed from the same numbers."""
    nx, ny, nz = volume.shape
    lo, hi = max(z0 - 1, 0), min(z1 + 1, nz)  # a plane more each side: the normals' central differences
    around = _field(volume, iso, clip, slope, lo, hi)
    field = around[:, :, z0 - lo:z1 - lo]
    cubes = wp.MarchingCubes(nx, ny, z1 - z0, lower=(0.0, 0.0, float(z0)), upper=(nx - 1.0, ny - 1.0, z1 - 1.0))
    cubes.surface(wp.array(field, dtype=wp.float32, device=device), float(iso))
    at = cubes.verts.numpy().astype(np.float64)
    keys = _edge_keys(field, iso, z0, nz, at)
    spacing = np.asarray(volume.spacing, np.float64)
    mesh = Mesh((at * spacing).astype(np.float32), cubes.indices.numpy().reshape(-1, 3).astype(np.int32),
                _outward_normals(around, lo, volume.shape, at, spacing))
    if clip.active and not clip.capped:
        scale, offset = volume.world_transform()
        mesh, keys = _cut(mesh, keys, clip.half_spaces(), (scale / spacing).max(), offset, made)
    return mesh, keys


def _edge_keys(field: np.ndarray, iso: float, z0: int, nz: int, at: np.ndarray) -> np.ndarray:
    """The voxel edge of each vertex Warp's marching cubes made of ``field`` (planes from ``z0`` of
    ``nz``), as its index in the whole volume (``((x * ny + y) * nz + z) * 3 + axis``): Warp makes
    one vertex per crossed edge, in that order; checked against the vertices ``at`` (each on its edge).

    Raises:
        RuntimeError: the vertices do not lie on the crossed edges in that order (another Warp).
    """
    inside = field >= np.float32(iso)  # as Warp's kernel compares
    crossed = np.zeros(field.shape + (3,), bool)
    for axis in range(3):
        ahead = [slice(None)] * 3
        ahead[axis] = slice(0, -1)
        crossed[(*ahead, axis)] = np.diff(inside, axis=axis)
    x, y, z, axis = np.unravel_index(np.flatnonzero(crossed), crossed.shape)
    along = at - np.stack([x, y, z + z0], axis=1) if len(x) == len(at) else None
    # Warp's lerp (a (1 - t) + b t, float32) may miss the grid by an ulp; a wrong edge by a voxel.
    if along is None or not np.where(np.arange(3) == axis[:, None], (along > -1e-3) & (along < 1 + 1e-3),
                                     np.abs(along) < 1e-3).all():
        raise RuntimeError("mesh: Warp's marching cubes vertices are not one per crossed edge in edge order: "
                           "the slabs cannot be welded")
    return ((x * field.shape[1] + y) * nz + z + z0) * 3 + axis


def _stitch(pieces: list[tuple[Mesh, np.ndarray]]) -> Mesh:
    """The slabs' meshes as one: the vertices of one key welded (the shared planes'), faces re-indexed."""
    if not pieces:
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))
    meshes = [mesh for mesh, _ in pieces]
    starts = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    _, first, inverse = np.unique(np.concatenate([keys for _, keys in pieces]), return_index=True,
                                  return_inverse=True)
    faces = np.concatenate([m.faces + start for m, start in zip(meshes, starts)])
    return Mesh(np.concatenate([m.vertices for m in meshes])[first], inverse[faces].astype(np.int32),
                np.concatenate([m.normals for m in meshes])[first])


def _cut(mesh: Mesh, keys: np.ndarray, rows: np.ndarray, world_per_unit: float, offset: np.ndarray,
         made: dict[tuple[int, int, int], int]) -> tuple[Mesh, np.ndarray]:
    """``mesh`` (physical units) cut by each half-space of ``rows`` (world, :meth:`Clip.half_spaces`),
    and its vertices' keys: those of ``keys`` kept, a new vertex's from ``made`` (``(half-space,
    key of its edge's inside end, outside end)`` to a negative key, entered at its first cut; a
    mesh edge on a slab's shared plane is cut in both slabs, to one key)."""
    for plane, row in enumerate(rows):
        if len(mesh.faces) == 0:
            break
        distance = (mesh.vertices.astype(np.float64) * world_per_unit + offset) @ row[:3] + row[3]
        mesh, ends = _cut_one(mesh, distance)
        new = ends[:, 1] >= 0
        pairs = zip(keys[ends[new, 0]].tolist(), keys[ends[new, 1]].tolist())
        keys = keys[ends[:, 0]]
        keys[new] = [made.setdefault((plane, a, b), -1 - len(made)) for a, b in pairs]
    return mesh, keys


def _cut_one(mesh: Mesh, distance: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """``mesh`` where ``distance >= 0`` (per vertex, linear along edges): triangles wholly outside
    dropped, those across split on the zero crossing, whose new vertices their neighbours share;
    and where each vertex came from: ``(its index in mesh, -1)``, or a new one's edge ``(inside,
    outside)``."""
    inside = distance >= 0.0
    faces = mesh.faces
    count = inside[faces].sum(axis=1)
    one, two = faces[count == 1], faces[count == 2]
    # Rotate (keeping the winding) so the lone inside vertex (one) or the lone outside one (two) comes first.
    one = np.take_along_axis(one, (np.argmax(inside[one], axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    two = np.take_along_axis(two, (np.argmin(inside[two], axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    edges = np.concatenate([one[:, [0, 1]], one[:, [0, 2]], two[:, [1, 0]], two[:, [2, 0]]])  # (inside, outside)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    a, b = unique[:, 0], unique[:, 1]
    # An edge whose inside end lies on the plane crosses at that vertex: no copy (its slivers are dropped).
    slot = np.where(distance[a] == 0.0, a, len(mesh.vertices) + np.arange(len(unique)))[inverse.reshape(-1)]
    t = (distance[a] / (distance[a] - distance[b]))[:, None]
    vertices = np.concatenate([mesh.vertices, mesh.vertices[a] + t * (mesh.vertices[b] - mesh.vertices[a])])
    normals = mesh.normals[a] + t * (mesh.normals[b] - mesh.normals[a])
    normals = np.concatenate([mesh.normals, normals / np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)])
    n1, n2 = len(one), len(two)
    e01, e02 = slot[:n1], slot[n1:2 * n1]
    e10, e20 = slot[2 * n1:2 * n1 + n2], slot[2 * n1 + n2:]
    kept = np.concatenate([faces[count == 3], np.stack([one[:, 0], e01, e02], axis=1),
                           np.stack([two[:, 1], two[:, 2], e20], axis=1), np.stack([two[:, 1], e20, e10], axis=1)])
    kept = kept[(kept[:, 0] != kept[:, 1]) & (kept[:, 1] != kept[:, 2]) & (kept[:, 2] != kept[:, 0])]
    used, faces = np.unique(kept, return_inverse=True)
    old = np.arange(len(mesh.vertices))
    ends = np.concatenate([np.stack([old, np.full_like(old, -1)], axis=1), unique])[used]
    return Mesh(vertices[used].astype(np.float32), faces.reshape(-1, 3).astype(np.int32),
                normals[used].astype(np.float32)), ends


def write_mesh(mesh: Mesh, path: str | os.PathLike) -> None:
    """Write ``mesh`` by its suffix (``MESH_FORMATS``), with its vertex normals where the format
    keeps them (STL keeps face normals only); whole or not at all (a temporary file renamed).

    Raises:
        ValueError: a suffix not of ``MESH_FORMATS``.
    """
    import meshio

    path = Path(path)
    kind = MESH_FORMATS.get(path.suffix.lower())
    if kind is None:
        raise ValueError(f"mesh: {path.name} must end in one of {', '.join(MESH_FORMATS)}")
    normals = {"ply": {"nx": mesh.normals[:, 0], "ny": mesh.normals[:, 1], "nz": mesh.normals[:, 2]},
               "obj": {"obj:vn": mesh.normals}, "vtu": {"Normals": mesh.normals}, "stl": {}}[kind]
    out = meshio.Mesh(mesh.vertices, [("triangle", mesh.faces)], point_data=normals)
    fd, scratch = tempfile.mkstemp(suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        meshio.write(scratch, out, file_format=kind, **({"binary": True} if kind in ("ply", "stl") else {}))
        os.replace(scratch, path)
    finally:
        Path(scratch).unlink(missing_ok=True)


def mesh_bytes(mesh: Mesh, suffix: str) -> bytes:
    """``mesh`` as the bytes of a ``suffix`` file (:func:`write_mesh`)."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"surface{suffix}"
        write_mesh(mesh, path)
        return path.read_bytes()


def _crossed_cells(field: np.ndarray, iso: float) -> int:
    """Cells (2x2x2 voxels) with corners on both sides of ``iso``."""
    inside = field >= iso
    low, high = inside[:-1, :-1, :-1].copy(), inside[:-1, :-1, :-1].copy()
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                corner = inside[dx:dx + field.shape[0] - 1, dy:dy + field.shape[1] - 1, dz:dz + field.shape[2] - 1]
                low &= corner
                high |= corner
    return int((high & ~low).sum())


def _outward_normals(field: np.ndarray, first: int, shape: tuple[int, int, int], at: np.ndarray,
                     spacing: np.ndarray) -> np.ndarray:
    """Unit normals at voxel coordinates ``at`` of a volume of ``shape``: minus the field's
    central-difference gradient (per physical unit) at the nearest voxel (one-sided at the volume's
    faces); ``field`` holds its z planes from ``first``, those the differences read."""
    i = np.clip(np.rint(at).astype(np.int64), 0, np.asarray(shape) - 1)
    gradient = np.empty_like(at)
    for axis in range(3):
        up, down = i.copy(), i.copy()
        up[:, axis] = np.minimum(i[:, axis] + 1, shape[axis] - 1)
        down[:, axis] = np.maximum(i[:, axis] - 1, 0)
        step = (up[:, axis] - down[:, axis]).clip(1) * spacing[axis]
        up[:, 2] -= first
        down[:, 2] -= first
        gradient[:, axis] = (field[tuple(up.T)] - field[tuple(down.T)]) / step
    length = np.linalg.norm(gradient, axis=1, keepdims=True)
    return (-gradient / np.where(length > 0, length, 1.0)).astype(np.float32)
