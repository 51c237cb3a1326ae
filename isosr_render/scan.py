"""One streaming pass over a voxel source: what must be known before any voxel reaches the device.

:func:`scan` reads a source box by box (:func:`~isosr_render.voxels.boxes`) on a few threads,
holding at most a few boxes at once, and gathers:

- the finite value range and the non-finite counts (stored units);
- the min-max bricks: per ``BRICK``-voxel brick, the min and max of its voxels including the
  one-voxel overlap with the next brick (the voxels that trilinear samples inside it read).
  A box holds whole blocks of ``BRICK^3`` voxels but not the next block's first plane, so
  each box keeps eight summaries per block (the block, its three low faces, three low edges
  and low corner) and :meth:`Scan.bricks` joins each brick with its neighbours' faces;
- a strided subsample (at most about two million voxels, for Otsu's threshold);
- for 8- and 16-bit integers, the count of every stored value (an exact histogram).

Everything is one pass. 8- and 16-bit integers go to the device as they are read (``sink``):
their device values do not depend on the range. Float and 32-bit data take a second pass to
upload (normalized by the range known only at the end), and a float histogram one more (its
bins span that range): :meth:`Volume.histogram` does it on demand.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from isosr_render import voxels
from isosr_render.voxels import (
    VolumeError,
    VoxelSource,
    boxes,
    check_source,
    map_bounded,
)

BRICK = 8  # voxels per min-max brick edge; the renderer's bricks are multiples of it
SUBSAMPLE = 2_000_000  # voxels in the Otsu subsample, about
# Summaries kept per block: the block, its low x/y/z faces, low xy/xz/yz edges, low corner.
_PARTS = ((None, None, None), (0, None, None), (None, 0, None), (None, None, 0),
          (0, 0, None), (0, None, 0), (None, 0, 0), (0, 0, 0))


def native_integer(dtype: np.dtype) -> bool:
    """Whether voxels of ``dtype`` go to the device as (unsigned) integers, known before any scan."""
    dtype = np.dtype(dtype)
    return dtype.kind in "iu" and dtype.itemsize <= 2


def unsigned_view(values: np.ndarray) -> np.ndarray:
    """8- and 16-bit integers as unsigned ``stored + 2^(bits-1)`` for signed ones (the sign bit flipped)."""
    if values.dtype.kind == "u":
        return values
    unsigned = values.view(values.dtype.str.replace("i", "u"))
    return unsigned ^ unsigned.dtype.type(1 << (8 * values.dtype.itemsize - 1))


def _extremes(dtype: np.dtype) -> tuple:
    """Values that lose every min (``hi``) and every max (``lo``) of the type."""
    if dtype.kind == "f":
        return dtype.type(np.inf), dtype.type(-np.inf)
    info = np.iinfo(dtype)
    return dtype.type(info.max), dtype.type(info.min)


def _reduce8(values: np.ndarray, axis: int, op: np.ufunc) -> np.ndarray:
    """``op`` over runs of 8 along ``axis`` (the axis length a multiple of 8), by 8 strided slices."""
    split = values.reshape(values.shape[:axis] + (values.shape[axis] // BRICK, BRICK) + values.shape[axis + 1:])
    index = [slice(None)] * split.ndim
    out = None
    for k in range(BRICK):
        index[axis + 1] = k
        part = split[tuple(index)]
        out = part.copy() if out is None else op(out, part, out=out)
    return out


def _parts(values: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per ``_PARTS`` entry, the (min, max) block arrays of a box, axis by axis: along each axis a
    block's 8 values reduce (``None``) or its first one is kept (``0``), outer axes first so that
    the slow inner axis runs on 1/64 of the data; a low part is a strided view, shared by min and max.

    Shape:
        values: (8a, 8b, 8c) -> each (a, b, c)
    """
    level = {(): (values, values)}
    for axis in range(3):
        low = (slice(None),) * axis + (slice(0, None, BRICK),)
        level = {key + part: pair for key, (mn, mx) in level.items()
                 for part, pair in (((None,), (_reduce8(mn, axis, np.minimum), _reduce8(mx, axis, np.maximum))),
                                    ((0,), (mn[low], mx[low])))}
    return [tuple(np.ascontiguousarray(p) for p in level[low]) for low in _PARTS]


