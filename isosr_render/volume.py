"""The in-memory volume: normalized float32 voxels, their spacing and original value range."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from isosr_render.conventions import world_from_voxel
from isosr_render.voxels import VolumeError, VoxelSource, check_source


@dataclass(frozen=True)
class Volume:
    """A scalar volume ready for rendering.

    Attributes:
        data: float32 voxels normalized to [0, 1], indexed ``data[x, y, z]``.
        spacing: voxel size per axis (x, y, z), in the file's units.
        value_range: ``(min, max)`` of the original values, to convert iso-values.
        name: where the volume came from (file name or procedural spec).

    Shape:
        data: (nx, ny, nz), each at least 2.
    """

    data: np.ndarray
    spacing: tuple[float, float, float]
    value_range: tuple[float, float]
    name: str = ""

    @classmethod
    def from_array(cls, values: np.ndarray, spacing=(1.0, 1.0, 1.0), name: str = "") -> "Volume":
        """Validate and normalize an array of original values indexed ``[x, y, z]``.

        Non-finite voxels are replaced, with a warning that counts them: NaN by the smallest
        finite value (treated as empty space), +Inf/-Inf by the largest/smallest finite
        value. A volume with no finite voxel is an error.
        """
        label = name or "array"
        values = np.asarray(values)
        if values.ndim != 3:
            raise VolumeError(f"{label}: expected a 3D array, got {values.ndim}D with shape {values.shape}")
        if min(values.shape) < 2:
            raise VolumeError(f"{label}: every axis needs at least 2 voxels, got shape {values.shape}")
        if not (np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating)
                or values.dtype == np.bool_):
            raise VolumeError(f"{label}: unsupported voxel dtype {values.dtype}")
        spacing = tuple(float(s) for s in spacing)
        if len(spacing) != 3 or not all(np.isfinite(s) and s > 0 for s in spacing):
            raise VolumeError(f"{label}: spacing must be 3 positive finite numbers, got {spacing}")

        values = values.astype(np.float64 if values.dtype == np.float64 else np.float32, copy=False)
        finite = np.isfinite(values)
        if not finite.all():
            if not finite.any():
                raise VolumeError(f"{label}: no finite voxel (all NaN or Inf)")
            lo, hi = values[finite].min(), values[finite].max()
            n_nan, n_posinf = int(np.isnan(values).sum()), int(np.isposinf(values).sum())
            n_neginf = int(np.isneginf(values).sum())
            warnings.warn(f"{label}: replaced {n_nan} NaN voxels by the minimum {lo:g}, "
                          f"{n_posinf} +Inf by the maximum {hi:g} and {n_neginf} -Inf by the minimum",
                          stacklevel=2)
            values = np.nan_to_num(values, nan=lo, posinf=hi, neginf=lo)
        lo, hi = values.min(), values.max()
        if not np.isfinite(hi - lo):  # e.g. -3e38 .. 3e38 overflows float32: normalize in float64
            values = values.astype(np.float64)
        lo, hi = float(lo), float(hi)
        span = hi - lo
        scale = 1.0 / span if span > 0 else 0.0
        data = ((values - lo) * scale).astype(np.float32)
        np.clip(data, 0.0, 1.0, out=data)
        return cls(np.ascontiguousarray(data), spacing, (lo, hi), name)

    @classmethod
    def from_source(cls, source: VoxelSource) -> "Volume":
        """The volume of a voxel source, in original units (its rescale applied)."""
        check_source(source)
        values = source.read(*(slice(0, n) for n in source.shape))
        slope, intercept = source.rescale
        if (slope, intercept) != (1.0, 0.0):
            values = values.astype(np.float64) * slope + intercept
        return cls.from_array(values, source.spacing, name=source.name)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)

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
        stride = max(1, round((self.data.size / 2e6) ** (1 / 3)))
        u8 = (self.data[::stride, ::stride, ::stride] * 255.0 + 0.5).astype(np.uint8)
        threshold, _ = cv2.threshold(u8.reshape(-1, 1), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        return float(threshold) / 255.0

    def voxel_size_world(self) -> float:
        """The smallest voxel edge in world units."""
        return float(self.world_transform()[0].min())
