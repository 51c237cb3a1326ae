"""Time-varying volumes: a series of volumes of one shape, spacing and dtype, opened as one with a time axis.

    series = open_series("runs/run_*.nii.gz")   # run_2 before run_10
    volume = series.step(3)                     # read when asked, then kept (least recently used dropped)
    series.prefetch(3)                          # steps 4, 5 and 6 read and scanned on background threads

A series is any of:

- a glob of volume files (``run_*.nii.gz``) or a folder of them (one format, no other volume in
  it; a folder that is itself a volume, a DICOM series or a Zarr store, is not a series), in
  natural order: the digits of a name compare as numbers;
- a file or store with a time axis (:attr:`isosr_render.formats.base.Format.steps`): a 4D
  NIfTI (the fourth axis), a 4D ``.npy`` array ``(t, z, y, x)``, an OME-Zarr with a ``t`` axis;
- an HDF5 dataset ``file.h5#/path`` ``(t, z, y, x)`` or ``(z, y, x)`` (h5py, in the ``data`` extra).

Every step has the layout of step 0 (:class:`~isosr_render.formats.base.Layout`); a step that
differs is refused naming it and how it differs: a file series checks its files' headers when
opened, and every step is checked again when read. A step is a :class:`Volume` of its own (its
own value range and bricks): a viewer that keeps an iso in data units converts it per step
(:func:`step_iso`). Reading and scanning (min-max bricks) happen on the caller's thread or on
the prefetch threads, never on a device: uploads stay with the renderer's owner.
"""

from __future__ import annotations

import glob
import math
import os
import re
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from isosr_render.formats import FORMATS, format_of
from isosr_render.formats.base import Layout, natural_key, require, stored_dtype
from isosr_render.volume import Volume
from isosr_render.volume_io import open_source, volume_name
from isosr_render.voxels import ArraySource, VolumeError, VoxelSource

__all__ = ["SERIES_CACHE_BYTES", "VolumeSeries", "is_series", "natural_key", "open_series", "step_iso"]

# Bytes of steps' voxels (as stored) a series keeps read; the least recently used step goes first.
SERIES_CACHE_BYTES = 2 << 30
# Steps read ahead of the one shown, and read at once at most, on the prefetch threads; both
# also bounded by the steps the cache holds besides the shown one.
PREFETCH_STEPS = 3
PREFETCH_WORKERS = 3
GLOB_CHARS = re.compile(r"[*?\[]")
HDF5_SPEC = re.compile(r"^(?P<file>.+\.(?:h5|hdf5|he5))#(?P<dataset>/.*)$", re.IGNORECASE)


def series_files(spec: str | os.PathLike) -> list[Path] | None:
    """The files of a glob, or the volume files of a folder that is no volume itself, in natural
    order; None where ``spec`` is neither (a file, a store, a DICOM series, a TIFF stack)."""
    text = str(spec)
    if GLOB_CHARS.search(Path(text).name) and not Path(text).exists():
        files = [Path(p) for p in glob.glob(text)]
    elif Path(text).is_dir() and format_of(text) is None:
        files = [p for p in Path(text).iterdir() if p.is_file() and volume_name(p) is not None]
    else:
        return None
    return sorted(files, key=lambda p: natural_key(p.name))


def is_series(spec: str | os.PathLike) -> bool:
    """Whether :func:`open_series` takes ``spec`` as a series of more than one step (cheap: names,
    headers)."""
    try:
        return open_series(spec, check=False).count > 1
    except (VolumeError, OSError):
        return False


