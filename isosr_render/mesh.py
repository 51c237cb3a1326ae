"""The isosurface as a triangle mesh, to take on to ParaView or Blender: marching cubes where Warp
runs it (``warp.MarchingCubes``, on CUDA and on the CPU), in the volume's physical units (voxel
coordinates times the spacing, from the centre of voxel (0, 0, 0)), with outward vertex normals,
written through meshio.

    mesh = extract_mesh(volume, volume.normalized_iso(300.0), "cuda")
    write_mesh(mesh, "surface.ply")                          # .ply, .obj, .stl or .vtu

The values above the iso are inside: normals point to lower values.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from isosr_render.volume import Volume

# What one mesh may take: the voxels marching cubes reads at once (float32 on the device), and the
# triangles, estimated before it is built from the cells the surface crosses (each gives one or more).
MAX_MESH_VOXELS = 512**3
MAX_MESH_TRIANGLES = 20_000_000
MESH_FORMATS = {".ply": "ply", ".obj": "obj", ".stl": "stl", ".vtu": "vtu"}  # VTU: ParaView's XML (meshio has no VTP)
# The Warp module of Warp's marching cubes kernels (compiled at first use, as the project's own).
MESH_MODULE = wp.MarchingCubes.__module__


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
                 max_triangles: int = MAX_MESH_TRIANGLES) -> Mesh:
    """The isosurface of normalized ``iso`` of ``volume`` by marching cubes on ``device``.

    Raises:
        ValueError: the volume has more than ``max_voxels`` voxels, or the surface would take more
            than ``max_triangles`` triangles (each refused before the mesh is built, naming the limit).
    """
    voxels = int(np.prod(volume.shape, dtype=np.int64))
    if voxels > max_voxels:
        raise ValueError(f"mesh: the volume has {voxels:,} voxels, over the limit of {max_voxels:,} "
                         f"(a coarser level or a crop of it fits)")
    field = volume.data
    crossed = _crossed_cells(field, iso)
    if crossed > max_triangles:
        raise ValueError(f"mesh: the surface crosses {crossed:,} cells, more triangles than the limit of "
                         f"{max_triangles:,}")
    if crossed == 0:
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))
    cubes = wp.MarchingCubes(*volume.shape)
    cubes.surface(wp.array(field, dtype=wp.float32, device=device), float(iso))
    at = cubes.verts.numpy().astype(np.float64)
    faces = cubes.indices.numpy().reshape(-1, 3).astype(np.int32)
    spacing = np.asarray(volume.spacing, np.float64)
    return Mesh((at * spacing).astype(np.float32), faces, _outward_normals(field, at, spacing))


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
