"""Voxels as stored, read box by box: the interface between file readers and the renderer.

A reader (NIfTI, DICOM, Zarr, TIFF, numpy, procedural) returns a :class:`VoxelSource`: the
stored values in their own type, the linear map to original units (DICOM's rescale
slope/intercept) and the store's chunk shape. Nothing here holds a whole volume unless the
source is an in-memory array (:class:`ArraySource`): loaders read boxes from :func:`boxes`,
aligned to the store's chunks, so that peak host memory is bounded by a box, not the volume.
"""

from __future__ import annotations

import math
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Callable, Iterable, Iterator, Protocol, TypeVar, runtime_checkable

import numpy as np

T = TypeVar("T")
R = TypeVar("R")

BOX_BYTES = 32 << 20  # bytes of the boxes loaders read at once (default of box_extent and boxes)

# The stored types a source may hold.
STORED_DTYPES = tuple(np.dtype(t) for t in ("uint8", "int8", "uint16", "int16", "uint32", "int32",
                                             "float32", "float64"))


class VolumeError(ValueError):
    """A volume (file, array or voxel source) that cannot be rendered, with the reason."""


@runtime_checkable
class VoxelSource(Protocol):
    """Voxels as stored, read box by box.

    Attributes:
        name: where the voxels come from (file or folder name, procedural spec).
        shape: ``(nx, ny, nz)``, indexed ``[x, y, z]`` like ``Volume``; each at least 2.
        dtype: the stored type, one of ``STORED_DTYPES``.
        spacing: voxel size per axis (x, y, z), in the file's units.
        rescale: ``(slope, intercept)`` with ``original = stored * slope + intercept``.
        chunks: the store's chunk shape in (x, y, z); reads aligned to it are cheapest.
    """

    name: str
    shape: tuple[int, int, int]
    dtype: np.dtype
    spacing: tuple[float, float, float]
    rescale: tuple[float, float]
    chunks: tuple[int, int, int]

    def read(self, x: slice, y: slice, z: slice) -> np.ndarray:
        """Stored values of the box ``[x, y, z]`` (slices with step 1, inside the shape).

        Shape:
            returns: ``(x.stop - x.start, y.stop - y.start, z.stop - z.start)``, dtype ``self.dtype``.
        """
        ...