def open_series(spec: str | os.PathLike, *, max_bytes: int = SERIES_CACHE_BYTES, check: bool = True) -> VolumeSeries:
    """Open a series (module docstring): a glob, a folder, a file or store with a time axis, an HDF5 dataset.

    A plain volume file opens as a series of one step.

    Args:
        spec: the glob, folder, file or ``file.h5#/dataset``.
        max_bytes: the steps kept read (:class:`VolumeSeries`).
        check: check every file's layout against the first (headers); False only to count steps.

    Raises:
        VolumeError: nothing matches, files of several formats, a file series whose file differs
            from the first (naming it, e.g. ``step 3 (run_3.nii): shape (8, 8, 7) instead of
            (8, 8, 8)``), or what the readers raise.
    """
    text = str(spec)
    found = HDF5_SPEC.match(text)
    if found is not None:
        return _hdf5_series(Path(found["file"]), found["dataset"], max_bytes)
    files = series_files(text)
    if files is None:
        path = Path(text)
        fmt = format_of(path)
        steps = None if fmt is None or fmt.steps is None else fmt.steps(path)
        if steps is None:
            return VolumeSeries(path.name, 1, lambda i: open_source(path), [path.name], max_bytes=max_bytes)
        return VolumeSeries(path.name, steps.count, steps.open, [f"t={i}" for i in range(steps.count)],
                            max_bytes=max_bytes)
    if not files:
        raise VolumeError(f"{text}: no volume files {'match' if GLOB_CHARS.search(text) else 'in this folder'}")
    formats = sorted({format_of(f).name for f in files})
    if len(formats) > 1:
        raise VolumeError(f"{text}: a series is files of one format, found {', '.join(formats)}")
    name = Path(text).name
    series = VolumeSeries(name, len(files), lambda i: open_source(files[i]), [f.name for f in files],
                          max_bytes=max_bytes)
    if check:
        fmt = FORMATS[formats[0]]
        layout = fmt.header or (lambda p: Layout.of(open_source(p)))
        first = layout(files[0])
        for i, f in enumerate(files[1:], start=1):
            series.check_step(i, first, layout(f))
        series._first = first
    return series


def step_iso(iso: float, shown: Volume, step: Volume) -> float:
    """A normalized iso of ``shown`` as ``step`` normalizes the same data value (steps differ in range)."""
    lo, hi = shown.value_range
    return step.normalized_iso(lo + iso * (hi - lo))


