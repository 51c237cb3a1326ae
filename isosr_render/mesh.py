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
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from isosr_render.clip import Clip
from isosr_render.volume import Volume

# What one mesh may take: the voxels marching cubes reads at once (float32 on the device), and the
# triangles, estimated before it is built from the cells the surface crosses (each gives one or more).
MAX_MESH_VOXELS = 512**3
MAX_MESH_TRIANGLES = 20_000_000
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
    ``clip`` (module docstring; empty where it keeps nothing).

    Raises:
        MeshTooLarge: the volume has more than ``max_voxels`` voxels, or the surface would take more
            than ``max_triangles`` triangles (each refused before the mesh is built, naming the limit).
        ValueError: a crop box of zero volume.
    """
    voxels = int(np.prod(volume.shape, dtype=np.int64))
    if voxels > max_voxels:
        raise MeshTooLarge(f"mesh: the volume has {voxels:,} voxels, over the limit of {max_voxels:,} "
                         f"(a coarser level or a crop of it fits)")
    if clip.box is not None and any(a == b for a, b in zip(*clip.box)):
        raise ValueError(f"mesh: clip.box {clip.box} has zero volume (lo equals hi on an axis): it keeps no surface")
    field = volume.data if not clip.capped else _capped_field(volume, iso, clip)
    mesh = _marching_cubes(field, iso, volume.spacing, device, max_triangles)
    if clip.active and not clip.capped:
        scale, offset = volume.world_transform()
        mesh = _cut(mesh, clip.half_spaces(), (scale / np.asarray(volume.spacing)).max(), offset)
    return mesh


def _marching_cubes(field: np.ndarray, iso: float, spacing, device: str, max_triangles: int) -> Mesh:
    """Marching cubes of ``field`` (normalized values) at ``iso``, in physical units."""
    crossed = _crossed_cells(field, iso)
    if crossed > max_triangles:
        raise MeshTooLarge(f"mesh: the surface crosses {crossed:,} cells, more triangles than the limit of "
                         f"{max_triangles:,}")
    if crossed == 0:
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))
    cubes = wp.MarchingCubes(*field.shape)
    cubes.surface(wp.array(field, dtype=wp.float32, device=device), float(iso))
    at = cubes.verts.numpy().astype(np.float64)
    faces = cubes.indices.numpy().reshape(-1, 3).astype(np.int32)
    spacing = np.asarray(spacing, np.float64)
    return Mesh((at * spacing).astype(np.float32), faces, _outward_normals(field, at, spacing))


def _capped_field(volume: Volume, iso: float, clip: Clip) -> np.ndarray:
    """The field intersected with the region ``clip`` keeps (the region's signed distance at the
    field's slope), solid on the ``clip.cap`` side of ``iso``: marching cubes of it closes the cut."""
    field, (scale, offset) = volume.data, volume.world_transform()
    axes = [(np.arange(n) * s + o).reshape([-1 if a == axis else 1 for a in range(3)])
            for axis, (n, s, o) in enumerate(zip(volume.shape, scale, offset))]
    inside = np.full(volume.shape, np.inf, np.float32)  # world units into the kept region (< 0: removed)
    for row in clip.half_spaces():
        np.minimum(inside, sum(c * x for c, x in zip(row[:3], axes)) + row[3], out=inside)
    inside *= _slope(field, iso, scale)
    cut = np.minimum(field - iso, inside) if clip.cap == "above" else np.maximum(field - iso, -inside)
    return (cut + iso).astype(np.float32)


def _slope(field: np.ndarray, iso: float, scale: np.ndarray) -> float:
    """The field's median slope (per world unit) along the voxel edges the iso crosses; 1 where none."""
    slopes = []
    for axis in range(3):
        along = np.moveaxis(field, axis, 0)
        step = along[1:] - along[:-1]
        slopes.append(np.abs(step[(along[1:] >= iso) != (along[:-1] >= iso)]) / scale[axis])
    slopes = np.concatenate(slopes)
    return float(np.median(slopes)) if len(slopes) else 1.0


def _cut(mesh: Mesh, rows: np.ndarray, world_per_unit: float, offset: np.ndarray) -> Mesh:
    """``mesh`` (physical units) cut by each half-space of ``rows`` (world, :meth:`Clip.half_spaces`)."""
    for row in rows:
        if len(mesh.faces) == 0:
            break
        distance = (mesh.vertices.astype(np.float64) * world_per_unit + offset) @ row[:3] + row[3]
        mesh = _cut_one(mesh, distance)
    return mesh


def _cut_one(mesh: Mesh, distance: np.ndarray) -> Mesh:
    """``mesh`` where ``distance >= 0`` (per vertex, linear along edges): triangles wholly outside
    dropped, those across split on the zero crossing, whose new vertices their neighbours share."""
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
    return Mesh(vertices[used].astype(np.float32), faces.reshape(-1, 3).astype(np.int32),
                normals[used].astype(np.float32))


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


def _outward_normals(field: np.ndarray, at: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Unit normals at voxel coordinates ``at``: minus the field's central-difference gradient (per
    physical unit) at the nearest voxel."""
    i = np.clip(np.rint(at).astype(np.int64), 0, np.asarray(field.shape) - 1)
    gradient = np.empty_like(at)
    for axis in range(3):
        up, down = i.copy(), i.copy()
        up[:, axis] = np.minimum(i[:, axis] + 1, field.shape[axis] - 1)
        down[:, axis] = np.maximum(i[:, axis] - 1, 0)
        step = (up[:, axis] - down[:, axis]).clip(1) * spacing[axis]
        gradient[:, axis] = (field[tuple(up.T)] - field[tuple(down.T)]) / step
    length = np.linalg.norm(gradient, axis=1, keepdims=True)
    return (-gradient / np.where(length > 0, length, 1.0)).astype(np.float32)
