"""A volume ready for rendering: its voxel source, the device type and the map of its values to [0, 1].

The renderer samples normalized values in [0, 1]. On the device, voxels keep a narrow type:

| stored | on the device | normalized value |
|---|---|---|
| uint8, int8, bool | uint8: ``stored`` (+128 for int8) | ``(device - d0) * a`` in the kernels |
| uint16, int16 | uint16: ``stored`` (+32768 for int16) | ``(device - d0) * a`` in the kernels |
| float32, float64, int32, uint32 | float32 normalized, non-finite replaced | ``device`` (d0 = 0, a = 1) |

``d0`` is the device value of the smallest original value, an integer: the kernels subtract
it from each voxel exactly before interpolating, so a narrow range far from zero keeps its
precision.

int16 becomes uint16 with an offset (rather than a third integer type in the kernels): one
kernel type for both, exact, and DICOM's rescale folds into ``(d0, a)``. Floats are normalized
before upload (in float64 where needed) so that huge ranges (1e38) keep their precision; float32
without a rescale whose span float32 holds (:attr:`Volume.raw_float32`) travels as stored and is
normalized where it lands, in one pass on the device (:meth:`Volume.normalize_float32_`, the same
float32 arithmetic as on the host).

:meth:`Volume.from_source` reads the source once (:func:`~isosr_render.scan.scan`) for the value
range, the min-max bricks and Otsu's subsample; the renderer then streams the source again box
by box to the device (:meth:`Volume.device_box`), or pages bricks in (`bricks_pool`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from isosr_render.conventions import world_from_voxel
from isosr_render.scan import BRICK, Scan, native_integer, scan, unsigned_view
from isosr_render.voxels import (
    ArraySource,
    VolumeError,
    VoxelSource,
    boxes,
    check_source,
)

__all__ = ["BRICK", "Volume", "VolumeError", "native_integer"]


@dataclass(frozen=True)
class Volume:
    """A scalar volume ready for rendering.

    Attributes:
        source: the voxels as stored, read box by box.
        spacing: voxel size per axis (x, y, z), in the file's units.
        value_range: ``(min, max)`` of the finite original values (rescale applied), to convert iso-values.
        name: where the volume came from (file name or procedural spec).
        storage: the voxels' type on the device: ``uint8``, ``uint16`` or ``float32``.
        unit: ``(d0, a)``: normalized value = (device value - d0) * a.
        bricks: per ``BRICK``-voxel brick, the normalized (min, max) of its voxels and the
            one-voxel overlap with the next brick.
        otsu: Otsu's threshold of the normalized voxels (a subsample of at most ~2M).
        counts: 8/16-bit integers: the count of each device value (an exact histogram), else None.

    Shape:
        bricks: (ceil((nx - 1) / BRICK), ceil((ny - 1) / BRICK), ceil((nz - 1) / BRICK), 2).
    """

    source: VoxelSource
    spacing: tuple[float, float, float]
    value_range: tuple[float, float]
    name: str
    storage: np.dtype
    unit: tuple[float, float]
    bricks: np.ndarray
    otsu: float
    counts: np.ndarray | None

    @classmethod
    def from_array(cls, values: np.ndarray, spacing=(1.0, 1.0, 1.0), name: str = "") -> "Volume":
        """The volume of an array of original values indexed ``[x, y, z]`` (see :meth:`from_source`)."""
        return cls.from_source(ArraySource(values, spacing, name))

    @classmethod
    def from_source(cls, source: VoxelSource, sink=None) -> "Volume":
        """Scan a voxel source once and describe it for rendering.

        Non-finite voxels are replaced, with a warning that counts them: NaN by the smallest
        finite value (treated as empty space), +Inf/-Inf by the largest/smallest finite
        value. A volume with no finite voxel is an error.

        Args:
            sink: ``sink(box, device_values)`` receives every box during the scan where the
                device values are known before it (8/16-bit integers, :func:`native_integer`).
        """
        check_source(source)
        label = source.name or "array"
        found = scan(source, sink=sink)
        if found.lo is None:
            raise VolumeError(f"{label}: no finite voxel (all NaN or Inf)")
        if found.nan or found.posinf or found.neginf:
            warnings.warn(f"{label}: replaced {found.nan} NaN voxels by the minimum {found.lo:g}, "
                          f"{found.posinf} +Inf by the maximum {found.hi:g} and {found.neginf} -Inf by the minimum",
                          stacklevel=2)
        slope, intercept = source.rescale
        ends = sorted((found.lo * slope + intercept, found.hi * slope + intercept))
        lo, hi = float(ends[0]), float(ends[1])
        dtype = np.dtype(source.dtype)
        if native_integer(dtype):
            storage = np.dtype(f"uint{8 * dtype.itemsize}")
            shift = 0 if dtype.kind == "u" else 1 << (8 * dtype.itemsize - 1)
            span = hi - lo
            a = slope / span if span > 0 else 0.0
            d0 = float((found.lo if slope > 0 else found.hi) + shift)
        else:
            storage, d0, a = np.dtype(np.float32), 0.0, 1.0
        volume = cls(source, tuple(float(s) for s in source.spacing), (lo, hi), source.name, storage,
                     (d0, float(a)), np.empty((0, 0, 0, 2), np.float32), 0.0, found.counts)
        # Both through the device values, as the kernels see them (bricks must bound the samples).
        low, high = (volume.normalize(volume.device_box(m)) for m in found.bricks())
        # A negative slope swaps min and max.
        object.__setattr__(volume, "bricks", np.stack([np.minimum(low, high), np.maximum(low, high)], axis=-1))
        object.__setattr__(volume, "otsu", volume._otsu(found))
        return volume

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.source.shape)

    @property
    def device_bytes(self) -> int:
        """Bytes of the whole volume on the device (dense)."""
        return int(np.prod(self.shape, dtype=np.int64)) * self.storage.itemsize

    @property
    def float32_span(self) -> bool:
        """Whether the value range's span is finite in float32 (not, e.g., -3e38 .. 3e38): else floats are
        normalized in float64."""
        lo, hi = self.value_range
        with np.errstate(over="ignore"):
            return bool(np.isfinite(np.float32(hi) - np.float32(lo)))

    @property
    def raw_float32(self) -> bool:
        """Whether the device values are the stored float32 ones normalized by the range alone (no rescale, a
        span float32 holds): they may travel as stored and be normalized where they land (:meth:`normalize_float32_`)."""
        return (self.storage.kind == "f" and np.dtype(self.source.dtype) == np.float32
                and tuple(self.source.rescale) == (1.0, 0.0) and self.float32_span)

    def normalize_float32_(self, values: torch.Tensor) -> torch.Tensor:
        """Stored float32 values (where :attr:`raw_float32`) made device values in place, on any device: NaN and
        -inf to the range's min, +inf to its max, then ``(v - lo) * (1 / span)`` in float32, clipped to [0, 1]."""
        lo, hi = self.value_range
        span = hi - lo
        values.nan_to_num_(nan=lo, posinf=hi, neginf=lo)
        values.sub_(lo).mul_(1.0 / span if span > 0 else 0.0)
        return values.clamp_(0.0, 1.0)

    def device_box(self, stored: np.ndarray) -> np.ndarray:
        """Stored values of a box as the device holds them (``storage``; see the module table)."""
        if self.storage.kind == "u":
            return unsigned_view(stored)
        if self.raw_float32:
            return self.normalize_float32_(torch.from_numpy(np.array(stored, np.float32))).numpy()
        slope, intercept = self.source.rescale
        lo, hi = self.value_range
        values = stored.astype(np.float32 if stored.dtype == np.float32 else np.float64, copy=False)
        if (slope, intercept) != (1.0, 0.0):
            values = values.astype(np.float64) * slope + intercept
        if not np.isfinite(values).all():
            values = np.nan_to_num(values, nan=lo, posinf=hi, neginf=lo)
        if not self.float32_span:
            values = values.astype(np.float64)
        span = hi - lo
        data = values - lo  # one temporary, scaled in place (in the type of values, as before)
        data *= 1.0 / span if span > 0 else 0.0
        data = data.astype(np.float32, copy=False)
        return np.clip(data, 0.0, 1.0, out=data)

    def normalize(self, device: np.ndarray) -> np.ndarray:
        """Device values as normalized float32 (``(device - d0) * a`` in float32, as the kernels compute it)."""
        if self.storage.kind == "f":
            return device
        d0, a = (np.float32(u) for u in self.unit)
        return (device.astype(np.float32) - d0) * a

    def read_normalized(self, x: slice, y: slice, z: slice) -> np.ndarray:
        """A box of the volume normalized to float32 [0, 1] as the kernels read it, indexed
        ``[x, y, z]``, read from the source (a pick's neighbourhood, a slice)."""
        data = self.normalize(self.device_box(np.asarray(self.source.read(x, y, z))))
        return np.clip(data, 0.0, 1.0, out=data)

    @property
    def data(self) -> np.ndarray:
        """The whole volume normalized to float32 [0, 1], indexed ``[x, y, z]``, in host memory.

        Read from the source on every access: for small volumes, tests, references and meshes
        (:mod:`isosr_render.mesh` bounds the volume) only.
        """
        return self.read_normalized(*(slice(0, n) for n in self.shape))

    def normalized_iso(self, iso: float) -> float:
        """Convert an iso-value in the file's units to the normalized [0, 1] scale."""
        lo, hi = self.value_range
        if hi == lo:
            return 0.0 if iso <= lo else 2.0  # a constant volume: below/above everything
        return float((iso - lo) / (hi - lo))

    def world_transform(self):
        """``(scale, offset)`` with ``world = voxel * scale + offset`` (see conventions)."""
        return world_from_voxel(self.shape, self.spacing)

    def otsu_iso(self) -> float:
        """A starting iso-value: Otsu's threshold of the normalized voxels (on at most ~2M of them)."""
        return self.otsu

    def _otsu(self, found: Scan) -> float:
        u8 = (self.normalize(self.device_box(found.subsample)) * 255.0 + 0.5).astype(np.uint8)
        threshold, _ = cv2.threshold(u8.reshape(-1, 1), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        return float(threshold) / 255.0

    def histogram(self, bins: int) -> np.ndarray:
        """Voxel counts in ``bins`` equal bins of the normalized range [0, 1].

        Exact from ``counts`` for 8/16-bit integers; float data take a second pass over the source.
        """
        if self.counts is not None:
            device = np.arange(len(self.counts), dtype=np.float64)
            index = np.clip(np.floor(np.clip((device - self.unit[0]) * self.unit[1], 0, 1) * bins), 0, bins - 1)
            return np.bincount(index.astype(np.int64), weights=self.counts, minlength=bins).astype(np.int64)
        total = np.zeros(bins, np.int64)
        for box in boxes(self.source, BRICK):
            total += np.histogram(self.device_box(np.asarray(self.source.read(*box))), bins=bins, range=(0.0, 1.0))[0]
        return total

    def voxel_size_world(self) -> float:
        """The smallest voxel edge in world units."""
        return float(self.world_transform()[0].min())