class ArraySource:
    """A voxel source backed by a numpy array indexed ``[x, y, z]`` (tests, the readers that load whole files).

    Args:
        values: the stored values; bool becomes uint8, float16 becomes float32 (stored types only).
        spacing: voxel size per axis.
        name: where the values come from.
        rescale: ``(slope, intercept)`` to original units.
        chunks: the chunk shape reads are cut into; default: slabs of at most 64 MiB along x.

    Shape:
        values: (nx, ny, nz).
    """

    def __init__(self, values: np.ndarray, spacing=(1.0, 1.0, 1.0), name: str = "",
                 rescale: tuple[float, float] = (1.0, 0.0), chunks: tuple[int, int, int] | None = None):
        label = name or "array"
        values = np.asarray(values)
        if values.dtype == np.bool_:
            values = values.view(np.uint8)
        elif values.dtype == np.float16:
            values = values.astype(np.float32)
        if values.ndim == 3 and values.dtype.byteorder == ">":
            values = values.astype(values.dtype.newbyteorder("="))
        view = values.view()
        view.flags.writeable = False
        self.values = view
        self.name = name
        self.shape = tuple(int(n) for n in values.shape)
        self.dtype = values.dtype
        self.spacing = tuple(float(s) for s in np.ravel(spacing))
        self.rescale = tuple(float(r) for r in rescale)
        if chunks is None and values.ndim == 3:
            plane = max(1, values.dtype.itemsize * self.shape[1] * self.shape[2])
            chunks = (max(1, min(self.shape[0], (64 << 20) // plane)), self.shape[1], self.shape[2])
        self.chunks = tuple(int(c) for c in chunks) if chunks is not None else ()
        check_source(self, label)

    def read(self, x: slice, y: slice, z: slice) -> np.ndarray:
        """The box ``values[x, y, z]`` (a read-only view)."""
        return self.values[x, y, z]


def check_source(source: VoxelSource, label: str | None = None) -> None:
    """Raise `VolumeError` (one line naming the source) unless its attributes describe a readable volume."""
    label = label or source.name or "voxel source"
    shape = tuple(source.shape)
    if len(shape) != 3:
        raise VolumeError(f"{label}: expected a 3D volume, got {len(shape)}D with shape {shape}")
    if min(shape) < 2:
        raise VolumeError(f"{label}: every axis needs at least 2 voxels, got shape {shape}")
    if np.dtype(source.dtype).newbyteorder("=") not in STORED_DTYPES:
        raise VolumeError(f"{label}: unsupported voxel dtype {source.dtype} "
                          f"(expected one of {', '.join(d.name for d in STORED_DTYPES)})")
    spacing = tuple(source.spacing)
    if len(spacing) != 3 or not all(np.isfinite(s) and s > 0 for s in spacing):
        raise VolumeError(f"{label}: spacing must be 3 positive finite numbers, got {spacing}")
    slope, intercept = source.rescale
    if not (np.isfinite(slope) and np.isfinite(intercept) and slope != 0):
        raise VolumeError(f"{label}: rescale (slope, intercept) must be finite with a nonzero slope, "
                          f"got {tuple(source.rescale)}")
    chunks = tuple(source.chunks)
    if len(chunks) != 3 or not all(isinstance(c, (int, np.integer)) and c >= 1 for c in chunks):
        raise VolumeError(f"{label}: chunks must be 3 positive integers, got {chunks}")


def box_extent(source: VoxelSource, multiple: int = 8, max_bytes: int | None = None) -> tuple[int, int, int]:
    """The extent of the boxes :func:`boxes` reads: whole chunks, a multiple of ``multiple`` voxels
    per axis (the brick size, so that bricks never straddle boxes), grown along z, then y, then x
    while a box stays within ``max_bytes`` (default ``BOX_BYTES``; a box is never smaller than one
    such unit)."""
    max_bytes = max_bytes or BOX_BYTES
    unit = []
    for n, c in zip(source.shape, source.chunks):
        c = min(int(c), n)
        step = c * multiple // math.gcd(c, multiple)
        unit.append(step if step <= max(c, 4 * multiple) else -(-c // multiple) * multiple)
    extent = list(unit)
    itemsize = np.dtype(source.dtype).itemsize
    for axis in (2, 1, 0):
        while extent[axis] < source.shape[axis]:
            grown = list(extent)
            grown[axis] = extent[axis] + unit[axis]
            if math.prod(grown) * itemsize > max_bytes:
                break
            extent = grown
    return tuple(min(e, n) for e, n in zip(extent, source.shape))


def boxes(source: VoxelSource, multiple: int = 8, max_bytes: int | None = None) -> Iterator[tuple[slice, slice, slice]]:
    """The boxes that tile the source, x-major (see :func:`box_extent`); the last per axis may be shorter."""
    extent = box_extent(source, multiple, max_bytes)
    for x0 in range(0, source.shape[0], extent[0]):
        for y0 in range(0, source.shape[1], extent[1]):
            for z0 in range(0, source.shape[2], extent[2]):
                yield tuple(slice(o, min(o + e, n)) for o, e, n in zip((x0, y0, z0), extent, source.shape))


def map_bounded(fn: Callable[[T], R], items: Iterable[T], threads: int) -> Iterator[R]:
    """``fn`` over ``items`` on ``threads`` threads with at most ``2 threads`` in flight (so that at
    most that many boxes are in host memory), yielding results as they complete."""
    with ThreadPoolExecutor(max(1, threads)) as pool:
        pending = set()
        for item in items:
            if len(pending) >= 2 * max(1, threads):
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                yield from (future.result() for future in done)
            pending.add(pool.submit(fn, item))
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            yield from (future.result() for future in done)