class VolumeSeries:
    """Steps of one layout, read when asked and kept within a memory bound; the next ones read ahead.

    Args:
        name: where the series comes from (a folder, glob or file name).
        count: steps, at least 1.
        open_step: ``open_step(i)`` reads step ``i``'s voxels (:class:`VoxelSource`).
        labels: per step, what an error names (a file name, ``t=3``).
        max_bytes: bytes of steps' stored voxels to keep; the least recently used step is dropped
            past it (the newest always stays).
    """

    def __init__(self, name: str, count: int, open_step: Callable[[int], VoxelSource], labels: Sequence[str],
                 max_bytes: int = SERIES_CACHE_BYTES):
        if count < 1 or len(labels) != count:
            raise ValueError(f"{name}: a series needs at least one step and a label per step, got {count} "
                             f"and {len(labels)}")
        if max_bytes <= 0:
            raise ValueError(f"{name}: max_bytes must be positive, got {max_bytes}")
        self.name, self.count, self.labels, self.max_bytes = name, count, list(labels), max_bytes
        self._open = open_step
        self._first: Layout | None = None
        self._cache: OrderedDict[int, Volume] = OrderedDict()
        self._loading: dict[int, Future] = {}
        self._lock = threading.Lock()
        self._prefetcher: ThreadPoolExecutor | None = None

    def __len__(self) -> int:
        return self.count

    def cached(self) -> list[int]:
        """The steps kept read, least recently used first."""
        with self._lock:
            return list(self._cache)

    def held_bytes(self) -> int:
        """Bytes of the kept steps' stored voxels."""
        with self._lock:
            return sum(_bytes(v) for v in self._cache.values())

    def check_step(self, i: int, first: Layout, layout: Layout) -> None:
        """`VolumeError` naming step ``i`` where its layout differs from step 0's."""
        how = first.differs(layout)
        if how is not None:
            raise VolumeError(f"{self.name}: step {i} ({self.labels[i]}) differs from step 0 "
                              f"({self.labels[0]}): {how}")

    def step(self, i: int) -> Volume:
        """Step ``i`` as a volume: from the cache, else read and scanned now (or awaited where the
        prefetch reads it).

        Raises:
            IndexError: ``i`` outside ``[0, count)``.
            VolumeError: its file is missing or unreadable, or differs from step 0.
        """
        if not 0 <= i < self.count:
            raise IndexError(f"{self.name}: step {i} outside 0..{self.count - 1}")
        with self._lock:
            if i in self._cache:
                self._cache.move_to_end(i)
                return self._cache[i]
            future, owner = self._loading.get(i), False
            if future is None:
                future, owner = self._loading.setdefault(i, Future()), True
        if not owner:
            return future.result()
        try:
            volume = self._read(i)
        except BaseException as e:
            with self._lock:
                del self._loading[i]
            future.set_exception(e)
            raise
        with self._lock:
            del self._loading[i]
            self._cache[i] = volume
            while len(self._cache) > 1 and sum(_bytes(v) for v in self._cache.values()) > self.max_bytes:
                self._cache.popitem(last=False)
        future.set_result(volume)
        return volume

    def _read(self, i: int) -> Volume:
        source = self._open(i)
        layout = Layout.of(source)
        if i == 0:
            self._first = layout
        else:
            self.check_step(i, self._first or Layout.of(self._open(0)), layout)
        return Volume.from_source(source)

    def prefetch(self, shown: int, ahead: int = PREFETCH_STEPS) -> None:
        """Read the ``ahead`` steps after ``shown`` (wrapping around, as playback loops) on background
        threads, those neither kept nor being read; their errors wait for :meth:`step` to raise them.

        At most as many steps as the cache holds besides one (:meth:`_room`) are read ahead, on up
        to ``PREFETCH_WORKERS`` threads (so that a slow read overlaps the next ones).
        """
        with self._lock:
            room = self._room()
            wanted = [(shown + k) % self.count for k in range(1, min(ahead, room, self.count - 1) + 1)]
            wanted = [i for i in wanted if i not in self._cache and i not in self._loading]
            if wanted and self._prefetcher is None:
                self._prefetcher = ThreadPoolExecutor(min(PREFETCH_WORKERS, room),
                                                      thread_name_prefix="isosr-prefetch")
        for i in wanted:
            self._prefetcher.submit(self._quiet_step, i)

    def _room(self) -> int:
        """Steps the cache holds besides the newest, at least 1 (1 before any step is read; call under the lock)."""
        held = next(iter(self._cache.values()), None)
        return 1 if held is None else max(1, self.max_bytes // _bytes(held) - 1)

    def _quiet_step(self, i: int) -> None:
        try:
            self.step(i)
        except (VolumeError, OSError, IndexError):
            pass  # raised again when the step is asked for

    def close(self) -> None:
        """Stop the prefetch threads (queued reads dropped)."""
        if self._prefetcher is not None:
            self._prefetcher.shutdown(wait=True, cancel_futures=True)


def _bytes(volume: Volume) -> int:
    return math.prod(volume.shape) * np.dtype(volume.source.dtype).itemsize


def _hdf5_series(path: Path, dataset: str, max_bytes: int) -> VolumeSeries:
    """An HDF5 dataset ``(t, z, y, x)`` (or ``(z, y, x)``: one step), a step read at a time."""
    h5py = require("h5py", str(path), "HDF5")
    label = f"{path.name}#{dataset}"
    try:
        file = h5py.File(path, "r")
        data = file[dataset]
    except (OSError, KeyError) as e:
        raise VolumeError(f"{label}: cannot open ({type(e).__name__}: {e})") from e
    if not isinstance(data, h5py.Dataset) or data.ndim not in (3, 4):
        raise VolumeError(f"{label}: expected a 3D (z, y, x) or 4D (t, z, y, x) dataset")
    dtype = stored_dtype(data.dtype, label)
    count = data.shape[0] if data.ndim == 4 else 1
    lock = threading.Lock()  # h5py serializes anyway; one read at a time keeps the file handle safe

    def open_step(i: int) -> VoxelSource:
        try:
            with lock:
                values = data[i] if data.ndim == 4 else data[()]
        except OSError as e:
            raise VolumeError(f"{label}: cannot read step {i} ({e})") from e
        return ArraySource(np.asarray(values).transpose(2, 1, 0).astype(dtype, copy=False), name=f"{label}[t={i}]")
    return VolumeSeries(label, count, open_step, [f"t={i}" for i in range(count)], max_bytes=max_bytes)