def _box_parts(values: np.ndarray, pad: list[tuple[int, int]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`_parts` of a box padded by ``pad`` (edge values); a Fortran-ordered box (NIfTI's) through its
    transpose, a C-ordered view, so that the reductions run along memory (over 10x faster than across it)."""
    padded = np.pad(values, pad, mode="edge") if any(p for _, p in pad) else values
    if not padded.flags.f_contiguous or padded.flags.c_contiguous:
        return _parts(padded)
    flipped = dict(zip(_PARTS, _parts(padded.T)))
    return [tuple(p.T for p in flipped[low[::-1]]) for low in _PARTS]


def _histogram(values: np.ndarray) -> np.ndarray:
    """The count of each unsigned-viewed 8/16-bit value (cv2's histogram: several times np.bincount's
    speed, whose int64 cast of the voxels costs most; float32 counts, exact per call of < 2^24 voxels)."""
    bins = 1 << (8 * values.dtype.itemsize)
    values = values.T if values.flags.f_contiguous else values  # rows along memory: no copy
    rows = unsigned_view(values).reshape(-1, values.shape[-1])
    step = max(1, (1 << 24) // rows.shape[1] - 1)
    counts = np.zeros(bins, np.int64)
    for r in range(0, len(rows), step):
        counts += cv2.calcHist([rows[r: r + step]], [0], None, [bins], [0, bins]).ravel().astype(np.int64)
    return counts


@dataclass
class _BoxResult:
    box: tuple[slice, slice, slice]
    finite: tuple | None  # (min, max) of finite values, None if none
    nonfinite: tuple[int, int, int]
    parts: list  # per _PARTS entry: (min, max) block arrays
    counts: np.ndarray | None
    sub: np.ndarray
    device: np.ndarray | None  # the box's device values, for the sink


@dataclass
class Scan:
    """What one pass over a source found (stored units).

    Attributes:
        lo, hi: finite min and max (None if no finite voxel).
        nan, posinf, neginf: counts of non-finite voxels.
        parts_min, parts_max: per ``_PARTS`` entry, a block array (``ceil(n / BRICK)`` per axis).
        counts: occurrences of each unsigned-viewed stored value (8/16-bit integers), else None.
        subsample: stored values at ``[::stride, ::stride, ::stride]``.
    """

    shape: tuple[int, int, int]
    dtype: np.dtype
    lo: float | None
    hi: float | None
    nan: int
    posinf: int
    neginf: int
    parts_min: list
    parts_max: list
    counts: np.ndarray | None
    subsample: np.ndarray
    stride: int

    def bricks(self) -> tuple[np.ndarray, np.ndarray]:
        """Per brick, the min and max of its ``(BRICK + 1)^3`` voxels (clamped at the volume's end).

        Non-finite values count as stored by :func:`scan`: -Inf and +Inf as themselves, NaN as the one
        of them that rescales to the smallest original value (as ``Volume`` replaces NaN).

        Shape:
            returns: two arrays (ceil((nx - 1) / BRICK), ceil((ny - 1) / BRICK), ceil((nz - 1) / BRICK)).
        """
        nb = tuple(-(-(n - 1) // BRICK) for n in self.shape)
        big, small = _extremes(self.parts_min[0].dtype)
        out = []
        for parts, op, fill in ((self.parts_min, np.minimum, big), (self.parts_max, np.maximum, small)):
            acc = parts[0][: nb[0], : nb[1], : nb[2]].copy()
            for (lx, ly, lz), part in zip(_PARTS[1:], parts[1:]):
                # A low face/edge/corner of block b + offset lies in brick b (offset 1 where it is low).
                offset = tuple(0 if low is None else 1 for low in (lx, ly, lz))
                padded = np.pad(part, [(0, 1)] * 3, constant_values=fill)
                op(acc, padded[offset[0]: offset[0] + nb[0], offset[1]: offset[1] + nb[1],
                               offset[2]: offset[2] + nb[2]], out=acc)
            out.append(acc)
        return out[0], out[1]


def _scan_box(source: VoxelSource, box, stride: int, counted: bool, keep: bool) -> _BoxResult:
    """The summaries of one box (run on a worker thread)."""
    shape = tuple(s.stop - s.start for s in box)
    values = np.asarray(source.read(*box))
    if values.shape != shape or values.dtype != source.dtype:
        raise VolumeError(f"{source.name}: reading box {[(s.start, s.stop) for s in box]} gave "
                          f"{values.dtype} {values.shape}, expected {np.dtype(source.dtype)} {shape}")
    device = unsigned_view(values) if keep else None
    counts = _histogram(values) if counted else None
    pad = [(0, -n % BRICK) for n in shape]
    parts = _box_parts(values, pad)
    finite, nonfinite = (parts[0][0].min(), parts[0][1].max()), (0, 0, 0)
    # NaN propagates through min and max: finite extremes mean finite voxels (the common case).
    if values.dtype.kind == "f" and not np.isfinite(finite).all():
        ok = np.isfinite(values)
        nan = np.isnan(values)
        nonfinite = (int(nan.sum()), int(np.isposinf(values).sum()), int(np.isneginf(values).sum()))
        finite = (values[ok].min(), values[ok].max()) if ok.any() else None
        empty = -np.inf if source.rescale[0] > 0 else np.inf  # the end that becomes the smallest original value
        values = np.where(nan, values.dtype.type(empty), values)
        parts = _box_parts(values, pad)
    sub = values[tuple(slice((-s.start) % stride, None, stride) for s in box)]
    return _BoxResult(box, finite, nonfinite, parts, counts, sub, device)


def scan(source: VoxelSource, threads: int | None = None, box_bytes: int | None = None,
         sink: Callable[[tuple[slice, slice, slice], np.ndarray], None] | None = None) -> Scan:
    """Read ``source`` once, box by box on ``threads`` threads (default ``voxels.READ_THREADS``), and summarize it.

    Peak host memory: about ``2 threads`` boxes of ``box_bytes`` (default ``voxels.BOX_BYTES``;
    times a few for their summaries' temporaries), plus the block summaries (16 values per
    ``BRICK^3`` voxels).

    Args:
        sink: for 8/16-bit integer sources (:func:`native_integer`), called on this thread with
            each box and its device values (unsigned, as ``Volume`` stores them) as it is read.
    """
    check_source(source)
    dtype = np.dtype(source.dtype)
    counted = native_integer(dtype)
    keep = sink is not None and counted
    stride = max(1, round((np.prod(source.shape, dtype=np.float64) / SUBSAMPLE) ** (1 / 3)))
    nblk = tuple(-(-n // BRICK) for n in source.shape)
    big, small = _extremes(dtype)
    parts_min = [np.full(nblk, big, dtype) for _ in _PARTS]
    parts_max = [np.full(nblk, small, dtype) for _ in _PARTS]
    counts = np.zeros(1 << (8 * dtype.itemsize), np.int64) if counted else None
    subsample = np.empty(tuple(-(-n // stride) for n in source.shape), dtype)
    lo, hi, nonfinite = None, None, np.zeros(3, np.int64)

    def merge(r: _BoxResult):
        nonlocal lo, hi, nonfinite
        if r.finite is not None:
            lo = r.finite[0] if lo is None else min(lo, r.finite[0])
            hi = r.finite[1] if hi is None else max(hi, r.finite[1])
        nonfinite += r.nonfinite
        blk = tuple(slice(s.start // BRICK, s.start // BRICK + m) for s, m in zip(r.box, r.parts[0][0].shape))
        for k, (mn, mx) in enumerate(r.parts):
            parts_min[k][blk] = mn
            parts_max[k][blk] = mx
        if counts is not None:
            counts[:] += r.counts
        at = tuple(slice(-(-s.start // stride), -(-s.start // stride) + n) for s, n in zip(r.box, r.sub.shape))
        subsample[at] = r.sub
        if keep:
            sink(r.box, r.device)

    threads = threads or voxels.READ_THREADS
    def read(box):
        return _scan_box(source, box, stride, counted, keep)

    for result in map_bounded(read, boxes(source, BRICK, box_bytes), threads):
        merge(result)
    return Scan(tuple(source.shape), dtype, None if lo is None else lo.item(), None if hi is None else hi.item(),
                *(int(c) for c in nonfinite), parts_min, parts_max, counts, subsample, stride)
